"""Density control rules on crafted statistics, and the geometry of split children."""

from __future__ import annotations

import math

import numpy as np
import torch

from hktex_engine.config import FitParams
from hktex_engine.evaluation.synthetic import grid_patch
from hktex_engine.fitting.density import (
    DensityController,
    DensityRules,
    densify_selection,
    prune_mask,
    schedule,
)
from hktex_engine.fitting.loop import PointStats
from hktex_engine.fitting.optimise import KernelOptimiser
from hktex_engine.geometry.geodesics import SurfaceTracer
from tests.fitting_standins import FlatTracer, ToyModel, flat_patch

DT = torch.float64
RULES = DensityRules()


def test_schedules_are_fractions_of_total_steps():
    assert schedule(10_000, 0.2, 0.6, 0.1) == [2000, 3000, 4000, 5000, 6000]
    dens = schedule(10_000, 0.05, 0.7, 0.04)
    assert dens[0] == 500 and dens[-1] == 6900 and len(dens) == 17
    assert np.all(np.diff(dens) == 400)


def test_prune_thresholds():
    n = 300
    hits = torch.full((n,), 100.0, dtype=DT)
    contrib = torch.full((n,), 0.5, dtype=DT)
    hits[0] = 1000  # max -> 2 % of it is 20
    hits[1], hits[2] = 19.9, 20.0  # below / at the hit threshold
    contrib[3], contrib[4] = 0.069, 0.07  # below / at the contribution threshold
    remove = prune_mask(hits, contrib, RULES)
    assert torch.nonzero(remove).squeeze(1).tolist() == [1, 3]


def test_prune_never_below_floor_and_removes_least_hit_first():
    n = 105
    hits = torch.full((n,), 50.0, dtype=DT)
    contrib = torch.full((n,), 0.5, dtype=DT)
    weak = torch.arange(20)
    hits[weak] = torch.arange(20, dtype=DT) * 0.01  # all below 2 % of 50
    remove = prune_mask(hits, contrib, RULES)
    assert int(remove.sum()) == 5 and int((~remove).sum()) == 100
    assert torch.nonzero(remove).squeeze(1).tolist() == [0, 1, 2, 3, 4]
    assert not prune_mask(torch.zeros(100, dtype=DT), torch.zeros(100, dtype=DT), RULES).any()


def test_densify_caps_and_split_vs_clone():
    n = 200
    err = torch.zeros(n, dtype=DT)
    err[:150] = torch.linspace(0.5, 0.03, 150, dtype=DT)  # 150 candidates, descending
    eps = torch.full((n,), 0.95, dtype=DT)  # 1 - eps = 0.05: clone
    eps[::2] = 0.7  # 1 - eps = 0.3 > 0.235: split
    clone, split = densify_selection(err, eps, n_budget=10_000, rules=RULES)
    chosen = torch.cat([clone, split]).sort().values
    assert len(chosen) == 80  # 0.4 x 200
    assert chosen.tolist() == list(range(80))  # the highest errors
    assert (split % 2 == 0).all() and (clone % 2 == 1).all()
    # budget cap
    clone, split = densify_selection(err, eps, n_budget=230, rules=RULES)
    assert len(clone) + len(split) == 30
    # either side of the size proxy's threshold 0.235
    e = torch.zeros(10, dtype=DT)
    e[:2] = 0.1
    th = torch.full((10,), 0.9, dtype=DT)
    th[:2] = torch.tensor([0.766, 0.764], dtype=DT)
    clone, split = densify_selection(e, th, 100, RULES)
    assert clone.tolist() == [0] and split.tolist() == [1]
    # nobody above 0.0208
    clone, split = densify_selection(torch.full((5,), 0.02, dtype=DT), eps[:5], 100, RULES)
    assert clone.numel() == split.numel() == 0


