"""Several materials packed into one texture (hktex_engine.geometry.atlas) and the loaders
that use it: the atlas must read, at a face's new UVs, what the face's own material reads at
its file UVs (per-material lookup as the independent computation)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from hktex_engine.errors import TextureError
from hktex_engine.evaluation.synthetic import icosphere
from hktex_engine.geometry.atlas import (
    GUTTER,
    MAX_REPEATS,
    Appearance,
    linear_to_srgb,
    one_texture,
    srgb_to_linear,
    stored_albedo,
)
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.geometry.sampling import texture_lookup, uv_at


def random_points(n_faces: int, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    faces = rng.integers(0, n_faces, count)
    bary = rng.dirichlet(np.ones(3), count)
    return faces, bary


def per_material(appearances, face_app, uvs, faces, bary) -> np.ndarray:
    """The independent reading: each point looks up its own material at its file UV."""
    out = np.empty((len(faces), 3))
    for a, app in enumerate(appearances):
        pick = face_app[faces] == a
        if app.image is None:
            out[pick] = np.asarray(app.colour)
        else:
            out[pick] = texture_lookup(stored_albedo(app), uv_at(uvs, faces[pick], bary[pick]))
    return out


def three_appearances(rng) -> list[Appearance]:
    return [
        Appearance(("a",), image=rng.random((13, 21, 3), dtype=np.float32), name="a"),
        Appearance(
            ("b",), image=rng.random((8, 5, 3), dtype=np.float32), factor=(0.5, 1, 0.25), name="b"
        ),
        Appearance(("c",), colour=(0.2, 0.7, 0.9), name="c"),
    ]


def test_atlas_reads_what_each_material_reads_wrapping_included():
    rng = np.random.default_rng(0)
    apps = three_appearances(rng)
    n = 300
    face_app = rng.integers(0, 3, n)
    # Faces anywhere in UV space, spanning up to 2.5 periods: tiling materials.
    start = rng.uniform(-3, 3, (n, 1, 2))
    uvs = start + rng.uniform(0, 2.5, (n, 3, 2))
    atlas, atlas_uvs = one_texture(apps, face_app, uvs)
    assert atlas.dtype == np.float32 and atlas_uvs.shape == uvs.shape
    faces, bary = random_points(n, 20000, rng)
    want = per_material(apps, face_app, uvs, faces, bary)
    got = texture_lookup(atlas, uv_at(atlas_uvs, faces, bary))
    np.testing.assert_allclose(got, want, atol=2e-6)
    # ... and at the corners themselves, where a face's UVs may sit on a period's edge.
    corners = np.repeat(np.arange(n), 3)
    eye = np.tile(np.eye(3), (n, 1))
    np.testing.assert_allclose(
        texture_lookup(atlas, uv_at(atlas_uvs, corners, eye)),
        per_material(apps, face_app, uvs, corners, eye),
        atol=2e-6,
    )


def test_one_appearance_is_passed_through_untouched():
    rng = np.random.default_rng(1)
    image = rng.random((6, 7, 3), dtype=np.float32)
    uvs = rng.uniform(-2, 2, (10, 3, 2))
    tex, out = one_texture([Appearance(("x",), image=image)], np.zeros(10, int), uvs)
    assert tex is image and out is uvs


def test_no_image_means_no_texture():
    apps = [Appearance(("p",), colour=(1, 0, 0)), Appearance(("q",), colour=(0, 1, 0))]
    assert one_texture(apps, np.array([0, 1, 1]), None) == (None, None)


def test_gutters_keep_tiles_apart():
    """A bilinear read at a tile's very edge must wrap inside its own image."""
    red = Appearance(("r",), image=np.tile(np.float32([1, 0, 0]), (4, 4, 1)))
    blue = Appearance(("b",), image=np.tile(np.float32([0, 0, 1]), (4, 4, 1)))
    uvs = np.array([[[0, 0], [1, 0], [0, 1]], [[0, 0], [1, 0], [1, 1]]], dtype=float)
    atlas, out = one_texture([red, blue], np.array([0, 1]), uvs)
    got = texture_lookup(atlas, out.reshape(-1, 2))
    np.testing.assert_array_equal(got, [[1, 0, 0]] * 3 + [[0, 0, 1]] * 3)
    assert atlas.shape[0] >= 4 + 2 * GUTTER


