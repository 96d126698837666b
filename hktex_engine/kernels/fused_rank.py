"""The no-grad half of a training step, compiled: exact ``K_s`` nearest centres and ranking.

A training step evaluates ``K_s`` candidates per point but differentiates only the ``K_c``
that reach the blend. Through torch the no-grad half was most of the step (docs/kernels.md,
"The compiled training step"): a faiss search with an index rebuilt every step (the centres
move), the exact cut over a ``(P, K_s + margin, D)`` difference block, and a node matmul
that computes every candidate's response on all ``G`` grid nodes where it needs 4. Here each
point is one compiled loop (numba, ``nogil``; threads split the points):

- :func:`nearest`: the exact ``K_s`` nearest centres under the tie rule (distance, then
  kernel id), by a scan of :class:`Clusters` in order of a triangle-inequality bound that
  stops when no unscanned cluster can hold a nearer centre or a tie. Distances are computed
  directly per pair (a function of the pair alone, so the cut does not depend on the rest
  of the batch), the ``K_s`` best kept in a heap ordered by the rule. On surface embeddings
  a point scans ~2 sqrt(N) bounds and a few clusters' members instead of N centres.
- :func:`rank_pairs`: ``h_j(y)`` of the cut from the point's eigenfunctions on the grid
  nodes, ``r``, the soft step, the ``K_c`` choice under the tie rule, and what the chosen
  pairs' backward needs (``dots`` and ``blend``, as ``model._rank_pairs`` returns them).

Same mathematics and rule as the torch path; sums run in another order, so values agree to
float32 round-off and the choices are the same wherever no two keys sit within it (exact
ties, e.g. clones, are broken by the rule as there). CPU float32 only.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hktex_engine.kernels import compiled

#: Relative margin on the ``K_s``-th squared distance before a cluster is skipped: far above
#: the float64 round-off of the bounds and the float32 rounding of the distances (6e-8).
BOUND_MARGIN = 1e-6
#: Centres per block when assigning them to clusters (bounds the block to 8192 x clusters).
ASSIGN_ROWS = 8192
#: Points per thread below which one thread does the call.
THREAD_MIN_POINTS = 256


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the compiled training path can answer on ``device`` in ``dtype``."""
    return compiled.available(device, dtype)


def _exact_d2(emb_y, p, emb_c, j):
    """``|c_j - y_p|^2`` summed in float64 (SIMD lanes, the same order for every call: a
    function of the pair alone), as float32."""
    acc = 0.0
    for d in range(emb_c.shape[1]):
        diff = np.float64(emb_c[j, d]) - np.float64(emb_y[p, d])
        acc += diff * diff
    return np.float32(acc)


def _sort_by_rule(ids, d2, n):
    """Sort ``ids[:n]``/``d2[:n]`` in place by distance, then id (insertion sort: n ~ 100)."""
    for a in range(1, n):
        i, v = ids[a], d2[a]
        b = a - 1
        while b >= 0 and (d2[b] > v or (d2[b] == v and ids[b] > i)):
            ids[b + 1] = ids[b]
            d2[b + 1] = d2[b]
            b -= 1
        ids[b + 1] = i
        d2[b + 1] = v


def _worse(d_a, i_a, d_b, i_b):
    """Whether entry a ranks after entry b under the rule (distance, then id)."""
    return d_a > d_b or (d_a == d_b and i_a > i_b)


def _heap_offer(hd, hi, size, k, d, i):
    """Offer ``(d, i)`` to a max-heap (worst at the root) of the ``k`` best; returns its size."""
    if size == k:
        if not _worse(hd[0], hi[0], d, i):
            return size
        pos = 0  # replace the root, then sift down
        while True:
            child = 2 * pos + 1
            if child >= k:
                break
            if child + 1 < k and _worse(hd[child + 1], hi[child + 1], hd[child], hi[child]):
                child += 1
            if not _worse(hd[child], hi[child], d, i):
                break
            hd[pos], hi[pos] = hd[child], hi[child]
            pos = child
        hd[pos], hi[pos] = d, i
        return size
    pos = size  # append, then sift up
    while pos > 0:
        parent = (pos - 1) // 2
        if not _worse(d, i, hd[parent], hi[parent]):
            break
        hd[pos], hi[pos] = hd[parent], hi[parent]
        pos = parent
    hd[pos], hi[pos] = d, i
    return size + 1


