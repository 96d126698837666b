"""Compiling a numeric loop with numba: the one way every compiled path of the engine does it.

Torch-free on purpose: the spectra worker processes (``spectra.triangular``) compile their
sparse triangular solves through this module and must not pay torch's import. numba itself
is imported on first use (~0.5-1 s that a command not needing it should not pay); compiled
code is cached on disk, so later processes load it in well under a second.
"""

from __future__ import annotations

import importlib.util
import threading
from collections.abc import Callable

HAVE_NUMBA = importlib.util.find_spec("numba") is not None

#: LLVM flags that let a float32 dot product run in SIMD lanes (re-associated sums, fused
#: multiply-adds); none that change NaN, infinity or signed-zero handling.
SIMD_SUMS = frozenset({"reassoc", "contract"})

LOCK = threading.RLock()


def jit(fn: Callable, inline: bool = False, fastmath: frozenset = frozenset()) -> Callable:
    """``fn`` compiled by numba (``nogil``, cached on disk where a cache folder is writable)."""
    import numba

    flags = set(fastmath) or False
    with LOCK:
        if inline:
            return numba.njit(inline="always", fastmath=flags)(fn)
        try:
            return numba.njit(nogil=True, cache=True, fastmath=flags)(fn)
        except RuntimeError:  # no writable cache location: compile in each process
            return numba.njit(nogil=True, fastmath=flags)(fn)
