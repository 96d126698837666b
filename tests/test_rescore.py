"""``benchmarks/rescore.py``'s set changes: a rescored set differs from the fitted one in
exactly the attribute and the kernels named, so its score change is that change's alone."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hktex_engine.config import KernelConfig
from hktex_engine.kernels.model import SHARPNESS_RANGE, KernelSet

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def rescore():
    sys.path.insert(0, str(BENCHMARKS))  # the script imports its sibling ``_machine``
    try:
        spec = importlib.util.spec_from_file_location("rescore", BENCHMARKS / "rescore.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


def _set() -> KernelSet:
    n = 4
    return KernelSet(
        face_ids=np.arange(n),
        barycentrics=np.full((n, 3), 1 / 3),
        theta=np.zeros(n),
        eta=np.ones(n),
        threshold=np.array([0.5, 0.95, 0.85, 0.99]),
        sharpness=np.array([20.0, 100.0, 150.0, 190.0]),
        colors=np.zeros((n, 3)),
        base_color=np.full(3, 0.5),
        kernel_config=KernelConfig(k_search=50, k_blend=30),
    )


def test_sharpened_scales_only_the_chosen_kernels_and_stays_in_range(rescore):
    ks = _set()
    small = rescore.sharpened(ks, 1.5, "small")  # thresholds above 0.9: kernels 1 and 3
    np.testing.assert_allclose(small.sharpness, [20.0, 150.0, 150.0, SHARPNESS_RANGE[1]])
    large = rescore.sharpened(ks, 1.5, "large")
    np.testing.assert_allclose(large.sharpness, [30.0, 100.0, SHARPNESS_RANGE[1], 190.0])
    every = rescore.sharpened(ks, 0.5, "all")
    np.testing.assert_allclose(every.sharpness, ks.sharpness * 0.5)
    for changed in (small, large, every):
        np.testing.assert_array_equal(changed.threshold, ks.threshold)
        np.testing.assert_array_equal(changed.colors, ks.colors)
    np.testing.assert_allclose(ks.sharpness, [20.0, 100.0, 150.0, 190.0])  # input untouched


def test_with_counts_changes_the_counts_alone(rescore):
    ks = _set()
    other = rescore.with_counts(ks, 100, 10)
    assert (other.kernel_config.k_search, other.kernel_config.k_blend) == (100, 10)
    assert other.kernel_config.sigma_b == ks.kernel_config.sigma_b
    assert other.kernel_config.diffusion_time == ks.kernel_config.diffusion_time
    assert (ks.kernel_config.k_search, ks.kernel_config.k_blend) == (50, 30)
    np.testing.assert_array_equal(other.sharpness, ks.sharpness)


def test_solved_keeps_the_footprints_and_changes_the_colours(rescore):
    """``--solve``: the same kernels where they were, new colours; ``linear`` makes the set a
    linear-colour one with slopes, ``constant`` keeps it §4-5."""
    from tests.test_colour_solve import _setup

    mesh, _, model = _setup()
    ks = model.to_kernelset()
    for kind in ("constant", "linear"):
        out = rescore.solved(mesh, model.field, ks, kind, per_kernel=40)
        np.testing.assert_array_equal(out.face_ids, ks.face_ids)
        np.testing.assert_allclose(out.threshold, ks.threshold)
        assert np.abs(out.colors - ks.colors).max() > 1e-3
        assert out.kernel_config.colour == kind
        assert (out.color_slopes is not None) == (kind == "linear")