def test_a_face_over_too_many_periods_is_refused():
    apps = three_appearances(np.random.default_rng(2))
    uvs = np.zeros((2, 3, 2))
    uvs[0, 1, 0] = MAX_REPEATS + 0.5
    with pytest.raises(TextureError, match="repeats"):
        one_texture(apps, np.array([0, 2]), uvs)


def test_textured_faces_need_uvs():
    apps = three_appearances(np.random.default_rng(3))
    uvs = np.full((2, 3, 2), np.nan)
    with pytest.raises(TextureError, match="no UV"):
        one_texture(apps, np.array([0, 2]), uvs)


def test_srgb_transfer_against_its_definition():
    # IEC 61966-2-1 reference values: 0.5 stored is 0.2140 linear; 0.04045 is the knee.
    np.testing.assert_allclose(
        srgb_to_linear(np.float32([0.0, 0.04045, 0.5, 1.0])),
        [0.0, 0.04045 / 12.92, 0.21404114, 1.0],
        rtol=1e-5,
    )
    x = np.linspace(0, 1, 101, dtype=np.float32)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)


# --------------------------------------------------------------------------- loaders


def sphere_with_uvs(rng):
    v, f = icosphere(2)
    uvs = rng.uniform(-1.5, 2.0, (len(f), 1, 2)) + rng.uniform(0, 0.8, (len(f), 3, 2))
    return v, f, uvs


def write_png(path, image):
    Image.fromarray(np.round(image * 255).astype(np.uint8)).save(path)
    return np.round(image * 255) / 255


def write_material_obj(path, v, f, uvs, mtllib: str, material_of) -> None:
    """An OBJ of ``(v, f)`` with per-corner ``uvs``; before face ``i`` a ``usemtl
    material_of(i)`` line, or none where it returns None (the previous one stays in force)."""
    lines = [f"mtllib {mtllib}"] + [f"v {x} {y} {z}" for x, y, z in v]
    lines += [f"vt {a} {b}" for a, b in uvs.reshape(-1, 2)]
    for i, tri in enumerate(f):
        if material_of(i) is not None:
            lines.append(f"usemtl {material_of(i)}")
        lines.append("f " + " ".join(f"{tri[c] + 1}/{3 * i + c + 1}" for c in range(3)))
    path.write_text("\n".join(lines) + "\n")


def test_obj_with_several_materials_reads_each_materials_colours(tmp_path):
    rng = np.random.default_rng(4)
    v, f, uvs = sphere_with_uvs(rng)
    img_a = write_png(tmp_path / "a.png", rng.random((16, 24, 3)))
    img_b = write_png(tmp_path / "b b.png", rng.random((9, 9, 3)))
    (tmp_path / "m.mtl").write_text(
        "newmtl A\nKd 0.8 0.8 0.8\nmap_Kd a.png\n"
        "newmtl B\nmap_Kd -s 1 1 1 b b.png\n"
        "newmtl C\nKd 0.1 0.2 0.3\n"
    )
    mat = np.arange(len(f)) % 3  # A, B, C interleaved: three runs of usemtl and back
    write_material_obj(tmp_path / "m.obj", v, f, uvs, "m.mtl", lambda i: "ABC"[mat[i]])
    mesh = load_mesh(tmp_path / "m.obj")
    assert mesh.has_texture
    apps = [
        Appearance(("A",), image=img_a.astype(np.float32)),
        Appearance(("B",), image=img_b.astype(np.float32)),
        Appearance(("C",), colour=(0.1, 0.2, 0.3)),
    ]
    faces, bary = random_points(len(f), 5000, rng)
    want = per_material(apps, mat, uvs, faces, bary)
    got = texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, faces, bary))
    np.testing.assert_allclose(got, want, atol=1e-5)
    # Geometry is untouched by the materials; an explicit texture keeps the file's UVs.
    assert mesh.content_hash == load_mesh(tmp_path / "m.obj", read_texture=False).content_hash
    override = load_mesh(tmp_path / "m.obj", texture=tmp_path / "a.png")
    np.testing.assert_allclose(override.corner_uvs, uvs)


