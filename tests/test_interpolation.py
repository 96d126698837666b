"""SpectralField: bilinear grid interpolation and its gradients (ALGORITHM.md section 2)."""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.spectra import interpolation
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_points


def _numpy_bilinear(spectra, face_ids, bary, theta, s):
    """Independent reference: explicit cell search and bilinear formula per point in numpy."""
    gt, gs = spectra.grid_theta, np.log1p(spectra.grid_eta)
    n_s = gs.shape[0]
    lam = np.zeros((len(theta), spectra.evals.shape[1]))
    phi = np.zeros_like(lam)
    for p in range(len(theta)):
        x = min(max(theta[p], gt[0]), gt[-1])
        y = min(max(s[p], gs[0]), gs[-1])
        i = min(int(np.searchsorted(gt, x, side="right")) - 1, len(gt) - 2)
        j = min(int(np.searchsorted(gs, y, side="right")) - 1, len(gs) - 2)
        u = (x - gt[i]) / (gt[i + 1] - gt[i])
        v = (y - gs[j]) / (gs[j + 1] - gs[j])
        for di, dj, w in [
            (0, 0, (1 - u) * (1 - v)),
            (0, 1, (1 - u) * v),
            (1, 0, u * (1 - v)),
            (1, 1, u * v),
        ]:
            g = (i + di) * n_s + (j + dj)
            lam[p] += w * spectra.evals[g]
            corner = spectra.faces[face_ids[p]]
            phi[p] += w * (bary[p] @ spectra.evecs[corner, g, :])
    return lam, phi


def test_exact_at_nodes(spectra, field64):
    face_ids, bary = random_points(spectra, 5)
    for a, theta in enumerate(spectra.grid_theta):
        for b, s in enumerate(np.log1p(spectra.grid_eta)):
            g = a * len(spectra.grid_eta) + b
            th = torch.full((5,), float(theta), dtype=torch.float64)
            ss = torch.full((5,), float(s), dtype=torch.float64)
            lam = field64.eigenvalues(th, ss).numpy()
            phi = field64.eigenfunctions(torch.as_tensor(face_ids), torch.as_tensor(bary), th, ss)
            np.testing.assert_allclose(
                lam, np.broadcast_to(spectra.evals[g], lam.shape), rtol=1e-12
            )
            verts = spectra.faces[face_ids]
            expect = np.einsum("pv,pvk->pk", bary, spectra.evecs[verts, g, :])
            np.testing.assert_allclose(phi.detach().numpy(), expect, rtol=1e-10, atol=1e-12)


def test_bilinear_between_nodes_and_clamped(spectra, field64):
    rng = np.random.default_rng(3)
    face_ids, bary = random_points(spectra, 40)
    theta = rng.uniform(-0.5, np.pi + 0.5, 40)  # some outside: clamped
    s = rng.uniform(0.3, np.log1p(12.0), 40)
    lam_ref, phi_ref = _numpy_bilinear(spectra, face_ids, bary, theta, s)
    t = lambda x: torch.as_tensor(x)  # noqa: E731
    lam = field64.eigenvalues(t(theta), t(s)).numpy()
    phi = field64.eigenfunctions(t(face_ids), t(bary), t(theta), t(s)).detach().numpy()
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-12)
    np.testing.assert_allclose(phi, phi_ref, rtol=1e-10, atol=1e-12)


def test_node_values_match_eigenfunctions(spectra, field64):
    face_ids, bary = random_points(spectra, 7)
    all_nodes = field64.node_values(torch.as_tensor(face_ids), torch.as_tensor(bary))
    verts = spectra.faces[face_ids]
    expect = np.einsum("pv,pvgk->pgk", bary, spectra.evecs[verts])
    np.testing.assert_allclose(all_nodes.numpy(), expect, rtol=1e-10, atol=1e-12)


def test_gradients_against_finite_differences(spectra, field64, monkeypatch):
    monkeypatch.setattr(interpolation, "CHUNK_ROWS", 2)  # exercise the chunked backward
    rng = np.random.default_rng(5)
    face_ids = torch.as_tensor(rng.integers(0, spectra.faces.shape[0], 4))
    # keep points off cell boundaries, where the bilinear map is only piecewise smooth
    theta = torch.tensor([0.3, 1.2, 2.0, 2.9], dtype=torch.float64, requires_grad=True)
    s = torch.tensor([0.8, 1.5, 2.1, 1.0], dtype=torch.float64, requires_grad=True)
    bary = torch.as_tensor(rng.dirichlet(np.ones(3), 4)).requires_grad_(True)

    def phi(th, ss, b):
        return field64.eigenfunctions(face_ids, b, th, ss)

    assert torch.autograd.gradcheck(phi, (theta, s, bary))
    assert torch.autograd.gradcheck(lambda th, ss: field64.eigenvalues(th, ss), (theta, s))
    assert torch.autograd.gradcheck(lambda b: field64.node_values(face_ids, b), (bary,))


