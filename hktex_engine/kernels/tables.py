"""Per-vertex candidate tables: dense queries without a per-point search (issue 10, item 1).

A query point ``y`` in face ``f`` has its embedding ``e(y) = sum_v b_v e(v)`` inside the
triangle of its three vertex embeddings, and its heat response is linear in the barycentrics,
``h_j(y) = sum_v b_v H_j(v)``. So the per-point work can be moved to the vertices:

1. **Candidate lists that provably contain every point's ``K_s`` nearest centres.** For a
   vertex ``v`` let ``R_v`` be the longest embedding edge at ``v`` (every point of a face at
   ``v`` lies within ``R_v`` of ``e(v)``: the face's embedded triangle is in the ball) and
   ``D_v`` the distance from ``e(v)`` to its ``K_s``-th nearest centre. For ``y`` in a face
   at ``v`` the ``K_s``-th nearest distance is at most ``D_v + R_v`` (those ``K_s`` centres
   are that close to ``y``), and any centre that near ``y`` is within ``D_v + 2 R_v`` of
   ``e(v)`` (triangle inequality). The list of ``v`` holds every centre within that radius
   (plus the index's round-off), sorted by kernel index; a face's list is the intersection of
   its three vertices' lists (``searchsorted``), still a superset of each of its points'
   ``K_s`` nearest, ties included. The exact cut by the tie rule then runs per point on it.
2. **Per (vertex, candidate) values, computed once**: ``H_j(v)`` (the kernel's response at the
   vertex: one dense ``bmm`` of the candidates' spectral coefficients against the vertex's
   (G, K) eigenvector block, then the kernel's four bilinear nodes) and the squared distance
   ``D_j(v) = |e(v) - e(c_j)|^2`` (float64, directly).
3. **Per point**, for each candidate of its face: ``h = sum_v b_v H_j(v)`` and, exactly,
   ``|e(y) - e(c_j)|^2 = sum_v b_v D_j(v) - sum_{u<v} b_u b_v |e(u) - e(v)|^2`` (the identity
   ``|sum_v b_v x_v|^2 = sum_v b_v |x_v|^2 - sum_{u<v} b_u b_v |x_u - x_v|^2`` for
   ``sum_v b_v = 1``, with ``x_v = e(v) - e(c_j)``; evaluated in float64, so no cancellation
   matters at these scales). Three multiply-adds each instead of ``G K``.

Everything is torch on the field's device; no Python loop over points, kernels or vertices
(only over bounded chunks).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from hktex_engine.kernels import fused_tables

if TYPE_CHECKING:
    from hktex_engine.kernels.knn import CandidateSearch

#: Bytes of one chunk of the (vertices x centres) distance matrix.
DISTANCE_CHUNK_BYTES = 64 * 2**20
#: Vertices per patch whose responses are computed by shared dense products.
PATCH = 32
#: Bytes of one chunk of gathered candidate coefficients when computing ``H``.
H_CHUNK_BYTES = 32 * 2**20


@dataclass
class VertexTables:
    """Candidate lists and per-(vertex, candidate) values for a set of vertices.

    ``rows`` (n,) maps a mesh vertex to its row (-1: not in the table); ``kid`` (V, L) the
    candidates, ascending, padded with ``n_kernels``; ``h`` (V, L) ``H_j(v)`` and ``d2``
    (V, L) float64 ``D_j(v)``.
    """

    rows: torch.Tensor
    kid: torch.Tensor
    h: torch.Tensor
    d2: torch.Tensor
    n_kernels: int

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.rows, self.kid, self.h, self.d2))

    def covers(self, verts: torch.Tensor) -> bool:
        return bool((self.rows[verts] >= 0).all())


def star_radius(field) -> torch.Tensor:
    """``R_v`` (n,) float64: the longest embedding edge at each vertex."""
    emb = field.embedding.to(torch.float64)
    f = field.faces
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    length = torch.linalg.norm(emb[edges[:, 0]] - emb[edges[:, 1]], dim=1)
    out = torch.zeros(emb.shape[0], dtype=torch.float64, device=emb.device)
    out.scatter_reduce_(0, edges[:, 0], length, reduce="amax")
    out.scatter_reduce_(0, edges[:, 1], length, reduce="amax")
    return out


def build_tables(
    field,
    verts: torch.Tensor,
    centres: torch.Tensor,
    terms: tuple[torch.Tensor, ...],
    k_s: int,
    radius: torch.Tensor,
    search: Callable[[], CandidateSearch] | None = None,
) -> VertexTables:
    """Tables for the unique vertices ``verts`` (sorted), from the model's per-kernel terms.

    ``D_v`` needs only an upper bound: the largest exact distance to any ``K_s`` centres. The
    compiled lists (CPU float32, ``kernels.fused_tables``) take the exact ``K_s`` nearest;
    the torch lists take those found by ``search()`` (it returns a
    :class:`~hktex_engine.kernels.knn.CandidateSearch`; approximate ranking is fine), or
    without one a ``topk`` over the distance rows.
    """
    n_k = centres.shape[0]
    dev = centres.device
    emb = field.embedding.to(torch.float64)
    c64 = centres.to(torch.float64)
    slack = 1e-12 * (float((c64 * c64).sum(dim=1).max()) + float((emb * emb).sum(dim=1).max()))
    if _compiled(field, terms[0]) and centres.dtype == torch.float32:
        kid, d2 = fused_tables.vertex_lists(field.embedding[verts], centres, k_s, radius[verts], slack)  # fmt: skip
    else:
        kid, d2 = _lists(emb, verts, c64, k_s, radius, slack, search)
    h = _vertex_responses(field, verts, kid, terms)
    rows = torch.full((field.n_vertices,), -1, dtype=torch.long, device=dev)
    rows[verts] = torch.arange(verts.shape[0], device=dev)
    return VertexTables(rows=rows, kid=kid, h=h, d2=d2, n_kernels=n_k)


def _lists(emb, verts, c64, k_s, radius, slack, search) -> tuple[torch.Tensor, torch.Tensor]:
    """The vertex lists of :func:`build_tables` by torch on any device: ``(kid, d2)``."""
    n_k = c64.shape[0]
    dev = c64.device
    # Distances: one float64 GEMM per chunk of vertices, |a|^2 + |c|^2 - 2 a.c (round-off
    # ~1e-16 of |a|^2 + |c|^2, covered by the slack), over the distinct centres only, so that
    # clones (equal centres) get bit-equal distances, as the tie rule needs (a GEMM's rounding
    # can differ between equal columns).
    uniq, inverse = torch.unique(c64, dim=0, return_inverse=True)  # (sorted rows)
    has_clones = uniq.shape[0] < n_k
    if not has_clones:
        uniq = c64
    u_sq = (uniq * uniq).sum(dim=1)
    per_row = max(1, DISTANCE_CHUNK_BYTES // max(1, n_k * 8))
    if search is not None:
        index = search()
        near = index.search(emb[verts].to(index.centres.dtype), k_s)  # (V, k_s)
        reach_v = torch.empty(verts.shape[0], dtype=torch.float64, device=dev)
        step = max(1, DISTANCE_CHUNK_BYTES // max(1, k_s * emb.shape[1] * 8))
        for start in range(0, verts.shape[0], step):
            sl = slice(start, start + step)
            diff = emb[verts[sl]][:, None, :] - c64[near[sl]]
            reach_v[sl] = torch.sqrt((diff * diff).sum(dim=2).max(dim=1).values)
    r_idx, c_idx, vals = [], [], []
    for start in range(0, verts.shape[0], per_row):
        v = verts[start : start + per_row]
        e = emb[v]
        d2 = torch.addmm(u_sq[None, :], e, uniq.T, beta=1.0, alpha=-2.0)
        d2 += (e * e).sum(dim=1)[:, None]
        if has_clones:
            d2 = d2[:, inverse]
        if search is not None:
            kth = reach_v[start : start + per_row]
        else:
            kth = torch.sqrt(torch.topk(d2, k_s, dim=1, largest=False).values[:, -1].clamp(min=0))
        reach = kth + 2.0 * radius[v]
        bound = (reach * reach + slack) * (1 + 1e-9)
        rr, cc = torch.nonzero(d2 <= bound[:, None], as_tuple=True)
        r_idx.append(rr + start)
        c_idx.append(cc)
        vals.append(d2[rr, cc].clamp(min=0.0))
    rr, cc = torch.cat(r_idx), torch.cat(c_idx)  # row-major: kernel ids ascending per row
    counts = torch.bincount(rr, minlength=verts.shape[0])
    width = int(counts.max()) if counts.numel() else 0
    offsets = torch.cumsum(counts, 0) - counts
    slot = torch.arange(rr.shape[0], device=dev) - offsets[rr]
    kid = torch.full((verts.shape[0], width), n_k, dtype=torch.long, device=dev)
    kid[rr, slot] = cc
    d2 = torch.full(kid.shape, float("inf"), dtype=torch.float64, device=dev)
    d2[rr, slot] = torch.cat(vals)
    return kid, d2


def _vertex_responses(field, verts, kid, terms) -> torch.Tensor:
    """``H_j(v)`` (V, L) for the candidates ``kid`` (V, L) of each vertex.

    Each (vertex, kernel) pair needs four K-long dot products (the kernel's bilinear nodes)
    out of the vertex's (G, K) block. To run them as dense products, vertices are grouped
    into spatial patches of :data:`PATCH` (Morton order of their positions); per patch and
    grid node ``g``, the patch's vertex rows at ``g`` (PATCH, K) multiply the coefficients of
    the patch's candidates that use node ``g`` (one batched matmul for all (patch, node)
    blocks of a chunk). Against one (L, K) x (K, G) product per vertex this does about
    ``4 |union| / L`` instead of ``G`` products per pair.
    """
    coef, _, nodes, weights, _ = terms
    if _compiled(field, coef):
        return fused_tables.vertex_responses(field, verts, kid, terms)
    v_n, width = kid.shape
    n_k, k = coef.shape
    g_n = field.n_nodes
    dev = coef.device
    out = torch.zeros((v_n, width), dtype=coef.dtype, device=dev)
    if width == 0 or v_n == 0:
        return out
    order = _morton_order(field.vertices[verts])
    n_p = (v_n + PATCH - 1) // PATCH
    patch_of = torch.empty(v_n, dtype=torch.long, device=dev)
    patch_of[order] = torch.arange(v_n, device=dev) // PATCH
    local_of = torch.empty(v_n, dtype=torch.long, device=dev)
    local_of[order] = torch.arange(v_n, device=dev) % PATCH
    valid = kid < n_k
    # union of the lists of each patch: sorted unique (patch, kernel) keys
    keys = (patch_of[:, None] * n_k + kid)[valid]
    ukeys, inverse = torch.unique(keys, return_inverse=True)
    up, uj = ukeys // n_k, ukeys % n_k  # union entries (U,)
    # (patch, node) groups: 4 corners per union entry
    corner_g = nodes[uj]  # (U, 4)
    gkey = (up[:, None] * g_n + corner_g).reshape(-1)  # (U * 4,)
    gsorted, gorder = torch.sort(gkey, stable=True)
    counts = torch.bincount(gsorted, minlength=n_p * g_n)
    starts = torch.cumsum(counts, 0) - counts
    slot_sorted = torch.arange(gsorted.shape[0], device=dev) - starts[gsorted]
    slot = torch.empty_like(slot_sorted)
    slot[gorder] = slot_sorted
    m_max = int(counts.max())
    # vertex rows of each patch: (n_p, PATCH) vertex ids, padded by repeating the first
    members = torch.full((n_p * PATCH,), -1, dtype=torch.long, device=dev)
    members[patch_of * PATCH + local_of] = verts
    members = members.view(n_p, PATCH)
    members = torch.where(members >= 0, members, members[:, :1])
    # values per union entry and patch vertex: (U, PATCH)
    values = torch.zeros((up.shape[0], PATCH), dtype=coef.dtype, device=dev)
    flat_slot = gsorted * m_max + slot_sorted  # row of each sorted (entry, corner) in a block
    ent_sorted = gorder // 4
    coef_sorted = uj[ent_sorted]
    w_sorted = weights[coef_sorted, gorder % 4]
    bounds = torch.searchsorted(gsorted, torch.arange(0, n_p + 1, device=dev) * g_n).tolist()
    per = max(1, H_CHUNK_BYTES // max(1, g_n * m_max * k * coef.element_size()))
    for p0 in range(0, n_p, per):
        p1 = min(n_p, p0 + per)
        a, b = bounds[p0], bounds[p1]
        if a == b:
            continue
        rows_in = flat_slot[a:b] - p0 * g_n * m_max
        # unused slots stay uninitialised: each product column reads only its own slot
        block = torch.empty(((p1 - p0) * g_n * m_max, k), dtype=coef.dtype, device=dev)
        block.index_copy_(0, rows_in, coef.index_select(0, coef_sorted[a:b]))
        rows = field.evecs.index_select(0, members[p0:p1].reshape(-1)).to(coef.dtype)
        rows = rows.view(p1 - p0, PATCH, g_n, k).transpose(1, 2).reshape(-1, PATCH, k)
        block = block.view(-1, m_max, k)
        dots = torch.bmm(block, rows.transpose(1, 2))  # ((p, g), m_max, PATCH)
        picked = dots.view(-1, PATCH).index_select(0, rows_in) * w_sorted[a:b, None]
        _add_corners(values, ent_sorted[a:b], gorder[a:b] % 4, picked)
    # back to the vertex tables: entry of (patch(v), kid) for each valid slot
    flat = torch.zeros(valid.shape, dtype=torch.long, device=dev)
    flat[valid] = inverse
    out = values.view(-1)[flat * PATCH + local_of[:, None]]
    return torch.where(valid, out, torch.zeros_like(out))


def _compiled(field, coef: torch.Tensor) -> bool:
    """Whether the compiled builders (``kernels.fused_tables``) answer: CPU float32 terms on
    a float32 or float16 grid."""
    grid = field.evecs.dtype in (torch.float32, torch.float16)
    return grid and fused_tables.available(coef.device, coef.dtype)


def _add_corners(
    values: torch.Tensor, entry: torch.Tensor, corner: torch.Tensor, terms: torch.Tensor
) -> None:
    """``values[entry] += terms``, summing each entry's four corner terms in corner order.

    One pass per corner, so no index repeats within a pass: CUDA's ``index_add_`` adds
    repeated indices by atomics in no fixed order, which gave clones (equal kernels) responses
    a bit apart and broke the tie rule's index order among them (tests/test_cuda.py, measured
    on an H200). The same order on every device, so clones stay bit-equal everywhere.
    """
    for c in range(4):
        mask = corner == c
        values.index_add_(0, entry[mask], terms[mask])


def _morton_order(points: torch.Tensor) -> torch.Tensor:
    """An ordering of 3-D points along a Z-order curve (10 bits per axis)."""
    lo = points.min(dim=0).values
    span = torch.clamp(points.max(dim=0).values - lo, min=1e-12)
    q = ((points - lo) / span * 1023).to(torch.long).clamp(0, 1023)
    code = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return torch.argsort(code)


@dataclass
class FaceTables:
    """The candidates of faces: intersection of their vertices' lists, values per corner."""

    rows: torch.Tensor  # (m,) face -> row, -1 absent
    kid: torch.Tensor  # (F, L), padded with n_kernels
    h: torch.Tensor  # (F, L, 3)
    d2: torch.Tensor  # (F, L, 3) float64, 0 on padding
    edge2: torch.Tensor  # (F, 3) float64: |e0 - e1|^2, |e0 - e2|^2, |e1 - e2|^2
    n_kernels: int
    count: torch.Tensor  # (F,) candidates per face (they come first in each row)


