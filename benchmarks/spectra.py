"""Spectra benchmark: our grid builder against the naive one, on the shared meshes.

    python benchmarks/spectra.py [--meshes spot,bob,blub,marble_bust_01,marble_35k]
                                 [--naive-nodes 3] [--angles 7] [--k 256] [--k-iso 65]

For each mesh, in child processes (so ``ru_maxrss`` is that run's own peak; tracemalloc
would not see ARPACK or SuperLU):

* ours: ``compute_spectra(mesh, config, out_dir=...)`` on the full grid, streamed to disk;
  time, peak RSS, bytes on disk, solver iterations and residuals from the manifest.
* naive: every node solved from scratch by ARPACK shift-invert (``eigs_cold``). Timed on
  ``--naive-nodes`` nodes and extrapolated to the whole grid (stated as such in the
  results); the same solves are the exact reference for accuracy: eigen residuals of our
  stored nodes, and the relative L2 difference of heat kernels (t = 8.133e-4, 16 sources)
  between our stored node and the exact one, in float32 and in float16.

``marble_35k`` is marble_bust_01 after one midpoint subdivision (34,914 vertices).
Writes benchmarks/results/spectra.json and .md with the machine and the command.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
MESHES = {
    "spot": "spot/spot_triangulated.obj",
    "bob": "bob/bob_tri.obj",
    "blub": "blub/blub_triangulated.obj",
    "marble_bust_01": "marble_bust_01/marble_bust_01_4k.gltf",
    "marble_35k": "marble_bust_01/marble_bust_01_4k.gltf",
}
T_HEAT = 8.133e-4


def load(name: str):
    from hktex_engine.mesh import load_mesh, mesh_from_arrays

    mesh = load_mesh(DATA / MESHES[name])
    if name.endswith("_35k"):
        import trimesh

        v, f = trimesh.remesh.subdivide(mesh.vertices, mesh.faces)
        mesh = mesh_from_arrays(v, f, source_name=name)
    return mesh


def config_from(args: argparse.Namespace):
    from hktex_engine.config import SpectralConfig

    aniso = tuple(float(x) for x in args.anisotropies.split(","))
    return SpectralConfig(angles=args.angles, anisotropies=aniso, k=args.k, k_iso=args.k_iso)


def full_grid_estimate(ours: dict, full_nodes: int, full_distinct: int) -> float:
    """Our time for the full grid from a reduced-grid run: fixed costs + per distinct node."""
    t = ours["timings"]
    fixed = t["operators_s"] + t["isotropic_s"] + t.get("write_s", 0.0)
    per_node = ours["seconds_per_solved_node"]
    align = t["align_s"] / max(1, ours["nodes_solved"] + ours["nodes_copied"])
    return fixed + full_distinct * per_node + full_nodes * align


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child_ours(args: argparse.Namespace) -> dict:
    from hktex_engine.spectra import compute_spectra

    mesh = load(args.child_mesh)
    config = config_from(args)
    t0 = time.perf_counter()
    sp = compute_spectra(
        mesh,
        config,
        out_dir=Path(args.workdir) / "spectra",
        solver=args.solver,
        workers=args.workers,
    )
    seconds = time.perf_counter() - t0
    log = sp.manifest["solver"]["nodes"]
    solved = [e for e in log if e["method"].startswith("cold") or e["method"] == "warm"]
    return {
        "n_vertices": mesh.n_vertices,
        "seconds": seconds,
        "peak_rss_mb": peak_mb(),
        "bytes": sp.manifest["bytes"],
        "evecs_bytes": sp.manifest["files"]["evecs"],
        "timings": sp.manifest["timings"],
        "nodes_solved": len(solved),
        "nodes_copied": len(log) - len(solved),
        "solver": args.solver,
        "workers": args.workers,
        "fallbacks_to_cold": sum(e["method"].startswith("cold (") for e in log),
        "iterations_mean": float(np.mean([e["iterations"] for e in solved])) if solved else 0,
        "max_residual": max(e["max_residual"] for e in log),
        "seconds_per_solved_node": float(np.mean([e["seconds"] for e in solved])) if solved else 0,
    }


def _heat(evals: np.ndarray, evecs: np.ndarray, src: np.ndarray) -> np.ndarray:
    return evecs @ (np.exp(-T_HEAT * evals)[:, None] * evecs[src].T)


def child_naive(args: argparse.Namespace) -> dict:
    from hktex_engine.eigensolver import eigs_cold, residuals
    from hktex_engine.operators import AlboAssembler
    from hktex_engine.spectra import load_spectra

    sp = load_spectra(Path(args.workdir) / "spectra")
    V, F, M = np.asarray(sp.vertices), np.asarray(sp.faces), np.asarray(sp.mass)
    asm = AlboAssembler(V, F, np.asarray(sp.face_frames))
    S, K = len(sp.grid_eta), sp.evals.shape[1]
    nodes = sp.manifest["solver"]["nodes"]
    solved = [e["node"] for e in nodes if e["method"].startswith("cold") or e["method"] == "warm"]
    pick = [solved[int(i)] for i in np.linspace(0, len(solved) - 1, args.naive_nodes)]
    src = np.random.default_rng(0).choice(len(V), 16, replace=False)
    rows = []
    for g in pick:
        L = asm.stiffness(sp.grid_theta[g // S], sp.grid_eta[g % S])
        t0 = time.perf_counter()
        exact_vals, exact_vecs = eigs_cold(L, M, K)
        seconds = time.perf_counter() - t0
        ours = np.asarray(sp.evecs[:, g, :], dtype=np.float64)
        h_exact = _heat(exact_vals, exact_vecs, src)
        norm = np.linalg.norm(h_exact)
        res = residuals(L, M, sp.evals[g], ours)
        half = ours.astype(np.float16).astype(np.float64)
        # the stored eigenvalues are permuted by alignment: compare as sets
        ev_err = np.abs(np.sort(sp.evals[g]) - exact_vals).max() / exact_vals.max()
        rows.append(
            {
                "node": g,
                "theta": float(sp.grid_theta[g // S]),
                "eta": float(sp.grid_eta[g % S]),
                "naive_seconds": seconds,
                "ours_max_residual": float(res.max()),
                "ours_median_residual": float(np.median(res)),
                "eigenvalue_max_rel_error": float(ev_err),
                "heat_rel_diff_float32": float(
                    np.linalg.norm(_heat(sp.evals[g], ours, src) - h_exact) / norm
                ),
                "heat_rel_diff_float16": float(
                    np.linalg.norm(_heat(sp.evals[g], half, src) - h_exact) / norm
                ),
                "float16_vs_float32": float(
                    np.linalg.norm(_heat(sp.evals[g], half, src) - _heat(sp.evals[g], ours, src))
                    / norm
                ),
            }
        )
    # what truncation at K costs anyway (context for the numbers above): K vs 1.25 K exact
    g = pick[0]
    L = asm.stiffness(sp.grid_theta[g // S], sp.grid_eta[g % S])
    big_vals, big_vecs = eigs_cold(L, M, int(1.25 * K))
    h_big = _heat(big_vals, big_vecs, src)
    h_k = _heat(big_vals[:K], big_vecs[:, :K], src)
    per_node = float(np.mean([r["naive_seconds"] for r in rows]))
    G = sp.evals.shape[0]
    return {
        "nodes": rows,
        "naive_seconds_per_node": per_node,
        "naive_extrapolated_total_s": per_node * G,
        "naive_peak_rss_mb": peak_mb(),
        "truncation_rel_diff_K_vs_1.25K": float(
            np.linalg.norm(h_k - h_big) / np.linalg.norm(h_big)
        ),
    }


def run_child(kind: str, mesh: str, workdir: Path, args: argparse.Namespace) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--child-mesh",
        mesh,
        "--workdir",
        str(workdir),
    ]
    cmd += ["--angles", str(args.angles), "--anisotropies", args.anisotropies]
    cmd += ["--k", str(args.k), "--k-iso", str(args.k_iso), "--naive-nodes", str(args.naive_nodes)]
    cmd += ["--solver", args.solver, "--workers", str(args.workers)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def machine() -> dict:
    cpu = "unknown"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    mem = Path("/proc/meminfo").read_text().splitlines()[0].split()[1]
    return {
        "nproc": os.cpu_count(),
        "cpu": cpu,
        "ram_gb": round(int(mem) / 2**20, 1),
        "python": platform.python_version(),
        "load_average_at_start": os.getloadavg(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default"),
    }


def write_md(path: Path, result: dict) -> None:
    lines = [
        "# Spectra benchmark",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {result['machine']}  ",
        f"Config: {result['config']}",
        "",
        "Naive = every node by ARPACK shift-invert from scratch, timed on a few nodes and "
        "**extrapolated** to the grid (column 'naive (extrap.)').",
        "",
        "| mesh | n | ours s | naive s (extrap.) | speed-up | ours peak MB | naive peak MB | "
        "disk MB | max resid | heat diff f32 | heat diff f16 | trunc. K vs 1.25K |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in result["meshes"].items():
        o, nv = r.get("ours", {}), r.get("naive", {})
        if "error" in o or "error" in nv:
            lines.append(f"| {name} | error: {o.get('error') or nv.get('error')} |")
            continue
        if "reduced_grid" in r:
            rg = r["reduced_grid"]
            lines.append(
                f"| {name} (grid {rg['angles']} x [{rg['anisotropies']}], full grid "
                f"extrapolated: ours {r['ours_full_grid_estimate_s']:.0f} s, naive "
                f"{r['naive_full_grid_estimate_s']:.0f} s) | | | | | | | | | | | |"
            )
        hk32 = max(x["heat_rel_diff_float32"] for x in nv["nodes"])
        hk16 = max(x["heat_rel_diff_float16"] for x in nv["nodes"])
        res = max(x["ours_max_residual"] for x in nv["nodes"])
        lines.append(
            f"| {name} | {o['n_vertices']} | {o['seconds']:.1f} | "
            f"{nv['naive_extrapolated_total_s']:.1f} | "
            f"{nv['naive_extrapolated_total_s'] / o['seconds']:.1f}x | {o['peak_rss_mb']:.0f} | "
            f"{nv['naive_peak_rss_mb']:.0f} | {o['bytes'] / 1e6:.1f} | {res:.1e} | {hk32:.1e} | "
            f"{hk16:.1e} | {nv['truncation_rel_diff_K_vs_1.25K']:.1e} |"
        )
    lines += [
        "",
        "Per-mesh details (solver iterations, timings, per-node accuracy) in spectra.json.",
    ]
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--meshes",
        default="spot;bob;blub;marble_bust_01;marble_35k",
        help="';'-separated; 'name:A:e1,e2' runs a reduced grid and extrapolates",
    )
    ap.add_argument("--naive-nodes", type=int, default=3)
    ap.add_argument("--angles", type=int, default=7)
    ap.add_argument("--anisotropies", default="1,5,15,30,60,100,200")
    ap.add_argument("--k", type=int, default=256)
    ap.add_argument("--k-iso", type=int, default=65)
    ap.add_argument("--solver", choices=("cold", "warm"), default="cold")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--child", choices=("ours", "naive"), help=argparse.SUPPRESS)
    ap.add_argument("--child-mesh", help=argparse.SUPPRESS)
    ap.add_argument("--workdir", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        result = child_ours(args) if args.child == "ours" else child_naive(args)
        print(json.dumps(result))
        return
    result = {
        "command": "python benchmarks/spectra.py " + " ".join(sys.argv[1:]),
        "machine": machine(),
        "config": {
            "angles": args.angles,
            "anisotropies": args.anisotropies,
            "k": args.k,
            "k_iso": args.k_iso,
            "solver": args.solver,
            "workers": args.workers,
        },
        "naive_nodes_timed": args.naive_nodes,
        "meshes": {},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    full_nodes = args.angles * len(args.anisotropies.split(","))
    full_distinct = full_nodes - len(args.anisotropies.split(","))  # theta = pi is theta = 0
    for spec in args.meshes.split(";"):
        # "name" runs the grid of the flags; "name:A:e1,e2" a reduced grid (extrapolated)
        name, *grid = spec.split(":")
        run_args = argparse.Namespace(**vars(args))
        if grid:
            run_args.angles, run_args.anisotropies = int(grid[0]), grid[1]
        with tempfile.TemporaryDirectory(prefix="hktex-bench-") as tmp:
            ours = run_child("ours", name, Path(tmp), run_args)
            naive = run_child("naive", name, Path(tmp), run_args) if "error" not in ours else {}
        entry = {"ours": ours, "naive": naive}
        if grid and "error" not in ours and "error" not in naive:
            entry["reduced_grid"] = {"angles": run_args.angles, "anisotropies": grid[1]}
            entry["ours_full_grid_estimate_s"] = full_grid_estimate(ours, full_nodes, full_distinct)
            entry["naive_full_grid_estimate_s"] = naive["naive_seconds_per_node"] * full_nodes
        result["meshes"][name] = entry
        print(name, json.dumps(result["meshes"][name])[:400], flush=True)
        (args.out / "spectra.json").write_text(json.dumps(result, indent=1))
        write_md(args.out / "spectra.md", result)


if __name__ == "__main__":
    main()
