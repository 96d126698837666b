"""Fidelity of UV fits per configuration, against vertex colours of equal bytes.

    python benchmarks/fidelity.py --meshes spot bob --run 'earlier' \\
        --run 'later:{"steps": 1500}' --run 'later+polish' [--minutes 20] [--k 64]

Each ``--run`` is ``PRESET[+polish][:JSON overrides of FitParams]`` (``spectra_k`` in the JSON
picks the spectra's K for that run; ``kernel``, an object, overrides KernelConfig fields such
as ``diffusion_time``). ``--subdivide N`` fits on the mesh midpoint-subdivided N
times (the same surface; rows labelled ``@midN``), scored on the same points;
``--tangent-field curvature`` on spectra of the curvature reference field (``@curvature``);
``--mesh-file NAME=MESH[,TEXTURE]`` fits a mesh outside the shared data (e.g. the torus of
``textured_torus.py``). Per mesh and run: a UV fit, then

- surface PSNR (EVALUATION.md: 60,000 points, seed 0) and the kernel set's zipped bytes;
- vertex colours **of equal bytes**: PSNR of the L0-L3 baselines interpolated linearly in
  log(bytes) at the kernel set's zipped bytes (beyond L3 or below L0: the nearest level's
  line extended, flagged ``extrapolated``);
- the diagnostics of ``hktex_engine.evaluation.diagnostics`` (truncation ``exp(-t λ_K)``,
  saturated candidates, edge/flat error split) and, with ``+polish``, the PSNR before the
  least-squares colour solve (its gain is the colour's share of the error; what remains is
  the footprints');
- an error map (original | kernel bake | heat map of the error) under ``--pictures``.

Every finished run is appended to ``benchmarks/results/fidelity.jsonl`` at once (a stopped
session keeps what ran); ``--table`` rewrites ``fidelity.md`` from the JSONL; ``--rebyte``
re-measures the quantised bytes of every saved set in the current ``.hkt`` format first.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from _machine import machine_info, machine_line

from hktex_engine.config import SIGMA_RATIO_RANGE, SpectralConfig, fit_preset
from hktex_engine.evaluation.baselines import (
    MLPBaseline,
    VertexColorBaseline,
    midpoint_subdivide,
    subdivided_location,
)
from hktex_engine.evaluation.diagnostics import edge_flat_split, saturation, truncation
from hktex_engine.evaluation.metrics import psnr, surface_samples
from hktex_engine.fitting.uv import evaluate_albedo, fit_uv
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.kernels.hkt import written_version
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.grid import SpectraCache
from hktex_engine.spectra.interpolation import SpectralField

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"
MESHES = {
    "spot": ("spot/spot_triangulated.obj", "spot/spot_texture.png"),
    "bob": ("bob/bob_tri.obj", None),
    "blub": ("blub/blub_triangulated.obj", "blub/blub_texture.png"),
    "cesiumman": ("cesiumman/CesiumMan.glb", None),
    "marble_bust_01": ("marble_bust_01/marble_bust_01_4k.gltf", None),
}


def mesh_sources(mesh_files: list[str]) -> dict[str, tuple[Path, Path | None]]:
    """The shared meshes by name, plus each ``NAME=MESH[,TEXTURE]`` of ``--mesh-file``."""
    sources = {
        name: (DATA / obj, DATA / tex if tex else None) for name, (obj, tex) in MESHES.items()
    }
    for spec in mesh_files:
        name, _, files = spec.partition("=")
        obj, _, tex = files.partition(",")
        if not name or not obj:
            raise SystemExit(f"--mesh-file wants NAME=MESH[,TEXTURE], got {spec!r}")
        sources[name] = (Path(obj), Path(tex) if tex else None)
    return sources


def add_mesh_file_argument(ap: argparse.ArgumentParser) -> None:
    """``--mesh-file NAME=MESH[,TEXTURE]``, the same in every fidelity script."""
    ap.add_argument(
        "--mesh-file",
        action="append",
        default=[],
        metavar="NAME=MESH[,TEXTURE]",
        help="a mesh outside the shared data (e.g. benchmarks/textured_torus.py's), used like "
        "the named ones; repeatable",
    )


def mesh_file_names(mesh_files: list[str], names: list[str]) -> list[str]:
    """``names`` followed by the ``--mesh-file`` names not already among them."""
    extra = [spec.partition("=")[0] for spec in mesh_files]
    return list(names) + [n for n in dict.fromkeys(extra) if n not in names]


def load_source(source: tuple[Path, Path | None]):
    """A mesh of :func:`mesh_sources`, textured."""
    obj, tex = source
    return load_mesh(obj, texture=tex)


def named_mesh_and_spectra(mesh_files: list[str], name: str, k: int):
    """``(mesh, spectra)`` of a shared mesh or a ``--mesh-file`` name, its spectra (the
    default 7-angle grid at ``k``) from the user's cache; an unknown name exits with the list."""
    sources = mesh_sources(mesh_files)
    if name not in sources:
        raise SystemExit(f"unknown mesh {name!r}; choose from {sorted(sources)}")
    mesh = load_source(sources[name])
    cache = SpectraCache(Path.home() / ".cache/hktex/spectra")
    return mesh, cache.get_or_compute(mesh, SpectralConfig(angles=7, k=k))