def _nearest_clustered(emb_y, emb_c, order, starts, centroid, radius, k, out_id, out_d2):
    """Per point: the exact ``k`` nearest centres, scanning clusters nearest bound first.

    A cluster's members are at least ``max(0, |y - mu| - R)`` from the point (triangle
    inequality); once ``k`` distances are known, every cluster whose bound is above the
    ``k``-th (by a relative margin far above the bound's round-off) holds no nearer centre
    and no tie, so the scan stops there. The ``k`` best so far sit in a heap ordered by the
    rule, so the ``k``-th is always at hand."""
    n_cl, dim = centroid.shape[0], emb_c.shape[1]
    bound = np.empty(n_cl, np.float64)
    hd = np.empty(k, np.float32)
    hi = np.empty(k, np.int64)
    for p in range(emb_y.shape[0]):
        for c in range(n_cl):
            acc = 0.0
            for d in range(dim):
                diff = centroid[c, d] - np.float64(emb_y[p, d])
                acc += diff * diff
            gap = math.sqrt(acc) - radius[c]
            bound[c] = gap * gap if gap > 0.0 else 0.0
        size = 0
        for _ in range(n_cl):
            c = 0  # the nearest cluster not yet scanned (a few are; a full sort costs more)
            for a in range(1, n_cl):
                if bound[a] < bound[c]:
                    c = a
            if size == k and bound[c] > np.float64(hd[0]) * (1.0 + BOUND_MARGIN):
                break
            bound[c] = np.inf
            for i in range(starts[c], starts[c + 1]):  # members' rows are contiguous
                size = _heap_offer(hd, hi, size, k, _exact_d2(emb_y, p, emb_c, i), order[i])
        _sort_by_rule(hi, hd, k)
        for i in range(k):
            out_id[p, i] = hi[i]
            out_d2[p, i] = hd[i]


def _half_row(src, bits, vals):
    """``vals = float32(src)`` for one row of float16 bit patterns, exactly (numba has no
    float16; written by hand because no library converts inside a compiled loop). The
    exponent is rebased from 15 to 127 with integer operations; subnormal halves are
    renormalised by one exact float subtraction of ``2^-14`` (no float32 subnormal ever
    enters an arithmetic operation, which costs microcode assists on some CPUs); infinities
    and NaNs keep an all-ones exponent. ``vals`` is ``bits`` viewed as float32. Tested on
    all 65,536 patterns."""
    for q in range(src.shape[0]):
        u = (np.int64(src[q]) & 0x7FFF) << 13
        e = u & 0x0F800000
        u += 0x38000000
        if e == 0x0F800000:
            u += 0x38000000
        if e == 0:
            u += 0x00800000
        bits[q] = u
    for q in range(src.shape[0]):
        h = np.int64(src[q])
        sub = np.float32(6.103515625e-05) if (h & 0x7C00) == 0 else np.float32(0.0)
        sign = np.float32(-1.0) if (h & 0x8000) != 0 else np.float32(1.0)
        vals[q] = (vals[q] - sub) * sign


def _half_to_float32(src, out):
    """:func:`_half_row` over the rows of a 2-D array (the tests' check of the conversion)."""
    bits = np.empty(src.shape[1], np.int32)
    vals = bits.view(np.float32)
    for r in range(src.shape[0]):
        _half_row(src[r], bits, vals)
        for q in range(src.shape[1]):
            out[r, q] = vals[q]


