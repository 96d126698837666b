"""Error-driven training points: unbiased weights, the mixture's floor, scores, resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hktex_engine.config import FitParams
from hktex_engine.errors import Cancelled
from hktex_engine.fitting.error_sampling import ErrorSampler
from hktex_engine.fitting.loop import latest_checkpoint
from hktex_engine.fitting.uv import fit_uv, point_loss
from tests.fitting_standins import StopAfter
from tests.test_fit_uv import sphere, two_colour_sphere  # noqa: F401  (fixture)


@pytest.fixture()
def sampler():
    return ErrorSampler(two_colour_sphere(), 5000, 0.5, np.random.default_rng(0))


def test_weights_make_the_batch_mean_an_unbiased_surface_mean(sampler):
    """Exactly: sum_i q_i w_i f_i over the pool equals the plain pool mean of f."""
    rng = np.random.default_rng(1)
    sampler.update(np.arange(len(sampler)), rng.gamma(0.3, size=len(sampler)))
    q = sampler.probabilities(True)
    f = rng.random(len(sampler))
    w = 1.0 / (len(sampler) * q)
    assert np.isclose(q.sum(), 1.0)
    assert np.isclose((q * w * f).sum(), f.mean(), rtol=1e-12)
    # and by simulation, against the uniform mean computed independently
    idx, wd = sampler.draw(400_000, rng, True)
    assert np.allclose(wd, w[idx])
    assert abs((wd * f[idx]).mean() - f.mean()) < 0.01 * f.mean()


def test_draws_follow_the_residual_with_a_uniform_floor(sampler):
    n = len(sampler)
    score = np.zeros(n)
    score[:50] = 1.0  # 1 % of the pool holds all the error
    sampler.update(np.arange(n), score)
    q = sampler.probabilities(True)
    assert q.min() >= 0.5 / n - 1e-15  # the uniform share: weights at most 1 / mix
    idx, w = sampler.draw(20_000, np.random.default_rng(2), True)
    share = np.mean(idx < 50)
    assert 0.45 < share < 0.56  # half the batch goes to the 1 % with error (+ its uniform 0.5 %)
    assert w.max() <= 2.0 + 1e-12
    uniform, _ = sampler.draw(20_000, np.random.default_rng(2), False)
    assert np.mean(uniform < 50) < 0.02


def test_unseen_points_score_the_mean_of_the_seen(sampler):
    sampler.update(np.array([0, 1]), np.array([1.0, 3.0]))
    q = sampler.probabilities(True)
    n = len(sampler)
    expect_unseen = 0.5 / n + 0.5 * 2.0 / (1.0 + 3.0 + 2.0 * (n - 2))
    assert np.isclose(q[2], expect_unseen)
    sampler.update(np.array([0]), np.array([3.0]))
    assert sampler.score[0] == pytest.approx(2.0)  # EMA of 1 then 3 with weight 0.5


def test_weighted_loss_equals_the_plain_loss_at_unit_weights():
    pred, target = torch.rand(7, 3), torch.rand(7, 3)
    for rgb in (True, False):
        p = FitParams(loss="mse", loss_sum_rgb=rgb)
        assert torch.allclose(
            point_loss(pred, target, p, torch.ones(7)), point_loss(pred, target, p)
        )
    w = torch.tensor([2.0, 0, 0, 0, 0, 0, 0])
    p = FitParams(loss="mse", loss_sum_rgb=True)
    assert torch.allclose(
        point_loss(pred, target, p, w), 2 * ((pred[0] - target[0]) ** 2).sum() / 7
    )


def test_error_sampled_fit_learns_and_resumes_exactly(sphere, tmp_path):  # noqa: F811
    mesh, spectra = sphere
    p = FitParams(
        kernels=150,
        max_kernels=300,
        steps=10,
        points_per_step=256,
        seed=7,
        checkpoint_every=0,
        sampling="error",
        sampling_pool=4000,
        sampling_warmup=0.2,
    )
    a = fit_uv(mesh, spectra, p, eval_points=500)

    with pytest.raises(Cancelled):
        fit_uv(mesh, spectra, p, StopAfter(6), checkpoint_dir=tmp_path, eval_points=500)
    assert latest_checkpoint(tmp_path).name == "step-000000006"
    c = fit_uv(mesh, spectra, p, checkpoint_dir=tmp_path, eval_points=500)
    assert c.metrics["resumed_from"] == 6
    for name in ("face_ids", "barycentrics", "theta", "eta", "threshold", "colors", "base_color"):
        assert np.array_equal(getattr(a.kernelset, name), getattr(c.kernelset, name)), name


def test_error_sampled_fit_reaches_the_uniform_tests_psnr(sphere):  # noqa: F811
    """The settings of test_fit_uv's short fit, with error-driven points after 10 steps."""
    mesh, spectra = sphere
    p = FitParams(
        kernels=150,
        steps=60,
        points_per_step=256,
        seed=7,
        densify=False,
        lr_colors=0.05,
        lr_threshold=0.03,
        sampling="error",
        sampling_pool=20_000,
        sampling_warmup=10 / 60,
    )
    m = fit_uv(mesh, spectra, p, eval_points=4000).metrics
    assert m["surface_psnr"] >= 16.0
    assert m["surface_psnr"] > m["surface_psnr_initial"] + 4.0


def test_bad_sampling_settings_are_refused():
    with pytest.raises(ValueError):
        FitParams(sampling="importance")
    with pytest.raises(ValueError):
        FitParams(sampling_mix=0.0)
    with pytest.raises(ValueError):
        FitParams(sampling_pool=0)


def test_cli_sampling_flag_reaches_the_fit(tmp_path, capsys, sphere):  # noqa: F811
    from hktex_engine.cli import main
    from hktex_engine.evaluation.synthetic import write_textured_obj
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.spectra.grid import write_spectra
    from tests.test_fit_uv import two_colour_arrays

    _, spectra = sphere
    obj = write_textured_obj(tmp_path / "m.obj", *two_colour_arrays())
    sdir = write_spectra(spectra, tmp_path / "spectra")
    out = tmp_path / "out.hkt"
    argv = [str(obj), "-o", str(out), "--spectra", str(sdir), "--kernels", "120", "--steps", "3"]
    argv += ["--eval-points", "300", "--sampling", "error", "--json"]
    assert main(["fit", *argv]) == 0
    capsys.readouterr()
    assert load_hkt(out).fitting["params"]["sampling"] == "error"
