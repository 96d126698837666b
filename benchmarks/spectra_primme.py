"""PRIMME against our node solver and plain ARPACK, one grid node at a time (issue 10).

    apt-get install libopenblas-dev liblapack-dev && pip install primme==3.2.3
    python benchmarks/spectra_primme.py [--meshes spot blub] [--tol 1e-6] [--out DIR]

Issue 10 names PRIMME (preconditioned Davidson methods, which can start from educated
guesses) as a candidate for the spectra. It has no wheel for this Python; its source build
needs a system BLAS/LAPACK, which Debian's packages above provide. PRIMME is therefore not a
dependency of the product: this script measures it beside the product's solver and exits
with the install line when it is missing.

Per mesh, at the nodes ``theta = 0``, ``eta`` in 1, 5, 30, 200 (default K), it times:

- ``arpack``: plain ``eigsh(L, k=K, M=M, sigma=-1e-6)``, the issue's baseline, which is also
  the accuracy reference;
- ``ours``: :func:`hktex_engine.spectra.eigensolver.eigs_node` at the grid's tolerance;
- PRIMME on ``L x = lambda M x`` for the K smallest pairs (``which="SA"``), preconditioned
  by the exact shift-invert solve (a sparse LU of ``L + 1e-6 M``, the best preconditioner
  there is, so its count of solves is comparable with ARPACK's): GD+k (``MIN_MATVECS``), JDQMR
  (``MIN_TIME``), GD+k at a 1000x tighter tolerance, GD+k with blocks of 8, and GD+k started from the converged basis of the
  node one angle step (30 degrees) away and, from the second eta on, of the previous eta:
  the warm starts a grid offers for free.

Accuracy: heat kernels at t = 0.0625 (the default diffusion time) from 64 sources against
ARPACK's, max relative entry error. Writes ``spectra_primme.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import sys
import time
from pathlib import Path

import numpy as np
from _machine import machine_info, machine_line

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ETAS = (1.0, 5.0, 30.0, 200.0)
ANGLE_STEP = np.pi / 6
T_HEAT = 0.0625
SHIFT = -1e-6


def heat(vals, vecs, src) -> np.ndarray:
    """Heat kernels at ``T_HEAT`` from the ``src`` vertices, (n, len(src))."""
    return (vecs * np.exp(-T_HEAT * vals)) @ vecs[src].T


def heat_error(vals, vecs, ref: np.ndarray, src) -> float:
    """Largest heat-kernel entry error from ``src``, relative to the reference's largest."""
    return float(np.abs(heat(vals, vecs, src) - ref).max() / np.abs(ref).max())


def sorted_pairs(vals, vecs):
    order = np.argsort(vals)
    return vals[order], vecs[:, order]


def arpack(L, Md, k):
    from scipy.sparse.linalg import eigsh

    t0 = time.perf_counter()
    vals, vecs = eigsh(L, k=k, M=Md, sigma=SHIFT)
    return (*sorted_pairs(vals, vecs), time.perf_counter() - t0)


