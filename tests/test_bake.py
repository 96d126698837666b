"""Baking kernel sets to textures / GLB / OBJ and checking the result against the query."""

from __future__ import annotations

import numpy as np
import pytest

from hktex_engine.errors import SpectraError
from tests.demo_support import DEMO_CONFIG, demo_arrays, random_kernelset


@pytest.fixture(scope="module")
def setup():
    from hktex_engine.geometry.mesh import mesh_from_arrays
    from hktex_engine.spectra.grid import compute_spectra

    V, F, uv, tex = demo_arrays()
    mesh = mesh_from_arrays(V * 2.0 + 0.5, F, uv, tex)
    spectra = compute_spectra(mesh, DEMO_CONFIG)
    return mesh, spectra, random_kernelset(spectra, 80)


def test_rasterize_matches_bruteforce_point_in_triangle():
    from hktex_engine.render.bake import rasterize_uv

    rng = np.random.default_rng(3)
    uv = rng.random((6, 3, 2))
    face, bary = rasterize_uv(uv, 17, 13)
    ys, xs = np.mgrid[0:13, 0:17]
    centre = np.stack([(xs + 0.5) / 17, 1 - (ys + 0.5) / 13], -1)  # OBJ: v = 0 at the bottom
    for y in range(13):
        for x in range(17):
            p = centre[y, x]
            inside = []
            for i, t in enumerate(uv):
                m = np.array([t[1] - t[0], t[2] - t[0]]).T
                b1, b2 = np.linalg.solve(m, p - t[0])
                if min(1 - b1 - b2, b1, b2) >= -1e-9:
                    inside.append((i, (1 - b1 - b2, b1, b2)))
            if not inside:
                assert face[y, x] == -1
            else:
                assert face[y, x] in [i for i, _ in inside]
                want = dict(inside)[face[y, x]]
                assert np.allclose(bary[y, x], want, atol=1e-9)
                assert np.allclose(np.einsum("k,kd->d", bary[y, x], uv[face[y, x]]), p)


def test_padding_fills_from_nearest():
    from hktex_engine.render.bake import pad_texture

    tex = np.zeros((5, 5, 3), np.float32)
    covered = np.zeros((5, 5), bool)
    tex[0, 0], covered[0, 0] = 1.0, True
    tex[4, 4], covered[4, 4] = 0.5, True
    out = pad_texture(tex, covered)
    assert (out[1, 0] == 1.0).all() and (out[3, 4] == 0.5).all() and (out[4, 3] == 0.5).all()


def _baked_vs_query(mesh_uvs, texture, spectra, ks, n=2000):
    from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at
    from hktex_engine.kernels.query import AlbedoQuery

    rng = np.random.default_rng(5)
    f, b = sample_surface(spectra.vertices, spectra.faces, n, rng)
    baked = texture_lookup(texture, uv_at(mesh_uvs, f, b))
    return np.abs(baked - AlbedoQuery(spectra, ks).colors(f, b)).max(axis=1)


def test_baked_texture_matches_query_on_mesh_uvs(setup, tmp_path):
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.render.bake import bake_texture, textured_trimesh, write_glb

    mesh, spectra, ks = setup
    bake = bake_texture(spectra, ks, mesh, resolution=160)
    assert bake.atlas == "mesh" and 0.05 < bake.coverage < 1
    err = _baked_vs_query(mesh.corner_uvs, bake.texture, spectra, ks)
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.05
    # a shuffled texture does not match: the comparison can fail
    wrong = _baked_vs_query(mesh.corner_uvs, bake.texture[::-1], spectra, ks)
    assert np.median(wrong) > 5 * np.median(err)
    # GLB round trip: file units restored, texture and UVs survive, faces keep their order
    glb = write_glb(tmp_path / "out.glb", textured_trimesh(spectra, bake))
    back = load_mesh(glb)
    assert back.n_faces == mesh.n_faces
    assert np.allclose(
        back.to_file_units(back.vertices)[back.faces],
        mesh.to_file_units(mesh.vertices)[mesh.faces],
        atol=1e-5,
    )
    err_glb = _baked_vs_query(back.corner_uvs, back.texture, spectra, ks)
    assert np.median(err_glb) < 0.01


def test_xatlas_bake_and_obj(setup, tmp_path):
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.render.bake import bake_texture, write_obj

    mesh, spectra, ks = setup
    bake = bake_texture(spectra, ks, None, resolution=160)
    assert bake.atlas == "xatlas"
    err = _baked_vs_query(bake.corner_uvs, bake.texture, spectra, ks)
    assert np.median(err) < 0.015
    obj = write_obj(tmp_path / "x.obj", spectra, bake)
    assert (tmp_path / "x.mtl").is_file() and (tmp_path / "x.png").is_file()
    back = load_mesh(obj)
    assert back.has_texture and back.n_faces == mesh.n_faces
    err_obj = _baked_vs_query(back.corner_uvs, back.texture, spectra, ks)
    assert np.median(err_obj) < 0.015


def test_vertex_colors_and_mesh_mismatch(setup):
    from hktex_engine.kernels.query import AlbedoQuery
    from hktex_engine.render.bake import bake_texture, vertex_colors

    mesh, spectra, ks = setup
    vc = vertex_colors(spectra, ks)
    q = AlbedoQuery(spectra, ks)
    f = np.asarray(spectra.faces)[:5, 0]
    assert np.allclose(vc[f], q.colors(np.arange(5), np.tile([1.0, 0, 0], (5, 1))), atol=1e-5)
    other = type(mesh)(**{**mesh.__dict__, "content_hash": "x"})
    with pytest.raises(SpectraError):
        bake_texture(spectra, ks, other, resolution=16)


@pytest.mark.parametrize("layout", ["tiling", "overlapping"])
def test_uvs_a_texture_cannot_hold_bake_on_a_fresh_atlas(setup, layout):
    """Tiled or overlapping UVs would give faces of different colours the same texels: the
    bake takes its own layout, says why, and still reads back as the query."""
    from hktex_engine.geometry.mesh import mesh_from_arrays
    from hktex_engine.render.bake import bake_texture, layout_problem, rasterize_uv

    mesh, spectra, ks = setup
    uv = np.array(mesh.corner_uvs)
    assert layout_problem(uv, rasterize_uv(uv, 160, 160)[0]) == ""  # the demo's own atlas
    if layout == "tiling":
        uv[::2] += 1.0  # the same texels under wrapping, outside [0, 1]
    else:
        uv[1::2] = uv[::2][: len(uv[1::2])]  # every odd face on an even face's texels
    V = mesh.to_file_units(mesh.vertices)
    moved = mesh_from_arrays(V, mesh.faces, uv, mesh.texture)
    assert moved.content_hash == mesh.content_hash
    bake = bake_texture(spectra, ks, moved, resolution=160)
    assert bake.atlas == "xatlas"
    assert "overlap or leave [0, 1]" in bake.atlas_reason
    err = _baked_vs_query(bake.corner_uvs, bake.texture, spectra, ks)
    assert np.median(err) < 0.015
    # read on the mesh's own (bad) UVs the same texture would be wrong on many points
    assert np.median(_baked_vs_query(uv, bake.texture, spectra, ks)) > 3 * np.median(err)
