"""Per-kernel spectral terms with their analytic backward, compiled (ALGORITHM.md 2 and 4).

For kernel ``j`` with centre barycentrics ``b`` on vertices ``v`` and bilinear grid nodes
``n_c`` with weights ``w_c``:

    phi    = sum_v sum_c b_v w_c E[v, n_c]          (K,)  eigenfunctions at the centre
    lambda = sum_c w_c Lambda[n_c]                   (K,)  interpolated eigenvalues
    coef   = exp(-t lambda) * phi                    (K,)
    norm   = coef . phi                                    h_j(c_j)

and, for upstream gradients ``g_coef`` and ``g_norm`` (with ``e = exp(-t lambda)``):

    g_phi    = e g_coef + 2 g_norm coef
    g_lambda = -t coef (g_coef + g_norm phi)
    T_vc     = E[v, n_c] . g_phi
    g_b_v    = sum_c w_c T_vc
    g_w_c    = sum_v b_v T_vc + Lambda[n_c] . g_lambda

Why hand-written: through autograd this chain is a dozen tensor passes over ``(N, 12, K)``
gathered rows and their products (a third of a training step at 10k kernels); here it is
two loops over kernels (16 K multiply-adds each way), reading the grid's rows in place.
The weights' own dependence on ``(theta, s)`` stays in torch (``bilinear_nodes``). CPU
float32 only; the torch path (``HeatKernelModel._spectral_terms``) stays the reference.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hktex_engine.kernels import compiled
from hktex_engine.kernels.fused_rank import can_rank, field_evecs32, has_float32
from hktex_engine.spectra.interpolation import gather_rows

#: Kernels per thread below which one thread does the call.
THREAD_MIN_KERNELS = 2048


def available(field, dtype: torch.dtype) -> bool:
    """Whether the compiled terms can answer for ``field`` in ``dtype`` (a float16 grid with
    no float32 copy has its kernels' rows gathered and up-cast per call, :func:`row_table`)."""
    return compiled.available(field.device, dtype) and can_rank(field)


def _forward(table, ridx, evals, nodes, bary, weights, t, coef, phi, decay, norm):
    """``ridx[j, 4 v + c]``: the row of ``table`` holding ``E[vertex v of j, node c of j]``."""
    k = table.shape[1]
    lam = np.empty(k, np.float32)
    for j in range(ridx.shape[0]):
        for q in range(k):
            phi[j, q] = np.float32(0.0)
            lam[q] = np.float32(0.0)
        for c in range(4):
            w = weights[j, c]
            for v in range(3):
                bw = bary[j, v] * w
                row = ridx[j, 4 * v + c]
                for q in range(k):
                    phi[j, q] += bw * table[row, q]
            g = nodes[j, c]
            for q in range(k):
                lam[q] += w * evals[g, q]
        acc = np.float32(0.0)
        for q in range(k):
            e = np.float32(math.exp(-t * lam[q]))
            decay[j, q] = e
            coef[j, q] = e * phi[j, q]
            acc += coef[j, q] * phi[j, q]
        norm[j] = acc


def _backward(table, ridx, evals, nodes, bary, weights, t, coef, phi, decay, g_coef, g_norm, g_bary, g_w):  # fmt: skip
    k = table.shape[1]
    g_phi = np.empty(k, np.float32)
    g_lam = np.empty(k, np.float32)
    for j in range(ridx.shape[0]):
        gn = g_norm[j]
        if gn == 0.0:  # a kernel no chosen pair used (most, in small batches): no rows to read
            used = False
            for q in range(k):
                if g_coef[j, q] != 0.0:
                    used = True
                    break
            if not used:
                for v in range(3):
                    g_bary[j, v] = np.float32(0.0)
                for c in range(4):
                    g_w[j, c] = np.float32(0.0)
                continue
        for q in range(k):
            g_phi[q] = decay[j, q] * g_coef[j, q] + 2 * gn * coef[j, q]
            g_lam[q] = -t * coef[j, q] * (g_coef[j, q] + gn * phi[j, q])
        for v in range(3):
            g_bary[j, v] = np.float32(0.0)
        for c in range(4):
            g = nodes[j, c]
            acc = np.float32(0.0)
            for q in range(k):
                acc += evals[g, q] * g_lam[q]
            g_w[j, c] = acc
            for v in range(3):
                row = ridx[j, 4 * v + c]
                acc = np.float32(0.0)
                for q in range(k):
                    acc += table[row, q] * g_phi[q]
                g_bary[j, v] += weights[j, c] * acc
                g_w[j, c] += bary[j, v] * acc


def _embed(table, verts, bary, out):
    """``out[u] = sum_v bary[u, v] table[verts[u, v]]`` (biharmonic embedding at points)."""
    for u in range(verts.shape[0]):
        for d in range(table.shape[1]):
            out[u, d] = (
                bary[u, 0] * table[verts[u, 0], d]
                + bary[u, 1] * table[verts[u, 1], d]
                + bary[u, 2] * table[verts[u, 2], d]
            )


def _embed_backward(table, verts, g_out, g_bary):
    for u in range(verts.shape[0]):
        for v in range(3):
            acc = np.float32(0.0)
            row = verts[u, v]
            for d in range(table.shape[1]):
                acc += table[row, d] * g_out[u, d]
            g_bary[u, v] = acc


_FORWARD = None
_BACKWARD = None
_EMBED = None
_EMBED_BACKWARD = None


def _kernels():
    global _FORWARD, _BACKWARD, _EMBED, _EMBED_BACKWARD
    if _FORWARD is None:
        _FORWARD = compiled.jit(_forward, fastmath=compiled.SIMD_SUMS)
        _BACKWARD = compiled.jit(_backward, fastmath=compiled.SIMD_SUMS)
        _EMBED = compiled.jit(_embed, fastmath=compiled.SIMD_SUMS)
        _EMBED_BACKWARD = compiled.jit(_embed_backward, fastmath=compiled.SIMD_SUMS)
    return _FORWARD, _BACKWARD


def _embedding_table(field) -> np.ndarray:
    """The field's vertex embedding as a C-contiguous float32 array, made once per field (the
    spectra may hold it column-major, and a copy per call cost more than the loop)."""
    table = getattr(field, "_embedding32", None)
    if table is None:
        table = np.ascontiguousarray(field.embedding.numpy(), dtype=np.float32)
        field._embedding32 = table
    return table


class Embedding(torch.autograd.Function):
    """The biharmonic embedding at points (``SpectralField.embedding_at``), differentiable
    in the barycentrics: through autograd a gathered ``(P, 3, D)`` block and an einsum each
    way (a tenth of a training step at 10k kernels), here one loop each way."""

    @staticmethod
    def forward(ctx, field, face_ids, bary):  # type: ignore[override]
        _kernels()
        table = _embedding_table(field)
        verts = compiled.array(field.faces[face_ids])
        out = np.empty((verts.shape[0], table.shape[1]), np.float32)
        b = compiled.array(bary.to(torch.float32))

        def run(sl: slice) -> None:
            _EMBED(table, verts[sl], b[sl], out[sl])

        compiled.run_threaded(run, verts.shape[0], THREAD_MIN_KERNELS)
        ctx.table, ctx.verts, ctx.dtype = table, verts, bary.dtype
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g_out):  # type: ignore[override]
        g = compiled.array(g_out.to(torch.float32))
        g_bary = np.empty((ctx.verts.shape[0], 3), np.float32)
        _EMBED_BACKWARD(ctx.table, ctx.verts, g, g_bary)
        return None, None, torch.from_numpy(g_bary).to(ctx.dtype)


