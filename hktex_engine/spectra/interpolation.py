"""Differentiable interpolation of the spectral grid (ALGORITHM.md section 2).

A kernel with a continuous angle ``theta`` and anisotropy coordinate ``s = ln(1 + eta)`` uses
the spectrum bilinearly interpolated from the four surrounding grid nodes; a surface point
``(face, barycentrics)`` reads eigenfunctions as the barycentric blend of its three vertices.
Gradients reach ``theta``, ``s`` and the barycentrics; the eigen data are constants.

Why a hand-written autograd function (:class:`_InterpolatedRows`): the eigenfunctions at
``U`` points for per-point grid nodes need the gathered block ``(U, 3 vertices, 4 nodes, K)``.
Plain autograd would keep that block alive until backward (hundreds of MB for the tens of
thousands of kernel centres a fit touches per step); the function below gathers it chunk by
chunk in forward and again in backward, so memory stays bounded by the chunk size.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import numpy as np
import torch

from hktex_engine.spectra.grid import Spectra

#: Rows per chunk when gathering eigenfunction blocks; bounds peak memory of one gather to
#: about ``CHUNK_ROWS * 12 * K * itemsize`` bytes.
CHUNK_ROWS = 4096
#: Bytes :class:`_InterpolatedRows` may keep between forward and backward (the 7 blended
#: vectors per row); above it backward regathers. 10k kernels at K = 256 float32 take 72 MB.
SAVE_BYTES = 512 * 2**20


def resolve_device(device: str | torch.device | None) -> torch.device:
    """CUDA when present and not asked otherwise; the CPU always works."""
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _chunks(n: int, size: int) -> Iterator[slice]:
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def bilinear_nodes(
    grid_theta: torch.Tensor, grid_s: torch.Tensor, theta: torch.Tensor, s: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Four surrounding grid nodes and their bilinear weights for each ``(theta, s)``.

    Returns ``nodes`` (P, 4) long (node ``g = a * S + b``, angle-major, corners ordered
    (a0,b0), (a0,b1), (a1,b0), (a1,b1)) and ``weights`` (P, 4) summing to one. Coordinates
    outside the grid are clamped onto it, so the gradient there is zero (the grid holds no
    information beyond its ends). A one-node axis gets weight 1 on that node.
    """
    a0, ta = _axis_cell(grid_theta, theta)
    b0, tb = _axis_cell(grid_s, s)
    a1 = torch.clamp(a0 + 1, max=grid_theta.shape[0] - 1)
    b1 = torch.clamp(b0 + 1, max=grid_s.shape[0] - 1)
    n_s = grid_s.shape[0]
    nodes = torch.stack([a0 * n_s + b0, a0 * n_s + b1, a1 * n_s + b0, a1 * n_s + b1], dim=-1)
    weights = torch.stack([(1 - ta) * (1 - tb), (1 - ta) * tb, ta * (1 - tb), ta * tb], dim=-1)
    return nodes, weights


