"""The compiled training step (kernels.fused_rank, fused_pairs, fused_terms) against
independent computations: the exact search against a brute-force cut over all centres, each
autograd function's forward and backward against plain torch autograd of the same formulas
written here, finite differences, and a whole differentiable batch against the torch path it
replaces (same kernels chosen, albedo within 1e-5, gradients to float32 round-off). The
saturated-tie cases run through it in tests/test_ties.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from hktex_engine.config import KernelConfig
from hktex_engine.kernels import blending, compiled, fused_pairs, fused_rank, fused_terms
from hktex_engine.kernels.model import _exhaustive_cut, soft_step
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import tiny_spectra
from tests.test_kernels import make_model, make_params

pytestmark = pytest.mark.skipif(not compiled.HAVE_NUMBA, reason="numba is not installed")

CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=16, k_blend=5)


@pytest.fixture(scope="module")
def spectra3():
    return tiny_spectra(3)


@pytest.fixture(scope="module")
def field32(spectra3):
    return SpectralField(spectra3, device="cpu", dtype=torch.float32)


def _points(spectra, n, seed):
    rng = np.random.default_rng(seed)
    return rng.integers(0, spectra.faces.shape[0], n), rng.dirichlet(np.ones(3), n)


def test_nearest_equals_a_brute_force_cut(field32, spectra3):
    """Surface embeddings (clusters prune) and structureless 40-D noise (they cannot), with
    exact clones: the same ids in the same order as the cut over all centres by the rule."""
    kp = make_params(spectra3, 400, seed=3)
    f = torch.as_tensor(kp["face_ids"])
    b = torch.as_tensor(kp["bary"], dtype=torch.float32)
    emb_c = field32.embedding_at(f, b)
    emb_c = torch.cat([emb_c, emb_c[::7]])  # clones: exact distance ties, broken by id
    pf, pb = _points(spectra3, 700, 4)
    emb_y = field32.embedding_at(torch.as_tensor(pf), torch.as_tensor(pb, dtype=torch.float32))
    noise = torch.randn((300, 40), generator=torch.Generator().manual_seed(0))
    for y, c in ((emb_y, emb_c), (noise[:100], noise[100:])):
        for k in (1, 16, c.shape[0]):
            ids, d2 = fused_rank.nearest(y, c, k)
            ref_ids, ref_d2 = _exhaustive_cut(y, c, k)
            ids, d2, ref_ids = ids.numpy(), d2.numpy(), ref_ids.numpy()
            # the same set (distances are summed in another order, so the order may differ
            # only between distances within round-off of each other)
            np.testing.assert_array_equal(np.sort(ids, axis=1), np.sort(ref_ids, axis=1))
            np.testing.assert_allclose(d2, ref_d2.numpy(), rtol=1e-5, atol=1e-9)
            assert (np.diff(d2, axis=1) >= 0).all()
            tied = np.diff(d2, axis=1) == 0  # exact ties (the clones): by id
            assert (np.diff(ids, axis=1)[tied] > 0).all()
            if k < c.shape[0]:
                assert (ids == ref_ids).mean() > 0.999
    # any grouping is exact (training keeps an earlier one while the centres move): a
    # random assignment to 7 clusters, empty ones included
    labels = np.random.default_rng(1).integers(0, 9, emb_c.shape[0]) % 7
    labels[labels == 3] = 8  # clusters 3 and 7 stay empty
    cl = fused_rank.Clusters(emb_c, labels)
    ids, d2 = fused_rank.nearest(emb_y, cl, 16)
    ref_ids, ref_d2 = _exhaustive_cut(emb_y, emb_c, 16)
    np.testing.assert_array_equal(np.sort(ids.numpy(), 1), np.sort(ref_ids.numpy(), 1))
    np.testing.assert_allclose(d2.numpy(), ref_d2.numpy(), rtol=1e-5, atol=1e-9)


def test_kernel_terms_against_autograd_and_finite_differences(field32, spectra3):
    """coef and norm of ALGORITHM.md 4 (interpolated eigenfunctions and eigenvalues), and
    their gradients to the centre barycentrics and the bilinear weights."""
    field = field32
    kp = make_params(spectra3, 50, seed=8)
    f = torch.as_tensor(kp["face_ids"])
    verts = field.faces[f]
    nodes, weights = field.nodes(
        torch.as_tensor(kp["theta"], dtype=torch.float32),
        torch.log1p(torch.as_tensor(kp["eta"], dtype=torch.float32)),
    )
    bary = torch.as_tensor(kp["bary"], dtype=torch.float32)
    t = 0.01
    g = torch.Generator().manual_seed(1)
    g_coef = torch.randn((50, field.k), generator=g)
    g_norm = torch.randn(50, generator=g)

    def reference(b, w):
        e = field.evecs[verts[:, :, None], nodes[:, None, :]].to(torch.float64)  # (U, 3, 4, K)
        phi = torch.einsum("uv,uc,uvck->uk", b, w, e)
        lam = torch.einsum("uc,uck->uk", w, field.evals.to(torch.float64)[nodes])
        coef = torch.exp(-t * lam) * phi
        return coef, (coef * phi).sum(dim=1)

    b64 = bary.double().requires_grad_(True)
    w64 = weights.double().requires_grad_(True)
    ref_coef, ref_norm = reference(b64, w64)
    ((ref_coef * g_coef.double()).sum() + (ref_norm * g_norm.double()).sum()).backward()

    for rows in (None, "cache"):
        cache = None
        if rows:
            from hktex_engine.spectra.interpolation import RowCache

            cache = RowCache(2**30)
        table, ridx = fused_terms.row_table(field, verts, nodes, cache)
        b32 = bary.clone().requires_grad_(True)
        w32 = weights.detach().clone().requires_grad_(True)
        coef, norm = fused_terms.KernelTerms.apply(table, ridx, field, nodes, b32, w32, t)
        np.testing.assert_allclose(coef.detach().numpy(), ref_coef.detach().numpy(), atol=2e-5)
        np.testing.assert_allclose(norm.detach().numpy(), ref_norm.detach().numpy(), rtol=1e-4)
        ((coef * g_coef).sum() + (norm * g_norm).sum()).backward()
        scale = float(b64.grad.abs().max())
        np.testing.assert_allclose(b32.grad.numpy(), b64.grad.numpy(), atol=1e-4 * scale)
        scale = float(w64.grad.abs().max())
        np.testing.assert_allclose(w32.grad.numpy(), w64.grad.numpy(), atol=1e-4 * scale)

    # finite differences of the float64 reference itself close the loop on the formulas
    eps = 1e-6
    db = torch.zeros_like(b64)
    db[3, 1] = eps
    with torch.no_grad():
        plus = reference(b64 + db, w64)
        minus = reference(b64 - db, w64)
    fd = sum(((p - m) * gg.double()).sum() for p, m, gg in zip(plus, minus, (g_coef, g_norm), strict=True)) / (2 * eps)  # fmt: skip
    assert abs(float(fd) - float(b64.grad[3, 1])) <= 1e-6 * max(1.0, abs(float(fd)))


def test_embedding_against_autograd(field32, spectra3):
    f, b = _points(spectra3, 300, 9)
    f = torch.as_tensor(f)
    b32 = torch.as_tensor(b, dtype=torch.float32).requires_grad_(True)
    b_ref = b32.detach().clone().requires_grad_(True)
    got = fused_terms.Embedding.apply(field32, f, b32)
    ref = field32.embedding_at(f, b_ref)
    np.testing.assert_allclose(got.detach().numpy(), ref.detach().numpy(), atol=1e-6)
    g = torch.randn(ref.shape, generator=torch.Generator().manual_seed(2))
    (got * g).sum().backward()
    (ref * g).sum().backward()
    np.testing.assert_allclose(b32.grad.numpy(), b_ref.grad.numpy(), rtol=1e-5, atol=1e-6)


def _pair_reference(top, dots, blend, emb_y, sigma_b, coef, norm, w, emb_c, thr, sharp, col, base, prio=None):  # fmt: skip
    """ALGORITHM.md 4-5 for chosen pairs, in plain torch float64 (autograd does backward).
    ``h`` takes its value from ``dots`` and its coef-gradient from ``blend`` (dh/dcoef), as
    the saved ranking quantities define it. ``prio``: the layered blend, written out here
    without the max shift (it cancels)."""
    via_coef = (coef[top] * blend).sum(dim=2)
    h = (w[top] * dots).sum(dim=2) + via_coef - via_coef.detach()
    d2 = ((emb_y[:, None, :] - emb_c[top]) ** 2).sum(dim=2)
    r = h * torch.exp(-d2 / (2 * sigma_b**2)) / norm[top]
    rho = soft_step(r, thr[top], sharp[top])
    if prio is not None:
        omega = rho * torch.exp(prio[top])
        cover = torch.clamp(rho.sum(dim=1, keepdim=True), max=1.0)
        mass = omega.sum(dim=1, keepdim=True)
        mix = torch.einsum("pc,pcd->pd", omega, col[top]) * cover / torch.where(mass > 0, mass, 1)
        return torch.clamp(base + mix, 0.0, 1.0), rho
    den = torch.clamp(rho.sum(dim=1, keepdim=True), min=1.0)
    out = torch.clamp(base + torch.einsum("pc,pcd->pd", rho, col[top]) / den, 0.0, 1.0)
    return out, rho


@pytest.mark.parametrize(("layered", "scaled"), [(False, False), (True, False), (False, True)])
def test_pair_blend_against_autograd(layered, scaled):
    """Random pairs with every regime present: rho saturated at 1, at 0, in between; sums of
    rho above and below 1; albedo clamped at both ends. The compiled footprints, then the
    torch blend (either rule), against plain float64 autograd; ``scaled``: a sigma per
    kernel (its gradient too)."""
    g = torch.Generator().manual_seed(7)
    n_k, p, k_c, kk, dim = 40, 300, 6, 12, 5
    top = torch.stack([torch.randperm(n_k, generator=g)[:k_c] for _ in range(p)])
    blend = torch.randn((p, k_c, kk), generator=g)
    coef = torch.randn((n_k, kk), generator=g)
    dots = torch.randn((p, k_c, 4), generator=g) + 0.5  # some h < 0: rho = 0 there
    params = {
        "norm": torch.rand(n_k, generator=g) + 0.5,
        "w": torch.rand((n_k, 4), generator=g),
        "emb_c": torch.randn((n_k, dim), generator=g) * 0.2,
        "thr": 0.3 + 0.69 * torch.rand(n_k, generator=g),
        "sharp": 10 + 60 * torch.rand(n_k, generator=g),
        "col": torch.rand((n_k, 3), generator=g) * 2 - 1,
        "base": torch.tensor([0.2, 0.5, 0.9]),
    }
    if layered:
        params["prio"] = torch.rand(n_k, generator=g) * 6 - 3
    sigma_b = 0.3
    if scaled:
        params["sigma"] = sigma_b * torch.exp(torch.rand(n_k, generator=g) * 1.4 - 0.7)
    emb_y = torch.randn((p, dim), generator=g) * 0.2
    ref_in = {n: v.double().requires_grad_(True) for n, v in params.items()}
    coef64 = coef.double().requires_grad_(True)
    sigma_pairs = ref_in["sigma"][top] if scaled else sigma_b
    out_r, rho_r = _pair_reference(
        top, dots.double(), blend.double(), emb_y.double(), sigma_pairs, coef64, ref_in["norm"],
        ref_in["w"], ref_in["emb_c"], ref_in["thr"], ref_in["sharp"], ref_in["col"], ref_in["base"],
        ref_in.get("prio"),
    )  # fmt: skip
    rho_np = rho_r.detach().numpy()
    assert (rho_np == 1).any() and (rho_np == 0).any() and ((rho_np > 0) & (rho_np < 1)).any()
    sums = rho_np.sum(axis=1)
    assert (sums > 1).any() and (sums < 1).any()
    assert ((out_r == 0) | (out_r == 1)).any() and ((out_r > 0) & (out_r < 1)).any()
    got_in = {n: v.clone().requires_grad_(True) for n, v in params.items()}
    coef32 = coef.clone().requires_grad_(True)
    ratio = got_in["sigma"] / sigma_b if scaled else None
    scale = fused_pairs.pair_scales(sigma_b, ratio, n_k)
    rho = fused_pairs.PairResponse.apply(
        top, dots, blend, emb_y, scale, coef32, got_in["norm"], got_in["w"], got_in["emb_c"],
        got_in["thr"], got_in["sharp"],
    )  # fmt: skip
    prio = got_in["prio"][top] if layered else None
    out = blending.albedo(rho, got_in["col"][top], got_in["base"], prio)
    np.testing.assert_allclose(out.detach().numpy(), out_r.detach().numpy(), atol=1e-5)
    np.testing.assert_allclose(rho.detach().numpy(), rho_np, atol=1e-5)  # f32 against f64
    g_out = torch.randn((p, 3), generator=g)
    (out * g_out).sum().backward()
    (out_r * g_out.double()).sum().backward()
    for name, ref in ref_in.items():
        scale = float(ref.grad.abs().max())
        np.testing.assert_allclose(got_in[name].grad.numpy(), ref.grad.numpy(), atol=2e-5 * scale, err_msg=name)  # fmt: skip
    scale = float(coef64.grad.abs().max())
    np.testing.assert_allclose(coef32.grad.numpy(), coef64.grad.numpy(), atol=2e-5 * scale)


def step_grads(model, f, b, target):
    model.zero_grad()
    out, aux = model.albedo(f, b, return_aux=True)
    ((out - target) ** 2).mean().backward()
    grads = {n: p.grad.detach().clone() for n, p in model.named_parameters() if p.requires_grad}
    return out.detach(), aux, grads


@pytest.mark.parametrize(
    ("threads", "blend", "sigma"),
    [(1, "paper", "uniform"), (2, "paper", "uniform"), (2, "layered", "uniform"),
     (1, "paper", "per_kernel"), (2, "paper", "per_kernel")],
)  # fmt: skip
def test_training_batch_equals_the_torch_path(field32, spectra3, monkeypatch, threads, blend, sigma):  # fmt: skip
    """A differentiable batch through the compiled step against the torch path (ranking by
    node matmul, autograd through the pairs and per-kernel terms); with a sigma per kernel
    (``log_sigma``'s gradient too)."""
    monkeypatch.setattr(fused_rank, "THREAD_MIN_POINTS", 200)
    monkeypatch.setattr(fused_pairs, "THREAD_MIN_POINTS", 200)
    monkeypatch.setattr(fused_terms, "THREAD_MIN_KERNELS", 100)
    kp = make_params(spectra3, 300, seed=21)
    config = replace(CONFIG, blend=blend, sigma=sigma)
    if blend == "layered":
        kp["priority"] = np.random.default_rng(4).uniform(-3, 3, 300)
    if sigma == "per_kernel":
        kp["sigma_ratio"] = np.exp(np.random.default_rng(4).uniform(-0.9, 0.9, 300))
    f, b = _points(spectra3, 900, 6)
    target = torch.rand((900, 3), generator=torch.Generator().manual_seed(3))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = step_grads(make_model(field32, kp, config), f, b, target)
        monkeypatch.setattr(compiled, "available", lambda device, dtype: False)
        ref = step_grads(make_model(field32, kp, config), f, b, target)
    finally:
        torch.set_num_threads(old)
    np.testing.assert_allclose(got[0].numpy(), ref[0].numpy(), atol=1e-5)
    same = (got[1]["indices"] == ref[1]["indices"]).all(dim=1)
    assert same.float().mean() > 0.999
    for name, g_ref in ref[2].items():
        scale = float(g_ref.abs().max())
        np.testing.assert_allclose(got[2][name].numpy(), g_ref.numpy(), atol=1e-3 * scale, err_msg=name)  # fmt: skip


def test_other_dtypes_and_devices_keep_the_torch_path(field64):
    assert not fused_rank.available(torch.device("cpu"), torch.float64)
    assert not fused_rank.available(torch.device("cuda"), torch.float32)
    assert not fused_terms.available(field64, torch.float64)


def test_sparse_no_grad_queries_equal_the_torch_path(field32, spectra3, monkeypatch):
    """The per-point no-grad path (no candidate tables) ranks through the same compiled loop."""
    from hktex_engine.kernels import model as kernels_mod

    monkeypatch.setattr(kernels_mod, "TABLE_PATH", "never")
    kp = make_params(spectra3, 300, seed=22)
    f, b = _points(spectra3, 800, 7)
    with torch.no_grad():
        got, aux = make_model(field32, kp, CONFIG).albedo(f, b, return_aux=True)
        monkeypatch.setattr(compiled, "available", lambda device, dtype: False)
        ref, ref_aux = make_model(field32, kp, CONFIG).albedo(f, b, return_aux=True)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-5)
    assert (aux["indices"] == ref_aux["indices"]).all(dim=1).float().mean() > 0.999
    np.testing.assert_allclose(aux["rho"].numpy(), ref_aux["rho"].numpy(), atol=1e-5)


