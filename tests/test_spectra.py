"""Eigensolver, alignment, the spectra artefact and its cache (ALGORITHM.md sections 2-3)."""

from __future__ import annotations

import json
import multiprocessing
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from hktex_engine.config import SpectralConfig
from hktex_engine.errors import Cancelled, SpectraError
from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.operators import AlboAssembler, cotangent_stiffness, lumped_mass
from hktex_engine.spectra import cores
from hktex_engine.spectra import grid as spectra_mod
from hktex_engine.spectra.alignment import align_basis, eigen_clusters
from hktex_engine.spectra.eigensolver import eigs_cold, eigs_warm, residuals
from hktex_engine.spectra.grid import (
    SpectraCache,
    compute_spectra,
    load_spectra,
    write_spectra,
)

TINY = SpectralConfig(
    angles=3, anisotropies=(1.0, 10.0), k=16, k_iso=9, rotation="block", evecs_dtype="float32"
)


def _ellipsoid_mesh(level: int = 3, seed: int = 2) -> Mesh:
    """A bumpy ellipsoid (642 vertices at level 3): no symmetry, so no exact degeneracy."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=level)
    rng = np.random.default_rng(seed)
    V = m.vertices * np.array([1.0, 0.7, 0.5])
    V = V * (1 + 0.03 * rng.standard_normal((len(V), 1)))
    return Mesh(
        vertices=V,
        faces=np.asarray(m.faces, dtype=np.int64),
        scale=1.0,
        translation=np.zeros(3),
        content_hash=f"ellipsoid-{level}-{seed}",
    )


@pytest.fixture(scope="module")
def mesh() -> Mesh:
    return _ellipsoid_mesh()


@pytest.fixture(scope="module")
def tiny(mesh):
    return compute_spectra(mesh, TINY)


def _operator(mesh, spectra, g):
    asm = AlboAssembler(mesh.vertices, mesh.faces, spectra.face_frames)
    S = len(spectra.grid_eta)
    return asm.stiffness(spectra.grid_theta[g // S], spectra.grid_eta[g % S])


# ------------------------------------------------------------------ eigensolver


def test_every_stored_node_is_an_m_orthonormal_eigenbasis(mesh, tiny):
    n, G, K = tiny.evecs.shape
    assert (n, G, K) == (mesh.n_vertices, 6, 16)
    M = tiny.mass
    for g in range(G):
        L = _operator(mesh, tiny, g)
        phi = np.asarray(tiny.evecs[:, g, :], dtype=np.float64)
        gram = phi.T @ (M[:, None] * phi)
        np.testing.assert_allclose(gram, np.eye(K), atol=1e-5)
        assert residuals(L, M, tiny.evals[g], phi).max() < 1e-4
    # isotropic spectrum: lambda_0 = 0 with a constant eigenvector
    iso = tiny.iso_evecs
    assert abs(tiny.iso_evals[0]) < 1e-8
    assert np.ptp(iso[:, 0]) < 1e-8 * np.abs(iso[:, 0]).max()
    np.testing.assert_allclose(iso.T @ (M[:, None] * iso), np.eye(TINY.k_iso), atol=1e-8)
    L = cotangent_stiffness(mesh.vertices, mesh.faces)
    assert residuals(L, M, tiny.iso_evals, iso).max() < 1e-8


def test_full_rotation_nodes_span_the_exact_eigenspaces(mesh):
    """Full Procrustes keeps each node M-orthonormal and inside the span of
    its K lowest eigenvectors, with the eigenvalues only permuted."""
    sp = compute_spectra(mesh, SpectralConfig(**{**TINY.to_dict(), "rotation": "full"}))
    M = sp.mass
    for g in range(sp.evals.shape[0]):
        phi = np.asarray(sp.evecs[:, g, :], dtype=np.float64)
        np.testing.assert_allclose(phi.T @ (M[:, None] * phi), np.eye(16), atol=1e-5)
        vals, exact = eigs_cold(_operator(mesh, sp, g), M, 16)
        np.testing.assert_allclose(np.sort(sp.evals[g]), vals, rtol=1e-6, atol=1e-9)
        inside = exact @ (exact.T @ (M[:, None] * phi))  # M-projection on the exact span
        assert np.abs(inside - phi).max() < 1e-4


def test_node_spectra_equal_an_independent_dense_solve(mesh, tiny):
    import scipy.linalg as sla

    for g in (1, 3):
        L = _operator(mesh, tiny, g).toarray()
        exact = sla.eigh(L, np.diag(tiny.mass), eigvals_only=True, subset_by_index=(0, 15))
        np.testing.assert_allclose(np.sort(tiny.evals[g]), exact, rtol=1e-6, atol=1e-9)


def test_warm_solver_matches_cold_from_a_neighbour_start(mesh):
    V, F = mesh.vertices, mesh.faces
    from hktex_engine.geometry.operators import reference_tangent_field

    asm = AlboAssembler(V, F, reference_tangent_field(V, F))
    M = lumped_mass(V, F)
    _, start = eigs_cold(asm.stiffness(0.0, 5.0), M, 30)
    L = asm.stiffness(0.4, 8.0)
    cold, _ = eigs_cold(L, M, 24)
    vals, vecs, info = eigs_warm(L, M, start, 24, tol=1e-8)
    assert info.max_residual < 1e-8
    np.testing.assert_allclose(vals[:24], cold, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    "kwargs", [{"solver": "warm"}, {"solver": "cold"}, {"solver": "block"}, {"workers": 2}]
)
def test_other_solvers_and_worker_processes_give_the_same_grid(mesh, tiny, kwargs):
    other = compute_spectra(mesh, TINY, **kwargs)
    # the default ("auto") picks by size: 642 vertices for 16 pairs is the block side
    assert tiny.manifest["solver"]["nodes"][1]["method"] == "block"
    assert other.manifest["solver"]["nodes"][1]["method"] == kwargs.get("solver", "block")
    src = np.array([0, 200, 400])
    for g in range(tiny.evals.shape[0]):
        a, b = np.sort(other.evals[g]), np.sort(tiny.evals[g])
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * b.max())
        h_a = _heat(tiny.evals[g], tiny.evecs[:, g, :], src, 0.1)
        h_b = _heat(other.evals[g], other.evecs[:, g, :], src, 0.1)
        assert np.linalg.norm(h_a - h_b) < 1e-4 * np.linalg.norm(h_a)
    # theta = pi is theta = 0: copied, not solved again
    methods = [e["method"] for e in tiny.manifest["solver"]["nodes"]]
    assert methods[4:] == ["copy of node 0", "copy of node 1"]


def _same_grid(a, b) -> None:
    for g in range(a.evals.shape[0]):
        np.testing.assert_allclose(a.evals[g], b.evals[g], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(
            np.asarray(a.evecs[:, g, :], float), np.asarray(b.evecs[:, g, :], float), atol=1e-5
        )


def test_spawned_workers_give_the_same_grid(mesh, tiny, monkeypatch):
    monkeypatch.setattr(spectra_mod, "worker_context", lambda: multiprocessing.get_context("spawn"))
    # and load the compiled solves in their initializer, as grids from PRELOAD_MIN_N do
    monkeypatch.setattr(spectra_mod, "PRELOAD_MIN_N", 0)
    _same_grid(compute_spectra(mesh, TINY, workers=2), tiny)


def test_the_command_line_forks_its_workers_and_stores_the_same_grid(mesh, tmp_path):
    """``hktex spectra`` in a fresh process (one thread, no torch) forks its workers, and the
    grid they solve is the one a single process computes. Run in a subprocess: this test
    process holds torch and threads, where forking is what the rule forbids."""
    import subprocess

    import trimesh

    from hktex_engine.geometry.mesh import load_mesh

    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork here")
    obj, out = tmp_path / "m.obj", tmp_path / "spectra"
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(obj)
    code = (
        "import sys; from hktex_engine.cli import main; code = main(sys.argv[1:]); "
        "from hktex_engine.spectra.grid import worker_context; "
        "print('start:', worker_context().get_start_method()); sys.exit(code)"
    )
    grid = ["--angles", "3", "--anisotropies", "1,10", "--k", "16", "--k-iso", "9"]
    args = ["spectra", str(obj), "-o", str(out), *grid, "--evecs-dtype", "float32"]
    run = subprocess.run(
        [sys.executable, "-c", code, *args, "--workers", "2"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "start: fork"
    stored = load_spectra(out)
    assert stored.manifest["solver"]["workers"] == 2
    _same_grid(stored, compute_spectra(load_mesh(obj, read_texture=False), TINY))


@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_grids_load_the_compiled_solves_before_their_workers(monkeypatch, mesh, start):
    """From PRELOAD_MIN_N vertices a grid loads the compiled triangular solves once: in this
    process (which solves too) before its pool, so forked workers inherit them, and in each
    spawned worker through the pool's initializer; below it, nowhere. Every worker starts
    through ``_start_worker`` (its allocator keeps freed memory)."""
    from hktex_engine.spectra import triangular

    seen = []

    class Pool:  # records how the pool was made, solves in this process
        def __init__(self, max_workers, mp_context, initializer, initargs):
            seen.append((mp_context.get_start_method(), initializer, initargs, max_workers))
            seen.append(triangular._preloaded)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args):
            from concurrent.futures import Future

            fut = Future()
            fut.set_result(fn(*args))
            return fut

    monkeypatch.setattr(spectra_mod, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(spectra_mod, "worker_context", lambda: multiprocessing.get_context(start))
    from hktex_engine.spectra import eigensolver

    # grid imports the solver when a grid is built (not with the module), so patch it there
    monkeypatch.setattr(
        eigensolver, "solve_node_timed", lambda L, mass, k, e, s, tol: (None, None, 0.0, "fake")
    )
    tasks = [(None, 4, 1.0, 1e-6)] * 2
    for min_n, expect in ((10**9, False), (0, triangular.HAVE_NUMBA)):
        monkeypatch.setattr(triangular, "_preloaded", False)
        monkeypatch.setattr(spectra_mod, "PRELOAD_MIN_N", min_n)
        assert len(list(spectra_mod._cold_solutions(iter(tasks), mesh.vertices, 2))) == 2
        parent_loaded = seen.pop()
        method, initializer, initargs, pool_size = seen.pop()
        assert method == start and pool_size == 1  # this process is the other solver
        assert initializer is spectra_mod._start_worker and parent_loaded == expect
        assert initargs == ((min_n == 0) and start == "spawn",)


@pytest.mark.parametrize("total", [None, 12])
def test_in_order_shares_tasks_with_the_pool_and_keeps_their_order(total):
    """Results come in task order whoever solved them; while the result needed next is still
    in the pool this process solves later tasks itself, the pool is never more than
    ``in_flight`` deep, and closing the iterator early cancels what the pool has not
    started."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    here, depth, outstanding = [], [], []
    lock = threading.Lock()

    def pooled(i):
        time.sleep(0.03)
        with lock:
            outstanding.remove(i)
        return (i, "pool")

    with ThreadPoolExecutor(1) as pool:

        def submit(i):
            with lock:
                outstanding.append(i)
                depth.append(len(outstanding))
            return pool.submit(pooled, i)

        def solve_here(i):
            here.append(i)
            time.sleep(0.03)
            return (i, "here")

        out = list(spectra_mod._in_order(iter(range(12)), submit, solve_here, 2, 3, total))
    assert [r[0] for r in out] == list(range(12))
    assert here and len(here) < 12 and max(depth) <= 2
    assert all(r[1] == ("here" if r[0] in here else "pool") for r in out)

    first, rest = threading.Event(), threading.Event()
    with ThreadPoolExecutor(1) as pool:
        futures = []

        def submit_gated(i):
            futures.append(pool.submit((first if i == 0 else rest).wait))
            return futures[-1]

        it = spectra_mod._in_order(iter(range(6)), submit_gated, lambda i: ("here", i), 3, 2)
        threading.Timer(0.1, first.set).start()
        assert next(it) is True  # task 0, from the pool, after this process solved 3 and 4
        it.close()  # what the pool has not started is cancelled
        rest.set()
    assert len(futures) == 3 and futures[2].cancelled()  # task 1 may have started


