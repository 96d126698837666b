"""Candidate kernels for a query point: nearest centres in the biharmonic embedding.

ALGORITHM.md section 5 step 1. Two exact backends return the same neighbours (up to ties):

- ``"faiss"``: ``faiss.IndexFlatL2`` (CPU; the faiss-cpu wheel has no GPU index);
- ``"torch"``: ``|q|^2 + |c|^2 - 2 q.c`` by one matmul per chunk of queries, then ``topk``.
  Runs on any torch device, so it is the CUDA path.

``"auto"`` picks faiss on the CPU and torch elsewhere: measured in benchmarks/kernels.py
(10k centres x 1e5 queries, K_s = 100, 64-D, one thread) faiss searched in 6.8 s against
10.9 s for the torch search, with identical neighbour lists up to distance ties
(docs/kernels.md, "Decisions").
"""

from __future__ import annotations

import numpy as np
import torch

#: Bytes one chunk of the torch distance matrix may occupy.
DISTANCE_CHUNK_BYTES = 64 * 2**20

BACKENDS = ("auto", "torch", "faiss")


class CandidateSearch:
    """Exact k-nearest-centre search over a fixed set of centre embeddings (N, D)."""

    def __init__(self, centres: torch.Tensor, backend: str = "auto") -> None:
        if backend not in BACKENDS:
            raise ValueError(f"knn backend must be one of {BACKENDS}, got {backend!r}")
        if backend == "auto":
            backend = "faiss" if centres.device.type == "cpu" else "torch"
        if backend == "faiss" and centres.device.type != "cpu":
            raise ValueError("the faiss backend runs on the CPU only; use backend='torch'")
        self.backend = backend
        self.centres = centres.detach()
        self.n = int(centres.shape[0])
        if backend == "faiss":
            import faiss

            self._index = faiss.IndexFlatL2(int(centres.shape[1]))
            self._index.add(np.ascontiguousarray(self.centres.cpu().numpy(), dtype=np.float32))
        else:
            self._sq = (self.centres * self.centres).sum(dim=1)

    def search(self, queries: torch.Tensor, k: int) -> torch.Tensor:
        """Indices (P, min(k, N)) of the nearest centres, nearest first."""
        k = min(int(k), self.n)
        queries = queries.detach()
        if self.backend == "faiss":
            q = np.ascontiguousarray(queries.cpu().numpy(), dtype=np.float32)
            _, idx = self._index.search(q, k)
            return torch.as_tensor(idx, dtype=torch.long, device=queries.device)
        return self._search_torch(queries.to(self.centres.dtype), k)

    def _search_torch(self, queries: torch.Tensor, k: int) -> torch.Tensor:
        item = self.centres.element_size()
        rows = max(1, DISTANCE_CHUNK_BYTES // max(1, self.n * item))
        out = torch.empty((queries.shape[0], k), dtype=torch.long, device=queries.device)
        for start in range(0, queries.shape[0], rows):
            q = queries[start : start + rows]
            # |q - c|^2 up to the per-row constant |q|^2, which does not change the ranking.
            d2 = torch.addmm(self._sq[None, :], q, self.centres.T, beta=1.0, alpha=-2.0)
            out[start : start + rows] = torch.topk(d2, k, dim=1, largest=False).indices
        return out
