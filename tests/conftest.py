"""Shared test fixtures: where the shared meshes are, and small generated meshes."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import tiny_spectra

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared real meshes (../shared/data); tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


@pytest.fixture(scope="module")
def spectra():
    """The kernel tests' tiny icosphere spectra (``kernels_support.tiny_spectra``, cached per
    process); a module may override it (test_query moves it to another file frame)."""
    return tiny_spectra()


@pytest.fixture(scope="module")
def field64(spectra):
    """A float64 CPU :class:`SpectralField` on ``spectra``, for tight comparisons."""
    return SpectralField(spectra, device="cpu", dtype=torch.float64)
