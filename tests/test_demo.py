"""``hktex demo``: registered in the CLI, and (slow) the whole path on tiny settings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hktex_engine.cli import build_parser


def test_demo_is_a_cli_command_with_scaling_flags() -> None:
    args = build_parser().parse_args(["demo", "-o", "x", "--steps", "7", "--kernels", "9"])
    assert args.command == "demo" and args.steps == 7 and args.kernels == 9
    assert args.out == Path("x") and callable(args.func)


@pytest.mark.slow
def test_demo_end_to_end_on_tiny_settings(tmp_path: Path) -> None:
    from hktex_engine.cli import main

    argv = [
        "demo",
        "-o",
        str(tmp_path),
        "--subdivisions",
        "2",
        "--texture-size",
        "64",
        "--angles",
        "2",
        "--anisotropies",
        "1,10",
        "--k",
        "8",
        "--k-iso",
        "6",
        "--kernels",
        "32",
        "--max-kernels",
        "64",
        "--steps",
        "20",
        "--eval-points",
        "1000",
        "--render-size",
        "24",
        "--quiet",
    ]
    assert main(argv) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["job"]["state"] == "succeeded" and summary["kernelset"]["kernels"] > 0
    assert summary["quality"]["surface_psnr_db"] > 5
    names = ("report.html", "report.md", "render_kernels.png", "demo.hkt", "demo.glb")
    for name in names + ("uv_error.png", "loss_curve.png", "render_error_map.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / "render_kernels.png").read_bytes()[:4] == b"\x89PNG"
    # the curve is the record's, every step of the fit, not the few progress events
    assert [p[0] for p in summary["loss_curve"]] == list(range(1, 21))
    assert "loss_curve" not in summary["kernelset"]["fit_metrics"]


def test_demo_verdict_is_honest_and_loss_curve_draws(tmp_path: Path) -> None:
    from hktex_server.demo import _loss_curve_png, _recorded_curve, _verdict
    from PIL import Image

    baselines = [
        {"method": "mean colour", "bytes": 3, "psnr_db": 10.0},
        {"method": "vertex colours L0", "bytes": 1000, "psnr_db": 25.0},
        {"method": "UV texture 64px", "bytes": 9000, "psnr_db": 30.0},
    ]
    worse = _verdict(1200, 20.0, baselines)
    assert "5.00 dB worse" in worse and "vertex colours L0" in worse and "not yet" in worse
    better = _verdict(1200, 26.0, baselines)
    assert "1.00 dB better" in better and "No baseline of equal or fewer bytes" in better
    assert _loss_curve_png([(1, 0.1)], tmp_path / "one.png") is None
    assert _recorded_curve({"loss_curve": [[10, 0.5], [20, 0.25]]}) == [(10, 0.5), (20, 0.25)]
    assert _recorded_curve({}) == [] and _recorded_curve({"loss_curve": "x"}) == []
    # a diverged step's loss is stored as null (the record's JSON has no NaN): skipped
    assert _recorded_curve({"loss_curve": [[1, 1.0], [2, None], [3, 2.0]]}) == [(1, 1.0), (3, 2.0)]
    curve = _loss_curve_png([(s, 1.0 / s) for s in range(1, 50)], tmp_path / "c.png")
    img = Image.open(curve)
    assert img.size == (720, 400) and len(np.unique(np.asarray(img).reshape(-1, 3), axis=0)) > 2


def test_demo_serve_prints_the_dashboard_and_stops_on_sigterm(tmp_path: Path, capsys) -> None:
    import os
    import signal
    import threading
    from types import SimpleNamespace

    from hktex_server.demo import _serve_until_interrupted

    before = signal.getsignal(signal.SIGTERM)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    _serve_until_interrupted(SimpleNamespace(quiet=True), "http://127.0.0.1:1234", tmp_path)
    timer.join()
    out = capsys.readouterr().out
    assert "dashboard at http://127.0.0.1:1234/" in out
    assert signal.getsignal(signal.SIGTERM) == before, "the previous handler must be restored"