def parse_run(spec: str) -> tuple[str, dict]:
    """``PRESET[+polish][:JSON]`` -> (label, FitParams overrides incl. ``preset``)."""
    head, _, js = spec.partition(":")
    preset, _, flag = head.partition("+")
    over = json.loads(js) if js else {}
    if flag == "polish":
        over["polish_colors"] = True
    elif flag:
        raise ValueError(f"unknown run flag {flag!r}")
    return spec, {"preset": preset, **over}


def read_rows(jsonl: Path) -> list[dict]:
    """A benchmark's results file: one JSON object per non-empty line."""
    return [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]


def refined_mesh(mesh, levels: int):
    """The mesh midpoint-subdivided ``levels`` times: the same surface with 4^levels x the
    faces, for a kernel set fitted on finer triangles and scored on the original's points
    (located on it by ``subdivided_location``). Why: eigenfunctions are interpolated linearly
    inside a face (ALGORITHM.md 2), so a footprint's boundary is about one straight segment
    per face (docs/fitting.md, sixth pass)."""
    v, f, uv = mesh.vertices, mesh.faces, mesh.corner_uvs
    for _ in range(levels):
        v, f, uv = midpoint_subdivide(v, f, uv)
    return replace(
        mesh, vertices=v, faces=f, corner_uvs=uv, content_hash=f"{mesh.content_hash}-mid{levels}"
    )


def vertex_colour_curve(mesh, eval_f, eval_b, target) -> list[dict]:
    rows = []
    for level in range(4):
        vc = VertexColorBaseline(level)
        vc.fit(mesh)
        rows.append(
            {
                "level": level,
                "bytes": int(vc.nbytes),
                "psnr": psnr(vc.albedo(eval_f, eval_b), target),
            }
        )
    return rows


def at_equal_bytes(curve: list[dict], nbytes: float) -> dict:
    """PSNR of vertex colours at ``nbytes``, linear in log(bytes) between levels."""
    x = np.log([r["bytes"] for r in curve])
    y = np.array([r["psnr"] for r in curve])
    lx = np.log(nbytes)
    i = int(np.clip(np.searchsorted(x, lx) - 1, 0, len(x) - 2))
    value = y[i] + (y[i + 1] - y[i]) * (lx - x[i]) / (x[i + 1] - x[i])
    return {"psnr": float(value), "extrapolated": bool(lx < x[0] or lx > x[-1])}


