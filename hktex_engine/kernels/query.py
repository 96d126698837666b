"""Batched albedo queries against a fitted kernel set (the service keeps one of these warm).

:class:`AlbedoQuery` builds the query state once (spectral grid on the device, per-kernel
spectral coefficients and centre responses, the KNN index) and answers any number of calls in
chunks of points, under ``torch.no_grad``, so a million points run in bounded memory.
"""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.errors import KernelSetError, QueryError
from hktex_engine.geometry.sampling import closest_surface_point
from hktex_engine.kernels.model import KNN_MARGIN, HeatKernelModel, KernelSet
from hktex_engine.progress import Progress, check_cancel
from hktex_engine.spectra.grid import Spectra
from hktex_engine.spectra.interpolation import SpectralField

#: Default bytes the tensors of one chunk may take (see :meth:`AlbedoQuery.bytes_per_point`).
DEFAULT_MEMORY_BUDGET = 512 * 2**20
#: Calls with at least this many points per mesh vertex build whole-mesh candidate tables.
TABLES_POINTS_PER_VERTEX = 1.0
#: Points per chunk when whole-mesh face tables answer through the compiled blend (its
#: threads split a chunk, and the per-point path's chunk of ~3,000 points ran it on one
#: thread: a million points 1.9 s against 1.04 s at this size, 8,192-vertex torus, 10,000
#: kernels, 2 cores); a chunk is also the step of progress reports and cancellation.
TABLE_CHUNK_POINTS = 262_144
#: Upper estimate of the working bytes of one point there (ids, barycentrics in two dtypes,
#: face rows, colours: ~70 bytes counted).
TABLE_BYTES_PER_POINT = 128
#: Barycentric rows may miss the simplex by this much (round-off in a caller's own tools).
BARY_TOL = 1e-4
#: numpy twin of the field's torch dtype (query batches are converted before torch sees them).
_NUMPY_DTYPE = {torch.float32: np.float32, torch.float64: np.float64}


