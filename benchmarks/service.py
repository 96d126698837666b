"""Service load benchmark: albedo query throughput and health latency under fitting load.

    python benchmarks/service.py [--clients 32] [--points 10000] [--duration 30]
                                 [--health-duration 20] [--out benchmarks/results]

1. Starts ``hktex serve`` as a child process on a free loopback port (its own data dir, two
   worker slots), so the load generator and the server do not share a GIL.
2. Fits a small kernel set through the client (demo blob, tiny grid, few steps).
3. ``--clients`` concurrent async clients each send albedo queries of ``--points`` surface
   locations (NPY both ways) back to back for ``--duration`` seconds: throughput, latency
   p50/p99, errors (the target is zero).
4. Submits two long fit jobs and, while both run, measures ``GET /v1/health`` latency
   (p50/p99) for ``--health-duration`` seconds, then cancels them.

Writes ``service.json`` and ``service.md`` (machine, command, numbers). Loopback only; every
loop is bounded by its duration and a request timeout.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _machine import machine_info
from hktex_client import AsyncClient, Client
from hktex_server.demo import spawned_service

SPECTRAL = {"angles": 3, "anisotropies": [1.0, 15.0, 100.0], "k": 32, "k_iso": 17}
FIT = {"kernels": 300, "max_kernels": 1200, "steps": 300, "seed": 0, "eval_points": 5000}


def fit_kernelset(url: str, work: Path) -> tuple[str, int, dict]:
    """Upload the demo blob and fit a small kernel set; returns (kernelset id, faces, info)."""
    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj

    v, f, uv, tex = textured_demo(subdivisions=4, texture_size=256)
    obj = write_textured_obj(work / "bench.obj", v, f, uv, tex)
    with Client(url, timeout=300) as client:
        mesh = client.upload_mesh(obj, texture=obj.with_name("bench_albedo.png"))
        spectra = client.request_spectra(mesh.id, **SPECTRAL)
        if not spectra.ready and spectra.job_id:
            client.wait(spectra.job_id, timeout=900)
        job = client.wait(client.fit_uv(mesh.id, spectra=SPECTRAL, **FIT).id, timeout=1800)
        ks = client.get_kernelset(job.result.kernelset_id)
    return (
        ks.id,
        mesh.n_faces,
        {
            "mesh_id": mesh.id,
            "vertices": mesh.n_vertices,
            "faces": mesh.n_faces,
            "kernels": ks.n_kernels,
        },
    )


def _percentiles(latencies: list[float]) -> dict:
    if not latencies:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None}
    a = np.asarray(latencies) * 1000.0
    return {
        "p50_ms": round(float(np.percentile(a, 50)), 2),
        "p99_ms": round(float(np.percentile(a, 99)), 2),
        "max_ms": round(float(a.max()), 2),
    }


async def query_load(
    url: str, ks_id: str, n_faces: int, clients: int, points: int, duration: float
) -> dict:
    """``clients`` concurrent clients, each sending back-to-back NPY queries until time is up."""
    latencies: list[float] = []
    errors: list[str] = []
    rng = np.random.default_rng(0)
    batches = [
        (rng.integers(0, n_faces, points), rng.dirichlet(np.ones(3), points)) for _ in range(4)
    ]

    async def one_client(i: int, stop_at: float) -> None:
        async with AsyncClient(url, timeout=120) as client:
            k = i
            while time.monotonic() < stop_at:
                faces, bary = batches[k % len(batches)]
                k += 1
                t0 = time.monotonic()
                try:
                    colors = await client.albedo(ks_id, face_ids=faces, barycentrics=bary)
                    if colors.shape != (points, 3):
                        raise ValueError(f"shape {colors.shape}")
                    latencies.append(time.monotonic() - t0)
                except Exception as exc:  # counted and reported, never hidden
                    errors.append(f"{type(exc).__name__}: {exc}"[:200])

    start = time.monotonic()
    stop_at = start + duration
    await asyncio.gather(*(one_client(i, stop_at) for i in range(clients)))
    elapsed = time.monotonic() - start
    return {
        "clients": clients,
        "points_per_request": points,
        "duration_s": round(elapsed, 2),
        "requests": len(latencies),
        "errors": len(errors),
        "error_samples": errors[:5],
        "requests_per_s": round(len(latencies) / elapsed, 2),
        "points_per_s": round(len(latencies) * points / elapsed),
        **_percentiles(latencies),
    }


def health_under_fits(url: str, mesh_id: str, duration: float) -> dict:
    """/v1/health latency while two fit jobs run (the API must stay responsive)."""
    with Client(url, timeout=30) as client:
        jobs = [
            client.fit_uv(mesh_id, spectra=SPECTRAL, **{**FIT, "steps": 1_000_000, "seed": s})
            for s in (1, 2)
        ]
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:  # wait until both run (or give up and say so)
            states = [client.get_job(j.id).state for j in jobs]
            if all(s == "running" for s in states):
                break
            time.sleep(0.5)
        latencies, errors = [], 0
        stop_at = time.monotonic() + duration
        while time.monotonic() < stop_at:
            t0 = time.monotonic()
            try:
                client.health()
                latencies.append(time.monotonic() - t0)
            except Exception:
                errors += 1
            time.sleep(0.02)
        running = [client.get_job(j.id).state for j in jobs]
        for j in jobs:
            with contextlib.suppress(Exception):
                client.cancel_job(j.id)
        for j in jobs:
            with contextlib.suppress(Exception):
                client.wait(j.id, timeout=120, raise_on_failure=False)
    return {
        "fit_jobs": 2,
        "job_states_during": running,
        "duration_s": duration,
        "requests": len(latencies),
        "errors": errors,
        **_percentiles(latencies),
    }


def write_results(out: Path, result: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "service.json").write_text(json.dumps(result, indent=2) + "\n")
    q, h = result["queries"], result["health_under_fits"]
    md = [
        "# Service benchmark",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpus']} CPUs, "
        f"Python {result['machine']['python']}, load average at start "
        f"{result['machine']['load_average_1min']} (other work on the machine)  ",
        f"Date: {result['date']}",
        "",
        f"Kernel set: {result['kernelset']['kernels']} kernels on "
        f"{result['kernelset']['vertices']:,} vertices.",
        "",
        "| albedo queries | value |",
        "|---|---|",
        f"| concurrent clients | {q['clients']} |",
        f"| points per request | {q['points_per_request']:,} |",
        f"| duration | {q['duration_s']} s |",
        f"| requests / errors | {q['requests']} / {q['errors']} |",
        f"| throughput | {q['requests_per_s']} req/s, {q['points_per_s']:,} points/s |",
        f"| latency p50 / p99 / max | {q['p50_ms']} / {q['p99_ms']} / {q['max_ms']} ms |",
        "",
        "Every request carries all its points through the engine's query (one thread per "
        "process); with 32 requests in flight each waits for the others, so latency is about "
        "clients x points / throughput.",
        "",
        "| /v1/health during two fit jobs | value |",
        "|---|---|",
        f"| job states while measured | {', '.join(h['job_states_during'])} |",
        f"| requests / errors | {h['requests']} / {h['errors']} |",
        f"| latency p50 / p99 / max | {h['p50_ms']} / {h['p99_ms']} / {h['max_ms']} ms |",
    ]
    (out / "service.md").write_text("\n".join(md) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--points", type=int, default=10_000)
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--health-duration", type=float, default=20.0)
    parser.add_argument("--threads", type=int, default=1, help="CPU threads per process")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    command = "python benchmarks/service.py " + shlex.join(
        argv if argv is not None else sys.argv[1:]
    )
    with tempfile.TemporaryDirectory(prefix="hktex-bench-") as tmp:
        work = Path(tmp)
        (work / "data").mkdir()
        threads = {
            v: str(args.threads)
            for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
        }
        # Threads pinned per process (docs/client.md: spinning OpenMP threads on a loaded
        # 2-core machine cost 10x); the API process and each job process inherit them.
        with spawned_service(work / "data", 2, {**threads, "HKTEX_TOKENS": ""}) as url:
            t0 = time.monotonic()
            ks_id, n_faces, ks_info = fit_kernelset(url, work)
            ks_info["setup_s"] = round(time.monotonic() - t0, 1)
            print(f"kernel set {ks_id} ready: {ks_info}", file=sys.stderr)
            queries = asyncio.run(
                query_load(url, ks_id, n_faces, args.clients, args.points, args.duration)
            )
            print(f"queries: {queries}", file=sys.stderr)
            health = health_under_fits(url, ks_info["mesh_id"], args.health_duration)
            print(f"health: {health}", file=sys.stderr)
    result = {
        "command": command.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(
            note="loopback; load generator and server share the machine's cores"
        ),
        "kernelset": ks_info,
        "queries": queries,
        "health_under_fits": health,
    }
    write_results(args.out, result)
    print(json.dumps({"queries": queries, "health": health}))
    return 0 if queries["errors"] == 0 and health["errors"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
