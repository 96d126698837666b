"""Linear colours per kernel (``KernelConfig.colour = "linear"``, .hkt versions 9/10): every
evaluation path against the numpy reading of ALGORITHM.md §4-5 with ``a_j + G_j (x - x(c_j))``
as the colour, slopes of zero against §4-5, the slopes' gradient against finite differences,
the joint least-squares solve (``benchmarks/rescore.py --solve``) against a dense one,
storage, and a fit that trains them."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import torch

from hktex_engine.config import SLOPE_RANGE, FitParams, fit_params_from
from hktex_engine.errors import KernelSetError
from hktex_engine.fitting.colour_solve import (
    SLOPE_COLUMN_SCALE,
    blend_weights,
    design_matrix,
    slope_offsets,
    solve_colours,
)
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
from hktex_engine.kernels import compiled
from hktex_engine.kernels import model as kernels_mod
from hktex_engine.kernels.hkt import encode_hkt, load_hkt
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_points
from tests.test_colour_solve import TINY, _demo_mesh, _setup
from tests.test_kernels import (
    CONFIG,
    assert_extension_member_checked,
    assert_float32_query_paths_match,
    assert_float64_paths_match,
    make_model,
    make_params,
    reference_albedo,
)
from tests.test_per_kernel_sigma import _rewrite_manifest

LINEAR = replace(CONFIG, colour="linear")
HAVE_COMPILED = compiled.available(torch.device("cpu"), torch.float32)


@pytest.fixture(scope="module")
def case(spectra):
    """30 kernels with slopes large enough to move colours by ~0.1-0.5 across a footprint,
    60 points, and the numpy reading."""
    kp = make_params(spectra, 30, seed=2)
    kp["color_slopes"] = np.random.default_rng(8).uniform(-0.8, 0.8, (30, 9))
    face_ids, bary = random_points(spectra, 60, seed=4)
    ref, rho = reference_albedo(spectra, kp, CONFIG, face_ids, bary)
    return kp, face_ids, bary, ref, rho


def test_every_float64_path_matches_the_numpy_reading(spectra, field64, case):
    kp, face_ids, bary, ref, _ = case
    flat = {k: v for k, v in kp.items() if k != "color_slopes"}
    constant = reference_albedo(spectra, flat, CONFIG, face_ids, bary)[0]
    assert np.abs(ref - constant).max() > 0.05, "the slopes must change colours here"
    assert_float64_paths_match(make_model(field64, kp, LINEAR), face_ids, bary, ref)


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("table_path", ["always", "never"])
def test_float32_query_paths_match(case, spectra, field64, fused, table_path, monkeypatch):
    """Candidate tables (the compiled blend's choice mixed in torch, or its torch twin) and
    the per-point path."""
    kp, face_ids, bary, _, _ = case
    assert_float32_query_paths_match(
        spectra, field64, kp, LINEAR, face_ids, bary, fused, table_path, monkeypatch
    )


@pytest.mark.parametrize("table_path", ["always", "never"])
def test_zero_slopes_are_the_constant_set(case, spectra, table_path, monkeypatch):
    """Within float32 round-off: the compiled blend sums a constant set's colours in its own
    order, and a linear-colour set takes that blend's choice and mixes it in torch."""
    kp, face_ids, bary, _, _ = case
    monkeypatch.setattr(kernels_mod, "TABLE_PATH", table_path)
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    zero = {**kp, "color_slopes": np.zeros((30, 9))}
    flat = {k: v for k, v in kp.items() if k != "color_slopes"}
    with torch.no_grad():
        got = make_model(field, zero, LINEAR).albedo(face_ids, bary)
        ref = make_model(field, flat, CONFIG).albedo(face_ids, bary)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-6)


