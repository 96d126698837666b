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


def split(src, s0, cnt, pivot, dst, d0):
    """``src[s0:s0 + cnt]``'s entries below ``pivot`` to the front of ``dst[d0:d0 + cnt]`` and
    those above it to its back, without a data-dependent branch (every entry is written to
    both free ends and only the matching end's count moves: the other write lands outside
    both filled ranges). Returns ``(below, above)``."""
    below = 0
    above = 0
    last = d0 + cnt - 1
    for i in range(cnt):
        v = src[s0 + i]
        dst[d0 + below] = v
        dst[last - above] = v
        below += v < pivot
        above += v > pivot
    return below, above


def middle_of_three(x, y, z):
    """The median of three values (the pivot: always an entry, so each round drops one)."""
    return max(min(x, y), min(max(x, y), z))


def kth_and_below(a, n, k, buf):
    """``(v, below)``: the ``k``-th smallest (0-based) ``v`` of ``a[:n]`` and how many entries
    are smaller than it, ``a`` unchanged (``buf``: scratch of ``2 n``). A quickselect whose
    partition has no data-dependent branch (:func:`split`), ping-ponging between the two
    halves of ``buf``; entries equal to the pivot leave each round at once, and the entries
    left behind below the answer are counted on the way (the caller's cut needs that count).
    Why not Hoare's in-place partition: on a blend's ~94 candidate distances its
    mispredicted branches cost ~2 us a point, half the blend."""
    pivot = middle_of_three(a[0], a[n >> 1], a[n - 1])
    below, above = split(a, 0, n, pivot, buf, 0)
    start = 0
    cnt = n
    passed = 0  # entries known to lie below the answer, outside the current range
    while True:
        if k < below:
            cnt = below
        elif k >= cnt - above:
            k -= cnt - above
            passed += cnt - above
            start += cnt - above
            cnt = above
        else:
            return pivot, passed + below
        if cnt <= 8:
            for i in range(start + 1, start + cnt):  # insertion sort of the few left
                v = buf[i]
                j = i - 1
                while j >= start and buf[j] > v:
                    buf[j + 1] = buf[j]
                    j -= 1
                buf[j + 1] = v
            v = buf[start + k]
            first = k
            while first > 0 and buf[start + first - 1] == v:
                first -= 1
            return v, passed + first
        pivot = middle_of_three(buf[start], buf[start + (cnt >> 1)], buf[start + cnt - 1])
        dst = n if start < n else 0
        below, above = split(buf, start, cnt, pivot, buf, dst)
        start = dst


def kth_smallest(a, n, k, buf):
    """The ``k``-th smallest (0-based) of ``a[:n]``, ``a`` unchanged (:func:`kth_and_below`)."""
    return kth_and_below(a, n, k, buf)[0]


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


def pick_by_rule(rho, d2, n, k, top, buf):
    """Positions ``top[:q]`` (``q = min(k, n)``) of the same ``k`` best of ``rho[:n]`` as
    :func:`choose_by_rule` picks, in position order instead of rule order, for callers that
    only sum them: a branch-free quickselect (:func:`kth_and_below` on ``-rho`` in
    ``buf[2n:3n]``, ``buf``: float64 scratch of ``3 n``) finds the ``k``-th largest ``rho``,
    every entry above it is in, and the entries equal to it fill the rest by smallest ``d2``,
    then position (the tie rule; settled by insertion, as ties at the cut are few). Linear in
    ``n`` where the sorted buffer moves up to ``k`` entries per insertion. Returns ``q``."""
    if n <= k:
        for i in range(n):
            top[i] = i
        return n
    for i in range(n):
        buf[2 * n + i] = -rho[i]
    neg_cut, _ = kth_and_below(buf[2 * n : 3 * n], n, k - 1, buf)
    cut = -neg_cut  # exact: a float32 value held in a float64
    above = 0
    ties = 0
    for i in range(n):  # without data-dependent branches
        top[above] = i
        above += rho[i] > cut
        ties += rho[i] == cut
    need = k - above
    filled = 0
    for i in range(n):
        if rho[i] != cut:
            continue
        if ties == need:
            top[above + filled] = i
            filled += 1
            continue
        if filled == need:
            if not d2[i] < d2[top[above + need - 1]]:
                continue
            slot = need - 1
        else:
            slot = filled
            filled += 1
        while slot > 0 and d2[i] < d2[top[above + slot - 1]]:
            top[above + slot] = top[above + slot - 1]
            slot -= 1
        top[above + slot] = i
    return k