def test_obj_materials_sharing_one_map_read_as_one(tmp_path):
    rng = np.random.default_rng(5)
    v, f, uvs = sphere_with_uvs(rng)
    img = write_png(tmp_path / "a.png", rng.random((8, 8, 3)))
    (tmp_path / "m.mtl").write_text("newmtl A\nmap_Kd a.png\nnewmtl B\nmap_Kd a.png\n")
    write_material_obj(tmp_path / "m.obj", v, f, uvs, "m.mtl", lambda i: "AB"[i % 2])
    mesh = load_mesh(tmp_path / "m.obj")
    np.testing.assert_allclose(mesh.texture, img, atol=1e-6)
    np.testing.assert_allclose(mesh.corner_uvs, uvs)


@pytest.mark.parametrize("defect", ["no usemtl", "undefined material"])
def test_obj_faces_without_a_known_colour_are_refused(tmp_path, defect):
    rng = np.random.default_rng(6)
    v, f, uvs = sphere_with_uvs(rng)
    write_png(tmp_path / "a.png", rng.random((8, 8, 3)))
    (tmp_path / "m.mtl").write_text("newmtl A\nmap_Kd a.png\nnewmtl B\nKd 1 0 0\n")
    if defect == "no usemtl":
        names = {0: None, 1: "A", 2: "B"}  # face 0 comes before any usemtl
    else:
        names = {0: "A", 1: "A", 2: "Z"}  # no MTL defines Z
    write_material_obj(tmp_path / "m.obj", v, f, uvs, "m.mtl", lambda i: names[i % 3])
    with pytest.raises(TextureError, match="colour is unknown"):
        load_mesh(tmp_path / "m.obj")


def test_glb_with_several_primitives_and_base_colour_factors(tmp_path):
    """One sphere in two primitives: a textured one with a factor and a plain one. glTF's base
    colour is the factor times the image in linear light, and the factor alone without one."""
    rng = np.random.default_rng(7)
    v, f = icosphere(2)
    half = len(f) // 2
    image = np.round(rng.random((16, 16, 3)) * 255).astype(np.uint8)
    factors = np.float32([[0.5, 1.0, 1.0], [0.2, 0.4, 1.0]])
    scene, uvs = trimesh.Scene(), []
    for part, faces in enumerate((f[:half], f[half:])):
        split_v = v[faces].reshape(-1, 3)
        uv = rng.uniform(0.05, 0.95, (len(split_v), 2))
        uvs.append(uv.reshape(-1, 3, 2))
        material = trimesh.visual.material.PBRMaterial(
            baseColorTexture=Image.fromarray(image) if part == 0 else None,
            baseColorFactor=[*factors[part], 1.0],
        )
        visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
        split_f = np.arange(len(split_v)).reshape(-1, 3)
        scene.add_geometry(trimesh.Trimesh(split_v, split_f, visual=visual, process=False))
    scene.export(tmp_path / "two.glb")
    mesh = load_mesh(tmp_path / "two.glb")
    # The scene graph decides the primitives' order: find each loaded face's part and UVs.
    centres = mesh.to_file_units(mesh.vertices)[mesh.faces].mean(axis=1)
    key = {tuple(np.round(c, 5)): i for i, c in enumerate(v[f].mean(axis=1))}
    source = np.array([key[tuple(np.round(c, 5))] for c in centres])
    part = (source >= half).astype(int)
    file_uv = np.concatenate(uvs)[source]
    faces, bary = random_points(len(f), 4000, rng)
    got = texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, faces, bary))
    stored = np.round(factors * 255) / 255  # glTF factors travel through trimesh as bytes
    # The definition, texel by texel: linear = factor x decode(stored); stored = encode(linear).
    reference = linear_to_srgb(srgb_to_linear(image / np.float32(255)) * stored[0])
    first = part[faces] == 0
    want = texture_lookup(reference, uv_at(file_uv, faces[first], bary[first]))
    np.testing.assert_allclose(got[first], want, atol=1e-5)
    plain = np.tile(linear_to_srgb(stored[1]), (int((~first).sum()), 1))
    np.testing.assert_allclose(got[~first], plain, atol=1e-6)


