"""Straightest geodesics and transport, each checked against an independent computation.

Flat patches and a (developable) cylinder give closed forms: straight lines in the plane or
in the unrolled strip, and transport that is the identity there. On the icosphere, potpourri3d
(geometry-central) traces the same straightest geodesics between vertices; through a vertex
it turns by pi instead of half the cone angle, so vertex crossings are checked instead by
measuring the angles on both sides of the path around the vertex's fan, directly in 3-D.
"""

from __future__ import annotations

import igl
import numpy as np
import pytest
import torch

from hktex_engine.errors import DegenerateFacesError, NonManifoldError, QueryError
from hktex_engine.evaluation import synthetic
from hktex_engine.geometry.geodesics import SurfaceTracer

# ------------------------------------------------------------------ small test meshes


def grid_patch(n: int = 10, half: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Flat square [-half, half]^2 in z = 0, n x n quads split along alternating diagonals.

    Local rather than ``synthetic.grid_patch`` (one diagonal everywhere): alternating
    diagonals give interior vertices of valence 4 and 8, so straight lines through vertices
    meet fans of both kinds.
    """
    x, y = np.meshgrid(np.linspace(-half, half, n + 1), np.linspace(-half, half, n + 1))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    flip = ((np.arange(n)[:, None] + np.arange(n)[None, :]) % 2).ravel().astype(bool)
    F1 = np.where(flip[:, None], np.c_[a, b, c], np.c_[a, b, d])
    F2 = np.where(flip[:, None], np.c_[a, c, d], np.c_[b, c, d])
    return V, np.r_[F1, F2]


def open_cylinder(
    radius: float = 0.5, sections: int = 24, rows: int = 8, height: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Polygonal tube without caps (a developable surface with two boundary loops)."""
    return synthetic.cylinder(sections, rows + 1, radius=radius, height=height)


def icosphere(level: int = 2) -> tuple[np.ndarray, np.ndarray]:
    return synthetic.icosphere(level)


# ------------------------------------------------------------------ helpers


def cylinder_unrolled_point(
    radius: float, sections: int, s: np.ndarray, z: np.ndarray
) -> np.ndarray:
    """3-D point on the polygonal tube at arc length s (from angle 0) and height z."""
    side = 2 * radius * np.sin(np.pi / sections)
    s = np.mod(s, side * sections)
    k = np.floor(s / side).astype(int)
    t = (s - k * side) / side
    a0, a1 = 2 * np.pi * k / sections, 2 * np.pi * (k + 1) / sections
    p0 = np.c_[np.cos(a0), np.sin(a0)] * radius
    p1 = np.c_[np.cos(a1), np.sin(a1)] * radius
    return np.c_[(1 - t)[:, None] * p0 + t[:, None] * p1, z]


def cylinder_unrolled_coords(radius: float, sections: int, p: np.ndarray) -> np.ndarray:
    """Inverse of the above: arc length along the polygon for points on the tube."""
    side = 2 * radius * np.sin(np.pi / sections)
    ang = np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi)
    k = np.floor(ang / (2 * np.pi / sections)).astype(int) % sections
    a0 = 2 * np.pi * k / sections
    p0 = np.c_[np.cos(a0), np.sin(a0)] * radius
    return k * side + np.linalg.norm(p[:, :2] - p0, axis=1)