_HELPERS = None


def helpers():
    """The helpers above compiled, once: they replace the plain functions in this module's
    namespace first, so a helper that calls another (``kth_smallest`` calls
    ``kth_and_below``, which calls ``split``) is compiled against the compiled one. Returns
    ``(unit, kth_smallest, choose_by_rule, pick_by_rule)``; ``kth_and_below`` is compiled with
    them (a module global)."""
    global _HELPERS, unit, split, middle_of_three, kth_smallest, choose_by_rule
    global pick_by_rule, kth_and_below
    with LOCK:
        if _HELPERS is None:
            unit = jit(unit, inline=True)
            choose_by_rule = jit(choose_by_rule, inline=True)
            split = jit(split, inline=True)
            middle_of_three = jit(middle_of_three, inline=True)
            kth_and_below = jit(kth_and_below, inline=True)
            kth_smallest = jit(kth_smallest)
            pick_by_rule = jit(pick_by_rule)
            _HELPERS = (unit, kth_smallest, choose_by_rule, pick_by_rule)
    return _HELPERS


def array(t: torch.Tensor) -> np.ndarray:
    """A C-contiguous numpy view of a CPU tensor without a graph (a copy only when it is not
    contiguous)."""
    t = t.detach()
    return t.numpy() if t.is_contiguous() else np.ascontiguousarray(t.numpy())


def row_scales(sigma_b: float, ratio: torch.Tensor | None, n: int) -> np.ndarray:
    """``2 sigma^2`` per kernel row (float64), the decay's divisor: ``2 sigma_b^2`` for all
    ``n`` rows (the number the scalar was, so uniform sets keep their bits) or times each
    row's ``ratio = sigma_j / sigma_b`` squared (exactly that number at a ratio of one)."""
    if ratio is None:
        return np.full(n, 2.0 * sigma_b**2)
    return 2.0 * sigma_b**2 * ratio.detach().to(torch.float64).cpu().numpy() ** 2


def run_threaded(run: Callable[[slice], None], n: int, min_points: int) -> None:
    """``run(slice)`` over ``range(n)`` in up to ``torch.get_num_threads()`` threads, each with
    at least ``min_points`` points (the compiled loops release the GIL)."""
    threads = max(1, min(torch.get_num_threads(), n // max(1, min_points)))
    if threads == 1:
        run(slice(0, n))
        return
    bounds = np.linspace(0, n, threads + 1).astype(int)
    list(
        _pool(threads).map(run, [slice(a, z) for a, z in zip(bounds[:-1], bounds[1:], strict=True)])
    )


def run_each(run: Callable[[int], None], threads: int) -> None:
    """``run(i)`` for ``i < threads``, each in its own thread (one: in this one)."""
    if threads == 1:
        run(0)
        return
    list(_pool(threads).map(run, range(threads)))


_POOL: list[tuple[int, ThreadPoolExecutor]] = []  # (threads, pool), at most one


def _pool(threads: int) -> ThreadPoolExecutor:
    """One process-wide pool for the compiled loops, grown when more threads are asked for.

    Why kept: a render asks for the albedo four times and a fit every step; starting fresh
    threads each call cost ~0.3-1 ms under load. Calls from several threads share it (their
    chunks queue), which also keeps concurrent callers from oversubscribing the cores."""
    with LOCK:
        if not _POOL or _POOL[0][0] < threads:
            old = _POOL[:]
            _POOL[:] = [(threads, ThreadPoolExecutor(threads, thread_name_prefix="hktex-compiled"))]
            for _, pool in old:
                pool.shutdown(wait=False)
        return _POOL[0][1]