def _rank_points(
    verts, bary, local, d2, evecs, half, coef, norm, nodes, weights, thr, sharp, low, high,
    scale, k_c, keep, out_top, out_dots, out_blend, out_rho,
):  # fmt: skip
    """Per point: responses of its candidates, the ``k_c`` best by the rule, and for those
    ``dots`` (coef . Phi_y[node]) and ``blend`` (sum_c w_c Phi_y[node_c]). The grid is
    ``evecs`` (float32), or ``half`` (float16 bit patterns, read in place) when ``evecs``
    has no rows."""
    use_half = evecs.shape[0] == 0
    n_nodes, k = (half.shape[1], half.shape[2]) if use_half else (evecs.shape[1], evecs.shape[2])
    c_count = local.shape[1]
    phi = np.empty((n_nodes, k), np.float32)
    bits = np.empty((3, k), np.int32)
    rows = bits.view(np.float32)
    dots = np.empty((c_count, 4), np.float32)
    rho = np.empty(c_count, np.float32)
    top = np.empty(k_c, np.int64)
    one = np.float32(1.0)
    for p in range(local.shape[0]):
        v0, v1, v2 = verts[p, 0], verts[p, 1], verts[p, 2]
        b0, b1, b2 = bary[p, 0], bary[p, 1], bary[p, 2]
        # the point's eigenfunctions on every node: three contiguous (G, K) vertex blocks,
        # read in order (a candidate-driven order of nodes measured slower: cache misses)
        for g in range(n_nodes):
            if use_half:
                _half_row(half[v0, g], bits[0], rows[0])
                _half_row(half[v1, g], bits[1], rows[1])
                _half_row(half[v2, g], bits[2], rows[2])
                for q in range(k):
                    phi[g, q] = b0 * rows[0, q] + b1 * rows[1, q] + b2 * rows[2, q]
            else:
                for q in range(k):
                    phi[g, q] = b0 * evecs[v0, g, q] + b1 * evecs[v1, g, q] + b2 * evecs[v2, g, q]
        for i in range(c_count):
            j = local[p, i]
            h = np.float32(0.0)
            for c in range(4):
                g = nodes[j, c]
                acc = np.float32(0.0)
                for q in range(k):
                    acc += coef[j, q] * phi[g, q]
                dots[i, c] = acc
                h += acc * weights[j, c]
            w = np.float32(math.exp(np.float32(-d2[p, i] / scale[j])))
            x = h * w / norm[j]
            s = one / (one + np.float32(math.exp(-(sharp[j] * (x - thr[j])))))
            rho[i] = _unit((s - low[j]) / (high[j] - low[j]))
        # K_c choice by the rule; candidates come nearest first (distance, then id)
        _choose(rho, d2[p], c_count, k_c, top)
        for t in range(k_c):
            i = top[t]
            j = local[p, i]
            out_top[p, t] = j
            out_rho[p, t] = rho[i]
            if not keep:
                continue
            for c in range(4):
                out_dots[p, t, c] = dots[i, c]
            g0, g1, g2, g3 = nodes[j, 0], nodes[j, 1], nodes[j, 2], nodes[j, 3]
            w0, w1, w2, w3 = weights[j, 0], weights[j, 1], weights[j, 2], weights[j, 3]
            for q in range(k):  # the four node rows in SIMD lanes along q
                out_blend[p, t, q] = w0 * phi[g0, q] + w1 * phi[g1, q] + w2 * phi[g2, q] + w3 * phi[g3, q]  # fmt: skip


_NEAREST = None
_RANK = None
_GROUP = None
_HALF = None
_unit = compiled.unit
_choose = compiled.choose_by_rule


def _kernels():
    """The compiled loops (built on first use, then loaded from numba's disk cache)."""
    global _NEAREST, _RANK, _unit, _exact_d2, _sort_by_rule, _worse, _heap_offer
    global _choose, _GROUP, _half_row, _HALF
    if _RANK is None:
        _GROUP = compiled.jit(_group)
        _half_row = compiled.jit(_half_row, inline=True)
        _HALF = compiled.jit(_half_to_float32)
        _unit, _, _choose, _ = compiled.helpers()
        _worse = compiled.jit(_worse, inline=True)
        _heap_offer = compiled.jit(_heap_offer, inline=True)
        _exact_d2 = compiled.jit(_exact_d2, inline=True, fastmath=compiled.SIMD_SUMS)
        _sort_by_rule = compiled.jit(_sort_by_rule)
        _NEAREST = compiled.jit(_nearest_clustered, fastmath=compiled.SIMD_SUMS)
        _RANK = compiled.jit(_rank_points, fastmath=compiled.SIMD_SUMS)
    return _NEAREST, _RANK


def _group(emb, labels, n_cl, order, starts, centroid, radius, emb_sorted):
    """Centres grouped by ``labels``: a counting sort (``order``, ``starts``), the rows in
    that order, and each cluster's centroid and radius in float64."""
    n, dim = emb.shape
    counts = np.zeros(n_cl + 1, np.int64)
    for j in range(n):
        counts[labels[j] + 1] += 1
    for c in range(n_cl):
        counts[c + 1] += counts[c]
    starts[:] = counts
    fill = counts[:n_cl].copy()
    for j in range(n):
        c = labels[j]
        order[fill[c]] = j
        fill[c] += 1
    centroid[:] = 0.0
    for i in range(n):
        j = order[i]
        emb_sorted[i] = emb[j]
    for c in range(n_cl):
        size = starts[c + 1] - starts[c]
        if size == 0:
            radius[c] = 0.0
            continue
        for i in range(starts[c], starts[c + 1]):
            for d in range(dim):
                centroid[c, d] += emb_sorted[i, d]
        for d in range(dim):
            centroid[c, d] /= size
        far = 0.0
        for i in range(starts[c], starts[c + 1]):
            acc = 0.0
            for d in range(dim):
                diff = np.float64(emb_sorted[i, d]) - centroid[c, d]
                acc += diff * diff
            far = max(far, acc)
        radius[c] = math.sqrt(far)


