"""A biharmonic scale per kernel (``KernelConfig.sigma = "per_kernel"``): every evaluation
path against the independent numpy reading of §4-5 with ``sigma_j`` in place of sigma_B, ratios
of one against the uniform set bit for bit, the scale's gradient (compiled and torch) against
finite differences, storage (versions 7 and 8) and a fit that learns the scales. The compiled
training batch against the torch path: tests/test_fused_training.py."""

from __future__ import annotations

import io
import json
import math
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import torch

from hktex_engine.config import SIGMA_RATIO_RANGE, fit_params_from
from hktex_engine.errors import KernelSetError
from hktex_engine.kernels import compiled
from hktex_engine.kernels import model as kernels_mod
from hktex_engine.kernels.hkt import encode_hkt, load_hkt
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_points, tiny_spectra
from tests.test_fused_training import step_grads
from tests.test_kernels import (
    CONFIG,
    assert_extension_member_checked,
    assert_float32_query_paths_match,
    assert_float64_paths_match,
    make_model,
    make_params,
    reference_albedo,
)

PER_KERNEL = replace(CONFIG, sigma="per_kernel")
HAVE_COMPILED = compiled.available(torch.device("cpu"), torch.float32)


@pytest.fixture(scope="module")
def case(spectra):
    """30 kernels with ratios over the whole box, 60 points, and the numpy reading."""
    kp = make_params(spectra, 30, seed=2)
    kp["sigma_ratio"] = np.exp(np.random.default_rng(5).uniform(*np.log(SIGMA_RATIO_RANGE), 30))
    face_ids, bary = random_points(spectra, 60, seed=4)
    ref, rho = reference_albedo(spectra, kp, CONFIG, face_ids, bary)
    return kp, face_ids, bary, ref, rho


def test_every_float64_path_matches_the_numpy_reading(spectra, field64, case):
    kp, face_ids, bary, ref, rho = case
    uniform = reference_albedo(spectra, {**kp, "sigma_ratio": np.ones(30)}, CONFIG, face_ids, bary)
    assert np.abs(ref - uniform[0]).max() > 0.05, "the scales must change colours here"
    model = make_model(field64, kp, PER_KERNEL)
    got_rho, _ = model.responses(face_ids, bary)  # with a graph
    np.testing.assert_allclose(got_rho.detach().numpy(), rho, atol=1e-9)
    assert_float64_paths_match(model, face_ids, bary, ref)


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("table_path", ["always", "never"])
def test_float32_query_paths_match(case, spectra, field64, fused, table_path, monkeypatch):
    """Candidate tables (compiled blend or its torch twin) and the per-point path (compiled
    ranking or torch)."""
    kp, face_ids, bary, _, _ = case
    assert_float32_query_paths_match(
        spectra, field64, kp, PER_KERNEL, face_ids, bary, fused, table_path, monkeypatch
    )


@pytest.fixture(scope="module")
def spectra3():
    return tiny_spectra(3)


@pytest.mark.skipif(not HAVE_COMPILED, reason="numba is not installed")
def test_ratios_of_one_are_the_uniform_set_bit_for_bit(spectra3, monkeypatch):
    """Per-kernel scales all equal to sigma_B: the same numbers as §4's set on the compiled
    paths (tables, per-point ranking, a training batch and its gradients)."""
    field = SpectralField(spectra3, device="cpu", dtype=torch.float32)
    kp = make_params(spectra3, 300, seed=21)
    f, b = random_points(spectra3, 900, seed=6)
    target = torch.rand((900, 3), generator=torch.Generator().manual_seed(3))
    ones = {**kp, "sigma_ratio": np.ones(300)}
    uniform, scaled = make_model(field, kp, CONFIG), make_model(field, ones, PER_KERNEL)
    ref, got = step_grads(uniform, f, b, target), step_grads(scaled, f, b, target)
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1]["indices"], ref[1]["indices"])
    for name, g in ref[2].items():
        assert torch.equal(got[2][name], g), name
    assert "log_sigma" in got[2] and "log_sigma" not in ref[2]
    for path in ("always", "never"):
        monkeypatch.setattr(kernels_mod, "TABLE_PATH", path)
        with torch.no_grad():
            assert torch.equal(scaled.albedo(f, b), uniform.albedo(f, b)), path


