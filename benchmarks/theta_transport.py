"""A/B: UV fits with kernel orientation carried across faces versus theta kept as a number.

    python benchmarks/theta_transport.py [--seeds 7,8,9] [--steps 60] [--blob-steps 120]

A kernel's theta is measured from its centre face's u_ref. With ``transport_theta=True`` a
centre stepping into another face (and a split child landing in one) has its long axis
parallel-transported along the path and theta re-expressed there (optimise.theta_in_faces);
"off" is ``fit_uv(..., transport_theta=False)``, the default: theta kept as a number. Same
seeds, same initialisation, same batches: only the orientation handling differs.

Cases: the two-colour icosphere of tests/test_fit_uv.py (150 kernels, density off, the test's
learning rates) and the procedural textured blob (synthetic.textured_demo(3), density on,
reference rates). Also counts how many kernels changed face per step (where re-expression
acts). Writes benchmarks/results/theta_transport.json and .md with the command and machine.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from _machine import machine_info, machine_line

from hktex_engine.config import FitParams, SpectralConfig
from hktex_engine.evaluation.synthetic import icosphere, textured_demo
from hktex_engine.fitting.optimise import KernelOptimiser
from hktex_engine.fitting.uv import fit_uv
from hktex_engine.geometry.mesh import mesh_from_arrays
from hktex_engine.spectra.grid import compute_spectra

ROOT = Path(__file__).resolve().parents[1]
TINY = SpectralConfig(angles=3, anisotropies=(1.0, 10.0), k=16, k_iso=9)


def two_colour_mesh():
    """The icosphere of tests/test_fit_uv.py: red where x < 0, blue elsewhere."""
    v, f = icosphere(2)
    tex = np.zeros((4, 4, 3), dtype=np.float32)
    tex[:, :2], tex[:, 2:] = [0.9, 0.1, 0.1], [0.1, 0.2, 0.9]
    left = v[f].mean(axis=1)[:, 0] < 0
    uv = np.where(left[:, None, None], [0.25, 0.5], [0.75, 0.5]) * np.ones((len(f), 3, 2))
    return mesh_from_arrays(v, f, corner_uvs=uv, texture=tex)


def blob_mesh():
    v, f, uv, tex = textured_demo(3, 128)
    return mesh_from_arrays(v, f, corner_uvs=uv, texture=tex)


class _Counter:
    """Counts kernels that changed face at each centre step (wraps KernelOptimiser._reorient)."""

    def __init__(self) -> None:
        self.changed: list[int] = []
        self.total: list[int] = []


@contextmanager
def counting(counter: _Counter):
    """Record per step how many kernels changed face (only called with transport on)."""
    orig = KernelOptimiser._reorient

    def wrapped(self, f0, f1, axes):
        counter.changed.append(int((f1 != f0).sum()))
        counter.total.append(int(f0.shape[0]))
        return orig(self, f0, f1, axes)

    try:
        KernelOptimiser._reorient = wrapped
        yield
    finally:
        KernelOptimiser._reorient = orig


def run_case(name, mesh, spectra, params, eval_points) -> list[dict]:
    rows = []
    for mode in ("off", "on"):
        counter = _Counter()
        t = time.perf_counter()
        with counting(counter):
            res = fit_uv(
                mesh, spectra, params, eval_points=eval_points, transport_theta=mode == "on"
            )
        frac = (
            float(np.sum(counter.changed) / max(1, np.sum(counter.total)))
            if counter.total
            else None
        )
        rows.append(
            {
                "case": name,
                "mode": mode,
                "seed": params.seed,
                "steps": params.steps,
                "psnr": round(float(res.metrics["surface_psnr"]), 3),
                "psnr_initial": round(float(res.metrics["surface_psnr_initial"]), 3),
                "kernels": int(res.metrics["kernels"]),
                "face_changes_per_step_fraction": frac,
                "seconds": round(time.perf_counter() - t, 1),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="7,8,9")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--blob-steps", type=int, default=120)
    ap.add_argument("--blob-seeds", default="7")
    ap.add_argument("--eval-points", type=int, default=4000)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows: list[dict] = []
    sphere = two_colour_mesh()
    sphere_spectra = compute_spectra(sphere, TINY)
    for seed in (int(s) for s in args.seeds.split(",") if s):
        params = FitParams(
            kernels=150,
            max_kernels=300,
            steps=args.steps,
            points_per_step=256,
            seed=seed,
            densify=False,
            lr_colors=0.05,
            lr_threshold=0.03,
        )
        rows += run_case("two-colour sphere", sphere, sphere_spectra, params, args.eval_points)
    if args.blob_steps > 0:
        blob = blob_mesh()
        blob_spectra = compute_spectra(blob, TINY)
        for seed in (int(s) for s in args.blob_seeds.split(",") if s):
            params = FitParams(
                kernels=300, max_kernels=1200, steps=args.blob_steps, points_per_step=512, seed=seed
            )
            rows += run_case("textured blob", blob, blob_spectra, params, args.eval_points)
    out = {
        "command": "python benchmarks/theta_transport.py " + shlex.join(sys.argv[1:]),
        "machine": machine_info(),
        "rows": rows,
    }
    res_dir = ROOT / "benchmarks" / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / "theta_transport.json").write_text(json.dumps(out, indent=2))
    lines = [
        "# Kernel orientation across faces: A/B",
        "",
        f"Command: `{out['command']}`  ",
        f"Machine: {machine_line(out['machine'])}",
        "",
        "| case | seed | steps | theta handling | PSNR dB | initial dB | kernels "
        "| face changes / kernel-step | s |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        mode = "transported" if r["mode"] == "on" else "kept as number (default)"
        frac = r["face_changes_per_step_fraction"]
        lines.append(
            f"| {r['case']} | {r['seed']} | {r['steps']} | {mode} | {r['psnr']:.2f} "
            f"| {r['psnr_initial']:.2f} | {r['kernels']} "
            f"| {'' if frac is None else f'{frac:.4f}'} | {r['seconds']} |"
        )
    (res_dir / "theta_transport.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
