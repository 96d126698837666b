"""Kernel evaluation on a GPU: queries, training steps and a default UV fit, against the CPU.

    python benchmarks/kernels_cuda.py [--device cuda] [--sections query,train,fit]
        [--kernels 10000] [--k 256] [--queries 1000000] [--cpu-queries 100000]

The same engine code on a CUDA device and on the same machine's CPU, in one process: the
CPU is the baseline (it runs the compiled numba paths; CUDA runs the torch paths, which are
the same mathematics, checked in tests/test_cuda.py). Setup as benchmarks/kernels.py: a
~10k-vertex torus with the reference grid shape and random eigenvectors of the right size
(the cost does not depend on their values), 10k random kernels, K_s 100, K_c 10 (``issue``)
or the product's kernel configuration at K = 64 (``default``).

- ``query``: AlbedoQuery.colors throughput (points/s, tables build included and apart), the
  device's float32 matmul rate in the same run (points per GFLOP), peak device memory for a
  million points, and the largest colour difference to the CPU on the CPU's points.
- ``train``: a training step (forward, backward, Adam, projection) at 512 and 4,096 points,
  median of ``--rounds``, with the output and gradients of one batch compared to the CPU's.
- ``fit``: a whole ``fit_uv`` with the default preset on the textured torus of
  benchmarks/textured_torus.py (spectra computed on the machine, timed), its surface PSNR
  beside the CPU fit's recorded in benchmarks/results/fidelity.jsonl.

Writes ``kernels_cuda.json`` and ``.md`` to ``--out`` after every section.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _machine import machine_info, machine_line
from kernels import build_spectra, clock, random_kernelset

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hktex_engine.config import LATER_KERNEL, KernelConfig, SpectralConfig  # noqa: E402
from hktex_engine.geometry.sampling import sample_surface  # noqa: E402
from hktex_engine.kernels.model import HeatKernelModel  # noqa: E402
from hktex_engine.kernels.query import AlbedoQuery  # noqa: E402
from hktex_engine.spectra.interpolation import SpectralField  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_rate(device: torch.device, n: int, repeat: int = 10) -> dict:
    """Dense float32 matmul GFLOP/s on ``device`` now (full float32: TF32 off)."""
    torch.backends.cuda.matmul.allow_tf32 = False
    g = torch.Generator(device=device).manual_seed(0)
    a = torch.randn(n, n, device=device, generator=g)
    b = torch.randn(n, n, device=device, generator=g)
    a @ b
    sync(device)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        a @ b
        sync(device)
        times.append(time.perf_counter() - t0)
    t = statistics.median(times)
    return {"n": n, "seconds": round(t, 5), "gflop_per_s": round(2 * n**3 / t / 1e9, 1)}


def bench_query(spectra, ks, device: torch.device, args, rng) -> dict:
    f, b = sample_surface(spectra.vertices, spectra.faces, args.queries, rng)
    nc = min(args.cpu_queries, args.queries)
    res: dict = {"points": args.queries, "cpu_points": nc}
    sides = {"device": AlbedoQuery(spectra, ks, device=device)}
    sides["cpu"] = AlbedoQuery(spectra, ks, device="cpu")
    colors = {}
    for name, query in sides.items():
        n = args.queries if name == "device" else nc
        build_w, _, _ = clock(lambda q=query: (q.model.prepare_tables(), sync(q.device)))
        runs = []
        for _ in range(2):
            w, c, colors[name] = clock(lambda q=query, n=n: q.colors(f[:n], b[:n]))
            runs.append((w, c))
        wall = min(r[0] for r in runs)
        res[name] = {
            "tables_build_s": round(build_w, 3),
            "wall_s": round(wall, 3),
            "points_per_s": round(n / wall),
            "points_per_s_including_tables": round(n / (wall + build_w)),
        }
        print(name, json.dumps(res[name]), flush=True)
    res["ratio_points_per_s"] = round(res["device"]["points_per_s"] / res["cpu"]["points_per_s"], 2)
    diff = np.abs(colors["device"][:nc] - colors["cpu"]).max(axis=1)
    res["max_color_diff_to_cpu"] = float(diff.max())
    res["points_beyond_1e-4"] = int((diff > 1e-4).sum())
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        fm, bm = sample_surface(spectra.vertices, spectra.faces, args.million, rng)
        w, _, _ = clock(lambda: sides["device"].colors(fm, bm))
        res["million"] = {
            "points": args.million,
            "wall_s": round(w, 3),
            "points_per_s": round(args.million / w),
            "peak_device_mb_above_state": round(
                (torch.cuda.max_memory_allocated(device) - before) / 2**20, 1
            ),
            "query_state_mb": round(before / 2**20, 1),
        }
    return res


def train_step_times(model, opt, spectra, n_pts: int, rounds: int, rng) -> list[float]:
    dev = model.field.device
    times = []
    for _ in range(rounds):
        f, b = sample_surface(spectra.vertices, spectra.faces, n_pts, rng)
        target = torch.rand(n_pts, 3, device=dev)
        sync(dev)
        t0 = time.perf_counter()
        model.zero_grad()
        ((model.albedo(f, b) - target) ** 2).mean().backward()
        opt.step()
        model.project_()
        sync(dev)
        times.append(time.perf_counter() - t0)
    return times


def bench_train(spectra, ks, device: torch.device, args, rng) -> dict:
    fields = {"device": SpectralField(spectra, device=device)}
    fields["cpu"] = SpectralField(spectra, device="cpu")
    models = {n: HeatKernelModel.from_kernelset(ks, fl) for n, fl in fields.items()}
    f, b = sample_surface(spectra.vertices, spectra.faces, 512, rng)
    target = torch.rand(512, 3)
    outs, grads = {}, {}
    for name, model in models.items():
        model.zero_grad()
        out = model.albedo(f, b)
        ((out - target.to(out.device)) ** 2).mean().backward()
        outs[name] = out.detach().cpu()
        grads[name] = {
            n: p.grad.detach().cpu() for n, p in model.named_parameters() if p.grad is not None
        }
    res: dict = {
        "max_albedo_diff_to_cpu": float((outs["device"] - outs["cpu"]).abs().max()),
        "max_rel_grad_diff_to_cpu": max(
            float((grads["device"][n] - g).abs().max() / g.abs().max().clamp(min=1e-30))
            for n, g in grads["cpu"].items()
        ),
    }
    for n_pts in (512, 4096):
        row = {}
        for name, model in models.items():
            opt = torch.optim.Adam(model.parameters(), lr=1e-3)
            rounds = args.rounds if name == "device" else max(3, args.rounds // 4)
            train_step_times(model, opt, spectra, n_pts, 2, rng)  # warm-up
            times = train_step_times(model, opt, spectra, n_pts, rounds, rng)
            row[name] = {"median_s": round(statistics.median(times), 4), "rounds": rounds}
        row["ratio"] = round(row["cpu"]["median_s"] / row["device"]["median_s"], 2)
        res[f"points_{n_pts}"] = row
        print("train", n_pts, json.dumps(row), flush=True)
    return res


class StepPrinter:
    """Prints the fit's step and seconds now and then (a run cut short still tells its pace)."""

    def __init__(self, every: int = 500) -> None:
        self.every, self.t0, self.last = every, time.perf_counter(), -1

    def update(self, step: int, total: int, **metrics) -> None:
        if step // self.every != self.last // self.every:
            print(f"fit step {step}/{total} {time.perf_counter() - self.t0:.1f} s", flush=True)
        self.last = step

    def should_stop(self) -> bool:
        return False


