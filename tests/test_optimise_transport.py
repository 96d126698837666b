"""Kernel orientation across faces: theta re-expressed after centre steps and splits.

theta is measured from the centre face's u_ref. With transport on, a centre that changes face
keeps its long axis in 3-D (parallel-transported). Expected answers come from geometry that
does not use the code under test: on a plane the axis is unchanged, on a cylinder transport
keeps the (around, along) components, on a sphere the axis keeps its signed angle to the
geodesic. The last tests pin why transport is off by default: with the real kernel model the
response of a kernel with a fixed theta is continuous as its centre crosses an edge, and
re-expressing theta makes it jump.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hktex_engine.config import FitParams
from hktex_engine.evaluation.synthetic import cylinder, grid_patch, icosphere
from hktex_engine.fitting.density import DensityController
from hktex_engine.fitting.optimise import (
    KernelOptimiser,
    _AdamRows,
    axis_pair,
    face_unit_normals,
    long_axis,
    theta_in_faces,
)
from hktex_engine.geometry.geodesics import SurfaceTracer
from tests.fitting_standins import FlatTracer, ToyModel, ToyObjective, flat_patch

DT = torch.float64


def _random_frames(v: np.ndarray, f: np.ndarray, rng) -> np.ndarray:
    """A different u_ref per face: a random in-plane unit vector."""
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r = rng.normal(size=(len(f), 3))
    r -= (r * n).sum(1, keepdims=True) * n
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def _random_centres(v: np.ndarray, f: np.ndarray, rng, n: int):
    """Random per-face frames and ``n`` kernel centres (face, barycentric, theta) on (v, f)."""
    frames = _random_frames(v, f, rng)
    fid = rng.integers(0, len(f), n)
    bary = rng.dirichlet(np.ones(3), n)
    theta = rng.uniform(0, math.pi, n)
    return frames, fid, bary, theta


def _setup(v, f, frames, fid, bary, theta, lr=1.0):
    """ToyModel + KernelOptimiser with frames; only centres take a step (lr_centers = lr)."""
    model = ToyModel(v, f, fid, bary)
    with torch.no_grad():
        model.theta.copy_(torch.as_tensor(theta, dtype=DT))
    params = FitParams(kernels=len(fid), steps=10, lr_centers=lr)
    verts, faces = torch.as_tensor(v, dtype=DT), torch.as_tensor(f)
    opt = KernelOptimiser(
        model,
        params,
        SurfaceTracer(v, f),
        verts,
        faces,
        face_frames=torch.as_tensor(frames, dtype=DT),
    )
    return model, opt, verts, faces


def _step_by(model, opt, verts, faces, step_vec: torch.Tensor) -> None:
    """One optimiser step moving each centre by ``step_vec`` (in its face plane).

    dL/db_v = -step . x_v makes the tangent gradient exactly -step (g . (x_v - x_0) =
    G_v - G_0 for an in-plane g), so -lr * g = step with lr = 1.
    """
    corners = verts[faces[model.face_ids]]  # (N, 3, 3)
    model.bary.grad = -(corners * step_vec[:, None, :]).sum(-1)
    opt.step(0)
    model.bary.grad = None


def _axes(frames, normals, fid, theta) -> torch.Tensor:
    return long_axis(torch.as_tensor(frames, dtype=DT), normals, fid, theta)


def _in_plane(vec, normals, fid):
    n = normals[fid]
    return vec - (vec * n).sum(-1, keepdim=True) * n


def test_flat_patch_with_rotated_frames_keeps_3d_axes_and_adam_meaning():
    v, f = grid_patch(11, 11, size=2.0)
    f = f.copy()
    f[1::3] = f[1::3, ::-1]  # a third of the faces wound the other way (normal -z)
    rng = np.random.default_rng(0)
    n = 400
    frames, fid, bary, theta = _random_centres(v, f, rng, n)
    theta[:4] = [0.0, math.pi, 0.0, math.pi]  # the ends of the range
    model, opt, verts, faces = _setup(v, f, frames, fid, bary, theta)
    normals = face_unit_normals(verts, faces)
    # known Adam state for theta (no theta gradient this step, so only transport can touch it)
    m1 = torch.as_tensor(rng.normal(size=n), dtype=DT)
    opt.adam.state["theta"] = _AdamRows(
        m1.clone(), torch.ones(n, dtype=DT), torch.ones(n, dtype=DT)
    )
    f0 = model.face_ids.clone()
    th0 = model.theta.detach().clone()
    a0 = _axes(frames, normals, f0, th0)
    step = torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT) * 0.25
    step[:, 2] = 0
    step[4:40] = 0  # some centres do not move
    _step_by(model, opt, verts, faces, step)
    f1, th1 = model.face_ids, model.theta.detach()
    crossed = f1 != f0
    assert int(crossed.sum()) > n // 2
    assert bool(((th1 >= 0) & (th1 <= math.pi)).all())
    a1 = _axes(frames, normals, f1, th1)
    # a plane transports by the identity: the same line in 3-D (axes have no sign)
    assert torch.allclose((a0 * a1).sum(-1).abs(), torch.ones(n, dtype=DT), atol=1e-12)
    # same face: theta untouched, bit for bit
    assert torch.equal(th1[~crossed], th0[~crossed])
    # Adam's first moment still means the same rotation rate about +z in 3-D
    m_after = opt.adam.state["theta"].exp_avg
    assert torch.allclose(m_after * normals[f1, 2], m1 * normals[f0, 2], atol=0)
    assert bool((m_after[crossed] != m1[crossed]).any())  # some crossed to the other winding


def test_uniform_frames_keep_theta_continuous_at_the_range_ends():
    v, f = flat_patch(9)
    frames = np.tile([1.0, 0.0, 0.0], (len(f), 1))
    rng = np.random.default_rng(1)
    n = 60
    fid = rng.integers(0, len(f), n)
    bary = rng.dirichlet(np.ones(3), n)
    theta = np.r_[np.zeros(20), np.full(20, math.pi), rng.uniform(0, math.pi, 20)]
    model, opt, verts, faces = _setup(v, f, frames, fid, bary, theta)
    step = torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT) * 0.4
    step[:, 2] = 0
    f0 = model.face_ids.clone()
    _step_by(model, opt, verts, faces, step)
    assert int((model.face_ids != f0).sum()) > n // 2
    # the same frame everywhere: theta keeps its value, 0 stays 0 and pi stays pi
    assert torch.allclose(model.theta.detach(), torch.as_tensor(theta, dtype=DT), atol=1e-12)


def test_cylinder_axis_follows_parallel_transport():
    v, f = cylinder(24, 9, radius=1.0, height=2.0)
    rng = np.random.default_rng(2)
    n = 300
    frames, fid, bary, theta = _random_centres(v, f, rng, n)
    model, opt, verts, faces = _setup(v, f, frames, fid, bary, theta)
    normals = face_unit_normals(verts, faces)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=DT)

    def components(axis, fids):
        # unrolling the (polygonal) cylinder: around = z x n, along = z, both unit, in plane
        around = torch.linalg.cross(z.expand_as(axis), normals[fids], dim=-1)
        return torch.stack([(axis * around).sum(-1), axis[:, 2]], 1)

    f0 = model.face_ids.clone()
    c0 = components(_axes(frames, normals, f0, model.theta.detach()), f0)
    step = _in_plane(torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT), normals, f0)
    _step_by(model, opt, verts, faces, 0.6 * step)
    f1, th1 = model.face_ids, model.theta.detach()
    assert int((f1 != f0).sum()) > n // 2
    assert bool(((th1 >= 0) & (th1 <= math.pi)).all())
    c1 = components(_axes(frames, normals, f1, th1), f1)
    sign = torch.sign((c0 * c1).sum(-1, keepdim=True))  # axes have no sign
    assert torch.allclose(c1 * sign, c0, atol=1e-9)
    # and the 3-D axis really turned for centres that went some way around
    a0, a1 = _axes(frames, normals, f0, model.theta.detach()), _axes(frames, normals, f1, th1)
    assert bool(((a0 * a1).sum(-1).abs() < 0.99).any())


def _signed_angle(a, b, n):
    return torch.atan2((torch.linalg.cross(a, b, dim=-1) * n).sum(-1), (a * b).sum(-1))


def test_sphere_axis_keeps_its_angle_to_the_geodesic():
    v, f = icosphere(2)
    rng = np.random.default_rng(3)
    n = 300
    frames, fid, bary, theta = _random_centres(v, f, rng, n)
    model, opt, verts, faces = _setup(v, f, frames, fid, bary, theta)
    normals = face_unit_normals(verts, faces)
    f0 = model.face_ids.clone()
    a0 = _axes(frames, normals, f0, model.theta.detach())
    step = _in_plane(torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT), normals, f0) * 0.5
    _step_by(model, opt, verts, faces, step)
    f1, th1 = model.face_ids, model.theta.detach()
    assert int((f1 != f0).sum()) > n // 2
    a1 = _axes(frames, normals, f1, th1)
    d_end = -opt.centres.buf  # momentum 0: the buffer is the transported gradient = -step
    ang0 = _signed_angle(step, a0, normals[f0])
    ang1 = _signed_angle(d_end, a1, normals[f1])
    diff = torch.remainder(ang1 - ang0 + math.pi / 2, math.pi) - math.pi / 2  # mod pi
    assert diff.abs().max() < 1e-9


def _controller(model, v, f, frames):
    params = FitParams(kernels=len(model.face_ids), steps=100)
    verts, faces = torch.as_tensor(v, dtype=DT), torch.as_tensor(f)
    tracer = SurfaceTracer(v, f)
    fr = torch.as_tensor(frames, dtype=DT)
    ctl = DensityController(params, 100, verts, faces, fr, tracer, transport_theta=True)
    ctl.bind(model)
    return ctl, face_unit_normals(verts, faces)


@pytest.mark.parametrize("surface", ["flat", "cylinder"])
def test_split_children_keep_the_parent_axis(surface):
    rng = np.random.default_rng(4)
    if surface == "flat":
        v, f = grid_patch(11, 11, size=2.0)
        fid = np.full(60, 110)  # the middle of the patch
    else:
        v, f = cylinder(16, 9, radius=1.0, height=2.0)
        fid = rng.integers(0, len(f), 60)
    frames = _random_frames(v, f, rng)
    n = len(fid)
    model = ToyModel(v, f, fid, rng.dirichlet(np.ones(3), n))
    with torch.no_grad():
        model.theta.copy_(torch.as_tensor(rng.uniform(0, math.pi, n), dtype=DT))
        model.threshold.copy_(torch.as_tensor(rng.uniform(0.3, 0.6, n), dtype=DT))
    ctl, normals = _controller(model, v, f, frames)
    split = torch.arange(n)
    rows = ctl.new_rows(model, torch.zeros(0, dtype=torch.long), split)
    a_parent = _axes(frames, normals, model.face_ids, model.theta.detach())
    a_parent = torch.cat([a_parent, a_parent])
    f_parent = torch.cat([model.face_ids, model.face_ids])
    f_child, th_child = rows["face_ids"], rows["theta"]
    assert int((f_child != f_parent).sum()) > n
    assert bool(((th_child >= 0) & (th_child <= math.pi)).all())
    a_child = _axes(frames, normals, f_child, th_child)
    if surface == "flat":
        expected = a_parent
    else:  # the cylinder transports the (around, along) components unchanged
        z = torch.tensor([0.0, 0.0, 1.0], dtype=DT).expand_as(a_parent)
        around0 = torch.linalg.cross(z, normals[f_parent], dim=-1)
        around1 = torch.linalg.cross(z, normals[f_child], dim=-1)
        expected = (a_parent * around0).sum(-1, keepdim=True) * around1 + a_parent[:, 2:] * z
    assert torch.allclose((a_child * expected).sum(-1).abs(), torch.ones(2 * n, dtype=DT))
    # the children sit at +/- (1 - eps) 0.2 along the parent's axis (flat: straight lines)
    if surface == "flat":
        x = (torch.as_tensor(v)[torch.as_tensor(f)[f_child]] * rows["bary"][:, :, None]).sum(1)
        xp = model.centres().detach()
        off = ((1 - model.threshold.detach()) * 0.2)[:, None] * a_parent[:n]
        assert torch.allclose(x, torch.cat([xp + off, xp - off]), atol=1e-9)


def test_theta_in_faces_picks_the_representative_nearest_the_old_angle():
    frames = torch.tensor([[1.0, 0, 0]], dtype=DT)
    normals = torch.tensor([[0.0, 0, 1]], dtype=DT)
    fid = torch.zeros(6, dtype=torch.long)
    ang = torch.tensor([0.0, math.pi, 1e-3, math.pi - 1e-3, 2.0, 0.5], dtype=DT)
    ref = torch.tensor([math.pi, 0.0, math.pi, 0.0, 2.0, 0.5], dtype=DT)
    a = torch.stack([torch.cos(ang), torch.sin(ang), 0 * ang], 1)
    sign = torch.tensor([1.0, -1, 1, -1, -1, 1], dtype=DT)[:, None]  # axes have no sign
    b = torch.linalg.cross(normals.expand_as(a), a, dim=-1)
    axes = torch.stack([a * sign, b * sign], 1)
    t, rev = theta_in_faces(frames, normals, fid, axes, ref)
    # 0 seen from pi stays pi; pi seen from 0 stays 0; small wraps go to the other end
    expect = torch.tensor([math.pi, 0.0, 1e-3, math.pi - 1e-3, 2.0, 0.5], dtype=DT)
    assert torch.allclose(t, expect, atol=1e-12)
    assert not bool(rev.any())
    t2, rev2 = theta_in_faces(frames, normals, fid, torch.stack([a, -b], 1), ref)
    assert bool(rev2.all()) and torch.allclose(t2, expect, atol=1e-12)


def test_frames_need_a_tracer_that_transports():
    v, f = flat_patch(5)
    model = ToyModel(v, f, np.arange(3), np.full((3, 3), 1 / 3))

    class TraceOnly:
        def trace(self, face_ids, bary, vectors):
            return FlatTracer(v, f).trace(face_ids, bary, vectors)

    with pytest.raises(TypeError):
        KernelOptimiser(
            model,
            FitParams(),
            TraceOnly(),
            torch.as_tensor(v),
            torch.as_tensor(f),
            face_frames=torch.as_tensor(np.tile([1.0, 0, 0], (len(f), 1))),
        )


def test_fit_loop_keeps_theta_unless_asked(monkeypatch):
    from hktex_engine.fitting import loop as fitting

    seen = []
    real = fitting.KernelOptimiser

    def spy(*args, **kw):
        seen.append(kw.get("face_frames"))
        return real(*args, **kw)

    monkeypatch.setattr(fitting, "KernelOptimiser", spy)
    v, f = flat_patch(5)
    frames = torch.as_tensor(np.tile([1.0, 0, 0], (len(f), 1)), dtype=DT)
    for flag in (False, True):
        model = ToyModel(v, f, np.arange(3), np.full((3, 3), 1 / 3))
        fitting.run_fit(
            model,
            ToyObjective(v, f, 8),
            FitParams(kernels=3, steps=1, densify=False),
            FlatTracer(v, f),
            torch.as_tensor(v, dtype=DT),
            torch.as_tensor(f),
            frames,
            transport_theta=flag,
        )
    assert seen[0] is None and seen[1] is frames


@pytest.fixture(scope="module")
def real_model_parts():
    from hktex_engine.config import SpectralConfig
    from hktex_engine.geometry.mesh import mesh_from_arrays
    from hktex_engine.spectra.grid import compute_spectra
    from hktex_engine.spectra.interpolation import SpectralField

    v, f = icosphere(2)
    cfg = SpectralConfig(angles=5, anisotropies=(1.0, 30.0), k=16, k_iso=9)
    sp = compute_spectra(mesh_from_arrays(v, f), cfg)
    return sp, SpectralField(sp, device="cpu")


def test_fixed_theta_kernel_is_continuous_across_an_edge_and_transport_jumps(real_model_parts):
    """Why transport_theta is off by default (measured on the real HeatKernelModel).

    The basis at (theta, s) is the global ALBO whose axis is at angle theta from u_ref in
    every face, so a kernel's footprint follows that field: moving its centre a distance h
    across an edge at fixed theta changes its responses by O(h); re-expressing theta swaps
    the whole field for one rotated by the frames' difference, a jump that does not shrink.
    """
    from hktex_engine.geometry.sampling import sample_surface
    from hktex_engine.kernels.model import HeatKernelModel

    sp, field = real_model_parts
    V = torch.as_tensor(np.array(sp.vertices), dtype=DT)
    F = torch.as_tensor(np.array(sp.faces))
    frames = torch.as_tensor(np.array(sp.face_frames), dtype=DT)
    normals = face_unit_normals(V, F)
    tracer = SurfaceTracer(np.array(sp.vertices), np.array(sp.faces))
    rng = np.random.default_rng(5)
    n = 40
    fid = torch.as_tensor(rng.integers(0, len(F), n))
    d = 1e-5  # start just inside edge (0, 1), step straight out across it
    bary = torch.tensor([[0.5 - d, 0.5 - d, 2 * d]], dtype=DT).expand(n, 3).clone()
    tri = V[F[fid]]
    out = torch.linalg.cross(tri[:, 1] - tri[:, 0], normals[fid], dim=-1)
    away = ((out * (tri[:, 2] - tri[:, 0])).sum(-1) > 0)[:, None]
    out = torch.where(away, -out, out)
    out = out / out.norm(dim=-1, keepdim=True)
    theta = torch.as_tensor(rng.uniform(0.3, math.pi - 0.3, n), dtype=DT)
    pf, pb = (torch.as_tensor(a) for a in sample_surface(V.numpy(), F.numpy(), 1500, rng))

    def responses(face, b, th):
        m = HeatKernelModel(
            field,
            face,
            b,
            th,
            torch.full((n,), 30.0),
            torch.full((n,), 0.6),
            torch.full((n,), 50.0),
            torch.zeros(n, 3),
            torch.zeros(3),
        )
        with torch.no_grad():
            return m.responses(pf, pb)[0].to(DT)

    r0 = responses(fid, bary, theta)
    change = {}
    for h in (1e-3, 1e-4):
        res = tracer.trace_full(
            fid, bary, h * out, transport=axis_pair(frames, normals, fid, theta)
        )
        assert bool((res.face_ids != fid).all())
        th_t, _ = theta_in_faces(frames, normals, res.face_ids, res.transported, theta)
        keep = (responses(res.face_ids, res.bary, theta) - r0).abs().max(0).values.median()
        moved = (responses(res.face_ids, res.bary, th_t) - r0).abs().max(0).values.median()
        change[h] = (float(keep), float(moved))
    assert change[1e-4][0] < 0.2 * change[1e-3][0]  # O(h): continuous
    assert change[1e-4][1] > 0.5 * change[1e-3][1]  # does not shrink with h: a jump
    assert change[1e-4][1] > 5 * change[1e-4][0]
