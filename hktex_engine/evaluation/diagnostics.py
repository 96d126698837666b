"""Where a fitted kernel set loses fidelity: measurements, not scores.

Three questions the fidelity work asks of every configuration (docs/fitting.md):

- *Is the kernel converged?* ``truncation``: ``exp(-t λ_K)`` at the grid's smallest last
  eigenvalue. Near 1 the truncated heat kernel rings and its peak leaves the centre.
- *Do responses saturate?* ``saturation``: how many candidates reach ``r ≥ 1`` (so ρ = 1
  exactly, a plateau no threshold can shrink) at a point; more than ``K_c`` makes the tie
  rule of ALGORITHM.md §5 decide the colour.
- *Edges or flats?* ``edge_flat_split``: the squared error split between points on texture
  edges and the rest, with a PSNR for each part.
"""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.evaluation.metrics import psnr
from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.sampling import texture_gradient_energy, texture_lookup, uv_at

#: Texture-gradient magnitude (central differences, summed over RGB) above which a texel is
#: "edge": a step of 0.1 in one channel across two texels. Smooth ramps stay far below it.
EDGE_GRADIENT = 0.05
#: points per brute-force chunk in ``saturation`` (P x N responses in memory)
SATURATION_CHUNK = 64


def truncation(spectra, diffusion_time: float) -> float:
    """``exp(-t λ_K)`` at the grid's smallest last eigenvalue: the weight of the first mode the
    spectra leave out (1 % needs ``t ≈ 4.6 / λ_K``)."""
    last = np.asarray(spectra.evals)[..., -1]
    return float(np.exp(-diffusion_time * float(np.min(last))))


@torch.no_grad()
def saturation(model, face_ids: np.ndarray, bary: np.ndarray) -> dict:
    """Saturated candidates (ρ = 1, i.e. ``r ≥ 1``) over *all* kernels at the given points.

    Brute force (every kernel a candidate), so the count does not depend on the candidate
    search; meant for a few thousand points.
    """
    dev, dt = model.base_color.device, model.base_color.dtype
    k_c = int(model.config.k_blend)
    counts, active = [], []
    for start in range(0, len(face_ids), SATURATION_CHUNK):
        f = torch.as_tensor(face_ids[start : start + SATURATION_CHUNK], device=dev)
        b = torch.as_tensor(bary[start : start + SATURATION_CHUNK], device=dev, dtype=dt)
        rho, _ = model.responses(f, b, None)
        counts.append((rho >= 1.0).sum(dim=1).cpu().numpy())
        active.append((rho > 0).sum(dim=1).cpu().numpy())
    sat, act = np.concatenate(counts), np.concatenate(active)
    return {
        "points": int(len(sat)),
        "saturated_mean": float(sat.mean()),
        "saturated_max": int(sat.max()) if len(sat) else 0,
        "points_over_k_blend": float(np.mean(sat > k_c)),
        "saturated_pair_fraction": float(sat.sum() / max(1, act.sum())),
        "active_mean": float(act.mean()),
    }


def edge_mask(mesh: Mesh, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """True where the texture's gradient magnitude at the point exceeds ``EDGE_GRADIENT``."""
    energy = texture_gradient_energy(mesh.texture)[..., None]
    uv = uv_at(mesh.corner_uvs, face_ids, bary)
    return np.sqrt(np.clip(texture_lookup(energy, uv)[:, 0], 0.0, None)) > EDGE_GRADIENT


def edge_flat_split(
    mesh: Mesh, pred: np.ndarray, target: np.ndarray, face_ids: np.ndarray, bary: np.ndarray
) -> dict:
    """The share of squared error on edge points, and PSNR on edges and on flats."""
    edge = edge_mask(mesh, face_ids, bary)
    sq = ((np.asarray(pred) - np.asarray(target)) ** 2).sum(axis=1)
    total = float(sq.sum()) or 1.0
    out = {
        "edge_fraction": float(edge.mean()),
        "edge_error_share": float(sq[edge].sum() / total),
        "psnr_all": psnr(pred, target),
    }
    out["psnr_edge"] = psnr(pred[edge], target[edge]) if edge.any() else None
    out["psnr_flat"] = psnr(pred[~edge], target[~edge]) if (~edge).any() else None
    return out


def edge_widths(model, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Surface width ``1 / |∇ρ|`` of kernel edges at the given points (normalised units).

    At each point the final kernel whose ρ is nearest 0.5 is taken (its level set runs
    there); points where no final kernel lies in (0.05, 0.95) give NaN. ``∇ρ`` is the
    tangent gradient through the barycentrics (autograd), so this measures the footprint's
    edge as the model draws it, soft step and heat kernel together.
    """
    from hktex_engine.kernels.model import barycentric_gradients

    dev, dt = model.base_color.device, model.base_color.dtype
    f = torch.as_tensor(face_ids, device=dev)
    with torch.no_grad():
        _, aux = model.albedo(f, torch.as_tensor(bary, device=dev, dtype=dt), return_aux=True)
    rho, kid = aux["rho"], aux["indices"]
    pick = (rho - 0.5).abs().argmin(dim=1, keepdim=True)
    inside = ((rho.gather(1, pick) > 0.05) & (rho.gather(1, pick) < 0.95)).squeeze(1)
    b = torch.as_tensor(bary, device=dev, dtype=dt).clone().requires_grad_(True)
    r, _ = model.responses(f, b, kid.gather(1, pick))
    (g_b,) = torch.autograd.grad(r.sum(), b)
    vertices = torch.as_tensor(np.asarray(model.field.spectra.vertices), device=dev, dtype=dt)
    faces = torch.as_tensor(np.asarray(model.field.spectra.faces), device=dev)
    grads = barycentric_gradients(vertices, faces)[f]  # (P, 3, 3)
    g = (g_b.detach()[:, :, None] * grads).sum(dim=1).norm(dim=1)
    width = torch.where(inside & (g > 0), 1.0 / g.clamp_min(1e-12), torch.nan)
    return width.cpu().numpy()


def texel_size(mesh: Mesh) -> float:
    """Median surface length of one texel (normalised units): how wide a sharp texture edge
    is on the surface, to set beside ``edge_widths``."""
    faces = np.asarray(mesh.faces)
    p = np.asarray(mesh.vertices)[faces]
    a3 = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    uv = np.asarray(mesh.corner_uvs)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    auv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    h, w = np.asarray(mesh.texture).shape[:2]
    ok = auv > 0
    return float(np.median(np.sqrt(a3[ok] / (auv[ok] * h * w))))