@pytest.mark.parametrize("compiled_path", [True, False])
def test_slope_gradient_against_finite_differences(spectra, compiled_path):
    """The training batch's d albedo / d G_j (autograd through the slope term, on the
    compiled training path in float32 or the torch one in float64) against central
    differences of the no-grad albedo, and the slopes learnt only when linear."""
    if compiled_path and not HAVE_COMPILED:
        pytest.skip("numba is not installed")
    dtype = torch.float32 if compiled_path else torch.float64
    field = SpectralField(spectra, device="cpu", dtype=dtype)
    kp = make_params(spectra, 60, seed=12)
    kp["color_slopes"] = np.random.default_rng(9).uniform(-0.3, 0.3, (60, 9))
    kp["colors"] = np.asarray(kp["colors"]) * 0.3  # away from the clamp
    f, b = random_points(spectra, 400, seed=3)
    weights = torch.randn((400, 3), generator=torch.Generator().manual_seed(6), dtype=dtype)
    model = make_model(field, kp, LINEAR)
    assert model._compiled_training() == compiled_path
    (model.albedo(f, b) * weights).sum().backward()
    grad = model.color_slopes.grad.clone()
    chosen = torch.argsort(grad.abs().flatten(), descending=True)[:5]
    assert float(grad.flatten()[chosen].abs().min()) > 0.01  # a check that can fail
    eps = 1e-2 if compiled_path else 1e-5
    flat = model.color_slopes.data.view(-1)
    for i in chosen.tolist():
        values = []
        for sign in (1, -1):
            with torch.no_grad():
                flat[i] += sign * eps
                values.append(float((model.albedo(f, b) * weights).sum()))
                flat[i] -= sign * eps
        fd = (values[0] - values[1]) / (2 * eps)
        rel = 1e-3 if compiled_path else 1e-6
        assert fd == pytest.approx(float(grad.flatten()[i]), rel=rel, abs=1e-4)
    flat_kp = {k: v for k, v in kp.items() if k != "color_slopes"}
    assert not make_model(field, flat_kp, CONFIG).color_slopes.requires_grad


def test_clones_and_appended_kernels_carry_their_slopes(field64, case):
    kp = case[0]
    model = make_model(field64, kp, LINEAR)
    before = model.color_slopes.clone()
    model.select(torch.tensor([3, 3, 7]))
    assert torch.equal(model.color_slopes, before[[3, 3, 7]])
    rows = {k: np.asarray(v)[:2] for k, v in kp.items() if k != "base_color"}
    model.append(
        rows["face_ids"], rows["bary"], rows["theta"], rows["eta"], rows["threshold"],
        rows["sharpness"], rows["colors"],
    )  # fmt: skip
    assert model.color_slopes.shape == (5, 3, 3) and not model.color_slopes[3:].any()


def test_storage_round_trips_and_versions(field64, case):
    kp = case[0]
    ks = make_model(field64, kp, LINEAR).to_kernelset()
    np.testing.assert_allclose(ks.color_slopes, kp["color_slopes"], rtol=1e-12)
    plain = load_hkt(io.BytesIO(encode_hkt(ks, compact=True)))
    np.testing.assert_allclose(plain.color_slopes, kp["color_slopes"], rtol=5e-4)  # float16
    assert plain.kernel_config.colour == "linear"
    quant = load_hkt(io.BytesIO(encode_hkt(ks, compact=True, quantised=True)))
    order = np.argsort(kp["face_ids"], kind="stable")  # a quantised file sorts by face
    want = kp["color_slopes"][order]
    step = (want.max(axis=0) - want.min(axis=0)) / 255  # 8 bits over each column's range
    assert (np.abs(quant.color_slopes - want) <= step / 2 + 1e-9).all()
    versions = {}
    for quantised in (False, True):
        with zipfile.ZipFile(io.BytesIO(encode_hkt(ks, True, quantised))) as zf:
            versions[quantised] = json.loads(zf.read("manifest.json"))["version"]
    assert versions == {False: 9, True: 10}
    # with both other extensions: every member comes back, in either layout
    rng = np.random.default_rng(1)
    kp_all = {**kp, "priority": rng.uniform(-3, 3, 30), "sigma_ratio": rng.uniform(0.5, 2, 30)}
    config = replace(LINEAR, blend="layered", sigma="per_kernel")
    every = make_model(field64, kp_all, config).to_kernelset()
    for quantised in (False, True):
        back = load_hkt(io.BytesIO(encode_hkt(every, True, quantised)))
        assert back.kernel_config == config
        assert back.priority is not None and back.sigma_ratio is not None
        assert back.color_slopes.shape == (30, 9)
    # a §4-5 set keeps its manifest: no ``colour`` key, version 1
    flat = {k: v for k, v in kp.items() if k != "color_slopes"}
    with zipfile.ZipFile(io.BytesIO(encode_hkt(make_model(field64, flat).to_kernelset(), True))) as zf:  # fmt: skip
        manifest = json.loads(zf.read("manifest.json"))
    assert manifest["version"] == 1 and "colour" not in manifest


