"""Operators against independent computations (ALGORITHM.md section 1)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import expm_multiply

from hktex_engine.errors import MeshError
from hktex_engine.geometry.operators import (
    AlboAssembler,
    albo_stiffness,
    cotangent_stiffness,
    lumped_mass,
    reference_tangent_field,
)


def _patch(nx: int, ny: int, jitter: float = 0.0, seed: int = 0):
    """A triangulated square [-1, 1]^2 in the z = 0 plane, optionally with jittered interior."""
    x, y = np.meshgrid(np.linspace(-1, 1, nx), np.linspace(-1, 1, ny), indexing="xy")
    V = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    if jitter:
        rng = np.random.default_rng(seed)
        interior = (np.abs(V[:, 0]) < 1) & (np.abs(V[:, 1]) < 1)
        V[interior, :2] += rng.uniform(-jitter, jitter, (interior.sum(), 2)) * 2 / (nx - 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # alternate the diagonal so the mesh has no preferred direction
    flip = ((np.arange(ny - 1)[:, None] + np.arange(nx - 1)[None, :]) % 2).astype(bool)
    t1 = np.where(flip[..., None], np.stack([a, b, d], -1), np.stack([a, b, c], -1))
    t2 = np.where(flip[..., None], np.stack([a, d, c], -1), np.stack([b, d, c], -1))
    F = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])
    return V, F


def _bumpy_sphere(level: int = 2, seed: int = 1):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=level)
    rng = np.random.default_rng(seed)
    V = m.vertices * (1 + 0.1 * rng.standard_normal((len(m.vertices), 1)))
    return V * np.array([1.0, 0.8, 0.6]), np.asarray(m.faces)


def _angle(p, q, r):
    """Angle at p of triangle (p, q, r), by arccos of normalised dot products."""
    u, v = q - p, r - p
    return np.arccos(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v))


def test_cotangent_weights_match_angles_computed_independently():
    V, F = _bumpy_sphere(1)
    n = len(V)
    ref = np.zeros((n, n))
    for f in F:  # deliberately a plain loop: an independent, obviously-correct reference
        for c in range(3):
            i, j, k = f[c], f[(c + 1) % 3], f[(c + 2) % 3]
            w = 0.5 / np.tan(_angle(V[k], V[i], V[j]))  # angle at k, opposite edge ij
            ref[i, j] -= w
            ref[j, i] -= w
            ref[i, i] += w
            ref[j, j] += w
    L = cotangent_stiffness(V, F).toarray()
    np.testing.assert_allclose(L, ref, atol=1e-12)


def test_cotangent_matches_libigl_and_mass_matches_areas():
    import igl

    V, F = _bumpy_sphere(2)
    L = cotangent_stiffness(V, F)
    assert abs(L + igl.cotmatrix(V, F)).max() < 1e-10
    areas = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    M = lumped_mass(V, F)
    assert M.sum() == pytest.approx(areas.sum())
    np.testing.assert_allclose(M[F[0, 0]], areas[np.any(F == F[0, 0], axis=1)].sum() / 3)


@pytest.mark.parametrize("theta,eta", [(0.0, 0.0), (0.7, 1.0), (2.0, 60.0), (np.pi, 200.0)])
def test_albo_symmetric_psd_with_constants_in_null_space(theta, eta):
    V, F = _bumpy_sphere(2)
    L = albo_stiffness(V, F, reference_tangent_field(V, F), theta, eta)
    assert abs(L - L.T).max() < 1e-12
    assert np.abs(L @ np.ones(len(V))).max() < 1e-10
    w = np.linalg.eigvalsh(L.toarray())
    assert w.min() > -1e-10 * w.max()
    assert np.sum(w < 1e-10 * w.max()) == 1  # connected mesh: only constants


def test_albo_reduces_to_cotangent_for_identity_tensor_and_small_eta():
    V, F = _bumpy_sphere(2)
    frames = reference_tangent_field(V, F)
    L = cotangent_stiffness(V, F)
    for theta in (0.0, 1.1, 2.9):
        assert abs(albo_stiffness(V, F, frames, theta, 0.0) - L).max() < 1e-12
        diff = abs(albo_stiffness(V, F, frames, theta, 1e-6) - L).max()
        assert diff < 1e-5 * abs(L).max()
    # and a real anisotropy is really different
    assert abs(albo_stiffness(V, F, frames, 0.3, 5.0) - L).max() > 0.1 * abs(L).max()


def test_albo_matches_direct_fem_integral_with_explicit_tensor():
    """Independent assembly: gradients of hat functions, D built as a 3x3 matrix per face."""
    V, F = _bumpy_sphere(1)
    frames = reference_tangent_field(V, F)
    theta, eta = 0.9, 7.0
    n = len(V)
    ref = np.zeros((n, n))
    for f, u in zip(F, frames, strict=True):
        X = V[f]
        nrm = np.cross(X[1] - X[0], X[2] - X[0])
        area = 0.5 * np.linalg.norm(nrm)
        nrm /= np.linalg.norm(nrm)
        u = u - np.dot(u, nrm) * nrm
        u /= np.linalg.norm(u)
        # Rodrigues rotation of u about the normal by theta
        ut = u * np.cos(theta) + np.cross(nrm, u) * np.sin(theta)
        wt = np.cross(nrm, ut)
        D = np.outer(ut, ut) + np.outer(wt, wt) / (1 + eta)
        # hat-function gradients from the 3x3 linear system of the affine map
        E = np.array([X[1] - X[0], X[2] - X[0], nrm])
        grads = np.linalg.solve(E, np.array([[-1, 1, 0], [-1, 0, 1], [0, 0, 0]], float)).T
        ref[np.ix_(f, f)] += area * grads @ D @ grads.T
    L = albo_stiffness(V, F, frames, theta, eta).toarray()
    np.testing.assert_allclose(L, ref, atol=1e-10 * np.abs(ref).max())


def test_theta_is_periodic_with_period_pi():
    V, F = _bumpy_sphere(1)
    asm = AlboAssembler(V, F, reference_tangent_field(V, F))
    assert abs(asm.stiffness(0.0, 30.0) - asm.stiffness(np.pi, 30.0)).max() < 1e-10


def _second_moments(V, u):
    w = u / u.sum()
    mu = w @ V[:, :2]
    d = V[:, :2] - mu
    return (d * w[:, None]).T @ d


@pytest.mark.parametrize("theta", [0.0, np.pi / 3])
def test_anisotropic_heat_kernel_is_elongated_by_one_plus_eta(theta):
    """Heat from a point spreads with covariance 2 t D: along/across variance = 1 + eta."""
    V, F = _patch(61, 61, jitter=0.2)
    frames = reference_tangent_field(V, F)
    np.testing.assert_allclose(np.abs(frames[:, 0]), 1.0, atol=1e-12)  # flat: axis x
    eta, t = 3.0, 0.01
    L = albo_stiffness(V, F, frames, theta, eta)
    M = lumped_mass(V, F)
    src = np.argmin(np.linalg.norm(V[:, :2], axis=1))
    u0 = np.zeros(len(V))
    u0[src] = 1.0 / M[src]
    u = expm_multiply(-t * sp.diags(1 / M) @ L, u0)
    C = _second_moments(V, u)
    along = np.array([np.cos(theta), np.sin(theta)])
    across = np.array([-np.sin(theta), np.cos(theta)])
    var_along, var_across = along @ C @ along, across @ C @ across
    assert var_along / var_across == pytest.approx(1 + eta, rel=0.1)
    assert var_along == pytest.approx(2 * t, rel=0.15)  # the long axis keeps the isotropic rate
    assert abs(along @ C @ across) < 0.05 * var_along


def test_reference_field_is_unit_tangent_and_sign_free_smooth():
    V, F = _bumpy_sphere(2)
    for mode in ("axis_smoothed", "curvature"):
        u = reference_tangent_field(V, F, mode=mode)
        nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-12)
        assert np.abs(np.einsum("fd,fd->f", u, nrm)).max() < 1e-10


def test_bad_input_raises_mesh_error():
    V, F = _bumpy_sphere(1)
    with pytest.raises(MeshError):
        cotangent_stiffness(V, F + len(V))
    bad = F.copy()
    bad[0] = [0, 0, 1]
    with pytest.raises(MeshError):
        lumped_mass(V, bad)
    with pytest.raises(ValueError):
        albo_stiffness(V, F, reference_tangent_field(V, F), 0.0, -1.0)
