"""Generalised sparse eigenproblems ``L phi = lambda M phi`` with a lumped (diagonal) M.

Solvers (ALGORITHM.md section 2; decisions in docs/spectra.md):

* :func:`eigs_node` (the per-node default): :func:`eigs_block_lowest` on big meshes,
  :func:`eigs_sliced` (ARPACK, two slices) on small ones, as measured.
* :func:`eigs_block`: block shift-invert Krylov-Schur, ARPACK's problem and stopping rule
  organised as matrix-matrix work (multi-right-hand-side solves, GEMM Gram-Schmidt).
* :func:`eigs_cold`: ARPACK shift-invert through ``scipy.sparse.linalg.eigsh``; exact to
  machine precision, no start needed; used for the first basis and as the naive reference.
* :func:`eigs_warm`: block shift-invert subspace iteration with Rayleigh-Ritz in the M inner
  product, started from a neighbouring operator's eigenvectors. Neighbouring grid operators
  differ little, so a few iterations reach the cold solver's accuracy at a fraction of its
  cost (ARPACK's cost is its orthogonalisation over ~2K Lanczos vectors, not the
  factorisation). SciPy has no such warm-started block solver, hence this one; LOBPCG from
  the same start was measured slower (docs/design STACK-NOTES).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dtrtri as _trtri
from scipy.sparse.linalg import eigsh

from hktex_engine.errors import SpectraError
from hktex_engine.spectra.triangular import FactorSolve, factor_compiled

#: Shift below the spectrum for shift-invert (meshes are normalised to a bounding box of side
#: 2, where lambda_1 is O(1)); negative so that L - sigma M is positive definite.
COLD_SIGMA = -1e-2


@dataclass
class SolveInfo:
    """What a solve cost and how accurate it is (max relative residual over the kept pairs)."""

    method: str
    iterations: int
    max_residual: float
    seconds: float = 0.0


def residuals(L: sp.spmatrix, mass: np.ndarray, evals: np.ndarray, vecs: np.ndarray) -> np.ndarray:
    """Relative residuals ``||L phi - lambda M phi||_{M^-1} / max(lambda, 1)`` per column.

    The M^-1 norm makes the measure independent of the mesh resolution (it is the L2 norm of
    the strong-form residual ``M^-1 L phi - lambda phi``).
    """
    R = L @ vecs - (mass[:, None] * vecs) * evals[None, :]
    return np.sqrt(np.einsum("ij,ij->j", R, R / mass[:, None])) / np.maximum(np.abs(evals), 1.0)


def eigs_cold(
    L: sp.spmatrix, mass: np.ndarray, k: int, sigma: float = COLD_SIGMA
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` eigenpairs nearest ``sigma``, ascending, M-orthonormal, by ARPACK
    shift-invert. With the default shift (below 0) these are the lowest ``k``."""
    n = L.shape[0]
    if k >= n - 1:
        raise SpectraError(f"cannot compute {k} eigenpairs of a mesh with {n} vertices")
    M = sp.diags(mass).tocsc()
    # A fixed start vector makes the result reproducible (ARPACK's default is random).
    v0 = np.random.default_rng(0).standard_normal(n)
    try:
        evals, vecs = eigsh(L.tocsc(), k=k, M=M, sigma=sigma, which="LM", v0=v0)
    except Exception as exc:  # ARPACK reports non-convergence as several exception types
        raise SpectraError(f"eigensolver failed: {exc}") from exc
    order = np.argsort(evals)
    return evals[order], canonical_signs(_m_normalise(vecs[:, order], mass))


#: Where the shift goes, as a fraction of an estimate of lambda_k (see eigs_lowest).
MID_SHIFT_FRACTION = 0.45


def estimate_lambda_k(iso_lambda_k: float, eta: float) -> float:
    """Weyl-law estimate of an ALBO's k-th eigenvalue from the isotropic one.

    Eigenvalue counts grow like ``area * lambda / (4 pi sqrt(det D))`` and ``det D = 1 /
    (1 + eta)``, so ``lambda_k ~ lambda_k_iso / sqrt(1 + eta)``. Measured on the shared
    meshes the true value is at or above this (e.g. 94 vs 37 at eta = 200 on
    marble_bust_01), which errs on the safe side for :func:`eigs_lowest`.
    """
    return float(iso_lambda_k) / np.sqrt(1.0 + float(eta))