def bench_fit(device: torch.device, args) -> dict:
    """A default-preset UV fit of the textured torus on ``device`` (spectra timed apart)."""
    import textured_torus

    from hktex_engine.config import fit_preset, spectra_k_for
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.spectra.grid import compute_spectra

    tmp = Path(tempfile.mkdtemp(prefix="hktex_torus_"))
    obj = textured_torus.write(tmp, 128, 64, 1024)
    mesh = load_mesh(obj, texture=tmp / "torus_texture.png")
    k = spectra_k_for("default")
    t0 = time.perf_counter()
    spectra = compute_spectra(mesh, SpectralConfig(angles=7, k=k))
    spectra_s = time.perf_counter() - t0
    print(f"spectra K={k}: {spectra_s:.1f} s", flush=True)
    params = fit_preset("default", seed=0)
    if args.fit_steps:
        params = fit_preset("default", seed=0, steps=args.fit_steps)
    t0 = time.perf_counter()
    res = fit_uv(mesh, spectra, params, StepPrinter(), device=device)
    total = time.perf_counter() - t0
    return {
        "mesh": "textured torus 128 x 64 (benchmarks/textured_torus.py)",
        "vertices": int(mesh.vertices.shape[0]),
        "spectra_k": k,
        "spectra_s": round(spectra_s, 1),
        "steps": params.steps,
        "fit_total_s": round(total, 1),
        "loop_s": round(res.timings["fit_s"], 1),
        "loop_s_per_step": round(res.timings["fit_s"] / max(params.steps, 1), 4),
        "surface_psnr": round(res.metrics["surface_psnr"], 2),
        "kernels": res.metrics["kernels"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sections", default="query,train,fit")
    ap.add_argument("--kernels", type=int, default=10_000)
    ap.add_argument("--k", type=int, default=256)
    ap.add_argument("--kernel-config", choices=("issue", "default"), default="issue")
    ap.add_argument("--queries", type=int, default=1_000_000)
    ap.add_argument("--cpu-queries", type=int, default=100_000)
    ap.add_argument("--million", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=20)
    ap.add_argument("--fit-steps", type=int, default=0, help="0: the default preset's steps")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--name", default="kernels_cuda", help="output file stem")
    args = ap.parse_args()
    device = torch.device(args.device)
    sections = set(args.sections.split(","))
    rng = np.random.default_rng(0)
    res: dict = {
        "command": "python " + " ".join(sys.argv),
        "machine": machine_info(device=str(device)),
        "matmul_device": matmul_rate(device, 8192 if device.type == "cuda" else 2048),
        "matmul_cpu": matmul_rate(torch.device("cpu"), 2048, 3),
    }
    print("matmul", res["matmul_device"], res["matmul_cpu"], flush=True)
    if sections & {"query", "train"}:
        config = SpectralConfig(k=args.k)
        spectra = build_spectra(config, rng)
        kc = LATER_KERNEL if args.kernel_config == "default" else KernelConfig()
        ks = random_kernelset(spectra, args.kernels, rng, kc)
        res["setup"] = {
            "vertices": int(spectra.vertices.shape[0]),
            "grid_nodes": int(spectra.evecs.shape[1]),
            "k": args.k,
            "kernels": args.kernels,
            "kernel_config": args.kernel_config,
            "k_search": kc.k_search,
            "k_blend": kc.k_blend,
        }
    if "query" in sections:
        res["query"] = bench_query(spectra, ks, device, args, rng)
        gflops = res["matmul_device"]["gflop_per_s"]
        res["query"]["points_per_gflop"] = round(res["query"]["device"]["points_per_s"] / gflops, 2)
        save(res, args)
    if "train" in sections:
        res["train"] = bench_train(spectra, ks, device, args, rng)
        save(res, args)
    if "fit" in sections:
        res["fit"] = bench_fit(device, args)
        print("fit", json.dumps(res["fit"]), flush=True)
        save(res, args)
    save(res, args)


def save(res: dict, args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(res, indent=1))
    (args.out / f"{args.name}.md").write_text(render_md(res))


def render_md(res: dict) -> str:
    lines = [
        "# Kernel evaluation on a GPU (benchmarks/kernels_cuda.py)",
        "",
        f"Command: `{res['command']}`  ",
        f"Machine: {machine_line(res['machine'])}.  ",
        f"Dense float32 matmul: device {res['matmul_device']['gflop_per_s']} GFLOP/s "
        f"({res['matmul_device']['n']}^3, TF32 off), CPU {res['matmul_cpu']['gflop_per_s']} "
        "GFLOP/s.",
        "",
    ]
    if "setup" in res:
        s = res["setup"]
        lines += [
            f"Setup: torus {s['vertices']} vertices, {s['grid_nodes']} grid nodes x K = "
            f"{s['k']}, {s['kernels']} kernels ({s['kernel_config']}: K_s {s['k_search']}, "
            f"K_c {s['k_blend']}).",
            "",
        ]
    if "query" in res:
        q = res["query"]
        lines += [
            "| queries | points | tables s | points/s | incl. tables |",
            "|---|---:|---:|---:|---:|",
        ]
        for name in ("device", "cpu"):
            r = q[name]
            n = q["points"] if name == "device" else q["cpu_points"]
            lines.append(
                f"| {name} | {n} | {r['tables_build_s']} | {r['points_per_s']} | "
                f"{r['points_per_s_including_tables']} |"
            )
        lines += [
            "",
            f"Device / CPU: **{q['ratio_points_per_s']}x**; {q['points_per_gflop']} points per "
            f"device GFLOP; largest colour difference to the CPU {q['max_color_diff_to_cpu']:.2e}"
            f" ({q['points_beyond_1e-4']} points beyond 1e-4).",
        ]
        if "million" in q:
            m = q["million"]
            lines.append(
                f"A million points: {m['wall_s']} s ({m['points_per_s']} points/s), peak device "
                f"memory {m['peak_device_mb_above_state']} MB above the query state "
                f"({m['query_state_mb']} MB)."
            )
        lines.append("")
    if "train" in res:
        t = res["train"]
        lines += [
            "| training step | device s | CPU s | CPU / device |",
            "|---|---:|---:|---:|",
        ]
        for key in ("points_512", "points_4096"):
            r = t[key]
            lines.append(
                f"| {key.split('_')[1]} points | {r['device']['median_s']} | "
                f"{r['cpu']['median_s']} | {r['ratio']}x |"
            )
        lines += [
            "",
            f"One batch against the CPU: albedo {t['max_albedo_diff_to_cpu']:.2e}, gradients "
            f"{t['max_rel_grad_diff_to_cpu']:.2e} (largest relative).",
            "",
        ]
    if "fit" in res:
        f = res["fit"]
        lines += [
            f"Fit: {f['mesh']}, {f['vertices']} vertices, default preset, {f['steps']} steps: "
            f"spectra (K = {f['spectra_k']}) {f['spectra_s']} s, fit {f['fit_total_s']} s "
            f"(loop {f['loop_s_per_step']} s a step), {f['kernels']} kernels, surface PSNR "
            f"{f['surface_psnr']} dB.",
            "",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
