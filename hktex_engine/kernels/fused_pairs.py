"""The differentiable footprints of each point's chosen pairs, compiled, with their analytic
backward.

After the ranking (``kernels.fused_rank``) a training point keeps ``K_c`` kernels; for each
pair ``(p, j)`` with the saved ``dots_c = coef_j . Phi_p[n_jc]`` and ``blend = sum_c w_jc
Phi_p[n_jc]``:

    h   = sum_c w_jc dots_c                   d2 = |e_j - e_p|^2
    r   = h exp(-d2 / scale_j) / norm_j       scale_j = 2 sigma_j^2 (sigma_B, or per kernel)
    rho = S(r; eps_j, k_j) = clamp((sig(k (r - eps)) - sig(-k eps)) / (sig(k (1 - eps)) - sig(-k eps)), 0, 1)

and backward by the chain rule through each line from ``d loss / d rho``, with ``dh/dcoef_j =
blend`` and ``dh/dw_jc = dots_c``; the clamp passes the gradient where torch's does (inside,
ends included). Gradients reach the per-kernel rows (coef, norm, weights, centre embedding,
threshold, sharpness, and ``scale`` for a per-kernel-sigma set); the point side is constant
(batches whose query barycentrics need a gradient take the torch path). The colour blend after it (``kernels.blending``) is a few
``(P, K_c)`` torch operations, so it stays in torch and either blend rule trains through it.

Why hand-written: through autograd these are a dozen passes over ``(P, K_c, K)`` and
``(P, K_c, D)`` gathered blocks and their scatter-add backward, a third of a training step
after the ranking was compiled; here one loop per point forward and one backward, threads
with private accumulators summed at the end (so no two threads write one kernel's row).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hktex_engine.kernels import compiled

#: Points per thread below which one thread does the call.
THREAD_MIN_POINTS = 1024


def _sig(x):
    return np.float32(1.0) / (np.float32(1.0) + np.float32(math.exp(-x)))


def _forward(top, dots, emb_y, norm, weights, emb_c, thr, sharp, low, high, scale, rho, r_s, w_s, s_s):  # fmt: skip
    """Also keeps per pair ``r``, the weight ``w`` and ``sig(k (r - eps))`` (``r_s``, ``w_s``,
    ``s_s``) for backward; ``low``/``high``: the soft step's ends per kernel."""
    k_c = top.shape[1]
    one = np.float32(1.0)
    for p in range(top.shape[0]):
        for t in range(k_c):
            j = top[p, t]
            h = np.float32(0.0)
            for c in range(4):
                h += weights[j, c] * dots[p, t, c]
            d2 = np.float32(0.0)
            for d in range(emb_c.shape[1]):
                diff = emb_y[p, d] - emb_c[j, d]
                d2 += diff * diff
            w = np.float32(math.exp(-d2 / scale[j]))
            r = h * w / norm[j]
            sr = _sig(sharp[j] * (r - thr[j]))
            u = (sr - low[j]) / (high[j] - low[j])
            r_s[p, t] = r
            w_s[p, t] = w
            s_s[p, t] = sr
            rho[p, t] = max(min(u, one), np.float32(0.0))


def _backward(top, dots, blend, emb_y, coef, norm, weights, emb_c, thr, sharp, low, high, scale, r_s, w_s, s_s, g_rho,
              g_coef, g_norm, g_w, g_emb, g_thr, g_sharp, g_scale):  # fmt: skip
    """Accumulates into the ``g_*`` arrays (this thread's own)."""
    k_c = top.shape[1]
    kk = coef.shape[1]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for p in range(top.shape[0]):
        for t in range(k_c):
            j = top[p, t]
            # soft step (r, w and sig(k (r - eps)) as forward computed them)
            e, k = thr[j], sharp[j]
            r, w, sr = r_s[p, t], w_s[p, t], s_s[p, t]
            lo, hi = low[j], high[j]
            u = (sr - lo) / (hi - lo)
            if not (u >= zero and u <= one):
                continue
            gu = g_rho[p, t] / (hi - lo)
            ds = sr * (one - sr)
            dl = lo * (one - lo)
            dh = hi * (one - hi)
            # u = (sr - lo) / (hi - lo)
            g_r = gu * k * ds
            g_k = gu * ((r - e) * ds + e * dl - u * ((one - e) * dh + e * dl))
            g_e = gu * (-k * ds + k * dl - u * (-k * dh + k * dl))
            g_thr[j] += g_e
            g_sharp[j] += g_k
            # r = h w / norm
            g_h = g_r * w / norm[j]
            sc = scale[j]
            g_d2 = -g_r * r / sc
            g_norm[j] += -g_r * r / norm[j]
            for c in range(4):
                g_w[j, c] += g_h * dots[p, t, c]
            for q in range(kk):
                g_coef[j, q] += g_h * blend[p, t, q]
            d2 = zero
            for d in range(emb_c.shape[1]):
                diff = emb_c[j, d] - emb_y[p, d]
                g_emb[j, d] += 2 * g_d2 * diff
                d2 += diff * diff
            # r = h exp(-d2 / scale) / norm: dr/dscale = r d2 / scale^2
            g_scale[j] += -g_d2 * d2 / sc


