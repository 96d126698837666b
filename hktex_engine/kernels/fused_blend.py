"""The no-grad blend of ALGORITHM.md section 5 from face tables, compiled, one pass per point.

Why hand-written: the torch path (``HeatKernelModel._blend_tables``) spends its time in a
dozen full passes over ``(P, L)`` candidate arrays (strided gathers, two ``topk`` and the tie
bookkeeping around them), each a trip through memory for a few flops; on the CPU that is
~20 us per point where the arithmetic is ~1 us. No library fuses a top-k under a custom tie
rule with the heat-kernel response, so this module does it in one compiled loop per point
(numba, ``nogil``: threads split the points).

Same mathematics, same rule: the squared distances (which decide the ``K_s`` cut) are the
same floating-point operations in the same order as the torch path, bit for bit; the
responses and footprints are float32 as there, with ``exp`` in float32 (the torch path takes
float64 ``exp`` and casts: within an ulp, and 20 % of this loop's time) and libm's
``exp``/``sigmoid`` in place of torch's, so ``rho`` agrees to float32 round-off, the chosen
kernels are the same wherever no two ``rho`` are within round-off of each other (saturated
ties at exactly 0 or 1 included), and colours agree to ~1e-6.
Only the CPU float32 path uses it; CUDA and other dtypes keep the torch path. The layered
blend (``kernels.blending``) is the same loop with the chosen kernels' priorities weighting
their shares (``layered``; ``prio`` holds one priority per kernel).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from hktex_engine.kernels import compiled

HAVE_NUMBA = compiled.HAVE_NUMBA

log = logging.getLogger("hktex.kernels")

#: Off with ``HKTEX_FUSED_BLEND=0`` (``kernels.compiled``) or when it fails to build.
ENABLED = compiled.ENABLED
#: Below this many points one thread does the whole call (thread start-up would dominate).
THREAD_MIN_POINTS = 2048

_unit = compiled.unit
_choose = compiled.choose_by_rule
_pick = compiled.pick_by_rule
_kth_below = compiled.kth_and_below


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the compiled blend can answer for a model on ``device`` in ``dtype``."""
    return ENABLED and compiled.available(device, dtype)


#: Columns of the per-kernel attribute rows :func:`_blend_points` reads (one 32-byte row a
#: kernel, so a candidate's five attributes and colour arrive in one cache line: measured
#: 3.83 -> 3.30 us a point on a render's points, bit-identical, against six separate arrays).
NORM, THR, SHARP, LOW, HIGH, RED = range(6)
ATTR_WIDTH = 8


