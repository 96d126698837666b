"""HeatKernelModel against an independent numpy reading of ALGORITHM.md sections 4-5."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator
from scipy.special import expit

from hktex_engine.config import KernelConfig
from hktex_engine.kernels import model as kernels_mod
from hktex_engine.kernels.model import HeatKernelModel, KernelSet, soft_step
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_kernels, random_points

# A tiny icosphere has few, broad modes: a longer time and wider decay give graded responses.
CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=12, k_blend=4)


def make_params(spectra, n, seed=0):
    kp = random_kernels(spectra, n, seed)
    rng = np.random.default_rng(seed + 100)
    kp["threshold"] = rng.uniform(0.3, 0.6, n)
    kp["sharpness"] = rng.uniform(10, 30, n)
    return kp


def make_model(field, kp, config=CONFIG, backend="auto"):
    return HeatKernelModel(
        field,
        kp["face_ids"],
        kp["bary"],
        kp["theta"],
        kp["eta"],
        kp["threshold"],
        kp["sharpness"],
        kp["colors"],
        kp["base_color"],
        config=config,
        knn_backend=backend,
        priority=kp.get("priority"),
        sigma_ratio=kp.get("sigma_ratio"),
        color_slopes=kp.get("color_slopes"),
    )


# ------------------------------------------------------------------ independent reference
def reference_albedo(spectra, kp, config, face_ids, bary):
    """Sections 4-5 in numpy, straight from ALGORITHM.md (brute force over all kernels);
    ``kp["sigma_ratio"]``, when present, scales each kernel's sigma_B, and
    ``kp["color_slopes"]`` (N, 9) makes each colour ``a_j + G_j (x - x(c_j))`` (our
    extensions)."""
    gt = spectra.grid_theta
    gs = np.log1p(spectra.grid_eta)
    a_n, s_n = len(gt), len(gs)
    evals = spectra.evals.reshape(a_n, s_n, -1)
    evecs = np.moveaxis(np.asarray(spectra.evecs, dtype=np.float64), 1, 0).reshape(a_n, s_n, -1)
    lam_i = RegularGridInterpolator((gt, gs), evals)
    phi_i = RegularGridInterpolator((gt, gs), evecs)
    n_v, k = spectra.evecs.shape[0], spectra.evecs.shape[2]
    emb = spectra.iso_evecs[:, 1:] / spectra.iso_evals[1:]

    def at(values_per_vertex, f, b):
        return np.einsum("v,v...->...", b, values_per_vertex[spectra.faces[f]])

    n_k, n_p = len(kp["theta"]), len(face_ids)
    rho = np.zeros((n_p, n_k))
    for j in range(n_k):
        coord = [
            np.clip(kp["theta"][j], gt[0], gt[-1]),
            np.clip(np.log1p(kp["eta"][j]), gs[0], gs[-1]),
        ]
        lam = lam_i(coord)[0]
        phi_vertices = phi_i(coord)[0].reshape(n_v, k)
        phi_c = at(phi_vertices, kp["face_ids"][j], kp["bary"][j])
        e_c = at(emb, kp["face_ids"][j], kp["bary"][j])
        h_c = np.sum(np.exp(-config.diffusion_time * lam) * phi_c * phi_c)
        eps, sharp = kp["threshold"][j], kp["sharpness"][j]
        sigma = config.sigma_b * (kp["sigma_ratio"][j] if "sigma_ratio" in kp else 1.0)
        for p in range(n_p):
            phi_y = at(phi_vertices, face_ids[p], bary[p])
            h = np.sum(np.exp(-config.diffusion_time * lam) * phi_c * phi_y)
            d2 = np.sum((e_c - at(emb, face_ids[p], bary[p])) ** 2)
            r = h * np.exp(-d2 / (2 * sigma**2)) / h_c
            num = expit(sharp * (r - eps)) - expit(-sharp * eps)
            den = expit(sharp * (1 - eps)) - expit(-sharp * eps)
            rho[p, j] = min(max(num / den, 0.0), 1.0)
    out = np.zeros((n_p, 3))
    slopes = kp.get("color_slopes")
    for p in range(n_p):
        top = np.argsort(-rho[p])[: config.k_blend]
        colors = np.array(kp["colors"][top], dtype=np.float64)
        if slopes is not None:
            x = at(spectra.vertices, face_ids[p], bary[p])
            for i, j in enumerate(top):
                c = at(spectra.vertices, kp["face_ids"][j], kp["bary"][j])
                colors[i] += np.reshape(slopes[j], (3, 3)) @ (x - c)
        blend = (rho[p, top, None] * colors).sum(0) / max(1.0, rho[p, top].sum())
        out[p] = np.clip(kp["base_color"] + blend, 0, 1)
    return out, rho


def assert_extension_member_checked(ks, name: str, owner: str) -> None:
    """An extension's member (``priority``, ``sigma_ratio``, ``color_slopes``) is refused
    when its set lacks it, when a §4-5 set carries it, and when it holds a NaN."""
    from dataclasses import replace

    from hktex_engine.errors import KernelSetError
    from hktex_engine.kernels.hkt import encode_hkt

    with pytest.raises(KernelSetError, match=f"needs member '{name}'"):
        encode_hkt(replace(ks, **{name: None}), compact=True)
    with pytest.raises(KernelSetError, match=f"{owner} only"):
        encode_hkt(replace(ks, kernel_config=CONFIG), compact=True)
    with pytest.raises(KernelSetError, match=name):
        encode_hkt(replace(ks, **{name: np.full_like(getattr(ks, name), np.nan)}), compact=True)


def assert_float32_query_paths_match(
    spectra, field64, kp, config, face_ids, bary, fused, table_path, monkeypatch
):
    """A float32 model's no-grad albedo on one query path against the float64 exact-cut
    evaluation: candidate tables (``table_path="always"``) or the per-point path
    (``"never"``), with the compiled loops (``fused``) or their torch twins."""
    from hktex_engine.kernels import compiled

    if fused and not compiled.available(torch.device("cpu"), torch.float32):
        pytest.skip("numba is not installed")
    with torch.no_grad():
        ref = make_model(field64, kp, config).albedo_bruteforce(face_ids, bary, exact_search=True)
    if not fused:
        monkeypatch.setattr(compiled, "available", lambda device, dtype: False)
    monkeypatch.setattr(kernels_mod, "TABLE_PATH", table_path)
    model = make_model(SpectralField(spectra, device="cpu", dtype=torch.float32), kp, config)
    if fused and table_path == "never":
        model.albedo(face_ids, bary).sum().backward()  # makes the float32 grid copy: compiled
    with torch.no_grad():
        got = model.albedo(face_ids, bary)
    np.testing.assert_allclose(got.numpy(), ref, atol=2e-5)


def assert_float64_paths_match(model, face_ids, bary, ref):
    """Every float64 albedo path of ``model``: brute force over all kernels equals ``ref`` (the
    numpy reading); with the K_s cut (the exact nearest centres) the index, tables and grad
    paths agree with each other."""
    with torch.no_grad():
        brute = model.albedo_bruteforce(face_ids, bary)
        exact = model.albedo_bruteforce(face_ids, bary, exact_search=True)
        knn = model.albedo(face_ids, bary)
    np.testing.assert_allclose(brute.numpy(), ref, atol=1e-9)
    np.testing.assert_allclose(knn.numpy(), exact.numpy(), atol=1e-12)
    grad_path = model.albedo(face_ids, bary)
    np.testing.assert_allclose(grad_path.detach().numpy(), exact.numpy(), atol=1e-12)


# ------------------------------------------------------------------ tests
def test_soft_step_ends_monotone_and_clamped():
    eps = torch.tensor([0.3, 0.5, 0.9, 0.9999], dtype=torch.float64)[:, None]
    k = torch.tensor([10.0, 50.0, 200.0, 120.0], dtype=torch.float64)[:, None]
    x = torch.linspace(0, 1, 501, dtype=torch.float64)[None, :].expand(4, -1)
    y = soft_step(x, eps, k)
    np.testing.assert_allclose(y[:, 0].numpy(), 0.0, atol=1e-12)
    np.testing.assert_allclose(y[:, -1].numpy(), 1.0, atol=1e-12)
    assert torch.all(torch.diff(y, dim=1) >= 0)
    outside = soft_step(torch.tensor([[-0.5, 1.7]], dtype=torch.float64), eps[:1], k[:1])
    assert outside.tolist() == [[0.0, 1.0]]


def test_response_is_one_at_the_centre(spectra, field64):
    kp = make_params(spectra, 25)
    model = make_model(field64, kp)
    cand = torch.arange(25)[:, None]
    with torch.no_grad():
        r = model._ratio(model.face_ids, model.bary, cand)
        rho, _ = model.responses(model.face_ids, model.bary, cand)
    np.testing.assert_allclose(r.numpy(), 1.0, rtol=1e-10)
    np.testing.assert_allclose(rho.numpy(), 1.0, rtol=1e-10)


def test_model_matches_independent_numpy(spectra, field64):
    kp = make_params(spectra, 30, seed=2)
    face_ids, bary = random_points(spectra, 40, seed=4)
    ref_albedo, ref_rho = reference_albedo(spectra, kp, CONFIG, face_ids, bary)
    assert (ref_rho > 0.05).sum() > 40, "the test set must exercise non-trivial responses"
    assert np.ptp(ref_albedo) > 0.05
    model = make_model(field64, kp)
    rho, _ = model.responses(face_ids, bary)  # grad path
    np.testing.assert_allclose(rho.detach().numpy(), ref_rho, atol=1e-9)
    with torch.no_grad():  # cached path
        rho_cached, _ = model.responses(face_ids, bary)
        brute = model.albedo_bruteforce(face_ids, bary)
    np.testing.assert_allclose(rho_cached.numpy(), ref_rho, atol=1e-9)
    np.testing.assert_allclose(brute.numpy(), ref_albedo, atol=1e-9)


@pytest.mark.parametrize("backend", ["torch", "faiss"])
def test_knn_path_equals_bruteforce(spectra, field64, backend):
    kp = make_params(spectra, 30, seed=6)
    face_ids, bary = random_points(spectra, 60, seed=7)
    full = make_model(field64, kp, KernelConfig(0.01, 0.3, k_search=30, k_blend=4), backend)
    with torch.no_grad():
        brute, aux_b = full.albedo_bruteforce(face_ids, bary, return_aux=True)
        knn, aux_k = full.albedo(face_ids, bary, return_aux=True)
    np.testing.assert_allclose(knn.numpy(), brute.numpy(), atol=1e-12)  # K_s >= N: identical

    part = make_model(field64, kp, KernelConfig(0.01, 0.3, k_search=8, k_blend=4), backend)
    with torch.no_grad():
        knn, aux = part.albedo(face_ids, bary, return_aux=True)
        _, rho_all = part.responses(face_ids, bary)
        rho_all, _ = part.responses(face_ids, bary)
        cand = part._knn.search(
            field64.embedding_at(torch.as_tensor(face_ids), torch.as_tensor(bary)), 8
        )
    true_top = torch.topk(rho_all, 4, dim=1)
    covered = torch.tensor(
        [
            bool(set(true_top.indices[p][true_top.values[p] > 0].tolist()) <= set(cand[p].tolist()))
            for p in range(60)
        ]
    )
    assert covered.sum() > 30
    np.testing.assert_allclose(knn[covered].numpy(), brute[covered].numpy(), atol=1e-12)
    assert aux["indices"].shape == (60, 4) and aux["rho"].shape == (60, 4)


def test_response_gradients_against_finite_differences(spectra, field64):
    kp = make_params(spectra, 6, seed=9)
    kp["theta"] = np.array([0.3, 1.2, 2.0, 2.9, 0.7, 1.9])  # off grid lines (kinks)
    kp["eta"] = np.array([2.0, 3.5, 6.0, 8.0, 4.0, 5.0])
    model = make_model(field64, kp)
    face_ids, bary = random_points(spectra, 3, seed=10)
    face_ids, bary = torch.as_tensor(face_ids), torch.as_tensor(bary)
    cand = torch.arange(6).expand(3, -1)
    names = ["theta", "s", "threshold", "sharpness", "bary"]
    start = [getattr(model, n).detach().clone() for n in names]

    def rho_of(*values):
        for n, v in zip(names, values, strict=True):
            setattr(model, n, v)
        return model.responses(face_ids, bary, cand)[0]

    inputs = tuple(v.clone().requires_grad_(True) for v in start)
    try:
        # swap Parameters for plain tensors so gradcheck's inputs are the leaves
        for n in names:
            delattr(model, n)
        assert torch.autograd.gradcheck(rho_of, inputs, atol=1e-6, fast_mode=True)
    finally:
        for n, v in zip(names, start, strict=True):
            setattr(model, n, torch.nn.Parameter(v))


def test_albedo_gradients_colors_and_base(spectra, field64):
    kp = make_params(spectra, 8, seed=11)
    kp["colors"] *= 0.2
    kp["base_color"] = np.full(3, 0.5)
    model = make_model(field64, kp)
    face_ids, bary = random_points(spectra, 6, seed=12)
    colors = model.colors.detach().clone().requires_grad_(True)
    base = model.base_color.detach().clone().requires_grad_(True)

    # swap the Parameters for plain tensors so gradcheck's inputs are the leaves
    del model.colors, model.base_color

    def g(c, b):
        model.colors, model.base_color = c, b
        return model.albedo_bruteforce(face_ids, bary)

    assert torch.autograd.gradcheck(g, (colors, base))


def _bary_of(points, tri):
    """Barycentrics of points in the plane of triangle ``tri`` (3, 3), least squares."""
    a = (tri[1:] - tri[0]).T
    coef, *_ = np.linalg.lstsq(a, (points - tri[0]).T, rcond=None)
    return np.concatenate([1 - coef.sum(0, keepdims=True), coef]).T


def test_centre_tangent_gradient_against_finite_differences(spectra, field64):
    kp = make_params(spectra, 5, seed=13)
    kp["bary"] = np.full((5, 3), 1 / 3)
    model = make_model(field64, kp)
    face_ids, bary = random_points(spectra, 30, seed=14)
    target = torch.as_tensor(np.random.default_rng(1).uniform(0, 1, (30, 3)))

    def loss_of(model):
        return ((model.albedo_bruteforce(face_ids, bary) - target) ** 2).sum()

    loss_of(model).backward()
    g = model.centre_tangent_grad().numpy()
    verts, faces = spectra.vertices, spectra.faces
    rng = np.random.default_rng(2)
    for j in range(5):
        tri = verts[faces[kp["face_ids"][j]]]
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        normal /= np.linalg.norm(normal)
        assert abs(g[j] @ normal) < 1e-10 * max(1.0, np.linalg.norm(g[j]))
        d = rng.normal(size=3)
        d -= (d @ normal) * normal
        d *= 1e-5 / np.linalg.norm(d)
        centre = kp["bary"][j] @ tri
        losses = []
        for sign in (1, -1):
            with torch.no_grad():
                b = model.bary.detach().clone()
                b[j] = torch.as_tensor(_bary_of((centre + sign * d)[None], tri)[0])
                moved = make_model(field64, {**kp, "bary": b.numpy()})
                losses.append(float(loss_of(moved)))
        np.testing.assert_allclose((losses[0] - losses[1]) / 2, g[j] @ d, rtol=1e-4, atol=1e-12)


def test_select_append_keep_parameter_identity(spectra, field64):
    kp = make_params(spectra, 10, seed=15)
    model = make_model(field64, kp)
    ids = [id(p) for p in model.parameters()]
    face_ids, bary = random_points(spectra, 12, seed=16)
    with torch.no_grad():
        model.albedo(face_ids, bary)  # build caches
        model.select(torch.tensor([7, 2, 2, 5]))
        sub = make_model(
            field64, {k: (v[[7, 2, 2, 5]] if k != "base_color" else v) for k, v in kp.items()}
        )
        np.testing.assert_allclose(
            model.albedo(face_ids, bary).numpy(), sub.albedo(face_ids, bary).numpy()
        )
        extra = {k: v[:3] for k, v in kp.items() if k != "base_color"}
        model.append(
            extra["face_ids"],
            extra["bary"],
            extra["theta"],
            extra["eta"],
            extra["threshold"],
            extra["sharpness"],
            extra["colors"],
        )
    assert len(model) == 7 and [id(p) for p in model.parameters()] == ids
    idx = [7, 2, 2, 5, 0, 1, 2]
    both = make_model(field64, {k: (v[idx] if k != "base_color" else v) for k, v in kp.items()})
    with torch.no_grad():
        np.testing.assert_allclose(
            model.albedo(face_ids, bary).numpy(), both.albedo(face_ids, bary).numpy()
        )


def test_cache_follows_in_place_steps_and_projection(spectra, field64):
    kp = make_params(spectra, 10, seed=17)
    model = make_model(field64, kp)
    face_ids, bary = random_points(spectra, 12, seed=18)
    with torch.no_grad():
        before = model.albedo(face_ids, bary)
        model.theta.add_(0.4)
        model.s.add_(5.0)  # beyond eta = 200: projection brings it back
        model.project_()
        after = model.albedo(face_ids, bary)
    assert float(model.eta.detach().max()) <= 200.0 + 1e-9
    theta, eta = model.theta.detach().numpy(), model.eta.detach().numpy()
    fresh = make_model(field64, {**kp, "theta": theta, "eta": eta})
    with torch.no_grad():
        np.testing.assert_allclose(after.numpy(), fresh.albedo(face_ids, bary).numpy(), atol=1e-12)
    assert not torch.allclose(before, after)


def test_footprint_is_pi_periodic_on_a_generic_mesh():
    """theta and theta + pi are one footprint (an axis has no sign; the grid's end nodes have
    one operator), and the response is continuous across the ends, on a mesh without
    symmetries. The exact icosphere is not such a mesh: its degenerate eigenvalue clusters,
    cut at K, leave the two end nodes different truncations (so this test deforms it). Why it
    matters: docs/fitting.md, twenty-fourth pass (folding theta instead of clamping it)."""
    from hktex_engine.geometry.mesh import mesh_from_arrays
    from hktex_engine.spectra.grid import compute_spectra
    from tests.kernels_support import TINY_CONFIG, tiny_mesh

    v, f = tiny_mesh(2)
    rng = np.random.default_rng(5)
    v = v * (1.0 + 0.15 * rng.standard_normal((len(v), 1))) * np.array([1.0, 0.8, 0.6])
    spectra = compute_spectra(mesh_from_arrays(v, f), TINY_CONFIG)
    field = SpectralField(spectra, device="cpu", dtype=torch.float64)
    kp = make_params(spectra, 10, seed=21)
    face_ids, bary = random_points(spectra, 40, seed=22)

    def responses(theta: float) -> np.ndarray:
        model = make_model(field, {**kp, "theta": np.full(10, theta)})
        with torch.no_grad():
            return model.responses(face_ids, bary)[0].numpy()

    at_zero = responses(0.0)
    assert float(at_zero.max()) > 0.5  # the points do see the kernels
    np.testing.assert_allclose(responses(np.pi), at_zero, atol=1e-9)
    np.testing.assert_allclose(responses(np.pi - 1e-6), responses(1e-6), atol=1e-5)
    assert np.abs(responses(np.pi / 2) - at_zero).max() > 0.1  # and theta does matter


def test_kernelset_round_trip(spectra, field64):
    kp = make_params(spectra, 10, seed=19)
    model = make_model(field64, kp)
    ks = model.to_kernelset(fitting={"task": "test"})
    assert isinstance(ks, KernelSet) and len(ks) == 10
    ks.validate(n_faces=spectra.faces.shape[0])
    np.testing.assert_allclose(ks.eta, kp["eta"], rtol=1e-12)
    again = HeatKernelModel.from_kernelset(ks, field64)
    for name in ("theta", "s", "threshold", "sharpness", "colors", "bary", "base_color"):
        np.testing.assert_allclose(getattr(again, name).detach(), getattr(model, name).detach())
    other = KernelSet(**{**ks.__dict__, "mesh_hash": "another"})
    with pytest.raises(Exception, match="another mesh"):
        HeatKernelModel.from_kernelset(other, field64)


def test_large_grad_batches_are_checkpointed_with_equal_gradients(spectra, field64, monkeypatch):
    from hktex_engine.kernels import model as kernels

    kp = make_params(spectra, 8, seed=21)
    face_ids, bary = random_points(spectra, 16, seed=22)
    grads = []
    for chunk in (10**6, 7):
        monkeypatch.setattr(kernels, "GRAD_CHUNK_POINTS", chunk)
        model = make_model(field64, kp)
        out = model.albedo(face_ids, bary)
        (out**2).sum().backward()
        grads.append([p.grad.clone() for p in model.parameters() if p.requires_grad])
    for a, b in zip(*grads, strict=True):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-10, atol=1e-12)


def test_gradient_reaches_query_barycentrics(spectra, field64):
    kp = make_params(spectra, 8, seed=23)
    model = make_model(field64, kp)
    face_ids, bary = random_points(spectra, 3, seed=24)
    face_ids = torch.as_tensor(face_ids)
    cand = torch.arange(8).expand(3, -1)
    b = torch.as_tensor(bary).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: model.responses(face_ids, q, cand)[0], (b,))


@pytest.mark.parametrize("dense", [True, False])
def test_vertex_pair_path_equals_node_matmul(spectra, field64, monkeypatch, dense):
    from hktex_engine.kernels import model as kernels

    kp = make_params(spectra, 30, seed=25)
    model = make_model(field64, kp)
    rng = np.random.default_rng(26)
    n_faces, n_points = (1, 200) if dense else (spectra.faces.shape[0], 60)
    face_ids = rng.integers(0, n_faces, n_points)
    bary = rng.dirichlet(np.ones(3), n_points)
    results = {}
    for path in ("bmm", "vertex", "auto"):
        monkeypatch.setattr(kernels, "PAIR_PATH", path)
        monkeypatch.setattr(kernels, "PAIR_CHUNK", 7)  # several gathered blocks
        with torch.no_grad():
            results[path] = model.albedo(face_ids, bary).numpy()
    np.testing.assert_allclose(results["vertex"], results["bmm"], atol=1e-12)
    np.testing.assert_allclose(results["auto"], results["bmm"], atol=1e-12)
    with torch.no_grad():  # and the auto rule takes the vertex path for dense batches only
        monkeypatch.setattr(kernels, "PAIR_PATH", "auto")
        cand = model._knn.search(
            field64.embedding_at(torch.as_tensor(face_ids), torch.as_tensor(bary)), 12
        )
        got = kernels._h_by_vertex_pairs(
            torch.as_tensor(face_ids),
            torch.as_tensor(bary),
            cand,
            *[model._terms[i] for i in (0, 2, 3)],
            field64,
        )
    assert (got is not None) == dense


def test_top_pair_gradients_equal_full_autograd(spectra, field64):
    """The fast training path (rank without a graph, differentiate only the top K_c pairs)
    gives the gradients of plain autograd through all K_s responses and ``topk``."""
    kp = make_params(spectra, 30, seed=31)
    face_ids, bary = random_points(spectra, 25, seed=32)
    fast = make_model(field64, kp)
    out, aux = fast.albedo(face_ids, bary, return_aux=True)
    (out**2).sum().backward()

    slow = make_model(field64, kp)
    with torch.no_grad():
        _, aux_ref = slow.albedo(face_ids, bary, return_aux=True)
        emb = field64.embedding_at(torch.as_tensor(face_ids), torch.as_tensor(bary))
        cand = slow._knn.search(emb, CONFIG.k_search + 8)
        cand, _ = kernels_mod._exact_cut(emb, slow._centre_emb, cand, CONFIG.k_search)
    rho, cand = slow.responses(face_ids, bary, cand)  # every candidate differentiable
    rho_top, pos = torch.topk(rho, CONFIG.k_blend, dim=1)
    kid = cand.gather(1, pos)
    mix = torch.einsum("pc,pcd->pd", rho_top, slow.colors[kid])
    mix = mix / torch.clamp(rho_top.sum(dim=1, keepdim=True), min=1.0)
    ref = torch.clamp(slow.base_color[None, :] + mix, 0.0, 1.0)
    (ref**2).sum().backward()
    np.testing.assert_allclose(out.detach().numpy(), ref.detach().numpy(), atol=1e-12)
    assert torch.equal(aux["indices"], kid)
    np.testing.assert_allclose(aux["rho"].detach().numpy(), rho_top.detach().numpy(), atol=1e-12)
    for name in ("theta", "s", "threshold", "sharpness", "colors", "bary", "base_color"):
        g_fast, g_ref = getattr(fast, name).grad, getattr(slow, name).grad
        assert g_ref.abs().max() > 0, name
        np.testing.assert_allclose(g_fast.numpy(), g_ref.numpy(), rtol=1e-9, atol=1e-12)


def test_candidates_do_not_depend_on_the_batch(spectra):
    """A point's candidates are the same alone and inside a large batch (exact per-pair cut)."""
    field32 = SpectralField(spectra, device="cpu", dtype=torch.float32)
    kp = make_params(spectra, 60, seed=33)
    config = KernelConfig(0.01, 0.3, k_search=10, k_blend=4)
    model = make_model(field32, kp, config)
    face_ids, bary = random_points(spectra, 300, seed=34)
    with torch.no_grad():
        _, aux = model.albedo(face_ids, bary, return_aux=True)
        for p in range(0, 300, 37):
            _, one = model.albedo(face_ids[p : p + 1], bary[p : p + 1], return_aux=True)
            assert torch.equal(one["indices"][0], aux["indices"][p])


