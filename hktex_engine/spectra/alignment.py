"""Aligning one eigenbasis to another so the grid can be interpolated (ALGORITHM.md section 3).

Independent eigen-decompositions of neighbouring operators differ by a permutation of the
columns, their signs and rotations inside (near-)degenerate eigenspaces; interpolating
``phi_k`` between nodes is only meaningful once those are undone against an aligned
reference. The M inner product is used throughout because the bases are M-orthonormal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import linear_sum_assignment

#: Relative eigenvalue gap below which neighbouring eigenpairs form one cluster for the
#: block-wise Procrustes (our choice: well above the solver's eigenvalue error, ~1e-6, and
#: small enough that rotating inside a cluster changes a heat kernel by far less than 1e-3).
CLUSTER_RTOL = 1e-3


@dataclass
class AlignmentInfo:
    """How well a node matched its reference: mean and minimum of the aligned |diag(C)|."""

    mean_overlap: float
    min_overlap: float
    n_clusters: int


def eigen_clusters(evals: np.ndarray, rtol: float = CLUSTER_RTOL) -> list[np.ndarray]:
    """Index groups of near-equal eigenvalues (consecutive in sorted order within ``rtol``)."""
    order = np.argsort(evals, kind="stable")
    v = evals[order]
    scale = np.maximum(np.abs(v), np.abs(v).max() * 1e-9 + 1e-300)
    gaps = np.diff(v) > rtol * scale[1:]
    starts = np.r_[0, np.nonzero(gaps)[0] + 1]
    return [order[a:b] for a, b in zip(starts, np.r_[starts[1:], len(v)], strict=True)]


def _procrustes(C: np.ndarray) -> np.ndarray:
    """Orthogonal ``R`` maximising ``trace(C R)`` (``C = ref^T M new``): ``new @ R ~ ref``."""
    U, _, Wt = np.linalg.svd(C)
    return Wt.T @ U.T


def align_basis(
    ref: np.ndarray,
    vecs: np.ndarray,
    evals: np.ndarray,
    mass: np.ndarray,
    rotation: Literal["block", "full", "none"] = "block",
    rtol: float = CLUSTER_RTOL,
) -> tuple[np.ndarray, np.ndarray, AlignmentInfo]:
    """Align ``vecs`` (n, K) with eigenvalues ``evals`` (K,) to the aligned ``ref`` (n, K_ref).

    Steps: Hungarian assignment on ``-|ref^T M vecs|`` (columns and eigenvalues reordered
    together; columns no reference column claims go last, ascending), then rotation, then
    signs. ``block`` rotates only inside clusters of near-equal eigenvalues, so each column
    stays an eigenvector (its eigenvalue becomes the Rayleigh quotient, equal within the
    cluster tolerance); ``full`` does one Procrustes over the matched columns and keeps the
    permuted eigenvalues (the reference implementation's way; no longer an eigenbasis);
    ``none`` only permutes and flips.
    Returns new arrays; the inputs are not modified.
    """
    K_ref, K = ref.shape[1], vecs.shape[1]
    if ref.shape[0] != vecs.shape[0] or evals.shape != (K,):
        raise ValueError("ref, vecs and evals do not agree in shape")
    C = ref.T @ (mass[:, None] * vecs)  # (K_ref, K)
    # scipy.sparse.csgraph's LAPJVsp matching (no scipy.optimize import, 0.12 s) was tried
    # and dropped: it never returned on a 16 x 16 alignment of a test grid (docs/spectra.md)
    rows, cols = linear_sum_assignment(-np.abs(C))
    matched = cols[np.argsort(rows)]
    rest = np.setdiff1d(np.arange(K), matched)
    rest = rest[np.argsort(evals[rest], kind="stable")]
    perm = np.r_[matched, rest].astype(np.int64)
    vecs = vecs[:, perm]
    evals = np.asarray(evals, dtype=np.float64)[perm].copy()
    C = C[:, perm]
    m = min(K_ref, K)
    n_clusters = 0
    if rotation == "block":
        for idx in eigen_clusters(evals[:m], rtol):
            if len(idx) < 2:
                continue
            n_clusters += 1
            R = _procrustes(C[np.ix_(idx, idx)])
            vecs[:, idx] = vecs[:, idx] @ R
            C[:, idx] = C[:, idx] @ R
            evals[idx] = np.einsum("ij,i,ij->j", R, evals[idx], R)
    elif rotation == "full":
        R = _procrustes(C[:m, :m])
        vecs[:, :m] = vecs[:, :m] @ R
        C[:, :m] = C[:, :m] @ R
    elif rotation != "none":
        raise ValueError(f"unknown rotation mode {rotation!r}")
    diag = np.diagonal(C[:m, :m]).copy()
    flip = np.ones(K)
    flip[:m][diag < 0] = -1.0
    vecs = vecs * flip[None, :]
    overlap = np.abs(diag)
    info = AlignmentInfo(float(overlap.mean()), float(overlap.min()), n_clusters)
    return vecs, evals, info