class Clusters:
    """Centre embeddings grouped for :func:`nearest`: ``ceil(2 sqrt(N))`` clusters around
    centres drawn with a fixed seed, each centre in its nearest one, with the clusters'
    centroids and radii (float64). Any grouping gives exact answers; a good one only makes
    the scan shorter (per point ~2 sqrt(N) bounds plus a few clusters' members, against N
    distances for a flat search). ``labels``: keep an earlier grouping of the same centres
    (training: the centres move a little each step; centroids and radii are recomputed, the
    assignment is not)."""

    def __init__(self, emb_c: torch.Tensor, labels: np.ndarray | None = None) -> None:
        c = emb_c.detach().to(torch.float32).contiguous()
        n, dim = c.shape
        if labels is None or labels.shape[0] != n:
            labels = _assign(c)
        n_cl = int(labels.max()) + 1
        self.labels = labels
        self.order = np.empty(n, np.int64)
        self.starts = np.empty(n_cl + 1, np.int64)
        self.centroid = np.empty((n_cl, dim), np.float64)
        self.radius = np.empty(n_cl, np.float64)
        self.emb = np.empty((n, dim), np.float32)  # rows by cluster: a scan reads them in turn
        _kernels()
        _GROUP(c.numpy(), labels, n_cl, self.order, self.starts, self.centroid, self.radius, self.emb)  # fmt: skip


def _assign(c: torch.Tensor) -> np.ndarray:
    """Each centre's nearest of ``ceil(2 sqrt(N))`` seeds (fixed seed), by BLAS blocks."""
    n = c.shape[0]
    n_cl = max(1, min(n, math.ceil(2.0 * math.sqrt(n))))
    seeds = torch.from_numpy(np.random.default_rng(0).choice(n, n_cl, replace=False))
    s = c[seeds]
    ssq = (s * s).sum(dim=1)
    labels = torch.empty(n, dtype=torch.long)
    for start in range(0, n, ASSIGN_ROWS):
        block = torch.addmm(ssq[None, :], c[start : start + ASSIGN_ROWS], s.T, alpha=-2.0)
        labels[start : start + ASSIGN_ROWS] = block.argmin(dim=1)
    return labels.numpy()


