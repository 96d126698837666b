"""The shared fit loop on a toy model: determinism, progress, cancellation, checkpoints, resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hktex_engine.config import FitParams
from hktex_engine.errors import Cancelled
from hktex_engine.fitting.loop import CheckpointError, latest_checkpoint, loss_curve, run_fit
from tests.fitting_standins import FlatTracer, ToyModel, ToyObjective, flat_patch


def _setup(n=120, seed=0):
    v, f = flat_patch(7)
    rng = np.random.default_rng(seed)
    fid = rng.integers(0, len(f), n)
    b = rng.dirichlet(np.ones(3), n)
    model = ToyModel(v, f, fid, b)
    frames = torch.as_tensor(np.tile([1.0, 0.0, 0.0], (len(f), 1)))
    geo = (FlatTracer(v, f), torch.as_tensor(v), torch.as_tensor(f), frames)
    return model, ToyObjective(v, f), geo


def _params(**kw):
    base = dict(kernels=120, max_kernels=200, steps=40, seed=3, checkpoint_every=10)
    base.update(kw)
    return FitParams(**base)


def _rows(model):
    names = ("face_ids", "bary", "theta", "s", "threshold", "sharpness", "colors")
    return {k: getattr(model, k).detach().clone() for k in (*names, "base_color")}


class StopAt:
    """Progress sink that asks to stop once ``step`` was reported; counts reports."""

    def __init__(self, step=None):
        self.stop_step, self.last, self.reports = step, 0, 0

    def update(self, step, total, **metrics):
        self.last, self.reports = step, self.reports + 1
        assert "loss" in metrics and "kernels" in metrics

    def should_stop(self):
        return self.stop_step is not None and self.last >= self.stop_step


def test_loop_learns_and_is_deterministic():
    m1, obj, geo = _setup()
    r1 = run_fit(m1, obj, _params(), *geo)
    m2, obj, geo = _setup()
    r2 = run_fit(m2, obj, _params(), *geo)
    assert r1.losses == r2.losses
    for k, t in _rows(m1).items():
        assert torch.equal(t, getattr(m2, k).detach()), k
    assert np.mean(r1.losses[-10:]) < 0.5 * np.mean(r1.losses[:5])
    # density control ran (schedule at 0.05 T...) and respected the budget
    assert max(r1.kernel_counts) <= 200 and len(set(r1.kernel_counts)) > 1


def test_cancel_leaves_checkpoint_and_resume_matches(tmp_path, monkeypatch):
    import hktex_engine.fitting.loop as fitting

    # report every step so the stop request lands at a known step
    monkeypatch.setattr(fitting.time, "perf_counter", _fake_clock())
    full, obj, geo = _setup()
    run_fit(full, obj, _params(), *geo)

    part, obj, geo = _setup()
    with pytest.raises(Cancelled):
        run_fit(part, obj, _params(), *geo, progress=StopAt(23), checkpoint_dir=tmp_path)
    ck = latest_checkpoint(tmp_path)
    assert ck is not None and ck.name == "step-000000023"
    assert not list(tmp_path.glob(".tmp-*"))

    fresh, obj, geo = _setup()
    res = run_fit(fresh, obj, _params(), *geo, checkpoint_dir=tmp_path)
    assert res.resumed_from == 23 and res.steps == 40
    for k, t in _rows(full).items():
        assert torch.equal(t, getattr(fresh, k).detach()), k


def test_periodic_checkpoint_and_foreign_refused(tmp_path):
    m, obj, geo = _setup()
    run_fit(m, obj, _params(steps=25), *geo, checkpoint_dir=tmp_path, fingerprint={"a": 1})
    assert latest_checkpoint(tmp_path).name == "step-000000020"
    m, obj, geo = _setup()
    with pytest.raises(CheckpointError):
        run_fit(m, obj, _params(steps=25), *geo, checkpoint_dir=tmp_path, fingerprint={"a": 2})


def test_a_checkpoint_from_before_colour_slopes_resumes(tmp_path):
    """Checkpoints written before kernels had colour slopes hold no ``model.color_slopes``:
    they resume with flat colours, as those fits had, and finish as the uninterrupted fit."""
    m, obj, geo = _setup()
    full = run_fit(m, obj, _params(steps=25), *geo)
    m, obj, geo = _setup()
    run_fit(m, obj, _params(steps=25), *geo, checkpoint_dir=tmp_path)
    ck = latest_checkpoint(tmp_path)
    with np.load(ck / "state.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "model.color_slopes"}
    np.savez(ck / "state.npz", **arrays)
    fresh, obj, geo = _setup()
    res = run_fit(fresh, obj, _params(steps=25), *geo, checkpoint_dir=tmp_path)
    assert res.resumed_from == 20 and res.losses[-5:] == full.losses[-5:]
    assert not fresh.color_slopes.any()


def test_progress_is_throttled():
    m, obj, geo = _setup()
    sink = StopAt()
    run_fit(m, obj, _params(steps=20), *geo, progress=sink)
    assert sink.last == 20 and sink.reports < 20


def _fake_clock():
    t = [0.0]

    def clock():
        t[0] += 2.0
        return t[0]

    return clock


def test_loss_curve_is_chunk_means_counted_back_from_the_last_step():
    # 10 losses of a fit resumed at step 90: steps 91..100
    losses = [float(v) for v in range(10)]
    assert loss_curve(losses, 100, max_points=20) == [[91 + i, float(i)] for i in range(10)]
    # 4 points: runs of 3, 3, 2, 2 steps, each point at its run's last step, its mean
    assert loss_curve(losses, 100, max_points=4) == [[93, 1.0], [96, 4.0], [98, 6.5], [100, 8.5]]
    many = np.random.default_rng(0).random(5003)
    curve = np.asarray(loss_curve(list(many), 5003))
    assert curve.shape == (200, 2) and curve[-1, 0] == 5003
    # equal-weight means of a partition: their size-weighted mean is the overall mean
    sizes = np.diff(np.concatenate([[0], curve[:, 0]]))
    assert np.isclose((curve[:, 1] * sizes).sum() / sizes.sum(), many.mean())
    assert loss_curve([], 7) == []