_FORWARD = None
_BACKWARD = None


def _kernels():
    global _FORWARD, _BACKWARD, _sig
    if _FORWARD is None:
        _sig = compiled.jit(_sig, inline=True)
        _FORWARD = compiled.jit(_forward, fastmath=compiled.SIMD_SUMS)
        _BACKWARD = compiled.jit(_backward, fastmath=compiled.SIMD_SUMS)
    return _FORWARD, _BACKWARD


def pair_scales(sigma_b: float, ratio: torch.Tensor | None, n: int) -> torch.Tensor:
    """``scale`` (n,) float32 for :class:`PairResponse`: ``2 sigma_b^2`` for every row (no
    gradient), or times each row's ``ratio = sigma_j / sigma_b`` squared (with its graph,
    when it has one)."""
    if ratio is None:
        return torch.full((n,), 2.0 * sigma_b**2, dtype=torch.float32)
    return (2.0 * sigma_b**2 * ratio**2).to(torch.float32)


class PairResponse(torch.autograd.Function):
    """``rho`` (P, K_c) of the chosen pairs ``top`` (rows of the per-kernel arrays) with saved
    ``dots``/``blend``; ``scale`` (rows) ``2 sigma^2`` (:func:`pair_scales`); see the module
    doc."""

    @staticmethod
    def forward(ctx, top, dots, blend, emb_y, scale, coef, norm, weights, emb_c, thr, sharp):  # type: ignore[override]  # fmt: skip
        forward, _ = _kernels()
        # the soft step's ends per kernel, by soft_step's own torch expressions
        low = torch.sigmoid(-sharp.detach() * thr.detach())
        high = torch.sigmoid(sharp.detach() * (1 - thr.detach()))
        arrays = [compiled.array(x) for x in (top, dots, emb_y, norm, weights, emb_c, thr, sharp, low, high)]  # fmt: skip
        rho, r_s, w_s, s_s = (np.empty(top.shape, np.float32) for _ in range(4))
        scale = np.ascontiguousarray(compiled.array(scale), dtype=np.float32)

        def run(sl: slice) -> None:
            forward(*(a[sl] for a in arrays[:3]), *arrays[3:], scale, rho[sl], r_s[sl], w_s[sl], s_s[sl])  # fmt: skip

        compiled.run_threaded(run, top.shape[0], THREAD_MIN_POINTS)
        ctx.scale = scale
        ctx.per_pair = [r_s, w_s, s_s]
        ctx.ends = [compiled.array(low), compiled.array(high)]
        ctx.save_for_backward(top, dots, blend, emb_y, coef, norm, weights, emb_c, thr, sharp)
        return torch.from_numpy(rho)

    @staticmethod
    def backward(ctx, g_rho):  # type: ignore[override]
        _, backward = _kernels()
        saved = [compiled.array(x) for x in ctx.saved_tensors]
        top, dots, blend, emb_y, coef, norm, weights, emb_c, thr, sharp = saved
        r_s, w_s, s_s = ctx.per_pair
        low, high = ctx.ends
        g = compiled.array(g_rho.to(torch.float32).contiguous())
        p = top.shape[0]
        shapes = [coef.shape, norm.shape, weights.shape, emb_c.shape, thr.shape, sharp.shape, ctx.scale.shape]  # fmt: skip
        threads = max(1, min(torch.get_num_threads(), p // THREAD_MIN_POINTS))
        accs = [[np.zeros(s, np.float32) for s in shapes] for _ in range(threads)]
        bounds = np.linspace(0, p, threads + 1).astype(int)
        slices = [slice(a, z) for a, z in zip(bounds[:-1], bounds[1:], strict=True)]

        def run(i: int) -> None:
            sl = slices[i]
            backward(top[sl], dots[sl], blend[sl], emb_y[sl], coef, norm, weights, emb_c, thr, sharp, low, high, ctx.scale, r_s[sl], w_s[sl], s_s[sl], g[sl], *accs[i])  # fmt: skip

        compiled.run_each(run, threads)
        grads = [sum(a[n] for a in accs[1:]) + accs[0][n] for n in range(len(shapes))]
        grads = [torch.from_numpy(np.ascontiguousarray(x)) for x in grads]
        g_scale = grads.pop()
        return (None, None, None, None, g_scale, *grads)