def _controller(model, v, f, tracer, frames=None, total=100, **kw):
    params = FitParams(kernels=len(model.face_ids), steps=total, **kw)
    frames = frames if frames is not None else np.tile([1.0, 0.0, 0.0], (len(f), 1))
    ctl = DensityController(
        params,
        total,
        torch.as_tensor(v, dtype=DT),
        torch.as_tensor(f),
        torch.as_tensor(frames, dtype=DT),
        tracer,
    )
    ctl.bind(model)
    opt = KernelOptimiser(model, params, tracer, torch.as_tensor(v), torch.as_tensor(f))
    return ctl, opt


def test_record_hits_contributions_and_error_spreading():
    v, f = flat_patch(5)
    model = ToyModel(v, f, np.arange(4), np.full((4, 3), 1 / 3))
    ctl, _ = _controller(model, v, f, FlatTracer(v, f))
    ctl.step = 4  # inside the window of the densify event at step 5 (and prune at 20? no)
    topk = torch.tensor([[0, 1, -1], [1, 2, 3], [0, 3, 2]])
    rho = torch.tensor([[0.5, 0.25, 0.0], [1.0, 0.0, 0.5], [0.2, 0.2, 0.6]], dtype=DT)
    err = torch.tensor([0.3, 0.6, 0.1], dtype=DT)
    ctl.record(PointStats(err, topk, rho))
    # independent loop computation of the spread errors
    exp_sum, exp_w = np.zeros(4), np.zeros(4)
    for p in range(3):
        tot = sum(r for k, r in zip(topk[p].tolist(), rho[p].tolist(), strict=True) if k >= 0)
        for k, r in zip(topk[p].tolist(), rho[p].tolist(), strict=True):
            if k >= 0 and r > 0:
                exp_sum[k] += err[p].item() * r / tot
                exp_w[k] += r / tot
    assert np.allclose(ctl.acc["err_sum"].numpy(), exp_sum)
    assert np.allclose(ctl.acc["err_weight"].numpy(), exp_w)
    assert "hits" not in ctl.acc or ctl.acc["hits"].sum() == 0  # prune window not open yet
    ctl.step = 19  # prune event at 20: window (5 steps) open; densify window too
    ctl.record(PointStats(err, topk, rho))
    assert ctl.acc["hits"].tolist() == [2, 2, 1, 2]  # the zero response does not count
    assert np.allclose(ctl.acc["rho_sum"].numpy(), [0.7, 1.25, 0.6, 0.7])


def test_record_weights_points_by_their_importance_weights():
    """Error-sampled points carry 1 / (n q): a point of weight w counts as w points."""
    v, f = flat_patch(5)
    model = ToyModel(v, f, np.arange(4), np.full((4, 3), 1 / 3))
    topk = torch.tensor([[0, 1, -1], [1, 2, 3], [0, 3, 2]])
    rho = torch.tensor([[0.5, 0.25, 0.0], [1.0, 0.0, 0.5], [0.2, 0.2, 0.6]], dtype=DT)
    err = torch.tensor([0.3, 0.6, 0.1], dtype=DT)
    w = torch.tensor([2.0, 1.0, 0.5], dtype=DT)
    # the same points repeated by their weight (point 2 at half weight: half of everything)
    weighted, _ = _controller(model, v, f, FlatTracer(v, f))
    plain, _ = _controller(model, v, f, FlatTracer(v, f))
    for ctl in (weighted, plain):
        ctl.step = 19  # both windows open
    weighted.record(PointStats(err, topk, rho, weights=w))
    plain.record(PointStats(err[[0, 0, 1]], topk[[0, 0, 1]], rho[[0, 0, 1]]))
    half, _ = _controller(model, v, f, FlatTracer(v, f))
    half.step = 19
    half.record(PointStats(err[[2]], topk[[2]], rho[[2]]))
    for key in ("hits", "rho_sum", "err_sum", "err_weight"):
        expect = plain.acc[key] + 0.5 * half.acc[key]
        assert torch.allclose(weighted.acc[key], expect), key
    ones, _ = _controller(model, v, f, FlatTracer(v, f))
    none, _ = _controller(model, v, f, FlatTracer(v, f))
    for ctl in (ones, none):
        ctl.step = 19
    ones.record(PointStats(err, topk, rho, weights=torch.ones(3, dtype=DT)))
    none.record(PointStats(err, topk, rho))
    for key in ("hits", "rho_sum", "err_sum", "err_weight"):
        assert torch.equal(ones.acc[key], none.acc[key]), key


