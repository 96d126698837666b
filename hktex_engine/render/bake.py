"""Bake a kernel set back into ordinary assets: a UV texture, glTF/GLB, OBJ, vertex colours.

Every texel of the target texture is located on the surface (face + barycentrics) by
rasterising the triangles in UV space, its albedo is queried from the kernel set, and empty
texels are filled from the nearest covered texel so that bilinear filtering and mip-mapping
never blend in a background colour across UV seams. A mesh without UVs gets a fresh atlas
from xatlas. Textures are sRGB, like the kernel set's colours.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hktex_engine.errors import SpectraError, TextureError
from hktex_engine.progress import Progress, check_cancel

#: Candidate (face, texel) pairs tested per chunk while rasterising (bounds memory).
RASTER_CHUNK = 4_000_000

#: The mesh's UV islands count as overlapping when the texels they cover are fewer than this
#: fraction of their summed area in texels (texel centres inside a triangle number its area
#: on average, so a proper layout sits near 1 and mirrored halves near 0.5).
MIN_DISTINCT_COVER = 0.9


@dataclass
class Bake:
    """A baked texture and the UV layout it belongs to (OBJ convention, v = 0 at the bottom)."""

    texture: np.ndarray  # (H, W, 3) float32 sRGB in [0, 1]
    corner_uvs: np.ndarray  # (m, 3, 2)
    coverage: float  # fraction of texels covered by a triangle before padding
    atlas: str  # "mesh" (the mesh's own UVs) or "xatlas"
    atlas_reason: str = ""  # why the mesh's own UVs were not used, when they were not


def rasterize_uv(corner_uvs: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Face id (H, W) (-1 where empty) and barycentrics (H, W, 3) of every texel centre.

    Vectorised over triangles: every triangle's texel bounding box is enumerated as one ragged
    range (numpy repeat/arange arithmetic), all candidates are tested at once, in chunks.
    Where UV islands overlap the later face wins.
    """
    uv = np.asarray(corner_uvs, dtype=np.float64)
    if uv.ndim != 3 or uv.shape[1:] != (3, 2):
        raise TextureError(f"corner_uvs must be (m, 3, 2), got {uv.shape}")
    # texel (x, y) centre sits at u = (x + 0.5) / W, v = 1 - (y + 0.5) / H
    px = uv[..., 0] * width - 0.5
    py = (1.0 - uv[..., 1]) * height - 0.5
    x0 = np.clip(np.floor(px.min(1)).astype(np.int64), 0, width - 1)
    x1 = np.clip(np.ceil(px.max(1)).astype(np.int64), 0, width - 1)
    y0 = np.clip(np.floor(py.min(1)).astype(np.int64), 0, height - 1)
    y1 = np.clip(np.ceil(py.max(1)).astype(np.int64), 0, height - 1)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    counts = bw * bh
    face_img = np.full((height, width), -1, dtype=np.int64)
    bary_img = np.zeros((height, width, 3), dtype=np.float64)
    # signed double area in texel space; degenerate UV triangles cover nothing
    d = (px[:, 1] - px[:, 0]) * (py[:, 2] - py[:, 0]) - (px[:, 2] - px[:, 0]) * (
        py[:, 1] - py[:, 0]
    )
    ok = np.abs(d) > 1e-12
    faces = np.flatnonzero(ok)
    ends = np.cumsum(counts[faces])
    start = 0
    while start < len(faces):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + RASTER_CHUNK))
        stop = max(stop, start + 1)
        f = faces[start:stop]
        n = counts[f]
        fid = np.repeat(f, n)
        local = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        x = x0[fid] + local % bw[fid]
        y = y0[fid] + local // bw[fid]
        b1 = (
            (x - px[fid, 0]) * (py[fid, 2] - py[fid, 0])
            - (px[fid, 2] - px[fid, 0]) * (y - py[fid, 0])
        ) / d[fid]
        b2 = (
            (px[fid, 1] - px[fid, 0]) * (y - py[fid, 0])
            - (x - px[fid, 0]) * (py[fid, 1] - py[fid, 0])
        ) / d[fid]
        b0 = 1.0 - b1 - b2
        inside = (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
        face_img[y[inside], x[inside]] = fid[inside]
        bary = np.stack([b0, b1, b2], axis=1)[inside]
        bary = np.clip(bary, 0.0, None)
        bary_img[y[inside], x[inside]] = bary / bary.sum(axis=1, keepdims=True)
        start = stop
    return face_img, bary_img


def layout_problem(corner_uvs: np.ndarray, face_img: np.ndarray) -> str:
    """Why a mesh's UVs cannot hold a baked texture ("" when they can): islands that overlap
    (mirrored halves, stacked copies) or lie outside [0, 1] (a tiling layout) leave the
    texels they cover well short of their area. Real layouts that poke a little past the
    square's edge (spot's reach -0.05) pass: the rule is on area, not on extremes."""
    uv = np.asarray(corner_uvs, dtype=np.float64)
    h, w = face_img.shape
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()) * w * h
    covered = int((face_img >= 0).sum())
    if covered < MIN_DISTINCT_COVER * area:
        return (
            "the mesh's UV islands overlap or leave [0, 1] (distinct texels "
            f"{covered / area:.0%} of their area)"
        )
    return ""


