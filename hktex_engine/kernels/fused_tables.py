"""The candidate tables' per-vertex responses and per-face lists, compiled (CPU float32).

Why hand-written: ``kernels.tables`` builds both with torch on any device. On the CPU its
vertex responses run as patch-batched matmuls over the *union* of a patch's lists (about
``4 |union| / L`` products per pair instead of 4), and the face lists as a dozen full passes
over ``(faces, L)`` arrays (``searchsorted``, gathers, a ``topk``, a compaction); together
~0.9 s of a one-off ``hktex query`` at 8,192 vertices and 10,000 kernels, more than the
evaluation of a million points. Here each vertex (each face) is one pass of a compiled loop:
exactly the four ``K``-long dot products a (vertex, candidate) pair needs, the vertex's
float16 rows converted once in the loop (``fused_rank``'s exact conversion, no copy of the
grid), and a face's list as a merge of its three sorted vertex lists. No library fuses a
sorted-list intersection with a selection under a bound, hence the loop.

Same mathematics as the torch functions: a pair's response sums its four corners in corner
order (the torch path adds them in that order too), so equal kernels (clones) get equal bits;
the dot products run in another order (float32 round-off, ~1e-7 relative). A face's list
holds the same candidates, its per-corner values copied bit for bit from the vertex tables.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hktex_engine.kernels import compiled, fused_rank

#: A face takes the triangle bound only when its embedded triangle is this well shaped
#: (Gram determinant over the squared sum of two edges' squares, ~1 / its condition number):
#: a sliver's nearest point is ill-conditioned, and the bound must never undercut.
WELL_SHAPED = 1e-6
#: Vertices (faces) per thread below which one thread does the call.
THREAD_MIN_ROWS = 256
# Output arrays are filled with their padding by numpy before the threads write into them:
# fresh pages first touched by two threads' interleaved row writes cost up to ~6x more than
# numpy's sequential fill (face lists of a 16,384-face torus, 148 MB: 0.16 s against 0.01 s
# plus 0.026 s, on this project's VMs), and the loops then write only what they find.

#: Slots per vertex list on the first try, per ``K_s`` (measured lists: ~3.7 K_s on average,
#: 6 K_s at most on a 10,000-kernel torus); longer lists are gathered again at their length.
LIST_SLOTS_PER_KS = 8


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the compiled table builders can answer on ``device`` for terms in ``dtype``."""
    return compiled.available(device, dtype)


def _vertex_responses(verts, kid, evecs, half, coef, nodes, weights, n_k, out):
    """``out[r, i] = H_j(v)`` for ``v = verts[r]`` and its candidates ``j = kid[r, i]``
    (ascending, padding at the end: ``out`` holds 0 there already):
    ``sum_c w_jc coef_j . phi(v)[node_jc]``, corners in order. The grid is ``evecs``
    (float32), or ``half`` (float16 bit patterns read in place) when ``evecs`` has no rows."""
    use_half = evecs.shape[0] == 0
    n_nodes, k = (half.shape[1], half.shape[2]) if use_half else (evecs.shape[1], evecs.shape[2])
    phi = np.empty((n_nodes, k), np.float32)
    bits = np.empty(k, np.int32)
    vals = bits.view(np.float32)
    for r in range(verts.shape[0]):
        v = verts[r]
        for g in range(n_nodes):
            if use_half:
                _half_row(half[v, g], bits, vals)
                for q in range(k):
                    phi[g, q] = vals[q]
            else:
                for q in range(k):
                    phi[g, q] = evecs[v, g, q]
        for i in range(kid.shape[1]):
            j = kid[r, i]
            if j >= n_k:
                break
            h = np.float32(0.0)
            for c in range(4):
                g = nodes[j, c]
                acc = np.float32(0.0)
                for q in range(k):
                    acc += coef[j, q] * phi[g, q]
                h += acc * weights[j, c]
            out[r, i] = h


def _pair_d2(emb_y, p, emb_c, i):
    """``|c_i - y_p|^2`` in float64 (the float32 embeddings' exact differences; SIMD lanes,
    the same order for every pair, so equal centres get equal bits)."""
    acc = 0.0
    for d in range(emb_c.shape[1]):
        diff = np.float64(emb_c[i, d]) - np.float64(emb_y[p, d])
        acc += diff * diff
    return acc


