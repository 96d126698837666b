"""The least-squares colour solve (fitting/colour_solve.py) against independent computations."""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.config import FitParams, SpectralConfig
from hktex_engine.evaluation.synthetic import textured_demo
from hktex_engine.fitting.colour_solve import blend_weights, design_matrix, solve_colours
from hktex_engine.fitting.uv import fit_uv, initial_kernelset
from hktex_engine.geometry.mesh import mesh_from_arrays
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.grid import compute_spectra
from hktex_engine.spectra.interpolation import SpectralField

TINY = SpectralConfig(angles=3, anisotropies=(1.0, 10.0), k=16, k_iso=9)


def _demo_mesh():
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=32)
    return mesh_from_arrays(v, f, corner_uvs=uv, texture=tex)


def _setup(n_kernels: int = 60):
    mesh = _demo_mesh()
    spectra = compute_spectra(mesh, TINY)
    params = FitParams(kernels=n_kernels, seed=3)
    ks = initial_kernelset(mesh, spectra, params, np.random.default_rng(3))
    model = HeatKernelModel.from_kernelset(ks, SpectralField(spectra, dtype=torch.float64))
    return mesh, spectra, model


def test_design_matrix_reproduces_the_model_albedo():
    """A @ [a0; a] equals the model's own (unclamped-range) albedo at the same points."""
    mesh, _, model = _setup()
    f, b = sample_surface(mesh.vertices, mesh.faces, 500, np.random.default_rng(0))
    idx, w = blend_weights(model, f, b)
    a = design_matrix(idx, w, len(model))
    x = np.concatenate([model.base_color.detach().numpy()[None], model.colors.detach().numpy()])
    with torch.no_grad():
        ref = model.albedo(torch.as_tensor(f), torch.as_tensor(b)).numpy()
    np.testing.assert_allclose(np.clip(a @ x, 0, 1), ref, atol=1e-10)


def test_solve_matches_dense_lstsq_and_lowers_the_residual():
    """Undamped LSQR equals numpy's dense least squares on the same system (where the
    clipped ranges are not active), and the fit's residual can only go down. Solved to a
    tight tolerance: at LSQR's default 1e-6 this system (condition number ~400) leaves
    colours ~2e-3 off, which is the stopping rule, not the set-up under test."""
    mesh, _, model = _setup()
    rng = np.random.default_rng(11)
    state = rng.bit_generator.state
    f, b = sample_surface(mesh.vertices, mesh.faces, 3000, rng)
    target = np.asarray(texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, f, b)))
    idx, w = blend_weights(model, f, b)
    a = design_matrix(idx, w, len(model)).toarray()
    dense, *_ = np.linalg.lstsq(a, target, rcond=None)
    rng.bit_generator.state = state  # the solve draws the same points
    out = solve_colours(model, mesh, 3000, rng, damp=0.0, passes=1, tol=1e-10)
    solved = np.concatenate(
        [model.base_color.detach().numpy()[None], model.colors.detach().numpy()]
    )
    inside = np.all((dense[1:] > -1) & (dense[1:] < 1), axis=1)
    np.testing.assert_allclose(solved[1:][inside], dense[1:][inside], atol=1e-6)
    assert out["rmse_after"] < out["rmse_before"]


def test_polish_in_fit_uv_is_recorded_and_helps_on_fresh_points():
    mesh = _demo_mesh()
    spectra = compute_spectra(mesh, TINY)
    base = dict(kernels=200, steps=40, points_per_step=256, seed=5, densify=False)
    plain = fit_uv(mesh, spectra, FitParams(**base), eval_points=4000)
    polished = fit_uv(mesh, spectra, FitParams(**base, polish_colors=True), eval_points=4000)
    assert "colour_solve" in polished.metrics and "colour_solve" not in plain.metrics
    # evaluation points are independent of the solve's points (EVAL_SEED vs the fit's rng);
    # measured 16.51 -> 16.70 dB (2026-12-01): this tiny fit is footprint-bound, as real ones are
    assert polished.metrics["surface_psnr"] > plain.metrics["surface_psnr"]


def test_a_solve_that_loses_on_validation_points_is_undone(monkeypatch):
    """The guard in fit_uv: a solve scoring worse on its validation points than the
    optimiser's colours is reverted (here a stand-in solve that ruins the colours), and the
    fit then equals the unpolished one exactly."""
    from hktex_engine.fitting import uv as uv_mod

    mesh = _demo_mesh()
    spectra = compute_spectra(mesh, TINY)
    base = dict(kernels=200, steps=20, points_per_step=256, seed=5, densify=False)
    plain = fit_uv(mesh, spectra, FitParams(**base), eval_points=3000)

    def ruin(model, mesh_, n_points, rng, **kw):
        with torch.no_grad():
            model.colors.fill_(0.9)
        return {"points": n_points, "rmse_before": 0.0, "rmse_after": 1.0}

    monkeypatch.setattr(uv_mod, "solve_colours", ruin)
    guarded = fit_uv(mesh, spectra, FitParams(**base, polish_colors=True), eval_points=3000)
    solve = guarded.metrics["colour_solve"]
    assert solve["kept"] is False
    assert solve["validation_psnr_after"] < solve["validation_psnr_before"]
    assert guarded.metrics["surface_psnr"] == plain.metrics["surface_psnr"]
    np.testing.assert_array_equal(guarded.kernelset.colors, plain.kernelset.colors)
