"""Mesh loading, validation, normalisation and hashing (hktex_engine.geometry.mesh)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

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
from hktex_engine.evaluation.synthetic import (
    grid_patch,
    icosphere,
    textured_demo,
    write_textured_obj,
)
from hktex_engine.geometry.mesh import load_mesh, load_texture, mesh_from_arrays, texture_hash

# Two triangles of a unit square, a quad version, and a tetrahedron-like open fan.
SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def write(tmp_path, name: str, text: str | bytes):
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def obj_text(vertices, faces) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, dtype=float).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- hostile inputs


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb", ".off", ""])
def test_garbage_bytes_are_unreadable(tmp_path, suffix):
    data = np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    path = write(tmp_path, "garbage" + suffix, data)
    with pytest.raises(UnreadableMeshError):
        load_mesh(path)


def test_text_garbage_obj_is_unreadable(tmp_path):
    path = write(tmp_path, "words.obj", "hello world\nthis is not a mesh\n")
    with pytest.raises(UnreadableMeshError, match="no vertex or face"):
        load_mesh(path)


def test_truncated_obj_reports_the_line(tmp_path):
    path = write(tmp_path, "trunc.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1\n")
    with pytest.raises(UnreadableMeshError, match="line 4"):
        load_mesh(path)


def test_truncated_obj_face(tmp_path):
    path = write(tmp_path, "trunc.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2")
    with pytest.raises(UnreadableMeshError, match="at least 3 corners"):
        load_mesh(path)


def test_truncated_binary_ply(tmp_path):
    v, f = icosphere(1)
    data = trimesh.Trimesh(v, f, process=False).export(file_type="ply")
    path = write(tmp_path, "trunc.ply", data[: len(data) // 2])
    with pytest.raises(UnreadableMeshError):
        load_mesh(path)


@pytest.mark.parametrize("index", ["7", "0", "-9"])
def test_out_of_range_obj_index(tmp_path, index):
    path = write(tmp_path, "oor.obj", f"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 {index}\n")
    with pytest.raises(UnreadableMeshError, match="out of range"):
        load_mesh(path)


def test_out_of_range_array_index():
    with pytest.raises(UnreadableMeshError, match="face 1"):
        mesh_from_arrays(SQUARE_V, np.array([[0, 1, 2], [0, 2, 4]]))


@pytest.mark.parametrize(
    "faces", [np.array([["a", "b", "c"]]), np.array([[0, 1, 2.5]]), np.zeros((2, 4), int)]
)
def test_malformed_face_arrays(faces):
    with pytest.raises(UnreadableMeshError):
        mesh_from_arrays(np.eye(3), faces)


def test_empty_mesh(tmp_path):
    path = write(tmp_path, "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(EmptyMeshError):
        load_mesh(path)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "nope.obj")


def test_nan_vertex(tmp_path):
    path = write(tmp_path, "nan.obj", "v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(NonFiniteError, match="vertex 1"):
        load_mesh(path)


def test_repeated_index_face():
    with pytest.raises(DegenerateFacesError, match="face 1 repeats"):
        mesh_from_arrays(SQUARE_V, np.array([[0, 1, 2], [0, 2, 2]]))


def test_repeated_index_after_merging_by_position():
    v = np.vstack([SQUARE_V, SQUARE_V[2]])  # vertex 4 duplicates vertex 2's position
    with pytest.raises(DegenerateFacesError):
        mesh_from_arrays(v, np.array([[0, 1, 2], [0, 2, 3], [1, 2, 4]]))


def test_zero_area_face():
    v = np.vstack([SQUARE_V, [[2.0, 0.0, 0.0]]])
    # (0, 1, 4) is collinear along the x axis: zero area.
    with pytest.raises(DegenerateFacesError, match="zero area"):
        mesh_from_arrays(v, np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4]]))


def test_edge_shared_by_three_faces():
    v = np.vstack([SQUARE_V, [[0.5, 0.5, 1.0]]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4]])
    with pytest.raises(NonManifoldError, match=r"shared by 3 faces"):
        mesh_from_arrays(v, faces)


def test_bow_tie_vertex():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0]], dtype=float)
    with pytest.raises(NonManifoldError, match="vertex 0 .* 2 separate fans"):
        mesh_from_arrays(v, np.array([[0, 1, 2], [0, 3, 4]]))


def test_two_closed_cones_touching_at_a_tip():
    """No boundary edges at all, so a boundary-count test would miss it; the fan test does not."""
    sv, sf = icosphere(0)
    # Point reflection through vertex 0: a second sphere touching the first only there.
    shifted = 2.0 * sv[0] - sv
    v = np.vstack([sv, shifted])
    f = np.vstack([sf, sf + len(sv)])
    with pytest.raises(NonManifoldError, match="separate fans"):
        mesh_from_arrays(v, f)


def test_two_components():
    v = np.vstack([SQUARE_V, SQUARE_V + [5.0, 0.0, 0.0]])
    f = np.vstack([SQUARE_F, SQUARE_F + 4])
    with pytest.raises(DisconnectedMeshError, match="2 connected components"):
        mesh_from_arrays(v, f)


def test_too_many_vertices_counts_after_merging():
    v, f = grid_patch(6, 6)  # 36 vertices
    with pytest.raises(TooManyVerticesError, match="36 vertices"):
        mesh_from_arrays(v, f, max_vertices=35)
    assert mesh_from_arrays(v, f, max_vertices=36).n_vertices == 36


def test_open_boundary_is_allowed():
    v, f = grid_patch(4, 3)
    assert mesh_from_arrays(v, f).n_faces == 12


# --------------------------------------------------------------------------- format details


def test_quads_are_triangulated_in_place_with_corner_uvs(tmp_path):
    text = (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
        "vt 0 0\nvt 0.5 0\nvt 0.5 1\nvt 0 1\nvt 1 0\nvt 1 1\n"
        "f 1/1 2/2 4/4\n"  # triangle
        "f 2/2 5/5 6/6 3/3\n"  # quad -> (2,5,6), (2,6,3)
        "f 2/2 3/3 4/4\n"
    )
    mesh = load_mesh(write(tmp_path, "mixed.obj", text))
    assert mesh.n_faces == 4
    file_v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    expect = [[0, 1, 3], [1, 4, 5], [1, 5, 2], [1, 2, 3]]
    got = mesh.to_file_units(mesh.vertices)[mesh.faces]
    np.testing.assert_allclose(got, file_v[expect], atol=1e-12)
    np.testing.assert_allclose(mesh.corner_uvs[1], [[0.5, 0], [1, 0], [1, 1]])
    np.testing.assert_allclose(mesh.corner_uvs[2], [[0.5, 0], [1, 1], [0.5, 1]])


def test_negative_obj_indices(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\nv 0 1 0\nf 1 3 -1\n"
    mesh = load_mesh(write(tmp_path, "neg.obj", text))
    ref = mesh_from_arrays(SQUARE_V, SQUARE_F)
    assert mesh.content_hash == ref.content_hash


def test_seam_vertices_are_merged_but_uvs_kept():
    v, f, uv, tex = textured_demo(subdivisions=1, texture_size=32)
    sphere_v, _ = icosphere(1)
    # Split every corner into its own vertex (as a glTF export would), then load.
    split_v = v[f].reshape(-1, 3)
    split_f = np.arange(len(split_v)).reshape(-1, 3)
    mesh = mesh_from_arrays(split_v, split_f, uv, tex)
    assert mesh.n_vertices == len(sphere_v)
    np.testing.assert_array_equal(mesh.corner_uvs, uv)
    assert mesh.content_hash == mesh_from_arrays(v, f).content_hash


def test_normalisation():
    rng = np.random.default_rng(0)
    v, f = icosphere(2)
    file_v = v * [3.0, 1.0, 0.5] + rng.normal(size=3) * 10
    mesh = mesh_from_arrays(file_v, f)
    np.testing.assert_allclose(mesh.vertices.mean(axis=0), 0.0, atol=1e-12)
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    assert extent.max() == pytest.approx(2.0)
    # Vertices are renumbered (first use in the face list); faces keep the file's order.
    np.testing.assert_allclose(
        mesh.vertices[mesh.faces], mesh.scale * file_v[f] + mesh.translation, atol=1e-12
    )
    np.testing.assert_allclose(mesh.to_file_units(mesh.vertices)[mesh.faces], file_v[f], atol=1e-9)


def test_hash_is_format_and_whitespace_independent(tmp_path):
    v, f = icosphere(1)
    v = v.astype(np.float32).astype(np.float64)  # what a float32 PLY stores
    obj = write(tmp_path, "a.obj", obj_text(v, f))
    messy = write(tmp_path, "b.obj", "# comment\n\n" + obj_text(v, f).replace(" ", "   "))
    ply = tmp_path / "c.ply"
    trimesh.Trimesh(v, f, process=False).export(ply)
    off = tmp_path / "d.off"
    trimesh.Trimesh(v, f, process=False).export(off)
    hashes = {load_mesh(p).content_hash for p in (obj, messy, ply, off)}
    assert len(hashes) == 1
    moved = v.copy()
    moved[0] += 1e-3
    assert mesh_from_arrays(moved, f).content_hash not in hashes


def test_texture_does_not_change_the_geometry_hash():
    v, f, uv, tex = textured_demo(subdivisions=1, texture_size=32)
    a = mesh_from_arrays(v, f, uv, tex)
    b = mesh_from_arrays(v, f, uv, 1.0 - tex)
    assert a.content_hash == b.content_hash
    assert texture_hash(a.texture) != texture_hash(b.texture)


def test_obj_with_mtl_texture_round_trip(tmp_path):
    v, f, uv, tex = textured_demo(subdivisions=1, texture_size=32)
    path = write_textured_obj(tmp_path / "demo.obj", v, f, uv, tex)
    mesh = load_mesh(path)
    assert mesh.has_texture
    np.testing.assert_array_equal(mesh.corner_uvs, uv)
    np.testing.assert_allclose(mesh.texture, tex, atol=0.5 / 255 + 1e-6)
    assert mesh.content_hash == mesh_from_arrays(v, f).content_hash
    bare = load_mesh(path, read_texture=False)  # what spectra read: geometry, UVs, no image
    assert bare.texture is None and bare.content_hash == mesh.content_hash
    np.testing.assert_array_equal(bare.corner_uvs, uv)


def test_glb_keeps_uv_convention(tmp_path):
    """glTF stores v downwards; the loader must hand back OBJ-convention corner UVs."""
    v, f, uv, tex = textured_demo(subdivisions=1, texture_size=32)
    split_v = v[f].reshape(-1, 3)
    split_f = np.arange(len(split_v)).reshape(-1, 3)
    image = Image.fromarray(np.round(tex * 255).astype(np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uv.reshape(-1, 2), image=image)
    path = tmp_path / "demo.glb"
    trimesh.Trimesh(split_v, split_f, visual=visual, process=False).export(path)
    mesh = load_mesh(path)
    np.testing.assert_allclose(mesh.corner_uvs, uv, atol=1e-6)
    assert mesh.texture.shape == (32, 32, 3)
    # Same triangles as the welded OBJ arrays (GLB holds float32): same content hash.
    assert mesh.content_hash == mesh_from_arrays(v, f).content_hash
    bare = load_mesh(path, read_texture=False)
    assert bare.texture is None and bare.content_hash == mesh.content_hash


def test_explicit_texture_overrides_and_converts(tmp_path):
    grey = np.linspace(0, 255, 12, dtype=np.uint8).reshape(3, 4)
    Image.fromarray(grey).save(tmp_path / "g.png")
    rgba = np.zeros((2, 2, 4), dtype=np.uint8)
    rgba[..., 0] = 255
    rgba[..., 3] = 7
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    g = load_texture(tmp_path / "g.png")
    assert g.shape == (3, 4, 3) and g.dtype == np.float32
    np.testing.assert_allclose(g[..., 1], grey / 255.0, atol=1e-7)
    np.testing.assert_allclose(load_texture(tmp_path / "rgba.png")[0, 0], [1, 0, 0])
    with pytest.raises(TextureError):
        load_texture(np.full((2, 2, 3), 2.0))
    with pytest.raises(TextureError):
        load_texture(tmp_path / "missing.png")


# --------------------------------------------------------------------------- the shared meshes

SHARED = [
    ("spot/spot_triangulated.obj", "spot/spot_texture.png", 2930, 5856, 1024),
    ("cesiumman/CesiumMan.glb", None, 2338, 4672, 1024),
    ("bob/bob_tri.obj", None, 5344, 10688, 2048),
    ("blub/blub_triangulated.obj", "blub/blub_texture.png", 7106, 14208, 2048),
    ("marble_bust_01/marble_bust_01_4k.gltf", None, 8730, 17456, 4096),
]


@pytest.mark.parametrize("rel, tex, n, m, size", SHARED, ids=[s[0].split("/")[0] for s in SHARED])
def test_shared_meshes_load_with_documented_counts(shared_data, rel, tex, n, m, size):
    mesh = load_mesh(shared_data / rel, texture=shared_data / tex if tex else None)
    assert (mesh.n_vertices, mesh.n_faces) == (n, m)
    assert mesh.has_texture
    assert mesh.texture.shape == (size, size, 3)
    assert mesh.corner_uvs.shape == (m, 3, 2)
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    assert extent.max() == pytest.approx(2.0)


def test_header_counts_cannot_blow_memory(tmp_path):
    """Headers claiming 10^12 elements over a tiny body must fail fast, not allocate."""
    ply = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
        b"property float x\nproperty float y\nproperty float z\n"
        b"element face 1\nproperty list uchar int vertex_indices\nend_header\n" + b"\x00" * 64
    )
    off = "OFF\n1000000000 1000000000 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    for name, data in (("huge.ply", ply), ("huge.off", off)):
        with pytest.raises((TooManyVerticesError, UnreadableMeshError)):
            load_mesh(write(tmp_path, name, data))


def test_gltf_cannot_reference_files_outside_its_folder(tmp_path):
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.zeros(9, dtype=np.float32).tobytes())
    (tmp_path / "up").mkdir()
    gltf = (
        '{"asset":{"version":"2.0"},"buffers":[{"uri":"../secret.bin","byteLength":36}],'
        '"bufferViews":[{"buffer":0,"byteLength":36}],"accessors":[{"bufferView":0,'
        '"componentType":5126,"count":3,"type":"VEC3"}],"meshes":[{"primitives":'
        '[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}],"scenes":[{"nodes":[0]}],"scene":0}'
    )
    with pytest.raises(UnreadableMeshError):
        load_mesh(write(tmp_path / "up", "evil.gltf", gltf))


def test_fast_and_line_by_line_obj_readers_agree(tmp_path, monkeypatch):
    """A regular file takes the vectorised path; a trailing comment forces the line reader."""
    import hktex_engine.geometry.mesh as mesh_module

    calls = []
    line_reader = mesh_module._parse_obj_lines
    monkeypatch.setattr(
        mesh_module, "_parse_obj_lines", lambda *a: calls.append(1) or line_reader(*a)
    )
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=16)
    regular = write_textured_obj(tmp_path / "a.obj", v, f, uv)
    text = regular.read_text()
    irregular = write(tmp_path, "b.obj", text.replace("\nv ", "  # x\nv ", 1))
    a = load_mesh(regular)
    assert calls == []
    b = load_mesh(irregular)
    assert calls == [1]
    assert a.content_hash == b.content_hash
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.corner_uvs, b.corner_uvs)


def test_obj_statement_counts_are_capped_before_parsing(tmp_path):
    path = write(tmp_path, "many.obj", "v 0 0 0\n" * 100 + "f 1 2 3\n")
    with pytest.raises(TooManyVerticesError, match="100 vertex"):
        load_mesh(path, max_vertices=10)


@pytest.mark.parametrize(
    ("mtllib", "map_kd"),
    [("../outside.mtl", "tex.png"), ("inside.mtl", "../tex.png"), ("inside.mtl", "/etc/hostname")],
)
def test_obj_material_paths_cannot_leave_the_mesh_folder(tmp_path, mtllib, map_kd):
    """A hostile upload must not make the loader read files beyond its own folder."""
    from PIL import Image

    from hktex_engine.errors import TextureError

    folder = tmp_path / "upload"
    folder.mkdir()
    Image.new("RGB", (4, 4), (255, 0, 0)).save(tmp_path / "tex.png")
    for mtl in (tmp_path / "outside.mtl", folder / "inside.mtl"):
        mtl.write_text(f"newmtl m\nmap_Kd {map_kd}\n")
    obj = folder / "tri.obj"
    obj.write_text(
        f"mtllib {mtllib}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
        "usemtl m\nf 1/1 2/2 3/3\n"
    )
    with pytest.raises(TextureError, match="outside the mesh's folder"):
        load_mesh(obj)