@pytest.mark.parametrize("compiled_path", [True, False])
def test_scale_gradient_against_finite_differences(spectra3, compiled_path, monkeypatch):
    """``K_c = K_s``: no selection, so the blend is smooth in every scale; the analytic
    d albedo / d log sigma_j against central differences of the no-grad albedo (float64
    torch path, or the compiled float32 one)."""
    if compiled_path and not HAVE_COMPILED:
        pytest.skip("numba is not installed")
    dtype = torch.float32 if compiled_path else torch.float64
    field = SpectralField(spectra3, device="cpu", dtype=dtype)
    config = replace(PER_KERNEL, k_search=8, k_blend=8)
    kp = make_params(spectra3, 120, seed=32)
    kp["sigma_ratio"] = np.exp(np.random.default_rng(7).uniform(-0.5, 0.5, 120))
    f, b = random_points(spectra3, 900, seed=9)
    weights = torch.randn((900, 3), generator=torch.Generator().manual_seed(6), dtype=dtype)
    model = make_model(field, kp, config)
    assert model._compiled_training() == compiled_path
    (model.albedo(f, b) * weights).sum().backward()
    grad = model.log_sigma.grad.clone()
    chosen = torch.argsort(grad.abs(), descending=True)[:4]
    assert float(grad[chosen].abs().min()) > 0.1  # a check that can fail
    eps = 1e-2 if compiled_path else 1e-5
    for j in chosen.tolist():
        values = []
        for sign in (1, -1):
            with torch.no_grad():
                model.log_sigma[j] += sign * eps
                values.append(float((model.albedo(f, b) * weights).sum()))
                model.log_sigma[j] -= sign * eps
        fd = (values[0] - values[1]) / (2 * eps)
        rel = 2e-2 if compiled_path else 1e-5
        assert fd == pytest.approx(float(grad[j]), rel=rel, abs=1e-3 if compiled_path else 1e-8)


def test_storage_round_trips_and_versions(field64, case):
    kp = case[0]
    ks = make_model(field64, kp, PER_KERNEL).to_kernelset()
    np.testing.assert_allclose(ks.sigma_ratio, kp["sigma_ratio"], rtol=1e-12)
    plain = load_hkt(io.BytesIO(encode_hkt(ks, compact=True)))
    np.testing.assert_allclose(plain.sigma_ratio, kp["sigma_ratio"], rtol=5e-4)  # float16
    assert plain.kernel_config.sigma == "per_kernel"
    payload = encode_hkt(ks, compact=True, quantised=True)
    quant = load_hkt(io.BytesIO(payload))
    order = np.argsort(kp["face_ids"], kind="stable")  # a quantised file sorts by face
    step = math.log(SIGMA_RATIO_RANGE[1] / SIGMA_RATIO_RANGE[0]) / 255
    err = np.abs(np.log(quant.sigma_ratio / kp["sigma_ratio"][order]))
    assert err.max() <= step / 2 + 1e-9
    versions = {}
    for quantised in (False, True):
        with zipfile.ZipFile(io.BytesIO(encode_hkt(ks, True, quantised))) as zf:
            versions[quantised] = json.loads(zf.read("manifest.json"))["version"]
    assert versions == {False: 7, True: 8}
    # with the layered blend as well: the same versions, both members
    kp_l = {**kp, "priority": np.random.default_rng(1).uniform(-3, 3, 30)}
    both = make_model(field64, kp_l, replace(PER_KERNEL, blend="layered")).to_kernelset()
    for quantised in (False, True):
        back = load_hkt(io.BytesIO(encode_hkt(both, True, quantised)))
        assert back.priority is not None and back.sigma_ratio is not None
        assert back.kernel_config.blend == "layered"
    # a §4-5 set keeps its manifest: no ``sigma`` key, version 1
    paper = make_model(field64, kp, CONFIG).to_kernelset()
    assert paper.sigma_ratio is None
    with zipfile.ZipFile(io.BytesIO(encode_hkt(paper, True))) as zf:
        manifest = json.loads(zf.read("manifest.json"))
    assert manifest["version"] == 1 and "sigma" not in manifest


def test_a_loaded_set_evaluates_as_written(spectra, case):
    kp, face_ids, bary, _, _ = case
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    model = make_model(field, kp, PER_KERNEL)
    back = kernels_mod.HeatKernelModel.from_kernelset(
        load_hkt(io.BytesIO(encode_hkt(model.to_kernelset(), compact=False))), field
    )
    with torch.no_grad():
        np.testing.assert_allclose(
            back.albedo(face_ids, bary).numpy(), model.albedo(face_ids, bary).numpy(), atol=1e-6
        )


def _rewrite_manifest(payload: bytes, **changes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(payload)) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "manifest.json":
                manifest = {k: v for k, v in json.loads(data).items() if k not in changes}
                data = json.dumps({**manifest, **{k: v for k, v in changes.items() if v}})
                data = data.encode()
            dst.writestr(item, data)
    return out.getvalue()


def test_storage_refuses_what_its_version_cannot_hold(field64, case):
    kp = case[0]
    ks = make_model(field64, kp, PER_KERNEL).to_kernelset()
    assert_extension_member_checked(ks, "sigma_ratio", "a per-kernel-sigma set")
    with pytest.raises(KernelSetError, match="out of range"):
        encode_hkt(replace(ks, sigma_ratio=np.full(len(ks), 3.0)), compact=True)
    # a version-7 file whose manifest claims sigma_B for all, and a version-1 claiming more
    v7 = encode_hkt(ks, compact=True)
    with pytest.raises(KernelSetError, match="version-7 file cannot hold a 'uniform' sigma"):
        load_hkt(io.BytesIO(_rewrite_manifest(v7, sigma=None)))
    v1 = encode_hkt(make_model(field64, kp, CONFIG).to_kernelset(), compact=True)
    with pytest.raises(KernelSetError, match="version-1 file cannot hold a 'per_kernel'"):
        load_hkt(io.BytesIO(_rewrite_manifest(v1, sigma="per_kernel")))
    with pytest.raises(KernelSetError, match="cannot hold a 'per_face' sigma"):
        load_hkt(io.BytesIO(_rewrite_manifest(v7, sigma="per_face")))


