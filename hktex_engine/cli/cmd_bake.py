"""``hktex bake``: a kernel set baked into a UV texture, optionally GLB / OBJ / vertex colours."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from hktex_engine.cli import add_max_vertices


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "bake",
        help="bake a kernel set into a UV texture (PNG) and optionally GLB / OBJ",
        description="Rasterise the mesh's UVs (or a fresh xatlas atlas when it has none), query "
        "the kernel set at every texel, pad the islands, and write an sRGB PNG.",
    )
    p.add_argument("kernels", type=Path, help="kernel-set file (.hkt)")
    p.add_argument("--spectra", type=Path, required=True, help="spectra directory")
    p.add_argument("--mesh", type=Path, required=True, help="the mesh the spectra were made from")
    p.add_argument("-o", "--output", type=Path, required=True, help="texture PNG")
    p.add_argument("--resolution", type=int, default=1024, help="texture side in texels")
    p.add_argument("--glb", type=Path, default=None, help="also write a textured GLB")
    p.add_argument("--obj", type=Path, default=None, help="also write OBJ + MTL + PNG")
    p.add_argument(
        "--vertex-colors",
        action="store_true",
        help="the GLB / OBJ carry per-vertex colours instead of the texture",
    )
    p.add_argument("--device", default=None, help="torch device for the albedo queries")
    add_max_vertices(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from hktex_engine.cli import TerminalProgress, load_kernelset_with_spectra
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.render.bake import (
        bake_texture,
        colored_trimesh,
        textured_trimesh,
        vertex_colors,
        write_glb,
        write_obj,
        write_png,
    )

    spectra, kernelset = load_kernelset_with_spectra(args.kernels, args.spectra)
    mesh = load_mesh(args.mesh, max_vertices=args.max_vertices)
    progress = TerminalProgress("bake")
    start = time.perf_counter()
    try:
        bake = bake_texture(
            spectra, kernelset, mesh, args.resolution, device=args.device, progress=progress
        )
    finally:
        progress.close()
    written = [str(write_png(args.output, bake.texture))]
    colors = vertex_colors(spectra, kernelset, args.device) if args.vertex_colors else None
    if args.glb is not None:
        tm = (
            colored_trimesh(spectra, colors)
            if colors is not None
            else textured_trimesh(spectra, bake)
        )
        written.append(str(write_glb(args.glb, tm)))
    if args.obj is not None:
        written.append(
            str(write_obj(args.obj, spectra, None if colors is not None else bake, colors))
        )
    seconds = time.perf_counter() - start
    return {
        "output": str(args.output),
        "files": written,
        "resolution": args.resolution,
        "atlas": bake.atlas,
        "atlas_reason": bake.atlas_reason,
        "coverage": round(bake.coverage, 4),
        "seconds": round(seconds, 3),
        "message": f"wrote {', '.join(written)} ({seconds:.1f} s)",
    }
