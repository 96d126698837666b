"""``hktex demo``: registered in the CLI, and (slow) the whole path on tiny settings."""

from __future__ import annotations

import json
from pathlib import Path

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
    for name in ("report.html", "report.md", "render_kernels.png", "demo.hkt"):
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / "render_kernels.png").read_bytes()[:4] == b"\x89PNG"
