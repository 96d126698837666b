"""The issue's outside check of queries: ``hktex query`` as a user runs it, against a matmul.

    python benchmarks/query_cli.py --hkt SET.hkt --spectra DIR [--points 5000,10000,...]
        [--baseline-python PATH --baseline-root DIR] [--out DIR]

Issue 10 checks queries from outside: the ``hktex query`` command's throughput on a held-out
mesh against a dense float32 matmul timed in the same run. This script draws area-uniform
surface points (fixed seed), runs the command once per point count as a fresh process, and
records both the command's own figure (``points_per_s`` of ``--json``: the evaluation alone)
and the whole command's wall time (imports, loading, query state and candidate tables
included), each as points per measured GFLOP. With ``--baseline-root`` (a checkout of an
earlier commit) the same commands run there too, alternately, and the colours are compared.
Writes ``query_cli.json`` and ``.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _machine import machine_info, machine_line

ROOT = Path(__file__).resolve().parents[1]


def matmul_gflops(threads: int) -> float:
    """Best of five 2048^3 float32 products with ``threads`` torch threads."""
    import torch

    torch.set_num_threads(threads)
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    best = min(_timed(lambda: a @ b) for _ in range(5))
    return 2 * 2048**3 / best / 1e9


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def surface_points(spectra_dir: Path, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Face ids and barycentrics of ``n`` points drawn uniformly by area."""
    v = np.load(spectra_dir / "vertices.npy")
    f = np.load(spectra_dir / "faces.npy")
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    rng = np.random.default_rng(seed)
    faces = rng.choice(len(f), n, p=area / area.sum())
    return faces.astype(np.int64), rng.dirichlet(np.ones(3), n)


def run_query(python: str, root: Path, hkt: Path, spectra: Path, faces: Path, bary: Path,
              out: Path) -> dict:  # fmt: skip
    """One ``hktex query`` process: its JSON summary plus the wall time of the whole command."""
    cmd = [python, "-m", "hktex_engine", "query", str(hkt), "--spectra", str(spectra)]
    cmd += ["--faces", str(faces), "--barycentrics", str(bary), "-o", str(out), "--json"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, check=True, cwd=root, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    summary["wall_s"] = wall
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hkt", type=Path, required=True)
    ap.add_argument("--spectra", type=Path, required=True)
    ap.add_argument("--points", default="5000,10000,30000,100000,300000,1000000")
    ap.add_argument("--baseline-python", default=None)
    ap.add_argument("--baseline-root", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    threads = os.cpu_count() or 1
    gflops = matmul_gflops(threads)
    sides = [("current", sys.executable, ROOT)]
    if args.baseline_root is not None:
        sides.append(("baseline", args.baseline_python or sys.executable, args.baseline_root))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        # one untimed call per side first: numba compiles a fresh checkout's loops once
        faces, bary = surface_points(args.spectra, 1000)
        np.save(work / "f.npy", faces)
        np.save(work / "b.npy", bary)
        for _name, python, root in sides:
            run_query(python, root, args.hkt.resolve(), args.spectra.resolve(),
                      work / "f.npy", work / "b.npy", work / "warm.npy")  # fmt: skip
        for n in [int(x) for x in args.points.split(",")]:
            faces, bary = surface_points(args.spectra, n)
            np.save(work / "f.npy", faces)
            np.save(work / "b.npy", bary)
            row: dict = {"points": n}
            colours = {}
            for name, python, root in sides:
                out = work / f"{name}.npy"
                s = run_query(python, root, args.hkt.resolve(), args.spectra.resolve(),
                              work / "f.npy", work / "b.npy", out)  # fmt: skip
                colours[name] = np.load(out)
                row[name] = {
                    "seconds": s["seconds"],
                    "state_seconds": s["state_seconds"],
                    "wall_s": round(s["wall_s"], 3),
                    "points_per_s": s["points_per_s"],
                    "wall_points_per_s": round(n / s["wall_s"], 1),
                    "points_per_gflop": round(s["points_per_s"] / gflops, 1),
                    "wall_points_per_gflop": round(n / s["wall_s"] / gflops, 1),
                }
            if "baseline" in colours:
                diff = np.abs(colours["current"] - colours["baseline"]).max(axis=1)
                row["max_colour_difference"] = float(diff.max())
                row["points_beyond_1e-4"] = int((diff > 1e-4).sum())
            rows.append(row)
            print(json.dumps(row), flush=True)
    result = {
        "command": " ".join(["python", "benchmarks/query_cli.py", *sys.argv[1:]]),
        "machine": machine_info(),
        "matmul_gflops": round(gflops, 2),
        "threads": threads,
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "query_cli.json").write_text(json.dumps(result, indent=1))
    lines = [
        "# `hktex query` from outside (benchmarks/query_cli.py)",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {machine_line(result['machine'])}  ",
        f"Dense float32 matmul (2048^3, {threads} threads): {gflops:.1f} GFLOP/s.",
        "",
        "| points | side | eval s | state s | wall s | points/s (eval) | points/s (wall) "
        "| per GFLOP (eval) | per GFLOP (wall) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        for name, _, _ in sides:
            r = row[name]
            lines.append(
                f"| {row['points']:,} | {name} | {r['seconds']:.3f} | {r['state_seconds']:.2f} "
                f"| {r['wall_s']:.2f} | {r['points_per_s']:,.0f} | {r['wall_points_per_s']:,.0f} "
                f"| {r['points_per_gflop']:,.0f} | {r['wall_points_per_gflop']:,.0f} |"
            )
    if args.baseline_root is not None:
        lines += ["", "Colours, current against baseline (max difference; points beyond 1e-4):"]
        lines += [
            f"- {r['points']:,}: {r['max_colour_difference']:.2e}; {r['points_beyond_1e-4']}"
            for r in rows
        ]
    (args.out / "query_cli.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