def test_split_children_on_a_flat_patch():
    v, f = grid_patch(11, 11, size=2.0)
    tracer = SurfaceTracer(v, f)

    # kernels at the patch centre, various angles; u_ref = +x on every face, normal = +z
    n = 110
    rng = np.random.default_rng(0)
    centre_face = 110  # cell (5, 5): the middle of the patch, far from its border
    fid = np.full(n, centre_face)
    bary = rng.dirichlet(np.ones(3), n)
    model = ToyModel(v, f, fid, bary)
    with torch.no_grad():
        model.theta.copy_(torch.linspace(0, math.pi, n, dtype=DT))
        model.threshold.copy_(torch.linspace(0.5, 0.99, n, dtype=DT))
    ctl, opt = _controller(model, v, f, tracer)
    x_before = model.centres().detach().clone()
    theta = model.theta.detach().clone()
    eps = model.threshold.detach().clone()
    colors = model.colors.detach().clone()
    split = torch.tensor([3, 40, 77])
    clone = torch.tensor([5])
    ctl.step = 5
    rows = ctl.new_rows(model, clone, split)
    keep = torch.tensor([i for i in range(n) if i not in split.tolist()])
    ctl._resize(model, opt, keep, rows, "densify")
    assert len(model.face_ids) == n - 3 + 1 + 2 * 3  # net +1 per clone and per split
    x_after = model.centres().detach()
    # clone: same position and attributes, appended after the survivors
    assert torch.allclose(x_after[n - 3], x_before[5])
    assert torch.allclose(model.colors.detach()[n - 3], colors[5])
    # children: +/- (1 - eps) * 0.2 * (cos theta, sin theta, 0), eps' = 1 - (1 - eps) / 1.6
    k = len(split)
    for side, sign in ((0, 1.0), (1, -1.0)):
        got = x_after[n - 2 + side * k : n - 2 + (side + 1) * k]
        off = (1 - eps[split]) * 0.2
        u = torch.stack([torch.cos(theta[split]), torch.sin(theta[split]), 0 * theta[split]], 1)
        assert torch.allclose(got, x_before[split] + sign * off[:, None] * u, atol=1e-9)
        new_eps = model.threshold.detach()[n - 2 + side * k : n - 2 + (side + 1) * k]
        assert torch.allclose(new_eps, 1 - (1 - eps[split]) / 1.6)
    # parents gone: survivors keep order
    assert torch.allclose(model.theta.detach()[: n - 3], theta[keep])