def test_float16_grids_are_read_in_place_by_sparse_queries(spectra3, monkeypatch):
    """A service holds float16 grids memory-mapped and shared between workers: sparse no-grad
    queries rank compiled on the float16 grid itself (no private float32 copy), with the same
    colours and choices as on the grid's float32 values; training makes the copy (once per
    field) and runs compiled."""
    import dataclasses

    from hktex_engine.kernels import model as kernels_mod

    monkeypatch.setattr(kernels_mod, "TABLE_PATH", "never")
    half = dataclasses.replace(spectra3, evecs=np.asarray(spectra3.evecs, dtype=np.float16))
    field = SpectralField(half, device="cpu", dtype=torch.float32)
    assert field.evecs.dtype == torch.float16
    widened = dataclasses.replace(spectra3, evecs=np.asarray(half.evecs, dtype=np.float32))
    field_wide = SpectralField(widened, device="cpu", dtype=torch.float32)
    kp = make_params(half, 200, seed=4)
    model = make_model(field, kp, CONFIG)
    assert model.ranks_compiled()
    calls = []
    real = fused_rank.rank_pairs
    monkeypatch.setattr(fused_rank, "rank_pairs", lambda *a, **k: calls.append(1) or real(*a, **k))
    f, b = _points(half, 300, 8)
    with torch.no_grad():
        got, aux = model.albedo(f, b, return_aux=True)
        ref, ref_aux = make_model(field_wide, kp, CONFIG).albedo(f, b, return_aux=True)
    assert calls and getattr(field, "_evecs32", None) is None
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-6)
    assert (aux["indices"] == ref_aux["indices"]).all(dim=1).float().mean() > 0.999
    model.albedo(f, b).sum().backward()
    assert field._evecs32.dtype == np.float32 and model.colors.grad is not None