def pad_texture(texture: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Fill every empty texel with its nearest covered texel's colour (edge padding).

    Filling the whole background (not a few pixels) keeps every mip level seam-free; one
    exact Euclidean distance transform gives the nearest covered texel for all at once.
    """
    from scipy import ndimage

    if covered.all() or not covered.any():
        return texture
    _, (iy, ix) = ndimage.distance_transform_edt(~covered, return_indices=True)
    return texture[iy, ix]


def xatlas_uvs(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A fresh UV atlas (corner UVs (m, 3, 2), OBJ convention) for a mesh without UVs.

    xatlas keeps triangle order (output triangle i is input triangle i), which we check, so
    the atlas lines up with the spectra's face ids.
    """
    import xatlas

    vmapping, indices, uvs = xatlas.parametrize(
        np.asarray(vertices, np.float32), np.asarray(faces, np.uint32)
    )
    if len(indices) != len(faces) or not np.array_equal(vmapping[indices], faces):
        raise TextureError("xatlas reordered the triangles; cannot align the atlas")
    return uvs[indices].astype(np.float64)


def bake_texture(
    spectra: Any,
    kernelset: Any,
    mesh: Any = None,
    resolution: int = 1024,
    device: Any = None,
    progress: Progress | None = None,
) -> Bake:
    """Bake ``kernelset`` into a square texture on ``mesh``'s UVs (or an xatlas atlas)."""
    from hktex_engine.kernels.query import AlbedoQuery

    if resolution < 4 or resolution > 16384:
        raise ValueError("resolution must be in [4, 16384]")
    faces = np.asarray(spectra.faces, dtype=np.int64)
    if mesh is not None and mesh.content_hash != spectra.mesh_hash:
        raise SpectraError("the spectra were computed for another mesh than the one to bake")
    reason = "the mesh has no UVs"
    if mesh is not None and mesh.corner_uvs is not None:
        corner_uvs, atlas = np.asarray(mesh.corner_uvs, np.float64), "mesh"
        face_img, bary_img = rasterize_uv(corner_uvs, resolution, resolution)
        reason = layout_problem(corner_uvs, face_img)
    if reason:
        # A texture holds one colour per texel: tiling or overlapping UVs would give faces
        # with different kernel colours the same texels, so the bake gets its own layout.
        corner_uvs, atlas = xatlas_uvs(spectra.vertices, faces), "xatlas"
        check_cancel(progress)
        face_img, bary_img = rasterize_uv(corner_uvs, resolution, resolution)
    covered = face_img >= 0
    if not covered.any():
        raise TextureError("no texel is covered by a triangle: are the UVs inside [0, 1]?")
    check_cancel(progress)
    query = AlbedoQuery(spectra, kernelset, device=device)
    colors = query.colors(face_img[covered], bary_img[covered], progress=progress)
    texture = np.zeros((resolution, resolution, 3), dtype=np.float32)
    texture[covered] = np.asarray(colors, dtype=np.float32)
    texture = pad_texture(texture, covered)
    return Bake(
        texture=np.clip(texture, 0.0, 1.0),
        corner_uvs=corner_uvs,
        coverage=float(covered.mean()),
        atlas=atlas,
        atlas_reason="" if atlas == "mesh" else reason,
    )


def vertex_colors(spectra: Any, kernelset: Any, device: Any = None) -> np.ndarray:
    """sRGB colour (n, 3) at every vertex: the lighter export, interpolated by any viewer."""
    from hktex_engine.kernels.query import AlbedoQuery

    faces = np.asarray(spectra.faces, dtype=np.int64)
    n = len(spectra.vertices)
    # one incident face per vertex and the matching unit barycentric
    face_of = np.empty(n, dtype=np.int64)
    corner_of = np.empty(n, dtype=np.int64)
    flat = faces.ravel()
    face_of[flat] = np.repeat(np.arange(len(faces)), 3)
    corner_of[flat] = np.tile(np.arange(3), len(faces))
    bary = np.eye(3)[corner_of]
    return np.asarray(AlbedoQuery(spectra, kernelset, device=device).colors(face_of, bary))


# --------------------------------------------------------------------------- files


def _u8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, texture: np.ndarray) -> Path:
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(_u8(texture), mode="RGB").save(path, format="PNG")
    return path