def test_act_resizes_optimiser_state_and_stats_with_the_kernels():
    v, f = flat_patch(7)
    n = 120
    rng = np.random.default_rng(1)
    model = ToyModel(v, f, rng.integers(0, len(f), n), rng.dirichlet(np.ones(3), n))
    ctl, opt = _controller(model, v, f, FlatTracer(v, f), max_kernels=140)
    pts = (
        torch.as_tensor(rng.integers(0, len(f), 32)),
        torch.as_tensor(rng.dirichlet(np.ones(3), 32)),
    )
    model.albedo(*pts).sum().backward()
    opt.step(0)
    # give each row a recognisable state
    st = opt.adam.state["colors"]
    st.exp_avg.copy_(torch.arange(n, dtype=DT)[:, None].expand(n, 3))
    ctl.step = 4
    ctl._ensure(n, torch.device("cpu"))
    err = torch.zeros(n, dtype=DT)
    err[10:60] = torch.linspace(0.9, 0.1, 50, dtype=DT)
    ctl.acc["err_sum"].copy_(err)
    ctl.acc["err_weight"].fill_(1.0)
    ctl.acc["hits"] = torch.arange(n, dtype=DT)
    with torch.no_grad():
        model.threshold.fill_(0.95)  # all clones
    assert ctl.act(5, model, opt)
    m = len(model.face_ids)
    assert m == 140  # budget cap: 20 of the 50 candidates
    st = opt.adam.state["colors"]
    assert torch.equal(st.exp_avg[:n, 0], torch.arange(n, dtype=DT))  # survivors keep theirs
    assert torch.equal(st.exp_avg[n:], torch.zeros(20, 3, dtype=DT))  # newcomers start at 0
    assert torch.equal(st.steps[n:], torch.zeros(20, dtype=DT))
    assert ctl.acc["hits"].shape[0] == m and torch.equal(
        ctl.acc["hits"][n:], torch.zeros(20, dtype=DT)
    )
    # clones are copies of the 20 worst kernels (10..29)
    assert torch.equal(model.face_ids[n:], model.face_ids[10:30])
    # prune at 20: everything below 2 % of the max hits goes (rows 0..2 have hits 0, 1, 2)
    ctl.acc["hits"] = torch.cat([torch.arange(n, dtype=DT), torch.full((20,), 50.0, dtype=DT)])
    ctl.acc["rho_sum"] = ctl.acc["hits"] * 0.5
    assert ctl.act(20, model, opt)
    assert len(model.face_ids) == 140 - 3
    assert torch.equal(opt.adam.state["colors"].exp_avg[:3, 0], torch.tensor([3.0, 4, 5], dtype=DT))


def test_step_sum_statistics_of_the_later_configuration():
    """§7b: error mass and contribution are per-step sums averaged over the window's steps
    (independent computation on crafted statistics), and prune runs at 0.2 T and 0.4 T."""
    from hktex_engine.config import LATER_DENSITY

    v, f = flat_patch(5)
    model = ToyModel(v, f, np.arange(4), np.full((4, 3), 1 / 3))
    tracer = FlatTracer(v, f)
    params = FitParams(kernels=4, steps=100, density=LATER_DENSITY)
    ctl = DensityController(
        params,
        100,
        torch.as_tensor(v, dtype=DT),
        torch.as_tensor(f),
        torch.as_tensor(np.tile([1.0, 0.0, 0.0], (len(f), 1)), dtype=DT),
        tracer,
    )
    ctl.bind(model)
    assert ctl.prune_steps == [20, 40]
    assert ctl.densify_steps[:3] == [8, 10, 12]
    topk = torch.tensor([[0, 1, -1], [1, 2, 3], [0, 3, 2]])
    rho = torch.tensor([[0.5, 0.25, 0.0], [1.0, 0.0, 0.5], [0.2, 0.2, 0.6]], dtype=DT)
    err = torch.tensor([0.3, 0.6, 0.1], dtype=DT)
    for step in (17, 18, 19):  # three recorded steps in both windows
        ctl.step = step
        ctl.record(PointStats(err, topk, rho))
    mass = np.zeros(4)
    for p in range(3):
        tot = sum(r for k, r in zip(topk[p].tolist(), rho[p].tolist(), strict=True) if k >= 0)
        for k, r in zip(topk[p].tolist(), rho[p].tolist(), strict=True):
            if k >= 0 and r > 0:
                mass[k] += err[p].item() * r / tot
    assert ctl.window_steps == {"prune": 3, "densify": 3}
    # three identical steps: the per-step mean of the sums is one step's sum
    assert np.allclose(ctl.acc["err_sum"].numpy() / ctl.window_steps["densify"], mass)
    assert np.allclose(
        ctl.acc["rho_sum"].numpy() / ctl.window_steps["prune"], [0.7, 1.25, 0.6, 0.7]
    )