def test_half_conversion_is_exact_on_every_pattern():
    """The compiled float16 -> float32 conversion against numpy's on all 65,536 bit patterns:
    the same bits (zeros of both signs, subnormals, infinities), NaN where numpy has NaN."""
    bits = np.arange(2**16, dtype=np.uint16).reshape(512, 128)
    got = fused_rank.half_to_float32(bits)
    ref = bits.view(np.float16).astype(np.float32)
    nan = np.isnan(ref)
    assert (np.isnan(got) == nan).all()
    assert (got[~nan].view(np.uint32) == ref[~nan].view(np.uint32)).all()


def test_training_reads_a_float16_grid_in_place_above_the_copy_cap(spectra3, monkeypatch):
    """A grid whose float32 copy would pass ``EVECS32_MAX_BYTES`` (a 128k-vertex mesh's is
    3.2 GB) trains compiled on the float16 grid itself: no copy, and the same step (colours,
    choices and every gradient) as training on the copy. Before, it fell back to the torch
    path, 5x slower a step at that size."""
    import dataclasses

    from hktex_engine.kernels import model as kernels_mod

    monkeypatch.setattr(kernels_mod, "TABLE_PATH", "never")
    half = dataclasses.replace(spectra3, evecs=np.asarray(spectra3.evecs, dtype=np.float16))
    kp = make_params(half, 300, seed=23)
    f, b = _points(half, 900, 9)
    target = torch.rand((900, 3), generator=torch.Generator().manual_seed(5))
    copied = SpectralField(half, device="cpu", dtype=torch.float32)
    ref = step_grads(make_model(copied, kp, CONFIG), f, b, target)
    assert copied._evecs32.dtype == np.float32  # under the cap: the copy, as before

    monkeypatch.setattr(fused_rank, "EVECS32_MAX_BYTES", 0)
    in_place = SpectralField(half, device="cpu", dtype=torch.float32)
    calls = []
    real = fused_rank.rank_pairs
    monkeypatch.setattr(fused_rank, "rank_pairs", lambda *a, **k: calls.append(k) or real(*a, **k))
    model = make_model(in_place, kp, CONFIG)
    assert model._compiled_training() and fused_terms.available(in_place, torch.float32)
    got = step_grads(model, f, b, target)
    assert calls and getattr(in_place, "_evecs32", None) is None
    np.testing.assert_allclose(got[0].numpy(), ref[0].numpy(), atol=1e-6)
    assert (got[1]["indices"] == ref[1]["indices"]).all()
    for name, g_ref in ref[2].items():
        scale = float(g_ref.abs().max())
        np.testing.assert_allclose(got[2][name].numpy(), g_ref.numpy(), atol=1e-5 * scale, err_msg=name)  # fmt: skip
