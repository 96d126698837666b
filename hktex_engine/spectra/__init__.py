"""Spectra: a mesh in, the aligned anisotropic eigenbasis grid out (ALGORITHM.md §2-3).

Takes a ``Mesh`` and a ``SpectralConfig``; gives ``Spectra`` (the aligned ALBO grid, the
isotropic spectrum and biharmonic embedding, the normalising transform), stored as a
memory-mapped directory and cached per (mesh hash, config), and ``SpectralField``, its
differentiable interpolation at surface points.
"""

from importlib import import_module
from typing import Any

#: Public name -> the module that defines it. Imported on first use (PEP 562), so importing a
#: submodule (a spectra worker process unpickling its solve function from ``eigensolver``)
#: does not pull in torch or the mesh loaders through this package.
_EXPORTS = {
    "Spectra": "grid",
    "SpectraCache": "grid",
    "SpectralField": "interpolation",
    "align_basis": "alignment",
    "auto_workers": "cores",
    "compute_spectra": "grid",
    "eigs_block": "eigensolver",
    "eigs_cold": "eigensolver",
    "eigs_node": "eigensolver",
    "eigs_sliced": "eigensolver",
    "eigs_warm": "eigensolver",
    "load_spectra": "grid",
    "write_spectra": "grid",
}


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


__all__ = [
    "Spectra",
    "SpectraCache",
    "SpectralField",
    "align_basis",
    "auto_workers",
    "compute_spectra",
    "eigs_block",
    "eigs_cold",
    "eigs_node",
    "eigs_sliced",
    "eigs_warm",
    "load_spectra",
    "write_spectra",
]
