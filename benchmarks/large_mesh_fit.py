"""``hktex fit`` on a large mesh, as a user runs it: step rate and peak memory.

    python benchmarks/large_mesh_fit.py [--major 512 --minor 250] [--steps 200]
        [--baseline-root DIR] [--out DIR]

A real asset the project has never seen may have 100k+ vertices, where the default grid's
float32 copy passes the training path's cap (``fused_rank.EVECS32_MAX_BYTES``). This writes
the held-out textured torus of ``textured_torus.py`` at that size, computes its spectra once
(shared cache), then runs ``hktex fit --steps N --no-polish-colors`` as a fresh process per
side (this checkout, and ``--baseline-root``, an earlier checkout, when given), recording the
fit's own steps per second, the whole command's wall time and its peak RSS. Writes
``large_mesh_fit.json`` and ``.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _machine import machine_info, machine_line
from textured_torus import write

ROOT = Path(__file__).resolve().parents[1]


def run_fit(root: Path, mesh: Path, texture: Path, steps: int, cache: Path, out: Path) -> dict:
    """One ``hktex fit`` process of the tree at ``root``: its JSON summary, wall time and
    peak RSS (read from the child's own rusage by a wrapper, so sides do not mix)."""
    fit = [sys.executable, "-m", "hktex_engine", "--json", "fit", str(mesh), "--texture",
           str(texture), "-o", str(out), "--steps", str(steps), "--max-vertices", "1000000",
           "--cache-dir", str(cache), "--no-polish-colors"]  # fmt: skip
    wrapper = (
        "import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]);"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr);"
        "sys.exit(r.returncode)"
    )
    env = {**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", wrapper, *fit], check=True, cwd=root, env=env,
                          capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    return {
        "steps_per_second": round(summary["metrics"]["steps_per_second"], 3),
        "surface_psnr": round(summary["metrics"]["surface_psnr"], 3),
        "fit_seconds": round(summary["seconds"], 1),
        "wall_s": round(wall, 1),
        "peak_rss_gb": round(int(done.stderr.strip().splitlines()[-1]) / 2**20, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--major", type=int, default=512)
    ap.add_argument("--minor", type=int, default=250)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--baseline-root", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=Path("/tmp/hktex-large-mesh"))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    mesh = write(args.work / f"torus_{args.major}x{args.minor}", args.major, args.minor, 2048)
    texture = mesh.with_name("torus_texture.png")
    cache = args.work / "cache"
    sides = [("current", ROOT)]
    if args.baseline_root is not None:
        sides.append(("baseline", args.baseline_root.resolve()))
    # the spectra once, outside the timed runs (both sides read the same cache entry)
    run_fit(ROOT, mesh, texture, 1, cache, args.work / "warm.hkt")
    rows = {name: run_fit(root, mesh, texture, args.steps, cache, args.work / f"{name}.hkt")
            for name, root in sides}  # fmt: skip
    result = {
        "command": " ".join(["python", "benchmarks/large_mesh_fit.py", *sys.argv[1:]]),
        "machine": machine_info(),
        "vertices": args.major * args.minor,
        "steps": args.steps,
        "rows": rows,
    }
    if "baseline" in rows:
        result["speedup"] = round(
            rows["current"]["steps_per_second"] / rows["baseline"]["steps_per_second"], 2
        )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "large_mesh_fit.json").write_text(json.dumps(result, indent=1))
    lines = [
        "# `hktex fit` on a large mesh (benchmarks/large_mesh_fit.py)",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {machine_line(result['machine'])}  ",
        f"Mesh: textured torus, {result['vertices']:,} vertices; {args.steps} steps, spectra "
        "cached beforehand",
        "",
        "| side | steps/s | fit s | wall s | peak RSS GB | surface PSNR dB |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['steps_per_second']} | {r['fit_seconds']} | {r['wall_s']} | "
            f"{r['peak_rss_gb']} | {r['surface_psnr']} |"
        )
    if "speedup" in result:
        lines += ["", f"Steps per second, current over baseline: **{result['speedup']}x**"]
    (args.out / "large_mesh_fit.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
