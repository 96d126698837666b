"""Discrete Laplace-Beltrami operators on a triangle mesh (ALGORITHM.md section 1).

Isotropic cotangent stiffness, lumped mass, the per-face reference tangent field and the
anisotropic LBO (ALBO) for any ``(theta, eta)``. Everything is vectorised over faces.

The ALBO is written by hand: libigl offers only the isotropic ``cotmatrix``. Its assembly
splits into a geometric part computed once per mesh (:class:`AlboAssembler`) and a cheap
per-``(theta, eta)`` part, because the spectral grid needs 49 operators of the same mesh.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp

from hktex_engine.errors import MeshError

_AXES = np.eye(3)


def _check(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise MeshError(f"expected vertices (n,3) and faces (m,3), got {V.shape} and {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise MeshError("face indices out of range")
    return V, F


def _face_geometry(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges opposite each corner (cyclic orientation), unit normals and areas.

    ``edges[f, i] = x[i+2] - x[i+1]`` so the three edges of a face sum to zero and
    ``n x edges[f, i]`` is ``2 A_f`` times the gradient of the hat function of corner ``i``.
    """
    X = V[F]  # (m, 3, 3)
    edges = np.roll(X, -2, axis=1) - np.roll(X, -1, axis=1)
    cross = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    if np.any(double_area <= 1e-300):
        raise MeshError("mesh has zero-area faces; the Laplacian is undefined there")
    normals = cross / double_area[:, None]
    return edges, normals, 0.5 * double_area