def test_keep_freed_memory_stops_the_page_faults_of_a_repeated_allocation():
    """A process that keeps freed memory (spectra.heap) reuses freed blocks instead of mapping
    fresh pages for them each time. The pattern is a node solve's in small: three 9 MB arrays
    a round, freed together, which glibc's adaptive defaults trim from the heap every round
    (counted as minor page faults, in fresh processes so this one's allocator is left
    alone)."""
    import subprocess

    code = (
        "import resource, sys, numpy as np\n"
        "from hktex_engine.spectra.heap import keep_freed_memory\n"
        "kept = keep_freed_memory() if sys.argv[1] == 'keep' else None\n"
        "def round_():\n"
        "    blocks = [np.ones((2930, 384)) for _ in range(3)]\n"
        "    return sum(float(b[0, 0]) for b in blocks)\n"
        "round_()\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "for _ in range(10):\n"
        "    round_()\n"
        "print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n"
    )
    faults, took = {}, {}
    for mode in ("keep", "default"):
        run = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        took[mode], count = run.stdout.split()
        faults[mode] = int(count)
    if took["keep"] != "True":
        assert not sys.platform.startswith("linux"), "glibc's mallopt refused the settings"
        pytest.skip("no glibc mallopt here")
    assert faults["keep"] < 500 < 5000 < faults["default"]  # measured: 0 and 13,155


