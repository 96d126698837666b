"""Fit-loop speed: the same UV fit by the current engine and a baseline commit, alternately.

    python benchmarks/fit_step.py [--mesh spot] [--steps 150] [--kernels 5000]
        [--points 4096] [--baseline 385fb2f] [--rounds 2] [--threads 1]

Each side runs ``fit_uv`` on a shared mesh (../shared/data) with the default preset
(``config.fit_preset("default")``: the product's kernel configuration, 4,096 points per step,
error-driven sampling, density control) at ``--kernels`` kernels (the budget held fixed, so
the steps are the budget's steady state), ``--steps`` steps, in its own process started
outside the repository with ``PYTHONPATH`` at that side's tree (a ``git worktree`` of the
baseline). The figure is the loop's own time (forward,
backward, optimiser, geodesic centre steps, density control, error sampling; ``FitResult.
timings["fit_s"]``) per step; the
sides alternate so the shared machine's load falls on both. Both fits draw the same points;
their final PSNR is reported beside (the compiled path sums in another order, so the fits
drift apart by round-off over the steps, not systematically).

Writes benchmarks/results/fit_step.json and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine_info

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

CHILD = r"""
import json, sys, time
import torch
from pathlib import Path
torch.set_num_threads(int(sys.argv[5]))
import hktex_engine
from hktex_engine.config import SpectralConfig, fit_preset
from hktex_engine.fitting.uv import fit_uv
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.spectra.grid import SpectraCache
obj, tex, steps, kernels, _, points = sys.argv[1:7]
mesh = load_mesh(Path(obj), texture=Path(tex))
spectra = SpectraCache(Path.home() / ".cache/hktex/spectra").get_or_compute(mesh, SpectralConfig())
params = fit_preset("default", steps=int(steps), kernels=int(kernels), max_kernels=int(kernels),
                    points_per_step=int(points), polish_colors=False)
res = fit_uv(mesh, spectra, params, eval_points=20000)
print(json.dumps({"fit_s": res.timings["fit_s"], "steps": int(steps),
                  "kernels": res.metrics["kernels"], "psnr": res.metrics["surface_psnr"],
                  "engine": hktex_engine.__file__}))
"""

MESHES = {
    "spot": ("spot/spot_triangulated.obj", "spot/spot_texture.png"),
    "bob": ("bob/bob_tri.obj", "bob/bob_diffuse.png"),
    "blub": ("blub/blub_triangulated.obj", "blub/blub_texture.png"),
}


def run_side(tree: Path, args, work: Path) -> dict:
    obj, tex = (DATA / p for p in MESHES[args.mesh])
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, "-c", CHILD, str(obj), str(tex), str(args.steps), str(args.kernels)]
    cmd += [str(args.threads), str(args.points)]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"{tree}: the fit failed:\n{out.stderr[-3000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["process_s"] = round(time.perf_counter() - t0, 1)
    res["s_per_step"] = res["fit_s"] / res["steps"]
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="spot", choices=sorted(MESHES))
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--kernels", type=int, default=5000)
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--baseline", default="385fb2f", help="git ref of the baseline engine")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="hktex_fit_step_"))
    base_tree = work / "baseline"
    subprocess.run(
        ["git", "worktree", "add", "--detach", str(base_tree), args.baseline],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    runs: dict = {"baseline": [], "current": []}
    load_before = round(os.getloadavg()[0], 2)
    try:
        for _ in range(args.rounds):
            for name, tree in (("baseline", base_tree), ("current", ROOT)):
                runs[name].append(run_side(tree, args, work))
                print(name, json.dumps(runs[name][-1]), flush=True)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(base_tree)], cwd=ROOT)
        shutil.rmtree(work, ignore_errors=True)
    med = {n: statistics.median(r["s_per_step"] for r in runs[n]) for n in runs}
    res = {
        "command": "python " + " ".join(sys.argv),
        "machine": machine_info(device="cpu"),
        "torch": _torch_version(),
        "load_before": load_before,
        "load_after": round(os.getloadavg()[0], 2),
        "args": {k: str(v) for k, v in vars(args).items()},
        "runs": runs,
        "median_s_per_step": med,
        "ratio": round(med["baseline"] / med["current"], 2),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fit_step.json").write_text(json.dumps(res, indent=1))
    (args.out / "fit_step.md").write_text(render_md(res))
    print(render_md(res))


def _torch_version() -> str:
    out = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.__version__)"],
        capture_output=True,
        text=True,
    )
    return out.stdout.strip()


def render_md(res: dict) -> str:
    a, m = res["args"], res["machine"]
    lines = [
        "# Fit-loop speed (benchmarks/fit_step.py)",
        "",
        f"Command: `{res['command']}`  ",
        f"Machine: {m.get('cpu', m.get('platform'))}, {m['cpus']} CPU cores, torch "
        f"{res['torch']}, {a['threads']} thread(s); load {res['load_before']} before, "
        f"{res['load_after']} after.  ",
        f"Fit: `fit_uv` on {a['mesh']}, default preset, {a['kernels']} kernels (budget fixed), "
        f"{a['points']} points per step, {a['steps']} steps; baseline engine at "
        f"`{a['baseline']}`, alternating.",
        "",
        "| side | loop s per step (each run) | median | final PSNR dB | kernels |",
        "|---|---|---:|---:|---:|",
    ]
    for name in ("baseline", "current"):
        r = res["runs"][name]
        each = ", ".join(f"{x['s_per_step']:.3f}" for x in r)
        lines.append(
            f"| {name} | {each} | {res['median_s_per_step'][name]:.3f} | {r[-1]['psnr']:.2f} | "
            f"{r[-1]['kernels']} |"
        )
    lines += ["", f"**{res['ratio']}x** fewer seconds per step than the baseline."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
