"""Per-vertex candidate tables (kernels.tables) against the per-point KNN path and brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hktex_engine.config import KernelConfig
from hktex_engine.kernels import model as kernels_mod
from hktex_engine.kernels import tables as tables_mod
from hktex_engine.kernels.model import _exhaustive_cut
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import tiny_spectra
from tests.test_kernels import make_model, make_params

CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=12, k_blend=4)


@pytest.fixture(scope="module")
def spectra3():
    return tiny_spectra(3)  # 642 vertices: lists are a small part of 300 kernels


@pytest.fixture(scope="module")
def dense_points(spectra3):
    rng = np.random.default_rng(11)
    n = 3000
    return rng.integers(0, spectra3.faces.shape[0], n), rng.dirichlet(np.ones(3), n)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_tables_equal_the_per_point_path(spectra3, dense_points, monkeypatch, dtype):
    field = SpectralField(spectra3, device="cpu", dtype=dtype)
    model = make_model(field, make_params(spectra3, 300, seed=12), CONFIG)
    f, b = dense_points
    results = {}
    for path in ("never", "always"):
        monkeypatch.setattr(kernels_mod, "TABLE_PATH", path)
        monkeypatch.setattr(tables_mod, "PATCH", 5)  # several patches, a ragged last one
        with torch.no_grad():
            results[path] = model.albedo(f, b, return_aux=True)
    assert model._vtables is not None and model._vtables.kid.shape[1] < 300
    (a, aux_a), (t, aux_t) = results["never"], results["always"]
    if dtype == torch.float64:
        np.testing.assert_allclose(t.numpy(), a.numpy(), atol=1e-12)
        assert torch.equal(aux_t["indices"], aux_a["indices"])
    else:
        diff = (t - a).abs().max(dim=1).values
        assert diff.max() < 1e-4
        assert (aux_t["indices"] == aux_a["indices"]).all(dim=1).float().mean() > 0.99


def test_face_lists_contain_every_points_nearest(spectra3, dense_points):
    """The provable superset: each point's exact K_s nearest centres (tie rule, over all
    centres) are among its face's candidates."""
    field = SpectralField(spectra3, device="cpu", dtype=torch.float64)
    model = make_model(field, make_params(spectra3, 300, seed=13), CONFIG)
    f, b = (torch.as_tensor(x) for x in dense_points)
    with torch.no_grad():
        tables = model.prepare_tables()
        ft = tables_mod.face_tables(field, tables, torch.unique(f), CONFIG.k_search)
        kid, h, d2 = tables_mod.point_terms(ft, f, b)
        nearest, d2_near = _exhaustive_cut(field.embedding_at(f, b), model._centre_emb, 12)
    found = (kid[:, :, None] == nearest[:, None, :]).any(dim=1)
    assert found.all()
    # and the identity-based distances equal the direct ones
    pos = (kid[:, :, None] == nearest[:, None, :]).float().argmax(dim=1)
    np.testing.assert_allclose(d2.gather(1, pos).numpy(), d2_near.numpy(), atol=1e-12)
    assert kid.shape[1] < 150  # well below all 300 kernels


def test_vertex_responses_equal_a_direct_computation(spectra3):
    """H_j(v) from the patch products against coef_j . phi^j(v) computed per pair."""
    field = SpectralField(spectra3, device="cpu", dtype=torch.float64)
    model = make_model(field, make_params(spectra3, 80, seed=14), CONFIG)
    with torch.no_grad():
        tables = model.prepare_tables()
        coef, _, nodes, weights, _ = model._terms
        v = torch.arange(field.n_vertices)[:, None].expand_as(tables.kid)
        valid = tables.kid < 80
        j = torch.where(valid, tables.kid, 0)
        rows = field.evecs[v[..., None], nodes[j]]  # (V, L, 4, K)
        direct = ((rows * weights[j][..., None]).sum(dim=2) * coef[j]).sum(dim=-1)
    np.testing.assert_allclose(tables.h[valid].numpy(), direct[valid].numpy(), atol=1e-12)