def fan_polar_angles(V: np.ndarray, F: np.ndarray, vid: int, dirs: np.ndarray):
    """Polar angle of each 3-D direction around vertex ``vid``, by walking its fan in 3-D.

    Independent of the tracer: orders the one-ring by shared vertices, accumulates corner
    angles with arccos, and finds the face plane each direction lies in.
    """
    ring = [int(g) for g in np.nonzero((F == vid).any(1))[0]]
    used: set[int] = set()
    first = F[ring[0]]
    edge_v = [int(x) for x in first if x != vid][0]
    fan, acc = [], 0.0
    while True:
        cand = [g for g in ring if g not in used and edge_v in F[g]]
        if not cand:
            break
        g = cand[0]
        used.add(g)
        other = [int(x) for x in F[g] if x not in (vid, edge_v)][0]
        a, b = V[edge_v] - V[vid], V[other] - V[vid]
        beta = np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
        fan.append((a, b, beta, acc))
        acc += beta
        edge_v = other
    out = []
    for d in dirs:
        found = None
        for a, b, beta, acc0 in fan:
            nrm = np.cross(a, b)
            if abs(d @ nrm) > 1e-7 * np.linalg.norm(d) * np.linalg.norm(nrm):
                continue
            ang_a = np.arccos(np.clip(a @ d / np.linalg.norm(a) / np.linalg.norm(d), -1, 1))
            ang_b = np.arccos(np.clip(b @ d / np.linalg.norm(b) / np.linalg.norm(d), -1, 1))
            if abs(ang_a + ang_b - beta) < 1e-7:
                found = acc0 + ang_a
        out.append(found)
    return out, acc


def assert_valid_bary(tr: SurfaceTracer, faces, bary) -> None:
    faces, bary = np.asarray(faces), np.asarray(bary)
    assert np.all((faces >= 0) & (faces < tr.n_faces))
    assert np.isfinite(bary).all()
    assert bary.min() >= -1e-12
    np.testing.assert_allclose(bary.sum(1), 1.0, atol=1e-12)


def random_starts(tr: SurfaceTracer, rng: np.random.Generator, n: int):
    f = rng.integers(0, tr.n_faces, n)
    b = rng.dirichlet([1.0, 1.0, 1.0], n)
    return f, b


# ------------------------------------------------------------------ flat patches


def test_flat_patch_paths_are_straight_and_transport_is_identity():
    V, F = grid_patch(12)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(0)
    f, b = random_starts(tr, rng, 3000)
    p = tr.points(f, b)
    ang = rng.uniform(0, 2 * np.pi, 3000)
    length = rng.uniform(0, 0.8, 3000)
    v = np.c_[np.cos(ang), np.sin(ang), np.zeros(3000)] * length[:, None]
    other = rng.normal(size=(3000, 3))
    res = tr.trace_full(f, b, v, transport=other)
    target = p + v
    inside = (np.abs(target[:, :2]) < 1 - 1e-9).all(1)
    assert inside.sum() > 2000
    np.testing.assert_allclose(res.points.numpy()[inside], target[inside], atol=1e-12)
    np.testing.assert_allclose(res.vectors.numpy()[inside], v[inside], atol=1e-12)
    flat_other = other * np.array([1.0, 1.0, 0.0])  # projected to the plane z = 0
    np.testing.assert_allclose(res.transported.numpy()[inside, 0], flat_other[inside], atol=1e-12)
    assert not res.hit_boundary.numpy()[inside].any()
    assert_valid_bary(tr, res.face_ids, res.bary)


def test_paths_through_vertices_stay_straight_on_flat_patch():
    """Start exactly at vertices and aim exactly through others (axis, diagonal, knight)."""
    V, F = grid_patch(10)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(1)
    n = 2000
    f = rng.integers(0, tr.n_faces, n)
    b = np.eye(3)[rng.integers(0, 3, n)]
    p = tr.points(f, b)
    dirs = np.array([[1, 0], [0, 1], [1, 1], [1, -1], [-1, -1], [-1, 0], [2, 1], [1, -2]], float)
    dd = dirs[rng.integers(0, len(dirs), n)]
    dd /= np.linalg.norm(dd, axis=1, keepdims=True)
    v = np.c_[dd, np.zeros(n)] * rng.uniform(0, 1.5, n)[:, None]
    perp = np.c_[-dd[:, 1], dd[:, 0], np.zeros(n)]
    res = tr.trace_full(f, b, v, transport=perp)
    target = p + v
    inside = (np.abs(target[:, :2]) < 1 - 1e-9).all(1)
    assert inside.sum() > 500
    np.testing.assert_allclose(res.points.numpy()[inside], target[inside], atol=1e-9)
    np.testing.assert_allclose(res.vectors.numpy()[inside], v[inside], atol=1e-9)
    np.testing.assert_allclose(res.transported.numpy()[inside, 0], perp[inside], atol=1e-9)
    assert_valid_bary(tr, res.face_ids, res.bary)