def _segment_d2(da: torch.Tensor, db: torch.Tensor, eab: torch.Tensor) -> torch.Tensor:
    """min over u in [0, 1] of |a + u (b - a) - c|^2 from |a - c|^2, |b - c|^2, |a - b|^2."""
    proj = 0.5 * (da + eab - db)
    u = torch.where(eab > 0, proj / eab.clamp(min=1e-300), torch.zeros_like(proj)).clamp(0, 1)
    return da - 2.0 * u * proj + u * u * eab


def triangle_d2(d2: torch.Tensor, edge2: torch.Tensor) -> torch.Tensor:
    """Squared distance from each candidate centre to its face's triangle, in the embedding.

    ``d2`` (F, L, 3): the candidate's squared distances to the three corners; ``edge2`` (F, 3):
    |e0 - e1|^2, |e0 - e2|^2, |e1 - e2|^2. Only these are needed: with ``a = e1 - e0``,
    ``b = e2 - e0``, ``w = c - e0`` the Gram entries ``a.w``, ``b.w``, ``a.b`` follow from them
    (polarisation), and the nearest point of the triangle is the free minimum of the quadratic
    when it falls inside, else the nearest point of one of the three edges. Degenerate faces
    (zero area) take their edges only. No library computes point-to-triangle distances in a
    space of the embedding's dimension from distances alone; here it is a few lines.
    """
    d0, d1, d2_ = d2[..., 0], d2[..., 1], d2[..., 2]
    e01, e02, e12 = (edge2[:, i : i + 1] for i in range(3))
    aw = 0.5 * (d0 + e01 - d1)
    bw = 0.5 * (d0 + e02 - d2_)
    ab = 0.5 * (e01 + e02 - e12)
    det = e01 * e02 - ab * ab
    best = torch.minimum(
        torch.minimum(_segment_d2(d0, d1, e01), _segment_d2(d0, d2_, e02)),
        _segment_d2(d1, d2_, e12),
    )
    safe = torch.where(det > 0, det, torch.ones_like(det))
    s = (aw * e02 - bw * ab) / safe
    t = (bw * e01 - aw * ab) / safe
    inner = d0 - 2 * s * aw - 2 * t * bw + s * s * e01 + 2 * s * t * ab + t * t * e02
    inside = (det > 0) & (s >= 0) & (t >= 0) & (s + t <= 1)
    return torch.where(inside, torch.minimum(best, inner), best).clamp(min=0.0)