def test_a_grid_solved_with_the_compiled_solves_is_the_same(monkeypatch, mesh, tiny):
    from hktex_engine.spectra import triangular

    monkeypatch.setattr(triangular, "_preloaded", False)
    monkeypatch.setattr(spectra_mod, "PRELOAD_MIN_N", 0)
    _same_grid(compute_spectra(mesh, TINY), tiny)
    assert triangular._preloaded == triangular.HAVE_NUMBA


def test_workers_fork_only_from_a_single_threaded_process_without_torch(monkeypatch):
    """Fork saves each worker its imports, but a lock another thread holds at the fork
    stays held in the child, and torch's OpenMP can hang a forked child: spawn then."""
    monkeypatch.setitem(sys.modules, "torch", None)
    assert spectra_mod.worker_context().get_start_method() == "spawn"
    monkeypatch.delitem(sys.modules, "torch")
    monkeypatch.setattr(threading, "active_count", lambda: 3)
    assert spectra_mod.worker_context().get_start_method() == "spawn"
    monkeypatch.setattr(threading, "active_count", lambda: 1)
    expected = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    assert spectra_mod.worker_context().get_start_method() == expected


def test_node_solver_choice_follows_size(mesh):
    """The block solver from BLOCK_MIN_VERTICES_PER_PAIR vertices per wanted pair (measured
    faster there at the grid's tolerances and at machine precision alike), sliced ARPACK
    below; either way the same pairs, to the tolerance asked."""
    from hktex_engine.spectra import eigensolver
    from hktex_engine.spectra.eigensolver import GRID_TOL, eigs_node, estimate_lambda_k

    n = mesh.n_vertices
    k = n // 20  # 20 vertices per pair
    L, M, iso, exact, _ = _albo_problem(mesh, k, 0.3, 30.0)
    estimate = estimate_lambda_k(iso[-1], 30.0)
    for tol, rtol in ((GRID_TOL["float16"], 1e-6), (1e-10, 1e-8)):
        vals, _, method = eigs_node(L, M, k, estimate, tol)
        assert method.startswith("block")
        np.testing.assert_allclose(vals, exact, rtol=rtol, atol=1e-9)
    vals, _, method = eigs_node(L, M, n // (eigensolver.BLOCK_MIN_VERTICES_PER_PAIR - 1), estimate)
    assert not method.startswith("block")


def _albo_problem(mesh, k: int, theta: float, eta: float):
    """(L, M, lowest k isotropic eigenvalues) at one grid node, plus its exact lowest k pairs
    by a cold ARPACK solve: the reference the faster solvers are checked against."""
    from hktex_engine.geometry.operators import reference_tangent_field

    V, F = mesh.vertices, mesh.faces
    M = lumped_mass(V, F)
    iso, _ = eigs_cold(cotangent_stiffness(V, F), M, k)
    L = AlboAssembler(V, F, reference_tangent_field(V, F)).stiffness(theta, eta)
    exact, exact_vecs = eigs_cold(L, M, k)
    return L, M, iso, exact, exact_vecs


def test_mid_spectrum_shift_finds_the_lowest_pairs_or_falls_back(mesh):
    from hktex_engine.spectra.eigensolver import eigs_lowest, estimate_lambda_k

    L, M, iso, exact, _ = _albo_problem(mesh, 20, 0.3, 30.0)
    vals, vecs, method = eigs_lowest(L, M, 20, estimate_lambda_k(iso[-1], 30.0))
    assert method == "cold"
    np.testing.assert_allclose(vals, exact, rtol=1e-9, atol=1e-10)
    assert residuals(L, M, vals, vecs).max() < 1e-8
    # an estimate far too high puts the shift among higher eigenvalues: detected, redone
    vals, _, method = eigs_lowest(L, M, 20, 50 * exact[-1])
    assert method == "cold (shift below 0)"
    np.testing.assert_allclose(vals, exact, rtol=1e-9, atol=1e-10)


def test_spectrum_slicing_equals_one_solve(mesh):
    from hktex_engine.spectra.eigensolver import eigs_sliced, estimate_lambda_k

    L, M, iso, exact, exact_vecs = _albo_problem(mesh, 80, 1.2, 15.0)
    vals, vecs, method = eigs_sliced(L, M, 80, estimate_lambda_k(iso[-1], 15.0))
    assert method == "sliced"
    np.testing.assert_allclose(vals, exact, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(vecs.T @ (M[:, None] * vecs), np.eye(80), atol=1e-8)
    assert residuals(L, M, vals, vecs).max() < 1e-8
    # same span as the single solve (heat kernels equal)
    src = np.array([0, 300])
    h_a, h_b = _heat(vals, vecs, src, 0.05), _heat(exact, exact_vecs, src, 0.05)
    assert np.linalg.norm(h_a - h_b) < 1e-8 * np.linalg.norm(h_b)


@pytest.mark.parametrize("shift", ["below 0", "mid"])
def test_block_solver_equals_a_dense_solve_and_plain_eigsh(mesh, shift):
    """eigs_block against two independent computations: a dense generalised eigh (every
    eigenvalue) and scipy's plain eigsh shift-invert (heat kernels, i.e. the eigenspaces)."""
    import scipy.linalg as sla
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigsh

    from hktex_engine.spectra.eigensolver import eigs_block, eigs_block_lowest

    L, M, iso, _, _ = _albo_problem(mesh, 40, 0.7, 15.0)
    k = 40
    dense = sla.eigh(L.toarray(), np.diag(M), eigvals_only=True, subset_by_index=(0, k - 1))
    if shift == "mid":
        vals, vecs, method = eigs_block_lowest(L, M, k, dense[-1])
        assert method == "block"
    else:
        vals, vecs, info = eigs_block(L, M, k)
        assert info.method == "block"
    np.testing.assert_allclose(vals, dense, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(vecs.T @ (M[:, None] * vecs), np.eye(k), atol=1e-9)
    assert residuals(L, M, vals, vecs).max() < 1e-7
    w, U = eigsh(L, k=k, M=sp.diags(M), sigma=-1e-6)
    src = np.array([0, 300, 600])
    for t in (8.133e-4, 0.0625):
        h_a, h_b = _heat(vals, vecs, src, t), _heat(w, U, src, t)
        assert np.linalg.norm(h_a - h_b) < 1e-8 * np.linalg.norm(h_b)


@pytest.mark.parametrize("tol", [1e-6, 1e-7])
def test_grid_tolerance_solve_is_accurate_to_its_storage(mesh, tol):
    """At a grid's tolerance (GRID_TOL: 1e-6 for float16 storage, 1e-7 for float32) the
    block solver re-orthogonalises periodically; against a dense generalised eigh and plain
    eigsh its eigenvalues still agree to ~1e-12 of lambda_K, the basis is M-orthonormal and
    heat kernels differ by less than float32 rounding of the eigenvectors does."""
    import scipy.linalg as sla
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigsh

    from hktex_engine.spectra.eigensolver import GRID_TOL, eigs_block_lowest

    assert sorted(GRID_TOL.values()) == [1e-7, 1e-6]
    L, M, _, _, _ = _albo_problem(mesh, 40, 0.7, 15.0)
    k = 40
    dense = sla.eigh(L.toarray(), np.diag(M), eigvals_only=True, subset_by_index=(0, k - 1))
    vals, vecs, method = eigs_block_lowest(L, M, k, dense[-1], tol=tol)
    assert method == "block"
    np.testing.assert_allclose(vals, dense, rtol=0, atol=1e-10 * dense[-1])
    np.testing.assert_allclose(vecs.T @ (M[:, None] * vecs), np.eye(k), atol=1e-8)
    w, U = eigsh(L, k=k, M=sp.diags(M), sigma=-1e-6)
    src = np.array([0, 300, 600])
    for t in (8.133e-4, 0.0625):
        h_ref = _heat(w, U, src, t)
        h_f32 = _heat(w, U.astype(np.float32).astype(np.float64), src, t)
        budget = max(np.linalg.norm(h_f32 - h_ref), 1e-9 * np.linalg.norm(h_ref))
        assert np.linalg.norm(_heat(vals, vecs, src, t) - h_ref) < 10 * budget


def test_lost_orthogonality_is_detected_and_redone(mesh):
    """Re-orthogonalising too rarely (every fourth block, against the whole basis) lets
    Lanczos lose orthogonality; the final Gram check catches it and the solve is redone
    with full re-orthogonalisation, so the answer is right either way."""
    import scipy.linalg as sla

    from hktex_engine.spectra.eigensolver import eigs_block

    L, M, _, _, _ = _albo_problem(mesh, 40, 0.7, 15.0)
    k = 40
    dense = sla.eigh(L.toarray(), np.diag(M), eigvals_only=True, subset_by_index=(0, k - 1))
    methods = set()
    for every in (2, 4, 1000):
        vals, vecs, info = eigs_block(L, M, k, sigma=0.45 * dense[-1], tol=1e-6, full_every=every)
        methods.add(info.method)
        np.testing.assert_allclose(vals, dense, rtol=0, atol=1e-9 * dense[-1])
        np.testing.assert_allclose(vecs.T @ (M[:, None] * vecs), np.eye(k), atol=1e-8)
    assert "block (re-orthogonalised)" in methods  # the check did fire at least once


@pytest.mark.parametrize("dependent", ["no", "nearly", "exactly"])
def test_orthonormal_block_factors_the_block(dependent):
    """CholQR2 gives ``Z = Q R`` with ``Q`` orthonormal and ``R`` upper triangular, checked
    against numpy's Householder QR (same R up to column signs); a block with dependent columns
    (nearly: to round-off, through CholQR2; exactly, a Krylov breakdown: through the
    rank-revealing fallback) still gives an orthonormal ``Q`` and an exact ``Z = Q R``."""
    from hktex_engine.spectra.eigensolver import _orthonormal_block

    rng = np.random.default_rng(3)
    Z = rng.standard_normal((500, 8)) * np.logspace(0, -4, 8)[None, :]
    if dependent == "nearly":
        Z[:, 5] = Z[:, 1] - 2.0 * Z[:, 2]
    if dependent == "exactly":
        Z[:, 5] = Z[:, 1]
    Q, R = _orthonormal_block(Z.copy(), np.random.default_rng(0))
    np.testing.assert_allclose(Q.T @ Q, np.eye(8), atol=1e-12)
    np.testing.assert_allclose(Q @ R, Z, atol=1e-12 * np.abs(Z).max())
    if dependent == "exactly":  # the weak direction: a random vector with no weight in R
        assert (np.abs(R).max(axis=1) == 0.0).sum() == 1
    if dependent == "no":
        assert np.allclose(np.tril(R, -1), 0.0, atol=1e-12 * np.abs(R).max())
        _, ref = np.linalg.qr(Z)
        np.testing.assert_allclose(np.abs(R), np.abs(ref), rtol=1e-9, atol=1e-14)


def test_block_solver_restarts_and_falls_back(mesh):
    """A basis too small to converge without restarting (thick restarts) still gives the
    exact pairs; a mid shift from a far too high estimate is detected and redone below 0."""
    from hktex_engine.spectra.eigensolver import eigs_block, eigs_block_lowest

    L, M, _, exact, _ = _albo_problem(mesh, 24, 2.0, 60.0)
    # the first Ritz analysis before, at and after the basis fills (then it restarts first):
    # where the analyses fall changes the cost, never the pairs
    for start in (1.0, 2.25, 5.0):
        vals, vecs, info = eigs_block(L, M, 24, block=4, max_dim=40, check_start=start)
        assert info.method == "block"
        np.testing.assert_allclose(vals, exact, rtol=1e-9, atol=1e-10)
    vals, _, method = eigs_block_lowest(L, M, 24, 50 * exact[-1])
    assert method == "block (shift below 0)"
    np.testing.assert_allclose(vals, exact, rtol=1e-9, atol=1e-10)


def test_too_few_vertices_is_a_spectra_error(mesh):
    with pytest.raises(SpectraError):
        compute_spectra(mesh, SpectralConfig(angles=2, anisotropies=(1.0,), k=700, k_iso=9))


# ------------------------------------------------------------------ alignment


def _basis(mesh, k=12):
    L = cotangent_stiffness(mesh.vertices, mesh.faces)
    M = lumped_mass(mesh.vertices, mesh.faces)
    _, phi = eigs_cold(L, M, k)
    return phi, M


def test_alignment_recovers_permutation_signs_and_degenerate_rotation(mesh):
    phi, M = _basis(mesh)
    K = phi.shape[1]
    evals = np.array([0.0, 1.0, 2.0, 2.0, 3.0, 4.0, 4.0, 4.0, 5.0, 6.0, 7.0, 8.0])
    rng = np.random.default_rng(0)
    Q = np.eye(K)
    c, s = np.cos(0.7), np.sin(0.7)
    Q[np.ix_([2, 3], [2, 3])] = [[c, -s], [s, c]]  # rotation in the 2-dim eigenspace
    R3, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    Q[np.ix_([5, 6, 7], [5, 6, 7])] = R3  # and one in the 3-dim eigenspace
    perm = rng.permutation(K)
    signs = rng.choice([-1.0, 1.0], K)
    new = (phi @ Q)[:, perm] * signs
    new_vals = evals[perm]
    out, out_vals, info = align_basis(phi, new, new_vals, M, rotation="block")
    np.testing.assert_allclose(out, phi, atol=1e-10)
    np.testing.assert_allclose(out_vals, evals, atol=1e-12)
    assert info.n_clusters == 2 and info.min_overlap > 1 - 1e-10
    # without rotation the degenerate blocks cannot be recovered: the test can fail
    bad, _, _ = align_basis(phi, new, new_vals, M, rotation="none")
    assert np.abs(bad - phi).max() > 0.1


def test_block_alignment_keeps_eigenvectors_full_alignment_keeps_closeness(mesh, tiny):
    L = _operator(mesh, tiny, 1)
    M = tiny.mass
    ref = np.asarray(tiny.evecs[:, 0, :], dtype=np.float64)
    vals, vecs = eigs_cold(L, M, 16)
    b, bvals, _ = align_basis(ref, vecs, vals, M, rotation="block")
    f, fvals, _ = align_basis(ref, vecs, vals, M, rotation="full")
    assert residuals(L, M, bvals, b).max() < 1e-6
    assert residuals(L, M, fvals, f).max() > 1e-3  # full Procrustes mixes eigenvectors
    dist = lambda X: np.sqrt(np.sum(M[:, None] * (X - ref) ** 2))  # noqa: E731
    assert dist(f) <= dist(b) + 1e-12
    np.testing.assert_allclose(np.sort(fvals), np.sort(vals))  # eigenvalues only permuted


def test_eigen_clusters_groups_near_equal_values():
    groups = eigen_clusters(np.array([0.0, 1.0, 1.0000001, 3.0, 2.0, 2.0000001]))
    assert sorted(sorted(g.tolist()) for g in groups) == [[0], [1, 2], [3], [4, 5]]


# ------------------------------------------------------------------ interpolation continuity


def _heat(evals, evecs, src, t):
    """Truncated spectral heat kernels from the source vertex/vertices ``src``, (n, S)."""
    evecs = np.asarray(evecs, dtype=np.float64)
    src = np.atleast_1d(src)
    return evecs @ (np.exp(-t * evals)[:, None] * evecs[src].T)


def _continuity(tiny, evecs, t=0.05, sources=(0, 100, 300)):
    """Worst relative jump between neighbouring nodes and worst mid-cell deviation."""
    S = len(tiny.grid_eta)
    A = len(tiny.grid_theta)
    jumps, mids = [], []
    for a in range(A - 1):
        g00, g01, g10, g11 = a * S, a * S + 1, (a + 1) * S, (a + 1) * S + 1
        cell = [g00, g01, g10, g11]
        lam_mid = np.mean([tiny.evals[g] for g in cell], axis=0)
        phi_mid = np.mean([evecs[:, g, :] for g in cell], axis=0)
        for src in sources:
            hs = [_heat(tiny.evals[g], evecs[:, g, :], src, t) for g in cell]
            h_mid = _heat(lam_mid, phi_mid, src, t)
            norm = np.linalg.norm(hs[0])
            jumps.append(np.linalg.norm(hs[0] - hs[2]) / norm)
            mids.append(np.linalg.norm(h_mid - np.mean(hs, axis=0)) / norm)
    return max(jumps), max(mids)


@pytest.mark.parametrize("rotation,mid_bound", [("block", 0.25), ("full", 0.12)])
def test_interpolated_heat_kernel_varies_continuously(mesh, rotation, mid_bound):
    """On a 30-degree grid, a mid-cell kernel stays near the mean of its four node kernels.

    Measured (642-vertex ellipsoid, t = 0.2, k = 16): jump 0.17, mid-cell deviation 0.18
    (block) / 0.07 (full); with one node's signs scrambled 0.6, with random signs 1.0.
    """
    cfg = SpectralConfig(angles=7, anisotropies=(1.0, 3.0), k=16, k_iso=9, rotation=rotation)
    sp = compute_spectra(mesh, cfg)
    evecs = np.asarray(sp.evecs, dtype=np.float64)
    jump, mid = _continuity(sp, evecs, t=0.2)
    assert jump < 0.3
    assert mid < mid_bound
    # scrambling one node's signs (an unaligned grid) breaks it: the measure can fail
    bad = evecs.copy()
    bad[:, 1, 1::2] *= -1
    assert _continuity(sp, bad, t=0.2)[1] > 2.5 * mid


# ------------------------------------------------------------------ artefact


def test_write_then_mmap_read_back_is_identical(tiny, tmp_path):
    out = write_spectra(tiny, tmp_path / "sp")
    back = load_spectra(out)
    assert isinstance(back.evecs, np.memmap)
    for name in ("vertices", "faces", "mass", "evals", "evecs", "iso_evals", "iso_evecs"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), getattr(tiny, name))
    assert back.config == TINY and back.mesh_hash == tiny.mesh_hash
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["format"] == "hktex-spectra" and manifest["sizes"]["nodes"] == 6
    assert back.evecs.shape == (tiny.vertices.shape[0], 6, 16)
    assert not list(tmp_path.glob(".sp.tmp-*"))


@pytest.mark.parametrize("buffered", [True, False])
def test_streamed_compute_equals_in_memory_and_float16_option(
    mesh, tiny, tmp_path, monkeypatch, buffered
):
    """A written grid equals the in-memory one whether it was buffered in memory (small
    grids) or streamed through the scratch file (big ones; forced here)."""
    from hktex_engine.spectra import grid

    if not buffered:
        monkeypatch.setattr(grid, "MEMORY_SINK_MAX_BYTES", 0)
    streamed = compute_spectra(mesh, TINY, out_dir=tmp_path / "s")
    np.testing.assert_allclose(np.asarray(streamed.evecs), tiny.evecs, atol=1e-6)
    assert (tmp_path / "s" / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]
    half16 = SpectralConfig(**{**TINY.to_dict(), "evecs_dtype": "float16"})
    half = compute_spectra(mesh, half16)
    assert half.evecs.dtype == np.float16
    assert np.abs(half.evecs.astype(np.float64) - tiny.evecs).max() < 1e-2
    written = compute_spectra(mesh, half16, out_dir=tmp_path / "h")
    np.testing.assert_array_equal(np.asarray(written.evecs), half.evecs)


def test_corrupt_or_missing_files_raise_spectra_error(tiny, tmp_path):
    out = write_spectra(tiny, tmp_path / "sp")
    with pytest.raises(SpectraError):
        load_spectra(tmp_path / "nope")
    (out / "manifest.json").write_text("{not json")
    with pytest.raises(SpectraError):
        load_spectra(out)
    out = write_spectra(tiny, tmp_path / "sp2")
    (out / "evals.npy").unlink()
    with pytest.raises(SpectraError):
        load_spectra(out)
    out = write_spectra(tiny, tmp_path / "sp3")
    np.save(out / "mass.npy", np.zeros(3))
    with pytest.raises(SpectraError):
        load_spectra(out)
    out = write_spectra(tiny, tmp_path / "sp4")
    with pytest.raises(SpectraError):
        load_spectra(out, expect_mesh_hash="someone-else")


def test_crashed_write_leaves_no_half_directory(tiny, tmp_path, monkeypatch):
    calls = {"n": 0}
    real_save = np.save

    def failing_save(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise OSError("disk full")
        return real_save(*args, **kwargs)

    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(OSError):
        write_spectra(tiny, tmp_path / "sp")
    assert list(tmp_path.iterdir()) == []


class _StopAfter:
    def __init__(self, n: int) -> None:
        self.n, self.calls = n, 0

    def update(self, step, total, **metrics):
        self.calls += 1

    def should_stop(self) -> bool:
        return self.calls >= self.n


def test_cancelled_compute_publishes_nothing(mesh, tmp_path):
    with pytest.raises(Cancelled):
        compute_spectra(mesh, TINY, progress=_StopAfter(3), out_dir=tmp_path / "sp")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ cache


def test_cache_hit_does_not_recompute(mesh, tmp_path, monkeypatch):
    cache = SpectraCache(tmp_path)
    first = cache.get_or_compute(mesh, TINY)
    assert cache.computed == 1

    def boom(*a, **k):
        raise AssertionError("recomputed on a cache hit")

    monkeypatch.setattr(spectra_mod, "compute_spectra", boom)
    again = SpectraCache(tmp_path).get_or_compute(mesh, TINY)
    assert again.path == first.path
    np.testing.assert_array_equal(np.asarray(again.evecs), np.asarray(first.evecs))
    assert cache.lookup(mesh.content_hash, SpectralConfig(angles=2, anisotropies=(1.0,))) is None


def test_concurrent_requests_compute_once(mesh, tmp_path, monkeypatch):
    real = spectra_mod.compute_spectra
    count = {"n": 0}
    lock = threading.Lock()

    def counting(*a, **k):
        with lock:
            count["n"] += 1
        return real(*a, **k)

    monkeypatch.setattr(spectra_mod, "compute_spectra", counting)
    caches = [SpectraCache(tmp_path) for _ in range(3)]
    results: list = []
    threads = [
        threading.Thread(target=lambda c=c: results.append(c.get_or_compute(mesh, TINY)))
        for c in caches
    ]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert count["n"] == 1 and len(results) == 3
    assert len({Path(r.path) for r in results}) == 1


# ------------------------------------------------------------------ command line


def test_cli_writes_spectra_and_prints_json_summary(mesh, tmp_path, capsys):
    import trimesh

    from hktex_engine.cli import main

    path = tmp_path / "ellipsoid.obj"
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    out = tmp_path / "sp"
    args = ["spectra", str(path), "-o", str(out), "--angles", "2", "--anisotropies", "1,4"]
    rc = main([*args, "--k", "8", "--k-iso", "5", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip())
    assert summary["path"] == str(out) and summary["n_vertices"] == mesh.n_vertices
    assert summary["bytes"] > 0 and "total_s" in summary["timings"]
    assert load_spectra(out).evecs.shape == (mesh.n_vertices, 4, 8)
    assert main(["spectra", str(tmp_path / "missing.obj"), "-o", str(out)]) == 2
    assert main([*args[:-1], "4,1"]) == 2  # not ascending
    assert "error" in capsys.readouterr().err


def test_cli_counts_free_cores_from_before_its_imports(mesh, tmp_path, monkeypatch):
    """``hktex spectra --workers auto`` measures the cores others keep busy over a window
    that starts when the command line starts, before the parser imports the commands, so
    the window is time the command spends anyway and it need not sleep to fill it."""
    import trimesh

    import hktex_engine.cli as cli
    from hktex_engine.spectra import cores

    path = tmp_path / "ellipsoid.obj"
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    built, seen = [], []
    real_build = cli.build_parser

    def build():
        built.append(cores.time.monotonic())
        return real_build()

    def fake_auto_workers(nodes=None, since=None):
        seen.append(since)
        raise ValueError("stop here")  # the command's error path: nothing is computed

    monkeypatch.setattr(cli, "build_parser", build)
    monkeypatch.setattr(cores, "auto_workers", fake_auto_workers)
    assert cli.main(["spectra", str(path), "-o", str(tmp_path / "sp")]) == 2
    (since,) = seen
    assert since is not None and since.wall_s <= built[0]


def test_auto_workers_counts_the_cores_idle_now(monkeypatch):
    """Free cores are the affinity count minus the cores busy now (sampled from /proc/stat),
    falling back to the 1-minute load average where that cannot be read."""
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda _: {0, 1, 2, 3})
    monkeypatch.setattr(cores, "_busy_cores", lambda since=None: 0.3)
    assert cores.auto_workers() == 4
    assert cores.auto_workers(nodes=3) == 3
    monkeypatch.setattr(cores, "_busy_cores", lambda since=None: 2.6)
    assert cores.auto_workers() == 1
    monkeypatch.setattr(cores, "_busy_cores", lambda since=None: None)
    monkeypatch.setattr(cores.os, "getloadavg", lambda: (1.2, 0.0, 0.0))
    assert cores.auto_workers() == 3


def test_busy_cores_reads_proc_stat():
    busy = cores._busy_cores(0.05)
    if busy is None:
        pytest.skip("no /proc/stat here")
    assert 0.0 <= busy <= cores.os.cpu_count() + 1e-9


def test_busy_cores_does_not_count_this_process(monkeypatch):
    """Sampled over a window this process spent computing, its own core is not 'busy': the
    command samples from before its imports and mesh load, and must still see an idle
    machine as idle. Checked on synthetic counters: 2 cores, one busy all window long,
    and this process's own CPU time equal to that window."""
    a = cores.CpuSample(total=1000, idle=500, own_s=10.0, wall_s=100.0)
    b = cores.CpuSample(total=1200, idle=600, own_s=11.0, wall_s=101.0)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(cores, "cpu_sample", lambda: b)
    monkeypatch.setattr(cores.time, "monotonic", lambda: 101.0)
    assert cores._busy_cores(since=a) == pytest.approx(0.0)
    # another process using the other core as well: one core busy that is not ours
    b2 = cores.CpuSample(total=1200, idle=500, own_s=11.0, wall_s=101.0)
    monkeypatch.setattr(cores, "cpu_sample", lambda: b2)
    assert cores._busy_cores(since=a) == pytest.approx(1.0)


def test_in_process_solves_use_one_blas_thread(monkeypatch, mesh):
    """The block solver ran 2x slower with 2 OpenBLAS threads than with 1, so solves in
    this process run under a one-thread BLAS limit."""
    from threadpoolctl import threadpool_info

    seen = []

    def fake(L, mass, k, estimate, solver, tol):
        seen.append([p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"])
        return None, None, 0.0, "fake"

    from hktex_engine.spectra import eigensolver

    monkeypatch.setattr(eigensolver, "solve_node_timed", fake)  # imported from there per grid
    list(spectra_mod._cold_solutions(iter([(None, 4, 1.0, 1e-6)] * 2), mesh.vertices, 1))
    assert len(seen) == 2 and all(threads and max(threads) == 1 for threads in seen)


def test_grid_nodes_are_solved_to_their_storage_tolerance(tiny):
    from hktex_engine.spectra.eigensolver import GRID_TOL

    assert tiny.manifest["solver"]["tol"] == GRID_TOL[TINY.evecs_dtype] == 1e-7


def test_a_spectra_worker_imports_neither_torch_nor_the_mesh_loaders():
    """What a worker process unpickles (eigensolver.solve_node_timed) imports numpy and
    scipy only, so workers start in a fraction of a second."""
    import subprocess
    import sys

    code = (
        "import sys, hktex_engine.spectra.eigensolver as e; e.solve_node_timed; "
        "print(sorted(m for m in ('torch', 'trimesh', 'PIL') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