def test_tables_follow_centre_moves(spectra3, dense_points):
    """Tables are rebuilt when centres (or attributes) change, never read stale."""
    field = SpectralField(spectra3, device="cpu", dtype=torch.float64)
    kp = make_params(spectra3, 200, seed=15)
    model = make_model(field, kp, CONFIG)
    f, b = dense_points
    with torch.no_grad():
        model.prepare_tables()
        model.albedo(f, b)
        moved = (model.face_ids + 7) % spectra3.faces.shape[0]
        model.set_centres(moved, model.bary.detach())
        model.theta.add_(0.3).clamp_(0, np.pi)
        got = model.albedo(f, b)
        kp2 = dict(kp, face_ids=moved.numpy(), theta=model.theta.numpy().copy())
        fresh = make_model(field, kp2, CONFIG)
        ref = fresh.albedo_bruteforce(f, b, exact_search=True)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-12)


def test_whole_mesh_tables_equal_the_per_point_path(spectra3, dense_points, monkeypatch):
    """prepare_tables (vertex and face tables of the whole mesh) against the KNN path."""
    field = SpectralField(spectra3, device="cpu", dtype=torch.float64)
    model = make_model(field, make_params(spectra3, 300, seed=16), CONFIG)
    f, b = dense_points
    with torch.no_grad():
        monkeypatch.setattr(kernels_mod, "TABLE_PATH", "never")
        ref, aux_ref = model.albedo(f, b, return_aux=True)
        monkeypatch.setattr(kernels_mod, "TABLE_PATH", "auto")
        model.prepare_tables()
        assert model._ftables is not None and model._ftables.kid.shape[0] == field.n_faces
        got, aux = model.albedo(f[:7], b[:7], return_aux=True)  # sparse: tables still used
        np.testing.assert_allclose(got.numpy(), ref[:7].numpy(), atol=1e-12)
        got, aux = model.albedo(f, b, return_aux=True)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-12)
    assert torch.equal(aux["indices"], aux_ref["indices"])


def _clones(kp: dict, copies: int) -> dict:
    """``kp`` with its first ``copies`` kernels appended again (exact clones: the tie rule's
    case that needs bit-equal distances and responses)."""
    return {k: np.concatenate([v, v[:copies]]) if k != "base_color" else v for k, v in kp.items()}


