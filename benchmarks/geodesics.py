"""Geodesic tracer throughput: paths per second for batches of kernel-centre moves.

    python benchmarks/geodesics.py [--kernels 10000] [--repeats 3] [--threads 1]
                                   [--out benchmarks/results]

For each mesh (spot, merged by position and normalised so its bounding box side is 2; an
icosphere of radius 1, the same scale) and each step length (0.001, 0.01, 0.05: typical
optimiser steps; 0.5: long moves), traces ``--kernels`` paths from area-uniform random starts
in random tangent directions, on the CPU and on CUDA when torch sees one. Reports the median
wall time over ``--repeats`` runs (after one warm-up), paths per second and crossing
iterations (the longest path's number of face changes). A second table times one crossing iteration's worth of
array operations in numpy and in torch, which is what the choice of torch rests on.

``--threads`` sets torch's intra-op threads (default 1: on a shared 2-core machine, two
threads spin against each other and the other tenants and ran 10-30x slower, measured).

Writes ``geodesics.json`` and ``geodesics.md`` (machine, command, numbers).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _machine import machine_info

from hktex_engine.evaluation.synthetic import icosphere
from hktex_engine.geometry.geodesics import SurfaceTracer
from hktex_engine.geometry.mesh import load_mesh

SPOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "spot" / "spot_triangulated.obj"
STEPS = (0.001, 0.01, 0.05, 0.5)


def _meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    if SPOT.is_file():
        mesh = load_mesh(SPOT)  # merges by position, normalises to bbox side 2
        out["spot"] = (mesh.vertices, mesh.faces)
    else:
        print(f"spot not found at {SPOT}; skipping it", file=sys.stderr)
    out["icosphere5"] = icosphere(5)
    return out


def _starts(tr: SurfaceTracer, n: int, step: float, seed: int):
    rng = np.random.default_rng(seed)
    V, F = tr.vertices.cpu().numpy(), tr.faces.cpu().numpy()
    area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    f = rng.choice(len(F), n, p=area / area.sum())
    b = rng.dirichlet([1.0, 1.0, 1.0], n)
    v = tr.project_to_tangent(f, rng.normal(size=(n, 3)))
    v *= (step / np.linalg.norm(v, axis=1))[:, None]
    return f, b, v


def _time_trace(tr: SurfaceTracer, f, b, v, repeats: int, device: torch.device) -> dict:
    ft = torch.as_tensor(f, device=device)
    bt = torch.as_tensor(b, device=device)
    vt = torch.as_tensor(v, device=device)
    res = tr.trace_full(ft, bt, vt)  # warm-up
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        res = tr.trace_full(ft, bt, vt)
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    t = float(np.median(times))
    return {
        "seconds": t,
        "paths_per_second": len(f) / t,
        "iterations": res.n_iterations,
        "hit_boundary": int(res.hit_boundary.sum()),
        "capped": int(res.capped.sum()),
    }


def _op_overhead(n: int, repeats: int = 200) -> dict:
    """One crossing iteration's core: gather per-face 3x3 blocks, contract, pick the exit."""
    rng = np.random.default_rng(0)
    m = 20000
    G = rng.normal(size=(m, 3, 3))
    f = rng.integers(0, m, n)
    d = rng.normal(size=(n, 3))
    b = rng.random((n, 3))

    def np_iter():
        rate = np.matmul(G.take(f, axis=0), d[:, :, None])[:, :, 0]
        s = np.where(rate < 0, b / np.maximum(-rate, 1e-300), np.inf)
        sm = s.min(1)
        sm = np.where(np.isfinite(sm), sm, 0.0)
        out = b + sm[:, None] * rate
        return out / (out[:, 0] + out[:, 1] + out[:, 2])[:, None]

    Gt, ft, dt, bt = (torch.as_tensor(x) for x in (G, f, d, b))

    def torch_iter():
        rate = torch.bmm(Gt.index_select(0, ft), dt.unsqueeze(2)).squeeze(2)
        s = torch.where(rate < 0, bt / (-rate).clamp_min(1e-300), torch.inf)
        sm, _ = s.min(1)
        sm = torch.where(torch.isfinite(sm), sm, 0.0)
        out = bt + sm[:, None] * rate
        return out / (out[:, 0] + out[:, 1] + out[:, 2])[:, None]

    res = {}
    for name, fn in (("numpy", np_iter), ("torch_cpu", torch_iter)):
        fn()
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        res[name] = (time.perf_counter() - t0) / repeats * 1e6
    return {"n": n, "us_per_iteration": res}


def run(kernels: int, repeats: int) -> dict:
    devices = [torch.device("cpu")]
    if torch.cuda.is_available():
        devices.append(torch.device("cuda"))
    rows = []
    for name, (V, F) in _meshes().items():
        for device in devices:
            tr = SurfaceTracer(V, F, device=device)
            for step in STEPS:
                f, b, v = _starts(tr, kernels, step, seed=0)
                r = _time_trace(tr, f, b, v, repeats, device)
                r.update(mesh=name, vertices=len(V), faces=len(F), device=str(device), step=step)
                rows.append(r)
                print(json.dumps(r), flush=True)
    overhead = [_op_overhead(n) for n in (100, 1000, 10000)]
    return {"rows": rows, "op_overhead": overhead}


def write_results(out: Path, result: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "geodesics.json").write_text(json.dumps(result, indent=2) + "\n")
    m = result["machine"]
    lines = [
        "# Geodesic tracer throughput",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {m['platform']}, {m['cpus']} CPUs ({m['torch_threads']} torch threads), "
        f"torch {m['torch']}, CUDA: {m['cuda'] or 'none'}, 1-min load average at the end "
        f"{m['load_average_1min']:.1f} (a shared machine: timings are upper bounds)  ",
        f"Kernels per batch: {result['kernels']}; median of {result['repeats']} runs after a "
        "warm-up. Meshes in the normalised frame (bounding box side 2).",
        "",
        "| mesh | vertices | device | step | seconds | paths/s | iterations | hit boundary |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['mesh']} | {r['vertices']} | {r['device']} | {r['step']} | "
            f"{r['seconds']:.4f} | {r['paths_per_second']:,.0f} | {r['iterations']} | "
            f"{r['hit_boundary']} |"
        )
    lines += [
        "",
        "One crossing iteration's core operations (gather 3x3 per face, contract, exit pick), "
        "microseconds:",
        "",
        "| active paths | numpy | torch CPU |",
        "|---:|---:|---:|",
    ]
    for o in result["op_overhead"]:
        u = o["us_per_iteration"]
        lines.append(f"| {o['n']} | {u['numpy']:.1f} | {u['torch_cpu']:.1f} |")
    (out / "geodesics.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernels", type=int, default=10000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    command = "python benchmarks/geodesics.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    result = run(args.kernels, args.repeats)
    result.update(
        command=command.strip(), machine=machine_info(), kernels=args.kernels, repeats=args.repeats
    )
    write_results(args.out, result)
    print(f"wrote {args.out / 'geodesics.json'} and geodesics.md")


if __name__ == "__main__":
    main()