def test_boundary_stops_path_where_the_line_leaves_the_square():
    V, F = grid_patch(8)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(2)
    n = 3000
    f, b = random_starts(tr, rng, n)
    p = tr.points(f, b)
    ang = rng.uniform(0, 2 * np.pi, n)
    u = np.c_[np.cos(ang), np.sin(ang), np.zeros(n)]
    res = tr.trace_full(f, b, u * 5.0)  # longer than the square: every path hits the boundary
    assert res.hit_boundary.all()
    # Independent: distance along u to the square's border.
    with np.errstate(divide="ignore"):
        tx = np.where(u[:, 0] > 0, (1 - p[:, 0]) / u[:, 0], (-1 - p[:, 0]) / u[:, 0])
        ty = np.where(u[:, 1] > 0, (1 - p[:, 1]) / u[:, 1], (-1 - p[:, 1]) / u[:, 1])
    t_exit = np.minimum(np.abs(tx), np.abs(ty))
    np.testing.assert_allclose(res.length.numpy(), t_exit, atol=1e-9)
    np.testing.assert_allclose(res.points.numpy(), p + u * t_exit[:, None], atol=1e-9)
    assert_valid_bary(tr, res.face_ids, res.bary)


# ------------------------------------------------------------------ cylinder (developable)


def test_cylinder_circumference_closes():
    r, k = 0.5, 24
    V, F = open_cylinder(r, k)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(3)
    f, b = random_starts(tr, rng, 200)
    p = tr.points(f, b)
    perimeter = k * 2 * r * np.sin(np.pi / k)
    tangent = np.cross(np.array([0.0, 0.0, 1.0]), tr.normals[f].numpy())
    res = tr.trace_full(f, b, tangent * perimeter)
    np.testing.assert_allclose(res.points.numpy(), p, atol=1e-12)
    np.testing.assert_allclose(res.vectors.numpy(), tangent * perimeter, atol=1e-12)
    assert not res.hit_boundary.any()


def test_cylinder_helix_matches_unrolled_line_and_transport():
    r, k = 0.5, 24
    V, F = open_cylinder(r, k, rows=10)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(4)
    n = 1000
    f, b = random_starts(tr, rng, n)
    p = tr.points(f, b)
    s0 = cylinder_unrolled_coords(r, k, p)
    nrm = tr.normals[f].numpy()
    circ = np.cross(np.array([0.0, 0.0, 1.0]), nrm)  # unit, counter-clockwise seen from +z
    axial = np.tile([0.0, 0.0, 1.0], (n, 1))
    ang = rng.uniform(-0.45 * np.pi, 0.45 * np.pi, n)
    length = rng.uniform(0.1, 6.0, n)  # up to about two turns
    ca, sa = np.cos(ang) * length, np.sin(ang) * length
    v = ca[:, None] * circ + sa[:, None] * axial
    w_a, w_c = rng.normal(size=n), rng.normal(size=n)
    other = w_c[:, None] * circ + w_a[:, None] * axial
    res = tr.trace_full(f, b, v, transport=other)
    z_end = p[:, 2] + sa
    inside = np.abs(z_end) < 1 - 1e-9
    assert inside.sum() > 300
    expected = cylinder_unrolled_point(r, k, s0 + ca, z_end)
    np.testing.assert_allclose(res.points.numpy()[inside], expected[inside], atol=1e-9)
    # In the unrolled strip transport is the identity: components along (circ, axial) stay.
    fe = res.face_ids.numpy()
    circ_end = np.cross(np.array([0.0, 0.0, 1.0]), tr.normals[fe].numpy())
    got = res.transported.numpy()[:, 0]
    np.testing.assert_allclose((got * circ_end).sum(1)[inside], w_c[inside], atol=1e-9)
    np.testing.assert_allclose(got[inside, 2], w_a[inside], atol=1e-9)
    vec = res.vectors.numpy()
    np.testing.assert_allclose((vec * circ_end).sum(1)[inside], ca[inside], atol=1e-9)
    # Those that leave through a rim stop on it.
    out = ~inside
    np.testing.assert_allclose(np.abs(res.points.numpy()[out, 2]), 1.0, atol=1e-9)
    assert res.hit_boundary.numpy()[out].all()


