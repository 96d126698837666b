"""Mesh input, validation and normalisation (ALGORITHM.md 'Normalisation').

A :class:`Mesh` is what every other module consumes: vertices merged by position and
normalised (centroid at the origin, largest bounding-box side 2), faces in the input file's
face order, optional per-corner UVs and albedo texture kept for UV fitting, and a content hash
of the canonical geometry that identifies it across uploads and caches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mesh:
    """A validated, normalised triangle mesh.

    ``vertices`` are in the normalised frame: ``x_norm = scale * x_file + translation``.
    ``corner_uvs`` is ``(m, 3, 2)`` (UVs per face corner, so seams survive the merge), OBJ
    convention (v = 0 at the bottom row of the image). ``texture`` is ``(H, W, 3)`` float32 in
    [0, 1], the file's own (sRGB) values.
    """

    vertices: np.ndarray  # (n, 3) float64, normalised
    faces: np.ndarray  # (m, 3) int64
    scale: float
    translation: np.ndarray  # (3,) float64
    content_hash: str
    corner_uvs: np.ndarray | None = None  # (m, 3, 2) float64
    texture: np.ndarray | None = None  # (H, W, 3) float32 in [0, 1]
    source_name: str = ""

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def has_texture(self) -> bool:
        return self.texture is not None and self.corner_uvs is not None

    def to_file_units(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - self.translation) / self.scale

    def to_normalised(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) * self.scale + self.translation
