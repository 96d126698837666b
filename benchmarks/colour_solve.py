"""The least-squares colour solve applied to saved kernel sets: fresh-point PSNR before/after.

    python benchmarks/colour_solve.py SET.hkt [SET.hkt ...] --mesh spot [--angles 7 --k 64]
        [--damp 0.3] [--passes 2] [--points-per-kernel 30]

The spectra come from the cache (``~/.cache/hktex/spectra``, the grid given). Surface PSNR is
EVALUATION.md's (60,000 points, seed 0); the solve draws its own points with seed 1, so the
evaluation points are fresh. Appends one JSON line per set to
benchmarks/results/colour_solve.jsonl and prints it.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
from _machine import machine_info, machine_line
from fidelity import DATA, MESHES, RESULTS

from hktex_engine.config import SpectralConfig
from hktex_engine.evaluation.metrics import psnr, surface_samples
from hktex_engine.fitting.colour_solve import solve_colours
from hktex_engine.fitting.uv import evaluate_albedo
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.kernels.hkt import load_hkt
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.grid import SpectraCache
from hktex_engine.spectra.interpolation import SpectralField


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("sets", nargs="+", type=Path)
    ap.add_argument("--mesh", default="spot", choices=sorted(MESHES))
    ap.add_argument("--angles", type=int, default=7)
    ap.add_argument("--k", type=int, default=64)
    ap.add_argument("--damp", type=float, default=0.3)
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--points-per-kernel", type=int, default=30)
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hktex" / "spectra")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    command = "python benchmarks/colour_solve.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    obj, tex = MESHES[args.mesh]
    mesh = load_mesh(DATA / obj, texture=(DATA / tex) if tex else None)
    spectra = SpectraCache(args.cache).get_or_compute(
        mesh, SpectralConfig(angles=args.angles, k=args.k)
    )
    eval_f, eval_b, target = surface_samples(mesh, 60_000, 0)
    for path in args.sets:
        ks = load_hkt(path, expect_mesh_hash=spectra.mesh_hash)
        model = HeatKernelModel.from_kernelset(ks, SpectralField(spectra))
        before = psnr(evaluate_albedo(model, eval_f, eval_b), target)
        t0 = time.perf_counter()
        info = solve_colours(
            model,
            mesh,
            args.points_per_kernel * len(model),
            np.random.default_rng(1),
            damp=args.damp,
            passes=args.passes,
        )
        seconds = time.perf_counter() - t0
        after = psnr(evaluate_albedo(model, eval_f, eval_b), target)
        row = {
            "set": path.name,
            "mesh": args.mesh,
            "kernels": len(model),
            "damp": args.damp,
            "passes": args.passes,
            "psnr_before": before,
            "psnr_after": after,
            "gain_db": after - before,
            "solve": info,
            "solve_s": seconds,
            "command": command,
            "machine": machine_line(machine_info()),
        }
        args.out.mkdir(parents=True, exist_ok=True)
        with (args.out / "colour_solve.jsonl").open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