# ------------------------------------------------------------------ curved: icosphere


def test_icosphere_matches_potpourri3d_between_vertices():
    pp3d = pytest.importorskip("potpourri3d")
    V, F = icosphere(3)
    tr = SurfaceTracer(V, F)
    ref_tracer = pp3d.GeodesicTracer(V, F)
    rng = np.random.default_rng(5)
    n = 200
    f, b = random_starts(tr, rng, n)
    v = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    length = rng.uniform(0.01, 2.0, n)
    v *= (length / np.linalg.norm(v, axis=1))[:, None]
    res = tr.trace_full(f, b, v)
    ref = np.array(
        [
            ref_tracer.trace_geodesic_from_face(int(a), bb, vv)[-1]
            for a, bb, vv in zip(f, b, v, strict=True)
        ]
    )
    # A random path meets a vertex with probability ~0, where the two definitions agree.
    np.testing.assert_allclose(res.points.numpy(), ref, atol=1e-9)
    chord = np.linalg.norm(res.points.numpy() - tr.points(f, b), axis=1)
    assert np.all(chord <= length + 1e-12)
    assert_valid_bary(tr, res.face_ids, res.bary)


def test_transport_preserves_length_and_angle_to_path_on_sphere():
    V, F = icosphere(2)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(6)
    n = 2000
    f, b = random_starts(tr, rng, n)
    v = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    v *= (rng.uniform(0.05, 3.0, n) / np.linalg.norm(v, axis=1))[:, None]
    other = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    res = tr.trace_full(f, b, v, transport=other)
    got, tang = res.transported.numpy()[:, 0], res.vectors.numpy()
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), np.linalg.norm(other, axis=1))
    np.testing.assert_allclose(np.linalg.norm(tang, axis=1), np.linalg.norm(v, axis=1))
    # Signed angle to the path's direction, in each end's own (oriented) face frame.
    n0, n1 = tr.normals[f].numpy(), tr.normals[res.face_ids].numpy()

    def signed(a, x, nrm):
        return np.arctan2((np.cross(a, x) * nrm).sum(1), (a * x).sum(1))

    np.testing.assert_allclose(signed(tang, got, n1), signed(v, other, n0), atol=1e-9)
    # End vectors lie in the end face's plane.
    np.testing.assert_allclose((got * n1).sum(1), 0, atol=1e-12)
    np.testing.assert_allclose((tang * n1).sum(1), 0, atol=1e-12)