def mlp_psnr(mesh, steps: int, batch: int, eval_f, eval_b, target) -> dict:
    """The positional-encoding MLP trained on the same samples and steps as the fit."""
    mlp = MLPBaseline(steps=steps, batch=batch)
    mlp.fit(mesh)
    return {"psnr": psnr(mlp.albedo(eval_f, eval_b), target), "bytes": int(mlp.nbytes)}


def error_map_png(mesh, spectra, kernelset, path: Path, size: int = 512) -> dict:
    """Original | kernel bake | error heat map, side by side, on the mesh's UV layout."""
    from PIL import Image

    from hktex_engine.render.bake import bake_texture
    from hktex_engine.render.errormap import error_texture, resample_texture

    baked = bake_texture(spectra, kernelset, mesh, resolution=size)
    heat, rms = error_texture(baked.texture, mesh.texture)
    ref = resample_texture(mesh.texture, size)
    strip = np.concatenate([ref, baked.texture, heat], axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(np.clip(strip, 0, 1) * 255).astype(np.uint8)).save(path)
    return {"path": str(path), "rms": rms}


def run_one(
    name, mesh, spectra, label, over, curve, eval_f, eval_b, target, pictures, save
) -> dict:
    preset = over.pop("preset")
    # JSON objects: KernelConfig / DensityRules fields over the preset's own
    nested = {key: over.pop(key) for key in ("kernel", "density") if over.get(key)}
    params = fit_preset(preset, **over)
    for key, fields in nested.items():
        params = replace(params, **{key: replace(getattr(params, key), **fields)})
        over[key] = fields
    t0 = time.perf_counter()
    res = fit_uv(mesh, spectra, params)
    wall = time.perf_counter() - t0
    m = res.metrics
    model = HeatKernelModel.from_kernelset(res.kernelset, SpectralField(spectra))
    pred = evaluate_albedo(model, eval_f, eval_b)
    sat_f, sat_b = eval_f[:1000], eval_b[:1000]
    row = {
        "mesh": name,
        "run": label,
        "params": {k: v for k, v in over.items()},
        "kernels": m["kernels"],
        "steps": m["steps"],
        # on the benchmark's own points (the fit scores its own draw on the mesh it was given,
        # which for --subdivide is another draw of the same surface)
        "surface_psnr": psnr(pred, target),
        "bytes_zip": m["bytes_zip"],
        "bytes_raw": m["bytes_raw"],
        "vertex_colours_equal_bytes": at_equal_bytes(curve, m["bytes_zip"]),
        "truncation": truncation(spectra, params.kernel.diffusion_time),
        "saturation": saturation(model, sat_f, sat_b),
        "split": edge_flat_split(mesh, pred, target, eval_f, eval_b),
        "colour_solve": m.get("colour_solve"),
        "mlp_equal_samples": mlp_psnr(
            mesh, params.steps, params.points_per_step, eval_f, eval_b, target
        ),
        "fit_s": wall,
        "spectra_k": int(np.asarray(spectra.evals).shape[-1]),
        "spectra_angles": int(np.asarray(spectra.grid_theta).shape[0]),
        "sigma_ratio": sigma_ratio_stats(res.kernelset),
    }
    # bytes of the file as written (the fit's metrics measure the set before its provenance
    # is attached: ~1 KB less)
    measure_file(row, res.kernelset, mesh, spectra, eval_f, eval_b, target, curve)
    # readable prefix + a digest of the whole label: two runs whose labels share their first
    # 60 characters once overwrote each other's saved set
    digest = hashlib.sha1(label.encode()).hexdigest()[:8]
    safe = "".join(c if c.isalnum() else "_" for c in label)[:48] + "_" + digest
    if save is not None:
        from hktex_engine.kernels.hkt import save_hkt

        save.mkdir(parents=True, exist_ok=True)
        row["hkt"] = str(save_hkt(res.kernelset, save / f"{name}_{safe}.hkt"))
    if pictures is not None:
        row["error_map"] = error_map_png(
            mesh, spectra, res.kernelset, pictures / f"{name}_{safe}.png"
        )
    return row


