"""Mesh input, validation and normalisation (ALGORITHM.md 'Normalisation').

A :class:`Mesh` is what every other module consumes: vertices merged by position and
normalised (centroid at the origin, largest bounding-box side 2), faces in the input file's
face order, optional per-corner UVs and albedo texture kept for UV fitting, and a content hash
of the canonical geometry that identifies it across uploads and caches.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from PIL import Image
from scipy.sparse.csgraph import connected_components

from hktex_engine.errors import (
    DegenerateFacesError,
    DisconnectedMeshError,
    EmptyMeshError,
    NonFiniteError,
    NonManifoldError,
    TextureError,
    TooManyVerticesError,
    UnreadableMeshError,
)

if TYPE_CHECKING:
    import trimesh

    from hktex_engine.geometry.atlas import Appearance


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


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------

#: The largest mesh (vertices after merging) the engine and CLI accept unless told otherwise
#: (the service sets its own, 60,000 by default, for a shared machine). Measured on two cores:
#: the default spectra of a 139,650-vertex mesh in 174 s at 1.9 GB peak, and a default
#: `hktex fit` of a 128,000-vertex torus (spectra cached) in 8 min 40 s at 2.9 GB peak.
DEFAULT_MAX_VERTICES = 150_000

#: Bumped whenever the canonical geometry behind :attr:`Mesh.content_hash` changes meaning.
HASH_VERSION = "hktex-mesh-v1"

#: A face whose area is below this fraction of (largest bounding-box side)^2 is degenerate:
#: its cotangent weights are unbounded and the FEM matrices lose definiteness.
DEGENERATE_AREA_FRACTION = 1e-12

#: Before merging, a file may hold at most this many times ``max_vertices`` positions and
#: triangles. A fully seam-split closed mesh has 3F = 6V corner positions, so 8x admits every
#: real mesh while a hostile file is refused before its arrays are built.
RAW_ELEMENT_FACTOR = 8

_TEXTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tga", ".tif", ".tiff", ".webp")

TextureSource = str | os.PathLike | np.ndarray | None


@dataclass
class _RawMesh:
    """What a file parser hands to validation: unmerged positions, triangles in file order."""

    positions: np.ndarray  # (p, 3) float64, file units
    faces: np.ndarray  # (m, 3) int64 into positions
    corner_uvs: np.ndarray | None  # (m, 3, 2) float64
    texture: np.ndarray | None  # (H, W, 3) float32


def load_mesh(
    path: str | os.PathLike,
    texture: TextureSource = None,
    max_vertices: int = DEFAULT_MAX_VERTICES,
    file_type: str | None = None,
    read_texture: bool = True,
) -> Mesh:
    """Read, validate and normalise a triangle mesh file (OBJ, PLY, OFF, GLB, glTF).

    ``texture`` (a path or an array) overrides whatever the file embeds or references; the
    spot and blub OBJs name no material, so their texture must come this way. ``file_type``
    overrides the extension (uploads may arrive under temporary names); without either the
    format is sniffed from the first bytes. ``read_texture=False`` skips decoding the
    texture a file references or embeds (spectra need geometry only, and decoding bob's
    2k PNG was 0.2 s of a 4 s ``hktex spectra``); the content hash is the same either way.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    kind = _detect_format(path, file_type)
    limit = RAW_ELEMENT_FACTOR * max_vertices
    # An explicit texture replaces the file's materials, so they are not read (nor packed).
    own_texture = read_texture and texture is None
    if kind == "obj":
        raw = _read_obj(path, limit, own_texture)
    else:
        _precheck_counts(path, kind, limit)
        raw = _read_with_trimesh(path, kind, own_texture)
    tex = load_texture(texture) if texture is not None else raw.texture
    return _build_mesh(
        raw.positions, raw.faces, raw.corner_uvs, tex, max_vertices, source_name=path.name
    )