class AlbedoQuery:
    """Albedo at surface points or 3-D points for one kernel set on its spectra.

    ``tables``: True builds the whole-mesh candidate tables (``kernels.tables``) with the
    query state, for callers that know a dense workload is coming; None (default) builds them
    on the first call with at least one point per mesh vertex; False never builds whole-mesh
    tables (a chunk dense enough may still use its own).
    """

    def __init__(
        self,
        spectra: Spectra,
        kernelset: KernelSet,
        device: str | torch.device | None = None,
        chunk_points: int | None = None,
        memory_budget: int = DEFAULT_MEMORY_BUDGET,
        knn_backend: str = "auto",
        tables: bool | None = None,
    ) -> None:
        if kernelset.mesh_hash and kernelset.mesh_hash != spectra.mesh_hash:
            raise KernelSetError("the kernel set was fitted on another mesh than these spectra")
        if kernelset.config_hash and kernelset.config_hash != spectra.config_hash:
            raise KernelSetError("the kernel set was fitted on spectra of another config")
        self.spectra = spectra
        self.field = SpectralField(spectra, device=device)
        self.model = HeatKernelModel.from_kernelset(kernelset, self.field, knn_backend)
        self.model.requires_grad_(False)
        self.tables = tables
        with torch.no_grad():
            self.model.refresh()
            if tables:
                # dense workloads known in advance: the whole-mesh candidate tables are part
                # of the query state (kernels.tables)
                self.model.prepare_tables()
        self._chunk_chosen = chunk_points is not None
        self._table_chunk = max(1, min(TABLE_CHUNK_POINTS, memory_budget // TABLE_BYTES_PER_POINT))
        if chunk_points is None:
            chunk_points = max(1, memory_budget // self.bytes_per_point())
        if chunk_points < 1:
            raise ValueError("chunk_points must be >= 1")
        self.chunk_points = int(chunk_points)

    @property
    def device(self) -> torch.device:
        return self.field.device

    def bytes_per_point(self) -> int:
        """Upper estimate of tensor bytes one query point needs during evaluation.

        Terms: the point's three gathered vertex rows and its eigenfunctions on every node,
        its candidates' coefficients, the candidate-by-node dot products, the gathered
        candidate embeddings and their differences to the point for the exact ``K_s`` cut
        (``K_s`` + margin of them) and small per-candidate vectors.
        """
        g, k = self.field.n_nodes, self.field.k
        k_s = min(self.model.config.k_search, len(self.model))
        d = int(self.field.embedding.shape[1])
        k_m = min(k_s + KNN_MARGIN, len(self.model))
        floats = 4 * g * k + k_s * k + k_s * g + 2 * k_m * d + 16 * k_m
        return int(floats * (torch.finfo(self.field.dtype).bits // 8))

    def colors(
        self, face_ids: np.ndarray, barycentrics: np.ndarray, progress: Progress | None = None
    ) -> np.ndarray:
        """Albedo (P, 3) float32 at surface points given as face ids and barycentrics."""
        face_ids, bary = self.validate(face_ids, barycentrics)
        # Chunks of points sorted by face share vertices, which dense queries exploit
        # (kernels._h_by_vertex_pairs); the answer goes back in the caller's order.
        order = np.argsort(face_ids, kind="stable")
        face_ids, bary = face_ids[order], bary[order]
        out = np.empty((face_ids.shape[0], 3), dtype=np.float32)
        with torch.no_grad():
            dense = face_ids.shape[0] >= TABLES_POINTS_PER_VERTEX * self.field.n_vertices
            if self.tables is None and dense:
                # dense workload: per-vertex candidate tables for the whole mesh, built once
                # and kept while this query object lives (kernels.tables)
                self.model.prepare_tables()
            chunk = self.chunk_points
            if not self._chunk_chosen and self.model.blends_from_mesh_tables():
                chunk = max(chunk, self._table_chunk)
            for start in range(0, face_ids.shape[0], chunk):
                sl = slice(start, start + chunk)
                # dtype conversion in numpy: torch's parallel copy contends with the caller's
                # threads when called from a renderer's callback (measured 14 ms a render)
                f = torch.from_numpy(np.ascontiguousarray(face_ids[sl])).to(self.device)
                b_np = np.ascontiguousarray(bary[sl], dtype=_NUMPY_DTYPE[self.field.dtype])
                b = torch.from_numpy(b_np).to(self.device)
                out[order[sl]] = self.model.albedo(f, b).cpu().numpy()
                check_cancel(progress)
                if progress is not None:
                    progress.update(min(start + chunk, len(out)), len(out))
        return out

    def colors_at_points(self, points: np.ndarray, progress: Progress | None = None) -> np.ndarray:
        """Albedo (P, 3) at the surface points closest to ``points`` given in file units."""
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise QueryError(f"points must have shape (P, 3), got {pts.shape}")
        if pts.dtype.kind not in "iuf":
            raise QueryError(f"points must be numbers, got dtype {pts.dtype}")
        pts = pts.astype(np.float64)
        if not np.all(np.isfinite(pts)):
            raise QueryError("points contain NaN or infinity")
        normalised = pts * self.spectra.scale + np.asarray(self.spectra.translation)[None, :]
        face_ids, bary = closest_surface_point(
            self.spectra.vertices, self.spectra.faces, normalised
        )
        return self.colors(face_ids, bary, progress)

    def validate(
        self, face_ids: np.ndarray, barycentrics: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Checked copies: face ids int64 (P,), barycentrics (P, 3) on the simplex."""
        f = np.asarray(face_ids)
        b = np.asarray(barycentrics)
        if f.ndim != 1:
            raise QueryError(f"face_ids must have shape (P,), got {f.shape}")
        if b.ndim != 2 or b.shape[1] != 3 or b.shape[0] != f.shape[0]:
            raise QueryError(f"barycentrics must have shape ({f.shape[0]}, 3), got {b.shape}")
        if f.size and f.dtype.kind not in "iu":
            raise QueryError(f"face_ids must be integers, got dtype {f.dtype}")
        if b.dtype.kind not in "iuf":
            raise QueryError(f"barycentrics must be numbers, got dtype {b.dtype}")
        f = f.astype(np.int64)
        b = b.astype(np.float64)
        m = self.field.n_faces
        if f.size and (f.min() < 0 or f.max() >= m):
            raise QueryError(f"face ids must lie in [0, {m}), got [{f.min()}, {f.max()}]")
        if not np.all(np.isfinite(b)):
            raise QueryError("barycentrics contain NaN or infinity")
        if b.size and (b.min() < -BARY_TOL or np.abs(b.sum(axis=1) - 1.0).max() > BARY_TOL):
            raise QueryError("barycentrics must be non-negative and each row must sum to 1")
        b = np.clip(b, 0.0, None)
        return f, b / b.sum(axis=1, keepdims=True)