def eigs_lowest(
    L: sp.spmatrix, mass: np.ndarray, k: int, lambda_k_estimate: float | None = None
) -> tuple[np.ndarray, np.ndarray, str]:
    """Lowest ``k`` eigenpairs, faster than :func:`eigs_cold` with a shift inside the range.

    Shift-invert Lanczos converges fastest for eigenvalues near the shift; with it at ~0.45
    of lambda_k instead of below 0 the whole wanted range is nearer to it, and ARPACK needed
    ~1.3-1.6x less time (marble_bust_01, K = 256). The k eigenvalues nearest a shift
    ``sigma > 0`` are the lowest k exactly when they include lambda_0 = 0 (the constants; the
    set nearest ``sigma`` is an interval around it), so that is checked, and a miss (an
    estimate far too high) falls back to the shift below 0. Returns (evals, evecs, method).
    """
    if lambda_k_estimate is not None and lambda_k_estimate > 0:
        sigma = MID_SHIFT_FRACTION * lambda_k_estimate
        vals, vecs = eigs_cold(L, mass, k, sigma=sigma)
        if abs(vals[0]) <= 1e-8 * max(abs(vals[-1]), 1.0):
            return vals, vecs, "cold"
    vals, vecs = eigs_cold(L, mass, k)
    return vals, vecs, "cold (shift below 0)"


#: Below this K a single ARPACK run is cheap enough that slicing does not pay.
SLICE_MIN_K = 64