def test_vertex_crossing_leaves_with_half_the_cone_angle_on_each_side():
    V, F = icosphere(2)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(7)
    for _ in range(20):
        fi = int(rng.integers(0, len(F)))
        b = rng.dirichlet([2.0, 2.0, 2.0])
        corner = int(rng.integers(0, 3))
        vid = int(F[fi, corner])
        p = tr.points([fi], b[None])[0]
        to_v = V[vid] - p
        dist = np.linalg.norm(to_v)
        u = to_v / dist
        other = tr.project_to_tangent([fi], rng.normal(size=(1, 3)))
        res = tr.trace_full([fi], b[None], (u * (dist + 0.02))[None], transport=other)
        q = res.points.numpy()[0]
        # Transport through the vertex keeps the vector's signed angle to the path.
        n0, n1 = tr.normals[fi].numpy(), tr.normals[int(res.face_ids[0])].numpy()
        out_dir = res.vectors.numpy()[0]
        got = res.transported.numpy()[0, 0]
        before = np.arctan2(np.cross(u, other[0]) @ n0, u @ other[0])
        after = np.arctan2(np.cross(out_dir, got) @ n1, out_dir @ got)
        assert after == pytest.approx(before, abs=1e-9)
        assert np.linalg.norm(q - V[vid]) == pytest.approx(0.02, abs=1e-12)
        (a_in, a_out), theta = fan_polar_angles(V, F, vid, [p - V[vid], q - V[vid]])
        assert theta == pytest.approx(float(tr.angle_sum[vid]), abs=1e-12)
        assert (a_out - a_in) % theta == pytest.approx(theta / 2, abs=1e-9)


# ------------------------------------------------------------------ robustness


@pytest.mark.parametrize("mesh", ["grid", "cylinder", "sphere", "torus"])
def test_centres_never_leave_the_surface(mesh):
    """Thousands of paths, many through vertices or into boundaries: all end valid."""
    V, F = {
        "grid": grid_patch(6),
        "cylinder": open_cylinder(0.5, 12, 4),
        "sphere": icosphere(1),
        "torus": synthetic.torus(12, 6),
    }[mesh]
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(8)
    n = 4000
    f = rng.integers(0, tr.n_faces, n)
    b = rng.dirichlet([1.0, 1.0, 1.0], n)
    kind = rng.integers(0, 3, n)  # interior / at a vertex / on an edge
    b[kind == 1] = np.eye(3)[rng.integers(0, 3, (kind == 1).sum())]
    e = kind == 2
    b[e, rng.integers(0, 3, e.sum())] = 0
    b /= b.sum(1, keepdims=True)
    p = tr.points(f, b)
    # Half aim at vertices of the mesh, half random.
    target = V[rng.integers(0, len(V), n)]
    v = np.where((rng.random(n) < 0.5)[:, None], target - p, rng.normal(size=(n, 3)))
    v = tr.project_to_tangent(f, v) * rng.uniform(0, 3, n)[:, None]
    v[::50] = 0.0
    res = tr.trace_full(f, b, v)
    assert_valid_bary(tr, res.face_ids, res.bary)
    for arr in (res.points, res.vectors, res.length):
        assert torch.isfinite(arr).all()
    assert not res.capped.any()
    assert np.all(res.length.numpy() <= np.linalg.norm(v, axis=1) + 1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(res.vectors.numpy(), axis=1), np.linalg.norm(v, axis=1), atol=1e-12
    )
    if mesh in ("sphere", "torus"):
        assert not res.hit_boundary.any()
    # The end point really is on the surface: distance to the mesh is ~0.
    sq, _, _ = igl.point_mesh_squared_distance(res.points.numpy(), V, F)
    assert np.sqrt(sq.max()) < 1e-9
    # Zero vectors: start point unchanged.
    np.testing.assert_array_equal(res.face_ids.numpy()[::50], f[::50])
    np.testing.assert_allclose(res.bary.numpy()[::50], b[::50], atol=1e-15)


def _batch_vs_single(n_paths: int, n_single: int) -> None:
    V, F = icosphere(2)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(9)
    f, b = random_starts(tr, rng, n_paths)
    v = rng.normal(size=(n_paths, 3)) * 0.3
    fb, bb, vb = tr.trace(f, b, v)
    for i in rng.choice(n_paths, n_single, replace=False):
        fs, bs, vs = tr.trace(f[i : i + 1], b[i : i + 1], v[i : i + 1])
        assert fs[0] == fb[i]
        np.testing.assert_allclose(bs[0], bb[i], atol=1e-13)
        np.testing.assert_allclose(vs[0], vb[i], atol=1e-13)


def test_batch_equals_one_at_a_time_subset():
    _batch_vs_single(5000, 150)


