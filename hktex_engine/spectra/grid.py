"""The spectra artefact (ALGORITHM.md sections 2-3, INTERFACES.md section 1).

:class:`Spectra` is the in-memory view of a spectra directory; big arrays are memory-mapped
``.npy`` files, vertex-major. Building, writing, reading and caching live in this module.
"""

from __future__ import annotations

import fcntl
import json
import multiprocessing
import os
import shutil
import sys
import tempfile
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from hktex_engine.config import SpectralConfig
from hktex_engine.errors import SpectraError
from hktex_engine.progress import NullProgress, Progress, check_cancel

if TYPE_CHECKING:
    import scipy.sparse as sp

    from hktex_engine.geometry.mesh import Mesh

# The solver stack (scipy, the mesh operators, the eigensolvers, the alignment) is imported by
# the functions that build a grid, not here: every query, render and service worker reads a
# spectra directory through this module, and those imports cost ~0.27 s of a one-off
# ``hktex query`` (measured with ``python -X importtime``).


@dataclass
class Spectra:
    """An aligned anisotropic eigenbasis grid plus the isotropic spectrum of one mesh.

    Node ``g = a * S + s`` (angle-major) for angle index ``a`` and anisotropy index ``s``.
    """

    vertices: np.ndarray  # (n, 3) normalised
    faces: np.ndarray  # (m, 3)
    mass: np.ndarray  # (n,)
    grid_theta: np.ndarray  # (A,) radians ascending, [0, pi]
    grid_eta: np.ndarray  # (S,) ascending
    evals: np.ndarray  # (A*S, K)
    evecs: np.ndarray  # (n, A*S, K) float16/32, possibly a read-only memmap
    iso_evals: np.ndarray  # (K_iso,)
    iso_evecs: np.ndarray  # (n, K_iso)
    face_frames: np.ndarray  # (m, 3) unit u_ref per face
    config: SpectralConfig
    mesh_hash: str
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    manifest: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def grid_s(self) -> np.ndarray:
        """Anisotropy grid coordinate s = ln(1 + eta)."""
        return np.log1p(self.grid_eta)

    @property
    def embedding(self) -> np.ndarray:
        """Biharmonic embedding per vertex, (n, K_iso - 1): psi_k / mu_k, constant mode dropped."""
        return self.iso_evecs[:, 1:] / self.iso_evals[1:][None, :]

    @property
    def config_hash(self) -> str:
        return self.config.key()


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------

FORMAT = "hktex-spectra"
FORMAT_VERSION = 1
#: Extra Ritz vectors carried along the warm-start chain (never stored): the subspace
#: iteration's slowest rate is about lambda_K / lambda_(K+p), so p buys convergence speed.
OVERSAMPLE_FRACTION = 0.25
_ARRAY_FILES = (
    "vertices",
    "faces",
    "mass",
    "grid_theta",
    "grid_eta",
    "evals",
    "evecs",
    "iso_evals",
    "iso_evecs",
    "face_frames",
)


def grid_nodes(config: SpectralConfig) -> tuple[np.ndarray, np.ndarray]:
    """Grid angles (radians, both ends of [0, pi]) and anisotropies of a config."""
    return np.linspace(0.0, np.pi, config.angles), np.asarray(config.anisotropies, dtype=float)


def _work_size(config: SpectralConfig, n: int) -> int:
    """Columns carried per node: K plus oversampling, bounded by what the mesh allows."""
    p = max(8, int(np.ceil(OVERSAMPLE_FRACTION * config.k)))
    return min(config.k + p, n - 2)


#: A written grid is buffered in memory, not streamed through a scratch file, when it is at most
#: this large in float32 (n x nodes x K x 4 bytes: ~10,000 vertices at K = 128; the buffer
#: holds it in the storage dtype, float16 by default, plus float32 copies of the nodes that
#: are copied to others).
#: Measured on blub (7,106 vertices, 178 MB, two fits on the other core): the scratch file's
#: writes took the parent 0.78 s during the solves and its transposing finalize 0.86 s after
#: them; the buffer 0.31 s and its write 0.29 s, both fsynced. Bigger grids keep streaming so
#: memory stays bounded.
MEMORY_SINK_MAX_BYTES = 256 << 20