def mesh_from_arrays(
    vertices: np.ndarray,
    faces: np.ndarray,
    corner_uvs: np.ndarray | None = None,
    texture: TextureSource = None,
    max_vertices: int = DEFAULT_MAX_VERTICES,
    source_name: str = "",
) -> Mesh:
    """Validate and normalise in-memory arrays exactly as :func:`load_mesh` does a file."""
    try:
        positions = np.asarray(vertices, dtype=np.float64)
        tri = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise UnreadableMeshError(f"vertices/faces are not numeric arrays: {exc}") from None
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise UnreadableMeshError(f"vertices must have shape (n, 3), got {positions.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise UnreadableMeshError(f"faces must have shape (m, 3), got {tri.shape}")
    if not np.issubdtype(tri.dtype, np.integer):
        try:
            as_float = tri.astype(np.float64)
        except (TypeError, ValueError):
            raise UnreadableMeshError("faces must hold integer vertex indices") from None
        if not np.all(np.isfinite(as_float)) or np.any(as_float != np.round(as_float)):
            raise UnreadableMeshError("faces must hold integer vertex indices")
        tri = as_float
    tri = tri.astype(np.int64)
    if tri.size and (tri.min() < 0 or tri.max() >= len(positions)):
        bad = int(np.flatnonzero(((tri < 0) | (tri >= len(positions))).any(axis=1))[0])
        raise UnreadableMeshError(
            f"face {bad} {tri[bad].tolist()} indexes a vertex outside 0..{len(positions) - 1}"
        )
    uvs = None
    if corner_uvs is not None:
        uvs = np.asarray(corner_uvs, dtype=np.float64)
        if uvs.shape != (len(tri), 3, 2):
            raise TextureError(f"corner_uvs must have shape ({len(tri)}, 3, 2), got {uvs.shape}")
    tex = load_texture(texture) if texture is not None else None
    return _build_mesh(positions, tri, uvs, tex, max_vertices, source_name=source_name)


def _detect_format(path: Path, file_type: str | None) -> str:
    """Pick a parser from the explicit type, the extension, or the first bytes."""
    known = {"obj", "ply", "off", "glb", "gltf", "stl"}
    if file_type is not None:
        kind = file_type.lower().lstrip(".")
        if kind not in known:
            raise UnreadableMeshError(f"unsupported mesh format {file_type!r}")
        return kind
    suffix = path.suffix.lower().lstrip(".")
    if suffix in known:
        return suffix
    with open(path, "rb") as fh:
        head = fh.read(64)
    if head.startswith(b"glTF"):
        return "glb"
    if head.startswith(b"ply"):
        return "ply"
    if head.lstrip().startswith((b"OFF", b"COFF", b"NOFF")):
        return "off"
    if head.lstrip().startswith(b"{"):
        return "gltf"
    return "obj"


def _read_obj(path: Path, limit: int, read_texture: bool = True) -> _RawMesh:
    """Strict OBJ reader keeping per-corner UVs in the file's face order.

    Written by hand because trimesh's OBJ loader (5.x) silently accepts truncated lines
    (a 2-coordinate vertex yields an (n, 2) array), raises a bare IndexError on an
    out-of-range index, and in ``maintain_order`` mode drops the UV seams. Regular files take
    a vectorised path; anything irregular (mixed polygon sizes, relative indices, trailing
    comments, a defect) is re-read line by line, which reports defects with line numbers.
    """
    data = path.read_bytes()
    if b"\x00" in data:
        raise UnreadableMeshError(f"{path.name}: binary data in an OBJ file (NUL byte)")
    n_v = data.count(b"\nv ") + data.startswith(b"v ")
    n_f = data.count(b"\nf ") + data.startswith(b"f ")
    if n_v > limit or n_f > limit:
        raise TooManyVerticesError(
            f"{path.name}: {n_v} vertex and {n_f} face statements; more than {limit} cannot "
            "merge to a mesh within the vertex limit"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UnreadableMeshError(
            f"{path.name}: not a text OBJ file (invalid UTF-8 at byte {exc.start})"
        ) from None
    lines = text.splitlines()
    mtllibs = [ln.split(None, 1)[1].strip() for ln in lines if ln.startswith("mtllib ")]
    materials_used = [ln.split()[1] for ln in lines if ln.startswith("usemtl ")]
    fast = _parse_obj_fast(text, lines)
    if fast is not None:
        pos, faces, corner_uvs = fast
    else:
        pos, faces, corner_uvs = _parse_obj_lines(path, lines)
    texture = None
    if read_texture and len(set(materials_used)) > 1:
        texture, corner_uvs = _obj_materials_texture(path, lines, mtllibs, corner_uvs)
    elif read_texture:
        texture = _obj_material_texture(path, mtllibs, materials_used)
    return _RawMesh(pos, faces, corner_uvs, texture)


_OBJ_IGNORED = ("#", "vn ", "vp ", "o ", "g ", "s ", "mtllib ", "usemtl ", "l ")


def _parse_obj_fast(text: str, lines: list[str]):
    """Vectorised parse of a regular OBJ, or None when the file needs the line-by-line reader.

    Regular: every line is empty, ignored, or a ``v x y z`` / ``vt u v [w]`` / ``f`` statement;
    all faces have the same corner count and corner format with positive indices in range;
    no vertex defined after the first face.
    """
    v_lines = [ln for ln in lines if ln.startswith("v ")]
    t_lines = [ln for ln in lines if ln.startswith("vt ")]
    f_lines = [ln for ln in lines if ln.startswith("f ")]
    other = sum(1 for ln in lines if not ln or ln.isspace() or ln.startswith(_OBJ_IGNORED))
    if (
        not v_lines
        or not f_lines
        or len(v_lines) + len(t_lines) + len(f_lines) + other != len(lines)
    ):
        return None
    first_f = text.find("\nf ")
    if text.rfind("\nv ") > first_f or text.rfind("\nvt ") > first_f:
        return None
    pos = _fast_table(v_lines, "v", 4)
    uvs = _fast_table(t_lines, "vt", len(t_lines[0].split())) if t_lines else None
    if pos is None or (t_lines and (uvs is None or uvs.shape[1] < 2)):
        return None
    k = len(f_lines[0].split()) - 1
    tokens = " ".join(f_lines).split()
    if k < 3 or len(tokens) != (k + 1) * len(f_lines):
        return None
    table = np.array(tokens).reshape(-1, k + 1)
    if not np.all(table[:, 0] == "f"):
        return None
    corners = table[:, 1:]
    first = corners[0, 0]
    slashes = first.count("/")
    if not np.all(np.char.count(corners, "/") == slashes) or slashes > 2:
        return None
    no_uv = slashes == 0 or "//" in first
    if "//" in first and not np.all(np.char.find(corners, "//") >= 0):
        return None
    per_corner = 1 if slashes == 0 else (2 if "//" in first else slashes + 1)
    flat = " ".join(corners.ravel()).replace("/", " ").split()
    if len(flat) != corners.size * per_corner:
        return None
    try:
        ints = np.array(flat).astype(np.int64).reshape(len(corners), k, per_corner)
    except ValueError:
        return None
    v_idx = ints[:, :, 0] - 1
    if v_idx.min() < 0 or v_idx.max() >= len(pos):
        return None
    fan = np.arange(1, k - 1)
    order = np.stack([np.zeros_like(fan), fan, fan + 1], axis=1)  # (k - 2, 3) corner slots
    faces = v_idx[:, order].reshape(-1, 3)
    corner_uvs = None
    if not no_uv and uvs is not None:
        t_idx = ints[:, :, 1] - 1
        if t_idx.min() < 0 or t_idx.max() >= len(uvs):
            return None
        corner_uvs = uvs[:, :2][t_idx[:, order].reshape(-1, 3)]
    return pos[:, :3], faces, corner_uvs


def _fast_table(lines: list[str], key: str, width: int) -> np.ndarray | None:
    """Numbers of equally long ``key a b c`` lines as a float array, or None if irregular."""
    tokens = " ".join(lines).split()
    if width < 2 or len(tokens) != width * len(lines):
        return None
    table = np.array(tokens).reshape(-1, width)
    if not np.all(table[:, 0] == key):
        return None
    try:
        return table[:, 1:].astype(np.float64)
    except ValueError:
        return None


def _parse_obj_lines(path: Path, lines: list[str]):
    """Line-by-line OBJ parse: slower, handles every variant, names the line of a defect."""
    positions: list[tuple[float, float, float]] = []
    uvs: list[tuple[float, float]] = []
    tri_v: list[tuple[int, int, int]] = []
    tri_t: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(lines, start=1):
        hash_at = line.find("#")
        if hash_at >= 0:
            line = line[:hash_at]
        tokens = line.split()
        if not tokens:
            continue
        key = tokens[0]
        if key == "v":
            positions.append(_obj_floats(tokens, 3, lineno, "vertex"))
        elif key == "vt":
            uvs.append(_obj_floats(tokens, 2, lineno, "texture coordinate"))
        elif key == "f":
            corners = [_obj_corner(tok, len(positions), len(uvs), lineno) for tok in tokens[1:]]
            if len(corners) < 3:
                raise UnreadableMeshError(
                    f"{path.name} line {lineno}: a face needs at least 3 corners, got {len(corners)}"
                )
            # Fan triangulation keeps a polygon's triangles in place in the face order.
            for i in range(1, len(corners) - 1):
                tri_v.append((corners[0][0], corners[i][0], corners[i + 1][0]))
                tri_t.append((corners[0][1], corners[i][1], corners[i + 1][1]))
    if not positions and not tri_v:
        raise UnreadableMeshError(f"{path.name}: no vertex or face statements (not an OBJ file?)")
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(tri_v, dtype=np.int64).reshape(-1, 3)
    corner_uvs = None
    t_idx = np.asarray(tri_t, dtype=np.int64).reshape(-1, 3)
    if len(faces) and uvs and np.all(t_idx >= 0):
        corner_uvs = np.asarray(uvs, dtype=np.float64)[t_idx]
    return pos, faces, corner_uvs


def _obj_floats(tokens: list[str], count: int, lineno: int, what: str) -> tuple:
    if len(tokens) - 1 < count:
        raise UnreadableMeshError(
            f"line {lineno}: a {what} needs {count} numbers, got {len(tokens) - 1} (truncated file?)"
        )
    try:
        return tuple(float(t) for t in tokens[1 : count + 1])
    except ValueError:
        raise UnreadableMeshError(
            f"line {lineno}: {what} {' '.join(tokens[1 : count + 1])!r} is not numeric"
        ) from None


def _obj_corner(token: str, n_pos: int, n_uv: int, lineno: int) -> tuple[int, int]:
    """Resolve one ``v[/vt[/vn]]`` corner to 0-based (position, uv or -1) indices."""
    parts = token.split("/")
    try:
        v = int(parts[0])
        t = int(parts[1]) if len(parts) > 1 and parts[1] else None
    except ValueError:
        raise UnreadableMeshError(f"line {lineno}: face corner {token!r} is not an index") from None
    v_idx = _obj_index(v, n_pos, lineno, "vertex")
    t_idx = _obj_index(t, n_uv, lineno, "texture coordinate") if t is not None else -1
    return v_idx, t_idx


def _obj_index(i: int, count: int, lineno: int, what: str) -> int:
    """OBJ indices are 1-based; negative ones count back from the latest definition."""
    resolved = i - 1 if i > 0 else count + i
    if i == 0 or not 0 <= resolved < count:
        raise UnreadableMeshError(
            f"line {lineno}: {what} index {i} is out of range (only {count} defined so far)"
        )
    return resolved


def _obj_material_texture(
    path: Path, mtllibs: list[str], materials_used: list[str]
) -> np.ndarray | None:
    """The diffuse map (map_Kd) of the first material the OBJ uses, if any can be found."""
    for lib in mtllibs:
        mtl_path = _inside_folder(path.parent, lib, "mtllib")
        if not mtl_path.is_file():
            continue
        maps = {name: m for name, (m, _) in _mtl_statements(mtl_path).items() if m is not None}
        if not maps:
            continue
        name = next((m for m in materials_used if m in maps), next(iter(maps)))
        return load_texture(_map_file(path, mtl_path, maps[name]))
    return None


def _mtl_statements(mtl_path: Path) -> dict[str, tuple[str | None, tuple | None]]:
    """Each ``newmtl`` of an MTL file: its diffuse map's file name and its ``Kd`` colour."""
    current = None
    out: dict = {}
    for line in mtl_path.read_text(errors="replace").splitlines():
        tokens = line.strip().split()
        if not tokens:
            continue
        if tokens[0] == "newmtl" and len(tokens) > 1:
            current = tokens[1]
            out.setdefault(current, (None, None))
        elif current is not None and tokens[0] == "map_Kd" and len(tokens) > 1:
            if out[current][0] is None:
                out[current] = (_map_name(tokens[1:]), out[current][1])
        elif current is not None and tokens[0] == "Kd" and len(tokens) >= 4:
            try:
                kd = tuple(float(t) for t in tokens[1:4])
            except ValueError:
                raise TextureError(f"{mtl_path.name}: Kd {' '.join(tokens[1:4])!r}") from None
            if not all(np.isfinite(kd)):
                raise TextureError(f"{mtl_path.name}: Kd of {current!r} is not finite")
            out[current] = (out[current][0], tuple(min(max(c, 0.0), 1.0) for c in kd))
    return out


#: Arguments each MTL map option takes (Wavefront's MTL specification; -o, -s and -t take one
#: to three numbers). The file name is what follows the options, spaces included, as Blender
#: and others write it.
_MAP_OPTIONS = {
    **dict.fromkeys(("-blendu", "-blendv", "-bm", "-boost", "-cc", "-clamp"), 1),
    **dict.fromkeys(("-imfchan", "-texres"), 1),
    "-mm": 2,
    **dict.fromkeys(("-o", "-s", "-t"), 3),
}


def _map_name(tokens: list[str]) -> str:
    """The file name of a ``map_Kd`` statement's arguments, its options skipped."""
    i = 0
    while i < len(tokens) - 1 and tokens[i] in _MAP_OPTIONS:
        most, i = _MAP_OPTIONS[tokens[i]], i + 1
        for _ in range(most):
            if i >= len(tokens) - 1 or (most == 3 and not _is_number(tokens[i])):
                break
            i += 1
    return " ".join(tokens[i:])


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _map_file(path: Path, mtl_path: Path, name: str) -> Path:
    """The image a ``map_Kd`` names. Written on Windows it may use backslashes, or an
    absolute path on the author's machine: then the file of that name beside the MTL is what
    the asset shipped (Blender's importer looks there too). Nothing outside the mesh's
    folder is read either way."""
    relative = name.replace("\\", "/")
    beside = _inside_folder(path.parent, str(mtl_path.parent / relative.split("/")[-1]), "map_Kd")
    if relative.startswith("/") or relative[1:3] == ":/":
        if beside.is_file():
            return beside
        raise TextureError(
            f"map_Kd {name!r} points outside the mesh's folder, and no "
            f"{beside.name!r} lies beside {mtl_path.name}"
        )
    image = _inside_folder(path.parent, str(mtl_path.parent / relative), "map_Kd")
    if image.is_file():
        return image
    if beside.is_file():
        return beside
    raise TextureError(f"{mtl_path.name}: map_Kd {name!r} not found")


def _obj_materials_texture(
    path: Path, lines: list[str], mtllibs: list[str], corner_uvs: np.ndarray | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Texture and UVs of an OBJ whose faces use several materials (one atlas when they differ).

    A textured material's ``Kd`` is not applied (exporters write a placeholder there); a
    material without ``map_Kd`` is its ``Kd`` colour, as stored. Faces of a material no MTL
    defines are refused when the materials differ: no colour could be honestly assumed.
    """
    from hktex_engine.geometry.atlas import Appearance, one_texture

    tri_material, names = _obj_triangle_materials(lines)
    statements: dict = {}
    for lib in mtllibs:
        mtl_path = _inside_folder(path.parent, lib, "mtllib")
        if mtl_path.is_file():
            for name, (map_name, kd) in _mtl_statements(mtl_path).items():
                statements.setdefault(name, (mtl_path, map_name, kd))
    appearances, images = [], {}
    for name in names:
        mtl_path, map_name, kd = statements.get(name, (None, None, None))
        if map_name is not None:
            file = _map_file(path, mtl_path, map_name)
            if file not in images:
                images[file] = load_texture(file)
            appearances.append(Appearance(("map", str(file)), image=images[file], name=name))
        else:
            appearances.append(Appearance(("kd", kd), colour=kd, name=name))
    keys = {appearances[i].key for i in np.unique(tri_material) if i >= 0}
    if len(keys) == 1:  # several names, one appearance: read as a single material
        texture = next(a.image for a in appearances if a.key in keys)
        return texture, corner_uvs
    if all(a.image is None for a in appearances):
        # No map at all (the MTL did not come along, as in a REST upload, or holds colours
        # only): untextured, as before; a texture can still be given explicitly.
        return None, corner_uvs
    unknown = sorted({a.name for a in appearances if a.image is None and a.colour is None})
    if np.any(tri_material < 0) or unknown:
        raise TextureError(
            f"{path.name}: faces use several materials, and some have no usemtl or one with "
            f"neither map_Kd nor Kd {unknown}; their colour is unknown"
        )
    uvs = corner_uvs
    if uvs is None:
        uvs = np.full((len(tri_material), 3, 2), np.nan)
    return one_texture(appearances, tri_material, uvs)


def _obj_triangle_materials(lines: list[str]) -> tuple[np.ndarray, list[str]]:
    """Per triangle (in the parsers' fan order), the index into the ``usemtl`` names in force,
    -1 before the first; and those names in order of first use."""
    index: dict[str, int] = {}
    current, per_face, counts = -1, [], []
    for line in lines:
        tokens = line.split("#", 1)[0].split()
        if len(tokens) > 1 and tokens[0] == "usemtl":
            current = index.setdefault(tokens[1], len(index))
        elif tokens and tokens[0] == "f":
            per_face.append(current)
            counts.append(len(tokens) - 3)
    return np.repeat(np.asarray(per_face, dtype=np.int64), counts), list(index)


def _inside_folder(folder: Path, reference: str, what: str) -> Path:
    """Resolve a file named inside a mesh file, refusing any that leaves the mesh's folder.

    A hostile upload could otherwise name ``../../etc/passwd`` or an absolute path as its
    material or texture and make the service read files beyond the upload.
    """
    root = folder.resolve()
    target = (folder / reference).resolve()
    if not target.is_relative_to(root):
        raise TextureError(f"{what} {reference!r} points outside the mesh's folder")
    return target


def _precheck_counts(path: Path, kind: str, limit: int) -> None:
    """Refuse a file whose header declares more elements than can merge within the limit.

    trimesh allocates what a header declares; reading the counts first keeps a large (or
    lying) PLY, OFF or glTF from costing gigabytes before the vertex limit is checked.
    """
    counts = {"ply": _ply_counts, "off": _off_counts, "glb": _gltf_counts, "gltf": _gltf_counts}
    reader = counts.get(kind)
    if reader is None:
        return
    try:
        n_vertices, n_faces = reader(path)
    except (OSError, ValueError, KeyError, TypeError, IndexError, struct.error):
        return  # unparsable headers are trimesh's to reject, with its own message
    if n_vertices > limit or n_faces > limit:
        raise TooManyVerticesError(
            f"{path.name}: declares {n_vertices} vertices and {n_faces} faces; more than "
            f"{limit} cannot merge to a mesh within the vertex limit"
        )


def _ply_counts(path: Path) -> tuple[int, int]:
    with open(path, "rb") as fh:
        head = fh.read(65536)
    header = head.split(b"end_header", 1)[0].decode("ascii", errors="replace")
    counts = {"vertex": 0, "face": 0}
    for line in header.splitlines():
        tokens = line.split()
        if len(tokens) == 3 and tokens[0] == "element" and tokens[1] in counts:
            counts[tokens[1]] = int(tokens[2])
    return counts["vertex"], counts["face"]


def _off_counts(path: Path) -> tuple[int, int]:
    with open(path, "rb") as fh:
        head = fh.read(65536).decode("ascii", errors="replace")
    tokens: list[str] = []
    for line in head.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            tokens += line.split()
        if len(tokens) >= 3:
            break
    if tokens and tokens[0].endswith("OFF"):
        tokens = tokens[1:]
    return int(tokens[0]), int(tokens[1])


def _gltf_document(path: Path) -> dict:
    """The JSON of a glTF file, or of a GLB's first chunk (at most 64 MB of it)."""
    with open(path, "rb") as fh:
        if fh.read(4) == b"glTF":
            fh.read(8)
            chunk_length = struct.unpack("<I", fh.read(4))[0]
            fh.read(4)
            return json.loads(fh.read(min(chunk_length, 64 << 20)))
        fh.seek(0)
        return json.loads(fh.read(64 << 20))


def _gltf_texture_problem(doc: dict) -> str:
    """What in a glTF's base colour textures trimesh would silently get wrong ("" if nothing):
    trimesh reads TEXCOORD_0 as stored, ignores ``KHR_texture_transform``, and decodes only
    images PIL can open from a texture's ``source`` (KTX2/Basis textures come back empty,
    which would read as the factor alone)."""
    textures = doc.get("textures", [])
    for i, material in enumerate(doc.get("materials", [])):
        ref = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if not isinstance(ref, dict):
            continue
        name = material.get("name", f"#{i}")
        if ref.get("texCoord", 0) != 0:
            return f"material {name!r} reads its base colour from TEXCOORD_{ref['texCoord']}"
        if "KHR_texture_transform" in ref.get("extensions", {}):
            return f"material {name!r} moves its base colour with KHR_texture_transform"
        index = ref.get("index")
        texture = textures[index] if isinstance(index, int) and index < len(textures) else {}
        if "source" not in texture:
            return f"material {name!r} has a base colour texture in an extension-only format"
    return ""


def _gltf_counts(path: Path) -> tuple[int, int]:
    doc = _gltf_document(path)
    accessors = doc.get("accessors", [])

    def mesh_counts(mesh: dict) -> tuple[int, int]:
        verts = faces = 0
        for prim in mesh.get("primitives", []):
            verts += int(accessors[prim["attributes"]["POSITION"]]["count"])
            if "indices" in prim:
                faces += int(accessors[prim["indices"]]["count"]) // 3
        return verts, faces

    per_mesh = [mesh_counts(m) for m in doc.get("meshes", [])]
    used = [n["mesh"] for n in doc.get("nodes", []) if "mesh" in n] or range(len(per_mesh))
    return sum(per_mesh[i][0] for i in used), sum(per_mesh[i][1] for i in used)


def _read_with_trimesh(path: Path, kind: str, read_texture: bool = True) -> _RawMesh:
    """PLY, OFF, STL, GLB and glTF through trimesh, unprocessed so face order is kept.

    trimesh is imported here, not at the top: it costs ~0.3 s (networkx, scipy.spatial), and
    OBJ, the common case, is read by our own parser (``hktex spectra`` on a 3-9k-vertex
    OBJ takes a few seconds in all, so that was a tenth of it).
    """
    import trimesh

    if read_texture and kind in ("glb", "gltf"):
        try:
            problem = _gltf_texture_problem(_gltf_document(path))
        except (OSError, ValueError, TypeError, AttributeError, struct.error):
            problem = ""  # an unparsable document is trimesh's to reject, with its message
        if problem:
            raise TextureError(
                f"{path.name}: {problem}, which this reader does not follow; bake the asset's "
                "base colour to one texture on TEXCOORD_0 first"
            )
    try:
        loaded = trimesh.load(str(path), file_type=kind, process=False)
    except (MemoryError, RecursionError):
        raise UnreadableMeshError(f"{path.name}: malformed {kind.upper()} file") from None
    except Exception as exc:  # trimesh raises whatever its parsers hit on a bad file
        message = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
        raise UnreadableMeshError(
            f"{path.name}: cannot parse as {kind.upper()}: {message}"
        ) from None
    if isinstance(loaded, trimesh.Scene):
        geometries = _scene_meshes(loaded)
    elif isinstance(loaded, trimesh.Trimesh):
        geometries = [loaded]
    else:
        geometries = []
    if not geometries:
        raise UnreadableMeshError(f"{path.name}: no triangle mesh found in the {kind.upper()} file")
    positions, faces, uv_parts, appearances = [], [], [], []
    image_cache: dict[int, tuple[np.ndarray, str]] = {}
    offset = 0
    for g in geometries:
        v = np.asarray(g.vertices, dtype=np.float64)
        f = np.asarray(g.faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or (f.size and f.shape[1] != 3):
            raise UnreadableMeshError(f"{path.name}: malformed vertex or face arrays")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise UnreadableMeshError(f"{path.name}: a face indexes a vertex out of range")
        positions.append(v)
        faces.append(f.reshape(-1, 3) + offset)
        offset += len(v)
        uv = getattr(g.visual, "uv", None)
        uv_parts.append(
            np.full((len(f), 3, 2), np.nan)
            if uv is None or len(uv) != len(v)
            else np.asarray(uv, dtype=np.float64)[f].reshape(-1, 3, 2)
        )
        if read_texture:
            appearances.append(_trimesh_appearance(g, image_cache))
    corner_uvs = np.concatenate(uv_parts, axis=0)
    texture = None
    if read_texture:
        from hktex_engine.geometry.atlas import one_texture

        # Instances of one geometry carry equal appearances: one tile serves them all.
        first: dict[tuple, int] = {}
        distinct = []
        for a in appearances:
            if a.key not in first:
                first[a.key] = len(distinct)
                distinct.append(a)
        per_face = np.repeat([first[a.key] for a in appearances], [len(f) for f in faces])
        texture, atlas_uvs = one_texture(distinct, per_face, corner_uvs)
        corner_uvs = atlas_uvs if texture is not None else corner_uvs
    if not np.all(np.isfinite(corner_uvs)):
        corner_uvs = None
    return _RawMesh(np.concatenate(positions), np.concatenate(faces), corner_uvs, texture)


def _scene_meshes(scene: trimesh.Scene) -> list[trimesh.Trimesh]:
    """Every mesh instance of a scene, with its node transform applied, in graph order."""
    import trimesh

    out = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry.get(name)
        if not isinstance(geom, trimesh.Trimesh):
            continue
        geom = geom.copy()
        geom.apply_transform(transform)
        out.append(geom)
    return out


def _trimesh_appearance(
    geom: trimesh.Trimesh, cache: dict[int, tuple[np.ndarray, str]]
) -> Appearance:
    """A geometry's base colour: its material's image times ``baseColorFactor``, or the factor
    alone (glTF's default material is white); ``cache`` (per load) converts and hashes each
    image once (the hash tells copies of one image on several instances apart from others)."""
    from hktex_engine.geometry.atlas import Appearance, linear_to_srgb

    material = getattr(geom.visual, "material", None)
    image = getattr(material, "baseColorTexture", None)
    if image is None:
        image = getattr(material, "image", None)
    factor = getattr(material, "baseColorFactor", None)
    rgb = (1.0, 1.0, 1.0) if factor is None else tuple(float(c) / 255.0 for c in factor[:3])
    name = str(getattr(material, "name", "") or "")
    if image is None:
        colour = tuple(float(c) for c in linear_to_srgb(np.asarray(rgb)))
        return Appearance(("colour", colour), colour=colour, name=name)
    key = id(image)  # the image stays referenced by ``geom`` for the whole load
    if key not in cache:
        pixels = load_texture(np.asarray(image.convert("RGB")))
        cache[key] = (pixels, texture_hash(pixels))
    pixels, digest = cache[key]
    return Appearance(("image", digest, rgb), image=pixels, factor=rgb, name=name)


# ---------------------------------------------------------------------------------------------
# Textures
# ---------------------------------------------------------------------------------------------


def load_texture(source: str | os.PathLike | np.ndarray) -> np.ndarray:
    """An albedo image as float32 (H, W, 3) in [0, 1]: alpha dropped, grey expanded to RGB.

    Values are kept as stored (sRGB), which is what EVALUATION.md measures PSNR in.
    """
    if isinstance(source, np.ndarray):
        return _texture_from_array(source)
    path = Path(source)
    if not path.is_file():
        raise TextureError(f"texture file not found: {path}")
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(img, dtype=np.float64)
                arr = arr / (65535.0 if arr.max() > 255 else 255.0)
            else:
                arr = np.asarray(img.convert("RGB"))
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise TextureError(f"cannot read texture {path.name}: {exc}") from None
    return _texture_from_array(arr)


def _texture_from_array(arr: np.ndarray) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise TextureError(f"texture must be (H, W), (H, W, 1|3|4), got shape {arr.shape}")
    if arr.shape[2] in (1, 2):  # grey or grey + alpha
        arr = np.repeat(arr[:, :, :1], 3, axis=2)
    arr = arr[:, :, :3]
    if arr.dtype == np.uint8:
        out = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        out = arr.astype(np.float32) / 65535.0
    elif np.issubdtype(arr.dtype, np.floating):
        out = arr.astype(np.float32)
        if not np.all(np.isfinite(out)) or out.min() < 0.0 or out.max() > 1.0:
            raise TextureError("a float texture must hold finite values in [0, 1]")
    else:
        raise TextureError(f"unsupported texture dtype {arr.dtype}")
    return np.ascontiguousarray(out)


def texture_hash(texture: np.ndarray | None) -> str | None:
    """SHA-256 of a texture's float32 pixels and shape (None without texture).

    Kept apart from :attr:`Mesh.content_hash` on purpose: spectra depend on geometry only, so
    re-texturing a mesh must hit the same spectra cache entry.
    """
    if texture is None:
        return None
    tex = np.ascontiguousarray(texture, dtype="<f4")
    h = hashlib.sha256(f"hktex-texture-v1:{tex.shape}".encode())
    h.update(tex.tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------
# Merge, validate, normalise
# ---------------------------------------------------------------------------------------------


def _build_mesh(
    positions: np.ndarray,
    faces: np.ndarray,
    corner_uvs: np.ndarray | None,
    texture: np.ndarray | None,
    max_vertices: int,
    source_name: str,
) -> Mesh:
    """Validate raw arrays, merge by position, normalise and hash."""
    where = f"{source_name}: " if source_name else ""
    if len(faces) == 0:
        raise EmptyMeshError(f"{where}the mesh has no triangles")
    if not np.all(np.isfinite(positions)):
        bad = int(np.flatnonzero(~np.isfinite(positions).all(axis=1))[0])
        raise NonFiniteError(f"{where}vertex {bad} has a non-finite coordinate {positions[bad]}")
    if corner_uvs is not None and not np.all(np.isfinite(corner_uvs)):
        raise TextureError(f"{where}texture coordinates contain NaN or infinity")
    vertices, tri = merge_by_position(positions, faces)
    if len(vertices) > max_vertices:
        raise TooManyVerticesError(
            f"{where}{len(vertices)} vertices after merging by position exceeds the limit "
            f"of {max_vertices}"
        )
    validate_topology(vertices, tri, where)
    centroid = vertices.mean(axis=0)
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    scale = 2.0 / extent
    translation = -scale * centroid
    return Mesh(
        vertices=vertices * scale + translation,
        faces=tri,
        scale=scale,
        translation=translation,
        content_hash=geometry_hash(vertices, tri),
        corner_uvs=corner_uvs,
        texture=texture,
        source_name=source_name,
    )


def merge_by_position(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weld vertices with identical coordinates; number them by first use in the face list.

    UV seams and glTF attribute splits duplicate positions; the surface's topology needs them
    welded. Numbering by first appearance in ``faces.ravel()`` makes the result depend only on
    the triangles (in file order), not on how a format orders or splits its vertex list, and
    drops unreferenced vertices (they would make the mass matrix singular).
    """
    _, key = np.unique(positions, axis=0, return_inverse=True)
    corner_keys = key.reshape(-1)[faces.reshape(-1)]
    uniq_keys, first = np.unique(corner_keys, return_index=True)
    order = np.argsort(first, kind="stable")
    new_id = np.empty(key.max() + 1, dtype=np.int64)
    new_id[uniq_keys[order]] = np.arange(len(order))
    representative = np.empty(key.max() + 1, dtype=np.int64)
    representative[key.reshape(-1)] = np.arange(len(positions))
    vertices = positions[representative[uniq_keys[order]]]
    return np.ascontiguousarray(vertices), new_id[corner_keys].reshape(-1, 3)


def geometry_hash(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 of the canonical geometry: merged file-unit vertices as float32, faces as int64.

    float32 because that is what binary formats (GLB, most PLY) store: the same surface read
    from an OBJ's decimal text and from a float32 PLY must hash alike. File units rather than
    normalised ones, since the stored transform (and so queries in file units) depends on them.
    """
    h = hashlib.sha256(f"{HASH_VERSION}:{len(vertices)}:{len(faces)}".encode())
    h.update(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


def validate_topology(vertices: np.ndarray, faces: np.ndarray, where: str = "") -> None:
    """Raise the specific error for the first defect: degenerate, non-manifold, disconnected."""
    _check_degenerate(vertices, faces, where)
    edges, edge_faces = _check_manifold_edges(faces, where)
    _check_manifold_vertices(vertices, faces, edges, edge_faces, where)
    _check_connected(len(vertices), faces, where)


def _check_degenerate(vertices: np.ndarray, faces: np.ndarray, where: str) -> None:
    repeated = (
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    )
    if repeated.any():
        f = int(np.flatnonzero(repeated)[0])
        raise DegenerateFacesError(
            f"{where}face {f} repeats a vertex {faces[f].tolist()} "
            f"({int(repeated.sum())} such faces; vertices merged by position)"
        )
    p = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    tiny = area <= DEGENERATE_AREA_FRACTION * extent**2
    if tiny.any():
        f = int(np.flatnonzero(tiny)[0])
        raise DegenerateFacesError(
            f"{where}face {f} has (near-)zero area {area[f]:.3g} "
            f"({int(tiny.sum())} such faces; mesh size {extent:.3g})"
        )


def _check_manifold_edges(faces: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Every undirected edge in at most two faces; returns sorted corner edges and their faces."""
    m = len(faces)
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    edges = np.sort(half, axis=1)
    edge_faces = np.repeat(np.arange(m), 3)
    uniq, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    over = counts > 2
    if over.any():
        e = int(np.flatnonzero(over)[0])
        owners = edge_faces[inverse.reshape(-1) == e]
        raise NonManifoldError(
            f"{where}edge ({uniq[e, 0]}, {uniq[e, 1]}) is shared by {counts[e]} faces "
            f"(faces {', '.join(map(str, owners[:6]))})"
        )
    return edges, edge_faces


def _check_manifold_vertices(
    vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray, edge_faces: np.ndarray, where: str
) -> None:
    """The faces around each vertex must form one fan (one edge-connected component).

    Nodes of the graph are face corners (face, vertex); two corners of the same vertex are
    linked when their faces share an edge through that vertex. A vertex whose corners fall in
    more than one component is a bow-tie (or two cones touching at a tip).
    """
    m = len(faces)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    se = edges[order]
    same = np.all(se[1:] == se[:-1], axis=1)
    i = np.flatnonzero(same)
    f1, f2 = edge_faces[order][i], edge_faces[order][i + 1]
    a, b = se[i, 0], se[i, 1]
    corner_of = _corner_lookup(faces)
    rows = np.concatenate([corner_of(f1, a), corner_of(f1, b)])
    cols = np.concatenate([corner_of(f2, a), corner_of(f2, b)])
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * m, 3 * m))
    _, label = connected_components(graph, directed=False)
    corner_vertex = faces.reshape(-1)
    pairs = np.unique(np.stack([corner_vertex, label], axis=1), axis=0)
    fans = np.bincount(pairs[:, 0], minlength=len(vertices))
    if np.any(fans > 1):
        v = int(np.flatnonzero(fans > 1)[0])
        raise NonManifoldError(
            f"{where}vertex {v} at {np.round(vertices[v], 6).tolist()} is non-manifold: "
            f"its faces form {fans[v]} separate fans"
        )


def _corner_lookup(faces: np.ndarray):
    """Map (face, vertex) pairs to corner ids 3 * face + slot."""

    def corner(f: np.ndarray, v: np.ndarray) -> np.ndarray:
        slot = np.argmax(faces[f] == v[:, None], axis=1)
        return 3 * f + slot

    return corner


def _check_connected(n: int, faces: np.ndarray, where: str) -> None:
    rows = faces.reshape(-1)
    cols = np.roll(faces, -1, axis=1).reshape(-1)
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    count, label = connected_components(graph, directed=False)
    if count > 1:
        sizes = np.bincount(label[faces[:, 0]], minlength=count)
        sizes = np.sort(sizes)[::-1]
        shown = ", ".join(map(str, sizes[:5])) + (", ..." if count > 5 else "")
        raise DisconnectedMeshError(
            f"{where}the mesh has {count} connected components (faces per component: {shown}); "
            "HKTex needs one connected surface"
        )