@pytest.mark.parametrize(
    "change",
    [
        ("texCoord", 1, "TEXCOORD_1"),
        ("extensions", {"KHR_texture_transform": {"scale": [2, 2]}}, "KHR_texture_transform"),
        ("no source", None, "extension-only"),
    ],
)
def test_gltf_base_colour_this_reader_would_misread_is_refused(tmp_path, change):
    """What trimesh would silently ignore (another UV set, a texture transform, a KTX2-only
    texture) must stop the load with a message, not fit the wrong colours."""
    import json

    from trimesh.exchange.gltf import export_gltf

    v, f = icosphere(1)
    split_v = v[f].reshape(-1, 3)
    uv = np.random.default_rng(8).uniform(0, 1, (len(split_v), 2))
    image = Image.fromarray(np.zeros((4, 4, 3), np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    mesh = trimesh.Trimesh(split_v, np.arange(len(split_v)).reshape(-1, 3), visual=visual)
    files = export_gltf(trimesh.Scene(mesh))
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    assert load_mesh(tmp_path / "model.gltf").has_texture  # as exported: readable
    doc = json.loads(files["model.gltf"])
    ref = doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]
    key, value, message = change
    if key == "no source":
        doc["textures"][ref["index"]] = {"extensions": {"KHR_texture_basisu": {"source": 0}}}
    else:
        ref[key] = value
    (tmp_path / "model.gltf").write_text(json.dumps(doc))
    with pytest.raises(TextureError, match=message):
        load_mesh(tmp_path / "model.gltf")
    # geometry alone (what spectra read) does not depend on the texture
    assert load_mesh(tmp_path / "model.gltf", read_texture=False).n_faces == len(f)


def test_obj_materials_without_any_map_load_untextured(tmp_path):
    """An OBJ whose MTL did not come along (a REST upload sends the mesh file alone) names
    several materials: it loads as geometry without texture, as before the atlas."""
    rng = np.random.default_rng(9)
    v, f, uvs = sphere_with_uvs(rng)
    write_material_obj(tmp_path / "m.obj", v, f, uvs, "missing.mtl", lambda i: "AB"[i % 2])
    mesh = load_mesh(tmp_path / "m.obj")
    assert mesh.texture is None and not mesh.has_texture
    np.testing.assert_allclose(mesh.corner_uvs, uvs)


@pytest.mark.parametrize(
    "written", ["textures\\a.png", "C:\\Users\\me\\assets\\a.png", "/home/me/assets/a.png"]
)
def test_map_kd_written_elsewhere_finds_the_shipped_file(tmp_path, written):
    """Windows separators and absolute paths from the author's machine: the map is read from
    where the asset ships it (its relative path, else its file name beside the MTL)."""
    rng = np.random.default_rng(10)
    v, f, uvs = sphere_with_uvs(rng)
    folder = tmp_path / "textures" if written.startswith("textures") else tmp_path
    folder.mkdir(exist_ok=True)
    img = write_png(folder / "a.png", rng.random((8, 8, 3)))
    (tmp_path / "m.mtl").write_text(f"newmtl A\nmap_Kd {written}\n")
    write_material_obj(tmp_path / "m.obj", v, f, uvs, "m.mtl", lambda i: "A")
    np.testing.assert_allclose(load_mesh(tmp_path / "m.obj").texture, img, atol=1e-6)