def test_a_loaded_set_evaluates_as_written(spectra, case):
    kp, face_ids, bary, _, _ = case
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    model = make_model(field, kp, LINEAR)
    payload = encode_hkt(model.to_kernelset(), compact=False)
    back = kernels_mod.HeatKernelModel.from_kernelset(load_hkt(io.BytesIO(payload)), field)
    with torch.no_grad():
        np.testing.assert_allclose(
            back.albedo(face_ids, bary).numpy(), model.albedo(face_ids, bary).numpy(), atol=1e-6
        )


def test_storage_refuses_what_its_version_cannot_hold(field64, case):
    kp = case[0]
    ks = make_model(field64, kp, LINEAR).to_kernelset()
    assert_extension_member_checked(ks, "color_slopes", "a linear-colour set")
    with pytest.raises(KernelSetError, match="color_slopes"):
        encode_hkt(replace(ks, color_slopes=np.zeros((len(ks), 3))), compact=True)
    with pytest.raises(KernelSetError, match="out of range"):
        encode_hkt(replace(ks, color_slopes=np.full((len(ks), 9), 2 * SLOPE_RANGE[1])), True)
    v9 = encode_hkt(ks, compact=True)
    with pytest.raises(KernelSetError, match="version-9 file cannot hold 'constant' colours"):
        load_hkt(io.BytesIO(_rewrite_manifest(v9, colour=None)))
    flat = {k: v for k, v in kp.items() if k != "color_slopes"}
    v1 = encode_hkt(make_model(field64, flat).to_kernelset(), compact=True)
    with pytest.raises(KernelSetError, match="version-1 file cannot hold 'linear' colours"):
        load_hkt(io.BytesIO(_rewrite_manifest(v1, colour="linear")))
    with pytest.raises(KernelSetError, match="cannot hold 'quadratic' colours"):
        load_hkt(io.BytesIO(_rewrite_manifest(v9, colour="quadratic")))


def test_design_matrix_with_slopes_reproduces_the_model_albedo():
    mesh, _, model = _setup()
    slopes = np.random.default_rng(3).uniform(-0.5, 0.5, (len(model), 3, 3))
    model.set_color_slopes(slopes)
    f, b = sample_surface(mesh.vertices, mesh.faces, 500, np.random.default_rng(0))
    idx, w = blend_weights(model, f, b)
    a = design_matrix(idx, w, len(model), slope_offsets(model, f, b, idx))
    x = np.concatenate(
        [model.base_color.detach().numpy()[None], model.colors.detach().numpy()]
        + [slopes[:, :, d] / SLOPE_COLUMN_SCALE for d in range(3)]
    )
    with torch.no_grad():
        ref = model.albedo(torch.as_tensor(f), torch.as_tensor(b)).numpy()
    np.testing.assert_allclose(np.clip(a @ x, 0, 1), ref, atol=1e-10)