@pytest.mark.slow
def test_batch_equals_one_at_a_time_all():
    _batch_vs_single(5000, 5000)


def test_torch_in_torch_out_and_numpy_in_numpy_out():
    V, F = icosphere(1)
    tr = SurfaceTracer(torch.as_tensor(V), torch.as_tensor(F))
    f = torch.tensor([0, 5, 7])
    b = torch.full((3, 3), 1 / 3, dtype=torch.float32)
    v = torch.randn(3, 3, dtype=torch.float32) * 0.2
    fe, be, ve = tr.trace(f, b, v)
    assert fe.dtype == torch.long and be.dtype == torch.float32 and ve.dtype == torch.float32
    fn, bn, vn = tr.trace(f.numpy(), b.double().numpy(), v.double().numpy())
    assert isinstance(fn, np.ndarray) and fn.dtype == np.int64
    np.testing.assert_array_equal(fn, fe.numpy())
    np.testing.assert_allclose(bn, be.double().numpy(), atol=1e-6)
    proj = tr.project_to_tangent(f, v)
    assert torch.allclose(
        (proj.double() * tr.normals[f]).sum(1), torch.zeros(3, dtype=torch.float64), atol=1e-6
    )


def test_iteration_cap_warns_and_stays_on_surface():
    V, F = icosphere(2)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(10)
    f, b = random_starts(tr, rng, 50)
    v = tr.project_to_tangent(f, rng.normal(size=(50, 3)))
    with pytest.warns(RuntimeWarning, match="cap"):
        res = tr.trace_full(f, b, v * 3, max_steps=2)
    assert res.capped.any()
    assert_valid_bary(tr, res.face_ids, res.bary)
    assert np.all(
        res.length.numpy()[res.capped.numpy()] < 3 * np.linalg.norm(v, axis=1)[res.capped.numpy()]
    )