@pytest.mark.parametrize("grid", ["float32", "float16"])
def test_compiled_tables_against_brute_force(spectra3, grid, monkeypatch):
    """The compiled builders (CPU float32, kernels.fused_tables) against independent numpy:
    each vertex list is exactly the centres within D_v + 2 R_v (D_v: the K_s-th nearest
    distance by a full sort; R_v: the longest embedding edge at v), ascending, with their
    squared distances; each response is sum_c w_c coef . phi(v)[node_c] on the grid's values
    (float16 read in place); clones get bit-equal entries. The float16 case also starts the
    lists one slot per K_s wide, so most are gathered again at their length."""
    import dataclasses

    from hktex_engine.kernels import fused_tables

    spectra = spectra3
    if grid == "float16":
        monkeypatch.setattr(fused_tables, "LIST_SLOTS_PER_KS", 1)
        spectra = dataclasses.replace(spectra3, evecs=np.asarray(spectra3.evecs, np.float16))
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    kp = _clones(make_params(spectra, 300, seed=17), 20)
    model = make_model(field, kp, CONFIG)
    assert tables_mod._compiled(field, model.colors)
    with torch.no_grad():
        tables = model.prepare_tables()
    assert getattr(field, "_evecs32", None) is None  # the float16 grid had no copy made
    emb = field.embedding.numpy().astype(np.float64)
    cen = model._centre_emb.numpy().astype(np.float64)
    d2 = ((emb[:, None, :] - cen[None, :, :]) ** 2).sum(axis=2)  # (n, N) direct
    edges = field.faces.numpy()[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    length = np.linalg.norm(emb[edges[:, 0]] - emb[edges[:, 1]], axis=1)
    r_v = np.zeros(len(emb))
    np.maximum.at(r_v, edges[:, 0], length)
    np.maximum.at(r_v, edges[:, 1], length)
    kth = np.sqrt(np.sort(d2, axis=1)[:, CONFIG.k_search - 1])
    inside = d2 <= (kth + 2 * r_v)[:, None] ** 2
    n_k = len(model)
    kid = tables.kid.numpy()
    for v in range(0, len(emb), 7):
        row = kid[v][kid[v] < n_k]
        expect = np.flatnonzero(inside[v])
        # the same set, up to entries on the bound's round-off margin
        assert set(expect) <= set(row) and len(row) - len(expect) <= 2
        np.testing.assert_array_equal(row, np.sort(row))
        np.testing.assert_allclose(tables.d2[v, : len(row)].numpy(), d2[v, row], atol=1e-12)
    coef, _, nodes, weights, _ = (t.numpy() for t in model._terms)
    evecs = field.evecs.numpy().astype(np.float32)
    valid = kid < n_k
    vv, ii = np.nonzero(valid)
    j = kid[vv, ii]
    rows = evecs[vv[:, None], nodes[j]]  # (pairs, 4, K)
    direct = ((rows * weights[j][..., None]).sum(axis=1) * coef[j]).sum(axis=1)
    np.testing.assert_allclose(tables.h.numpy()[vv, ii], direct, rtol=1e-5, atol=1e-6)
    # clones: kernel j and j + 300 hold the same centre and shape, so the same values
    first = kid[valid] < 20
    clone_rows = {(a, b): i for a, b, i in zip(vv, j, ii, strict=True)}
    for a, b in zip(vv[first], j[first], strict=True):
        i, c = clone_rows[(a, b)], clone_rows[(a, b + 300)]
        assert tables.h[a, i] == tables.h[a, c] and tables.d2[a, i] == tables.d2[a, c]
    # the face lists: bit for bit those of the torch builder on the same vertex tables
    faces = torch.arange(field.n_faces)
    got = fused_tables.face_lists(field, tables, faces, CONFIG.k_search)
    monkeypatch.setattr(tables_mod, "_compiled", lambda *a: False)
    torch_ft = tables_mod.face_tables(field, tables, faces, CONFIG.k_search)
    for name, value in zip(("kid", "h", "d2", "count"), (got[0], got[1], got[2], got[4]), strict=True):  # fmt: skip
        assert torch.equal(value, getattr(torch_ft, name)), name
    np.testing.assert_allclose(got[3].numpy(), torch_ft.edge2.numpy(), rtol=1e-14)


def _corner_tables(corners: np.ndarray, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d2, edge2)`` as the face tables hold them, from explicit coordinates: corners (F, 3,
    D), points (F, L, D)."""
    d2 = ((points[:, :, None, :] - corners[:, None, :, :]) ** 2).sum(axis=3)
    e = corners
    edge2 = np.stack(
        [
            ((e[:, 0] - e[:, 1]) ** 2).sum(1),
            ((e[:, 0] - e[:, 2]) ** 2).sum(1),
            ((e[:, 1] - e[:, 2]) ** 2).sum(1),
        ],
        axis=1,
    )
    return torch.from_numpy(d2), torch.from_numpy(edge2)


def test_triangle_distance_from_corner_distances_alone():
    """``triangle_d2`` against cases solved by hand (above the interior: the height; beyond a
    corner: that corner; beside an edge: the foot on it; degenerate faces: their segments)
    and against a dense barycentric sampling of random triangles in 6-D, which it may
    undercut only by the sampling's spacing, never by more."""
    from hktex_engine.kernels import fused_tables

    tri = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    points = np.array([[0.5, 0.5, 3.0], [-1.0, -2.0, 0.0], [1.0, -1.0, 0.5], [2.0, 2.0, 0.0]])
    expect = [9.0, 5.0, 1.25, 2.0]  # height^2; corner 0; foot (1, 0, 0); foot (1, 1, 0)
    degenerate = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])  # collinear
    twice = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # a repeated corner
    corners = np.stack([tri, degenerate, twice])
    pts = np.stack([points, points, points])
    d2, edge2 = _corner_tables(corners, pts)
    got = tables_mod.triangle_d2(d2, edge2).numpy()
    np.testing.assert_allclose(got[0], expect, atol=1e-12)
    np.testing.assert_allclose(got[1], [9.25, 5.0, 1.25, 4.0], atol=1e-12)  # segment x in [0, 3]
    np.testing.assert_allclose(got[2], [9.25, 5.0, 2.25, 5.0], atol=1e-12)  # segment y in [0, 1]
    # the compiled builder's per-pair twin (plain Python until its loops are compiled)
    compiled_one = fused_tables._triangle_d2
    for f in range(3):
        for i in range(4):
            assert compiled_one(*d2[f, i].tolist(), *edge2[f].tolist()) == pytest.approx(
                got[f, i], abs=1e-12
            )

    rng = np.random.default_rng(5)
    corners = rng.normal(size=(40, 3, 6))
    pts = rng.normal(size=(40, 25, 6)) * 1.5
    d2, edge2 = _corner_tables(corners, pts)
    got = tables_mod.triangle_d2(d2, edge2).numpy()
    n = 120
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    bary = np.stack([n - i[keep] - j[keep], i[keep], j[keep]], axis=1) / n  # (S, 3)
    samples = np.einsum("sc,fcd->fsd", bary, corners)  # (F, S, D)
    sampled = ((pts[:, :, None, :] - samples[:, None, :, :]) ** 2).sum(axis=3).min(axis=2)
    assert (got <= sampled + 1e-9).all()  # a lower bound
    spacing = np.sqrt(edge2.numpy().max(axis=1))[:, None] / n  # farthest a sample can miss
    assert (np.sqrt(sampled) - np.sqrt(got) <= spacing + 1e-9).all()  # and tight to the spacing


