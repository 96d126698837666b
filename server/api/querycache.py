"""Warm albedo queries: the last few kernel sets kept loaded (LRU) between requests.

Loading a kernel set means memory-mapping its spectra, reading the ``.hkt`` and building the
engine's ``AlbedoQuery`` (KNN index, device tensors): far more than one query's work, so a
client streaming batches must not pay it per request. Each entry has its own lock: one
kernel set answers one batch at a time (bounded memory), different sets run in parallel.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class WarmQuery:
    query: Any  # hktex_engine.kernels.query.AlbedoQuery
    spectra: Any
    kernelset: Any
    n_faces: int
    lock: threading.Lock

    def colors(self, face_ids: np.ndarray, bary: np.ndarray, chunk: int) -> np.ndarray:
        out = np.empty((len(face_ids), 3), dtype=np.float32)
        with self.lock:
            for start in range(0, len(face_ids), chunk):
                sl = slice(start, start + chunk)
                out[sl] = self.query.colors(face_ids[sl], bary[sl])
        return out

    def colors_at_points(self, points: np.ndarray, chunk: int) -> np.ndarray:
        out = np.empty((len(points), 3), dtype=np.float32)
        with self.lock:
            for start in range(0, len(points), chunk):
                sl = slice(start, start + chunk)
                out[sl] = self.query.colors_at_points(points[sl])
        return out


def load_warm(spectra_path: str, hkt_path: str, mesh_hash: str) -> WarmQuery:
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.kernels.query import AlbedoQuery
    from hktex_engine.spectra.grid import load_spectra

    spectra = load_spectra(spectra_path, mmap=True)
    kernelset = load_hkt(hkt_path, expect_mesh_hash=mesh_hash)
    query = AlbedoQuery(spectra, kernelset)
    return WarmQuery(query, spectra, kernelset, int(spectra.faces.shape[0]), threading.Lock())


class QueryCache:
    def __init__(self, size: int, loader: Callable[..., WarmQuery] = load_warm) -> None:
        self.size = max(1, size)
        self.loader = loader
        self._entries: OrderedDict[str, WarmQuery] = OrderedDict()
        self._lock = threading.Lock()
        self.loads = 0

    def get(self, key: str, *args: Any) -> WarmQuery:
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
                return entry
        entry = self.loader(*args)  # outside the lock: loading may take a second
        with self._lock:
            self.loads += 1
            self._entries[key] = entry
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        return entry

    def discard(self, key: str) -> None:
        """Forget a kernel set (it was deleted): its memory goes with the last reference."""
        with self._lock:
            self._entries.pop(key, None)
