"""The quantised ``.hkt`` (the current format version) on a fitted kernel set: bytes and fidelity loss.

    python benchmarks/hkt_quantised.py KERNELS.hkt --mesh MESH [--texture IMAGE]
        [--spectra DIR] [--points 60000] [--bits colors=10,threshold=12 ...] [--paper-views]

Reports the kernel set's bytes in every storage form (float32/int64, the compact version-1
default, the quantised file: raw arrays, zip of the members, the file), surface PSNR
(EVALUATION.md: 60,000 points, seed 0) of the set as read and quantised, the loss when each
member alone is quantised (which member costs what), and with ``--paper-views`` the paper-view
scores of both. Writes benchmarks/results/hkt_quantised.json and .md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine_info, machine_line

from hktex_engine.evaluation.metrics import psnr, storage_bytes, surface_samples
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.kernels.hkt import (
    QUANT_BITS,
    QUANTISED_VERSION,
    hkt_bytes,
    load_hkt,
    save_hkt,
    sorted_by_face,
)
from hktex_engine.kernels.query import AlbedoQuery
from hktex_engine.spectra.grid import load_spectra

ROOT = Path(__file__).resolve().parents[1]
MEMBERS = ("barycentrics", "theta", "eta", "threshold", "sharpness", "colors")


def _bits_arg(text: str) -> dict[str, int]:
    out = {}
    for part in filter(None, text.split(",")):
        name, value = part.split("=")
        out[name.strip()] = int(value)
    return out


def _quantised(ks, bits):
    with tempfile.TemporaryDirectory() as tmp:
        path = save_hkt(ks, Path(tmp) / "q.hkt", quantised=True, bits=bits)
        return load_hkt(path), storage_bytes(path), path.stat().st_size


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("hkt", type=Path)
    ap.add_argument("--mesh", type=Path, required=True)
    ap.add_argument("--texture", type=Path)
    ap.add_argument("--spectra", type=Path, required=True)
    ap.add_argument("--points", type=int, default=60_000)
    ap.add_argument("--bits", type=_bits_arg, action="append", default=[])
    ap.add_argument("--paper-views", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    mesh = load_mesh(args.mesh, texture=args.texture)
    spectra = load_spectra(args.spectra)
    # in the order a quantised file stores (sorted by face), so one member of the quantised
    # set can replace the exact one row for row (the albedo does not depend on the order)
    ks = sorted_by_face(load_hkt(args.hkt, spectra.mesh_hash, spectra.config_hash))
    n = len(ks)
    f, b, target = surface_samples(mesh, args.points, 0)

    def score(kset) -> float:
        return psnr(AlbedoQuery(spectra, kset, device="cpu").colors(f, b), target)

    t0 = time.perf_counter()
    base = score(ks)
    query_s = time.perf_counter() - t0
    settings = [None] + list(args.bits)
    variants = []
    for bits in settings:
        q, members, file_size = _quantised(ks, bits)
        full_bits = {**QUANT_BITS, **(bits or {})}
        q_psnr = score(q)
        variants.append(
            {
                "bits": full_bits,
                "raw": hkt_bytes(ks, quantised=True, bits=bits)["raw"],
                "zip_members": members["zip"],
                "file": file_size,
                "bytes_per_kernel_file": file_size / n,
                "psnr": q_psnr,
                "loss_db": base - q_psnr,
                "only": {
                    name: base - score(dataclasses.replace(ks, **{name: getattr(q, name)}))
                    for name in MEMBERS
                },
            }
        )
        variants[-1]["psnr_vs_exact"] = psnr(
            AlbedoQuery(spectra, q, device="cpu").colors(f, b),
            AlbedoQuery(spectra, ks, device="cpu").colors(f, b),
        )
    result = {
        "command": "python benchmarks/hkt_quantised.py " + shlex.join(argv or sys.argv[1:]),
        "machine": machine_info(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "kernels": n,
        "faces": mesh.n_faces,
        "fitting": ks.fitting,
        "surface_psnr": base,
        "query_s_per_eval": query_s,
        "bytes": {
            "float32": hkt_bytes(ks, compact=False),
            "compact_v1": hkt_bytes(ks),
        },
        "quantised": variants,
    }
    if args.paper_views:
        from hktex_engine.evaluation.paper_views import PaperViews, kernelset_albedo_fn

        views = PaperViews(mesh)
        result["paper_views"] = {"trace_s": views.trace_seconds, "points": views.albedo_points}
        for label, kset in (("exact", ks), ("quantised", _quantised(ks, None)[0])):
            result["paper_views"][label] = views.score(kernelset_albedo_fn(spectra, kset, "cpu"))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "hkt_quantised.json").write_text(json.dumps(result, indent=1, default=str))
    write_md(args.out / "hkt_quantised.md", result)
    print(json.dumps({k: result[k] for k in ("kernels", "surface_psnr")} | {"q": variants[0]}))
    return 0


def write_md(path: Path, r: dict) -> None:
    n = r["kernels"]
    lines = [
        f"# Quantised .hkt (format version {QUANTISED_VERSION})",
        "",
        f"Command: `{r['command']}`  ",
        f"Machine: {machine_line(r['machine'])}  ",
        f"Date: {r['date']}",
        "",
        f"{n} kernels on {r['faces']} faces; surface PSNR as read {r['surface_psnr']:.3f} dB "
        "(60,000 points, seed 0). Bytes: raw = the stored arrays; zip = the members deflated "
        "(EVALUATION.md count, manifest included); file = the .hkt as written.",
        "",
        "| storage | raw B | zip B | file B | B / kernel (file) | PSNR dB | loss dB |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, key in (("float32 / int64 (v1)", "float32"), ("compact (v1 default)", "compact_v1")):
        bb = r["bytes"][key]
        lines.append(f"| {label} | {bb['raw']} | - | {bb['zip']} | {bb['zip'] / n:.2f} | - | - |")
    for v in r["quantised"]:
        bits = ", ".join(f"{k} {b}" for k, b in v["bits"].items())
        lines.append(
            f"| quantised (v{QUANTISED_VERSION}: {bits}) | {v['raw']} | {v['zip_members']} | {v['file']} "
            f"| {v['bytes_per_kernel_file']:.2f} | {v['psnr']:.3f} | {v['loss_db']:+.3f} |"
        )
    lines += ["", "Loss when one member alone is quantised (dB), per setting:", ""]
    lines += ["| setting | " + " | ".join(MEMBERS) + " | quantised vs exact albedo dB |"]
    lines += ["|---|" + "---:|" * (len(MEMBERS) + 1)]
    for v in r["quantised"]:
        bits = ", ".join(f"{k} {v['bits'][k]}" for k in MEMBERS)
        cells = " | ".join(f"{v['only'][m]:+.3f}" for m in MEMBERS)
        lines.append(f"| {bits} | {cells} | {v['psnr_vs_exact']:.1f} |")
    pv = r.get("paper_views")
    if pv:
        lines += [
            "",
            f"Paper views (5 x 256², traced in {pv['trace_s']:.0f} s, {pv['points']} lookups):",
            "",
            "| set | view all dB | view mesh dB | SSIM all | SSIM mesh | render s |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for label in ("exact", "quantised"):
            s = pv[label]
            lines.append(
                f"| {label} | {s['psnr_all']:.3f} | {s['psnr_mesh']:.3f} | {s['ssim_all']:.4f} "
                f"| {s['ssim_mesh']:.4f} | {s['render_s']:.0f} |"
            )
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
