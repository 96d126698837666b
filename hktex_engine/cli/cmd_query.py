"""``hktex query``: albedo of a kernel set at surface points or 3-D points, to a .npy file."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from hktex_engine.errors import QueryError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "query",
        help="albedo of a kernel set at surface points (.npy in, .npy out)",
        description="Evaluate a fitted kernel set at (face, barycentric) surface points or at "
        "the surface points closest to 3-D points given in the mesh file's units.",
    )
    p.add_argument("kernels", type=Path, help="kernel-set file (.hkt)")
    p.add_argument("--spectra", type=Path, required=True, help="spectra directory")
    p.add_argument("--faces", type=Path, help="face ids, (P,) integer .npy")
    p.add_argument("--barycentrics", type=Path, help="barycentrics, (P, 3) float .npy")
    p.add_argument("--points", type=Path, help="3-D points in file units, (P, 3) float .npy")
    p.add_argument("-o", "--output", type=Path, required=True, help="colours, (P, 3) float32 .npy")
    p.add_argument("--device", default=None, help="torch device (default: cuda if present)")
    p.add_argument("--chunk-points", type=int, default=None, help="points per evaluation chunk")
    p.set_defaults(func=run)


def _load_array(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise QueryError(f"{what} file {path} is not a plain .npy array: {exc}") from exc


def run(args: argparse.Namespace) -> dict:
    from hktex_engine.cli import TerminalProgress, load_kernelset_with_spectra
    from hktex_engine.kernels.query import AlbedoQuery

    by_points = args.points is not None
    if by_points == (args.faces is not None or args.barycentrics is not None):
        raise QueryError("give either --points, or both --faces and --barycentrics")
    if not by_points and (args.faces is None or args.barycentrics is None):
        raise QueryError("--faces and --barycentrics go together")
    spectra, kernelset = load_kernelset_with_spectra(args.kernels, args.spectra)
    inputs = (
        [_load_array(args.points, "points")]
        if by_points
        else [_load_array(args.faces, "faces"), _load_array(args.barycentrics, "barycentrics")]
    )
    # a call with at least one point per vertex builds the candidate tables with the query
    # state (timed apart from the evaluation: "state_seconds")
    dense = int(inputs[0].shape[0]) >= spectra.vertices.shape[0] if inputs[0].ndim else False
    state_start = time.perf_counter()
    query = AlbedoQuery(
        spectra,
        kernelset,
        device=args.device,
        chunk_points=args.chunk_points,
        tables=True if dense else None,
    )
    state_seconds = time.perf_counter() - state_start
    progress = TerminalProgress("query")
    start = time.perf_counter()
    try:
        if by_points:
            colors = query.colors_at_points(inputs[0], progress)
        else:
            colors = query.colors(inputs[0], inputs[1], progress)
    finally:
        progress.close()
    seconds = time.perf_counter() - start
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with open(args.output, "wb") as fh:  # np.save(path) would append ".npy" to other names
        np.save(fh, colors, allow_pickle=False)
    count = int(colors.shape[0])
    return {
        "output": str(args.output),
        "count": count,
        "kernels": len(kernelset),
        "seconds": round(seconds, 4),
        "state_seconds": round(state_seconds, 4),
        "points_per_s": round(count / seconds, 1) if seconds > 0 else None,
        "device": str(query.device),
        "message": f"wrote {count} colours to {args.output} in {seconds:.2f} s",
    }
