"""The compiled solves with SuperLU's factor (spectra.triangular) against independent solves."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from hktex_engine.spectra import triangular
from hktex_engine.spectra.eigensolver import FACTOR_OPTIONS
from hktex_engine.spectra.triangular import FactorSolve


def _indefinite_laplacian(n_side: int = 30, shift: float = 0.3) -> sp.csc_matrix:
    """A grid Laplacian shifted into its spectrum (indefinite, like L - sigma M mid-range),
    with random positive weights so nothing is symmetric by accident of the grid."""
    rng = np.random.default_rng(0)
    n = n_side * n_side
    idx = np.arange(n).reshape(n_side, n_side)
    i = np.r_[idx[:, :-1].ravel(), idx[:-1, :].ravel()]
    j = np.r_[idx[:, 1:].ravel(), idx[1:, :].ravel()]
    w = rng.uniform(0.5, 1.5, len(i))
    W = sp.coo_matrix((w, (i, j)), shape=(n, n))
    W = W + W.T
    L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    return (L - shift * sp.eye(n)).tocsc()


@pytest.mark.parametrize("options", [{}, FACTOR_OPTIONS], ids=["partial", "symmetric"])
@pytest.mark.parametrize("cols", [None, 1, 8, 11])
def test_compiled_solve_equals_superlu_and_a_dense_solve(options, cols):
    A = _indefinite_laplacian()
    lu = splu(A, permc_spec="MMD_AT_PLUS_A", **options)
    rng = np.random.default_rng(1)
    B = rng.standard_normal(A.shape[0] if cols is None else (A.shape[0], cols))
    fs = FactorSolve(lu, min_n=0)
    assert fs.compiled == triangular.HAVE_NUMBA
    X = fs.solve(B)
    assert X.shape == B.shape
    np.testing.assert_allclose(X, lu.solve(B), rtol=1e-10, atol=1e-10)
    dense = np.linalg.solve(A.toarray(), B)
    np.testing.assert_allclose(X, dense, rtol=1e-8, atol=1e-8 * np.abs(dense).max())


def test_without_numba_superlu_solves(monkeypatch):
    monkeypatch.setattr(triangular, "HAVE_NUMBA", False)
    A = _indefinite_laplacian(10)
    lu = splu(A)
    B = np.random.default_rng(2).standard_normal((A.shape[0], 3))
    fs = FactorSolve(lu, min_n=0)
    assert not fs.compiled
    np.testing.assert_array_equal(fs.solve(B), lu.solve(B))


def test_small_factors_are_left_to_superlu(monkeypatch):
    monkeypatch.setattr(triangular, "_preloaded", False)
    lu = splu(_indefinite_laplacian(10))
    assert not FactorSolve(lu).compiled  # 100 unknowns: below COMPILED_MIN_N


def test_once_preloaded_the_compiled_loops_solve_small_factors(monkeypatch):
    """The loading cost is what kept small factors with SuperLU; a process that has paid it
    (a spectra grid preloads) solves compiled at every size, with SuperLU's answer."""
    monkeypatch.setattr(triangular, "_preloaded", False)
    lu = splu(_indefinite_laplacian(10), permc_spec="MMD_AT_PLUS_A", **FACTOR_OPTIONS)
    assert triangular.preload() == triangular.HAVE_NUMBA
    fs = FactorSolve(lu)
    assert fs.compiled == triangular.HAVE_NUMBA
    B = np.random.default_rng(3).standard_normal((lu.shape[0], 8))
    np.testing.assert_allclose(fs.solve(B), lu.solve(B), rtol=1e-10, atol=1e-10)
    assert not FactorSolve(lu, min_n=1000).compiled  # an explicit threshold still holds


def test_preload_without_numba_changes_nothing(monkeypatch):
    monkeypatch.setattr(triangular, "_preloaded", False)
    monkeypatch.setattr(triangular, "HAVE_NUMBA", False)
    assert triangular.preload() is False
    assert not FactorSolve(splu(_indefinite_laplacian(10))).compiled


@pytest.mark.parametrize("compiled", [True, False])
def test_factor_in_a_cached_order_solves_the_original_system(monkeypatch, compiled):
    """``factor_compiled`` factors ``A`` in a fill-reducing order taken once per sparsity
    pattern: its solves answer for ``A`` itself (against a dense solve), a second matrix of
    the same pattern reuses the order (SuperLU's own ordering is not called again) and gets
    the same fill as its own minimum-degree factor, and the matrix that set the order solves
    the same whether it came first or not. Without compiled solves SuperLU factors as before."""
    monkeypatch.setattr(triangular, "_ORDERS", triangular.OrderedDict())
    monkeypatch.setattr(triangular, "_preloaded", compiled and triangular.HAVE_NUMBA)
    A = _indefinite_laplacian(20)
    A2 = _indefinite_laplacian(20, shift=0.7)
    A2.data *= np.random.default_rng(5).uniform(0.9, 1.1, A2.nnz)
    A2 = ((A2 + A2.T) * 0.5).tocsc()
    B = np.random.default_rng(4).standard_normal((A.shape[0], 8))
    first = triangular.factor_compiled(A, FACTOR_OPTIONS)
    assert first.compiled == (compiled and triangular.HAVE_NUMBA)
    np.testing.assert_allclose(
        first.solve(B), np.linalg.solve(A.toarray(), B), rtol=1e-9, atol=1e-9
    )
    if not first.compiled:
        assert not triangular._ORDERS
        return
    calls = []
    real_splu = triangular.splu
    monkeypatch.setattr(triangular, "splu", lambda M, **kw: calls.append(kw) or real_splu(M, **kw))
    second = triangular.factor_compiled(A2, FACTOR_OPTIONS)
    assert [kw["permc_spec"] for kw in calls] == ["NATURAL"]  # the cached order, no new one
    dense = np.linalg.solve(A2.toarray(), B)
    np.testing.assert_allclose(second.solve(B), dense, rtol=1e-9, atol=1e-9 * np.abs(dense).max())
    own = real_splu(A2, permc_spec="MMD_AT_PLUS_A", **FACTOR_OPTIONS)
    assert second._lu.L.nnz + second._lu.U.nnz == own.L.nnz + own.U.nnz
    again = triangular.factor_compiled(A, FACTOR_OPTIONS)
    np.testing.assert_array_equal(again.solve(B), first.solve(B))
