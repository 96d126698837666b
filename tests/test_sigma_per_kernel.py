"""``benchmarks/sigma_per_kernel.py``'s probe: a kernel set whose per-kernel scales are all
``c`` is the product's set with ``sigma_B = c`` (no-grad albedo, training albedo and every
other gradient), the scales' own gradient matches finite differences, and leaving the probe
restores the model class."""

from __future__ import annotations

import importlib.util
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from hktex_engine.config import KernelConfig
from hktex_engine.kernels import compiled
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_points, tiny_spectra
from tests.test_kernels import make_model, make_params

pytestmark = pytest.mark.skipif(not compiled.HAVE_NUMBA, reason="numba is not installed")

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=16, k_blend=5)


@pytest.fixture(scope="module")
def probe():
    sys.path.insert(0, str(BENCHMARKS))  # the script imports its sibling ``_machine``
    try:
        spec = importlib.util.spec_from_file_location("sigma_per_kernel", BENCHMARKS / "sigma_per_kernel.py")  # fmt: skip
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


@pytest.fixture(scope="module")
def field32():
    return SpectralField(tiny_spectra(3), device="cpu", dtype=torch.float32)


def _grads(model, f, b, target):
    model.zero_grad()
    out = model.albedo(f, b)
    ((out - target) ** 2).mean().backward()
    grads = {n: p.grad.detach().clone() for n, p in model.named_parameters() if p.grad is not None}
    return out.detach(), grads


@pytest.mark.parametrize("scale", [1.0, 0.7])
def test_uniform_scales_are_the_product_at_that_sigma(probe, field32, scale):
    kp = make_params(field32.spectra, 300, seed=31)
    f, b = random_points(field32.spectra, 700, seed=8)
    target = torch.rand((700, 3), generator=torch.Generator().manual_seed(5))
    ref_model = make_model(field32, kp, replace(CONFIG, sigma_b=CONFIG.sigma_b * scale))
    with torch.no_grad():
        ref_plain = ref_model.albedo(f, b)
    ref_out, ref_grads = _grads(ref_model, f, b, target)
    with probe.per_kernel_sigma((0.4, 2.5)):
        model = make_model(field32, kp, CONFIG)
        with torch.no_grad():
            model.priority.fill_(math.log(scale))
            plain = model.albedo(f, b)
        out, grads = _grads(model, f, b, target)
    np.testing.assert_allclose(plain.numpy(), ref_plain.numpy(), atol=1e-5)
    np.testing.assert_allclose(out.numpy(), ref_out.numpy(), atol=1e-5)
    assert "priority" in grads and "priority" not in ref_grads
    for name, g_ref in ref_grads.items():
        tol = 1e-3 * float(g_ref.abs().max())
        np.testing.assert_allclose(grads[name].numpy(), g_ref.numpy(), atol=tol, err_msg=name)


def test_scale_gradient_against_finite_differences(probe, field32):
    """``K_c = K_s``: no selection, so the blend is smooth in every scale."""
    config = replace(CONFIG, k_search=8, k_blend=8)
    kp = make_params(field32.spectra, 120, seed=32)
    f, b = random_points(field32.spectra, 900, seed=9)
    weights = torch.randn((900, 3), generator=torch.Generator().manual_seed(6))
    with probe.per_kernel_sigma((0.1, 10.0)):
        model = make_model(field32, kp, config)
        with torch.no_grad():
            model.priority.copy_(torch.empty(120).uniform_(-0.5, 0.5, generator=torch.Generator().manual_seed(7)))  # fmt: skip
        (model.albedo(f, b) * weights).sum().backward()
        grad = model.priority.grad.clone()
        chosen = torch.argsort(grad.abs(), descending=True)[:4]
        assert float(grad[chosen].abs().min()) > 0.1  # a check that can fail
        eps = 1e-2
        for j in chosen.tolist():
            values = []
            for sign in (1, -1):
                with torch.no_grad():
                    model.priority[j] += sign * eps
                    values.append(float((probe.albedo_no_grad(model, f, b) * weights).sum()))
                    model.priority[j] -= sign * eps
            fd = (values[0] - values[1]) / (2 * eps)
            assert fd == pytest.approx(float(grad[j]), rel=2e-2, abs=1e-3)


def test_leaving_the_probe_restores_the_model(probe, field32):
    before = dict(HeatKernelModel.__dict__)
    with probe.per_kernel_sigma():
        assert HeatKernelModel.__dict__["albedo"] is not before["albedo"]
    for name in ("__init__", "_train_blend", "albedo", "project_", "priority_of"):
        assert HeatKernelModel.__dict__[name] is before[name]
    model = make_model(field32, make_params(field32.spectra, 10, seed=1), CONFIG)
    assert not model.priority.requires_grad
