"""``benchmarks/angle_histogram.py``: its statistics against angles placed by hand, and the
picture's shape (one row of two panels per set)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def angle_histogram():
    spec = importlib.util.spec_from_file_location(
        "angle_histogram", BENCHMARKS / "angle_histogram.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_uniform_angles_give_a_quarter_spacing_and_the_ends_their_share(angle_histogram):
    theta = np.linspace(0.0, np.pi, 180_001)  # uniform; 7 nodes are 30 degrees apart
    stats = angle_histogram.angle_stats(theta, 7)
    assert stats["median_deg_to_node"] == pytest.approx(7.5, abs=0.01)
    assert stats["uniform_would_be"] == 7.5
    assert stats["at_ends"] == pytest.approx(2.0 / 180.0, abs=1e-4)  # 1 degree at each end


def test_angles_at_nodes_and_ends_are_counted(angle_histogram):
    nodes = np.linspace(0.0, np.pi, 7)
    theta = np.concatenate([nodes, nodes[1:-1] + np.radians(3.0), [np.radians(0.5)]])
    stats = angle_histogram.angle_stats(theta, 7)
    # sorted distances: seven 0 (the nodes), 0.5 (beside the end 0), five 3.0: median 0
    assert stats["kernels"] == 13
    assert stats["median_deg_to_node"] == pytest.approx(0.0)
    off = angle_histogram.angle_stats(nodes[1:-1] + np.radians(3.0), 7)
    assert off["median_deg_to_node"] == pytest.approx(3.0) and off["at_ends"] == 0.0
    assert stats["at_ends"] == pytest.approx(
        3 / 13, abs=1e-4
    )  # 0, pi, the one at 0.5 degree (rounded)


def test_figure_has_a_row_per_set(angle_histogram, tmp_path):
    from hktex_engine.kernels.hkt import save_hkt
    from tests.kernels_support import kernelset_of, random_kernels, tiny_spectra
    from tests.test_kernels import CONFIG

    spectra = tiny_spectra()
    paths = []
    for i in range(2):
        path = tmp_path / f"s{i}.hkt"
        save_hkt(kernelset_of(spectra, random_kernels(spectra, 30, seed=i), CONFIG), path)
        paths.append(path)
    im, stats = angle_histogram.figure(paths, 7)
    row_h = angle_histogram.PANEL_H + 2 * angle_histogram.PAD
    assert im.size == (2 * angle_histogram.PANEL_W + 3 * angle_histogram.PAD, 2 * row_h)
    assert [s["set"] for s in stats] == ["s0.hkt", "s1.hkt"]
    assert all(s["kernels"] == 30 for s in stats)