def _split_corners(
    faces: np.ndarray, corner_uvs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices duplicated only where UVs differ (seams): (source vertex, uv, new faces)."""
    keys = np.concatenate(
        [faces.reshape(-1, 1).astype(np.float64), corner_uvs.reshape(-1, 2)], axis=1
    )
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    return uniq[:, 0].astype(np.int64), uniq[:, 1:], inverse.reshape(-1, 3)


def _file_vertices(spectra: Any) -> np.ndarray:
    return (np.asarray(spectra.vertices, np.float64) - np.asarray(spectra.translation)) / float(
        spectra.scale
    )


def textured_trimesh(spectra: Any, bake: Bake) -> Any:
    """A trimesh with the baked texture (PBR base colour), in the mesh file's units."""
    import trimesh
    from PIL import Image

    faces = np.asarray(spectra.faces, dtype=np.int64)
    src, uv, new_faces = _split_corners(faces, bake.corner_uvs)
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(_u8(bake.texture), mode="RGB"),
        metallicFactor=0.0,
        roughnessFactor=1.0,
    )
    visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    return trimesh.Trimesh(
        vertices=_file_vertices(spectra)[src], faces=new_faces, visual=visual, process=False
    )


def colored_trimesh(spectra: Any, colors: np.ndarray) -> Any:
    """A trimesh with per-vertex sRGB colours, in the mesh file's units."""
    import trimesh

    rgba = np.concatenate([_u8(colors), np.full((len(colors), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(
        vertices=_file_vertices(spectra),
        faces=np.asarray(spectra.faces, dtype=np.int64),
        vertex_colors=rgba,
        process=False,
    )


def write_glb(path: str | os.PathLike, mesh: Any) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(mesh.export(file_type="glb"))
    return path


def write_obj(
    path: str | os.PathLike, spectra: Any, bake: Bake | None, colors: np.ndarray | None = None
) -> Path:
    """OBJ + MTL + PNG (texture), or an OBJ with ``v x y z r g b`` vertex colours.

    Written by hand because the file names must be predictable (OBJ.mtl, OBJ.png beside the
    OBJ) and the faces must stay in the spectra's order with per-corner UVs (``f v/vt``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    V = _file_vertices(spectra)
    F = np.asarray(spectra.faces, dtype=np.int64) + 1
    lines = ["# HKTex bake"]
    if bake is not None:
        mtl, png = path.with_suffix(".mtl"), path.with_suffix(".png")
        write_png(png, bake.texture)
        mtl.write_text(f"newmtl hktex\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {png.name}\n")
        lines += [f"mtllib {mtl.name}", "usemtl hktex"]
    if colors is not None:
        vc = np.concatenate([V, np.clip(colors, 0, 1)], axis=1)
        lines += [f"v {a:.9g} {b:.9g} {c:.9g} {r:.6f} {g:.6f} {bb:.6f}" for a, b, c, r, g, bb in vc]
    else:
        lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in V]
    if bake is not None:
        uv = bake.corner_uvs.reshape(-1, 2)
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
        t = np.arange(1, len(uv) + 1).reshape(-1, 3)
        lines += [
            f"f {a}/{ta} {b}/{tb} {c}/{tc}"
            for (a, b, c), (ta, tb, tc) in zip(F.tolist(), t.tolist(), strict=True)
        ]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in F.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return path
