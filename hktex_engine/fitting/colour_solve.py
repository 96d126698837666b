"""Exact colours for fixed footprints: a sparse linear least-squares solve.

For fixed centres and shapes the albedo ``a_0 + Σ_j ρ_j a_j / max(1, Σ_j ρ_j)`` (ALGORITHM.md
§5; the layered blend of ``kernels.blending`` likewise, with priority-weighted shares) is linear in the base colour and the residual colours, so the colours that best fit the
texture at a set of points solve a sparse least-squares problem: one row per point, one column
per kernel (plus the base), ``K_c`` non-zeros a row, except where the final clamp to [0, 1]
is active (handled as an active set, :func:`solve_colours`). Gradient descent approaches that
optimum slowly (the colour learning rate decays every 1000 steps); the solve reaches it at
once. The colours are projected to their ranges afterwards.

Measured first without the clamp (a plain solve of the linear model, damp 1e-3): on spot
fits it *lost* 1.9 and 8.4 dB on fresh points while its own points improved, because fitted
kernels lean on the clamp (residuals near ±1 that saturate to white or black).

scipy's LSQR does the solve (a damped solve for the *change* of colours, so kernels that few
points see stay near their fitted values instead of being driven by one sample).

Linear colours (``KernelConfig.colour = "linear"``): kernel ``j``'s colour at ``y`` is
``a_j + G_j (x(y) - x(c_j))``, still linear in the unknowns, so the same solve finds the
colours and the slopes together (``linear=True``): three more columns a kernel, its blend
weight times the point's offset from the centre along each axis of the normalised frame. It
is a measurement, not a fit step (``benchmarks/rescore.py --solve linear``; docs/fitting.md,
eighteenth pass): on a §4-5 default set of the smooth held-out asset it gained +0.6 dB on
400,000 fresh points (flats +3.2, the eye's edge -0.9), on blub's -0.2, and after slopes were
trained it lost on validation points on both; training the slopes is what the fit does.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import lsqr

from hktex_engine.config import SLOPE_RANGE
from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
from hktex_engine.kernels import blending
from hktex_engine.kernels.model import COLOR_RANGE, HeatKernelModel

#: points per no-grad evaluation chunk while building the design matrix
CHUNK = 4096
#: LSQR damping of the colour *change*: a kernel whose column norm^2 (sum of its squared
#: blend weights over the points) is well below DAMP^2 stays near its fitted colour
DAMP = 0.3
PASSES = 2
ITER_LIMIT = 300
#: LSQR's stopping tolerances (its own defaults): ample for a fit's colours, whose errors are
#: far above 1e-6; a test comparing against a dense solve asks for tighter ones
TOL = 1e-6
#: Offsets from a centre enter the slope columns times this: footprints are ~0.02-0.1 of the
#: normalised frame across, so scaled offsets are O(1) and :data:`DAMP` holds a slope's
#: change of colour across a footprint back about as much as a colour's change.
SLOPE_COLUMN_SCALE = 20.0


@torch.no_grad()
def blend_weights(
    model: HeatKernelModel, face_ids: np.ndarray, bary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's final kernels (P, K_c) and their blend weights (``ρ / max(1, Σρ)`` for
    the paper's blend, ``kernels.blending.weights`` for either)."""
    dev, dt = model.base_color.device, model.base_color.dtype
    idx_parts, w_parts = [], []
    for start in range(0, len(face_ids), CHUNK):
        f = torch.as_tensor(face_ids[start : start + CHUNK], device=dev)
        b = torch.as_tensor(bary[start : start + CHUNK], device=dev, dtype=dt)
        _, aux = model.albedo(f, b, return_aux=True)
        rho, kid = aux["rho"].to(torch.float64), aux["indices"]
        prio = model.priority_of(kid)
        w = blending.weights(rho, None if prio is None else prio.detach().to(torch.float64))
        idx_parts.append(aux["indices"].cpu().numpy())
        w_parts.append(w.cpu().numpy())
    return np.concatenate(idx_parts), np.concatenate(w_parts)


def design_matrix(
    indices: np.ndarray,
    weights: np.ndarray,
    n_kernels: int,
    offsets: np.ndarray | None = None,
) -> sp.csr_matrix:
    """Sparse (P, 1 + N): column 0 the base colour (weight 1), column 1 + j kernel j.

    With ``offsets`` (P, K_c, 3; each point's position minus its chosen kernels' centres,
    scaled), (P, 1 + 4N): then columns ``1 + (1 + d) N + j`` hold kernel j's weight times the
    offset along axis ``d``, the columns of its slope. A kernel listed twice for one point (it
    cannot be, but the sum is the right meaning) has its weights added.
    """
    p, k = indices.shape
    idx = indices.astype(np.int64)
    blocks = [weights]
    if offsets is not None:
        blocks += [weights * offsets[..., d] for d in range(3)]
    cols = [np.zeros((p, 1), np.int64)] + [idx + 1 + b * n_kernels for b in range(len(blocks))]
    vals = np.concatenate([np.ones((p, 1)), *blocks], axis=1)
    rows = np.repeat(np.arange(p), vals.shape[1])
    shape = (p, 1 + len(blocks) * n_kernels)
    m = sp.csr_matrix((vals.ravel(), (rows, np.concatenate(cols, axis=1).ravel())), shape=shape)
    m.sum_duplicates()
    return m


