"""Optimiser maths: tangent gradient, Riemannian steps and transport, row-wise Adam state."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hktex_engine.config import FitParams
from hktex_engine.evaluation.synthetic import grid_patch, icosphere
from hktex_engine.fitting.optimise import (
    KernelOptimiser,
    RiemannianSGD,
    RowAdam,
    face_unit_normals,
    lr_factor,
    tangent_gradient,
)
from hktex_engine.geometry.geodesics import SurfaceTracer
from tests.fitting_standins import FlatTracer, ToyModel, flat_patch

DT = torch.float64


def _f(x: torch.Tensor) -> torch.Tensor:
    """A smooth non-linear function of 3-D position (the 'loss' in the FD tests)."""
    w = torch.tensor([1.3, -0.7, 2.1], dtype=x.dtype)
    return torch.sin(x @ w) + 0.5 * (x**2).sum(-1) * torch.cos(x[..., 2])


def test_tangent_gradient_matches_finite_differences_of_position():
    rng = np.random.default_rng(0)
    n = 50
    verts = torch.as_tensor(rng.normal(size=(3 * n, 3)), dtype=DT)
    faces = torch.arange(3 * n).reshape(n, 3)
    fid = torch.arange(n)
    bary = torch.as_tensor(rng.dirichlet(np.ones(3), n), dtype=DT).requires_grad_(True)
    x = (verts[faces[fid]] * bary[:, :, None]).sum(1)
    _f(x).sum().backward()
    g = tangent_gradient(verts, faces, fid, bary.grad)

    normals = face_unit_normals(verts, faces)
    assert torch.allclose((g * normals).sum(-1), torch.zeros(n, dtype=DT), atol=1e-10)
    x0 = x.detach()
    h = 1e-6
    for _ in range(3):  # random in-plane unit directions
        t = torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT)
        t = t - (t * normals).sum(-1, keepdim=True) * normals
        t = t / t.norm(dim=-1, keepdim=True)
        fd = (_f(x0 + h * t) - _f(x0 - h * t)) / (2 * h)
        assert torch.allclose((g * t).sum(-1), fd, rtol=1e-6, atol=1e-7)


def test_flat_step_equals_euclidean_step_and_stays_on_surface():
    v, f = grid_patch(11, 11, size=2.0)
    tracer = SurfaceTracer(v, f)
    rng = np.random.default_rng(1)
    n = 200
    fid = torch.as_tensor(rng.integers(0, len(f), n))
    bary = torch.as_tensor(rng.dirichlet(np.ones(3), n), dtype=DT)
    verts = torch.as_tensor(v, dtype=DT)
    x = (verts[torch.as_tensor(f)[fid]] * bary[:, :, None]).sum(1)
    # keep every path inside the patch: start well inside, short steps
    inside = ((x[:, :2] > 0.4) & (x[:, :2] < 1.6)).all(1)
    fid, bary, x = fid[inside], bary[inside], x[inside]
    g = torch.as_tensor(rng.normal(size=(len(fid), 3)), dtype=DT)
    g[:, 2] = 0
    opt = RiemannianSGD(tracer, lr=0.1, momentum=0.0)
    f2, b2 = opt.step(fid, bary, g)
    x2 = (verts[torch.as_tensor(f)[f2]] * b2[:, :, None]).sum(1)
    assert torch.allclose(x2, x - 0.1 * g, atol=1e-9)
    assert (b2 >= -1e-12).all() and torch.allclose(b2.sum(1), torch.ones(len(b2), dtype=DT))
    assert torch.equal(x2[:, 2], torch.zeros(len(b2), dtype=DT))


def test_steps_on_a_sphere_keep_centres_on_the_surface_and_transport_momentum():
    v, f = icosphere(3)
    tracer = SurfaceTracer(v, f)
    verts, faces = torch.as_tensor(v, dtype=DT), torch.as_tensor(f)
    normals = face_unit_normals(verts, faces)
    rng = np.random.default_rng(2)
    n = 300
    fid = torch.as_tensor(rng.integers(0, len(f), n))
    bary = torch.as_tensor(rng.dirichlet(np.ones(3), n), dtype=DT)
    g = torch.as_tensor(rng.normal(size=(n, 3)), dtype=DT)
    g = g - (g * normals[fid]).sum(-1, keepdim=True) * normals[fid]
    opt = RiemannianSGD(tracer, lr=0.3, momentum=0.9)
    f2, b2 = opt.step(fid, bary, g)
    x2 = (verts[faces[f2]] * b2[:, :, None]).sum(1)
    # on the polyhedron: inside its face (bary valid), close to the unit sphere
    assert (b2 >= -1e-12).all() and torch.allclose(b2.sum(1), torch.ones(n, dtype=DT))
    assert ((x2.norm(dim=1) - 1).abs() < 0.01).all()
    # momentum: same length, in the end face's plane, and it moved (not a copy of g)
    m = opt.buf
    assert torch.allclose(m.norm(dim=1), g.norm(dim=1), rtol=1e-9)
    assert ((m * normals[f2]).sum(-1).abs() < 1e-9).all()
    moved = f2 != fid
    assert moved.any() and not torch.allclose(m[moved], g[moved])


class _RotatingTracer:
    """Stays in place but rotates transported vectors by 30 degrees about z."""

    def __init__(self):
        c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
        self.R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    def trace(self, face_ids, bary, vectors):
        return face_ids, bary, np.asarray(vectors) @ self.R.T


def test_momentum_is_the_transported_vector_and_accumulates():
    tr = _RotatingTracer()
    opt = RiemannianSGD(tr, lr=0.5, momentum=0.9)
    fid = torch.zeros(4, dtype=torch.long)
    bary = torch.full((4, 3), 1 / 3, dtype=DT)
    g1 = torch.tensor([[1.0, 0, 0], [0, 2, 0], [1, 1, 0], [0.5, -1, 0]], dtype=DT)
    opt.step(fid, bary, g1)
    R = torch.as_tensor(tr.R)
    assert torch.allclose(opt.buf, g1 @ R.T)
    g2 = torch.ones(4, 3, dtype=DT)
    g2[:, 2] = 0
    opt.step(fid, bary, g2)
    assert torch.allclose(opt.buf, (0.9 * (g1 @ R.T) + g2) @ R.T)


def test_row_adam_equals_torch_adam_without_resizing():
    rng = np.random.default_rng(3)
    p1 = torch.as_tensor(rng.normal(size=(6, 3)), dtype=DT).requires_grad_(True)
    p2 = p1.detach().clone().requires_grad_(True)
    ours = RowAdam({"colors": 0.01}, eps=1e-8)
    ref = torch.optim.Adam([p2], lr=0.01, eps=1e-8)
    for _ in range(5):
        grad = torch.as_tensor(rng.normal(size=(6, 3)), dtype=DT)
        p1.grad, p2.grad = grad.clone(), grad.clone()
        ours.step({"colors": p1})
        ref.step()
    assert torch.allclose(p1, p2, rtol=1e-12, atol=1e-14)


def test_row_adam_state_follows_rows_on_resize():
    rng = np.random.default_rng(4)
    p = torch.as_tensor(rng.normal(size=(5, 3)), dtype=DT).requires_grad_(True)
    adam = RowAdam({"colors": 0.01, "base_color": 0.01})
    base = torch.zeros(3, dtype=DT, requires_grad=True)
    for _ in range(3):
        p.grad = torch.as_tensor(rng.normal(size=(5, 3)), dtype=DT)
        base.grad = torch.ones(3, dtype=DT)
        adam.step({"colors": p, "base_color": base})
    before = adam.state["colors"]
    keep = torch.tensor([3, 0, 4])
    adam.resize(keep, n_new=2)
    after = adam.state["colors"]
    assert torch.equal(after.exp_avg[:3], before.exp_avg[keep])
    assert torch.equal(after.exp_avg_sq[:3], before.exp_avg_sq[keep])
    assert torch.equal(after.steps, torch.tensor([3, 3, 3, 0, 0], dtype=DT))
    assert torch.equal(after.exp_avg[3:], torch.zeros(2, 3, dtype=DT))
    assert adam.state["base_color"].steps.item() == 3  # shared tensor untouched
    # a newcomer's first update is a bias-corrected first Adam step: lr * g / |g|
    q = torch.cat([p.detach()[keep], torch.zeros(2, 3, dtype=DT)]).requires_grad_(True)
    q.grad = torch.full((5, 3), 0.25, dtype=DT)
    adam.step({"colors": q})
    assert torch.allclose(q.detach()[3:], torch.full((2, 3), -0.01, dtype=DT), rtol=1e-9)


def test_lr_decay_schedule():
    p = FitParams()
    assert [lr_factor(s, p) for s in (0, 999, 1000, 2500, 9999)] == [1, 1, 0.5, 0.25, 0.5**9]


def test_kernel_optimiser_projects_into_ranges_and_moves_centres():
    v, f = flat_patch(7)
    rng = np.random.default_rng(5)
    fid = rng.integers(0, len(f), 20)
    model = ToyModel(v, f, fid, rng.dirichlet(np.ones(3), 20))
    params = FitParams(lr_colors=10.0, lr_theta=10.0, lr_eta=10.0, lr_threshold=10.0)
    opt = KernelOptimiser(model, params, FlatTracer(v, f), torch.as_tensor(v), torch.as_tensor(f))
    pts = (
        torch.as_tensor(rng.integers(0, len(f), 64)),
        torch.as_tensor(rng.dirichlet(np.ones(3), 64)),
    )
    before = model.centres().detach().clone()
    model.albedo(*pts).sum().backward()
    opt.step(0)
    assert float(model.theta.detach().min()) >= 0 and float(model.theta.detach().max()) <= math.pi
    assert (
        float(model.threshold.detach().max()) < 1 and float(model.threshold.detach().min()) >= 0.3
    )
    assert float(model.colors.detach().abs().max()) <= 1
    assert not torch.allclose(model.centres(), before)
    assert (model.bary >= 0).all()


@pytest.mark.parametrize("momentum", [0.0, 0.9])
def test_optimiser_state_arrays_round_trip(momentum):
    v, f = flat_patch(5)
    model = ToyModel(v, f, np.arange(10), np.full((10, 3), 1 / 3))
    opt = KernelOptimiser(
        model, FitParams(), FlatTracer(v, f), torch.as_tensor(v), torch.as_tensor(f), momentum
    )
    model.albedo(torch.arange(5), torch.full((5, 3), 1 / 3, dtype=DT)).sum().backward()
    opt.step(0)
    arrays = opt.state_arrays()
    other = KernelOptimiser(
        model, FitParams(), FlatTracer(v, f), torch.as_tensor(v), torch.as_tensor(f), momentum
    )
    other.load_state_arrays(arrays, torch.device("cpu"))
    for k, a in other.state_arrays().items():
        assert np.array_equal(a, arrays[k]), k
