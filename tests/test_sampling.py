"""Surface sampling, texture lookup, closest points and farthest-point sampling."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage, stats

from hktex_engine.errors import QueryError
from hktex_engine.evaluation.synthetic import grid_patch, icosphere
from hktex_engine.geometry.sampling import (
    closest_surface_point,
    face_areas,
    farthest_point_sampling,
    points_from_barycentric,
    sample_surface,
    texture_lookup,
    uv_at,
)


def uneven_patch():
    """A flat patch whose triangles have very different areas."""
    v, f = grid_patch(5, 4)
    v = v.copy()
    v[:, 0] = v[:, 0] ** 2  # squeeze the columns towards x = 0
    return v, f


def test_sampling_is_area_uniform_per_face():
    v, f = uneven_patch()
    area = face_areas(v, f)
    face_ids, bary = sample_surface(v, f, 40000, np.random.default_rng(3))
    counts = np.bincount(face_ids, minlength=len(f))
    expected = 40000 * area / area.sum()
    assert stats.chisquare(counts, expected).pvalue > 1e-3
    assert np.all(bary >= 0) and np.allclose(bary.sum(axis=1), 1.0)


def test_sampling_is_uniform_inside_a_face():
    v = np.array([[0.0, 0, 0], [3, 0, 0], [0, 1, 0]])
    face_ids, bary = sample_surface(v, np.array([[0, 1, 2]]), 40000, 5)
    # Uniform in a triangle: each barycentric is Beta(1, 2) (mean 1/3); a corner sub-triangle
    # (b_i > 1/2) holds a quarter of the area.
    np.testing.assert_allclose(bary.mean(axis=0), 1 / 3, atol=0.005)
    np.testing.assert_allclose((bary > 0.5).mean(axis=0), 0.25, atol=0.01)
    assert stats.kstest(bary[:, 1], stats.beta(1, 2).cdf).pvalue > 1e-3


def test_sampling_is_deterministic():
    v, f = icosphere(1)
    a = sample_surface(v, f, 100, 7)
    b = sample_surface(v, f, 100, np.random.default_rng(7))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_points_and_uvs_from_barycentric():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 4, 0]])
    f = np.array([[0, 1, 2]])
    bary = np.array([[0.5, 0.25, 0.25]])
    np.testing.assert_allclose(points_from_barycentric(v, f, [0], bary), [[0.5, 1.0, 0.0]])
    uvs = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    np.testing.assert_allclose(uv_at(uvs, [0], bary), [[0.25, 0.25]])


def test_texture_lookup_hand_values_and_v_flip():
    # 2 rows x 3 columns; row 0 is the TOP of the image.
    tex = np.array(
        [[[0.0], [1.0], [2.0]], [[10.0], [11.0], [12.0]]],
    )
    h, w = 2, 3
    # Texel centre of the bottom-left texel (row 1, col 0) is uv = (0.5/w, 0.5/h).
    np.testing.assert_allclose(texture_lookup(tex, [[0.5 / w, 0.5 / h]]), [[10.0]])
    np.testing.assert_allclose(texture_lookup(tex, [[0.5 / w, 1.5 / h]]), [[0.0]])
    # Halfway between columns 0 and 1 and a quarter of the way from the bottom row up:
    # x = 1, y = 0.5 -> 0.75 * bottom + 0.25 * top of the column mean.
    uv = [[1.0 / w, 0.75 / h]]
    expected = 0.75 * (10 + 11) / 2 + 0.25 * (0 + 1) / 2
    np.testing.assert_allclose(texture_lookup(tex, uv), [[expected]])


def test_texture_lookup_wraps_and_matches_scipy():
    rng = np.random.default_rng(0)
    tex = rng.random((5, 7, 3))
    uv = rng.uniform(-1.5, 2.5, size=(200, 2))
    got = texture_lookup(tex, uv)
    np.testing.assert_allclose(texture_lookup(tex, uv + [1.0, -2.0]), got, atol=1e-12)
    # Independent: scipy's periodic linear interpolation on image coordinates.
    rows = (1.0 - uv[:, 1]) * 5 - 0.5
    cols = uv[:, 0] * 7 - 0.5
    ref = np.stack(
        [
            ndimage.map_coordinates(tex[..., c], [rows, cols], order=1, mode="grid-wrap")
            for c in range(3)
        ],
        axis=1,
    )
    np.testing.assert_allclose(got, ref, atol=1e-12)


def _brute_closest(v, f, points, res=50):
    """Dense barycentric grid over every face: an upper bound close to the true distance."""
    i, j = np.meshgrid(np.arange(res + 1), np.arange(res + 1), indexing="ij")
    keep = i + j <= res
    b1, b2 = i[keep] / res, j[keep] / res
    bary = np.stack([1 - b1 - b2, b1, b2], axis=1)
    dense = np.einsum("gc,fcd->fgd", bary, v[f]).reshape(-1, 3)
    d2 = ((points[:, None, :] - dense[None]) ** 2).sum(-1)
    return np.sqrt(d2.min(axis=1))


def test_closest_surface_point_against_brute_force():
    v, f = icosphere(1)
    rng = np.random.default_rng(1)
    points = rng.normal(size=(40, 3)) * 0.8
    face_ids, bary = closest_surface_point(v, f, points)
    assert np.all(bary >= 0) and np.allclose(bary.sum(axis=1), 1.0)
    found = points_from_barycentric(v, f, face_ids, bary)
    dist = np.linalg.norm(points - found, axis=1)
    brute = _brute_closest(v, f, points)
    # brute >= true distance, and within the grid spacing of it.
    assert np.all(dist <= brute + 1e-9)
    assert np.all(brute - dist < 0.015)


def test_closest_surface_point_of_surface_points_is_itself():
    v, f = icosphere(2)
    face_ids, bary = sample_surface(v, f, 200, 4)
    points = points_from_barycentric(v, f, face_ids, bary)
    got_f, got_b = closest_surface_point(v, f, points)
    np.testing.assert_allclose(points_from_barycentric(v, f, got_f, got_b), points, atol=1e-9)


def test_closest_surface_point_rejects_bad_queries():
    v, f = icosphere(0)
    with pytest.raises(QueryError):
        closest_surface_point(v, f, np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(QueryError):
        closest_surface_point(v, f, np.zeros((3, 2)))


def _greedy_fps(points, k, first):
    """Textbook greedy FPS with a full distance matrix."""
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    chosen = [first]
    for _ in range(k - 1):
        chosen.append(int(np.argmax(d[:, chosen].min(axis=1))))
    return np.array(chosen)


def test_farthest_point_sampling_matches_brute_force_greedy():
    points = np.random.default_rng(2).random((300, 4))
    idx = farthest_point_sampling(points, 25, rng=11)
    first = int(np.random.default_rng(11).integers(300))
    np.testing.assert_array_equal(idx, _greedy_fps(points, 25, first))
    assert len(set(idx.tolist())) == 25


def test_farthest_point_sampling_torch_path_agrees():
    torch = pytest.importorskip("torch")
    points = np.random.default_rng(3).random((200, 3))
    a = farthest_point_sampling(points, 20, rng=1)
    b = farthest_point_sampling(torch.as_tensor(points), 20, rng=1)
    np.testing.assert_array_equal(a, b)
    from hktex_engine.geometry.sampling import _fps_torch

    np.testing.assert_array_equal(_fps_torch(torch.as_tensor(points), 20, int(a[0])), a)