def test_a_fit_learns_the_scales_and_keeps_them_through_density_control():
    """The ``sigma`` preset on a short UV fit with densification: ratios move off one, stay in
    their box, survive clones, splits and the colour solve, and the file evaluates as fitted."""
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.spectra.grid import compute_spectra
    from tests.test_fit_uv import TINY, two_colour_sphere

    mesh = two_colour_sphere()
    spectra = compute_spectra(mesh, TINY)
    params = fit_params_from(
        {"preset": "sigma", "kernels": 60, "steps": 80, "points_per_step": 256, "seed": 3}
    )
    params = replace(params, kernel=replace(params.kernel, k_search=20, k_blend=8))
    result = fit_uv(mesh, spectra, params, eval_points=500)
    ks = result.kernelset
    assert ks.kernel_config.sigma == "per_kernel" and ks.sigma_ratio is not None
    assert any(e["kind"] == "densify" for e in result.density_events)
    assert np.ptp(ks.sigma_ratio) > 0.02
    lo, hi = SIGMA_RATIO_RANGE
    assert ks.sigma_ratio.min() >= lo * (1 - 1e-9) and ks.sigma_ratio.max() <= hi * (1 + 1e-9)
    back = load_hkt(io.BytesIO(encode_hkt(ks, compact=False)))
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    f, b = random_points(spectra, 200, seed=9)
    with torch.no_grad():
        a = kernels_mod.HeatKernelModel.from_kernelset(ks, field).albedo(f, b)
        c = kernels_mod.HeatKernelModel.from_kernelset(back, field).albedo(f, b)
    np.testing.assert_allclose(a.numpy(), c.numpy(), atol=1e-5)


def test_scales_wait_for_their_start():
    """``sigma_start``: the optimiser keeps every ratio at 1 before that fraction of the steps,
    and trains them after it."""
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.spectra.grid import compute_spectra
    from tests.test_fit_uv import TINY, two_colour_sphere

    mesh = two_colour_sphere()
    spectra = compute_spectra(mesh, TINY)
    base = {"preset": "sigma", "kernels": 40, "steps": 20, "points_per_step": 128, "seed": 2}
    base["densify"] = False
    never = fit_uv(mesh, spectra, fit_params_from({**base, "sigma_start": 1.0}), eval_points=300)
    assert np.all(never.kernelset.sigma_ratio == 1)
    late = fit_uv(mesh, spectra, fit_params_from({**base, "sigma_start": 0.5}), eval_points=300)
    moved = np.abs(np.log(late.kernelset.sigma_ratio)).max()
    # ten steps at lr_sigma: an Adam step is at most (1 - b1) / sqrt(1 - b2) ~ 3.2 lr
    assert 0 < moved <= 10 * 0.01 * 3.2 + 1e-6


def test_clones_and_appended_kernels_carry_their_scale(field64, case):
    kp = case[0]
    model = make_model(field64, kp, PER_KERNEL)
    before = model.log_sigma.detach().clone()
    model.select(torch.tensor([3, 3, 7]))
    assert torch.equal(model.log_sigma.detach(), before[[3, 3, 7]])
    rows = {k: np.asarray(v)[:2] for k, v in kp.items() if k not in ("base_color",)}
    model.append(
        rows["face_ids"], rows["bary"], rows["theta"], rows["eta"], rows["threshold"],
        rows["sharpness"], rows["colors"], log_sigma=np.array([0.25, -0.5]),
    )  # fmt: skip
    np.testing.assert_allclose(model.log_sigma.detach().numpy()[3:], [0.25, -0.5])


def test_chunked_batches_keep_the_scale_gradient(spectra, case, monkeypatch):
    """Large differentiable batches (multi-view rays) recompute each chunk in backward; the
    scales' gradient must come through that as through one chunk."""
    kp = case[0]
    field = SpectralField(spectra, device="cpu", dtype=torch.float64)
    f, b = random_points(spectra, 300, seed=12)
    cand = torch.arange(30).expand(300, -1)
    grads = []
    for chunk in (10**6, 64):
        monkeypatch.setattr(kernels_mod, "GRAD_CHUNK_POINTS", chunk)
        model = make_model(field, kp, PER_KERNEL)
        rho, _ = model.responses(f, torch.as_tensor(b), cand)
        (rho * torch.linspace(-1, 1, 30, dtype=torch.float64)).sum().backward()
        grads.append(model.log_sigma.grad.clone())
    assert float(grads[0].abs().max()) > 0
    np.testing.assert_allclose(grads[1].numpy(), grads[0].numpy(), rtol=1e-10, atol=1e-12)
