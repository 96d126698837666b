"""``benchmarks/render.py``: both grids and a saved set reach the renders and the report, and
a saved set on the benchmark's own small grid is refused (it lives on the default grid)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.demo_support import require_render

pytestmark = pytest.mark.mitsuba

ROOT = Path(__file__).resolve().parents[1]
SPOT = ROOT.parent / "shared" / "data" / "spot" / "spot_triangulated.obj"


@pytest.fixture(scope="module")
def render_benchmark():
    if not SPOT.is_file():
        pytest.skip("shared data (spot) not found beside the project")
    require_render()
    if str(ROOT / "benchmarks") not in sys.path:  # the script imports its sibling _machine
        sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("render_bench", ROOT / "benchmarks" / "render.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SMALL = ["--repeats", "1", "--size", "16", "--spp", "1", "--kernels", "40"]


def test_a_saved_set_on_the_default_grid_is_rendered_and_reported(render_benchmark, tmp_path):
    from hktex_engine.config import FitParams, SpectralConfig, fit_preset
    from hktex_engine.fitting.uv import initial_kernelset
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import SpectraCache

    cache = tmp_path / "cache"
    mesh = load_mesh(SPOT, texture=SPOT.with_name("spot_texture.png"))
    spectra = SpectraCache(cache).get_or_compute(mesh, SpectralConfig(k=16))
    kernel = fit_preset("default").kernel
    ks = initial_kernelset(
        mesh, spectra, FitParams(kernels=30, kernel=kernel), np.random.default_rng(1)
    )
    save_hkt(ks, tmp_path / "set.hkt")

    args = [*SMALL, "--spectra", "default", "--k", "16", "--cache", str(cache)]
    assert (
        render_benchmark.main(
            [*args, "--hkt", str(tmp_path / "set.hkt"), "--tag", "saved", "--out", str(tmp_path)]
        )
        == 0
    )
    saved = json.loads((tmp_path / "render_saved.json").read_text())
    assert saved["setup"]["kernels"] == 30  # the saved set, not --kernels 40
    assert saved["setup"]["kernel_set"] == "the saved set set.hkt"
    assert saved["setup"]["spectra"]["k"] == 16 and saved["setup"]["spectra"]["angles"] == 7
    assert saved["ratio_kernel_uncached_vs_uv"] > 0
    md = (tmp_path / "render_saved.md").read_text()
    assert "spectra 7 x 7 x K = 16 (default grid)" in md and "30 kernels (the saved set" in md


def test_the_benchmark_grid_is_the_default_and_a_saved_set_needs_the_default_grid(
    render_benchmark, tmp_path
):
    assert render_benchmark.main([*SMALL, "--out", str(tmp_path)]) == 0
    row = json.loads((tmp_path / "render.json").read_text())
    assert row["setup"]["kernels"] == 40 and row["setup"]["kernel_set"] == "UV init"
    assert row["setup"]["spectra"]["k"] == 32 and row["setup"]["spectra"]["angles"] == 3
    with pytest.raises(SystemExit):
        render_benchmark.main(
            [*SMALL, "--hkt", str(tmp_path / "missing.hkt"), "--out", str(tmp_path)]
        )