def primme_solve(L, Md, k, tol, method, block=1, v0=None):
    """PRIMME with the exact shift-invert solve as preconditioner (its factorisation timed)."""
    import primme
    from scipy.sparse.linalg import LinearOperator, splu

    t0 = time.perf_counter()
    lu = splu((L - SHIFT * Md).tocsc())
    pre = LinearOperator(L.shape, matvec=lu.solve, matmat=lu.solve, dtype=np.float64)
    vals, vecs, stats = primme.eigsh(
        L, k, M=Md, which="SA", OPinv=pre, v0=v0, tol=tol, method=method,
        maxBlockSize=block, return_stats=True,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    vals, vecs = sorted_pairs(vals, vecs)
    return vals, vecs, seconds, int(stats["numPreconds"])


def node_row(asm, Md, mass, k, eta, tol, src, previous) -> tuple[dict, np.ndarray]:
    from hktex_engine.config import SpectralConfig
    from hktex_engine.spectra.eigensolver import GRID_TOL, eigs_node

    L = asm.stiffness(0.0, eta).tocsc()
    ref_vals, ref_vecs, t_arpack = arpack(L, Md, k)
    ref = heat(ref_vals, ref_vecs, src)
    row = {"eta": eta, "arpack_s": t_arpack}
    t0 = time.perf_counter()
    vals, vecs, method = eigs_node(L.tocsr(), mass, k, None, GRID_TOL[SpectralConfig().evecs_dtype])
    row |= {"ours_s": time.perf_counter() - t0, "ours_method": method}
    row["ours_heat_error"] = heat_error(*sorted_pairs(vals, vecs), ref, src)
    variants = {
        "gdk": ("PRIMME_DEFAULT_MIN_MATVECS", 1, tol),
        "gdk_tight": ("PRIMME_DEFAULT_MIN_MATVECS", 1, tol * 1e-3),
        "jdqmr": ("PRIMME_DEFAULT_MIN_TIME", 1, tol),
        "gdk_block8": ("PRIMME_DEFAULT_MIN_MATVECS", 8, tol),
    }
    for name, (meth, block, variant_tol) in variants.items():
        pv, pV, sec, solves = primme_solve(L, Md, k, variant_tol, meth, block)
        row |= {f"{name}_s": sec, f"{name}_solves": solves}
        row[f"{name}_heat_error"] = heat_error(pv, pV, ref, src)
    # warm from the node one angle step away (its exact basis), and from the previous eta
    L_angle = asm.stiffness(ANGLE_STEP, eta).tocsc()
    a_vals, a_vecs, _ = arpack(L_angle, Md, k)
    pv, pV, sec, solves = primme_solve(
        L_angle, Md, k, tol, "PRIMME_DEFAULT_MIN_MATVECS", v0=ref_vecs.copy()
    )
    row |= {"warm_angle_s": sec, "warm_angle_solves": solves}
    row["warm_angle_heat_error"] = heat_error(pv, pV, heat(a_vals, a_vecs, src), src)
    if previous is not None:
        pv, pV, sec, solves = primme_solve(
            L, Md, k, tol, "PRIMME_DEFAULT_MIN_MATVECS", v0=previous.copy()
        )
        row |= {"warm_eta_s": sec, "warm_eta_solves": solves}
        row["warm_eta_heat_error"] = heat_error(pv, pV, ref, src)
    return row, ref_vecs


def measure(mesh_name: str, k: int, tol: float) -> dict:
    import scipy.sparse as sps
    from spectra import load

    from hktex_engine.geometry.operators import (
        AlboAssembler,
        lumped_mass,
        reference_tangent_field,
    )

    mesh = load(mesh_name)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    mass = lumped_mass(V, F)
    asm = AlboAssembler(V, F, reference_tangent_field(V, F))
    Md = sps.diags(mass).tocsc()
    src = np.random.default_rng(0).choice(len(V), 64, replace=False)
    rows, previous = [], None
    for eta in ETAS:
        row, previous = node_row(asm, Md, mass, k, eta, tol, src, previous)
        rows.append(row)
        print(mesh_name, json.dumps({a: round(b, 4) if isinstance(b, float) else b
                                     for a, b in row.items()}), flush=True)  # fmt: skip
    return {"mesh": mesh_name, "n": len(V), "k": k, "tol": tol, "nodes": rows}


def write_md(path: Path, result: dict) -> None:
    lines = [
        "# PRIMME against our node solver and plain ARPACK (issue 10)",
        "",
        f"Machine: {machine_line(result['machine'])}. Command: `{result['command']}`.",
        f"PRIMME {result['primme']}, tolerance {result['tol']} (its `‖Lx − λMx‖ < tol·max|λ|`),"
        " preconditioned by the exact shift-invert solve. Seconds per node (factorisation"
        " included); heat error: max relative entry error of heat kernels at t = 0.0625 from"
        " 64 sources against ARPACK.",
        "",
        "| mesh | n | η | ARPACK s | ours s (×ARPACK; heat err) | GD+k s (heat err) | GD+k, tol"
        " ×1e-3, s (heat err) | JDQMR s | GD+k block 8 s (heat err) | GD+k warm from 30° s |"
        " GD+k warm from previous η s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m in result["meshes"]:
        for r in m["nodes"]:
            warm_eta = f"{r['warm_eta_s']:.3f}" if "warm_eta_s" in r else "—"
            lines.append(
                f"| {m['mesh']} | {m['n']:,} | {r['eta']:g} | {r['arpack_s']:.3f} | "
                f"{r['ours_s']:.3f} ({r['arpack_s'] / r['ours_s']:.2f}×; "
                f"{r['ours_heat_error']:.0e}) | {r['gdk_s']:.3f} ({r['gdk_heat_error']:.1e}) | "
                f"{r['gdk_tight_s']:.3f} ({r['gdk_tight_heat_error']:.1e}) | {r['jdqmr_s']:.3f} | "
                f"{r['gdk_block8_s']:.3f} ({r['gdk_block8_heat_error']:.1e}) | "
                f"{r['warm_angle_s']:.3f} | {warm_eta} |"
            )
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--meshes", nargs="+", default=["spot", "blub"])
    ap.add_argument("--k", type=int, default=128)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    try:
        version = importlib.metadata.version("primme")
    except importlib.metadata.PackageNotFoundError:
        sys.exit("primme is not installed: apt-get install libopenblas-dev liblapack-dev && "
                 "pip install primme==3.2.3")  # fmt: skip
    result = {
        "machine": machine_info(),
        "command": "python benchmarks/spectra_primme.py " + " ".join(sys.argv[1:]),
        "primme": version,
        "tol": args.tol,
        "meshes": [measure(name, args.k, args.tol) for name in args.meshes],
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "spectra_primme.json").write_text(json.dumps(result, indent=1) + "\n")
    write_md(args.out / "spectra_primme.md", result)


if __name__ == "__main__":
    main()
