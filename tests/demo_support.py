"""The small textured demo mesh, its spectra and a random kernel set, shared by the render,
bake, views and multi-view tests (one definition, so the tests exercise the same inputs)."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest

from hktex_engine.config import SpectralConfig
from hktex_engine.errors import RenderError

# 3 angles x 2 anisotropies x k=16: the smallest grid that still interpolates in both axes
DEMO_CONFIG = SpectralConfig(angles=3, anisotropies=(1.0, 5.0), k=16, k_iso=9)


def demo_arrays() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, corner_uvs, texture) of the tiny textured demo sphere."""
    from hktex_engine.evaluation.synthetic import textured_demo

    return textured_demo(subdivisions=2, texture_size=32)


def require_render() -> ModuleType:
    """The render module with its Mitsuba AD variant set; skips the test when there is none."""
    from hktex_engine.render import mitsuba as render

    try:
        render.ensure_variant()
    except RenderError as exc:
        pytest.skip(f"no Mitsuba AD variant: {exc}")
    return render


def random_kernelset(spectra, n: int, seed: int = 0):
    """``n`` kernels at random surface points with random shapes and colours, bound to
    ``spectra`` (wide ranges of theta/eta/threshold so the bake sees varied kernels)."""
    from hktex_engine.geometry.sampling import sample_surface
    from hktex_engine.kernels.model import KernelSet

    rng = np.random.default_rng(seed)
    f, b = sample_surface(spectra.vertices, spectra.faces, n, rng)
    return KernelSet(
        face_ids=f,
        barycentrics=b,
        theta=rng.uniform(0, np.pi, n),
        eta=1 + 99 * rng.random(n),
        threshold=rng.uniform(0.5, 0.9, n),
        sharpness=10 + 40 * rng.random(n),
        colors=rng.uniform(-0.5, 0.5, (n, 3)),
        base_color=np.array([0.5, 0.4, 0.3]),
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
    )