def _write_vertex_major(path: Path, dtype: np.dtype, shape: tuple, chunks) -> None:
    """An .npy file of ``shape`` from vertex chunks (each already in ``dtype``), fsynced."""
    with open(path, "wb") as f:
        header = {"descr": dtype.str, "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(f, header)
        for chunk in chunks:
            f.write(memoryview(np.ascontiguousarray(chunk)))  # no bytes copy of the chunk
        f.flush()
        os.fsync(f.fileno())


class _MemorySink:
    """Keeps every node's aligned eigenvectors in one vertex-major buffer of the storage dtype.

    A node copied to another (theta = pi) is realigned from it and must not be rounded to
    float16 twice, so the nodes named in ``keep`` are also kept as float32 blocks, the
    precision the file sink's scratch keeps (:meth:`get` serves only those). Converting each
    node as it is stored, not the whole float32 buffer at the end, took the conversion off
    the command's serial tail (0.055 s of ``hktex spectra`` on spot) and halves the buffer's
    memory. ``finalize`` writes the
    buffer in bounded vertex chunks.
    """

    def __init__(self, n: int, nodes: int, k: int, dtype: str, keep: Iterable[int] = ()) -> None:
        self.buffer = np.empty((n, nodes, k), dtype=np.dtype(dtype))
        self.keep = set(keep)
        self.kept: dict[int, np.ndarray] = {}

    def put(self, g: int, block: np.ndarray) -> None:
        # through float32, as the file sink's scratch rounds it: both sinks store the same bits
        block32 = np.asarray(block, dtype=np.float32)
        self.buffer[:, g, :] = block32
        if g in self.keep:
            self.kept[g] = block32

    def get(self, g: int) -> np.ndarray:
        return np.asarray(self.kept[g], dtype=np.float64)

    @property
    def array(self) -> np.ndarray:
        return self.buffer

    def finalize(self, path: Path, chunk_bytes: int = 64 << 20) -> None:
        n, nodes, k = self.buffer.shape
        rows = max(1, chunk_bytes // (nodes * k * self.buffer.itemsize))
        chunks = (self.buffer[v0 : v0 + rows] for v0 in range(0, n, rows))
        _write_vertex_major(path, self.buffer.dtype, self.buffer.shape, chunks)

    def close(self) -> None:
        self.buffer = np.empty((0, 0, 0), dtype=self.buffer.dtype)
        self.kept.clear()


class _FileSink:
    """Streams node blocks to a node-major scratch file, transposed to vertex-major at the end.

    Nodes are computed one at a time but stored vertex-major; writing strided slices into a
    memory map would make every page of the (up to GBs) array resident, so blocks go to a
    scratch file with plain positional writes and are transposed in bounded vertex chunks.
    """

    def __init__(self, directory: Path, n: int, nodes: int, k: int, dtype: str) -> None:
        self.n, self.nodes, self.k, self.dtype = n, nodes, k, np.dtype(dtype)
        self.scratch = directory / "evecs.scratch"
        self._fd = os.open(self.scratch, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        self._block = n * k * 4

    def put(self, g: int, block: np.ndarray) -> None:
        os.pwrite(
            self._fd, np.ascontiguousarray(block, dtype=np.float32).tobytes(), g * self._block
        )

    def get(self, g: int) -> np.ndarray:
        raw = os.pread(self._fd, self._block, g * self._block)
        return np.frombuffer(raw, dtype=np.float32).reshape(self.n, self.k).astype(np.float64)

    def finalize(self, path: Path, chunk_bytes: int = 64 << 20) -> None:
        rows = max(1, chunk_bytes // (self.nodes * self.k * 4))
        _write_vertex_major(path, self.dtype, (self.n, self.nodes, self.k), self._chunks(rows))
        self.close()

    def _chunks(self, rows: int):
        for v0 in range(0, self.n, rows):
            v1 = min(self.n, v0 + rows)
            buf = np.empty((v1 - v0, self.nodes, self.k), dtype=self.dtype)
            for g in range(self.nodes):
                off = g * self._block + v0 * self.k * 4
                raw = os.pread(self._fd, (v1 - v0) * self.k * 4, off)
                buf[:, g, :] = np.frombuffer(raw, dtype=np.float32).reshape(v1 - v0, self.k)
            yield buf

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        self.scratch.unlink(missing_ok=True)


def _operator_key(theta: float, eta: float) -> tuple[float, float]:
    """Nodes with equal keys have the same operator: D depends on theta mod pi only, and
    eta = 0 is the isotropic operator for every angle."""
    if eta == 0.0:
        return (-1.0, 0.0)
    return (round(float(np.mod(theta, np.pi)), 12), float(eta))


_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def worker_context() -> multiprocessing.context.BaseContext:
    """How worker processes start: forked where that is safe, spawned elsewhere.

    A forked worker starts with every import done; a spawned one imports numpy and scipy
    afresh, ~0.25 s of a core each, measured as ~0.5 s of the 4.9 s ``hktex spectra`` takes
    on a 7,106-vertex mesh (blub, two workers). Forking is safe when this process runs a
    single Python thread (a lock another thread holds at the fork stays held in the child
    for ever) and has no OpenMP runtime loaded (torch's: a forked child that enters OpenMP
    can hang); OpenBLAS resets its own threads at a fork. The command line is that case; a
    service process (threads, torch) spawns.
    """
    if (
        "fork" in multiprocessing.get_all_start_methods()
        and threading.active_count() == 1
        and "torch" not in sys.modules
    ):
        return multiprocessing.get_context("fork")
    return multiprocessing.get_context("spawn")


#: A grid loads the compiled triangular solves (``triangular.preload``, ~0.25 s of a core from
#: numba's cache) from this many vertices on, below the single-factor threshold
#: ``triangular.COMPILED_MIN_N``, because a grid is ~49 node solves of ~40 block solves each.
#: Measured (``hktex spectra --workers 1``, one core): spot (2,930 vertices) level, bob
#: (5,344), blub and marble_bust_01 10-15 % faster; with two workers 4-12 %. Hence the
#: threshold between spot and bob (figures: docs/spectra.md, "Compiled solves loaded once
#: per grid").
PRELOAD_MIN_N = 4_000


def _start_worker(preload: bool) -> None:
    """A grid's worker process, before its first task: it ends with the grid, so its
    allocator keeps what it frees (``heap``); a spawned one loads the compiled solves."""
    from hktex_engine.spectra import triangular
    from hktex_engine.spectra.heap import keep_freed_memory

    keep_freed_memory()
    if preload:
        triangular.preload()


def _in_order(
    tasks: Iterator,
    submit: Callable[[Any], Future],
    solve_here: Callable[[Any], tuple],
    in_flight: int,
    ahead: int,
    total: int | None = None,
) -> Iterator[tuple]:
    """The results of ``tasks`` in order, solved by a pool (``submit``) and by this process.

    The pool is kept ``in_flight`` tasks deep. Whenever the result needed next is still in
    the pool, this process solves the next task not yet submitted itself (``solve_here``)
    instead of waiting, while at most ``ahead`` of its own results wait their turn (memory
    stays bounded by a few bases). So the solving processes are exactly the cores given: on
    two cores one worker and this process, not two workers beside a third process that aligns
    and stores, which time-sliced with them (measured: a node took 0.10 s in the pool against
    0.085 s alone, spot). With the number of tasks known (``total``), the pool is kept one
    deep for the last few, so this process is not left waiting on a queue it could have
    shared. Which process solves a task does not change its result.
    """
    queue: deque = deque()  # futures and own results, in task order
    source = iter(tasks)
    more = True
    taken = 0

    def next_task() -> Any:
        nonlocal more, taken
        task = next(source, None) if more else None
        more = task is not None
        taken += more
        return task

    def depth() -> int:
        left = None if total is None else total - taken
        return in_flight if left is None or left > 2 * in_flight else 1

    def top_up() -> None:
        while more and sum(isinstance(e, Future) for e in queue) < depth():
            task = next_task()
            if task is not None:
                queue.append(submit(task))

    try:
        top_up()
        while queue:
            head = queue[0]
            if isinstance(head, Future) and not head.done() and more:
                if sum(not isinstance(e, Future) for e in queue) < ahead:
                    task = next_task()
                    if task is not None:
                        queue.append(solve_here(task))
                    continue
            queue.popleft()
            yield head.result() if isinstance(head, Future) else head
            top_up()
    finally:
        for entry in queue:
            if isinstance(entry, Future):
                entry.cancel()


def _cold_solutions(
    tasks: Iterator[tuple[sp.csr_matrix, int, float, float]],
    mass: np.ndarray,
    workers: int,
    solver: str = "auto",
    total: int | None = None,
) -> Iterator[tuple]:
    """Independent solves of ``tasks`` (operator, pairs, lambda_k estimate, tolerance) in
    order, by ``workers`` processes: this one and, with ``workers > 1``, a pool of the
    others (:func:`_in_order`).

    The pool is kept two tasks a worker deep, so it stays busy while this process solves
    or aligns, and at most four results wait here, so memory stays bounded by a few bases
    however large the grid. Workers start as :func:`worker_context` says. From
    :data:`PRELOAD_MIN_N` vertices the compiled triangular solves are loaded first: here,
    before forked workers (which inherit them), and in each spawned worker.
    """
    from threadpoolctl import threadpool_limits

    from hktex_engine.spectra import triangular
    from hktex_engine.spectra.eigensolver import solve_node_timed

    def solve_here(task: tuple) -> tuple:
        L, k, estimate, tol = task
        return solve_node_timed(L, mass, k, estimate, solver, tol)

    preload = len(mass) >= PRELOAD_MIN_N
    if preload:
        triangular.preload()
    if workers <= 1:
        # one BLAS thread: the block solver's tall-skinny GEMMs ran 2x *slower* with
        # OpenBLAS's 2 threads than with 1 (20k torus, K = 64: 2.03 s against 1.04 s)
        with threadpool_limits(limits=1, user_api="blas"):
            yield from map(solve_here, tasks)
        return
    ctx = worker_context()
    forked = ctx.get_start_method() == "fork"
    # one BLAS thread per worker (the workers are the parallelism; spawned children read
    # these at start-up, forked ones inherit the limit set below), unless the caller chose
    # otherwise
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    for v in _THREAD_VARS:
        os.environ.setdefault(v, "1")
    try:
        # and one here, which solves too: OpenBLAS's spinning second thread took a core from
        # the workers (alignment measured 17 ms a node alone, 98 ms beside two workers, 35k)
        with (
            threadpool_limits(limits=1, user_api="blas"),
            ProcessPoolExecutor(
                max_workers=workers - 1,
                mp_context=ctx,
                initializer=_start_worker,
                initargs=(preload and not forked,),
            ) as pool,
        ):

            def submit(task: tuple) -> Future:
                L, k, estimate, tol = task
                return pool.submit(solve_node_timed, L, mass, k, estimate, solver, tol)

            yield from _in_order(tasks, submit, solve_here, 2 * (workers - 1), 4, total)
    finally:  # workers are spawned on demand, so the variables stay set for the pool's life
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)


def _node_plan(thetas: np.ndarray, etas: np.ndarray) -> list[tuple[int, float, float, str, int]]:
    """For each node in order: (g, theta, eta, source, holder) with source 'iso', 'copy' (of
    node ``holder``, the same operator) or 'solve'."""
    plan = []
    seen: dict[tuple[float, float], int] = {}
    S = len(etas)
    for a, theta in enumerate(thetas):
        for s, eta in enumerate(etas):
            g = a * S + s
            key = _operator_key(theta, eta)
            if key == (-1.0, 0.0):
                plan.append((g, float(theta), float(eta), "iso", -1))
            elif key in seen:
                plan.append((g, float(theta), float(eta), "copy", seen[key]))
            else:
                seen[key] = g
                plan.append((g, float(theta), float(eta), "solve", -1))
    return plan


def compute_spectra(
    mesh: Mesh,
    config: SpectralConfig | None = None,
    progress: Progress | None = None,
    out_dir: str | Path | None = None,
    solver: Literal["auto", "block", "cold", "warm"] = "auto",
    workers: int = 1,
) -> Spectra:
    """Compute the aligned ALBO grid and the isotropic spectrum of ``mesh``.

    Without ``out_dir`` everything stays in memory (fine for small meshes and tests). With
    ``out_dir`` eigenvectors stream to disk while they are computed, the directory is
    published atomically, and the memory-mapped result is returned: the way to go for big
    meshes, whose grid (n x 49 x 256 floats) can exceed the memory one wants to use.

    ``solver``: ``block`` solves each distinct operator independently by a block
    shift-invert Krylov-Schur iteration (:func:`eigs_block_lowest`; ARPACK's stopping rule,
    matrix-matrix work); ``cold`` by ARPACK shift-invert (:func:`eigs_sliced`); ``auto``
    (default) picks the one measured faster for the mesh size (:func:`eigs_node`). With any
    of them nodes are independent, so ``workers`` processes can share them. ``warm`` runs a shift-invert
    block iteration from the previous node's basis (sequential; measured slower at equal
    accuracy, see docs/spectra.md). Nodes whose operator equals an earlier node's
    (``theta = pi`` is ``theta = 0``; ``eta = 0`` is isotropic) are never solved twice.
    Alignment is always sequential along the chain of ALGORITHM.md section 3.
    """
    from hktex_engine.geometry.operators import (
        AlboAssembler,
        cotangent_stiffness,
        lumped_mass,
        reference_tangent_field,
    )
    from hktex_engine.spectra.alignment import align_basis
    from hktex_engine.spectra.eigensolver import (
        BLOCK_TOL,
        GRID_TOL,
        NODE_SOLVERS,
        SolveInfo,
        eigs_sliced,
        eigs_warm,
        estimate_lambda_k,
    )

    config = config or SpectralConfig()
    progress = progress or NullProgress()
    if solver not in ("auto", "block", "cold", "warm"):
        raise ValueError(f"unknown solver {solver!r}")
    t_start = time.perf_counter()
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    n = len(V)
    K = config.k
    need = max(K, config.k_iso)
    if need >= n - 2:
        raise SpectraError(
            f"mesh has {n} vertices; k={K}, k_iso={config.k_iso} need more than {need + 2}"
        )
    thetas, etas = grid_nodes(config)
    A, S = len(thetas), len(etas)
    G = A * S
    total = G + 1
    plan = _node_plan(thetas, etas)
    timings: dict[str, float] = {}
    staging: Path | None = None
    sink: _MemorySink | _FileSink
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    if staging is not None and n * G * K * 4 > MEMORY_SINK_MAX_BYTES:
        sink = _FileSink(staging, n, G, K, config.evecs_dtype)
    else:
        holders = {h for *_, src, h in plan if src == "copy"}
        sink = _MemorySink(n, G, K, config.evecs_dtype, keep=holders)
    cold_iter: Iterator[tuple] | None = None
    try:
        t0 = time.perf_counter()
        mass = lumped_mass(V, F)
        frames = reference_tangent_field(V, F, mode=config.tangent_field)
        assembler = AlboAssembler(V, F, frames)
        timings["operators_s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        p = _work_size(config, n) if solver == "warm" else K
        k_first = max(p, need)
        area = mass.sum()
        weyl = 4.0 * np.pi * k_first / area  # lambda_k ~ 4 pi k / area on a surface
        iso_L = cotangent_stiffness(V, F)
        # the isotropic spectrum is stored in float64 (the biharmonic embedding, the alignment
        # reference): solved to the solver's own tolerance; the nodes to their storage's
        tol = GRID_TOL[config.evecs_dtype]
        if solver in NODE_SOLVERS:
            # the isotropic solve is the first task of the same queue, so with workers the
            # first nodes start beside it instead of after it; their shifts therefore come
            # from Weyl's law (within 4 % of the solved lambda_64 on the shared meshes and a
            # 20k torus) rather than the solved isotropic lambda_K
            weyl_k = 4.0 * np.pi * K / area
            tasks = chain(
                [(iso_L, k_first, weyl, BLOCK_TOL)],
                (
                    (assembler.stiffness(th, et), K, estimate_lambda_k(weyl_k, et), tol)
                    for _, th, et, src, _ in plan
                    if src == "solve"
                ),
            )
            total_tasks = 1 + sum(src == "solve" for *_, src, _ in plan)
            cold_iter = _cold_solutions(tasks, mass, workers, solver, total_tasks)
            iso_vals, iso_vecs, _, _ = next(cold_iter)
        else:
            iso_vals, iso_vecs, _ = eigs_sliced(iso_L, mass, k_first, weyl)
        timings["isotropic_s"] = time.perf_counter() - t0
        progress.update(1, total, stage="isotropic")
        check_cancel(progress)

        evals = np.empty((G, K))
        solve_log: list[dict] = []
        # the aligned reference and the warm start of the next node in the chain
        iso_pair = (iso_vecs[:, :K], iso_vecs[:, :p])
        first_of_prev_angle: tuple[np.ndarray, np.ndarray] | None = None
        prev: tuple[np.ndarray, np.ndarray] | None = None
        t_solve = t_align = 0.0
        for g, theta, eta, source, holder in plan:
            s = g % S
            ref, start = (first_of_prev_angle or iso_pair) if s == 0 else prev
            t0 = time.perf_counter()
            if source == "iso":
                vals, vecs = iso_vals[:p], iso_vecs[:, :p]
                info = SolveInfo("isotropic", 0, 0.0)
            elif source == "copy":  # same operator as an earlier node: reuse, realign
                vals, vecs = evals[holder], sink.get(holder)
                info = SolveInfo(f"copy of node {holder}", 0, 0.0)
            elif cold_iter is not None:
                vals, vecs, seconds, method = next(cold_iter)
                info = SolveInfo(method, 0, 0.0, seconds)
            else:
                L = assembler.stiffness(theta, eta)
                vals, vecs, info = eigs_warm(L, mass, start, K)
            info.seconds = time.perf_counter() - t0
            t_solve += info.seconds
            t0 = time.perf_counter()
            aligned, aligned_vals, ainfo = align_basis(
                ref, vecs[:, :K], vals[:K], mass, rotation=config.rotation
            )
            t_align += time.perf_counter() - t0
            evals[g] = aligned_vals
            sink.put(g, aligned)
            prev = (aligned, vecs if vecs.shape[1] >= p else start)
            if s == 0:
                first_of_prev_angle = prev
            solve_log.append(
                {
                    "node": g,
                    "theta": theta,
                    "eta": eta,
                    "method": info.method,
                    "iterations": info.iterations,
                    "max_residual": info.max_residual,
                    "seconds": round(info.seconds, 4),
                    "alignment_mean_overlap": ainfo.mean_overlap,
                }
            )
            progress.update(g + 2, total, stage="grid", node=g)
            check_cancel(progress)
        timings["solve_s"] = t_solve
        timings["align_s"] = t_align

        iso_vals_k = iso_vals[: config.k_iso].copy()
        iso_vecs_k = np.ascontiguousarray(iso_vecs[:, : config.k_iso])
        manifest = _manifest(mesh, config, n, len(F), G, timings, solve_log)
        manifest["solver"] = {
            "method": solver,
            "tol": tol,
            "workers": workers,
            "iso_lambda_k": float(iso_vals[K - 1]),
            "nodes": solve_log,
        }
        spectra = Spectra(
            vertices=V,
            faces=F,
            mass=mass,
            grid_theta=thetas,
            grid_eta=etas,
            evals=evals,
            evecs=sink.array if staging is None else np.empty((0, G, K)),
            iso_evals=iso_vals_k,
            iso_evecs=iso_vecs_k,
            face_frames=frames,
            config=config,
            mesh_hash=mesh.content_hash,
            scale=float(mesh.scale),
            translation=np.asarray(mesh.translation, dtype=np.float64),
            manifest=manifest,
        )
        timings["total_s"] = time.perf_counter() - t_start
        if staging is None:
            return spectra
        t0 = time.perf_counter()
        _write_arrays(spectra, staging, skip=("evecs",))
        sink.finalize(staging / "evecs.npy")
        timings["write_s"] = time.perf_counter() - t0
        _write_manifest(spectra, staging)
        _publish(staging, out_dir)
        staging = None
        return load_spectra(out_dir)
    finally:
        if cold_iter is not None:
            cold_iter.close()
        sink.close()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)


def _manifest(
    mesh: Mesh, config: SpectralConfig, n: int, m: int, G: int, timings: dict, log: list
) -> dict:
    import scipy

    import hktex_engine

    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "mesh_hash": mesh.content_hash,
        "config": config.to_dict(),
        "config_hash": config.key(),
        "scale": float(mesh.scale),
        "translation": [float(x) for x in np.asarray(mesh.translation).ravel()],
        "sizes": {
            "n_vertices": n,
            "n_faces": m,
            "angles": config.angles,
            "anisotropies": len(config.anisotropies),
            "nodes": G,
            "k": config.k,
            "k_iso": config.k_iso,
        },
        "libraries": {
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "hktex": getattr(hktex_engine, "__version__", "0"),
        },
        "timings": timings,
        "solver": {"nodes": log},
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


# --------------------------------------------------------------------------------------------
# Writing, publishing, reading
# --------------------------------------------------------------------------------------------


def _arrays_of(spectra: Spectra) -> dict[str, np.ndarray]:
    dtype = spectra.config.evecs_dtype
    return {
        "vertices": np.asarray(spectra.vertices, dtype=np.float64),
        "faces": np.asarray(spectra.faces, dtype=np.int64),
        "mass": np.asarray(spectra.mass, dtype=np.float64),
        "grid_theta": np.asarray(spectra.grid_theta, dtype=np.float64),
        "grid_eta": np.asarray(spectra.grid_eta, dtype=np.float64),
        "evals": np.asarray(spectra.evals, dtype=np.float64),
        "evecs": np.asarray(spectra.evecs, dtype=dtype),
        "iso_evals": np.asarray(spectra.iso_evals, dtype=np.float64),
        "iso_evecs": np.asarray(spectra.iso_evecs, dtype=np.float64),
        "face_frames": np.asarray(spectra.face_frames, dtype=np.float64),
    }


def _write_arrays(spectra: Spectra, directory: Path, skip: tuple[str, ...] = ()) -> None:
    for name, arr in _arrays_of(spectra).items():
        if name in skip:
            continue
        with open(directory / f"{name}.npy", "wb") as f:
            np.save(f, np.ascontiguousarray(arr), allow_pickle=False)
            f.flush()
            os.fsync(f.fileno())


def _write_manifest(spectra: Spectra, directory: Path) -> None:
    """The manifest goes last: a directory without one is never a valid spectra."""
    manifest = dict(spectra.manifest)
    manifest["files"] = {name: (directory / f"{name}.npy").stat().st_size for name in _ARRAY_FILES}
    manifest["bytes"] = int(sum(manifest["files"].values()))
    tmp = directory / "manifest.json.tmp"
    with open(tmp, "w") as f:
        json.dump(manifest, f, indent=1, default=float)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, directory / "manifest.json")
    spectra.manifest = manifest


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _publish(staging: Path, out_dir: Path) -> None:
    """Move a complete staging directory to ``out_dir`` with one rename.

    An existing ``out_dir`` is first renamed aside (then deleted), so a reader sees either
    the old complete directory, nothing for an instant, or the new complete one; never a
    half-written one.
    """
    _fsync_dir(staging)
    old: Path | None = None
    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}")
        os.rename(out_dir, old)
    os.rename(staging, out_dir)
    _fsync_dir(out_dir.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_spectra(spectra: Spectra, out_dir: str | Path) -> Path:
    """Write ``spectra`` as a spectra directory (INTERFACES.md section 1), atomically."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        _write_arrays(spectra, staging)
        _write_manifest(spectra, staging)
        _publish(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    spectra.path = out_dir
    return out_dir


def load_spectra(
    path: str | Path,
    mmap: bool = True,
    expect_mesh_hash: str | None = None,
    expect_config: SpectralConfig | None = None,
) -> Spectra:
    """Read a spectra directory; big arrays memory-mapped read-only when ``mmap``.

    Raises :class:`SpectraError` when the directory or its manifest is missing or corrupt,
    an array is missing or has the wrong shape, or it belongs to another mesh/config.
    """
    path = Path(path)
    mpath = path / "manifest.json"
    if not mpath.is_file():
        raise SpectraError(f"{path} is not a spectra directory (no manifest.json)")
    try:
        manifest = json.loads(mpath.read_text())
        if manifest.get("format") != FORMAT:
            raise SpectraError(f"{mpath}: format is {manifest.get('format')!r}, not {FORMAT!r}")
        if int(manifest.get("version", -1)) > FORMAT_VERSION:
            raise SpectraError(f"{mpath}: version {manifest['version']} is newer than supported")
        config = SpectralConfig.from_dict(manifest["config"])
        sizes = manifest["sizes"]
        mesh_hash = str(manifest["mesh_hash"])
        scale = float(manifest["scale"])
        translation = np.asarray(manifest["translation"], dtype=np.float64)
    except SpectraError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise SpectraError(f"{mpath} is corrupt: {exc}") from exc
    if expect_mesh_hash is not None and mesh_hash != expect_mesh_hash:
        raise SpectraError(f"{path} was computed for another mesh ({mesh_hash[:12]}...)")
    if expect_config is not None and config.key() != expect_config.key():
        raise SpectraError(f"{path} was computed with another spectral config")
    n, m, G, K = sizes["n_vertices"], sizes["n_faces"], sizes["nodes"], sizes["k"]
    A, S, K_iso = sizes["angles"], sizes["anisotropies"], sizes["k_iso"]
    expected = {
        "vertices": (n, 3),
        "faces": (m, 3),
        "mass": (n,),
        "grid_theta": (A,),
        "grid_eta": (S,),
        "evals": (G, K),
        "evecs": (n, G, K),
        "iso_evals": (K_iso,),
        "iso_evecs": (n, K_iso),
        "face_frames": (m, 3),
    }
    arrays: dict[str, np.ndarray] = {}
    for name, shape in expected.items():
        fpath = path / f"{name}.npy"
        try:
            arr = np.load(fpath, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise SpectraError(f"{fpath} is missing or unreadable: {exc}") from exc
        if arr.shape != shape:
            raise SpectraError(f"{fpath} has shape {arr.shape}, expected {shape}")
        arrays[name] = arr
    return Spectra(
        **arrays,
        config=config,
        mesh_hash=mesh_hash,
        scale=scale,
        translation=translation,
        manifest=manifest,
        path=path,
    )


# --------------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------------


class SpectraCache:
    """Spectra directories under ``root`` keyed by (mesh content hash, spectral config).

    The same request never computes twice: a hit is read back memory-mapped; a miss takes an
    exclusive lock file for that key so concurrent processes asking for the same spectra
    wait for the first one instead of computing it again.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.computed = 0  # how many times this instance actually computed (for tests/stats)

    def key(self, mesh_hash: str, config: SpectralConfig) -> str:
        return f"{mesh_hash[:24]}-{config.key()[:16]}"

    def path_for(self, mesh_hash: str, config: SpectralConfig) -> Path:
        return self.root / self.key(mesh_hash, config)

    def lookup(self, mesh_hash: str, config: SpectralConfig) -> Spectra | None:
        """The cached spectra if present and readable, else None (never computes)."""
        path = self.path_for(mesh_hash, config)
        if not (path / "manifest.json").is_file():
            return None
        try:
            return load_spectra(path, expect_mesh_hash=mesh_hash, expect_config=config)
        except SpectraError:
            return None

    def get_or_compute(
        self, mesh: Mesh, config: SpectralConfig | None = None, progress: Progress | None = None
    ) -> Spectra:
        config = config or SpectralConfig()
        hit = self.lookup(mesh.content_hash, config)
        if hit is not None:
            return hit
        self.root.mkdir(parents=True, exist_ok=True)
        lock_path = self.root / f"{self.key(mesh.content_hash, config)}.lock"
        with open(lock_path, "a+") as lock:
            while True:  # poll so a waiting task can still be cancelled
                try:
                    fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    check_cancel(progress)
                    time.sleep(0.2)
            try:
                hit = self.lookup(mesh.content_hash, config)
                if hit is not None:
                    return hit
                out = self.path_for(mesh.content_hash, config)
                result = compute_spectra(mesh, config, progress, out_dir=out)
                self.computed += 1
                return result
            finally:
                fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