def test_linear_solve_matches_a_dense_damped_solve_and_beats_the_constant_one():
    """The joint solve of colours and slopes at the product's damping equals the dense
    solution of the same damped problem (``[A; damp I] dx = [r; 0]`` over the rows the clamp
    leaves, unique where the undamped one is not: a slope along a face's normal is nearly free
    on a small curved patch), wherever no range binds; and on the same points it leaves a
    smaller residual than the constant solve, whose unknowns are a subset of its own."""
    mesh, _, model = _setup()
    rng = np.random.default_rng(11)
    state = rng.bit_generator.state
    f, b = sample_surface(mesh.vertices, mesh.faces, 4000, rng)
    target = np.asarray(texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, f, b)))
    idx, w = blend_weights(model, f, b)
    a = design_matrix(idx, w, len(model), slope_offsets(model, f, b, idx)).toarray()
    n, damp = len(model), 0.3
    x0 = np.zeros((a.shape[1], 3))
    x0[0] = model.base_color.detach().numpy()
    x0[1 : 1 + n] = model.colors.detach().numpy()
    pred = a @ x0
    dense = x0.copy()
    for c in range(3):
        done = ((pred[:, c] <= 0) & (target[:, c] <= 0)) | ((pred[:, c] >= 1) & (target[:, c] >= 1))
        rows = a[~done]
        lhs = np.vstack([rows, damp * np.eye(a.shape[1])])
        rhs = np.concatenate([target[~done, c] - rows @ x0[:, c], np.zeros(a.shape[1])])
        dense[:, c] += np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    _, _, constant_model = _setup()
    rng.bit_generator.state = state
    constant = solve_colours(constant_model, mesh, 4000, rng, damp=damp, passes=1, tol=1e-12)
    rng.bit_generator.state = state  # the same points again
    out = solve_colours(model, mesh, 4000, rng, damp=damp, passes=1, tol=1e-12, linear=True)
    assert model.linear_colour and model.config.colour == "linear"
    slopes = model.color_slopes.detach().numpy()
    x = np.concatenate(
        [model.base_color.detach().numpy()[None], model.colors.detach().numpy()]
        + [slopes[:, :, d] / SLOPE_COLUMN_SCALE for d in range(3)]
    )
    bound = np.r_[1.0, np.ones(n), np.full(3 * n, SLOPE_RANGE[1] / SLOPE_COLUMN_SCALE)]
    inside = np.abs(dense) < bound[:, None]
    assert inside.mean() > 0.9, "the check must cover most unknowns"
    np.testing.assert_allclose(x[inside], dense[inside], atol=1e-6)
    assert out["rmse_after"] < constant["rmse_after"] < constant["rmse_before"]


def test_slopes_trained_from_their_start_follow_density_control():
    """The fit is a linear-colour one from the first step (flat slopes), the slopes learn
    from their start, clones and split children carry them, and no colour solve ignores them
    after; a start at the end (nothing to train) is refused."""
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.spectra.grid import compute_spectra

    mesh = _demo_mesh()
    spectra = compute_spectra(mesh, TINY)
    base = dict(kernels=80, steps=40, points_per_step=256, seed=5, slope_start=0.25)
    assert fit_params_from({"colour": "linear"}).slope_start == 0.4  # the measured start
    params = fit_params_from({"preset": "default", **base, "colour": "linear"})
    fit = fit_uv(mesh, spectra, params, eval_points=3000)
    ks = fit.kernelset
    assert ks.kernel_config.colour == "linear" and len(ks) != 80  # density control ran
    assert (np.abs(ks.color_slopes).max(axis=1) > 0).mean() > 0.5
    assert "colour_solve" not in fit.metrics  # the default preset's solve reads no slopes
    with pytest.raises(ValueError, match="slope_start"):
        fit_uv(mesh, spectra, replace(params, slope_start=1.0), eval_points=3000)


def test_a_multiview_fit_refuses_linear_colours():
    from hktex_engine.fitting.multiview import fit_multiview

    params = FitParams(kernel=LINEAR)
    with pytest.raises(ValueError, match="linear colours are fitted against a UV texture"):
        fit_multiview(None, None, None, params)
