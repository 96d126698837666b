"""Fidelity diagnostics (evaluation/diagnostics.py) against independent computations."""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.evaluation.diagnostics import (
    edge_flat_split,
    edge_widths,
    saturation,
    texel_size,
    truncation,
)
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
from tests.test_colour_solve import _setup


def test_edge_width_is_the_inverse_finite_difference_slope():
    mesh, spectra, model = _setup(60)
    rng = np.random.default_rng(4)
    f, b = sample_surface(mesh.vertices, mesh.faces, 400, rng)
    b = 0.8 * b + 0.2 / 3  # away from edges, so a small step stays in the face
    w = edge_widths(model, f, b)
    ok = np.nonzero(np.isfinite(w))[0][:10]
    assert len(ok) >= 3
    with torch.no_grad():
        _, aux = model.albedo(torch.as_tensor(f), torch.as_tensor(b), return_aux=True)
    rho, kid = aux["rho"], aux["indices"]
    pick = (rho - 0.5).abs().argmin(dim=1, keepdim=True)
    v = np.asarray(mesh.vertices)
    for p in ok:
        tri = v[mesh.faces[f[p]]]
        e1 = tri[1] - tri[0]
        e1 /= np.linalg.norm(e1)
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        e2 = np.cross(n / np.linalg.norm(n), e1)
        m = np.stack([tri[1] - tri[0], tri[2] - tri[0]], axis=1)  # x = x0 + m @ (b1, b2)
        slopes = []
        for e in (e1, e2):
            d12 = np.linalg.lstsq(m, 1e-5 * e, rcond=None)[0]
            db = np.array([-d12.sum(), d12[0], d12[1]])
            vals = []
            for sign in (1, -1):
                bb = torch.as_tensor((b[p] + sign * db)[None])
                with torch.no_grad():
                    r, _ = model.responses(
                        torch.as_tensor(f[p : p + 1]), bb, kid[p : p + 1].gather(1, pick[p : p + 1])
                    )
                vals.append(float(r))
            slopes.append((vals[0] - vals[1]) / 2e-5)
        np.testing.assert_allclose(w[p], 1.0 / np.hypot(*slopes), rtol=1e-3)


def test_saturation_counts_and_truncation_formula():
    mesh, spectra, model = _setup(60)
    f, b = sample_surface(mesh.vertices, mesh.faces, 200, np.random.default_rng(1))
    out = saturation(model, f, b)
    with torch.no_grad():
        rho, _ = model.responses(torch.as_tensor(f), torch.as_tensor(b), None)
    assert np.isclose(out["saturated_mean"], float((rho >= 1).sum(dim=1).double().mean()))
    t = 0.01
    assert np.isclose(truncation(spectra, t), np.exp(-t * np.asarray(spectra.evals)[..., -1].min()))


def test_edge_flat_split_adds_up_and_texel_size_on_a_known_layout():
    mesh, _, model = _setup(60)
    f, b = sample_surface(mesh.vertices, mesh.faces, 3000, np.random.default_rng(2))
    target = np.asarray(texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, f, b)))
    pred = np.clip(target + np.random.default_rng(3).normal(0, 0.05, target.shape), 0, 1)
    out = edge_flat_split(mesh, pred, target, f, b)
    assert 0 <= out["edge_error_share"] <= 1 and 0 <= out["edge_fraction"] <= 1
    # uniform noise: the error share of the edges is about their share of the points
    assert abs(out["edge_error_share"] - out["edge_fraction"]) < 0.05


def test_texel_size_on_a_flat_square():
    """A square of side 2 (the normalised frame) mapped onto [0, 1]^2 of a 64^2 texture:
    one texel is 2 / 64 long on the surface."""
    from hktex_engine.evaluation.synthetic import grid_patch
    from hktex_engine.geometry.mesh import mesh_from_arrays

    v, faces = grid_patch(9, 9, size=2.0)
    xy = v[:, :2] - v[:, :2].min(axis=0)
    uv = (xy / xy.max())[faces]
    mesh = mesh_from_arrays(v, faces, corner_uvs=uv, texture=np.zeros((64, 64, 3), np.float32))
    assert np.isclose(texel_size(mesh), 2.0 / 64)