def auto_row(quantisation: dict, curve: list[dict]) -> dict:
    """The file ``hktex fit --quantise`` writes (widths chosen for the fit), its own surface
    PSNR, and vertex colours at its bytes."""
    keep = ("bits", "bytes", "surface_psnr", "budget_db")
    return {k: quantisation[k] for k in keep} | {
        "vertex_colours": at_equal_bytes(curve, quantisation["bytes"])
    }


def rebyte(jsonl: Path, cache: Path, auto_min_steps: int) -> None:
    """Quantised bytes of the saved sets in the current format, and VC at those bytes; for
    rows of at least ``auto_min_steps`` steps also the fit-chosen widths' file and its PSNR
    (a dozen queries per row, so not for every exploratory row)."""
    from hktex_engine.kernels.hkt import load_hkt

    rows = read_rows(jsonl)
    meshes: dict[str, tuple] = {}
    spectra_cache = SpectraCache(cache)
    for r in rows:
        path = Path(r.get("hkt") or "")
        if not path.is_file():
            continue
        key = (r["mesh"], int(r.get("subdivide", 0)))
        if key not in meshes:
            obj, tex = MESHES[r["mesh"]]
            mesh = load_mesh(DATA / obj, texture=(DATA / tex) if tex else None)
            f, b, target = surface_samples(mesh, 60_000, 0)
            curve = vertex_colour_curve(mesh, f, b, target)
            if key[1]:
                mesh, (f, b) = refined_mesh(mesh, key[1]), subdivided_location(f, b, key[1])
            meshes[key] = (mesh, f, b, target, curve)
        mesh, f, b, target, curve = meshes[key]
        spectra = None
        if r["steps"] >= auto_min_steps:
            config = SpectralConfig(
                angles=int(r.get("spectra_angles", 7)), k=int(r.get("spectra_k", 64))
            )
            spectra = spectra_cache.get_or_compute(mesh, config)
        measure_file(r, load_hkt(path), mesh, spectra, f, b, target, curve)
        print(r["mesh"], r["run"], r.get("quantised_auto"), flush=True)
    jsonl.write_text("".join(json.dumps(r) + "\n" for r in rows))


def sigma_ratio_stats(ks) -> dict | None:
    """A per-kernel-sigma set's learnt ``sigma_j / sigma_B``: quantiles and the shares at the
    box's ends (None for a §4 set)."""
    if ks.sigma_ratio is None:
        return None
    r = np.asarray(ks.sigma_ratio, dtype=np.float64)
    lo, hi = SIGMA_RATIO_RANGE
    q = np.quantile(r, [0.1, 0.5, 0.9])
    return {
        "p10": float(q[0]),
        "p50": float(q[1]),
        "p90": float(q[2]),
        "at_low": float(np.mean(r <= lo * 1.001)),
        "at_high": float(np.mean(r >= hi * 0.999)),
    }


def measure_file(row: dict, ks, mesh, spectra, f, b, target, curve) -> None:
    """The row's quantised bytes as the saved file holds the set (its fit's provenance in
    the manifest, as ``hktex fit`` writes it), VC at those bytes, and with ``spectra`` the
    fit-width file (``hktex fit --quantise``) scored itself."""
    from hktex_engine.fitting.uv import quantisation_for
    from hktex_engine.kernels.hkt import hkt_bytes

    qz = hkt_bytes(ks, quantised=True)["zip"]
    row["bytes_zip_quantised"] = qz
    row["quantised_version"] = written_version(ks, quantised=True)
    row["vertex_colours_equal_quantised_bytes"] = at_equal_bytes(curve, qz)
    if spectra is not None:
        row["quantised_auto"] = auto_row(quantisation_for(mesh, spectra, ks, f, b, target), curve)


