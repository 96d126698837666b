"""``benchmarks/uv_window.py``: the window sits on the first set's worst texel, every set gets
a row of the same window, and a window's RMS is that of its own rows' errors."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from hktex_engine.config import FitParams
from hktex_engine.evaluation.synthetic import textured_demo
from hktex_engine.fitting.uv import initial_kernelset
from hktex_engine.geometry.mesh import mesh_from_arrays
from hktex_engine.kernels.hkt import save_hkt
from hktex_engine.spectra.grid import compute_spectra
from hktex_engine.spectra.interpolation import SpectralField
from tests.test_fit_uv import TINY

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def uv_window():
    spec = importlib.util.spec_from_file_location("uv_window", BENCHMARKS / "uv_window.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rows_share_the_first_sets_worst_window(uv_window, tmp_path):
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=32)
    mesh = mesh_from_arrays(v, f, corner_uvs=uv, texture=tex)
    spectra = compute_spectra(mesh, TINY)
    ks = initial_kernelset(mesh, spectra, FitParams(kernels=40), np.random.default_rng(0))
    flat = replace(ks, colors=np.zeros_like(ks.colors))  # the base colour alone: worse
    paths = [tmp_path / "a.hkt", tmp_path / "b.hkt", tmp_path / "c.hkt"]
    for path, s in zip(paths, (ks, flat, ks), strict=True):
        save_hkt(s, path)
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    strip, rms = uv_window.window_rows(mesh, field, paths, width=64)
    assert strip.shape == (3 * 64, 3 * 64, 3)
    assert rms[0] == rms[2] and rms[1] > rms[0] > 0
    # each row's middle panel is its bake; the same set twice draws the same pixels
    np.testing.assert_array_equal(strip[:64], strip[128:])
    assert not np.array_equal(strip[:64, 64:128], strip[64:128, 64:128])
