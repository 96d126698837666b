"""``hktex render``: a Mitsuba preview of a kernel set on its mesh, written as an sRGB PNG."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a kernel set on its mesh to a PNG (Mitsuba 3)",
        description="Render a fitted kernel set as the diffuse albedo of its mesh under a white "
        "environment (prb, max_depth 3) and write an sRGB PNG.",
    )
    p.add_argument("kernels", type=Path, help="kernel-set file (.hkt)")
    p.add_argument("--spectra", type=Path, required=True, help="spectra directory")
    p.add_argument("-o", "--output", type=Path, required=True, help="output PNG")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=256)
    p.add_argument(
        "--view",
        default="30,20",
        help="AZIMUTH,ELEVATION in degrees on the bounding-sphere orbit, or an orbit view index",
    )
    p.add_argument("--spp", type=int, default=16, help="samples per pixel")
    p.add_argument("--fov", type=float, default=40.0, help="horizontal field of view, degrees")
    p.add_argument("--envmap", type=Path, default=None, help="environment map (default: white)")
    p.add_argument("--device", default=None, help="torch device for the albedo queries")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from hktex_engine.cli import load_kernelset_with_spectra
    from hktex_engine.render.mitsuba import (
        Lighting,
        RenderSettings,
        encode_png,
        file_frame_vertices,
        parse_view,
        render_kernelset,
    )

    spectra, kernelset = load_kernelset_with_spectra(args.kernels, args.spectra)
    if args.envmap is not None and not args.envmap.is_file():
        raise FileNotFoundError(f"environment map not found: {args.envmap}")
    lighting = Lighting("envmap", envmap=str(args.envmap)) if args.envmap else Lighting()
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp, lighting=lighting)
    camera = parse_view(args.view, file_frame_vertices(spectra), fov=args.fov)
    start = time.perf_counter()
    image = render_kernelset(spectra, kernelset, camera, settings, device=args.device)
    seconds = time.perf_counter() - start
    png = encode_png(image)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(png)
    return {
        "output": str(args.output),
        "width": args.width,
        "height": args.height,
        "spp": args.spp,
        "view": args.view,
        "render_seconds": round(seconds, 4),
        "bytes": len(png),
        "message": f"wrote {args.output} ({args.width}x{args.height}, {seconds:.2f} s)",
    }
