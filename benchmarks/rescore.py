"""A fitted set rescored with some of its parameters changed, no refit: is the fit at an optimum?

    python benchmarks/rescore.py --mesh blub --hkt SET.hkt \\
        --sharpness-scale 1.25 1.5 --where all small large \\
        --search-blend 100:30 30:30 50:10 [--k 128]

Each variant changes one thing in the saved set and scores it on the fidelity benchmark's
points (EVALUATION.md: 60,000 area-uniform points, seed 0), beside the set as fitted:

- ``--sharpness-scale S --where W``: every chosen kernel's sharpness ``k`` times ``S``
  (clamped to ALGORITHM.md section 4's 200); ``small`` = threshold above 0.9 (footprints
  under ~0.45 sigma_B: the eyes' and highlights' kernels on blub), ``large`` = the rest.
  If the fit left edges softer than its own loss wants, sharpening gains.
- ``--search-blend KS:KC``: the set evaluated with another candidate count ``K_s`` and
  blend count ``K_c`` than it was fitted with (ALGORITHM.md section 5). A change shows how
  much the fitted colours depend on the cut.
- ``--sigma-clamp C``, on a set with a scale per kernel (``sigma_ratio``, ``.hkt`` 7/8): the
  ratios clamped, ``narrow`` = none above 1 (only the kernels that learnt a wider scale
  lose it), ``wide`` = none below 1, ``one`` = all 1 (the §4 scale for every kernel). Which
  side of the learnt scales carries the gain.
- ``--solve constant|linear``: the set's colours re-solved by the fit's least-squares colour
  solve on ``--solve-points`` fresh points a kernel (``linear``: colours and colour slopes
  together, the set becoming a linear-colour one; ``fitting/colour_solve.py``), without the
  fit's validation guard: what the solve itself does to fresh points.

``--eval-points`` / ``--eval-seed`` change the scoring points (default: the benchmark's 60,000,
seed 0). A set whose error sits on a few edge points is scored noisily by 60,000 (on the smooth
held-out asset, 0.05 % of the points carry a third of the error): 400,000 narrow that.

Rows (with the machine and command) go to ``--out`` as JSON lines; nothing is refitted, so a
row costs seconds. Used in docs/fitting.md's thirteenth pass.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from _machine import machine_info

from hktex_engine.evaluation.diagnostics import edge_flat_split
from hktex_engine.evaluation.metrics import psnr, surface_samples
from hktex_engine.fitting.colour_solve import solve_colours
from hktex_engine.fitting.uv import evaluate_albedo
from hktex_engine.kernels.hkt import load_hkt
from hktex_engine.kernels.model import SHARPNESS_RANGE, HeatKernelModel, KernelSet
from hktex_engine.spectra.interpolation import SpectralField

#: A kernel whose threshold is above this draws a footprint under ~0.45 sigma_B in radius.
SMALL_THRESHOLD = 0.9


def sharpened(ks: KernelSet, scale: float, where: str) -> KernelSet:
    """``ks`` with the sharpness of the ``where`` kernels times ``scale``, kept in range."""
    small = np.asarray(ks.threshold) > SMALL_THRESHOLD
    chosen = {"all": np.ones_like(small), "small": small, "large": ~small}[where]
    k = np.asarray(ks.sharpness, dtype=np.float64)
    return replace(ks, sharpness=np.where(chosen, np.minimum(k * scale, SHARPNESS_RANGE[1]), k))


def with_counts(ks: KernelSet, k_search: int, k_blend: int) -> KernelSet:
    """``ks`` read with another ``K_s`` / ``K_c`` than it was fitted with."""
    return replace(ks, kernel_config=replace(ks.kernel_config, k_search=k_search, k_blend=k_blend))


def sigma_clamped(ks: KernelSet, clamp: str) -> KernelSet:
    """``ks`` with its per-kernel scale ratios clamped (``narrow``: at most 1; ``wide``: at
    least 1; ``one``: all 1), so the set reads each kernel at that scale."""
    if ks.sigma_ratio is None:
        raise SystemExit("--sigma-clamp needs a set with a scale per kernel (sigma_ratio)")
    ratio = np.asarray(ks.sigma_ratio, dtype=np.float64)
    lo, hi = {"narrow": (None, 1.0), "wide": (1.0, None), "one": (1.0, 1.0)}[clamp]
    return replace(ks, sigma_ratio=np.clip(ratio, lo, hi))


def solved(mesh, field: SpectralField, ks: KernelSet, kind: str, per_kernel: int) -> KernelSet:
    """``ks`` with its colours (and, ``linear``, colour slopes) re-solved by least squares on
    ``per_kernel`` fresh points a kernel (seed 7, not the scoring points)."""
    model = HeatKernelModel.from_kernelset(ks, field)
    rng = np.random.default_rng(7)
    solve_colours(model, mesh, per_kernel * len(model), rng, linear=kind == "linear")
    return model.to_kernelset(ks.color_space, ks.fitting, ks.extras)


def score(mesh, field: SpectralField, ks: KernelSet, points: tuple) -> dict:
    """Surface PSNR and the edge/flat split of ``ks`` on the benchmark's points."""
    f, b, target = points
    pred = evaluate_albedo(HeatKernelModel.from_kernelset(ks, field), f, b)
    split = edge_flat_split(mesh, pred, target, f, b)
    return {
        "surface_psnr": psnr(pred, target),
        "psnr_edge": split["psnr_edge"],
        "psnr_flat": split["psnr_flat"],
    }