def eigs_sliced(
    L: sp.spmatrix,
    mass: np.ndarray,
    k: int,
    lambda_k_estimate: float | None = None,
    tol: float | None = None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Lowest ``k`` eigenpairs from two half-size ARPACK runs (spectrum slicing).

    ARPACK runs to machine precision whatever ``tol`` (accepted for a common signature):
    its tolerance was measured not to save solves (docs/spectra.md).

    ARPACK's cost is dominated by orthogonalising ~2k Lanczos vectors (n k^2), so two runs
    of ~k/2 + overlap cost ~0.6 of one run of k (measured 1.5 s vs 2.5 s on bob, K = 256).
    Slice 1 is the lowest ``k1`` pairs (:func:`eigs_lowest`); slice 2 the pairs nearest a
    shift placed, by Weyl's linear growth of eigenvalues, so that its interval overlaps the
    top of slice 1 and reaches past lambda_k. Each slice holds every eigenvalue inside its
    interval, so cutting both at a gap strictly inside the overlap loses and duplicates
    nothing (pairs from either side of a gap are M-orthogonal). Whenever the overlap or the
    reach is not there, it falls back to one run of ``k``.
    """
    if k < SLICE_MIN_K:
        return eigs_lowest(L, mass, k, lambda_k_estimate)
    margin = max(4, k // 16)
    k1 = k // 2 + margin
    est1 = None if lambda_k_estimate is None else lambda_k_estimate * k1 / k
    w1, X1, method1 = eigs_lowest(L, mass, k1, est1)
    low = w1[k // 2 - margin]  # slice 2 must reach down to here...
    high = w1[-1] * (k + margin) / k1  # ...and up to about lambda_(k + margin)
    k2 = k - k // 2 + 2 * margin
    try:
        w2, X2 = eigs_cold(L, mass, k2, sigma=0.5 * (low + high))
    except SpectraError:  # e.g. the shift hit an eigenvalue exactly: do it the plain way
        w2 = X2 = None
    if w2 is None:
        vals, vecs, _ = eigs_lowest(L, mass, k, lambda_k_estimate)
        return vals, vecs, "cold (slice failed)"
    # cut at the widest gap between slice-1 eigenvalues strictly inside the overlap
    inside = np.nonzero((w1[:-1] > w2[0]) & (w1[1:] < w1[-1]))[0]
    if len(inside) >= 1 and w2[0] < w1[-1]:
        i = inside[np.argmax(w1[inside + 1] - w1[inside])]
        cut = 0.5 * (w1[i] + w1[i + 1])
        keep1, keep2 = w1 < cut, w2 > cut
        if keep1.sum() + keep2.sum() >= k and w2[-1] > w1[-1]:
            vals = np.r_[w1[keep1], w2[keep2]][:k]
            vecs = np.hstack([X1[:, keep1], X2[:, keep2]])[:, :k]
            return vals, vecs, "sliced" if method1 == "cold" else "sliced (shift below 0)"
    vals, vecs, _ = eigs_lowest(L, mass, k, lambda_k_estimate)
    return vals, vecs, "cold (slices did not meet)"


def _signs(vecs: np.ndarray) -> np.ndarray:
    """Per column, the sign of its largest-magnitude entry."""
    idx = np.argmax(np.abs(vecs), axis=0)
    return np.sign(vecs[idx, np.arange(vecs.shape[1])])


def canonical_signs(vecs: np.ndarray) -> np.ndarray:
    """Flip each column so its largest-magnitude entry is positive (a reproducible sign)."""
    return vecs * _signs(vecs)[None, :]


def _m_normalise(vecs: np.ndarray, mass: np.ndarray) -> np.ndarray:
    norms = np.sqrt(np.einsum("ij,ij->j", vecs, mass[:, None] * vecs))
    return vecs / norms[None, :]


def _rayleigh_ritz(
    L: sp.spmatrix, mass: np.ndarray, Z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ritz pairs of (L, M) on span(Z), ascending, M-orthonormal.

    Z is first reduced to an M-orthonormal basis through the eigen-decomposition of its Gram
    matrix, dropping directions that are numerically dependent (a block and its shift-invert
    image become nearly parallel as the iteration converges); the small problem is then
    solved as a generalised one so the residual non-orthogonality does not matter.
    """
    Z = Z / np.sqrt(np.einsum("ij,ij->j", Z, mass[:, None] * Z))[None, :]
    G = Z.T @ (mass[:, None] * Z)
    w, U = np.linalg.eigh(0.5 * (G + G.T))
    keep = w > w.max() * 1e-12
    Q = Z @ (U[:, keep] / np.sqrt(w[keep]))
    MQ = mass[:, None] * Q
    B = Q.T @ MQ
    A = Q.T @ (L @ Q)
    theta, C = sla.eigh(0.5 * (A + A.T), 0.5 * (B + B.T))
    return theta, Q @ C


#: SuperLU's pivoting for ``L - sigma M``: the symmetric fill-reducing order kept, a row
#: exchange only where a diagonal pivot is below a tenth of its column's largest entry.
#: Measured (35k / 20k vertices, sigma inside the wanted range, so indefinite): factor
#: 1.2-1.5x faster than partial pivoting, 2 % fewer non-zeros, backward error 1e-11 (against
#: 5e-13); without any pivoting (threshold 0) the backward error grew to 1e-9.
FACTOR_OPTIONS = {"diag_pivot_thresh": 0.1, "options": {"SymmetricMode": True}}


def _factor(L: sp.spmatrix, mass: np.ndarray, sigma: float) -> FactorSolve:
    """``L - sigma M`` factored for its solves (``triangular.factor_compiled``)."""
    try:
        return factor_compiled((L - sigma * sp.diags(mass)).tocsc(), FACTOR_OPTIONS)
    except RuntimeError as exc:  # exactly singular at this shift
        raise SpectraError(f"factorisation failed at shift {sigma}: {exc}") from exc


def eigs_warm(
    L: sp.spmatrix,
    mass: np.ndarray,
    start: np.ndarray,
    k: int,
    tol: float = 1e-6,
    max_iter: int = 25,
    krylov: bool = True,
) -> tuple[np.ndarray, np.ndarray, SolveInfo]:
    """Lowest ``k`` eigenpairs from a start block (n, p >= k) by shift-invert block iteration.

    Each iteration applies ``S = (L - sigma M)^-1 M`` to the block ``X`` (one sparse LU shared
    by the iterations) and does Rayleigh-Ritz on ``span(X, S X)`` (``krylov``; a two-block
    Krylov space, markedly faster per iteration than plain subspace iteration on ``S X``).
    The shift starts just below 0, where ``L - sigma M`` is definite and the iteration is
    safe from any start. Once the Ritz values settle it moves to half the k-th Ritz value:
    the wanted pairs are then all closer to it than the unwanted ones (which is true only
    while the k-th Ritz value is below lambda_(p+1), hence the wait), which speeds up the
    slowest, top pairs. Stops when every kept pair's relative residual is below ``tol``;
    falls back to :func:`eigs_cold` if it does not converge. Returns all ``p`` Ritz pairs
    (the extra ones are a better start for the next node).
    """
    n, p = start.shape
    if p < k:
        raise ValueError("start block must have at least k columns")
    theta, X = _rayleigh_ritz(L, mass, start)
    sigma = COLD_SIGMA
    lu = _factor(L, mass, sigma)
    res = residuals(L, mass, theta[:k], X[:, :k])
    it = 0
    moved = False
    while res.max() > tol and it < max_iter:
        Z = lu.solve(mass[:, None] * X)
        previous = theta[:k]
        theta, X = _rayleigh_ritz(L, mass, np.hstack([X, Z]) if krylov else Z)
        theta, X = theta[:p], X[:, :p]
        res = residuals(L, mass, theta[:k], X[:, :k])
        it += 1
        settled = np.abs(theta[:k] - previous).max() < 1e-2 * theta[k - 1]
        if not moved and settled and res.max() > tol:
            sigma, moved = 0.5 * theta[k - 1], True
            lu = _factor(L, mass, sigma)
    if res.max() > tol:
        vals, vecs = eigs_cold(L, mass, p)
        return (
            vals,
            vecs,
            SolveInfo(
                "cold (warm did not converge)",
                it,
                float(residuals(L, mass, vals[:k], vecs[:, :k]).max()),
            ),
        )
    return theta, X, SolveInfo("warm", it, float(res.max()))


# --------------------------------------------------------------------------------------------
# Block shift-invert Krylov-Schur (the default per-node solver; docs/spectra.md, Decisions)
# --------------------------------------------------------------------------------------------

#: Stopping rule of :func:`eigs_block`: ``||S x - nu x|| <= BLOCK_TOL * nu`` for each wanted
#: Ritz pair of the shift-invert operator S (ARPACK's own criterion, with its ``tol``).
BLOCK_TOL = 1e-10

#: The tolerance a spectra grid solves its nodes to, by the storage dtype of its eigenvectors:
#: the solver's error stays well below what storing the basis costs anyway. Measured on a
#: 20,000-vertex torus, K = 64, eta 1 / 15 / 200, heat kernels (t = 8.1e-4 and 0.0625, 16
#: sources) against plain eigsh: float32 rounding of the eigenvectors moves them by 3.6e-8,
#: float16 by 2.9e-4; tol 1e-7 leaves 2e-9 to 3e-9 and tol 1e-6 2e-7 to 2.5e-7, with
#: eigenvalues within 5e-13 of lambda_K either way, in 10-20 % fewer iterations than 1e-10.
GRID_TOL = {"float32": 1e-7, "float16": 1e-6}

#: :func:`eigs_block` at a tolerance of :data:`PERIODIC_REORTH_MIN_TOL` or looser (the grid's
#: nodes) re-orthogonalises each new block against the whole basis only every
#: ``FULL_REORTH_EVERY`` blocks (and on both blocks after a restart); in between, twice
#: against the two newest blocks (the block Lanczos recurrence). Reading the whole basis is
#: memory-bound and was ~35 % of a solve. Measured on a 20k torus, K = 64, eta 1 / 15 / 200:
#: every second block keeps the basis orthogonal to ~5e-11 and saves 15-25 % of a solve;
#: every third block lost orthogonality entirely (ghost copies of converged pairs). At
#: machine-precision tolerances the residuals came out 4-5x worse and a tiny restarted basis
#: failed to converge, hence full re-orthogonalisation there. A periodic solve's final basis
#: is checked and redone with full re-orthogonalisation if it lost orthogonality.
FULL_REORTH_EVERY = 2
PERIODIC_REORTH_MIN_TOL = 1e-8

#: Largest ``|X^T M X - I|`` entry accepted from the periodic re-orthogonalisation.
ORTHOGONALITY_TOL = 1e-8


#: :func:`_orthonormal_block` treats a block as numerically dependent when a squared Cholesky
#: pivot of its Gram matrix falls below this fraction of the largest diagonal entry (or the
#: factorisation fails). It replaced a test on the smallest eigenvalue (1e-24 of the largest);
#: a squared pivot is never below the smallest eigenvalue, hence a threshold 1e4 looser. A
#: block dependent only to round-off passes either test and is made orthonormal by CholQR2's
#: second pass (tested).
DEPENDENT_PIVOT = 1e-20


def _orthonormal_fallback(
    Z: np.ndarray, R: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``Z = Q R'`` for a numerically dependent block, and ``R' R``: a rank-revealing QR
    (column pivoting puts the weak directions last, their rows of R at round-off), those
    columns of Q replaced by random directions orthogonal to the rest, their rows of R zeroed.
    R' is then upper triangular only up to the pivoting, which the block recurrence allows
    (its coupling blocks need not be triangular)."""
    Q, Rp, piv = sla.qr(Z, mode="economic", pivoting=True)
    diag = np.abs(np.diag(Rp))
    weak = diag <= 1e-12 * max(diag.max(), 1e-300)
    strong = Q[:, ~weak]
    fill = rng.standard_normal((Z.shape[0], int(weak.sum())))
    for _ in range(2):  # twice: one projection leaves round-off along the strong part
        fill -= strong @ (strong.T @ fill)
        fill, _ = np.linalg.qr(fill)
    Q[:, weak] = fill
    Rp[weak, :] = 0.0
    unpivoted = np.empty_like(Rp)
    unpivoted[:, piv] = Rp  # Z[:, piv] = Q Rp
    return Q, unpivoted @ R


def _orthonormal_block(Z: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``Z = Q R`` with orthonormal columns by Cholesky QR, twice (CholQR2, BLAS-3).

    A numerically dependent block (a Krylov breakdown, rare) goes to
    :func:`_orthonormal_fallback`: its weak directions are replaced by random ones with no
    weight in R, which keeps ``Z = Q R`` exact. The 8 x 8 factors go straight to LAPACK
    (``potrf``, ``trtri``): the block solver calls this ~40 times a node, and numpy's
    wrappers (``cholesky``, ``inv``, their type checks) cost more than the arithmetic at
    this size (measured on 2,930 x 8: 0.129 ms a call through numpy, 0.082 ms direct).
    """
    R = np.eye(Z.shape[1])
    for _ in range(2):
        G = Z.T @ Z
        scale = max(G.diagonal().max(), 1e-300)
        # G = C C^T (lower), Z = (Z C^-T) C^T; potrf reads the lower triangle only
        C, info = _potrf(G, lower=1, clean=1)
        if info != 0 or C.diagonal().min() ** 2 <= DEPENDENT_PIVOT * scale:
            return _orthonormal_fallback(Z, R, rng)
        # C^-T as a small matrix, then one GEMM: a triangular solve on the transposed tall
        # block cost 1.8 ms a call at 35k vertices, ~5 % of a node
        Cinv, _ = _trtri(C, lower=1)
        Z = Z @ Cinv.T
        R = C.T @ R
    return Z, R


#: :func:`eigs_block`'s first Ritz analysis comes at ``CHECK_START * k`` columns. Each analysis
#: is a dense eigh of the projected matrix (~300 x 300 at K = 128), a cost that does not
#: shrink with the mesh. Measured 2026-12-03 (one core, tol 1e-6, nodes eta 1 / 30 / 200, a
#: solve converged after 38-42 blocks of 8 at K = 128, i.e. 2.4-2.6 K columns, and 23-26
#: blocks, 2.9-3.3 K, at K = 64, on spot, bob, marble_bust_01 and a 20k torus alike):
#: starting at 2.25 K instead of 1.5 K left every solve's block count unchanged and cut a
#: node's time by 15-37 % at K = 128 (spot 0.119 -> 0.085 s, bob 0.287 -> 0.182, marble
#: 0.310 -> 0.262, torus 0.978 -> 0.632) and 10-18 % at K = 64. Since the later analyses
#: come where convergence is predicted (:data:`CONVERGENCE_RATE`), a first one at 2.4 K
#: converges at once more often: 1.3 analyses a node instead of 2.0 for 0.2 more blocks
#: (42 nodes' logs of spot and bob replayed), measured 2-3 % faster on spot (paired, one
#: core: 0.0852 -> 0.0835 s) and 0.6 % on blub (2026-12-07).
CHECK_START = 2.4

#: After a Ritz analysis that has not converged, the next comes where the slowest wanted
#: pair's residual is predicted to pass: its ratio ``r`` to the tolerance falls by at least
#: this factor a block near convergence (measured 3-4.7 on spot and bob, K = 128, every eta,
#: tol 1e-6), so the next analysis is ``ceil(log r / log CONVERGENCE_RATE)`` blocks on, at
#: most :data:`MAX_CHECK_JUMP`. An analysis (a dense eigh, ~7 ms at K = 128) costs about three
#: blocks on a small mesh; a fixed step of k/8 columns took 2.9 analyses a node where the
#: prediction takes 2.0, for 0.4 fewer blocks (the same 42 nodes' logs replayed).
CONVERGENCE_RATE = 3.0
MAX_CHECK_JUMP = 8


def _blocks_to_converge(ratio: float) -> int:
    """Blocks until a residual ``ratio`` times the tolerance is predicted to pass it."""
    if not np.isfinite(ratio):
        return MAX_CHECK_JUMP
    return int(min(MAX_CHECK_JUMP, max(1, np.ceil(np.log(ratio) / np.log(CONVERGENCE_RATE)))))


def eigs_block(
    L: sp.spmatrix,
    mass: np.ndarray,
    k: int,
    sigma: float = COLD_SIGMA,
    tol: float = BLOCK_TOL,
    block: int | None = None,
    max_dim: int | None = None,
    seed: int = 0,
    check_start: float = CHECK_START,
    full_every: int | None = None,
    measure: bool = True,
) -> tuple[np.ndarray, np.ndarray, SolveInfo]:
    """Lowest ``k`` eigenpairs by a block shift-invert Krylov-Schur iteration.

    Same problem and same stopping rule as ARPACK's shift-invert mode (``eigsh(L, k, M,
    sigma)``: Ritz pairs of ``S = (L - sigma M)^-1 M`` whose residual ``||S x - nu x||`` is
    below ``tol * nu``), organised around matrix-matrix work: ``S`` is applied to blocks of
    ``block`` vectors (one sparse LU, multi-right-hand-side solves), the basis is
    re-orthogonalised by two block Gram-Schmidt passes (GEMM), the Ritz analysis uses the
    projected matrix the orthogonalisation produces, and the residual norms come for free
    from the last coupling block. ARPACK does the same work one vector at a time (BLAS-2),
    which is where its time goes. When the basis reaches ``max_dim`` columns it is restarted
    thickly from its best ``k + block`` Ritz vectors (Krylov-Schur). Works in the symmetric
    form ``y = M^(1/2) x`` so every inner product is a plain one. ``full_every``: how often a
    block is re-orthogonalised against the whole basis (1: every block); None chooses by
    ``tol`` (:data:`FULL_REORTH_EVERY`). ``check_start``: the first Ritz analysis at this many
    times ``k`` columns (:data:`CHECK_START`). ``measure``: compute the pairs' residuals for
    the returned info (an ``L X`` product: 18 ms of a 0.2 s blub node in a profile; NaN
    without).
    Returns the pairs ascending, M-orthonormal, with canonical signs.
    """
    n = L.shape[0]
    if k >= n - 1:
        raise SpectraError(f"cannot compute {k} eigenpairs of a mesh with {n} vertices")
    t0 = time.perf_counter()
    b = int(block or 8)
    dmax = int(max_dim or max(3 * k, k + 4 * b))
    dmax = min(dmax, n - 1)
    keep = min(k + b, dmax - 2 * b)
    if keep < k:  # the basis cannot hold the wanted pairs plus two blocks: plain ARPACK
        vals, vecs = eigs_cold(L, mass, k, sigma=sigma)
        res = float(residuals(L, mass, vals, vecs).max())
        return vals, vecs, SolveInfo("cold (basis too small)", 0, res)
    if full_every is None:
        full_every = FULL_REORTH_EVERY if tol >= PERIODIC_REORTH_MIN_TOL else 1
    rng = np.random.default_rng(seed)
    lu = _factor(L, mass, sigma)  # SuperLU's factor, compiled solves where loaded
    sq = np.sqrt(mass)

    def apply_s(Y: np.ndarray) -> np.ndarray:  # M^(1/2) (L - sigma M)^-1 M^(1/2) Y
        return sq[:, None] * lu.solve(sq[:, None] * Y)

    Q = np.empty((n, dmax), order="F")
    T = np.zeros((dmax, dmax))
    Q[:, :b], _ = _orthonormal_block(rng.standard_normal((n, b)), rng)
    # Ritz analyses (a d x d eigh each) only once the basis can plausibly hold k converged
    # pairs (CHECK_START), then where the last one predicts convergence (CONVERGENCE_RATE)
    next_check = min(dmax - b, b * int(np.ceil(check_start * k / b)))
    cur = 0  # first column of the block S is applied to next
    d = b  # columns in the basis
    it = 0
    converged = False
    fresh = 0  # blocks added since the (re)start
    nu = C = None
    while True:
        it += 1
        Z = apply_s(Q[:, cur : cur + b])
        # Gram-Schmidt: first against the newest columns (the three-term recurrence holds
        # most of S Q_cur), then once against the whole basis (full re-orthogonalisation):
        # two passes over the basis instead of four for classical Gram-Schmidt twice
        # (periodically: see FULL_REORTH_EVERY; the block right after a restart couples to
        # every kept Ritz vector, so it is always taken against the whole basis)
        lo = 0 if fresh == 0 else max(0, cur - b)
        H = np.zeros((d, b))
        H[lo:d] = Q[:, lo:d].T @ Z
        Z -= Q[:, lo:d] @ H[lo:d]
        lo2 = 0 if fresh % full_every == 0 else lo
        H2 = Q[:, lo2:d].T @ Z
        Z -= Q[:, lo2:d] @ H2
        H[lo2:d] += H2
        fresh += 1
        T[:d, cur : cur + b] = H
        T[cur : cur + b, :d] = H.T
        Znew, R = _orthonormal_block(Z, rng)
        done = d  # columns whose S-image is in the basis: T[:done, :done] is complete
        full = d + b > dmax
        if not full and done < next_check:
            Q[:, d : d + b] = Znew
            T[d : d + b, cur : cur + b] = R
            T[cur : cur + b, d : d + b] = R.T
            cur, d = d, d + b
            continue
        # Ritz analysis on the complete part; residual of pair i is ||R C[last block, i]||
        nu, C = np.linalg.eigh(0.5 * (T[:done, :done] + T[:done, :done].T))
        # the pairs nearest the shift first (largest |nu|): the lowest ones when sigma < 0,
        # an interval around sigma otherwise (the caller checks it reaches down to 0)
        order = np.argsort(-np.abs(nu), kind="stable")
        nu, C = nu[order], C[:, order]
        resid = np.linalg.norm(R @ C[done - b : done, :], axis=0)
        ratio = float(np.max(resid[:k] / (tol * np.abs(nu[:k])))) if done >= k else np.inf
        if ratio <= 1.0:
            converged = True
            break
        jump = _blocks_to_converge(ratio)
        next_check = done + b * jump
        if it > 10 * dmax // b:
            break
        if not full:
            Q[:, d : d + b] = Znew
            T[d : d + b, cur : cur + b] = R
            T[cur : cur + b, d : d + b] = R.T
            cur, d = d, d + b
            continue
        # thick restart: the best `keep` Ritz vectors, then the newest block
        Y = Q[:, :done] @ C[:, :keep]
        coupling = R @ C[done - b : done, :keep]
        Q[:, :keep] = Y
        Q[:, keep : keep + b] = Znew
        T[:] = 0.0
        T[:keep, :keep] = np.diag(nu[:keep])
        T[keep : keep + b, :keep] = coupling
        T[:keep, keep : keep + b] = coupling.T
        cur, d = keep, keep + b
        next_check = keep + b * jump
        fresh = 0
    vals = 1.0 / nu[:k] + sigma
    order = np.argsort(vals)
    vals = vals[order]
    # the Ritz vectors ascending, column-major: (C^T Q^T)^T is the same GEMM as Q C, and
    # every later step reads or gathers whole columns (numpy's argmax over the rows of a
    # row-major 2,930 x 128 block took 4.4 ms, a column-major one 0.7 ms)
    Y = (C[:, order].T @ Q[:, :done].T).T
    gram = None
    if converged and full_every > 1:
        # lost orthogonality shows as ghost copies of converged pairs (small residuals, a
        # singular Gram matrix): redo such a solve the safe way
        gram = Y.T @ Y
        if np.abs(gram - np.eye(k)).max() > ORTHOGONALITY_TOL:
            vals, X, info = eigs_block(
                L, mass, k, sigma, tol, block, max_dim, seed, check_start, 1, measure
            )
            info.method += " (re-orthogonalised)"
            return vals, X, info
    # X = M^(-1/2) Y, M-normalised (||x||_M = ||y||) with canonical signs, in one pass
    norms = np.sqrt(gram.diagonal() if gram is not None else np.einsum("ij,ij->j", Y, Y))
    X = Y * (1.0 / sq)[:, None]
    X *= (_signs(X) / norms)[None, :]
    res = float(residuals(L, mass, vals, X).max()) if measure else float("nan")
    info = SolveInfo("block" if converged else "block (not converged)", it, res)
    info.seconds = time.perf_counter() - t0
    if not converged:
        vals, X = eigs_cold(L, mass, k, sigma=sigma)
        info = SolveInfo(
            "cold (block did not converge)", it, float(residuals(L, mass, vals, X).max())
        )
    return vals, X, info


def eigs_block_lowest(
    L: sp.spmatrix,
    mass: np.ndarray,
    k: int,
    lambda_k_estimate: float | None = None,
    tol: float = BLOCK_TOL,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Lowest ``k`` eigenpairs by :func:`eigs_block` with the shift inside the wanted range.

    As for :func:`eigs_lowest`: with ``sigma`` at ``MID_SHIFT_FRACTION`` of an estimate of
    lambda_k the wanted pairs are nearer the shift and the iteration needs fewer solves
    (measured ~336 instead of ~456 at 10k vertices, K = 128). The k pairs nearest a shift
    ``sigma > 0`` are the lowest k exactly when they include lambda_0 = 0, which is checked;
    a miss (estimate far too high) is solved again with the shift below 0. Returns (evals,
    evecs, method).
    """
    if lambda_k_estimate is not None and lambda_k_estimate > 0:
        try:
            sigma = MID_SHIFT_FRACTION * lambda_k_estimate
            vals, vecs, info = eigs_block(L, mass, k, sigma=sigma, tol=tol, measure=False)
        except SpectraError:  # the shift hit an eigenvalue exactly
            vals = None
        if vals is not None and abs(vals[0]) <= 1e-8 * max(abs(vals[-1]), 1.0):
            return vals, vecs, info.method
    vals, vecs, info = eigs_block(L, mass, k, tol=tol, measure=False)
    return vals, vecs, info.method + " (shift below 0)"


#: :func:`eigs_node` uses the block solver from this many vertices per wanted pair on. History:
#: 40 at machine-precision tolerances and 16 at the grid's, measured 2026-12-03 (spot, K =
#: 128, tol 1e-10: block 0.176 s against sliced ARPACK 0.181; K = 256 at tol 1e-6: 0.428
#: against 0.381). Re-measured 2026-12-07 once the block solver's analyses came where
#: convergence is predicted (one core, spot, best of 2-3): tol 1e-10, the isotropic operator,
#: K = 64 / 128 / 192 (46 / 23 / 15 per pair): block 0.059 / 0.114 / 0.155 s against sliced
#: 0.102 / 0.261 / 0.480; K = 256 (11 per pair), anisotropic nodes eta 30 / 200: block
#: 0.23-0.34 s against sliced 0.74-0.93 at tol 1e-6 and 1e-10 alike, and level (0.65-0.92
#: against 0.79-0.89) where the mid shift missed lambda_0 and the block solve was redone below
#: 0. So one threshold, below the smallest ratio measured.
BLOCK_MIN_VERTICES_PER_PAIR = 10


def eigs_node(
    L: sp.spmatrix,
    mass: np.ndarray,
    k: int,
    lambda_k_estimate: float | None = None,
    tol: float = BLOCK_TOL,
) -> tuple[np.ndarray, np.ndarray, str]:
    """One grid node's lowest ``k`` pairs by the solver measured faster at this size:
    :func:`eigs_block_lowest` (to ``tol``) where there are enough vertices per wanted pair,
    :func:`eigs_sliced` (ARPACK, to machine precision) below that."""
    if L.shape[0] >= BLOCK_MIN_VERTICES_PER_PAIR * k:
        return eigs_block_lowest(L, mass, k, lambda_k_estimate, tol)
    return eigs_sliced(L, mass, k, lambda_k_estimate)


#: The per-node solvers ``compute_spectra(solver=...)`` offers (``warm`` is sequential, so it
#: is not here: it needs the previous node).
NODE_SOLVERS = {"auto": eigs_node, "block": eigs_block_lowest, "cold": eigs_sliced}


def solve_node_timed(
    L: sp.csr_matrix,
    mass: np.ndarray,
    k: int,
    estimate: float,
    solver: str = "auto",
    tol: float = BLOCK_TOL,
) -> tuple:
    """One independent node solve, timed. It lives here, not in ``grid``, because it is what
    a spectra worker process runs: unpickling it imports only this module (numpy and
    scipy), not the mesh loaders or torch, so a worker starts in a fraction of a second."""
    t0 = time.perf_counter()
    vals, vecs, method = NODE_SOLVERS[solver](L, mass, k, estimate, tol)
    return vals, vecs, time.perf_counter() - t0, method