def _within(emb_y, emb_c, order, starts, centroid, radius, r2, n_k, count, out_id, out_d2):
    """Per point ``p``: every centre within squared distance ``r2[p]``, in kernel order, into
    ``out_id[p]`` and ``out_d2[p]`` (whose padding, ``n_k`` and ``inf``, the caller wrote);
    ``count[p]`` their number (a row of more than the output's width is counted, not
    written). Clusters
    (``fused_rank.Clusters``) whose members are all farther (triangle inequality, with a
    margin far above the bound's round-off) are skipped."""
    n_cl = centroid.shape[0]
    dim = emb_c.shape[1]
    cap = out_id.shape[1]
    found_id = np.empty(emb_c.shape[0], np.int64)
    found_d2 = np.empty(emb_c.shape[0], np.float64)
    for p in range(emb_y.shape[0]):
        limit = r2[p]
        n = 0
        for c in range(n_cl):
            acc = 0.0
            for d in range(dim):
                diff = centroid[c, d] - np.float64(emb_y[p, d])
                acc += diff * diff
            gap = math.sqrt(acc) - radius[c]
            if gap > 0.0 and gap * gap > limit * (1.0 + fused_rank.BOUND_MARGIN):
                continue
            for i in range(starts[c], starts[c + 1]):
                d2 = _pair_d2(emb_y, p, emb_c, i)
                if d2 <= limit:
                    found_id[n] = order[i]
                    found_d2[n] = d2
                    n += 1
        count[p] = n
        if n > cap:
            continue
        by_id = np.argsort(found_id[:n])
        for t in range(n):
            out_id[p, t] = found_id[by_id[t]]
            out_d2[p, t] = found_d2[by_id[t]]


def _segment_d2(da, db, eab):
    """min over u in [0, 1] of |a + u (b - a) - c|^2 from |a - c|^2, |b - c|^2 and
    |a - b|^2 (``tables.triangle_d2``'s edges; a zero-length edge is its end)."""
    if not eab > 0.0:
        return da
    proj = 0.5 * (da + eab - db)  # (b - a) . (c - a)
    u = min(max(proj / eab, 0.0), 1.0)
    return da - 2.0 * u * proj + u * u * eab


def _triangle_d2(d0, d1, d2, e01, e02, e12):
    """``tables.triangle_d2`` for one (face, candidate) pair."""
    aw = 0.5 * (d0 + e01 - d1)
    bw = 0.5 * (d0 + e02 - d2)
    ab = 0.5 * (e01 + e02 - e12)
    det = e01 * e02 - ab * ab
    best = min(_segment_d2(d0, d1, e01), _segment_d2(d0, d2, e02), _segment_d2(d1, d2, e12))
    if det > 0.0:
        s = (aw * e02 - bw * ab) / det
        t = (bw * e01 - aw * ab) / det
        if s >= 0.0 and t >= 0.0 and s + t <= 1.0:
            inner = d0 - 2.0 * s * aw - 2.0 * t * bw + s * s * e01 + 2.0 * s * t * ab + t * t * e02
            best = min(best, inner)
    return max(best, 0.0)