def _diagnostics(r: dict) -> str:
    """The fit's diagnostic columns (absent from a row rescued from its saved set alone)."""
    sp, sat = r["split"], r["saturation"]
    return (
        f"| {sp['edge_error_share']:.2f} ({sp['edge_fraction']:.2f} of pts) "
        f"| {sp['psnr_edge']:.1f} / {sp['psnr_flat']:.1f} "
        f"| {sat['saturated_mean']:.1f} | {sat['points_over_k_blend']:.2f} "
        f"| {r['truncation']:.2g} | {r['fit_s']:.0f} |"
    )


def write_table(jsonl: Path, md: Path, command: str) -> None:
    rows = read_rows(jsonl)
    lines = [
        "# Fidelity per configuration (benchmarks/fidelity.py)",
        "",
        f"Command(s): `{command}` (appends; this table is every row of fidelity.jsonl).",
        "",
        "| mesh | run | kernels | steps | K | PSNR dB | KB zip | VC equal bytes dB | Δ dB |"
        " KB quantised | VC at those dB | Δq dB | KB fit-width file | its dB | VC at those | Δf dB |"
        " MLP dB |"
        " before solve | edge share | PSNR edge/flat | sat/pt | >K_c | exp(-tλ_K) | fit s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        "---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        vc = r["vertex_colours_equal_bytes"]
        vq = r.get("vertex_colours_equal_quantised_bytes")
        qb = r.get("bytes_zip_quantised")
        mlp = (r.get("mlp_equal_samples") or {}).get("psnr")
        cs = r.get("colour_solve") or {}
        sp = r.get("split")
        version = r.get("quantised_version")
        quant = (
            f"| {qb / 1e3:.1f}{'' if version and version >= 3 else ' (v2)'} "
            f"| {vq['psnr']:.2f}{'*' if vq['extrapolated'] else ''} "
            f"| {r['surface_psnr'] - vq['psnr']:+.2f} "
            if qb and vq
            else "| - | - | - "
        )
        qa = r.get("quantised_auto")
        quant += (
            f"| {qa['bytes'] / 1e3:.1f} | {qa['surface_psnr']:.2f} "
            f"| {qa['vertex_colours']['psnr']:.2f}{'*' if qa['vertex_colours']['extrapolated'] else ''} "
            f"| **{qa['surface_psnr'] - qa['vertex_colours']['psnr']:+.2f}** "
            if qa
            else "| - | - | - | - "
        )
        lines.append(
            f"| {r['mesh']} | `{r['run']}` | {r['kernels']} | {r['steps']} | {r['spectra_k']} "
            f"| {r['surface_psnr']:.2f} | {r['bytes_zip'] / 1e3:.1f} "
            f"| {vc['psnr']:.2f}{'*' if vc['extrapolated'] else ''} "
            f"| {r['surface_psnr'] - vc['psnr']:+.2f} "
            + quant
            + f"| {'-' if mlp is None else f'{mlp:.2f}'} "
            f"| {cs.get('surface_psnr_before', float('nan')):.2f} "
            + (_diagnostics(r) if sp else "| - | - | - | - | - | - |")
        )
    lines += [
        "",
        "VC equal bytes: vertex colours L0-L3 interpolated in log(bytes) at the kernel set's",
        "zipped bytes (* = outside L0-L3, extrapolated). Δ = HKTex minus that. KB quantised: the",
        "set as a quantised .hkt at the default widths (format 4 after a --rebyte, else as",
        "recorded; v2: before face ids were delta-coded); Δq = HKTex minus vertex colours at",
        "those bytes. Fit-width file: what `hktex fit --quantise` writes (code widths chosen",
        "for the fit, fitting/quantisation.py), scored itself (its dB, not the exact set's);",
        "Δf = that minus vertex colours at its bytes. MLP:",
        "the positional-encoding MLP trained on the same samples and steps. 'before solve' is",
        "the PSNR before the least-squares colour solve (runs with +polish). edge share: the",
        "fraction of squared error on texture-edge points. sat/pt: candidates with r >= 1 per",
        "point (brute force, 1000 points); >K_c: points with more saturated candidates than K_c.",
        "",
        f"Machine: {machine_line(machine_info())}",
    ]
    md.write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--meshes", nargs="*", default=None, choices=sorted(MESHES))
    add_mesh_file_argument(ap)
    ap.add_argument("--run", action="append", default=[], help="PRESET[+polish][:JSON]")
    ap.add_argument("--angles", type=int, default=SpectralConfig().angles)
    ap.add_argument(
        "--k", type=int, default=SpectralConfig().k, help="spectra K unless a run sets spectra_k"
    )
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hktex" / "spectra")
    ap.add_argument("--pictures", type=Path, default=None, help="folder for error maps")
    ap.add_argument("--save", type=Path, default=None, help="folder for the fitted .hkt files")
    ap.add_argument(
        "--subdivide",
        type=int,
        default=0,
        help="fit on the mesh midpoint-subdivided this many times (same surface and points)",
    )
    ap.add_argument(
        "--tangent-field",
        choices=("axis_smoothed", "curvature"),
        default=SpectralConfig().tangent_field,
        help="the spectra's reference direction (ALGORITHM.md 1; the later configuration's is "
        "curvature); rows on another than the default are labelled @FIELD",
    )
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--table", action="store_true", help="only rewrite fidelity.md")
    ap.add_argument(
        "--rebyte",
        action="store_true",
        help="re-measure the quantised bytes (current format) of every row whose saved .hkt"
        " still exists, with vertex colours at those bytes; then rewrite fidelity.md",
    )
    ap.add_argument(
        "--auto-min-steps",
        type=int,
        default=1500,
        help="--rebyte also measures the fit-width file of rows with at least these steps",
    )
    args = ap.parse_args()
    command = "python benchmarks/fidelity.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)  # before the fits: a row must not be lost
    jsonl, md = args.out / "fidelity.jsonl", args.out / "fidelity.md"
    if args.table:
        write_table(jsonl, md, command)
        return 0
    if args.rebyte:
        rebyte(jsonl, args.cache, args.auto_min_steps)
        write_table(jsonl, md, command)
        return 0
    torch.manual_seed(0)
    cache = SpectraCache(args.cache)
    names = mesh_file_names(args.mesh_file, args.meshes or ([] if args.mesh_file else ["spot"]))
    sources = mesh_sources(args.mesh_file)
    for name in names:
        mesh = load_source(sources[name])
        eval_f, eval_b, target = surface_samples(mesh, 60_000, 0)
        curve = vertex_colour_curve(mesh, eval_f, eval_b, target)
        print(name, "vertex colours", curve, flush=True)
        if args.subdivide:
            mesh = refined_mesh(mesh, args.subdivide)
            eval_f, eval_b = subdivided_location(eval_f, eval_b, args.subdivide)
        for spec in args.run:
            label, over = parse_run(spec)
            if args.subdivide:
                label = f"{label} @mid{args.subdivide}"
            if args.angles != SpectralConfig().angles:
                label = f"{label} @angles{args.angles}"
            field = args.tangent_field
            if field != SpectralConfig().tangent_field:
                label = f"{label} @{field}"
            k = int(over.pop("spectra_k", args.k))
            config = SpectralConfig(angles=args.angles, k=k, tangent_field=field)
            spectra = cache.get_or_compute(mesh, config)
            row = run_one(
                name,
                mesh,
                spectra,
                label,
                over,
                curve,
                eval_f,
                eval_b,
                target,
                args.pictures,
                args.save,
            )
            row["command"] = command
            row["machine"] = machine_line(machine_info())
            if args.subdivide:
                row["subdivide"] = args.subdivide
            row["tangent_field"] = field
            with jsonl.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(
                json.dumps(
                    {k: row[k] for k in ("mesh", "run", "surface_psnr", "bytes_zip")}
                    | {"vc": row["vertex_colours_equal_bytes"], "fit_s": row["fit_s"]}
                ),
                flush=True,
            )
    write_table(jsonl, md, command)
    return 0


if __name__ == "__main__":
    sys.exit(main())