def slope_offsets(
    model: HeatKernelModel, face_ids: np.ndarray, bary: np.ndarray, indices: np.ndarray
) -> np.ndarray:
    """Each point's offset from its chosen kernels' centres in the normalised frame (P, K_c,
    3), times :data:`SLOPE_COLUMN_SCALE` (:meth:`HeatKernelModel.centre_offsets`)."""
    dev, dt = model.base_color.device, model.base_color.dtype
    f = torch.as_tensor(face_ids, device=dev)
    b = torch.as_tensor(bary, device=dev, dtype=dt)
    k = torch.as_tensor(indices, device=dev)
    offsets = model.centre_offsets(k, f, b).cpu().numpy().astype(np.float64)
    return offsets * SLOPE_COLUMN_SCALE


def solve_colours(
    model: HeatKernelModel,
    mesh: Mesh,
    n_points: int,
    rng: np.random.Generator,
    damp: float = DAMP,
    passes: int = PASSES,
    tol: float = TOL,
    linear: bool = False,
) -> dict:
    """Replace the model's colours by the least-squares optimum for its footprints.

    ``linear=True`` solves colours and colour slopes together and leaves the model a
    linear-colour set (:meth:`HeatKernelModel.set_color_slopes`), its slopes starting from
    the model's own (zero for a §4-5 set).

    ``n_points`` area-uniform points (fresh draws from ``rng``) with the texture as target.
    The output clamp is part of the model: fits use it (a residual of +1 on a mid-grey base
    paints white), so a row whose prediction is clamped at a bound its target also reaches
    is already right and leaves the system (an active set, re-formed for ``passes`` rounds);
    every other row is linear. Returns the residual before and after (RMSE of the clamped
    prediction on those points) and LSQR's iterations. ``tol`` is LSQR's ``atol`` and
    ``btol``: the solution is as exact as the system's conditioning times ``tol`` allows.
    """
    face_ids, bary = sample_surface(mesh.vertices, mesh.faces, int(n_points), rng)
    target = np.asarray(texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, face_ids, bary)))
    idx, w = blend_weights(model, face_ids, bary)
    n = len(model)
    offsets = slope_offsets(model, face_ids, bary, idx) if linear else None
    a = design_matrix(idx, w, n, offsets)
    parts = [
        model.base_color.detach().cpu().numpy()[None, :].astype(np.float64),
        model.colors.detach().cpu().numpy().astype(np.float64),
    ]
    if linear:  # (N, c, d) -> per axis d an (N, c) block, in slope-column units
        slopes = model.color_slopes.detach().cpu().numpy().astype(np.float64)
        parts += [slopes[:, :, d] / SLOPE_COLUMN_SCALE for d in range(3)]
    x = np.concatenate(parts)
    before = float(np.sqrt(np.mean((target - np.clip(a @ x, 0.0, 1.0)) ** 2)))
    iters = []
    for _ in range(max(1, passes)):
        pred = a @ x
        for c in range(3):
            satisfied = ((pred[:, c] <= 0) & (target[:, c] <= 0)) | (
                (pred[:, c] >= 1) & (target[:, c] >= 1)
            )
            rows = np.nonzero(~satisfied)[0]
            sub = a[rows]
            sol = lsqr(
                sub,
                target[rows, c] - sub @ x[:, c],
                damp=damp,
                iter_lim=ITER_LIMIT,
                atol=tol,
                btol=tol,
            )
            x[:, c] += sol[0]
            iters.append(int(sol[2]))
        x[0] = np.clip(x[0], 0.0, 1.0)
        x[1 : 1 + n] = np.clip(x[1 : 1 + n], *COLOR_RANGE)
        x[1 + n :] = np.clip(x[1 + n :], *(np.asarray(SLOPE_RANGE) / SLOPE_COLUMN_SCALE))
    with torch.no_grad():
        model.base_color.copy_(torch.as_tensor(x[0], dtype=model.base_color.dtype))
        model.colors.copy_(torch.as_tensor(x[1 : 1 + n], dtype=model.colors.dtype))
    if linear:
        g = np.stack([x[1 + (1 + d) * n : 1 + (2 + d) * n] for d in range(3)], axis=2)
        model.set_color_slopes(g * SLOPE_COLUMN_SCALE)
    after = float(np.sqrt(np.mean((target - np.clip(a @ x, 0.0, 1.0)) ** 2)))
    return {
        "points": int(n_points),
        "rmse_before": before,
        "rmse_after": after,
        "lsqr_iterations": iters,
    }