def _blend_points(
    rows, bary, kid_t, h_t, d2_t, edge2, count, attrs, base, scale, k_s, k_c,
    out, out_kid, out_rho, ordered, prio, layered,
):  # fmt: skip
    """Colours ``out[p]`` for points ``p`` at face-table rows ``rows`` (see :func:`blend`),
    and, when ``ordered``, the blended kernels ``out_kid[p]`` with their ``out_rho[p]`` in
    rule order (else those two are not touched: the same kernels are chosen by a selection
    and summed in candidate order)."""
    width = kid_t.shape[1]
    n_kernels = attrs.shape[0]
    d2 = np.empty(width, np.float64)
    part = np.empty(3 * width, np.float64)
    pos = np.empty(width, np.int64)
    cd2 = np.empty(width, np.float64)
    rho = np.empty(width, np.float32)
    top = np.empty(max(k_c, width), np.int64)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for p in range(rows.shape[0]):
        r = rows[p]
        c0, c1, c2 = bary[p, 0], bary[p, 1], bary[p, 2]  # float32
        b0, b1, b2 = np.float64(c0), np.float64(c1), np.float64(c2)
        n = count[r]
        # exact squared embedding distance, in tables.point_distances' order of operations
        quad = b0 * b1 * edge2[r, 0] + b0 * b2 * edge2[r, 1]
        quad = quad + b1 * b2 * edge2[r, 2]
        for j in range(n):
            v = d2_t[r, j, 0] * b0 + d2_t[r, j, 1] * b1 + d2_t[r, j, 2] * b2
            v = v - quad
            d2[j] = v if v > 0.0 else 0.0
        # K_s cut: the k_s smallest distances, ties by kernel id (row order is kernel order)
        m = k_s if k_s < n else n
        if m < n:
            kth, less = _kth_below(d2, n, m - 1, part)
            ties = m - less
            taken = 0
            for j in range(n):  # without data-dependent branches (they mispredict half the time)
                v = d2[j]
                tie = (v == kth) & (ties > 0)
                pos[taken] = j
                taken += (v < kth) | tie
                ties -= tie
        else:
            for j in range(n):
                pos[j] = j
        # responses and footprints of the cut, as _blend_tables computes them in float32
        for i in range(m):
            j = pos[i]
            k = kid_t[r, j]
            h = h_t[r, j, 0] * c0 + h_t[r, j, 1] * c1 + h_t[r, j, 2] * c2
            w = math.exp(np.float32(-d2[j] / scale[k]))  # float32 exp: within an ulp of the cast
            x = h * w / attrs[k, NORM]
            s = one / (one + np.float32(math.exp(-(attrs[k, SHARP] * (x - attrs[k, THR])))))
            v = (s - attrs[k, LOW]) / (attrs[k, HIGH] - attrs[k, LOW])
            rho[i] = _unit(v)
            cd2[i] = d2[j]
        # K_c choice: largest rho, then smallest distance, then kernel id (row order)
        if ordered:
            q = _choose(rho, cd2, m, k_c, top)
        else:
            q = _pick(rho, cd2, m, k_c, top, part)
        top_prio = -np.inf
        if layered:
            for t in range(q):
                v = prio[kid_t[r, pos[top[t]]]]
                top_prio = v if v > top_prio else top_prio
        acc0 = zero
        acc1 = zero
        acc2 = zero
        total = zero
        mass = zero
        if ordered:
            for t in range(q, k_c):  # fewer candidates than K_c: padding, as the torch path
                out_kid[p, t] = n_kernels
                out_rho[p, t] = zero
        for t in range(q):
            i = top[t]
            k = kid_t[r, pos[i]]
            if ordered:
                out_kid[p, t] = k
                out_rho[p, t] = rho[i]
            omega = rho[i]
            if layered:
                omega = omega * np.float32(math.exp(prio[k] - top_prio))
            acc0 += omega * attrs[k, RED]
            acc1 += omega * attrs[k, RED + 1]
            acc2 += omega * attrs[k, RED + 2]
            total += rho[i]
            mass += omega
        if layered:  # coverage min(1, sum rho), shares by priority (kernels.blending)
            cover = total if total < one else one
            scale_out = cover / mass if mass > zero else zero
            out[p, 0] = _unit(base[0] + acc0 * scale_out)
            out[p, 1] = _unit(base[1] + acc1 * scale_out)
            out[p, 2] = _unit(base[2] + acc2 * scale_out)
        else:
            denom = total if total > one else one
            out[p, 0] = _unit(base[0] + acc0 / denom)
            out[p, 1] = _unit(base[1] + acc1 / denom)
            out[p, 2] = _unit(base[2] + acc2 / denom)


_COMPILED = None


def _kernel():
    """The compiled ``_blend_points`` (built on first use)."""
    global _COMPILED, _unit, _choose, _pick, _kth_below
    if _COMPILED is None:
        _unit, _, _choose, _pick = compiled.helpers()
        _kth_below = compiled.kth_and_below
        _COMPILED = compiled.jit(_blend_points)
    return _COMPILED