def face_tables(field, tables: VertexTables, faces: torch.Tensor, k_s: int) -> FaceTables:
    """Tables for the unique faces ``faces``: candidates in all three vertex lists and within
    the face's own bound (see the comment below)."""
    if _compiled(field, tables.h):
        return _face_tables_compiled(field, tables, faces, k_s)
    tri = field.faces[faces]  # (F, 3)
    rows = tables.rows[tri]  # (F, 3)
    n_k = tables.n_kernels
    base = tables.kid[rows[:, 0]]  # (F, L)
    width = base.shape[1]
    hs, ds = [tables.h[rows[:, 0]]], [tables.d2[rows[:, 0]]]
    valid = base < n_k
    for corner in (1, 2):
        other = tables.kid[rows[:, corner]]
        pos = torch.searchsorted(other, base).clamp(max=max(0, width - 1))
        valid &= other.gather(1, pos) == base
        hs.append(tables.h[rows[:, corner]].gather(1, pos))
        ds.append(tables.d2[rows[:, corner]].gather(1, pos))
    h = torch.stack(hs, dim=2)
    d2 = torch.stack(ds, dim=2)
    emb = field.embedding.to(torch.float64)[tri]  # (F, 3, D)
    edge2 = torch.stack(
        [
            ((emb[:, 0] - emb[:, 1]) ** 2).sum(dim=1),
            ((emb[:, 0] - emb[:, 2]) ** 2).sum(dim=1),
            ((emb[:, 1] - emb[:, 2]) ** 2).sum(dim=1),
        ],
        dim=1,
    )
    # Tighter per face: its points lie within R_f of the centroid c_f, so their K_s nearest
    # are within D_f + 2 R_f of c_f, D_f = the K_s-th nearest distance from c_f (exact here:
    # c_f's K_s nearest are in all three vertex lists). |c_f - c_j|^2 by the same identity.
    centroid = emb.mean(dim=1)
    r_f = torch.linalg.norm(emb - centroid[:, None, :], dim=2).max(dim=1).values
    dc2 = d2.sum(dim=2) / 3.0 - edge2.sum(dim=1, keepdim=True) / 9.0
    dc2 = torch.where(valid, dc2, torch.full_like(dc2, float("inf")))
    k = min(k_s, width)
    kth = torch.topk(dc2, k, dim=1, largest=False).values[:, -1].clamp(min=0.0)
    reach = torch.sqrt(kth) + 2.0 * r_f
    slack = 1e-12 * (1.0 + float((emb * emb).sum(dim=2).max()))
    merged = valid.clone()  # in all three vertex lists (the compiled builder's n entries)
    valid &= dc2 <= (reach * reach * (1 + 1e-9) + slack)[:, None]
    # Tighter still: a point's distance to a centre is at most the centre's farthest corner
    # distance (the distance is convex, the face the corners' hull), so its K_s-th nearest
    # distance is at most U_f = the K_s-th smallest farthest-corner distance, and a centre
    # can be among its K_s nearest only if the centre's distance to the whole triangle is
    # within U_f. Measured on a default fit of spot (4,984 kernels): lists of 144 -> 98.
    # (well-shaped faces only: fused_tables.WELL_SHAPED)
    far2 = torch.where(merged, d2.max(dim=2).values, torch.full_like(dc2, float("inf")))
    if k > 0:  # (k <= the lists' width by construction)
        u2 = torch.topk(far2, k, dim=1, largest=False).values[:, -1]
        e01, e02, e12 = edge2.unbind(dim=1)
        half = 0.5 * (e01 + e02 - e12)
        shaped = e01 * e02 - half * half > fused_tables.WELL_SHAPED * (e01 + e02) ** 2
        u2 = torch.where(shaped, u2, torch.full_like(u2, float("inf")))
        near2 = triangle_d2(d2, edge2)
        valid &= ~(near2 > (u2 * (1 + 1e-9) + slack)[:, None])  # NaN keeps a candidate
    # compact each row to its kept entries, kernel order kept (row-major nonzero)
    rr, cc = torch.nonzero(valid, as_tuple=True)
    counts = torch.bincount(rr, minlength=faces.shape[0])
    width = int(counts.max()) if counts.numel() else 0
    slot = torch.arange(rr.shape[0], device=faces.device) - (torch.cumsum(counts, 0) - counts)[rr]
    kid = torch.full((faces.shape[0], width), n_k, dtype=torch.long, device=faces.device)
    kid[rr, slot] = base[rr, cc]
    h_out = torch.zeros((faces.shape[0], width, 3), dtype=h.dtype, device=h.device)
    h_out[rr, slot] = h[rr, cc]
    d2_out = torch.zeros((faces.shape[0], width, 3), dtype=d2.dtype, device=d2.device)
    d2_out[rr, slot] = d2[rr, cc]
    h, d2 = h_out, d2_out
    face_rows = torch.full((field.n_faces,), -1, dtype=torch.long, device=faces.device)
    face_rows[faces] = torch.arange(faces.shape[0], device=faces.device)
    return FaceTables(rows=face_rows, kid=kid, h=h, d2=d2, edge2=edge2, n_kernels=n_k, count=counts)


