"""Exact colours for fixed footprints: a sparse linear least-squares solve.

For fixed centres and shapes the albedo ``a_0 + Σ_j ρ_j a_j / max(1, Σ_j ρ_j)`` (ALGORITHM.md
§5) is linear in the base colour and the residual colours, so the colours that best fit the
texture at a set of points solve a sparse least-squares problem: one row per point, one column
per kernel (plus the base), ``K_c`` non-zeros a row. Gradient descent approaches that optimum
slowly (the colour learning rate decays every 1000 steps); the solve reaches it at once. The
final clamp to [0, 1] is ignored in the solve (a point whose target lies inside [0, 1] and is
matched is not clamped); the colours are projected to their ranges afterwards.

scipy's LSQR does the solve (a damped solve for the *change* of colours, so kernels that few
points see stay near their fitted values instead of being driven by one sample).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import lsqr

from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
from hktex_engine.kernels.model import HeatKernelModel

#: points per no-grad evaluation chunk while building the design matrix
CHUNK = 4096


@torch.no_grad()
def blend_weights(
    model: HeatKernelModel, face_ids: np.ndarray, bary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's final kernels (P, K_c) and their blend weights ``ρ / max(1, Σρ)``."""
    dev, dt = model.base_color.device, model.base_color.dtype
    idx_parts, w_parts = [], []
    for start in range(0, len(face_ids), CHUNK):
        f = torch.as_tensor(face_ids[start : start + CHUNK], device=dev)
        b = torch.as_tensor(bary[start : start + CHUNK], device=dev, dtype=dt)
        _, aux = model.albedo(f, b, return_aux=True)
        rho = aux["rho"].to(torch.float64)
        w = rho / rho.sum(dim=1, keepdim=True).clamp_min(1.0)
        idx_parts.append(aux["indices"].cpu().numpy())
        w_parts.append(w.cpu().numpy())
    return np.concatenate(idx_parts), np.concatenate(w_parts)


def design_matrix(indices: np.ndarray, weights: np.ndarray, n_kernels: int) -> sp.csr_matrix:
    """Sparse (P, 1 + N): column 0 the base colour (weight 1), column 1 + j kernel j.

    A kernel listed twice for one point (it cannot be, but the sum is the right meaning)
    has its weights added.
    """
    p, k = indices.shape
    rows = np.repeat(np.arange(p), k + 1)
    cols = np.concatenate([np.zeros((p, 1), np.int64), indices.astype(np.int64) + 1], axis=1)
    vals = np.concatenate([np.ones((p, 1)), weights], axis=1)
    m = sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(p, 1 + n_kernels))
    m.sum_duplicates()
    return m


def solve_colours(
    model: HeatKernelModel,
    mesh: Mesh,
    n_points: int,
    rng: np.random.Generator,
    damp: float = 1e-3,
) -> dict:
    """Replace the model's colours by the least-squares optimum for its footprints.

    ``n_points`` area-uniform points (fresh draws from ``rng``) with the texture as target.
    Returns the fit residual before and after (RMSE on those points) and the LSQR iterations.
    """
    face_ids, bary = sample_surface(mesh.vertices, mesh.faces, int(n_points), rng)
    target = np.asarray(texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, face_ids, bary)))
    idx, w = blend_weights(model, face_ids, bary)
    a = design_matrix(idx, w, len(model))
    current = np.concatenate(
        [
            model.base_color.detach().cpu().numpy()[None, :].astype(np.float64),
            model.colors.detach().cpu().numpy().astype(np.float64),
        ]
    )
    residual = target - a @ current
    delta = np.empty_like(current)
    iters = []
    for c in range(3):
        sol = lsqr(a, residual[:, c], damp=damp, atol=1e-8, btol=1e-8, iter_lim=2000)
        delta[:, c] = sol[0]
        iters.append(int(sol[2]))
    solved = current + delta
    solved[0] = np.clip(solved[0], 0.0, 1.0)
    solved[1:] = np.clip(solved[1:], -1.0, 1.0)
    with torch.no_grad():
        model.base_color.copy_(torch.as_tensor(solved[0], dtype=model.base_color.dtype))
        model.colors.copy_(torch.as_tensor(solved[1:], dtype=model.colors.dtype))
    after = target - np.clip(a @ solved, 0.0, 1.0)
    return {
        "points": int(n_points),
        "rmse_before": float(np.sqrt(np.mean(residual**2))),
        "rmse_after": float(np.sqrt(np.mean(after**2))),
        "lsqr_iterations": iters,
    }