def test_compiled_face_lists_keep_every_points_nearest_and_are_tighter(spectra3, dense_points):
    """The compiled face lists (CPU float32) hold each point's K_s nearest centres (float64
    distances over all centres; entries within round-off of the K_s-th count as either), and
    the triangle bound makes them shorter than the centroid bound alone would."""
    from hktex_engine.kernels import fused_tables

    field = SpectralField(spectra3, device="cpu", dtype=torch.float32)
    model = make_model(field, make_params(spectra3, 300, seed=13), CONFIG)
    assert tables_mod._compiled(field, model.colors)
    f, b = dense_points
    with torch.no_grad():
        tables = model.prepare_tables()
    faces = torch.arange(field.n_faces)
    kid, _, _, _, count = fused_tables.face_lists(field, tables, faces, CONFIG.k_search)
    emb = field.embedding.numpy().astype(np.float64)
    cen = model._centre_emb.numpy().astype(np.float64)
    y = np.einsum("pc,pcd->pd", b, emb[field.faces.numpy()[f]])
    d2 = ((y[:, None, :] - cen[None, :, :]) ** 2).sum(axis=2)  # (P, N)
    kth = np.sort(d2, axis=1)[:, CONFIG.k_search - 1]
    must = d2 < kth[:, None] * (1 - 1e-6)
    rows = kid.numpy()[f]
    for p in range(len(f)):
        assert set(np.flatnonzero(must[p])) <= set(rows[p][rows[p] < len(model)])
    # the centroid bound alone (tables.face_tables' first bound), counted independently
    tri = field.faces.numpy()
    centroid = emb[tri].mean(axis=1)
    r_f = np.linalg.norm(emb[tri] - centroid[:, None, :], axis=2).max(axis=1)
    dc2 = ((centroid[:, None, :] - cen[None, :, :]) ** 2).sum(axis=2)
    kth_c = np.sort(dc2, axis=1)[:, CONFIG.k_search - 1]
    centroid_only = (dc2 <= ((np.sqrt(kth_c) + 2 * r_f) ** 2)[:, None]).sum(axis=1)
    assert count.numpy().mean() < 0.9 * centroid_only.mean()


def test_the_triangle_bound_skips_ill_shaped_faces(spectra3, monkeypatch):
    """With every face counted as a sliver (``WELL_SHAPED`` 1: no Gram determinant reaches
    it) the torch builder keeps the centroid bound's lists; by default they are shorter."""
    from hktex_engine.kernels import fused_tables

    field = SpectralField(spectra3, device="cpu", dtype=torch.float64)
    model = make_model(field, make_params(spectra3, 300, seed=13), CONFIG)
    faces = torch.arange(field.n_faces)
    with torch.no_grad():
        tables = model.prepare_tables()
        tight = tables_mod.face_tables(field, tables, faces, CONFIG.k_search)
        monkeypatch.setattr(fused_tables, "WELL_SHAPED", 1.0)
        loose = tables_mod.face_tables(field, tables, faces, CONFIG.k_search)
    assert (tight.count <= loose.count).all()
    assert tight.count.double().mean() < 0.9 * loose.count.double().mean()