def row_table(field, verts: torch.Tensor, nodes: torch.Tensor, rows=None):
    """``(table (R, K) float32, ridx (U, 12))`` for :class:`KernelTerms`: the kernels' rows
    of a ``RowCache`` (``rows``: contiguous, read in sequence) or of the grid itself."""
    if rows is not None or not has_float32(field):
        # the rows gathered (and up-cast) contiguously: the row cache's, or a block of this
        # call's own when the grid is float16 and has no float32 copy (a query service's
        # memory-mapped grids are not copied per process)
        if rows is not None:
            block = rows.rows(field, verts, nodes)  # (U, 12, K): rows v * 4 + c
        else:
            block = gather_rows(field.evecs, verts, nodes, torch.float32)
        u = block.shape[0]
        return compiled.array(block.reshape(u * 12, -1)), np.arange(u * 12, dtype=np.int64).reshape(u, 12)  # fmt: skip
    evecs = field_evecs32(field)
    g, k = evecs.shape[1], evecs.shape[2]
    ridx = (verts[:, :, None] * g + nodes[:, None, :]).reshape(-1, 12)
    return evecs.reshape(-1, k), compiled.array(ridx)


class KernelTerms(torch.autograd.Function):
    """``(coef (N, K), norm (N,))`` from centre barycentrics and bilinear weights; see the
    module doc. ``table``/``ridx`` (:func:`row_table`) and ``nodes`` (N, 4) are constants."""

    @staticmethod
    def forward(ctx, table, ridx, field, nodes, bary, weights, t):  # type: ignore[override]
        forward, _ = _kernels()
        evals = compiled.array(field.evals.to(torch.float32))
        n, k = ridx.shape[0], table.shape[1]
        coef = np.empty((n, k), np.float32)
        phi = np.empty((n, k), np.float32)
        decay = np.empty((n, k), np.float32)
        norm = np.empty(n, np.float32)
        args = [ridx] + [compiled.array(x) for x in (nodes, bary.to(torch.float32), weights.to(torch.float32))]  # fmt: skip

        def run(sl: slice) -> None:
            forward(table, *(a[sl] for a in args[:1]), evals, *(a[sl] for a in args[1:]), np.float32(t), coef[sl], phi[sl], decay[sl], norm[sl])  # fmt: skip

        compiled.run_threaded(run, n, THREAD_MIN_KERNELS)
        coef_t = torch.from_numpy(coef)
        ctx.table, ctx.ridx, ctx.evals, ctx.t = table, ridx, evals, t
        ctx.save_for_backward(nodes, bary, weights, coef_t, torch.from_numpy(phi), torch.from_numpy(decay))  # fmt: skip
        return coef_t, torch.from_numpy(norm)

    @staticmethod
    def backward(ctx, g_coef, g_norm):  # type: ignore[override]
        _, backward = _kernels()
        nodes, bary, weights, coef, phi, decay = ctx.saved_tensors
        n = nodes.shape[0]
        if g_coef is None:
            g_coef = torch.zeros_like(coef)
        if g_norm is None:
            g_norm = torch.zeros(n, dtype=coef.dtype)
        g_bary = np.empty((n, 3), np.float32)
        g_w = np.empty((n, 4), np.float32)
        args = [compiled.array(x.to(torch.float32) if x.is_floating_point() else x) for x in (nodes, bary, weights, coef, phi, decay, g_coef, g_norm)]  # fmt: skip
        table, ridx = ctx.table, ctx.ridx

        def run(sl: slice) -> None:
            backward(table, ridx[sl], ctx.evals, *(a[sl] for a in args[:3]), np.float32(ctx.t), *(a[sl] for a in args[3:]), g_bary[sl], g_w[sl])  # fmt: skip

        compiled.run_threaded(run, n, THREAD_MIN_KERNELS)
        gb = torch.from_numpy(g_bary).to(bary.dtype)
        gw = torch.from_numpy(g_w).to(weights.dtype)
        return None, None, None, None, gb, gw, None