def main() -> int:
    sys.path.insert(0, str(Path(__file__).parent))
    from fidelity import add_mesh_file_argument, named_mesh_and_spectra

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", required=True, help="a shared mesh or a --mesh-file name")
    add_mesh_file_argument(ap)
    ap.add_argument("--hkt", required=True, type=Path)
    ap.add_argument("--k", type=int, default=128, help="the spectra's K the set was fitted on")
    ap.add_argument("--sharpness-scale", type=float, nargs="*", default=[])
    ap.add_argument("--where", nargs="*", default=["all"], choices=["all", "small", "large"])
    ap.add_argument("--search-blend", nargs="*", default=[], help="KS:KC pairs")
    ap.add_argument("--sigma-clamp", nargs="*", default=[], choices=["narrow", "wide", "one"])
    ap.add_argument("--solve", nargs="*", default=[], choices=["constant", "linear"])
    ap.add_argument("--solve-points", type=int, default=80, help="solve points a kernel")
    ap.add_argument("--eval-points", type=int, default=60_000)
    ap.add_argument("--eval-seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rescore.jsonl"))
    args = ap.parse_args()

    mesh, spectra = named_mesh_and_spectra(args.mesh_file, args.mesh, args.k)
    field = SpectralField(spectra)
    points = surface_samples(mesh, args.eval_points, args.eval_seed)
    ks = load_hkt(args.hkt)
    cfg = ks.kernel_config
    variants: list[tuple[str, KernelSet]] = [("as fitted", ks)]
    variants += [
        (f"sharpness x{s:g} on {w}", sharpened(ks, s, w))
        for w in args.where
        for s in args.sharpness_scale
    ]
    for pair in args.search_blend:
        k_s, k_c = (int(v) for v in pair.split(":"))
        variants.append(
            (
                f"K_s {k_s}, K_c {k_c} (fitted: {cfg.k_search}, {cfg.k_blend})",
                with_counts(ks, k_s, k_c),
            )
        )
    variants += [(f"scale ratios clamped: {c}", sigma_clamped(ks, c)) for c in args.sigma_clamp]
    variants += [
        (f"colours solved: {k}, {args.solve_points} points a kernel", solved(mesh, field, ks, k, args.solve_points))
        for k in args.solve
    ]  # fmt: skip
    base = None
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    machine = machine_info()
    with args.out.open("a") as fh:
        for name, variant in variants:
            row = {"mesh": args.mesh, "set": args.hkt.name, "variant": name}
            row["eval_points"], row["eval_seed"] = args.eval_points, args.eval_seed
            row |= score(mesh, field, variant, points)
            base = row["surface_psnr"] if base is None else base
            row["delta_db"] = row["surface_psnr"] - base
            row["command"], row["machine"] = command, machine
            fh.write(json.dumps(row) + "\n")
            print(
                f"{name:45s} {row['surface_psnr']:.2f} dB ({row['delta_db']:+.2f}), "
                f"edge {row['psnr_edge']:.2f}, flat {row['psnr_flat']:.2f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
