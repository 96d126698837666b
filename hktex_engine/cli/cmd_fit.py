"""``hktex fit``: fit a kernel set to a mesh's texture (UV fitting) or to views (multi-view)."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from hktex_engine.cli import add_max_vertices
from hktex_engine.config import (
    COLOURS,
    DEFAULT_PRESET,
    PRESET_SPECTRA_K,
    PRESETS,
    SIGMAS,
    FitParams,
    SpectralConfig,
    fit_params_from,
    spectra_k_for,
)

#: where computed spectra are cached when --spectra is not given (override: HKTEX_CACHE_DIR)
DEFAULT_CACHE = Path(os.environ.get("HKTEX_CACHE_DIR", Path.home() / ".cache" / "hktex"))


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text}") from exc


def register(subparsers: argparse._SubParsersAction) -> None:
    d = PRESETS[DEFAULT_PRESET]
    s = SpectralConfig()
    p = subparsers.add_parser(
        "fit",
        help="fit a heat-kernel texture (.hkt) to a textured mesh or to views",
        description="UV fitting (the mesh's albedo texture, or --texture) or multi-view fitting "
        "(--views DIR). Spectra come from --spectra or are computed once into a cache.",
    )
    p.add_argument("mesh", type=Path, help="mesh file (OBJ, PLY, GLB/glTF, OFF)")
    p.add_argument("-o", "--output", type=Path, required=True, help="kernel-set file to write")
    p.add_argument("--texture", type=Path, help="albedo image (default: the mesh's own)")
    p.add_argument("--views", type=Path, help="multi-view dataset directory (docs/views.md)")
    p.add_argument("--spectra", type=Path, help="spectra directory (default: compute/cache)")
    p.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE, help="spectra cache root")
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default=DEFAULT_PRESET,
        help="base configuration (ALGORITHM.md §7b); the flags below override it",
    )
    p.add_argument("--kernels", type=int, default=None, help=f"initial kernel count ({d.kernels})")
    p.add_argument("--max-kernels", type=int, default=None, help="budget (default from preset)")
    p.add_argument("--steps", type=int, default=None, help=f"optimisation steps ({d.steps})")
    p.add_argument("--seed", type=int, default=None, help=f"random seed ({d.seed})")
    p.add_argument("--points-per-step", type=int, default=None, help=f"({d.points_per_step})")
    p.add_argument("--no-densify", action="store_true", help="keep the kernel count fixed")
    p.add_argument(
        "--blend",
        choices=("paper", "layered"),
        default=None,
        help="colour rule: the paper's average, or layered (a learnable priority per kernel;"
        " writes .hkt version 5/6, docs/kernels.md)",
    )
    p.add_argument(
        "--sigma",
        choices=SIGMAS,
        default=None,
        help="biharmonic scale: uniform (§4's one sigma_B) or per_kernel (learnt from 40 %% of the steps;"
        " writes .hkt version 7/8, which a §4-5 reader cannot score; on the default it is"
        " --preset sigma, above the default and the MLP on all five shared meshes,"
        " docs/fitting.md)",
    )
    p.add_argument(
        "--colour",
        choices=COLOURS,
        default=None,
        help="what a kernel's colour is: constant (§4) or linear (a colour slope per kernel,"
        " trained from 40 %% of the steps of a UV fit; writes .hkt version 9/10, which a §4-5"
        " reader cannot score; docs/fitting.md, eighteenth pass)",
    )
    p.add_argument(
        "--polish-colors",
        action=argparse.BooleanOptionalAction,
        default=None,
        help=f"least-squares colour solve after the last step ({d.polish_colors})",
    )
    p.add_argument(
        "--sampling",
        choices=("uniform", "error"),
        default=None,
        help=f"training points: fresh uniform, or drawn where the error is ({d.sampling})",
    )
    p.add_argument(
        "--quantise",
        action="store_true",
        help="write the quantised .hkt (format 4), its code widths chosen for this fit's accuracy"
        " (UV fits: the narrowest within 0.08 dB of the exact set; ~8-10 B/kernel)",
    )
    p.add_argument("--checkpoint-dir", type=Path, help="resumable fit: checkpoints go here")
    p.add_argument("--eval-points", type=int, default=60_000, help="surface-PSNR sample count")
    p.add_argument("--device", default=None, help="torch device (default: cuda if present)")
    add_max_vertices(p)
    p.add_argument("--angles", type=int, default=s.angles, help="spectra: angle nodes")
    p.add_argument(
        "--anisotropies", type=_floats, default=s.anisotropies, help="spectra: eta nodes, a,b,c"
    )
    p.add_argument(
        "--k",
        type=int,
        default=None,
        help=f"spectra: eigenpairs per node (default {s.k}; {PRESET_SPECTRA_K} for those presets)",
    )
    p.add_argument("--k-iso", type=int, default=s.k_iso, help="spectra: isotropic eigenpairs")
    p.set_defaults(func=run)


def _params(args: argparse.Namespace) -> FitParams:
    params = fit_params_from(
        {
            "preset": args.preset,
            "kernels": args.kernels,
            "max_kernels": args.max_kernels,
            "steps": args.steps,
            "seed": args.seed,
            "points_per_step": args.points_per_step,
            "densify": False if args.no_densify else None,
            "polish_colors": args.polish_colors,
            "sampling": args.sampling,
            "blend": args.blend,
            "sigma": args.sigma,
            "colour": args.colour,
        }
    )
    if params.kernels < 1 or params.steps < 0 or params.points_per_step < 1:
        raise ValueError("--kernels and --points-per-step must be >= 1, --steps >= 0")
    if params.max_kernels is not None and params.max_kernels < params.kernels:
        raise ValueError("--max-kernels must be >= --kernels")
    return params


def run(args: argparse.Namespace) -> dict:
    from hktex_engine.cli import TerminalProgress
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import SpectraCache, load_spectra

    params = _params(args)
    if not args.mesh.is_file():
        raise FileNotFoundError(f"mesh file not found: {args.mesh}")
    if args.texture is not None and not args.texture.is_file():
        raise FileNotFoundError(f"texture file not found: {args.texture}")
    if args.views is not None and not args.views.is_dir():
        raise FileNotFoundError(f"views directory not found: {args.views}")
    if not args.output.parent.is_dir():
        raise FileNotFoundError(f"output directory does not exist: {args.output.parent}")
    t0 = time.perf_counter()
    mesh = load_mesh(args.mesh, texture=args.texture, max_vertices=args.max_vertices)
    if args.spectra is not None:
        spectra = load_spectra(args.spectra, expect_mesh_hash=mesh.content_hash)
    else:
        config = SpectralConfig(
            angles=args.angles,
            anisotropies=args.anisotropies,
            k=args.k if args.k is not None else spectra_k_for(args.preset),
            k_iso=args.k_iso,
        )
        bar = TerminalProgress("spectra")
        try:
            spectra = SpectraCache(args.cache_dir / "spectra").get_or_compute(mesh, config, bar)
        finally:
            bar.close()
    bar = TerminalProgress("fit")
    try:
        if args.views is not None:
            # multi-view fitting lives with the renderer (Mitsuba); import only when asked
            from hktex_engine.fitting.multiview import fit_multiview
            from hktex_engine.fitting.views import load_views

            result = fit_multiview(
                mesh,
                spectra,
                load_views(args.views),
                params,
                bar,
                args.checkpoint_dir,
                args.device,
            )
            task = "fit_multiview"
        else:
            from hktex_engine.fitting.uv import fit_uv

            result = fit_uv(
                mesh, spectra, params, bar, args.checkpoint_dir, args.device, args.eval_points
            )
            task = "fit_uv"
    finally:
        bar.close()
    metrics = dict(result.metrics)
    # a UV fit chose its file's code widths for its own accuracy (fitting.quantisation)
    bits = (metrics.get("quantisation") or {}).get("bits")
    save_hkt(result.kernelset, args.output, quantised=args.quantise, bits=bits)
    psnr = metrics.get("surface_psnr", metrics.get("psnr"))
    return {
        "task": task,
        "output": str(args.output),
        "spectra": str(spectra.path) if spectra.path is not None else None,
        "kernels": len(result.kernelset),
        "metrics": metrics,
        "seconds": time.perf_counter() - t0,
        "message": f"wrote {args.output} ({len(result.kernelset)} kernels"
        + (f", PSNR {psnr:.2f} dB)" if isinstance(psnr, float) else ")"),
    }