def nearest(
    emb_y: torch.Tensor, emb_c: torch.Tensor | Clusters, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact ``k`` nearest centres of each point under the tie rule: ``(ids (P, k),
    d2 (P, k))``, nearest first (``model._exact_cut``'s contract, without an index).
    ``emb_c``: the centre embeddings, or their :class:`Clusters` when the caller keeps them."""
    kernel, _ = _kernels()
    cl = emb_c if isinstance(emb_c, Clusters) else Clusters(emb_c)
    y = compiled.array(emb_y.to(torch.float32))
    p = y.shape[0]
    k = min(int(k), cl.emb.shape[0])
    out_id = np.empty((p, k), np.int64)
    out_d2 = np.empty((p, k), np.float32)

    def run(sl: slice) -> None:
        kernel(y[sl], cl.emb, cl.order, cl.starts, cl.centroid, cl.radius, k, out_id[sl], out_d2[sl])  # fmt: skip

    compiled.run_threaded(run, p, THREAD_MIN_POINTS)
    return torch.from_numpy(out_id), torch.from_numpy(out_d2)


def rank_pairs(
    field,
    face_ids: torch.Tensor,
    bary: torch.Tensor,
    local: torch.Tensor,
    d2: torch.Tensor,
    threshold: torch.Tensor,
    sharpness: torch.Tensor,
    coef: torch.Tensor,
    norm: torch.Tensor,
    nodes: torch.Tensor,
    weights: torch.Tensor,
    sigma_b: float,
    k_c: int,
    keep: bool = True,
    ratio: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``model._rank_pairs``' results (``top`` (P, k_c) rows of the per-kernel terms, ``dots``
    (P, k_c, 4), ``blend`` (P, k_c, K)) and the chosen ``rho`` (P, k_c), in rule order.

    ``local`` (P, C): each point's candidates as rows of the terms, nearest first (distance,
    then kernel id); ``d2`` their squared embedding distances. ``keep=False``: no ``dots``
    and ``blend`` (empty; a no-grad blend needs only ``top`` and ``rho``). ``ratio``: each
    row's ``sigma_j / sigma_b`` (a per-kernel-sigma set), else ``sigma_b`` for all."""
    _, kernel = _kernels()
    evecs, half = ranking_grid(field, keep)
    verts = field.faces[face_ids].numpy()
    low = torch.sigmoid(-sharpness * threshold)  # soft_step's own expressions (same bits)
    high = torch.sigmoid(sharpness * (1 - threshold))
    attrs = [
        compiled.array(t) for t in (coef, norm, nodes, weights, threshold, sharpness, low, high)
    ]
    b = compiled.array(bary.to(torch.float32))
    loc = compiled.array(local)
    dd = compiled.array(d2.to(torch.float32))
    p, kk = loc.shape[0], evecs.shape[2]  # ranking_grid gives both the same (G, K)
    k_c = min(int(k_c), loc.shape[1])
    top = np.empty((p, k_c), np.int64)
    dots = np.empty((p, k_c, 4) if keep else (p, 0, 4), np.float32)
    blend = np.empty((p, k_c, kk) if keep else (p, 0, kk), np.float32)
    rho = np.empty((p, k_c), np.float32)
    scale = compiled.row_scales(sigma_b, ratio, norm.shape[0])

    def run(sl: slice) -> None:
        kernel(verts[sl], b[sl], loc[sl], dd[sl], evecs, half, *attrs, scale, k_c, keep, top[sl], dots[sl], blend[sl], rho[sl])  # fmt: skip

    compiled.run_threaded(run, p, THREAD_MIN_POINTS)
    return (torch.from_numpy(top), torch.from_numpy(dots), torch.from_numpy(blend), torch.from_numpy(rho))  # fmt: skip


#: Largest float32 copy of a float16 eigenvector grid the training path makes (bytes);
#: above it training reads the float16 grid in place, as sparse queries do (the same values:
#: the conversion is exact), so a large mesh trains compiled without a multi-GB copy.
EVECS32_MAX_BYTES = 2 * 2**30


def field_evecs32(field) -> np.ndarray:
    """The field's eigenvector grid as a float32 array (numba has no float16): the grid
    itself when it is float32, else a copy made once per field."""
    cached = getattr(field, "_evecs32", None)
    if cached is None:
        e = field.evecs
        cached = compiled.array(e) if e.dtype == torch.float32 else e.to(torch.float32).numpy()
        field._evecs32 = cached
    return cached


def has_float32(field) -> bool:
    """Whether the field's grid is float32 already, or its copy was made (by training)."""
    return field.evecs.dtype == torch.float32 or getattr(field, "_evecs32", None) is not None


def ranking_grid(field, keep: bool) -> tuple[np.ndarray, np.ndarray]:
    """The grid :func:`rank_pairs` reads: ``(float32 grid, empty)``, or ``(empty, float16
    bit patterns)`` for a no-grad ranking (``keep=False``) of a float16 grid with no float32
    copy. So sparse no-grad queries run compiled on a float16 grid read in place: a query
    service holding grids memory-mapped (shared between workers) makes no private copy, and
    a one-off ``hktex query`` pays no conversion of the whole grid. Training (``keep``) makes
    the copy once per field (:func:`field_evecs32`) where it :func:`fits`: its steps read
    each point's rows again; a larger grid is read in place by training too."""
    e = field.evecs
    if has_float32(field) or e.dtype != torch.float16 or (keep and fits(field)):
        evecs = field_evecs32(field)
        return evecs, np.empty((0, *evecs.shape[1:]), np.uint16)
    half = compiled.array(e).view(np.uint16)
    return np.empty((0, *half.shape[1:]), np.float32), half


def can_rank(field) -> bool:
    """Whether no-grad ranking can run compiled on this field's grid without a private copy
    above :data:`EVECS32_MAX_BYTES` (a float16 grid is read in place)."""
    return has_float32(field) or field.evecs.dtype == torch.float16 or fits(field)


def half_to_float32(bits: np.ndarray) -> np.ndarray:
    """float16 bit patterns (2-D uint16) as float32, by the compiled conversion the ranking
    uses (for tests)."""
    _kernels()
    out = np.empty(bits.shape, np.float32)
    _HALF(np.ascontiguousarray(bits, dtype=np.uint16), out)
    return out


def fits(field) -> bool:
    """Whether the field's grid can take the compiled training path (its float32 size)."""
    e = field.evecs
    return e.dtype == torch.float32 or e.numel() * 4 <= EVECS32_MAX_BYTES