def blend(
    ft,
    face_ids: torch.Tensor,
    bary: torch.Tensor,
    norm: torch.Tensor,
    threshold: torch.Tensor,
    sharpness: torch.Tensor,
    colors: torch.Tensor,
    base_color: torch.Tensor,
    sigma_b: float,
    k_s: int,
    k_c: int,
    ordered: bool = True,
    priority: torch.Tensor | None = None,
    ratio: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """``(albedo (P, 3), kernel ids (P, K_c), rho (P, K_c))`` at points ``(face_ids, bary)``
    from face tables ``ft`` (``kernels.tables.FaceTables`` covering their faces), the blended
    kernels in rule order; in threads over chunks of points. ``ordered=False`` returns the
    albedo alone (ids and rho None): the same kernels, chosen by a linear selection and
    summed in candidate order (colours within float32 round-off of the ordered sum), for
    queries and renders that need no statistics. ``priority`` (N,): the layered blend's;
    ``ratio`` (N,): each kernel's ``sigma_j / sigma_b`` (a per-kernel-sigma set), else none."""
    # gathers and casts in numpy: torch's parallel kernels contend with a renderer's threads
    rows = compiled.array(ft.rows)[face_ids.numpy()]
    # per-kernel ends of the soft step, by soft_step's own torch expressions (same bits)
    low = torch.sigmoid(-sharpness * threshold)
    high = torch.sigmoid(sharpness * (1 - threshold))
    # tables hold no graph (views, not copies: they may be the whole mesh's); the kernels'
    # attributes (possibly Parameters, detached) are copied into one row a kernel
    tables = [compiled.array(t) for t in (ft.kid, ft.h, ft.d2, ft.edge2, ft.count)]
    per_kernel = [norm, threshold, sharpness, low, high]
    # filled in numpy too: torch.zeros of 5,000 x 8 runs in parallel and waited ~1-5 ms a
    # call for a thread busy elsewhere (a renderer's, a fit's), a render's small calls' cost
    attrs = np.zeros((norm.shape[0], ATTR_WIDTH), dtype=np.float32)
    for i, t in enumerate(per_kernel):
        attrs[:, i] = compiled.array(t.detach())
    attrs[:, RED : RED + 3] = compiled.array(colors.detach())
    args = [*tables, attrs, compiled.array(base_color)]
    layered = priority is not None
    prio = np.ascontiguousarray(
        compiled.array(priority.detach()) if layered else np.zeros(1), dtype=np.float32
    )
    b = np.ascontiguousarray(compiled.array(bary), dtype=np.float32)
    # divided by, as the torch path does (not a reciprocal)
    scale = compiled.row_scales(sigma_b, ratio, norm.shape[0])
    n = rows.shape[0]
    k_c = min(k_c, k_s)
    out = np.empty((n, 3), dtype=np.float32)
    width = k_c if ordered else 0
    out_kid = np.empty((n, width), dtype=np.int64)
    out_rho = np.empty((n, width), dtype=np.float32)
    kernel = _kernel()

    def run(sl: slice) -> None:
        kernel(rows[sl], b[sl], *args, scale, k_s, k_c, out[sl], out_kid[sl], out_rho[sl], ordered, prio, layered)  # fmt: skip

    compiled.run_threaded(run, n, THREAD_MIN_POINTS)
    if not ordered:
        return torch.from_numpy(out), None, None
    return torch.from_numpy(out), torch.from_numpy(out_kid), torch.from_numpy(out_rho)


def warm() -> None:
    """Compile (or load from numba's on-disk cache) the blend now, on a one-point problem of
    the real argument types, so a service's first query does not pay it (seconds)."""
    global ENABLED
    if not HAVE_NUMBA or not ENABLED:
        return
    from types import SimpleNamespace

    f32, f64, i64 = torch.float32, torch.float64, torch.long
    ft = SimpleNamespace(
        rows=torch.zeros(1, dtype=i64),
        kid=torch.zeros((1, 1), dtype=i64),
        h=torch.ones((1, 1, 3), dtype=f32),
        d2=torch.zeros((1, 1, 3), dtype=f64),
        edge2=torch.zeros((1, 3), dtype=f64),
        count=torch.ones(1, dtype=i64),
    )
    one = torch.ones(1, dtype=f32)
    bary = torch.full((1, 3), 1.0 / 3.0, dtype=f32)
    try:
        blend(ft, torch.zeros(1, dtype=i64), bary, one, one / 2, one * 10, torch.zeros((1, 3)), one.expand(3), 0.1, 1, 1)  # fmt: skip
    except Exception:  # noqa: BLE001 - a compiler that fails here would fail every query
        log.exception("the compiled blend failed to build; the torch path answers instead")
        ENABLED = False