def _axis_cell(grid: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell index ``i`` with ``grid[i] <= x <= grid[i+1]`` and the fraction ``t`` in [0, 1]."""
    if grid.shape[0] == 1:
        return torch.zeros_like(x, dtype=torch.long), torch.zeros_like(x)
    xc = torch.clamp(x, min=float(grid[0]), max=float(grid[-1]))
    i = torch.searchsorted(grid, xc.detach().contiguous(), right=True) - 1
    i = torch.clamp(i, 0, grid.shape[0] - 2)
    lo, hi = grid[i], grid[i + 1]
    return i, (xc - lo) / (hi - lo)


class _InterpolatedRows(torch.autograd.Function):
    """``out[u] = sum_v b[u,v] sum_c w[u,c] E[vert[u,v], node[u,c], :]`` with chunked gathers.

    Backward needs, per row, the vertex blends ``P3[u,v] = sum_c w[u,c] E[.., c]`` (for
    d/db) and the node blends ``P4[u,c] = sum_v b[u,v] E[.., c]`` (for d/dw): 7 vectors of K
    instead of the 12 gathered ones. Forward keeps them when they fit in
    :data:`SAVE_BYTES` (one gather per step instead of two: the gather dominates the cost),
    and otherwise regathers per chunk in backward; see module doc.
    """

    @staticmethod
    def forward(ctx, evecs, verts, bary, nodes, weights, out_dtype, rows_all=None):  # type: ignore[override]
        ctx.out_dtype = out_dtype
        n, k = verts.shape[0], evecs.shape[2]
        need_grad = ctx.needs_input_grad[2] or ctx.needs_input_grad[4]
        itemsize = torch.finfo(out_dtype).bits // 8
        # Pre-gathered rows (a caller's cache, see :class:`RowCache`) are never saved: the
        # cache is updated in place between steps.
        keep = need_grad and (rows_all is not None or n * 7 * k * itemsize <= SAVE_BYTES)
        out = torch.empty((n, k), dtype=out_dtype, device=bary.device)
        if keep:
            p3 = torch.empty((n, 3, k), dtype=out_dtype, device=bary.device)
            p4 = torch.empty((n, 4 * k), dtype=out_dtype, device=bary.device)
        for sl in _chunks(n, CHUNK_ROWS):
            if rows_all is None:
                rows = gather_rows(evecs, verts[sl], nodes[sl], out_dtype)  # (c, 3 * 4, K)
            else:
                rows = rows_all[sl]
            b, w = bary[sl].to(out_dtype), weights[sl].to(out_dtype)
            c = rows.shape[0]
            if keep:
                # P3 = sum_c w_c E[v, c] (c, 3, K); P4 = sum_v b_v E[v, c] (c, 4, K); written
                # in place (bmm's out=) since copying them measured as much as computing them.
                w3 = w[:, None, None, :].expand(c, 3, 1, -1).reshape(c * 3, 1, -1)
                torch.bmm(w3, rows.view(c * 3, -1, k), out=p3[sl].view(c * 3, 1, k))
                torch.bmm(b[:, None, :], rows.view(c, 3, -1), out=p4[sl].view(c, 1, -1))
                out[sl] = torch.bmm(b[:, None, :], p3[sl]).squeeze(1)
            else:
                coeff = b[:, :, None] * w[:, None, :]  # (c, 3, 4)
                out[sl] = torch.bmm(coeff.reshape(c, 1, -1), rows).squeeze(1)
        ctx.keep = keep
        if keep:
            ctx.save_for_backward(p3, p4.view(n, 4, k), bary, weights)
        else:
            ctx.save_for_backward(evecs, verts, bary, nodes, weights)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        need_b, need_w = ctx.needs_input_grad[2], ctx.needs_input_grad[4]
        if not (need_b or need_w):
            return None, None, None, None, None, None, None
        if ctx.keep:
            p3, p4, bary, weights = ctx.saved_tensors
            g = grad_out[:, :, None]
            grad_b = torch.bmm(p3, g).squeeze(2).to(bary.dtype) if need_b else None
            grad_w = torch.bmm(p4, g).squeeze(2).to(weights.dtype) if need_w else None
            return None, None, grad_b, None, grad_w, None, None
        evecs, verts, bary, nodes, weights = ctx.saved_tensors
        grad_b = torch.zeros_like(bary) if need_b else None
        grad_w = torch.zeros_like(weights) if need_w else None
        for sl in _chunks(verts.shape[0], CHUNK_ROWS):
            rows = gather_rows(evecs, verts[sl], nodes[sl], ctx.out_dtype)
            t = torch.bmm(rows, grad_out[sl, :, None]).view(-1, 3, weights.shape[1])
            if need_b:
                grad_b[sl] = torch.einsum("uvc,uc->uv", t, weights[sl].to(t.dtype))
            if need_w:
                grad_w[sl] = torch.einsum("uvc,uv->uc", t, bary[sl].to(t.dtype))
        return None, None, grad_b, None, grad_w, None, None


class RowCache:
    """The gathered ``(N, 3 * 4, K)`` eigenvector rows of N points, kept between calls.

    A point's 12 rows depend only on its face's vertices and its 4 grid nodes, so between
    training steps only kernels that changed face or grid cell need a new gather; the rest
    reuse the block (the per-step gather of every centre's rows was a quarter of a training
    step, see docs/kernels.md "Performance"). The key comparison is the whole invalidation
    rule: equal keys mean equal rows. ``max_bytes`` caps the block; beyond it callers gather.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._key: torch.Tensor | None = None
        self._rows: torch.Tensor | None = None
        self.regathered = 0  # rows gathered by the last call (for tests and profiling)

    def fits(self, field: SpectralField, n: int) -> bool:
        itemsize = torch.finfo(field.dtype).bits // 8
        return n * 12 * field.k * itemsize <= self.max_bytes

    @torch.no_grad()
    def rows(self, field: SpectralField, verts: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
        key = torch.cat([verts, nodes], dim=1)
        if self._key is None or self._key.shape != key.shape or self._rows.dtype != field.dtype:
            self._rows = torch.empty(
                (key.shape[0], 12, field.k), dtype=field.dtype, device=field.device
            )
            changed = torch.arange(key.shape[0], device=key.device)
        else:
            changed = torch.nonzero((key != self._key).any(dim=1)).squeeze(1)
        for start in range(0, changed.shape[0], CHUNK_ROWS):
            idx = changed[start : start + CHUNK_ROWS]
            self._rows[idx] = gather_rows(field.evecs, verts[idx], nodes[idx], field.dtype)
        self._key = key
        self.regathered = int(changed.shape[0])
        return self._rows


def gather_rows(
    evecs: torch.Tensor, verts: torch.Tensor, nodes: torch.Tensor, dtype: torch.dtype
) -> torch.Tensor:
    """``evecs[verts[u, v], nodes[u, c], :]`` as a (U, 3 * 4, K) block in ``dtype``.

    One ``index_select`` on the (n * G, K) view: measured faster than two-tensor advanced
    indexing on the CPU.
    """
    n_nodes, k = evecs.shape[1], evecs.shape[2]
    flat = (verts[:, :, None] * n_nodes + nodes[:, None, :]).reshape(-1)
    rows = evecs.reshape(-1, k).index_select(0, flat)
    return rows.view(verts.shape[0], 3 * nodes.shape[1], k).to(dtype)


def _device_evecs(evecs: np.ndarray, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """The eigenvector grid as a tensor, shared with the spectra's array where possible.

    On the CPU a float16/float32 grid (typically a read-only memory map of ``evecs.npy``) is
    wrapped without a copy: worker processes serving the same spectra then share the page
    cache instead of each holding its own gigabytes. Rows are up-cast to the compute dtype
    when gathered. The tensor is never written to.
    """
    if evecs.dtype in (np.float16, np.float32) and device.type == "cpu":
        if not evecs.flags.c_contiguous:
            evecs = np.ascontiguousarray(evecs)
        with warnings.catch_warnings():  # read-only memory map: we only ever read it
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
            return torch.from_numpy(evecs)
    store = torch.float16 if evecs.dtype == np.float16 else dtype
    return torch.from_numpy(np.array(evecs, order="C")).to(device, store)


class SpectralField:
    """The aligned spectral grid of one mesh as device tensors, with differentiable lookups.

    ``dtype`` is the compute precision. Eigenvectors stored as float16 in the spectra stay
    float16 on the device (half the memory) and are up-cast row by row when gathered; on the
    CPU the grid is shared with the spectra's (memory-mapped) array, not copied.
    """

    def __init__(
        self,
        spectra: Spectra,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.device = resolve_device(device)
        self.dtype = dtype
        self.spectra = spectra
        self.evecs = _device_evecs(spectra.evecs, self.device, dtype)
        self.evals = self._t(spectra.evals)  # (G, K)
        self.grid_theta = self._t(spectra.grid_theta)
        self.grid_s = self._t(spectra.grid_s)
        self.faces = torch.from_numpy(np.array(spectra.faces, dtype=np.int64)).to(self.device)
        self.vertices = self._t(spectra.vertices)
        self.embedding = self._t(spectra.embedding)  # (n, K_iso - 1)
        n_nodes = self.grid_theta.shape[0] * self.grid_s.shape[0]
        if self.evecs.shape[1] != n_nodes or self.evals.shape != (n_nodes, self.evecs.shape[2]):
            raise ValueError(
                f"spectra grid is inconsistent: evecs {tuple(self.evecs.shape)}, evals "
                f"{tuple(self.evals.shape)}, {n_nodes} grid nodes"
            )

    def _t(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.array(array, dtype=np.float64)).to(self.device, self.dtype)

    @property
    def n_vertices(self) -> int:
        return int(self.evecs.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_nodes(self) -> int:
        return int(self.evecs.shape[1])

    @property
    def k(self) -> int:
        return int(self.evecs.shape[2])

    def nodes(self, theta: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Bilinear grid nodes (P, 4) and weights (P, 4) for ``(theta, s)``."""
        return bilinear_nodes(self.grid_theta, self.grid_s, theta, s)

    def eigenvalues(self, theta: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``lambda_k = sum_c w_c lambda_k^c`` at each ``(theta, s)``: (P, K).

        As a dense (P, G) weight matrix times the (G, K) table: a GEMM instead of gathering a
        (P, 4, K) block (the grid has only G ~ 49 nodes; measured faster for 10k kernels).
        """
        nodes, weights = self.nodes(theta, s)
        dense = torch.zeros((nodes.shape[0], self.n_nodes), dtype=weights.dtype, device=self.device)
        dense = dense.scatter_add(1, nodes, weights)  # corners may coincide at clamped ends
        return dense.to(self.dtype) @ self.evals

    def eigenfunctions(
        self,
        face_ids: torch.Tensor,
        bary: torch.Tensor,
        theta: torch.Tensor,
        s: torch.Tensor,
        rows: RowCache | None = None,
    ) -> torch.Tensor:
        """``phi_k(x)`` at surface points for per-point ``(theta, s)``: (P, K).

        Memory stays bounded by :data:`CHUNK_ROWS` in forward and backward. ``rows``: a
        :class:`RowCache` of the same points (one per kernel set) that keeps their gathered
        eigenvector rows between calls.
        """
        nodes, weights = self.nodes(theta, s)
        verts = self.faces[face_ids]
        block = None if rows is None else rows.rows(self, verts, nodes)
        return _InterpolatedRows.apply(self.evecs, verts, bary, nodes, weights, self.dtype, block)

    def node_values(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """Eigenfunctions at surface points on every grid node: (P, G, K).

        This is the query side of kernel evaluation: a point's three vertex rows are contiguous
        in the vertex-major layout, so gathering all nodes is three contiguous reads per point
        and serves every candidate kernel, whatever its angle and anisotropy.
        """
        verts = self.faces[face_ids]
        p, g, k = verts.shape[0], self.n_nodes, self.k
        # One gather of the three (G * K) vertex rows and one batched (1 x 3) @ (3 x G K)
        # product: measured faster than three gathers with elementwise multiply-adds, which
        # wrote the (P, G, K) block five times.
        rows = self.evecs.index_select(0, verts.reshape(-1)).view(p, 3, g * k).to(self.dtype)
        return torch.bmm(bary.to(self.dtype)[:, None, :], rows).view(p, g, k)

    def embedding_at(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """Biharmonic embedding interpolated barycentrically: (P, K_iso - 1)."""
        return torch.einsum("pvd,pv->pd", self.embedding[self.faces[face_ids]], bary.to(self.dtype))

    def positions(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """3-D points in the normalised frame: (P, 3)."""
        return torch.einsum("pvd,pv->pd", self.vertices[self.faces[face_ids]], bary.to(self.dtype))
