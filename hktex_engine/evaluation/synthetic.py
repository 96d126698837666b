"""Small deterministic meshes for tests and the demo.

Tests across the project need surfaces whose answers are known (a flat patch, an open
cylinder, a sphere, a torus of genus 1) and a textured closed mesh with UV seams for fitting;
generating them keeps the repository free of data files. Every function is deterministic.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from hktex_engine.errors import TextureError


def grid_patch(nx: int, ny: int, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat square ``[0, size]^2`` in the plane z = 0 with ``nx`` x ``ny`` vertices.

    Open boundary on all four sides; each grid cell is split into two triangles along the same
    diagonal, counter-clockwise seen from +z (normals point to +z).
    """
    if nx < 2 or ny < 2:
        raise ValueError("grid_patch needs nx >= 2 and ny >= 2 vertices per side")
    xs = np.linspace(0.0, size, nx)
    ys = np.linspace(0.0, size, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="xy")
    v00 = (j * nx + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx, v00 + nx + 1
    faces = np.stack([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 1)
    return vertices, faces.reshape(-1, 3).astype(np.int64)


def cylinder(
    n_around: int, n_along: int, radius: float = 1.0, height: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """An open cylinder (no caps) around the z axis, ``z`` in ``[-height/2, height/2]``.

    ``n_around`` vertices per ring, ``n_along`` rings; two boundary loops, genus 0.
    """
    if n_around < 3 or n_along < 2:
        raise ValueError("cylinder needs n_around >= 3 and n_along >= 2")
    angle = 2.0 * np.pi * np.arange(n_around) / n_around
    z = np.linspace(-height / 2.0, height / 2.0, n_along)
    a, zz = np.meshgrid(angle, z, indexing="xy")
    vertices = np.stack([radius * np.cos(a).ravel(), radius * np.sin(a).ravel(), zz.ravel()], 1)
    faces = _wrapped_quads(n_around, n_along - 1, wrap_rows=False)
    return vertices, faces


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A unit (or ``radius``) sphere from a subdivided icosahedron: near-uniform triangles."""
    if subdivisions < 0:
        raise ValueError("subdivisions must be >= 0")
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64)


def torus(
    n_major: int, n_minor: int, R: float = 1.0, r: float = 0.4
) -> tuple[np.ndarray, np.ndarray]:
    """A closed ring torus around the z axis (genus 1): ``n_major`` x ``n_minor`` vertices."""
    if n_major < 3 or n_minor < 3:
        raise ValueError("torus needs n_major >= 3 and n_minor >= 3")
    if not 0 < r < R:
        raise ValueError("torus needs 0 < r < R")
    u = 2.0 * np.pi * np.arange(n_major) / n_major
    v = 2.0 * np.pi * np.arange(n_minor) / n_minor
    uu, vv = np.meshgrid(u, v, indexing="xy")  # rows: minor angle, columns: major angle
    ring = R + r * np.cos(vv)
    vertices = np.stack([ring * np.cos(uu), ring * np.sin(uu), r * np.sin(vv)], -1).reshape(-1, 3)
    faces = _wrapped_quads(n_major, n_minor, wrap_rows=True)
    return vertices, faces


def _wrapped_quads(n_cols: int, n_rows: int, wrap_rows: bool) -> np.ndarray:
    """Triangles of a grid whose columns wrap around (and rows too for a torus)."""
    rows_total = n_rows if wrap_rows else n_rows + 1
    i, j = np.meshgrid(np.arange(n_cols), np.arange(n_rows), indexing="xy")
    i1 = (i + 1) % n_cols
    j1 = (j + 1) % rows_total
    v00, v10 = j * n_cols + i, j * n_cols + i1
    v01, v11 = j1 * n_cols + i, j1 * n_cols + i1
    faces = np.stack([np.stack([v00, v10, v11], -1), np.stack([v00, v11, v01], -1)], -2)
    return faces.reshape(-1, 3).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# A textured closed mesh with seams
# ---------------------------------------------------------------------------------------------

# Cube-map atlas: 3 columns x 2 rows of cells, one per cube face (+x, -x, +y, -y, +z, -z).
# Gnomonic coordinates in [-_REACH, _REACH] fill a cell, so corners of triangles that straddle
# a cube edge (|g| slightly above 1) still land inside their own cell, and the texels there hold
# the same continuous colour function: bilinear lookups near a seam stay correct.
_REACH = 1.35


def textured_demo(
    subdivisions: int = 4, texture_size: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A closed, spot-like blob with a cube-map UV atlas (seams) and a procedural albedo.

    Returns ``(vertices, faces, corner_uvs, texture)``. The albedo is a function of the
    direction from the centre with sharp features (a disc, stripes) and smooth ones (a colour
    gradient), so fitting has edges and ramps to learn. The texture is that function sampled
    in each atlas cell; the UVs are the gnomonic projections of each corner.
    """
    if texture_size < 16:
        raise ValueError("texture_size must be >= 16")
    sphere_v, faces = icosphere(subdivisions)
    radius = _blob_radius(sphere_v)
    vertices = sphere_v * radius[:, None]
    directions = sphere_v[faces]  # (m, 3, 3) unit directions of each corner
    cell = _dominant_axis(directions.mean(axis=1))  # (m,) cube face of each triangle
    corner_uvs = _atlas_uv(directions.reshape(-1, 3), np.repeat(cell, 3)).reshape(-1, 3, 2)
    texture = _atlas_texture(texture_size)
    return vertices, faces, corner_uvs, texture


def _blob_radius(d: np.ndarray) -> np.ndarray:
    """A smooth star-shaped bump field, so the demo is not a plain sphere."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return 1.0 + 0.12 * np.sin(3.0 * x) * np.cos(2.0 * y) + 0.08 * z**2 - 0.05 * x * y


def _dominant_axis(d: np.ndarray) -> np.ndarray:
    """Cube face index 0..5 for (+x, -x, +y, -y, +z, -z)."""
    axis = np.argmax(np.abs(d), axis=1)
    negative = d[np.arange(len(d)), axis] < 0
    return 2 * axis + negative


# For each cube face: (normal axis, sign, tangent axis u, tangent axis v).
_CUBE = [(0, 1, 1, 2), (0, -1, 1, 2), (1, 1, 0, 2), (1, -1, 0, 2), (2, 1, 0, 1), (2, -1, 0, 1)]


def _atlas_uv(d: np.ndarray, cell: np.ndarray) -> np.ndarray:
    spec = np.asarray(_CUBE)[cell]
    rows = np.arange(len(d))
    denom = np.abs(d[rows, spec[:, 0]])
    g = np.stack([d[rows, spec[:, 2]], d[rows, spec[:, 3]]], 1) / denom[:, None]
    local = 0.5 + 0.5 * g / _REACH  # in (0, 1) within the cell
    col, row = cell % 3, cell // 3
    u = (col + local[:, 0]) / 3.0
    v = (row + local[:, 1]) / 2.0
    return np.stack([u, v], 1)


def _atlas_texture(size: int) -> np.ndarray:
    """Sample the albedo function at each texel's direction (OBJ: v = 0 is the bottom row)."""
    px = (np.arange(size) + 0.5) / size
    u, v_img = np.meshgrid(px, px, indexing="xy")
    v = 1.0 - v_img  # image row 0 is the top, v = 1
    col = np.minimum((u * 3).astype(int), 2)
    row = np.minimum((v * 2).astype(int), 1)
    cell = (row * 3 + col).ravel()
    local_u = (u * 3 - col).ravel()
    local_v = (v * 2 - row).ravel()
    g = np.stack([(local_u - 0.5) * 2 * _REACH, (local_v - 0.5) * 2 * _REACH], 1)
    spec = np.asarray(_CUBE)[cell]
    d = np.zeros((len(cell), 3))
    rows = np.arange(len(cell))
    d[rows, spec[:, 0]] = spec[:, 1]
    d[rows, spec[:, 2]] = g[:, 0]
    d[rows, spec[:, 3]] = g[:, 1]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return demo_albedo(d).reshape(size, size, 3).astype(np.float32)


def demo_albedo(d: np.ndarray) -> np.ndarray:
    """The demo's albedo as a function of unit direction ``d`` (P, 3) -> RGB in [0, 1]."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    longitude = np.arctan2(y, x)
    # Smooth: a hue-like gradient around the equator and a brightness ramp along z.
    rgb = (
        np.stack(
            [
                0.55 + 0.35 * np.cos(longitude),
                0.55 + 0.35 * np.cos(longitude - 2.1),
                0.55 + 0.35 * np.cos(longitude + 2.1),
            ],
            1,
        )
        * (0.75 + 0.25 * z)[:, None]
    )
    # Sharp: dark stripes in the southern half.
    stripes = (np.sin(9.0 * np.arcsin(np.clip(z, -1, 1))) > 0.3) & (z < -0.2)
    rgb[stripes] = [0.08, 0.08, 0.1]
    # Sharp: a red disc around a fixed direction.
    centre = np.array([0.6, 0.0, 0.8])
    disc = d @ centre > np.cos(0.35)
    rgb[disc] = [0.85, 0.1, 0.1]
    return np.clip(rgb, 0.0, 1.0)


def write_textured_obj(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    corner_uvs: np.ndarray | None = None,
    texture: np.ndarray | None = None,
) -> Path:
    """Write an OBJ (+ MTL + PNG when a texture is given) that :func:`load_mesh` reads back.

    Coordinates are written with 17 significant digits so a round trip is exact and the
    content hash of the written file equals that of the arrays.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = io.StringIO()
    if texture is not None:
        if corner_uvs is None:
            raise TextureError("a texture needs corner_uvs to be written")
        png = path.with_name(path.stem + "_albedo.png")
        mtl = path.with_suffix(".mtl")
        mtl.write_text(f"newmtl albedo\nKd 1 1 1\nmap_Kd {png.name}\n")
        tex = np.clip(np.asarray(texture, dtype=np.float64), 0.0, 1.0)
        Image.fromarray(np.round(tex * 255.0).astype(np.uint8)).save(png)
        out.write(f"mtllib {mtl.name}\nusemtl albedo\n")
    np.savetxt(out, vertices, fmt="v %.17g %.17g %.17g")
    if corner_uvs is not None:
        uv = np.asarray(corner_uvs, dtype=np.float64).reshape(-1, 2)
        uniq, idx = np.unique(uv, axis=0, return_inverse=True)
        np.savetxt(out, uniq, fmt="vt %.17g %.17g")
        corners = np.stack([faces.reshape(-1) + 1, idx.reshape(-1) + 1], 1).reshape(-1, 6)
        np.savetxt(out, corners, fmt="f %d/%d %d/%d %d/%d")
    else:
        np.savetxt(out, faces + 1, fmt="f %d %d %d")
    path.write_text(out.getvalue())
    return path