def test_chunking_does_not_change_results(spectra, field64, monkeypatch):
    face_ids, bary = random_points(spectra, 9)
    th = torch.linspace(0, np.pi, 9, dtype=torch.float64)
    ss = torch.linspace(0.7, 2.3, 9, dtype=torch.float64)
    args = (torch.as_tensor(face_ids), torch.as_tensor(bary), th, ss)
    full = field64.eigenfunctions(*args)
    monkeypatch.setattr(interpolation, "CHUNK_ROWS", 4)
    np.testing.assert_array_equal(field64.eigenfunctions(*args).numpy(), full.numpy())


def test_float16_storage_upcasts(spectra):
    half = type(spectra)(**{**spectra.__dict__, "evecs": spectra.evecs.astype(np.float16)})
    field = SpectralField(half, device="cpu", dtype=torch.float32)
    assert field.evecs.dtype == torch.float16
    face_ids, bary = random_points(spectra, 3)
    th, ss = torch.zeros(3), torch.full((3,), 0.7)
    out = field.eigenfunctions(torch.as_tensor(face_ids), torch.as_tensor(bary), th, ss)
    assert out.dtype == torch.float32
    ref = SpectralField(spectra, device="cpu", dtype=torch.float64).eigenfunctions(
        torch.as_tensor(face_ids), torch.as_tensor(bary), th.double(), ss.double()
    )
    np.testing.assert_allclose(out.numpy(), ref.numpy(), atol=5e-3 * np.abs(ref.numpy()).max())


def test_cpu_field_shares_a_memory_mapped_grid(spectra, tmp_path):
    from hktex_engine.spectra.grid import load_spectra, write_spectra

    mapped = load_spectra(write_spectra(spectra, tmp_path / "s"), mmap=True)
    field = SpectralField(mapped, device="cpu", dtype=torch.float64)
    assert field.evecs.data_ptr() == mapped.evecs.ctypes.data  # no copy of the big array
    face_ids, bary = random_points(spectra, 6)
    th, ss = torch.full((6,), 0.4, dtype=torch.float64), torch.full((6,), 1.1, dtype=torch.float64)
    args = (torch.as_tensor(face_ids), torch.as_tensor(bary), th, ss)
    ref = SpectralField(spectra, device="cpu", dtype=torch.float64).eigenfunctions(*args)
    np.testing.assert_array_equal(field.eigenfunctions(*args).numpy(), ref.numpy())


def test_saved_blends_and_regathering_backward_agree(spectra, field64, monkeypatch):
    """Backward from the kept 7 blended rows equals backward that regathers (memory cap)."""
    rng = np.random.default_rng(8)
    face_ids = torch.as_tensor(rng.integers(0, spectra.faces.shape[0], 5))
    grads = []
    for cap in (interpolation.SAVE_BYTES, 0):
        monkeypatch.setattr(interpolation, "SAVE_BYTES", cap)
        theta = torch.tensor([0.3, 1.2, 2.0, 2.9, 0.5], dtype=torch.float64, requires_grad=True)
        s = torch.tensor([0.8, 1.5, 2.1, 1.0, 1.7], dtype=torch.float64, requires_grad=True)
        bary = torch.as_tensor(rng.dirichlet(np.ones(3), 5) if not grads else grads[0][3])
        bary = bary.clone().requires_grad_(True)
        out = field64.eigenfunctions(face_ids, bary, theta, s)
        (out * torch.linspace(-1, 1, out.shape[1], dtype=torch.float64)).sum().backward()
        grads.append((theta.grad, s.grad, bary.grad, bary.detach(), out.detach()))
    for a, b in zip(grads[0][:3] + grads[0][4:], grads[1][:3] + grads[1][4:], strict=True):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-12, atol=1e-14)


def test_row_cache_regathers_exactly_the_changed_points(spectra, field64):
    """Cached rows equal a fresh gather after faces and grid cells change for some points."""
    rng = np.random.default_rng(12)
    n = 9
    face_ids = torch.as_tensor(rng.integers(0, spectra.faces.shape[0], n))
    theta = torch.as_tensor(rng.uniform(0.1, 3.0, n))
    s = torch.as_tensor(rng.uniform(0.7, 2.2, n))
    cache = interpolation.RowCache(max_bytes=10**9)
    assert cache.fits(field64, n) and not interpolation.RowCache(0).fits(field64, n)

    def check():
        nodes, _ = field64.nodes(theta, s)
        verts = field64.faces[face_ids]
        got = cache.rows(field64, verts, nodes)
        expect = interpolation.gather_rows(field64.evecs, verts, nodes, torch.float64)
        assert torch.equal(got, expect)

    check()
    assert cache.regathered == n
    check()
    assert cache.regathered == 0
    before, _ = field64.nodes(theta, s)
    theta[2] = 3.1 if theta[2] < 1.5 else 0.05  # another grid cell
    face_ids[5] = (face_ids[5] + 1) % spectra.faces.shape[0]  # another face
    s[7] += 1e-9  # same cell: no regather
    after, _ = field64.nodes(theta, s)
    assert not torch.equal(before[2], after[2]) and torch.equal(before[7], after[7])
    check()
    assert cache.regathered == 2
