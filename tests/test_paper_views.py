"""The paper-view protocol (EVALUATION.md): renders, scores, and a check against Mitsuba."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from hktex_engine.evaluation.baselines import UVTextureBaseline, VertexColorBaseline
from hktex_engine.evaluation.paper_views import (
    MESH,
    PaperViews,
    PaperViewSettings,
    cosine_directions,
    image_scores,
    mesh_albedo_fn,
    paper_view_scores,
    to_uint8_srgb,
)
from hktex_engine.evaluation.synthetic import textured_demo
from hktex_engine.geometry.mesh import mesh_from_arrays
from hktex_engine.render.mitsuba import linear_to_srgb, srgb_to_linear

SMALL = PaperViewSettings(width=24, height=20, n_views=2, subpixels=2, secondary_rays=4)


@pytest.fixture(scope="module")
def mesh():
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=32)
    return mesh_from_arrays(v, f, uv, tex)


@pytest.fixture(scope="module")
def views(mesh):
    return PaperViews(mesh, SMALL)


def test_identical_method_scores_infinity(views, mesh):
    s = views.score(mesh_albedo_fn(mesh))
    assert s["psnr_all"] == float("inf") and s["psnr_mesh"] == float("inf")
    assert s["ssim_all"] == pytest.approx(1.0) and s["ssim_mesh"] == pytest.approx(1.0)
    assert views.reference.shape == (2, 20, 24, 3) and views.reference.dtype == np.uint8
    assert views.mesh_mask.any() and not views.mesh_mask.all()


def test_constant_colour_matches_independent_numpy(views):
    grey = np.array([0.4, 0.5, 0.6])
    const = views.render(lambda f, b: np.tile(grey, (len(f), 1)))
    ref = views.reference
    s = views.score(lambda f, b: np.tile(grey, (len(f), 1)))
    d = (const.astype(float) - ref.astype(float)) / 255.0
    mse_all = np.mean(d**2)
    mse_mesh = np.mean(d[views.mesh_mask] ** 2)
    assert s["psnr_all"] == pytest.approx(10 * np.log10(1 / mse_all))
    assert s["psnr_mesh"] == pytest.approx(10 * np.log10(1 / mse_mesh))
    # an imperfect method: background pixels agree, so all-pixel PSNR flatters it
    assert s["psnr_mesh"] < s["psnr_all"]
    a, b = const / 255.0, ref / 255.0
    ssims = [structural_similarity(a[v], b[v], data_range=1.0, channel_axis=-1) for v in range(2)]
    assert s["ssim_all"] == pytest.approx(np.mean(ssims))
    assert s["ssim_mesh"] < 1.0


def test_image_formation_is_albedo_times_shading(views, mesh):
    """Background is the environment (255); a white mesh shows the shading alone; radiance
    is linear in the primary albedo when the indirect light comes from the mesh itself."""
    bg = ~views.mesh_mask & (views._views[0].kind.reshape(20, 24, 4) == 0).all(axis=2)[None]
    assert (views.reference[bg] == 255).all()
    white = views.render_linear(lambda f, b: np.ones((len(f), 3)))
    half = views.render_linear(lambda f, b: np.full((len(f), 3), linear_to_srgb(0.5)))
    assert white.max() <= 1.0 + 1e-9 and white.min() >= 0.0
    # radiance = rho (A + rho_mesh * I): with rho = 0.5 everywhere on the mesh, mesh pixels
    # whose subsamples all hit the mesh lie between 0.25 and 0.5 of the white render
    full = (views._views[0].kind.reshape(20, 24, 4) == MESH).all(axis=2)
    w, h = white[0][full], half[0][full]
    assert np.all(h <= 0.5 * w + 1e-9) and np.all(h >= 0.25 * w - 1e-9)


def test_uint8_encoding_and_scores_errors():
    x = np.array([0.0, 0.5, 1.0, 2.0])
    np.testing.assert_array_equal(to_uint8_srgb(x), np.round(linear_to_srgb(x) * 255))
    assert to_uint8_srgb(np.array([2.0]))[0] == 255
    imgs = np.zeros((1, 8, 8, 3), np.uint8)
    with pytest.raises(ValueError):
        image_scores(imgs, imgs[:, :4], np.ones((1, 8, 8), bool))


def test_cosine_directions_are_cosine_distributed():
    rng = np.random.default_rng(0)
    n = np.tile([0.0, 0.0, -1.0], (40000, 1))
    n[::2] = [0.6, 0.8, 0.0]
    d = cosine_directions(n, rng)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    cos = (d * n).sum(axis=1)
    assert cos.min() >= 0.0
    # E[cos] = 2/3 and E[cos^2] = 1/2 under a cosine-weighted hemisphere
    assert cos.mean() == pytest.approx(2 / 3, abs=5e-3)
    assert (cos**2).mean() == pytest.approx(0.5, abs=5e-3)


def test_paper_view_scores_many_methods(mesh):
    res = paper_view_scores(
        mesh,
        {"vc1": VertexColorBaseline(1).fit(mesh), "uv16": UVTextureBaseline(16).fit(mesh)},
        SMALL,
    )
    assert res["vc1"]["psnr_mesh"] < res["vc1"]["psnr_all"]
    assert np.isfinite(res["uv16"]["psnr_all"]) and res["uv16"]["render_s"] >= 0
    assert res["_protocol"]["width"] == 24 and res["_protocol"]["mesh_pixels"] > 0


@pytest.mark.slow
def test_matches_mitsuba_path_tracer(mesh):
    """Our traced estimate of the ground truth against Mitsuba's own ``path`` integrator
    (max_depth 3, bitmap texture, the same plane and environment) at many samples."""
    import mitsuba as mi

    from hktex_engine.render.mitsuba import RenderScene

    s = PaperViewSettings(width=32, height=32, n_views=1, subpixels=4, secondary_rays=32)
    pv = PaperViews(mesh, s)
    ours = pv.render_linear(mesh_albedo_fn(mesh))[0]
    V = pv.vertices
    tex = mi.load_dict(
        {
            "type": "bitmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(srgb_to_linear(mesh.texture))),
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "repeat",
        }
    )
    bsdf = mi.load_dict({"type": "diffuse", "reflectance": tex})
    shape = RenderScene._mi_mesh(V, mesh.faces, mesh.corner_uvs, bsdf)
    half = s.plane_extent * pv.radius
    # rectangle: local xy square of half-side 1, normal +z; z -> up (+y), centred under the mesh
    to_world = np.eye(4)
    to_world[:3, 0] = [half, 0.0, 0.0]
    to_world[:3, 1] = [0.0, 0.0, -half]
    to_world[:3, 2] = [0.0, half, 0.0]
    to_world[:3, 3] = [pv.centre[0], pv.plane_height, pv.centre[2]]
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "mesh": shape,
            "plane": {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f(to_world),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}},
            },
        }
    )
    sensor = pv._scene.sensor(pv.cameras[0])
    theirs = np.array(mi.render(scene, sensor=sensor, spp=1024, seed=3), dtype=np.float64)
    assert theirs.shape == ours.shape
    err = ours - theirs
    # both converge to the same integral: small mean bias, residual noise only
    assert abs(err.mean()) < 5e-3
    assert np.sqrt(np.mean(err**2)) < 0.03


def test_hit_buffer_barycentrics_match_mitsubas_own(views):
    """RenderScene.hit_buffer's barycentrics equal Mitsuba's at the same pixel-centre rays
    (a regression: Dr.Jit hands points out as (3, n), once read as (n, 3))."""
    import mitsuba as mi

    scene, cam = views._scene, views.cameras[0]
    face, bary, mask = scene.hit_buffer(cam)
    h, w = mask.shape
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    n = h * w
    ray, _ = scene.sensor(cam).sample_ray(
        mi.Float(np.zeros(n, np.float32)),
        mi.Float(np.full(n, 0.5, np.float32)),
        mi.Point2f(
            mi.Float(((xs.ravel() + 0.5) / w).astype(np.float32)),
            mi.Float(((ys.ravel() + 0.5) / h).astype(np.float32)),
        ),
        mi.Point2f(0.5, 0.5),
    )
    si = scene.scene.ray_intersect(ray)
    uv = np.array(si.uv, dtype=np.float64).reshape(2, -1)
    theirs = np.stack([1 - uv[0] - uv[1], uv[0], uv[1]], axis=1).reshape(h, w, 3)
    assert mask.any()
    np.testing.assert_array_equal(face[mask], np.array(si.prim_index).reshape(h, w)[mask])
    np.testing.assert_allclose(bary[mask], theirs[mask], atol=2e-3)
