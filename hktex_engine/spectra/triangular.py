"""Solves with a sparse LU factor for a block of right-hand sides, compiled.

The block eigensolver (``spectra.eigensolver.eigs_block``) applies ``(L - sigma M)^-1`` to
blocks of 8 vectors ~25 times per grid node. SciPy's ``SuperLU.solve`` did that at ~4 ms
per vector on a 35k-vertex mesh (half of a node's time) although the factor's 2.6M
non-zeros make it ~40 Mflop per block. Here the factor SuperLU computed is taken apart once
into row-oriented (CSR) unit-lower and upper triangles and the two substitutions run as
compiled loops that keep a row's 8 partial sums in registers and read each factor entry
once per block. Same factor, same permutations, so the same solution up to the order of
floating-point sums (measured ~1e-11 relative to SuperLU's). No library offers a
multi-right-hand-side triangular solve over a CSR factor without Python per row
(``scipy.sparse.linalg.spsolve_triangular`` solves one factor column pass per call).
SuperLU still solves without numba, and below :data:`COMPILED_MIN_N` unknowns, where its
solves are cheap and loading the compiled loops would cost a worker more than they save,
unless the process has loaded them already (:func:`preload`: a spectra grid does, once, before
its workers fork), where they solve at every size.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from hktex_engine.jit import HAVE_NUMBA, SIMD_SUMS, jit

#: Right-hand sides per compiled pass: the block eigensolver's block size. A fixed width lets
#: the compiler keep the row's partial sums in registers (measured 1.6x faster than a width
#: known only at run time); other widths are padded to a multiple of it.
WIDTH = 8


def _forward_unit(indptr, indices, data, X):
    """``X <- L^-1 X`` for a unit lower-triangular CSR ``L`` whose rows end with their
    (unit) diagonal entry, which is skipped; ``X`` is (n, WIDTH)."""
    n = X.shape[0]
    acc = np.empty(WIDTH)
    for i in range(n):
        for c in range(WIDTH):
            acc[c] = X[i, c]
        for p in range(indptr[i], indptr[i + 1] - 1):
            j = indices[p]
            v = data[p]
            for c in range(WIDTH):
                acc[c] -= v * X[j, c]
        for c in range(WIDTH):
            X[i, c] = acc[c]


def _backward(indptr, indices, data, inv_diag, X):
    """``X <- U^-1 X`` for an upper-triangular CSR ``U`` whose rows start with their
    diagonal entry (skipped: ``inv_diag`` holds its reciprocals, a multiply being ~10x
    cheaper than a divide in this loop)."""
    n = X.shape[0]
    acc = np.empty(WIDTH)
    for i in range(n - 1, -1, -1):
        for c in range(WIDTH):
            acc[c] = X[i, c]
        for p in range(indptr[i] + 1, indptr[i + 1]):
            j = indices[p]
            v = data[p]
            for c in range(WIDTH):
                acc[c] -= v * X[j, c]
        d = inv_diag[i]
        for c in range(WIDTH):
            X[i, c] = acc[c] * d


_COMPILED: tuple | None = None


def _kernels() -> tuple:
    global _COMPILED
    if _COMPILED is None:
        _COMPILED = (jit(_forward_unit, fastmath=SIMD_SUMS), jit(_backward, fastmath=SIMD_SUMS))
    return _COMPILED


#: Below this many unknowns SuperLU solves: its solves are cheap there, and loading the
#: compiled loops costs each spectra worker ~0.6 s (numba's import and cache).
COMPILED_MIN_N = 10_000

#: Whether this process has loaded the compiled loops (:func:`preload`). Loaded, they are
#: faster than SuperLU's solve at every size measured (one core, 8 right-hand sides, an
#: anisotropic operator on icospheres: 642 unknowns 0.077 against 0.172 ms, 2,562: 0.41
#: against 1.26 ms, 10,242: 2.4 against 12.8 ms), so only the loading cost kept them from
#: small factors, and once it is paid :class:`FactorSolve` uses them at every size.
_preloaded = False


def preload() -> bool:
    """Load the compiled loops into this process (numba's disk cache, or a compile) and use
    them for every later :class:`FactorSolve` here; forked children inherit them. ~0.25 s
    from the cache. Returns whether they are compiled (False without numba)."""
    global _preloaded
    if not HAVE_NUMBA:
        return False
    if not _preloaded:
        # one solve through the real path loads the loops for the argument types SuperLU's
        # triangles have, so the first solve of a grid compiles nothing
        solver = FactorSolve(splu(sp.identity(2, format="csc")), min_n=0)
        solver.solve(np.zeros((2, WIDTH)))
        _preloaded = solver.compiled
    return _preloaded


def solves_compiled(n: int, min_n: int | None = None) -> bool:
    """Whether this process solves an ``n``-unknown factor with the compiled loops: from
    ``min_n`` unknowns, by default from :data:`COMPILED_MIN_N`, or at every size once
    :func:`preload` has run."""
    if min_n is None:
        min_n = 0 if _preloaded else COMPILED_MIN_N
    return HAVE_NUMBA and n >= min_n


class FactorSolve:
    """``A^-1 B`` for ``Pr A Pc = L U`` as SciPy's ``splu`` factors it (``B``: (n,) or (n, r)).

    With ``order`` the factor is of ``A[order][:, order]`` (:func:`factor_compiled`), and
    :meth:`solve` still answers for ``A``: the compiled path folds that permutation into
    SuperLU's own row and column permutations, so it costs nothing per solve.
    """

    def __init__(self, lu, min_n: int | None = None, order: np.ndarray | None = None) -> None:
        self._lu = lu
        self._order = order
        self.compiled = solves_compiled(lu.shape[0], min_n)
        if not self.compiled:
            return
        n = lu.shape[0]
        # X[perm_r] = b (gathered: X = b[src]) and x = X[perm_c]; with an order,
        # A[order][:, order] y = b[order] and x[order] = y
        inner = np.arange(n) if order is None else order
        self._src = np.empty(n, dtype=np.int64)
        self._src[lu.perm_r] = inner
        self._dst = np.empty(n, dtype=np.int64)
        self._dst[inner] = lu.perm_c
        lower = sp.csr_matrix(lu.L)
        upper = sp.csr_matrix(lu.U)
        lower.sort_indices()
        upper.sort_indices()
        # the loops read the diagonal by position: last in a row of L, first in a row of U
        rows = np.arange(n)
        if not (
            np.all(np.diff(lower.indptr) > 0)
            and np.all(np.diff(upper.indptr) > 0)
            and np.array_equal(lower.indices[lower.indptr[1:] - 1], rows)
            and np.array_equal(upper.indices[upper.indptr[:-1]], rows)
            and np.all(lower.indices <= np.repeat(rows, np.diff(lower.indptr)))
            and np.all(upper.indices >= np.repeat(rows, np.diff(upper.indptr)))
        ):
            self.compiled = False  # not the triangles SuperLU documents: let it solve
            return
        self._lower = (lower.indptr, lower.indices, lower.data)
        inv_diag = 1.0 / upper.data[upper.indptr[:-1]]
        self._upper = (upper.indptr, upper.indices, upper.data, inv_diag)
        self._forward, self._back = _kernels()

    def solve(self, B: np.ndarray) -> np.ndarray:
        if not self.compiled:
            if self._order is None:
                return self._lu.solve(B)
            out = np.empty(B.shape)
            out[self._order] = self._lu.solve(B[self._order])
            return out
        one = B.ndim == 1
        cols = B.reshape(B.shape[0], -1)
        out = np.empty(cols.shape)
        for a in range(0, cols.shape[1], WIDTH):
            z = min(a + WIDTH, cols.shape[1])
            X = np.zeros((cols.shape[0], WIDTH))
            X[:, : z - a] = cols[self._src, a:z]  # Pr b
            self._forward(*self._lower, X)
            self._back(*self._upper, X)
            out[:, a:z] = X[self._dst, : z - a]  # x = Pc y
        return out[:, 0] if one else out


#: Fill-reducing orders by sparsity pattern, this process's last few (:func:`factor_compiled`).
_ORDERS: OrderedDict[bytes, np.ndarray] = OrderedDict()
ORDERS_KEPT = 4


def _pattern_key(A: sp.csc_matrix) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for part in (np.asarray(A.shape, dtype=np.int64), A.indptr, A.indices):
        h.update(np.ascontiguousarray(part).tobytes())
    return h.digest()


def factor_compiled(A: sp.csc_matrix, options: dict) -> FactorSolve:
    """SuperLU's factor of ``A`` with compiled solves, in a fill-reducing order computed once
    per sparsity pattern, where this process solves compiled; SuperLU's own factor and solves
    elsewhere.

    Every operator of a spectral grid has the mesh's pattern, and SuperLU's minimum-degree
    ordering depends on the pattern alone, yet ``splu`` recomputes it at every factorisation.
    Here the order is taken once, from a first factorisation with ``MMD_AT_PLUS_A``, and every
    factorisation of the pattern (that first matrix's included, so a node's result does not
    depend on which node a process met first) is of the symmetrically permuted matrix in its
    natural order: the same fill. SciPy's ``splu`` takes no order of the caller's, hence the
    permutation. Only where the solves are compiled, which absorb the permutation for free;
    SuperLU's own solve would pay two gathers a call.
    """
    A = sp.csc_matrix(A)
    if not solves_compiled(A.shape[0]):
        return FactorSolve(splu(A, permc_spec="MMD_AT_PLUS_A", **options))
    A.sort_indices()
    key = _pattern_key(A)
    order = _ORDERS.get(key)
    if order is None:
        order = np.argsort(splu(A, permc_spec="MMD_AT_PLUS_A", **options).perm_c)
        _ORDERS[key] = order
        while len(_ORDERS) > ORDERS_KEPT:
            _ORDERS.popitem(last=False)
    return FactorSolve(splu(A[order][:, order], permc_spec="NATURAL", **options), order=order)
