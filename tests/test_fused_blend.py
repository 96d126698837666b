"""The compiled no-grad blend (kernels.fused_blend) against the torch path it replaces on the
CPU: the same kernels chosen under the tie rule, colours to float32 round-off, in one thread
and split across threads. The tie cases themselves are in tests/test_ties.py (their float32
table-path tests run through this code)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hktex_engine.config import KernelConfig
from hktex_engine.kernels import fused_blend
from hktex_engine.kernels import model as kernels_mod
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import tiny_spectra
from tests.test_kernels import make_model, make_params

pytestmark = pytest.mark.skipif(not fused_blend.HAVE_NUMBA, reason="numba is not installed")

CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=16, k_blend=5)


@pytest.fixture(scope="module")
def spectra3():
    return tiny_spectra(3)


def _both_paths(model, f, b, monkeypatch):
    results = {}
    for enabled in (False, True):
        monkeypatch.setattr(fused_blend, "ENABLED", enabled)
        with torch.no_grad():
            results[enabled] = model.albedo(f, b, return_aux=True)
    return results[False], results[True]


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_equals_the_torch_path(spectra3, monkeypatch, threads):
    monkeypatch.setattr(kernels_mod, "TABLE_PATH", "always")
    monkeypatch.setattr(fused_blend, "THREAD_MIN_POINTS", 500)
    field = SpectralField(spectra3, device="cpu", dtype=torch.float32)
    model = make_model(field, make_params(spectra3, 300, seed=21), CONFIG)
    rng = np.random.default_rng(5)
    n = 4000
    f, b = rng.integers(0, spectra3.faces.shape[0], n), rng.dirichlet(np.ones(3), n)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        (ref, ref_aux), (got, aux) = _both_paths(model, f, b, monkeypatch)
    finally:
        torch.set_num_threads(old)
    assert got.dtype == torch.float32 and got.shape == (n, 3)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-5)
    # same kernels in the same (rule) order wherever no rho sits within round-off of another
    same = (aux["indices"] == ref_aux["indices"]).all(dim=1)
    assert same.float().mean() > 0.999
    np.testing.assert_allclose(aux["rho"].numpy(), ref_aux["rho"].numpy(), atol=1e-5)


def test_other_dtypes_and_devices_keep_the_torch_path():
    assert fused_blend.available(torch.device("cpu"), torch.float32) == fused_blend.ENABLED
    assert not fused_blend.available(torch.device("cpu"), torch.float64)
    assert not fused_blend.available(torch.device("cuda"), torch.float32)


def test_kth_smallest_against_a_sort():
    """The sampled selection of the blend's K_s cut (compiled.kth_smallest) against a sort:
    small k against n (the sampled path, including samples that pass too few entries: sorted
    and reversed rows), large k (the full quickselect) and heavy ties; the input unchanged."""
    from hktex_engine.kernels import compiled

    _, kth_smallest, _, _ = compiled.helpers()
    rng = np.random.default_rng(1)
    for trial in range(400):
        n = int(rng.integers(1, 700))
        k = int(rng.integers(0, n)) if trial % 2 else int(rng.integers(0, max(1, n // 8)))
        a = rng.standard_normal(n)
        if trial % 5 == 0:
            a = np.round(a * 2) / 2  # ties
        elif trial % 5 == 1:
            a = np.sort(a)
        elif trial % 5 == 2:
            a = np.sort(a)[::-1].copy()
        before = a.copy()
        buf = np.empty(2 * n)
        assert kth_smallest(a, n, k, buf) == np.sort(a)[k]
        value, below = compiled.kth_and_below(a, n, k, buf)
        assert (value, below) == (np.sort(a)[k], int((a < np.sort(a)[k]).sum()))
        np.testing.assert_array_equal(a, before)


def test_unordered_blend_gives_the_ordered_colours(spectra3, monkeypatch):
    """``ordered=False`` (queries and renders: colours only) picks the same kernels by a
    selection and sums them in candidate order: colours within float32 round-off."""
    monkeypatch.setattr(kernels_mod, "TABLE_PATH", "always")
    field = SpectralField(spectra3, device="cpu", dtype=torch.float32)
    model = make_model(field, make_params(spectra3, 300, seed=22), CONFIG)
    rng = np.random.default_rng(6)
    n = 3000
    f = torch.as_tensor(rng.integers(0, spectra3.faces.shape[0], n))
    b = torch.as_tensor(rng.dirichlet(np.ones(3), n), dtype=torch.float32)
    with torch.no_grad():
        ordered = model.albedo(f, b, return_aux=True)[0]
        plain = model.albedo(f, b)
    np.testing.assert_allclose(plain.numpy(), ordered.numpy(), rtol=0, atol=2e-6)


def test_pick_by_rule_picks_the_set_choose_by_rule_ranks():
    """The linear K_c selection (compiled.pick_by_rule) against the rule-ordered insertion
    (choose_by_rule) on rows full of ties in rho and in d2: the same positions, as a set."""
    from hktex_engine.kernels import compiled

    _, _, choose, pick = compiled.helpers()
    rng = np.random.default_rng(2)
    for trial in range(500):
        n = int(rng.integers(1, 80))
        k = int(rng.integers(1, 40))
        rho = (rng.integers(0, 4 if trial % 2 else 50, n) / 3.0).astype(np.float32)
        d2 = rng.integers(0, 3 if trial % 3 else 100, n).astype(np.float64)
        top_c = np.empty(max(k, n), np.int64)
        top_p = np.empty(max(k, n), np.int64)
        q = choose(rho, d2, n, k, top_c)
        assert pick(rho, d2, n, k, top_p, np.empty(3 * n)) == q == min(k, n)
        assert sorted(top_p[:q]) == sorted(top_c[:q])
