"""Surface sampling and texture lookup: the supervision side of UV fitting and evaluation.

A surface point is ``(face id, barycentrics)``; every other module speaks in those, so they
survive normalisation and stay exact on the mesh. Texture conventions are the OBJ ones used by
EVALUATION.md: ``v = 0`` is the bottom image row, texel centres at ``(i + 0.5) / W``, bilinear
filtering, coordinates outside [0, 1] wrap around.
"""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.errors import QueryError

Rng = np.random.Generator | int | None


def _rng(rng: Rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas (m,)."""
    p = np.asarray(vertices, dtype=np.float64)[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, rng: Rng = None
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly distributed by area: face ids (n,) int64, barycentrics (n, 3).

    Faces are drawn by inverse-CDF on cumulative areas; inside a face the square-root warp
    (Osada et al. 2002) makes the density uniform.
    """
    if n < 0:
        raise ValueError("n must be >= 0")
    gen = _rng(rng)
    cdf = np.cumsum(face_areas(vertices, faces))
    face_ids = np.searchsorted(cdf, gen.random(n) * cdf[-1], side="right")
    face_ids = np.minimum(face_ids, len(faces) - 1).astype(np.int64)
    r1 = np.sqrt(gen.random(n))
    r2 = gen.random(n)
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    return face_ids, bary


def points_from_barycentric(
    vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """3-D positions (P, 3) of surface points."""
    corners = np.asarray(vertices)[np.asarray(faces)[face_ids]]  # (P, 3, 3)
    return np.einsum("pc,pcd->pd", bary, corners)


def uv_at(corner_uvs: np.ndarray, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Texture coordinates (P, 2) interpolated from per-corner UVs (seams stay exact)."""
    return np.einsum("pc,pcd->pd", bary, np.asarray(corner_uvs)[face_ids])


def texture_lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup (P, C) of an (H, W, C) image at OBJ-convention UVs, wrapping.

    Written by hand: neither scipy's ``map_coordinates`` nor torch's ``grid_sample`` offers the
    OBJ v-flip together with periodic wrap on a texel-centred grid in one call, and both would
    need a copy of the (possibly 4096^2) texture.
    """
    tex = np.asarray(texture)
    uv = np.asarray(uv, dtype=np.float64)
    h, w = tex.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = tex[y0, x0] * (1.0 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1.0 - fx) + tex[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


def closest_surface_point(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest surface point to each query: face ids (P,), barycentrics (P, 3) in the triangle.

    libigl's AABB tree finds the closest point; its barycentrics are clipped to be
    non-negative and renormalised so round-off never puts a point outside its face.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise QueryError(f"points must have shape (P, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise QueryError("points contain NaN or infinity")
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    import igl  # here, not at the top: ~0.1 s that queries by face ids need not pay

    _, face_ids, closest = igl.point_mesh_squared_distance(pts, v, f)
    face_ids = np.asarray(face_ids, dtype=np.int64).reshape(-1)
    tri = v[f[face_ids]]
    bary = igl.barycentric_coordinates(
        np.ascontiguousarray(closest),
        np.ascontiguousarray(tri[:, 0]),
        np.ascontiguousarray(tri[:, 1]),
        np.ascontiguousarray(tri[:, 2]),
    )
    bary = np.clip(np.asarray(bary, dtype=np.float64), 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return face_ids, bary


def farthest_point_sampling(
    points: np.ndarray | torch.Tensor,
    k: int,
    rng: Rng = None,
    device: str | torch.device | None = None,
) -> np.ndarray:
    """Indices (k,) of a greedy farthest-point subset of ``points`` (P, D), seeded at random.

    The greedy order is inherently sequential over the k picks; each pick is one vectorised
    update of all P distances. On the CPU that update runs in numpy on a (D, P) copy
    (measured 0.1 ms per pick for P = 100k against 8.7 ms for the same torch code on 2 busy
    cores); on CUDA (``device`` or a CUDA tensor) it runs in torch.
    """
    on_cuda = (isinstance(points, torch.Tensor) and points.is_cuda) or (
        device is not None and torch.device(device).type == "cuda"
    )
    n_points = len(points)
    if np.ndim(points) != 2 or n_points == 0:
        raise ValueError(f"points must have shape (P, D) with P > 0, got {tuple(np.shape(points))}")
    if not 0 < k <= n_points:
        raise ValueError(f"k must be in 1..{n_points}, got {k}")
    first = int(_rng(rng).integers(n_points))
    if on_cuda:
        return _fps_torch(torch.as_tensor(points, device=device), k, first)
    pts = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points
    cols = np.ascontiguousarray(np.asarray(pts, dtype=np.float64).T)
    chosen = np.empty(k, dtype=np.int64)
    dist = np.full(n_points, np.inf)
    idx = first
    for i in range(k):
        chosen[i] = idx
        diff = cols - cols[:, idx : idx + 1]
        np.minimum(dist, np.einsum("dp,dp->p", diff, diff), out=dist)
        idx = int(np.argmax(dist))
    return chosen


def _fps_torch(pts: torch.Tensor, k: int, first: int) -> np.ndarray:
    pts = pts.to(torch.float32) if not pts.is_floating_point() else pts
    chosen = torch.empty(k, dtype=torch.long, device=pts.device)
    dist = torch.full((len(pts),), float("inf"), dtype=pts.dtype, device=pts.device)
    idx = torch.tensor(first, device=pts.device)
    for i in range(k):
        chosen[i] = idx
        dist = torch.minimum(dist, ((pts - pts[idx]) ** 2).sum(dim=1))
        idx = torch.argmax(dist)
    return chosen.cpu().numpy()


def texture_gradient_energy(texture: np.ndarray) -> np.ndarray:
    """Squared gradient magnitude of the texture (H, W), summed over channels.

    Central differences with wrap-around, matching the lookup's wrap convention.
    """
    tex = np.asarray(texture, dtype=np.float32)
    gx = 0.5 * (np.roll(tex, -1, axis=1) - np.roll(tex, 1, axis=1))
    gy = 0.5 * (np.roll(tex, -1, axis=0) - np.roll(tex, 1, axis=0))
    return (gx**2 + gy**2).sum(axis=2)