def lumped_mass(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Barycentric lumped mass ``M_ii = sum_{f ni i} A_f / 3`` as an (n,) array."""
    V, F = _check(vertices, faces)
    _, _, area = _face_geometry(V, F)
    return np.bincount(F.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(V))


def cotangent_stiffness(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Isotropic cotangent stiffness, positive semi-definite (the negative of igl's cotmatrix).

    ``L_ij = -1/2 (cot a + cot b)`` for the angles opposite edge ``ij``; rows sum to zero.
    Computed from edge dot products: ``e_i . e_j / (4 A) = -1/2 cot(angle at k)``.
    """
    V, F = _check(vertices, faces)
    edges, _, area = _face_geometry(V, F)
    off = np.einsum("fid,fjd->fij", edges, edges) / (4.0 * area)[:, None, None]
    return _assemble(F, off, len(V))


def _assemble(F: np.ndarray, local: np.ndarray, n: int) -> sp.csr_matrix:
    """Sum per-face 3x3 blocks (off-diagonal part used; diagonal = minus row sum)."""
    rows = np.repeat(F, 3, axis=1).ravel()
    cols = np.tile(F, (1, 3)).ravel()
    vals = local.reshape(len(F), 9).copy()
    vals[:, [0, 4, 8]] = 0.0
    K = sp.coo_matrix((vals.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    K = K - sp.diags(np.asarray(K.sum(axis=1)).ravel())
    return K.tocsr()


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    V, F = _check(vertices, faces)
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for c in range(3):  # three scatter-adds, not a loop over faces
        np.add.at(N, F[:, c], cross)
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)


def _smooth_tensors(T: np.ndarray, F: np.ndarray, iterations: int) -> np.ndarray:
    """Average per-vertex 3x3 tensors over the closed 1-ring, ``iterations`` times.

    Directions are sign-free, so they are averaged as ``t t^T``; a vector average of ``t``
    and ``-t`` would cancel.
    """
    n = len(T)
    i = F[:, [0, 1, 2, 1, 2, 0]].ravel()
    j = F[:, [1, 2, 0, 0, 1, 2]].ravel()
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    A.data[:] = 1.0
    A = A + sp.identity(n, format="csr")
    A = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
    flat = T.reshape(n, 9)
    for _ in range(iterations):
        flat = A @ flat
    return flat.reshape(n, 3, 3)


def _faces_from_vertex_tensors(
    T: np.ndarray, F: np.ndarray, normals: np.ndarray, fallback: np.ndarray
) -> np.ndarray:
    """Principal direction of the face's mean corner tensor, projected into the face plane."""
    Tf = T[F].mean(axis=1)
    # Project the tensor into the face plane first so the principal direction is in-plane.
    P = np.eye(3)[None] - normals[:, :, None] * normals[:, None, :]
    Tp = P @ Tf @ P
    _, vecs = np.linalg.eigh(Tp)
    u = vecs[:, :, 2]
    u = u - np.einsum("fd,fd->f", u, normals)[:, None] * normals
    norm = np.linalg.norm(u, axis=1)
    bad = norm < 1e-8
    u[bad] = fallback[bad]
    norm[bad] = np.linalg.norm(u[bad], axis=1)
    return u / norm[:, None]


def reference_tangent_field(
    vertices: np.ndarray,
    faces: np.ndarray,
    mode: Literal["axis_smoothed", "curvature"] = "axis_smoothed",
    iterations: int = 20,
) -> np.ndarray:
    """Per-face unit reference direction ``u_ref`` (m, 3), in the face plane.

    ``axis_smoothed`` (reference default): per vertex the global axis most perpendicular to
    the normal, projected to the tangent plane, smoothed as a tensor over the 1-ring.
    ``curvature``: libigl's maximal principal curvature direction, smoothed the same way.
    """
    V, F = _check(vertices, faces)
    edges, normals, _ = _face_geometry(V, F)
    vn = vertex_normals(V, F)
    if mode == "axis_smoothed":
        axis = np.argmin(np.abs(vn), axis=1)
        t = _AXES[axis]
    elif mode == "curvature":
        import igl

        pd1 = igl.principal_curvature(V, F)[0]
        t = np.asarray(pd1, dtype=np.float64)
    else:
        raise ValueError(f"unknown tangent field mode {mode!r}")
    t = t - np.einsum("vd,vd->v", t, vn)[:, None] * vn
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    T = _smooth_tensors(t[:, :, None] * t[:, None, :], F, iterations)
    return _faces_from_vertex_tensors(T, F, normals, fallback=edges[:, 0])


class AlboAssembler:
    """Builds ALBO stiffness matrices of one mesh for many ``(theta, eta)`` quickly.

    With ``u_theta = cos(theta) u + sin(theta) v`` (``v = n x u``) and ``g_i = n x e_i``,
    ``g_i . u_theta`` and ``g_i . w_theta`` are fixed linear combinations of ``p_i = g_i . u``
    and ``q_i = g_i . v``; so each operator costs a few (m, 3, 3) products and one
    scatter into a precomputed CSR pattern instead of a fresh sparse construction.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, frames: np.ndarray) -> None:
        V, F = _check(vertices, faces)
        frames = np.asarray(frames, dtype=np.float64)
        if frames.shape != F.shape:
            raise ValueError(f"frames must be (m, 3) like faces, got {frames.shape}")
        edges, normals, area = _face_geometry(V, F)
        u = frames - np.einsum("fd,fd->f", frames, normals)[:, None] * normals
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        v = np.cross(normals, u)
        g = np.cross(normals[:, None, :], edges)  # (m, 3, 3): J e_i
        self.p = np.einsum("fid,fd->fi", g, u)
        self.q = np.einsum("fid,fd->fi", g, v)
        self.inv4a = 1.0 / (4.0 * area)
        self.n = len(V)
        self.F = F
        # CSR pattern of the operator and where each face's off-diagonal pair lands in it.
        iu, ju = np.array([0, 0, 1, 1, 2, 2]), np.array([1, 2, 0, 2, 0, 1])
        rows = F[:, iu].ravel()
        cols = F[:, ju].ravel()
        self._pairs = (iu, ju)
        pattern = sp.coo_matrix(
            (
                np.ones(len(rows) + self.n),
                (np.r_[rows, np.arange(self.n)], np.r_[cols, np.arange(self.n)]),
            ),
            shape=(self.n, self.n),
        ).tocsr()
        pattern.sum_duplicates()
        pattern.sort_indices()
        self._indptr, self._indices = pattern.indptr, pattern.indices
        self._slot = self._locate(rows, cols)
        self._diag_slot = self._locate(np.arange(self.n), np.arange(self.n))
        self._rows = rows

    def _locate(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Index into the CSR data array of each (row, col) entry (entries sorted per row)."""
        key_all = np.repeat(np.arange(self.n), np.diff(self._indptr)) * self.n + self._indices
        return np.searchsorted(key_all, rows * self.n + cols)

    def stiffness(self, theta: float, eta: float) -> sp.csr_matrix:
        """ALBO stiffness with ``D = u_t u_t^T + w_t w_t^T / (1 + eta)``, PSD, zero row sums."""
        if eta < 0:
            raise ValueError("anisotropy eta must be >= 0")
        c, s = np.cos(theta), np.sin(theta)
        a = c * self.p + s * self.q  # g_i . u_theta
        b = -s * self.p + c * self.q  # g_i . w_theta, w_theta = n x u_theta
        iu, ju = self._pairs
        off = (a[:, iu] * a[:, ju] + (b[:, iu] * b[:, ju]) / (1.0 + eta)) * self.inv4a[:, None]
        off = off.ravel()
        data = np.bincount(self._slot, weights=off, minlength=len(self._indices))
        data[self._diag_slot] -= np.bincount(self._rows, weights=off, minlength=self.n)
        return sp.csr_matrix(
            (data, self._indices.copy(), self._indptr.copy()), shape=(self.n, self.n)
        )


def albo_stiffness(
    vertices: np.ndarray, faces: np.ndarray, frames: np.ndarray, theta: float, eta: float
) -> sp.csr_matrix:
    """Anisotropic LBO stiffness for one ``(theta, eta)`` (ALGORITHM.md section 1)."""
    return AlboAssembler(vertices, faces, frames).stiffness(theta, eta)