def test_exact_cut_orders_by_distance_then_index():
    emb_c = torch.tensor([[0.0], [1.0], [-1.0], [2.0], [1.0]])
    cand = torch.tensor([[3, 4, 0, 1, 2]])
    got, d2 = kernels_mod._exact_cut(torch.zeros(1, 1), emb_c, cand, 4)
    assert got.tolist() == [[0, 1, 2, 4]]
    assert d2.tolist() == [[0.0, 1.0, 1.0, 1.0]]


def test_cached_centre_rows_give_the_same_training_step(spectra, field64, monkeypatch):
    """Training with the centre-row cache equals training without it, across steps that
    move kernels into other grid cells."""
    kp = make_params(spectra, 30, seed=35)
    face_ids, bary = random_points(spectra, 25, seed=36)
    runs = []
    for cap in (kernels_mod.ROWS_CACHE_BYTES, 0):
        monkeypatch.setattr(kernels_mod, "ROWS_CACHE_BYTES", cap)
        model = make_model(field64, kp)
        opt = torch.optim.SGD([model.theta, model.s, model.colors], lr=0.5)
        grads = []
        for step in range(3):
            opt.zero_grad()
            (model.albedo(face_ids, bary) ** 2).sum().backward()
            grads.append(
                torch.cat([p.grad.reshape(-1) for p in model.parameters() if p.requires_grad])
            )
            opt.step()
            model.project_()
            moved = model.face_ids.clone()
            moved[step::7] = (moved[step::7] + 1) % spectra.faces.shape[0]  # other faces
            model.set_centres(moved, model.bary.detach())
        runs.append(torch.stack(grads))
        if cap:
            assert model._rows.regathered < len(model)  # the cache was used and kept rows
    np.testing.assert_allclose(runs[0].numpy(), runs[1].numpy(), rtol=1e-9, atol=1e-12)