def _face_lists(
    tri, rows, vkid, vh, vd2, emb, n_k, k_s, slack, fill,
    count, kid, h, d2, edge2,
):  # fmt: skip
    """For each face: its candidates (in all three vertex lists, and within the face's own
    bound, as ``tables.face_tables`` states it), in kernel order. ``fill=False`` counts them
    into ``count``; ``fill=True`` also writes them (into ``kid``, ``h``, ``d2`` of width at
    least the largest count, whose padding, ``n_k``, 0 and 0, the caller wrote) and
    ``edge2``."""
    width = vkid.shape[1]
    dim = emb.shape[1]
    pos = np.empty((width, 3), np.int64)
    dc2 = np.empty(width, np.float64)
    far2 = np.empty(width, np.float64)
    buf = np.empty(2 * width, np.float64)
    centroid = np.empty(dim, np.float64)
    k = k_s if k_s < width else width
    for f in range(tri.shape[0]):
        r0, r1, r2 = rows[f, 0], rows[f, 1], rows[f, 2]
        # the three sorted lists merged: entries of the first found in the other two
        n = 0
        p1 = 0
        p2 = 0
        for i in range(width):
            j = vkid[r0, i]
            if j >= n_k:
                break
            while p1 < width and vkid[r1, p1] < j:
                p1 += 1
            while p2 < width and vkid[r2, p2] < j:
                p2 += 1
            if p1 == width or p2 == width:
                break
            if vkid[r1, p1] == j and vkid[r2, p2] == j:
                pos[n, 0] = i
                pos[n, 1] = p1
                pos[n, 2] = p2
                n += 1
        a, b, c = tri[f, 0], tri[f, 1], tri[f, 2]
        e01 = 0.0
        e02 = 0.0
        e12 = 0.0
        for d in range(dim):
            x0, x1, x2 = np.float64(emb[a, d]), np.float64(emb[b, d]), np.float64(emb[c, d])
            e01 += (x0 - x1) ** 2
            e02 += (x0 - x2) ** 2
            e12 += (x1 - x2) ** 2
            centroid[d] = (x0 + x1 + x2) / 3.0
        far = 0.0
        for corner in range(3):
            v = tri[f, corner]
            acc = 0.0
            for d in range(dim):
                acc += (np.float64(emb[v, d]) - centroid[d]) ** 2
            far = max(far, math.sqrt(acc))
        # the face's bound: its points' K_s nearest lie within D_f + 2 R_f of the centroid,
        # |c_f - c_j|^2 by the barycentric identity (tables.face_tables)
        quad = (e01 + e02 + e12) / 9.0
        for t in range(n):
            s = vd2[r0, pos[t, 0]] + vd2[r1, pos[t, 1]] + vd2[r2, pos[t, 2]]
            dc2[t] = s / 3.0 - quad
        bound = np.inf
        tight = np.inf
        if n >= k and k > 0:
            kth = max(_kth_smallest(dc2, n, k - 1, buf), 0.0)
            reach = math.sqrt(kth) + 2.0 * far
            bound = reach * reach * (1.0 + 1e-9) + slack
        half = 0.5 * (e01 + e02 - e12)
        if n >= k and k > 0 and e01 * e02 - half * half > WELL_SHAPED * (e01 + e02) ** 2:
            # the tighter bound (tables.face_tables): the K_s-th smallest farthest-corner
            # distance, against each candidate's distance to the triangle
            for t in range(n):
                far2[t] = max(vd2[r0, pos[t, 0]], vd2[r1, pos[t, 1]], vd2[r2, pos[t, 2]])
            tight = _kth_smallest(far2, n, k - 1, buf) * (1.0 + 1e-9) + slack
        m = 0
        for t in range(n):
            if not dc2[t] <= bound:
                continue
            i0, i1, i2 = pos[t, 0], pos[t, 1], pos[t, 2]
            if tight < np.inf:
                near = _triangle_d2(vd2[r0, i0], vd2[r1, i1], vd2[r2, i2], e01, e02, e12)
                if near > tight:  # NaN keeps the candidate
                    continue
            if fill:
                kid[f, m] = vkid[r0, i0]
                h[f, m, 0], h[f, m, 1], h[f, m, 2] = vh[r0, i0], vh[r1, i1], vh[r2, i2]
                d2[f, m, 0], d2[f, m, 1], d2[f, m, 2] = vd2[r0, i0], vd2[r1, i1], vd2[r2, i2]
            m += 1
        count[f] = m
        if fill:
            edge2[f, 0], edge2[f, 1], edge2[f, 2] = e01, e02, e12


_RESPONSES = None
_FACES = None
_WITHIN = None
_half_row = fused_rank._half_row
_kth_smallest = compiled.kth_smallest


def _kernels():
    """The compiled loops (built on first use, then loaded from numba's disk cache)."""
    global _RESPONSES, _FACES, _WITHIN, _half_row, _kth_smallest, _pair_d2
    global _segment_d2, _triangle_d2
    if _RESPONSES is None:
        fused_rank._kernels()  # compiles the float16 conversion, inlined here
        _half_row = fused_rank._half_row
        _, _kth_smallest, _, _ = compiled.helpers()
        _RESPONSES = compiled.jit(_vertex_responses, fastmath=compiled.SIMD_SUMS)
        _segment_d2 = compiled.jit(_segment_d2, inline=True)
        _triangle_d2 = compiled.jit(_triangle_d2, inline=True)
        _FACES = compiled.jit(_face_lists)
        _pair_d2 = compiled.jit(_pair_d2, inline=True, fastmath=compiled.SIMD_SUMS)
        _WITHIN = compiled.jit(_within, fastmath=compiled.SIMD_SUMS)
    return _RESPONSES, _FACES