def _face_tables_compiled(
    field, tables: VertexTables, faces: torch.Tensor, k_s: int, max_bytes: float = math.inf
) -> FaceTables | None:
    """:func:`face_tables` by ``kernels.fused_tables`` (None above ``max_bytes``)."""
    lists = fused_tables.face_lists(field, tables, faces, k_s, max_bytes)
    if lists is None:
        return None
    kid, h, d2, edge2, count = lists
    face_rows = torch.full((field.n_faces,), -1, dtype=torch.long)
    face_rows[faces] = torch.arange(faces.shape[0])
    return FaceTables(
        rows=face_rows, kid=kid, h=h, d2=d2, edge2=edge2, n_kernels=tables.n_kernels, count=count
    )


def all_face_tables(
    field, tables: VertexTables, k_s: int, max_bytes: int, chunk: int = 4096
) -> FaceTables | None:
    """Face tables of every face (built in chunks of faces), or None above ``max_bytes``."""
    if _compiled(field, tables.h):
        faces = torch.arange(field.n_faces, device=field.faces.device)
        return _face_tables_compiled(field, tables, faces, k_s, max_bytes)
    parts = []
    total = 0
    for start in range(0, field.n_faces, chunk):
        faces = torch.arange(start, min(field.n_faces, start + chunk), device=field.faces.device)
        ft = face_tables(field, tables, faces, k_s)
        total += sum(t.numel() * t.element_size() for t in (ft.kid, ft.h, ft.d2, ft.edge2))
        if total > max_bytes:
            return None
        parts.append(ft)
    width = max(ft.kid.shape[1] for ft in parts)

    def pad(t: torch.Tensor, value) -> torch.Tensor:
        extra = width - t.shape[1]
        if extra == 0:
            return t
        shape = (t.shape[0], extra, *t.shape[2:])
        return torch.cat([t, torch.full(shape, value, dtype=t.dtype, device=t.device)], dim=1)

    n_k = tables.n_kernels
    return FaceTables(
        rows=torch.arange(field.n_faces, device=field.faces.device),
        kid=torch.cat([pad(ft.kid, n_k) for ft in parts]),
        h=torch.cat([pad(ft.h, 0.0) for ft in parts]),
        d2=torch.cat([pad(ft.d2, 0.0) for ft in parts]),
        edge2=torch.cat([ft.edge2 for ft in parts]),
        n_kernels=n_k,
        count=torch.cat([ft.count for ft in parts]),
    )


