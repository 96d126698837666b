"""The spectra artefact (ALGORITHM.md sections 2-3, INTERFACES.md section 1).

:class:`Spectra` is the in-memory view of a spectra directory; big arrays are memory-mapped
``.npy`` files, vertex-major. Building, writing, reading and caching live in this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hktex_engine.config import SpectralConfig


@dataclass
class Spectra:
    """An aligned anisotropic eigenbasis grid plus the isotropic spectrum of one mesh.

    Node ``g = a * S + s`` (angle-major) for angle index ``a`` and anisotropy index ``s``.
    """

    vertices: np.ndarray  # (n, 3) normalised
    faces: np.ndarray  # (m, 3)
    mass: np.ndarray  # (n,)
    grid_theta: np.ndarray  # (A,) radians ascending, [0, pi]
    grid_eta: np.ndarray  # (S,) ascending
    evals: np.ndarray  # (A*S, K)
    evecs: np.ndarray  # (n, A*S, K) float16/32, possibly a read-only memmap
    iso_evals: np.ndarray  # (K_iso,)
    iso_evecs: np.ndarray  # (n, K_iso)
    face_frames: np.ndarray  # (m, 3) unit u_ref per face
    config: SpectralConfig
    mesh_hash: str
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    manifest: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def grid_s(self) -> np.ndarray:
        """Anisotropy grid coordinate s = ln(1 + eta)."""
        return np.log1p(self.grid_eta)

    @property
    def embedding(self) -> np.ndarray:
        """Biharmonic embedding per vertex, (n, K_iso - 1): psi_k / mu_k, constant mode dropped."""
        return self.iso_evecs[:, 1:] / self.iso_evals[1:][None, :]

    @property
    def config_hash(self) -> str:
        return self.config.key()
