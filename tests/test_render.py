"""Rendering: colour space, UV vs torch albedo agreement, gradients through Mitsuba."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from tests.demo_support import demo_arrays, require_render

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def R():
    return require_render()


@pytest.fixture(scope="module")
def textured():
    from hktex_engine.geometry.mesh import mesh_from_arrays

    V, F, uv, tex = demo_arrays()
    return mesh_from_arrays(V * 3.0 + 1.0, F, uv, tex)  # file units differ from normalised


def _interior(mask: np.ndarray) -> np.ndarray:
    # pixels whose box filter footprint lies fully on the mesh (edges mix in background)
    return ndimage.binary_erosion(mask, iterations=1)


def test_srgb_curves_roundtrip_and_known_values(R):
    x = np.linspace(0, 1, 101, dtype=np.float32)
    assert np.allclose(R.linear_to_srgb(R.srgb_to_linear(x)), x, atol=1e-5)
    # IEC 61966-2-1 reference points
    assert R.srgb_to_linear(np.float32(0.5)) == pytest.approx(0.214041, abs=1e-5)
    assert R.srgb_to_linear(np.float32(0.04)) == pytest.approx(0.04 / 12.92, abs=1e-7)
    t = torch.tensor([0.2, 0.5, 0.9])
    assert torch.allclose(R.srgb_to_linear(t), torch.from_numpy(R.srgb_to_linear(t.numpy())))


def test_constant_albedo_furnace(R):
    """A convex diffuse object under unit white light shows its linear albedo exactly."""
    from hktex_engine.evaluation.synthetic import icosphere

    V, F = icosphere(2)
    srgb = torch.tensor([0.8, 0.5, 0.2])
    scene = R.RenderScene(
        V,
        F,
        R.RenderSettings(width=24, height=24, spp=32),
        albedo_fn=lambda f, b: srgb.expand(len(f), 3),
    )
    cam = R.orbit_camera(V, 10, 15)
    img = scene.render(cam)
    m = _interior(scene.hit_buffer(cam)[2])
    assert m.sum() > 100
    expect = R.srgb_to_linear(srgb.numpy())
    assert np.allclose(img[m].mean(0), expect, rtol=0.01)
    far = ~ndimage.binary_dilation(scene.hit_buffer(cam)[2], iterations=1)
    assert np.allclose(img[far], 1.0)  # background = the environment


def test_uv_render_of_constant_texture_equals_constant_torch_albedo(R, textured):
    from hktex_engine.geometry.mesh import mesh_from_arrays

    c = np.array([0.3, 0.6, 0.9], np.float32)
    mesh = mesh_from_arrays(
        textured.to_file_units(textured.vertices),
        textured.faces,
        textured.corner_uvs,
        np.broadcast_to(c, (8, 8, 3)).copy(),
    )
    settings = R.RenderSettings(width=24, height=24, spp=8)
    V = mesh.to_file_units(mesh.vertices)
    cam = R.orbit_camera(V, 40, 25)
    uv_img = R.render_uv(mesh, cam, settings, seed=3)
    scene = R.RenderScene(
        V, mesh.faces, settings, albedo_fn=lambda f, b: torch.from_numpy(c).expand(len(f), 3)
    )
    kt_img = scene.render(cam, seed=3)
    assert np.abs(uv_img - kt_img).max() < 1e-4


def test_uv_render_matches_torch_texture_lookup(R, textured):
    """The bitmap path (per-corner UVs, v flip, bilinear) equals our own lookup of the texture."""
    from hktex_engine.geometry.sampling import texture_lookup, uv_at

    mesh = textured
    V = mesh.to_file_units(mesh.vertices)
    settings = R.RenderSettings(width=32, height=32, spp=4)
    cam = R.orbit_camera(V, 70, 30)

    # Mitsuba interpolates the linearised texture; do the same so only geometry can differ
    linear_tex = R.srgb_to_linear(mesh.texture)

    def lookup(f: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        uv = uv_at(mesh.corner_uvs, f.numpy(), b.detach().numpy().astype(np.float64))
        return torch.from_numpy(R.linear_to_srgb(texture_lookup(linear_tex, uv)))

    scene = R.RenderScene(V, mesh.faces, settings, albedo_fn=lookup)
    a = scene.render(cam, seed=1)
    b = R.render_uv(mesh, cam, settings, seed=1)
    m = _interior(scene.hit_buffer(cam)[2])
    assert np.percentile(np.abs(a[m] - b[m]), 95) < 2e-3
    # and a flipped texture does not match: the test can fail
    flipped = mesh.texture[::-1].copy()
    scene_flip = R.RenderScene(
        V,
        mesh.faces,
        settings,
        albedo_fn=lambda f, bb: torch.from_numpy(
            texture_lookup(
                flipped, uv_at(mesh.corner_uvs, f.numpy(), bb.detach().numpy().astype(float))
            ).astype(np.float32)
        ),
    )
    assert np.abs(scene_flip.render(cam, seed=1)[m] - b[m]).mean() > 1e-2


def test_hit_buffer_locates_surface_points(R):
    from hktex_engine.evaluation.synthetic import icosphere

    V, F = icosphere(1)
    scene = R.RenderScene(
        V,
        F,
        R.RenderSettings(width=16, height=16, spp=1),
        albedo_fn=lambda f, b: torch.ones(len(f), 3),
    )
    cam = R.orbit_camera(V, 0, 0)
    face, bary, mask = scene.hit_buffer(cam)
    assert mask.any() and not mask.all()
    assert (face[~mask] == -1).all()
    pts = np.einsum("pk,pkd->pd", bary[mask], V[F[face[mask]]])
    # each hit is on the camera-facing half of the sphere, on the mesh (|p| ~ 1 for icosphere)
    origin = cam.to_world[:3, 3]
    assert (np.einsum("pd,d->p", pts, origin) > 0).all()
    assert np.allclose(bary[mask].sum(1), 1.0)


def test_gradient_reaches_torch_parameter_matches_finite_difference(R):
    from hktex_engine.evaluation.synthetic import icosphere

    V, F = icosphere(1)
    colors = torch.full((len(F), 3), 0.5, requires_grad=True)
    scene = R.RenderScene(
        V, F, R.RenderSettings(width=16, height=16, spp=4), albedo_fn=lambda f, b: colors[f]
    )
    cam = R.orbit_camera(V, 0, 0)
    face, _, mask = scene.hit_buffer(cam)
    j = int(np.bincount(face[mask]).argmax())  # the face covering most pixels

    def loss_of(img: torch.Tensor) -> torch.Tensor:
        return (img * torch.tensor([0.5, 1.0, 2.0])).sum()

    img = scene.render_torch(cam, seed=7, spp=64, seed_grad=8)
    loss_of(img).backward()
    g = colors.grad[j, 1].item()
    assert g > 0
    h = 0.02
    vals = []
    for sign in (1, -1):
        with torch.no_grad():
            colors[j, 1] += sign * h
        vals.append(loss_of(torch.from_numpy(scene.render(cam, seed=7, spp=64))).item())
        with torch.no_grad():
            colors[j, 1] -= sign * h
    fd = (vals[0] - vals[1]) / (2 * h)
    assert g == pytest.approx(fd, rel=0.05)
    # faces turned away from the camera get no gradient
    centroid = V[F].mean(1)
    normal = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    back = np.flatnonzero(np.einsum("fd,fd->f", normal, cam.to_world[:3, 3] - centroid) < 0)
    assert len(back) > len(F) // 3
    assert colors.grad[back].abs().max() < 1e-3 * abs(g)


def test_parse_view_and_png(R):
    import io

    from PIL import Image

    V = np.random.default_rng(0).normal(size=(50, 3))
    cam = R.parse_view("30,10", V)
    assert np.allclose(cam.to_world, R.orbit_camera(V, 30, 10).to_world)
    assert np.allclose(R.parse_view("2", V).to_world, R.orbit_cameras(V, 3)[2].to_world)
    with pytest.raises(ValueError):
        R.parse_view("a,b", V)
    png = R.encode_png(np.full((4, 5, 3), R.srgb_to_linear(np.float32(0.5))))
    arr = np.asarray(Image.open(io.BytesIO(png)))
    assert arr.shape == (4, 5, 3) and (arr == 128).all()


def test_principled_and_envmap(R, tmp_path):
    import mitsuba as mi

    from hktex_engine.evaluation.synthetic import icosphere

    V, F = icosphere(1)
    fn = lambda f, b: torch.full((len(f), 3), 0.6)  # noqa: E731
    cam = R.orbit_camera(V, 0, 10)
    diffuse = R.RenderScene(V, F, R.RenderSettings(16, 16, spp=8), albedo_fn=fn).render(cam)
    principled = R.RenderScene(
        V, F, R.RenderSettings(16, 16, spp=8, bsdf="principled"), albedo_fn=fn
    ).render(cam)
    assert np.isfinite(principled).all() and not np.allclose(principled, diffuse)
    env = np.zeros((8, 16, 3), np.float32)
    env[:4] = 2.0  # bright sky, black ground
    path = tmp_path / "env.exr"
    mi.Bitmap(env).write(str(path))
    lit = R.RenderScene(
        V,
        F,
        R.RenderSettings(16, 16, spp=8, lighting=R.Lighting("envmap", envmap=str(path))),
        albedo_fn=fn,
    ).render(cam)
    m = R.RenderScene(V, F, R.RenderSettings(16, 16, spp=1), albedo_fn=fn).hit_buffer(cam)[2]
    rows = np.flatnonzero(m.any(1))
    top, bottom = lit[rows[0] + 1][m[rows[0] + 1]], lit[rows[-1] - 1][m[rows[-1] - 1]]
    assert top.mean() > bottom.mean()  # lit from above


def _smooth_albedo(V, F):
    """A position-dependent albedo (varies inside faces, so every distinct point matters)."""
    Vt = torch.as_tensor(V, dtype=torch.float32)
    Ft = torch.as_tensor(F, dtype=torch.long)
    weight = torch.tensor([[0.8, 0.1, 0.1], [0.1, 0.7, 0.2], [0.2, 0.1, 0.6]])

    def fn(f, b):
        p = (b[:, :, None] * Vt[Ft[f.long()]].to(b.dtype)).sum(1)
        return 0.5 + 0.4 * torch.sin(3.0 * p @ weight.to(b.dtype))

    return fn


def _counting_scene(R):
    """An icosphere scene whose smooth albedo records how many points each call asks about."""
    from hktex_engine.evaluation.synthetic import icosphere

    V, F = icosphere(2)
    counts = []
    base = _smooth_albedo(V, F)

    def fn(f, b):
        counts.append(len(f))
        return base(f, b)

    scene = R.RenderScene(V, F, R.RenderSettings(width=24, height=24, spp=4), albedo_fn=fn)
    return V, F, scene, R.orbit_camera(V, 20, 10), counts


def test_point_cache_renders_equal_uncached_and_evaluates_less(R, monkeypatch):
    """The per-render point cache is exact: the image equals the one where every request is
    evaluated, while the albedo runs on fewer points; the gradients are the same too."""
    from hktex_engine.render import mitsuba as rm

    V, F, scene, cam, counts = _counting_scene(R)
    cached = scene.render(cam, seed=3, cache=True)
    evaluated = sum(counts)
    # one albedo call on the recorded distinct points; the second pass asked for no other
    assert len(counts) == 1
    assert scene.last_cache.evaluated == evaluated < scene.last_cache.asked

    class NoCache:  # the same protocol, evaluating every request
        def __init__(self, fn, tape=None):
            self.fn, self.tape = fn, tape
            self.asked = self.evaluated = 0

        def __call__(self, f, b):
            out = self.fn(f, b)
            if self.tape is None:
                return out
            leaf = out.detach().requires_grad_(True)
            self.tape.append((out, leaf))
            return leaf

    colors = torch.full((len(F), 3), 0.5, requires_grad=True)
    shade = _smooth_albedo(V, F)
    dscene = R.RenderScene(
        V,
        F,
        R.RenderSettings(width=16, height=16, spp=4),
        albedo_fn=lambda f, b: colors[f.long()] * shade(f, b),
    )
    grads = []
    for patch in (False, True):
        if patch:
            monkeypatch.setattr(rm, "_PointCache", NoCache)
        colors.grad = None
        img = dscene.render_torch(cam, seed=5, seed_grad=6)
        (img * torch.tensor([0.5, 1.0, 2.0])).sum().backward()
        grads.append(colors.grad.clone())
    counts.clear()
    monkeypatch.setattr(rm, "_BounceMemo", lambda: None)  # every request evaluated
    uncached = scene.render(cam, seed=3)
    assert sum(counts) > evaluated
    np.testing.assert_allclose(cached, uncached, rtol=0, atol=1e-6)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-7)
    assert grads[0].abs().sum() > 0


def test_bounce_memo_renders_equal_the_torch_glue_and_evaluates_less(R, monkeypatch):
    """A plain render on the CPU answers through the bounce memo: the image equals the one the
    torch glue gives when every request is evaluated (to the sRGB curve's float32 round-off),
    while the albedo runs on fewer points (each bounce's repeated hits answered once)."""
    from hktex_engine.render import mitsuba as rm

    V, F, scene, cam, counts = _counting_scene(R)
    memo = scene.render(cam, seed=3)
    assert scene.last_memo.asked > scene.last_memo.evaluated == sum(counts) > 0
    evaluated = sum(counts)
    counts.clear()
    monkeypatch.setattr(rm, "_BounceMemo", lambda: None)  # the torch glue, no reuse
    every = scene.render(cam, seed=3)
    assert sum(counts) > evaluated
    np.testing.assert_allclose(memo, every, rtol=0, atol=1e-6)
    assert memo.max() > 0.1


def test_bounce_memo_reuses_only_equal_hits_in_order():
    """The memo reuses an answer exactly where the hit (face and barycentric bits) repeats in
    order, evaluates everything else, and its answers equal direct evaluation."""
    from hktex_engine.render import mitsuba as rm

    asked = []

    def fn(f, b):
        asked.append(f.clone())
        return torch.stack([f.float() / 10.0, b[:, 1], b[:, 2]], dim=1).clamp(0, 1)

    def lanes(face, u, v, valid):
        return (
            torch.tensor(face, dtype=torch.int32),
            torch.tensor(u, dtype=torch.float32),
            torch.tensor(v, dtype=torch.float32),
            torch.tensor(valid),
        )

    def direct(face, u, v, valid):
        f = torch.tensor(face)
        b = torch.tensor([[1.0 - a - c, a, c] for a, c in zip(u, v, strict=True)])
        out = rm.srgb_to_linear(fn(f, b).numpy()) * np.asarray(valid, dtype=np.float32)[:, None]
        asked.clear()
        return out

    memo = rm._BounceMemo()
    first = ([1, 2, 3, 4], [0.1, 0.2, 0.3, 0.4], [0.1, 0.1, 0.1, 0.1], [True, False, True, True])
    got = memo.answer(fn, *lanes(*first)).numpy()
    assert [a.tolist() for a in asked] == [[1, 3, 4]]
    asked.clear()
    np.testing.assert_allclose(got, direct(*first), atol=1e-7)
    # hits 1, 3 and 4 again in order with new ones between; hit 4's v differs in its last bit
    v4 = float(np.nextafter(np.float32(0.1), np.float32(1)))
    second = ([9, 1, 3, 8, 4], [0.5, 0.1, 0.3, 0.2, 0.4], [0.2, 0.1, 0.1, 0.3, v4], [True] * 5)
    got = memo.answer(fn, *lanes(*second)).numpy()
    assert [a.tolist() for a in asked] == [[9, 8, 4]]
    asked.clear()
    np.testing.assert_allclose(got, direct(*second), atol=1e-7)
    assert (memo.asked, memo.evaluated) == (8, 6)


def test_distinct_rows_equals_a_row_wise_unique_even_under_hash_collisions(monkeypatch):
    """The point cache's keying (a verified 64-bit hash) gives exactly the equivalence classes
    of ``torch.unique(dim=0)``; with a hash that collides on every row it still does (the
    verification sends it to the row-wise path)."""
    import hktex_engine.render.mitsuba as rm

    rng = np.random.default_rng(0)
    base = torch.as_tensor(rng.integers(-(2**31), 2**31, size=(500, 3)), dtype=torch.long)
    keys = base[torch.as_tensor(rng.integers(0, 500, size=3000))]  # many repeats
    _, ref = torch.unique(keys, dim=0, return_inverse=True)

    def same_classes(inv: torch.Tensor) -> bool:
        pairs = torch.stack([inv, ref], 1)
        return (
            torch.unique(pairs, dim=0).shape[0] == torch.unique(ref).shape[0] == int(inv.max() + 1)
        )

    inv, count = rm._distinct_rows(keys)
    assert count == int(ref.max()) + 1 and same_classes(inv)
    monkeypatch.setattr(rm, "_HASH_MULT", (0, 0, 0))  # every row hashes to 0
    inv, count = rm._distinct_rows(keys)
    assert count == int(ref.max()) + 1 and same_classes(inv)
