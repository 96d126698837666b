"""What the compiled (numba) evaluation paths share: availability, compilation, threads.

``kernels.fused_blend`` (no-grad queries from face tables) and ``kernels.fused_rank``
(the training step's candidate search and ranking) are loops over points compiled with
numba: each point's work is a few thousand flops spread over a dozen small arrays, which
torch can only do as a dozen full passes through memory. numba is imported on first use
(its import costs ~0.5-1 s that a CLI call should not pay) and its compiled code is cached
on disk, so later processes load it in well under a second.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from hktex_engine.jit import HAVE_NUMBA, LOCK, SIMD_SUMS, jit

__all__ = ["HAVE_NUMBA", "SIMD_SUMS", "jit"]


#: ``HKTEX_FUSED_BLEND=0`` turns every compiled path off (the torch paths answer).
ENABLED = os.environ.get("HKTEX_FUSED_BLEND", "1") != "0"


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether compiled paths can answer for tensors on ``device`` in ``dtype`` (CPU float32)."""
    return ENABLED and HAVE_NUMBA and device.type == "cpu" and dtype == torch.float32


def unit(v):
    """``v`` (float32) clamped to [0, 1]."""
    return max(min(v, np.float32(1.0)), np.float32(0.0))


def select(a, n, k):
    """The ``k``-th smallest (0-based) of ``a[:n]``, reordering ``a`` in place (Hoare's
    quickselect, middle pivot; ``np.partition`` would allocate a copy per point)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


def kth_smallest(a, n, k, buf):
    """The ``k``-th smallest (0-based) of ``a[:n]``, ``a`` unchanged (``buf``: scratch of
    ``n``). When ``k`` is small against ``n``, a strided sample's order statistic bounds about
    twice ``k`` entries, one predictable pass keeps those, and the quickselect runs on them
    (the ``k + 1`` smallest are all within the bound whenever more than ``k`` entries pass, so
    the answer is exact); otherwise, or when the sample passes too few, over all ``n``."""
    stride = 8
    if n >= 4 * (k + 1):
        m_s = (n + stride - 1) // stride
        for i in range(m_s):
            buf[i] = a[i * stride]
        bound = select(buf, m_s, min(m_s - 1, 2 * (k + 1) // stride + 2))
        m = 0
        for j in range(n):
            if a[j] <= bound:
                buf[m] = a[j]
                m += 1
        if m > k:
            return select(buf, m, k)
    buf[:n] = a[:n]
    return select(buf, n, k)


def choose_by_rule(rho, d2, n, k, top):
    """Positions ``top[:q]`` (``q = min(k, n)``) of the ``k`` best of ``rho[:n]`` in rule
    order: largest ``rho``, then smallest ``d2``, then position (the callers' entries come in
    kernel-id order or nearest first by the rule, so a later entry loses an exact tie on
    both); a sorted buffer, entries that cannot enter it cost one comparison. Returns ``q``."""
    q = k if k < n else n
    filled = 0
    for i in range(n):
        if filled == q:
            last = top[q - 1]
            if not (rho[i] > rho[last] or (rho[i] == rho[last] and d2[i] < d2[last])):
                continue
            slot = q - 1
        else:
            slot = filled
            filled += 1
        while slot > 0:
            a = top[slot - 1]
            if rho[i] > rho[a] or (rho[i] == rho[a] and d2[i] < d2[a]):
                top[slot] = a
                slot -= 1
            else:
                break
        top[slot] = i
    return q


_HELPERS = None


def helpers():
    """The helpers below compiled, once: they replace the plain functions in this module's
    namespace first, so a helper that calls another (``kth_smallest`` calls ``select``) is
    compiled against the compiled one. Returns ``(unit, select, kth_smallest,
    choose_by_rule)``."""
    global _HELPERS, unit, select, kth_smallest, choose_by_rule
    with LOCK:
        if _HELPERS is None:
            unit = jit(unit, inline=True)
            choose_by_rule = jit(choose_by_rule, inline=True)
            select = jit(select)
            kth_smallest = jit(kth_smallest)
            _HELPERS = (unit, select, kth_smallest, choose_by_rule)
    return _HELPERS


def array(t: torch.Tensor) -> np.ndarray:
    """A C-contiguous numpy view of a CPU tensor without a graph (a copy only when it is not
    contiguous)."""
    t = t.detach()
    return t.numpy() if t.is_contiguous() else np.ascontiguousarray(t.numpy())


def run_threaded(run: Callable[[slice], None], n: int, min_points: int) -> None:
    """``run(slice)`` over ``range(n)`` in up to ``torch.get_num_threads()`` threads, each with
    at least ``min_points`` points (the compiled loops release the GIL)."""
    threads = max(1, min(torch.get_num_threads(), n // max(1, min_points)))
    if threads == 1:
        run(slice(0, n))
        return
    bounds = np.linspace(0, n, threads + 1).astype(int)
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, [slice(a, z) for a, z in zip(bounds[:-1], bounds[1:], strict=True)]))


def run_each(run: Callable[[int], None], threads: int) -> None:
    """``run(i)`` for ``i < threads``, each in its own thread (one: in this one)."""
    if threads == 1:
        run(0)
        return
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, range(threads)))