def test_bad_input_raises_specific_errors():
    V, F = icosphere(1)
    tr = SurfaceTracer(V, F)
    ok_b = np.full((1, 3), 1 / 3)
    with pytest.raises(QueryError):
        tr.trace([len(F)], ok_b, np.zeros((1, 3)))
    with pytest.raises(QueryError):
        tr.trace([0], np.array([[0.5, 0.6, -0.1]]), np.zeros((1, 3)))
    with pytest.raises(QueryError):
        tr.trace([0], ok_b, np.array([[np.nan, 0, 0]]))
    with pytest.raises(QueryError):
        tr.trace([0], ok_b, np.zeros((2, 3)))
    with pytest.raises(QueryError):
        tr.trace([0.5], ok_b, np.zeros((1, 3)))
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge (0,1) in three faces
    with pytest.raises(NonManifoldError):
        SurfaceTracer(np.random.default_rng(0).normal(size=(5, 3)), fan)
    with pytest.raises(DegenerateFacesError):
        SurfaceTracer(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("mesh", ["grid", "sphere"])
def test_face_orientation_does_not_matter(mesh):
    """Flipping some faces' vertex order changes no end point, direction or transport."""
    V, F = {"grid": grid_patch(6), "sphere": icosphere(2)}[mesh]
    rng = np.random.default_rng(11)
    flip = rng.random(len(F)) < 0.4
    F2 = F.copy()
    F2[flip] = F2[flip][:, ::-1]
    tr1, tr2 = SurfaceTracer(V, F), SurfaceTracer(V, F2)
    n = 1500
    f, b = random_starts(tr1, rng, n)
    b2 = np.where(flip[f][:, None], b[:, ::-1], b)
    p = tr1.points(f, b)
    np.testing.assert_allclose(tr2.points(f, b2), p, atol=1e-15)
    target = V[rng.integers(0, len(V), n)]  # many paths through vertices
    v = np.where((rng.random(n) < 0.5)[:, None], target - p, rng.normal(size=(n, 3)))
    v = tr1.project_to_tangent(f, v) * rng.uniform(0, 2, n)[:, None]
    other = rng.normal(size=(n, 3))
    r1 = tr1.trace_full(f, b, v, transport=other)
    r2 = tr2.trace_full(f, b2, v, transport=other)
    np.testing.assert_allclose(r1.points.numpy(), r2.points.numpy(), atol=1e-9)
    np.testing.assert_allclose(r1.vectors.numpy(), r2.vectors.numpy(), atol=1e-9)
    np.testing.assert_allclose(r1.transported.numpy(), r2.transported.numpy(), atol=1e-9)


def test_start_on_boundary_vertex_moves_inward_and_stops_outward():
    V, F = grid_patch(4)
    tr = SurfaceTracer(V, F)
    corner_v = int(np.argmin(V[:, 0] + V[:, 1]))  # (-1, -1)
    faces = np.nonzero((F == corner_v).any(1))[0]
    f = np.full(4, faces[0])
    b = np.zeros((4, 3))
    b[:, list(F[faces[0]]).index(corner_v)] = 1.0
    v = np.array([[0.3, 0.3, 0], [0.5, 0.01, 0], [-0.2, 0.0, 0], [0.1, -0.3, 0]])
    res = tr.trace_full(f, b, v)
    pts = res.points.numpy()
    np.testing.assert_allclose(pts[:2], V[corner_v] + v[:2], atol=1e-12)
    assert not res.hit_boundary.numpy()[:2].any()
    np.testing.assert_allclose(pts[2:], V[[corner_v, corner_v]], atol=1e-12)
    assert res.hit_boundary.numpy()[2:].all()
    np.testing.assert_allclose(res.length.numpy()[2:], 0.0, atol=1e-15)


def test_spot_matches_potpourri3d(shared_data):
    """A real, irregular mesh (merged by position, normalised): optimiser-sized and long steps."""
    pp3d = pytest.importorskip("potpourri3d")
    from hktex_engine.geometry.mesh import load_mesh

    mesh = load_mesh(shared_data / "spot" / "spot_triangulated.obj")
    V, F = mesh.vertices, mesh.faces
    tr = SurfaceTracer(V, F)
    ref_tracer = pp3d.GeodesicTracer(V, F)
    rng = np.random.default_rng(12)
    n = 150
    f, b = random_starts(tr, rng, n)
    v = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    v *= (rng.choice([0.001, 0.01, 0.05, 0.5], n) / np.linalg.norm(v, axis=1))[:, None]
    res = tr.trace_full(f, b, v)
    ref = np.array(
        [
            ref_tracer.trace_geodesic_from_face(int(a), bb, vv)[-1]
            for a, bb, vv in zip(f, b, v, strict=True)
        ]
    )
    np.testing.assert_allclose(res.points.numpy(), ref, atol=1e-9)
    assert_valid_bary(tr, res.face_ids, res.bary)


def test_walking_back_returns_start_point_and_vector():
    """exp then exp of the reversed end tangent retraces the path (incl. through vertices)."""
    V, F = icosphere(2)
    tr = SurfaceTracer(V, F)
    rng = np.random.default_rng(13)
    n = 1000
    f, b = random_starts(tr, rng, n)
    p = tr.points(f, b)
    target = V[rng.integers(0, len(V), n)]
    v = np.where((rng.random(n) < 0.5)[:, None], target - p, rng.normal(size=(n, 3)))
    v = tr.project_to_tangent(f, v) * rng.uniform(0.1, 2.0, n)[:, None]
    w = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    there = tr.trace_full(f, b, v, transport=w)
    back = tr.trace_full(there.face_ids, there.bary, -there.vectors, transport=there.transported)
    np.testing.assert_allclose(back.points.numpy(), p, atol=1e-9)
    np.testing.assert_allclose(back.vectors.numpy(), -v, atol=1e-9)
    np.testing.assert_allclose(back.transported.numpy()[:, 0], w, atol=1e-9)
