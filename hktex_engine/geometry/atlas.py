"""Several materials' albedo packed into one texture, so a multi-material mesh fits like any other.

Everything downstream of loading (UV fitting's target, metrics, baselines, error maps, bakes)
reads one texture through per-corner UVs. A mesh whose faces use several materials (an OBJ
with several ``usemtl`` maps, a glTF with several primitives) therefore gets one atlas at load
time: each material's image becomes a tile, its faces' UVs are moved into the tile, and a
material without an image (an OBJ ``Kd`` colour, a glTF ``baseColorFactor`` alone) becomes a
small constant tile. Reading the atlas at a face's atlas UVs gives exactly what reading the
material's own image at the original UVs gives, wrap-around included (tested against the
per-material lookup), so fitting and scoring see the asset's own colours.

Written here because no library we use packs materials for us: trimesh can merge textured
meshes into an atlas, but it resamples the images and does not keep repeating (tiled) UVs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hktex_engine.errors import TextureError

#: A face may span at most this many periods of its material's image in u or v: the tile
#: holds that many copies, so the UVs of a tiling material stay exact.
MAX_REPEATS = 4

#: The atlas's pixel budget (float32 RGB: 12 bytes a pixel, so ~0.8 GB). Several 4k maps
#: fit; beyond it loading refuses with a message rather than resampling the asset's colours.
MAX_ATLAS_PIXELS = 64 * 1024 * 1024

#: Wrapped border around each tile, so a bilinear lookup at a tile's edge reads the
#: material's own wrap-around neighbour, never the next tile.
GUTTER = 2

#: Side of the tile that holds a constant colour.
CONSTANT_TILE = 4


@dataclass(frozen=True)
class Appearance:
    """One material's albedo as the file states it.

    ``image`` is the stored (sRGB) map in [0, 1] or None; ``factor`` is a linear RGB multiplier
    (glTF's ``baseColorFactor``; 1 for OBJ maps), or, without an image, ``colour`` is the
    constant stored (sRGB) value. ``key`` identifies equal appearances across materials.
    """

    key: tuple
    image: np.ndarray | None = None
    factor: tuple[float, float, float] = (1.0, 1.0, 1.0)
    colour: tuple[float, float, float] | None = None
    name: str = ""


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


def stored_albedo(appearance: Appearance) -> np.ndarray:
    """The appearance as a stored (sRGB) image: the map times its factor (in linear light,
    as glTF defines it), or a constant tile."""
    if appearance.image is None:
        colour = np.asarray(appearance.colour, dtype=np.float32).reshape(1, 1, 3)
        return np.ascontiguousarray(np.broadcast_to(colour, (CONSTANT_TILE, CONSTANT_TILE, 3)))
    factor = np.asarray(appearance.factor, dtype=np.float32)
    if np.all(factor == 1.0):
        return appearance.image
    return linear_to_srgb(srgb_to_linear(appearance.image) * factor)


def one_texture(
    appearances: list[Appearance],
    face_appearance: np.ndarray,
    corner_uvs: np.ndarray | None,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """One texture and per-corner UVs for faces that use ``appearances[face_appearance[f]]``.

    A single appearance keeps its image and the file's UVs untouched (the common case costs
    nothing and reads exactly as before); none with an image means no texture. ``corner_uvs``
    rows of faces whose appearance has no image may be NaN: they are not read.
    """
    used = np.unique(face_appearance)
    if not any(appearances[a].image is not None for a in used):
        return None, None
    if len(used) == 1:
        if corner_uvs is not None and not np.all(np.isfinite(corner_uvs)):
            corner_uvs = None  # some faces have no UVs: the mesh reads as untextured
        return stored_albedo(appearances[int(used[0])]), corner_uvs
    textured = np.isin(face_appearance, [a for a in used if appearances[a].image is not None])
    if corner_uvs is None or not np.all(np.isfinite(corner_uvs[textured])):
        names = sorted({appearances[a].name for a in np.unique(face_appearance[textured])})
        raise TextureError(f"faces of the textured material(s) {names} have no UV coordinates")
    return _pack(appearances, used, face_appearance, corner_uvs)


def _pack(
    appearances: list[Appearance],
    used: np.ndarray,
    face_appearance: np.ndarray,
    corner_uvs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Shelf-pack one tile per used appearance; move each face's UVs into its tile."""
    out_uvs = np.empty_like(corner_uvs, dtype=np.float64)
    placements = []
    for a in used:
        faces = np.flatnonzero(face_appearance == a)
        if appearances[a].image is None:
            local, reps = np.full((len(faces), 3, 2), 0.5), (1, 1)
            h = w = CONSTANT_TILE
        else:
            local, reps = _periods(corner_uvs[faces], appearances[a].name)
            h, w = appearances[a].image.shape[:2]
        placements.append((a, faces, local, (h, w), reps))
    sizes = [(r[1] * h + 2 * GUTTER, r[0] * w + 2 * GUTTER) for *_, (h, w), r in placements]
    origins, height, width = _shelves(sizes)
    if height * width > MAX_ATLAS_PIXELS:
        raise TextureError(
            f"the materials' images need a {width}x{height} atlas, more than "
            f"{MAX_ATLAS_PIXELS} pixels; bake the asset to one texture first"
        )
    atlas = np.zeros((height, width, 3), dtype=np.float32)
    for (y0, x0), (th, tw), (a, faces, local, (h, w), reps) in zip(
        origins, sizes, placements, strict=True
    ):
        tile = np.tile(stored_albedo(appearances[a]), (reps[1], reps[0], 1))
        atlas[y0 : y0 + th, x0 : x0 + tw] = np.pad(tile, ((GUTTER,), (GUTTER,), (0,)), "wrap")
        # texture_lookup reads x = u W - 0.5 (texel centres, v = 0 at the bottom row); these
        # UVs land on the tile's texel x0 + GUTTER + u_local w, rows counted from its top.
        out_uvs[faces, :, 0] = (x0 + GUTTER + local[..., 0] * w) / width
        out_uvs[faces, :, 1] = 1.0 - (y0 + GUTTER + (reps[1] - local[..., 1]) * h) / height
    return atlas, out_uvs


def _periods(uvs: np.ndarray, name: str) -> tuple[np.ndarray, tuple[int, int]]:
    """Each face's UVs moved by whole periods to start in [0, 1); how many periods they span."""
    local = uvs - np.floor(uvs.min(axis=1, keepdims=True))
    span = np.ceil(local.max(axis=(0, 1))).astype(np.int64)
    reps = (max(1, int(span[0])), max(1, int(span[1])))
    if max(reps) > MAX_REPEATS:
        raise TextureError(
            f"material {name!r}: a face spans {max(reps)} repeats of its image (at most "
            f"{MAX_REPEATS} can be packed with other materials); bake the asset to one texture"
        )
    return local, reps


def _shelves(sizes: list[tuple[int, int]]) -> tuple[list[tuple[int, int]], int, int]:
    """Top-left corners for (h, w) tiles in rows no wider than the widest tile or the square
    root of their total area, tallest first; and the atlas's height and width."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][0])
    limit = max(max(w for _, w in sizes), int(np.ceil(np.sqrt(sum(h * w for h, w in sizes)))))
    origins: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = row_h = width = 0
    for i in order:
        h, w = sizes[i]
        if x and x + w > limit:
            y, x, row_h = y + row_h, 0, 0
        origins[i] = (y, x)
        x += w
        row_h = max(row_h, h)
        width = max(width, x)
    return origins, y + row_h, width