def point_distances(
    ft: FaceTables, face_ids: torch.Tensor, bary: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(row, kid, d2)``: each point's face row, its candidates (P, L) (padded with
    ``n_kernels``) and their exact squared distances (``+inf`` on padding)."""
    row = ft.rows[face_ids]
    b64 = bary.to(torch.float64)
    # rows are compacted (candidates first): keep only the columns this batch's faces use
    width = int(ft.count[row].max()) if row.numel() else 0
    kid = ft.kid[row][:, :width]  # gather rows, then narrow (narrowing first copies the table)
    # elementwise (not a matmul), so equal table rows (clones) give equal bits
    dv = ft.d2[row][:, :width]
    d2 = dv[:, :, 0] * b64[:, 0:1] + dv[:, :, 1] * b64[:, 1:2] + dv[:, :, 2] * b64[:, 2:3]
    e2 = ft.edge2[row]
    quad = b64[:, 0] * b64[:, 1] * e2[:, 0] + b64[:, 0] * b64[:, 2] * e2[:, 1]
    quad = quad + b64[:, 1] * b64[:, 2] * e2[:, 2]
    d2 = torch.clamp(d2 - quad[:, None], min=0.0)
    d2 = d2.masked_fill(kid >= ft.n_kernels, float("inf"))
    return row, kid, d2


def point_responses(
    ft: FaceTables, row: torch.Tensor, pos: torch.Tensor, bary: torch.Tensor
) -> torch.Tensor:
    """``h_j(y) = sum_v b_v H_j(v)`` for the entries ``pos`` (P, C) of the points' face rows."""
    hv = ft.h[row[:, None], pos]  # (P, C, 3)
    bh = bary.to(ft.h.dtype)
    return hv[:, :, 0] * bh[:, 0:1] + hv[:, :, 1] * bh[:, 1:2] + hv[:, :, 2] * bh[:, 2:3]


def point_terms(
    ft: FaceTables, face_ids: torch.Tensor, bary: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(kid, h, d2)`` (P, L) for points: every candidate of the point's face."""
    row, kid, d2 = point_distances(ft, face_ids, bary)
    pos = torch.arange(kid.shape[1], device=kid.device).expand_as(kid)
    return kid, point_responses(ft, row, pos, bary), d2
