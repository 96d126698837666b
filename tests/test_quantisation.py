"""Code widths chosen per fit (fitting.quantisation): the ladder, the budget, what is written."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from hktex_engine.evaluation.metrics import psnr, surface_samples
from hktex_engine.fitting import quantisation as quant
from hktex_engine.fitting.uv import fit_uv
from hktex_engine.kernels.hkt import QUANT_BITS
from hktex_engine.kernels.query import AlbedoQuery
from tests.test_fit_uv import _params, sphere, two_colour_arrays  # noqa: F401 - fixture


@pytest.fixture(scope="module")
def fitted(sphere):  # noqa: F811 - the fixture above
    mesh, spectra = sphere
    params = _params(steps=40, densify=False, lr_colors=0.05, lr_threshold=0.03)
    res = fit_uv(mesh, spectra, params, eval_points=3000)
    return mesh, spectra, res


def test_ladder_narrows_from_the_format_default():
    assert quant.BITS_LADDER[0] == QUANT_BITS
    for wide, narrow in zip(quant.BITS_LADDER, quant.BITS_LADDER[1:], strict=False):
        assert set(wide) == set(narrow) == set(QUANT_BITS)
        assert all(narrow[k] <= wide[k] for k in wide) and narrow != wide
    # and the steps above it widen from the default, for fits it would cost too much
    steps = (QUANT_BITS, *quant.WIDER_LADDER)
    for narrow, wide in zip(steps, steps[1:], strict=False):
        assert set(wide) == set(QUANT_BITS)
        assert all(wide[k] >= narrow[k] for k in wide) and narrow != wide
        assert all(b <= 16 for b in wide.values())


def test_budget_picks_the_narrowest_step_within_it(fitted):
    mesh, spectra, res = fitted
    f, b, target = surface_samples(mesh, 2000, 5)
    loose = quant.choose_bits(spectra, res.kernelset, f, b, target, budget_db=100.0)
    assert loose["bits"] == quant.BITS_LADDER[-1]
    assert len(loose["tried"]) == len(quant.BITS_LADDER)
    sizes = [t["bytes"] for t in loose["tried"]]
    assert sizes[-1] < sizes[0]
    # an independent score of the chosen widths: the round trip scored here again
    q, nbytes = quant.roundtrip(res.kernelset, loose["bits"])
    again = psnr(AlbedoQuery(spectra, q, device="cpu").colors(f, b), target)
    assert nbytes == loose["bytes"] and again == pytest.approx(loose["psnr"], abs=1e-9)
    strict = quant.choose_bits(spectra, res.kernelset, f, b, target, budget_db=-1.0)
    # nothing is within a negative budget: the walk stops at the default, then widens to the
    # widest step, whose decoded file is what it returns
    assert [t["bits"] for t in strict["tried"]] == [QUANT_BITS, *quant.WIDER_LADDER]
    assert strict["bits"] == quant.WIDER_LADDER[-1]
    assert strict["bytes"] > strict["tried"][0]["bytes"]
    q, nbytes = quant.roundtrip(res.kernelset, strict["bits"])
    assert nbytes == strict["bytes"]
    np.testing.assert_array_equal(q.colors, strict["kernelset"].colors)
    # the wider codes are closer to the exact set: its albedo, not the texture (against the
    # texture a coarser file can score a hair higher by chance: 17.87811 against 17.87806 dB
    # once the spectra moved by their solver tolerance, 2026-12-03)
    exact = AlbedoQuery(spectra, res.kernelset, device="cpu").colors(f, b)
    default_q, _ = quant.roundtrip(res.kernelset, QUANT_BITS)
    wide_err = np.abs(AlbedoQuery(spectra, q, device="cpu").colors(f, b) - exact).max()
    default_err = np.abs(AlbedoQuery(spectra, default_q, device="cpu").colors(f, b) - exact).max()
    assert wide_err < default_err


def test_fit_metrics_report_the_chosen_file(fitted):
    _, _, res = fitted
    q = res.metrics["quantisation"]
    assert q["bits"] in quant.BITS_LADDER + quant.WIDER_LADDER
    assert res.metrics["bytes_zip_quantised"] == q["bytes"]
    assert q["bytes"] <= res.metrics["bytes_zip_quantised_default_bits"]
    tried = [t["psnr"] for t in q["tried"]]
    if q["bits"] not in quant.BITS_LADDER:  # the default lost more than the budget
        assert q["choice_psnr_exact"] - tried[0] > q["budget_db"]
        return
    index = quant.BITS_LADDER.index(q["bits"])
    assert q["choice_psnr_exact"] - tried[index] <= q["budget_db"]
    if index + 1 < len(tried):  # the next step was tried and lost more than the budget
        assert q["choice_psnr_exact"] - tried[index + 1] > q["budget_db"]
    assert np.isfinite(q["surface_psnr"])


def test_cli_quantise_writes_the_chosen_widths(tmp_path, capsys, sphere):  # noqa: F811
    from hktex_engine.cli import main
    from hktex_engine.evaluation.synthetic import write_textured_obj
    from hktex_engine.spectra.grid import write_spectra

    _, spectra = sphere
    obj = write_textured_obj(tmp_path / "m.obj", *two_colour_arrays())
    sdir = write_spectra(spectra, tmp_path / "spectra")
    out = tmp_path / "q.hkt"
    argv = [str(obj), "-o", str(out), "--spectra", str(sdir), "--kernels", "120"]
    argv += ["--steps", "3", "--eval-points", "300", "--json", "--quantise"]
    assert main(["fit", *argv]) == 0
    json.loads(capsys.readouterr().out)
    with zipfile.ZipFile(out) as zf:
        manifest = json.loads(zf.read("manifest.json"))
    chosen = manifest["fitting"]["metrics"]["quantisation"]["bits"]
    assert {k: manifest["quantisation"][k]["bits"] for k in chosen} == chosen
