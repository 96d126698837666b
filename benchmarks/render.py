"""Render benchmark: a kernel-textured Mitsuba render against the UV-textured render of the
same scene (same mesh, camera, light, integrator, spp and resolution), side by side.

    python benchmarks/render.py [--mesh spot] [--kernels 1500] [--size 128] [--spp 8]
    python benchmarks/render.py --spectra default --hkt SET.hkt [--k 128] [--tag NAME]

Setup (the multiview benchmark's): spot with its texture; spectra 3 angles x [1, 15],
K = 32, K_iso = 17 (in memory); a UV-initialised kernel set (``initial_kernelset``: colours
from the texture at farthest-point centres) with the default preset's kernel config (or
``--kernel-config bench-2026-11``: t = 0.004, sigma_B = 0.12). ``--spectra default`` uses
the default grid (``SpectralConfig``, K = ``--k``, from ``--cache``) instead, which is what a
default fit's set lives on, and ``--hkt`` renders a saved set (a fit of ``--mesh`` on that
grid) instead of the initialised one: the ratio a user of today's defaults sees. The kernel
scene shows the set through the public query path (``AlbedoQuery`` via ``query_albedo_fn``, what
``render_kernelset`` / ``hktex render`` use). Each render is warmed up once (Dr.Jit
compiles), then the three renders alternate ``--repeats`` times (the shared machine's load
hits all alike): kernel (point cache on, the default), kernel (cache off: every request
evaluated, today's behaviour before the cache), UV. Reported: median seconds, the ratios
against UV, albedo points asked / evaluated, and the largest pixel difference between the
cached and uncached kernel renders at the same seed (the cache is exact: expect ~0).
Writes benchmarks/results/render.json and .md with the machine and the command.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _machine import machine_info, machine_line  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
MESHES = {"spot": ("spot/spot_triangulated.obj", "spot/spot_texture.png")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="spot", choices=sorted(MESHES))
    ap.add_argument("--kernels", type=int, default=1500)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--view", default="30,20")
    ap.add_argument(
        "--kernel-config",
        choices=["default", "bench-2026-11"],
        default="default",
        help="the kernels' K_s/K_c/t/sigma_B: the default preset's (what a fit makes now), or "
        "the one earlier rows used (t = 0.004, sigma_B = 0.12, K_s = 100, K_c = 10)",
    )
    ap.add_argument(
        "--spectra",
        choices=["bench", "default"],
        default="bench",
        help="bench: 3 angles x [1, 15], K = 32 (the earlier rows'); default: SpectralConfig's "
        "grid at --k (what a default fit lives on)",
    )
    ap.add_argument(
        "--k", type=int, default=None, help="--spectra default: K (default: the config's)"
    )
    ap.add_argument(
        "--hkt", type=Path, default=None, help="render this saved set (needs --spectra default)"
    )
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hktex" / "spectra")
    ap.add_argument(
        "--tag", default="", help="write render_TAG.json/.md instead of render.json/.md"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    if args.hkt is not None and args.spectra != "default":
        ap.error("--hkt needs --spectra default (a fitted set lives on the default grid)")

    from hktex_engine.config import (
        DEFAULT_PRESET,
        FitParams,
        KernelConfig,
        SpectralConfig,
        fit_preset,
    )
    from hktex_engine.fitting.uv import initial_kernelset
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.kernels.query import AlbedoQuery
    from hktex_engine.render.mitsuba import (
        RenderScene,
        RenderSettings,
        ensure_variant,
        file_frame_vertices,
        parse_view,
        query_albedo_fn,
    )
    from hktex_engine.spectra.grid import SpectraCache, compute_spectra

    variant = ensure_variant()
    obj, tex = MESHES[args.mesh]
    mesh = load_mesh(DATA / obj, texture=DATA / tex)
    if args.spectra == "default":
        k = args.k if args.k is not None else SpectralConfig().k
        spectral = SpectralConfig(k=k)
        spectra = SpectraCache(args.cache).get_or_compute(mesh, spectral)
        grid_label = (
            f"spectra {spectral.angles} x {len(spectral.anisotropies)} x K = {k} (default grid)"
        )
    else:
        spectral = SpectralConfig(angles=3, anisotropies=(1.0, 15.0), k=32, k_iso=17)
        spectra = compute_spectra(mesh, spectral)
        grid_label = "spectra 3 x [1, 15] x K = 32"
    if args.hkt is not None:
        kernelset = load_hkt(args.hkt)
        kernel = kernelset.kernel_config
        origin = f"the saved set {args.hkt.name}"
    else:
        if args.kernel_config == "default":
            kernel = fit_preset(DEFAULT_PRESET).kernel
        else:
            kernel = KernelConfig(diffusion_time=0.004, sigma_b=0.12)
        params = FitParams(kernels=args.kernels, kernel=kernel)
        kernelset = initial_kernelset(mesh, spectra, params, np.random.default_rng(0))
        origin = "UV init"
    query = AlbedoQuery(spectra, kernelset)
    settings = RenderSettings(width=args.size, height=args.size, spp=args.spp)
    V = file_frame_vertices(spectra)
    kscene = RenderScene(V, spectra.faces, settings, albedo_fn=query_albedo_fn(query))
    uscene = RenderScene(
        mesh.to_file_units(mesh.vertices),
        mesh.faces,
        settings,
        corner_uvs=mesh.corner_uvs,
        texture=mesh.texture,
    )
    cam = parse_view(args.view, V)
    runs = {
        "kernel": lambda seed: kscene.render(cam, seed=seed, cache=True),
        "kernel_uncached": lambda seed: kscene.render(cam, seed=seed),
        "uv": lambda seed: uscene.render(cam, seed=seed),
    }
    for fn in runs.values():  # warm-up: Dr.Jit compiles the kernels once per scene
        fn(0)
    times: dict[str, list[float]] = {k: [] for k in runs}
    asked = evaluated = 0
    images = {}
    for i in range(args.repeats):
        for name, fn in runs.items():
            t0 = time.perf_counter()
            images[name] = fn(i + 1)
            times[name].append(time.perf_counter() - t0)
            if name == "kernel":
                asked, evaluated = kscene.last_cache.asked, kscene.last_cache.evaluated
    med = {k: float(np.median(v)) for k, v in times.items()}
    diff = float(np.abs(images["kernel"] - images["kernel_uncached"]).max())
    result = {
        "command": "python benchmarks/render.py "
        + " ".join(sys.argv[1:] if argv is None else argv),
        "machine": machine_info(mitsuba_variant=variant),
        "setup": {
            "mesh": args.mesh,
            "vertices": int(len(spectra.vertices)),
            "kernels": len(kernelset.theta),
            "kernel_set": origin,
            "spectra": spectral.to_dict(),
            "kernel_config": kernel.to_dict(),
            "size": args.size,
            "spp": args.spp,
            "view": args.view,
            "repeats": args.repeats,
        },
        "seconds": times,
        "median_seconds": med,
        "ratio_kernel_vs_uv": med["kernel"] / med["uv"],
        "ratio_kernel_uncached_vs_uv": med["kernel_uncached"] / med["uv"],
        "cache_speedup": med["kernel_uncached"] / med["kernel"],
        "albedo_points_asked": int(asked),
        "albedo_points_evaluated": int(evaluated),
        "cached_vs_uncached_max_pixel_diff": diff,
        "albedo_points_per_s": evaluated / med["kernel"] if med["kernel"] > 0 else None,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"render_{args.tag}" if args.tag else "render"
    (args.out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    s, m = result["setup"], med
    lines = [
        "# Render benchmark: kernel-textured vs UV-textured Mitsuba render",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {machine_line(result['machine'])}  ",
        f"Setup: {s['mesh']} ({s['vertices']} vertices), {s['kernels']} kernels ({origin}, "
        f"t = {kernel.diffusion_time:g}, sigma_B = {kernel.sigma_b:g}, K_s = "
        f"{kernel.k_search}, K_c = {kernel.k_blend}), {grid_label}, "
        f"{s['size']}^2 at "
        f"{s['spp']} spp, prb max_depth 3, constant white light, view {s['view']}; the three "
        f"renders alternate {s['repeats']} times after one warm-up each (medians).",
        "",
        "| render | median s | vs UV |",
        "|---|---:|---:|",
        f"| UV texture (bitmap) | {m['uv']:.3f} | 1.0x |",
        f"| kernels, point cache (`cache=True`) | {m['kernel']:.3f} | "
        f"{result['ratio_kernel_vs_uv']:.1f}x |",
        f"| kernels, one pass (default: every request evaluated) | {m['kernel_uncached']:.3f} | "
        f"{result['ratio_kernel_uncached_vs_uv']:.1f}x |",
        "",
        f"Albedo points per render: {asked} asked, {evaluated} evaluated "
        f"(cache speed-up {result['cache_speedup']:.2f}x); largest pixel difference cached vs "
        f"uncached at the same seed: {diff:.1e}.",
    ]
    (args.out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "machine"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