def vertex_lists(
    points: torch.Tensor, centres: torch.Tensor, k_s: int, radius: torch.Tensor, slack: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(kid, d2)`` (V, L) of ``tables.build_tables``: for each point (a vertex's embedding)
    every centre within ``D_v + 2 R_v`` (``D_v``: its ``K_s``-th nearest centre's distance,
    exact by ``fused_rank.nearest``; ``R_v``: ``radius``), in kernel order, padded with the
    kernel count and ``inf``; ``d2`` their squared distances, float64. Two clustered scans
    per point (the ``K_s`` nearest, then the ball) instead of a distance row to every
    centre."""
    _kernels()
    n_k = int(centres.shape[0])
    y = compiled.array(points.to(torch.float32))
    clusters = fused_rank.Clusters(centres)
    _, near_d2 = fused_rank.nearest(points, clusters, k_s)
    # an upper bound of D_v^2: the float32 rounding of the K_s-th distance (6e-8) covered
    kth = torch.sqrt(near_d2[:, -1].to(torch.float64) * (1.0 + fused_rank.BOUND_MARGIN))
    reach = kth + 2.0 * radius.to(torch.float64)
    r2 = ((reach * reach + slack) * (1 + 1e-9)).numpy()
    v_n = y.shape[0]
    count = np.zeros(v_n, np.int64)
    cap = min(n_k, LIST_SLOTS_PER_KS * k_s)
    kid = np.full((v_n, cap), n_k, np.int64)  # the padding, written in order (see below)
    d2 = np.full((v_n, cap), np.inf)
    cl = (clusters.emb, clusters.order, clusters.starts, clusters.centroid, clusters.radius)

    def run(sl: slice) -> None:
        _WITHIN(y[sl], *cl, r2[sl], n_k, count[sl], kid[sl], d2[sl])

    compiled.run_threaded(run, v_n, THREAD_MIN_ROWS)
    width = int(count.max()) if v_n else 0
    if width > cap:  # the few longer lists, gathered again at their length
        long = np.flatnonzero(count > cap)
        kid = np.concatenate([kid, np.full((v_n, width - cap), n_k, np.int64)], axis=1)
        d2 = np.concatenate([d2, np.full((v_n, width - cap), np.inf)], axis=1)
        k2, d22 = kid[long], d2[long]
        _WITHIN(y[long], *cl, r2[long], n_k, count[long], k2, d22)
        kid[long], d2[long] = k2, d22
    return torch.from_numpy(kid[:, :width].copy()), torch.from_numpy(d2[:, :width].copy())


def vertex_responses(field, verts: torch.Tensor, kid: torch.Tensor, terms) -> torch.Tensor:
    """``H_j(v)`` (V, L) for the candidates ``kid`` (V, L) of the vertices ``verts``
    (``tables._vertex_responses``' contract), on the field's float16 grid in place or its
    float32 grid."""
    responses, _ = _kernels()
    coef, _, nodes, weights, _ = terms
    evecs, half = fused_rank.ranking_grid(field, keep=False)
    v = compiled.array(verts)
    ids = compiled.array(kid)
    args = [compiled.array(t) for t in (coef, nodes, weights)]
    out = np.full(ids.shape, 0.0, np.float32)
    n_k = int(coef.shape[0])

    def run(sl: slice) -> None:
        responses(v[sl], ids[sl], evecs, half, *args, n_k, out[sl])

    compiled.run_threaded(run, v.shape[0], THREAD_MIN_ROWS)
    return torch.from_numpy(out)


def face_lists(field, tables, faces: torch.Tensor, k_s: int, max_bytes: float = math.inf):
    """``(kid, h, d2, edge2, count)`` of the faces ``faces`` (``tables.FaceTables``' fields,
    rows compacted to the widest face's count), or None when they would take more than
    ``max_bytes``. Two passes: the counts (the width), then the lists."""
    _, lists = _kernels()
    tri = field.faces[faces]
    rows = compiled.array(tables.rows[tri])
    tri = compiled.array(tri)
    vt = [compiled.array(t) for t in (tables.kid, tables.h, tables.d2)]
    emb = compiled.array(field.embedding)
    # round-off allowance of the bound, over the whole mesh's embedding (torch's, per chunk
    # of faces, is never larger: a superset of its lists)
    slack = 1e-12 * (1.0 + float((field.embedding.to(torch.float64) ** 2).sum(dim=1).max()))
    n_f = tri.shape[0]
    count = np.zeros(n_f, np.int64)
    none2 = np.empty((0, 0), np.int64)
    none3 = np.empty((0, 0, 3), np.float32)
    none3d = np.empty((0, 0, 3), np.float64)
    no_edges = np.empty((0, 3), np.float64)
    n_k = int(tables.n_kernels)

    def counted(sl: slice) -> None:
        lists(tri[sl], rows[sl], *vt, emb, n_k, k_s, slack, False, count[sl], none2, none3, none3d, no_edges)  # fmt: skip

    compiled.run_threaded(counted, n_f, THREAD_MIN_ROWS)
    width = int(count.max()) if n_f else 0
    h_item = vt[1].dtype.itemsize
    if n_f * (width * (8 + 3 * h_item + 3 * 8) + 3 * 8 + 8) > max_bytes:
        return None
    kid = np.full((n_f, width), n_k, np.int64)  # the padding, written in order (see below)
    h = np.full((n_f, width, 3), 0.0, vt[1].dtype)
    d2 = np.full((n_f, width, 3), 0.0)
    edge2 = np.empty((n_f, 3), np.float64)

    def filled(sl: slice) -> None:
        lists(tri[sl], rows[sl], *vt, emb, n_k, k_s, slack, True, count[sl], kid[sl], h[sl], d2[sl], edge2[sl])  # fmt: skip

    compiled.run_threaded(filled, n_f, THREAD_MIN_ROWS)
    return tuple(torch.from_numpy(x) for x in (kid, h, d2, edge2, count))
