"""``hktex spectra``: compute a mesh's aligned ALBO grid and write the spectra directory."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from hktex_engine.cli import add_max_vertices
from hktex_engine.config import SpectralConfig


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text}") from exc
    if not values:
        raise argparse.ArgumentTypeError("empty list of anisotropies")
    return values


def _workers(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--workers must be an integer or 'auto': {text}") from exc


def register(subparsers: argparse._SubParsersAction) -> None:
    s = SpectralConfig()
    p = subparsers.add_parser(
        "spectra",
        help="compute the spectral grid (aligned ALBO eigenbases) of a mesh",
        description="Writes a spectra directory (docs/spectra.md) atomically: a grid of "
        "angles x anisotropies anisotropic Laplace-Beltrami eigenbases plus the isotropic "
        "spectrum, aligned for interpolation.",
    )
    p.add_argument("mesh", type=Path, help="mesh file (OBJ, PLY, GLB/glTF, OFF)")
    p.add_argument("-o", "--output", type=Path, required=True, help="spectra directory to write")
    p.add_argument("--angles", type=int, default=s.angles, help="angle nodes over [0, pi]")
    p.add_argument(
        "--anisotropies",
        type=_floats,
        default=s.anisotropies,
        help="eta nodes, comma-separated, ascending (default 1,5,15,30,60,100,200)",
    )
    p.add_argument("--k", type=int, default=s.k, help="eigenpairs per grid node")
    p.add_argument("--k-iso", type=int, default=s.k_iso, help="isotropic eigenpairs (>= 65)")
    p.add_argument(
        "--rotation",
        choices=("block", "full"),
        default=s.rotation,
        help="alignment: Procrustes inside eigenvalue clusters (block) or over all K (full)",
    )
    p.add_argument(
        "--evecs-dtype", choices=("float32", "float16"), default=s.evecs_dtype, help="storage"
    )
    p.add_argument(
        "--tangent-field",
        choices=("axis_smoothed", "curvature"),
        default=s.tangent_field,
        help="reference direction u_ref",
    )
    p.add_argument(
        "--solver",
        choices=("auto", "block", "cold", "warm"),
        default="auto",
        help="auto (default): block or cold, whichever was measured faster for the mesh "
        "size; block: block shift-invert Krylov-Schur per node; cold: ARPACK per node; "
        "warm: block iteration from the previous node",
    )
    p.add_argument(
        "--workers",
        type=_workers,
        default="auto",
        help="processes that solve nodes, this one included; 'auto' (default): the free cores",
    )
    add_max_vertices(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from hktex_engine.cli import TerminalProgress
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.spectra.cores import auto_workers
    from hktex_engine.spectra.grid import compute_spectra
    from hktex_engine.spectra.heap import keep_freed_memory

    # this process ends with the grid, and solves nodes beside its workers: its allocator
    # may keep what it frees (spectra.heap)
    keep_freed_memory()

    config = SpectralConfig(
        angles=args.angles,
        anisotropies=args.anisotropies,
        k=args.k,
        k_iso=args.k_iso,
        rotation=args.rotation,
        evecs_dtype=args.evecs_dtype,
        tangent_field=args.tangent_field,
    )
    if args.workers != "auto" and args.workers < 1:
        raise ValueError("--workers must be >= 1")
    if not args.mesh.is_file():
        raise FileNotFoundError(f"mesh file not found: {args.mesh}")
    if args.output.exists() and not (args.output / "manifest.json").is_file():
        raise ValueError(f"{args.output} exists and is not a spectra directory; not replacing it")
    t0 = time.perf_counter()
    mesh = load_mesh(args.mesh, max_vertices=args.max_vertices, read_texture=False)
    t_load = time.perf_counter() - t0
    if args.workers == "auto":
        # since the command line's first sample (``cli.main``), so the window auto_workers
        # needs is time the command has spent anyway
        args.workers = auto_workers(since=getattr(args, "cpu_since", None))
    bar = TerminalProgress("spectra")
    try:
        spectra = compute_spectra(
            mesh, config, bar, out_dir=args.output, solver=args.solver, workers=args.workers
        )
    finally:
        bar.close()
    manifest = spectra.manifest
    timings = {"load_s": t_load, **manifest.get("timings", {})}
    timings["wall_s"] = time.perf_counter() - t0
    return {
        "path": str(args.output),
        "n_vertices": mesh.n_vertices,
        "n_faces": mesh.n_faces,
        "nodes": manifest["sizes"]["nodes"],
        "k": config.k,
        "k_iso": config.k_iso,
        "timings": {k: round(float(v), 3) for k, v in timings.items()},
        "bytes": manifest.get("bytes"),
        "message": f"wrote {args.output} ({mesh.n_vertices} vertices, "
        f"{manifest['sizes']['nodes']} nodes x {config.k}, {manifest.get('bytes', 0) / 1e6:.1f} MB"
        f", {timings['wall_s']:.1f} s)",
    }
