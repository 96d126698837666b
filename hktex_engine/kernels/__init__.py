"""Kernels: spectra and kernel parameters in, albedo at surface points out (ALGORITHM.md §4-5).

Takes ``Spectra`` and a ``KernelSet``; gives the differentiable ``HeatKernelModel``, the
candidate search in the biharmonic embedding, the ``.hkt`` file, and ``AlbedoQuery`` for
validated, bounded-memory batches of points.
"""

from hktex_engine.kernels.hkt import hkt_bytes, load_hkt, save_hkt
from hktex_engine.kernels.knn import CandidateSearch
from hktex_engine.kernels.model import HeatKernelModel, KernelSet, soft_step
from hktex_engine.kernels.query import AlbedoQuery

__all__ = [
    "AlbedoQuery",
    "CandidateSearch",
    "HeatKernelModel",
    "KernelSet",
    "hkt_bytes",
    "load_hkt",
    "save_hkt",
    "soft_step",
]
