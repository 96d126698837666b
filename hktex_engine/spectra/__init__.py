"""Spectra: a mesh in, the aligned anisotropic eigenbasis grid out (ALGORITHM.md §2-3).

Takes a ``Mesh`` and a ``SpectralConfig``; gives ``Spectra`` (the aligned ALBO grid, the
isotropic spectrum and biharmonic embedding, the normalising transform), stored as a
memory-mapped directory and cached per (mesh hash, config), and ``SpectralField``, its
differentiable interpolation at surface points.
"""

from hktex_engine.spectra.alignment import align_basis
from hktex_engine.spectra.eigensolver import (
    eigs_block,
    eigs_cold,
    eigs_node,
    eigs_sliced,
    eigs_warm,
)
from hktex_engine.spectra.grid import (
    Spectra,
    SpectraCache,
    compute_spectra,
    load_spectra,
    write_spectra,
)
from hktex_engine.spectra.interpolation import SpectralField

__all__ = [
    "Spectra",
    "SpectraCache",
    "SpectralField",
    "align_basis",
    "compute_spectra",
    "eigs_block",
    "eigs_cold",
    "eigs_node",
    "eigs_sliced",
    "eigs_warm",
    "load_spectra",
    "write_spectra",
]
