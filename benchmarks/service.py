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

``--compare REV`` (issue 11) instead measures the query path of the server code at git
revision ``REV`` against the working tree's, in the same run on the same machine: each server
(``hktex serve`` with the old ``hktex_server`` extracted by ``git archive`` first on
``PYTHONPATH``, then the current one) gets the same seeded kernel set (spectra computed here,
random kernels: no fit), the same query load, and ``/v1/health`` probed throughout the load.
``--with-engine`` puts the engine of ``REV`` on the old side's path too, so the old side is the
whole old product (issue 11 compares with the code as it was, engine included).
Results go to ``service_compare.json`` and ``service.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
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

    health: list[float] = []
    health_errors: list[str] = []

    async def probe_health(stop_at: float) -> None:
        """/v1/health every 50 ms during the load: the API must stay responsive."""
        async with httpx.AsyncClient(base_url=url, timeout=30) as client:
            while time.monotonic() < stop_at:
                t0 = time.monotonic()
                try:
                    (await client.get("/v1/health")).raise_for_status()
                    health.append(time.monotonic() - t0)
                except Exception as exc:  # counted and reported
                    health_errors.append(f"{type(exc).__name__}: {exc}"[:200])
                await asyncio.sleep(0.05)

    start = time.monotonic()
    stop_at = start + duration
    await asyncio.gather(probe_health(stop_at), *(one_client(i, stop_at) for i in range(clients)))
    elapsed = time.monotonic() - start
    return {
        "health": {
            "requests": len(health),
            "errors": len(health_errors),
            **_percentiles(health),
        },
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


def seed_kernelset(url: str, data_dir: Path, work: Path, kernels: int) -> tuple[str, int, dict]:
    """The demo blob uploaded, its spectra computed here into the service's cache (adopted by
    ``POST /spectra``), and ``kernels`` random kernels published as a kernel set: the same
    query cost as a fitted set of that size, without a fit. Deterministic (seed 0)."""
    from hktex_server.storage.blobs import BlobStore
    from hktex_server.storage.db import Database, KernelSetRow, new_id, now

    from hktex_engine.config import SpectralConfig
    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.kernels.model import KernelSet
    from hktex_engine.spectra.grid import SpectraCache

    v, f, uv, tex = textured_demo(subdivisions=4, texture_size=64)
    obj = write_textured_obj(work / "bench.obj", v, f, uv, tex)
    with httpx.Client(base_url=url, timeout=300) as c:
        mesh = c.post("/v1/meshes", files={"mesh": (obj.name, obj.read_bytes())})
        mesh.raise_for_status()
        mesh = mesh.json()
        config = SpectralConfig.from_dict(SPECTRAL)
        spectra = SpectraCache(data_dir / "spectra").get_or_compute(load_mesh(obj), config)
        r = c.post(f"/v1/meshes/{mesh['id']}/spectra", json=SPECTRAL)
        r.raise_for_status()
        spectra_id = r.json()["id"]
    rng = np.random.default_rng(0)
    n_faces = int(spectra.faces.shape[0])
    ks = KernelSet(
        face_ids=rng.integers(0, n_faces, kernels),
        barycentrics=rng.dirichlet(np.ones(3), kernels),
        theta=rng.uniform(0, np.pi, kernels),
        eta=1 + 99 * rng.uniform(size=kernels),
        threshold=rng.uniform(0.5, 0.95, kernels),
        sharpness=10 + 40 * rng.uniform(size=kernels),
        colors=rng.uniform(-0.5, 0.5, (kernels, 3)),
        base_color=np.full(3, 0.5),
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
    )
    store = BlobStore(data_dir)
    tmp = store.temp_path(".hkt")
    save_hkt(ks, tmp)
    rel, _digest, size = store.publish_file(tmp, "kernelsets", ".hkt")
    ks_id = new_id("kst")
    db = Database(f"sqlite:///{(data_dir / 'hktex.db').resolve()}")
    with db.write() as s:
        s.add(
            KernelSetRow(
                id=ks_id,
                owner="local",
                job_id=None,
                mesh_id=mesh["id"],
                spectra_id=spectra_id,
                path=rel,
                bytes=size,
                n_kernels=kernels,
                metrics={},
                manifest={"seeded": True},
                created_at=now(),
            )
        )
    db.dispose()
    info = {"vertices": mesh["n_vertices"], "faces": n_faces, "kernels": kernels}
    return ks_id, n_faces, info


def _server_pid(url: str) -> int | None:
    """The ``hktex serve`` process listening at ``url`` (spawned_service yields only the URL)."""
    port = url.rsplit(":", 1)[1]
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"serve" in argv and port.encode() in argv:
            return int(entry)
    return None


def tree_cpu_seconds(pid: int | None) -> float:
    """User + system CPU seconds of a process and its live descendants (from /proc)."""
    if pid is None:
        return float("nan")
    stats: dict[int, tuple[int, float]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            ticks = int(fields[11]) + int(fields[12])  # utime, stime
            stats[int(entry)] = (int(fields[1]), ticks / os.sysconf("SC_CLK_TCK"))
    tree, frontier = {pid}, [pid]
    while frontier:
        parent = frontier.pop()
        kids = [p for p, (pp, _) in stats.items() if pp == parent and p not in tree]
        tree.update(kids)
        frontier += kids
    return sum(stats[p][1] for p in tree if p in stats)


def old_server_path(rev: str, work: Path, with_engine: bool = False) -> Path:
    """``hktex_server`` as it was at ``rev`` (``git archive`` of ``server/``), for PYTHONPATH;
    with ``with_engine`` the engine package of ``rev`` too, so the old side is the whole old
    product (its query code included), not the old server calling today's engine."""
    repo = Path(__file__).resolve().parents[1]
    dest = work / "old-server"
    dest.mkdir()
    paths = ["server", "hktex_engine"] if with_engine else ["server"]
    archive = subprocess.run(
        ["git", "-C", str(repo), "archive", rev, *paths], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    (dest / "server").rename(dest / "hktex_server")
    return dest


def engine_location(env: dict[str, str], cwd: Path) -> str:
    """Where a server started with ``env`` from ``cwd`` imports ``hktex_engine`` from (the
    proof that each side ran the engine it names)."""
    probe = "import hktex_engine, os; print(os.path.dirname(hktex_engine.__file__))"
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, cwd=cwd, capture_output=True, text=True
    )
    return out.stdout.strip() or out.stderr.strip()[-200:]


def compare(args: argparse.Namespace, command: str) -> int:
    """Old server code vs the working tree's, same kernel set and load, one run."""
    threads = {
        v: str(args.threads) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    }
    runs = {}
    with tempfile.TemporaryDirectory(prefix="hktex-bench-") as tmp:
        work = Path(tmp)
        old = old_server_path(args.compare, work, args.with_engine)
        for label, extra in (
            (
                f"old ({args.compare}{' + its engine' if args.with_engine else ''})",
                {"PYTHONPATH": f"{old}{os.pathsep}" + os.environ.get("PYTHONPATH", "")},
            ),
            ("new (working tree)", {}),
        ):
            data = work / label.split()[0]
            env = {**threads, "HKTEX_TOKENS": "", **extra}
            load = os.getloadavg()[0]
            # outside the repository (both sides alike): from its root, ``python -m`` would
            # import today's hktex_engine ahead of the old one on PYTHONPATH (it did, until
            # 2026-12-01 night: the "old" side of earlier --with-engine runs had today's engine)
            with spawned_service(data, 0, env, cwd=work) as url:
                ks_id, n_faces, ks_info = seed_kernelset(url, data, work, args.kernels)
                with httpx.Client(base_url=url, timeout=300) as c:  # warm every worker
                    rng = np.random.default_rng(1)
                    rows = np.column_stack(
                        [rng.integers(0, n_faces, 64).astype(float), rng.dirichlet(np.ones(3), 64)]
                    )
                    body = {
                        "face_ids": rows[:, 0].astype(int).tolist(),
                        "barycentrics": rows[:, 1:].tolist(),
                    }
                    for _ in range(8):
                        c.post(f"/v1/kernelsets/{ks_id}/albedo", json=body).raise_for_status()
                pid = _server_pid(url)
                cpu0 = tree_cpu_seconds(pid)
                queries = asyncio.run(
                    query_load(url, ks_id, n_faces, args.clients, args.points, args.duration)
                )
                cpu = tree_cpu_seconds(pid) - cpu0
            queries["load_average_before"] = round(load, 2)
            queries["engine_imported_from"] = engine_location({**os.environ, **env}, work)
            # On a shared, saturated host throughput measures the scheduler; the server's CPU
            # use says what the code can do: cores it kept busy, points per CPU-second.
            queries["server_cpu_s"] = round(cpu, 1)
            queries["server_cores_busy"] = round(cpu / queries["duration_s"], 2)
            points = queries["requests"] * queries["points_per_request"]
            queries["points_per_server_cpu_s"] = round(points / cpu) if cpu > 0 else None
            print(f"{label}: {queries}", file=sys.stderr)
            runs[label] = queries
    old_q, new_q = runs.values()
    speedup = new_q["points_per_s"] / max(1, old_q["points_per_s"])
    result = {
        "command": command.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(
            note="loopback; load generator and server share the machine's cores"
        ),
        "kernelset": ks_info,
        "runs": runs,
        "speedup_points_per_s": round(speedup, 2),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "service_compare.json").write_text(json.dumps(result, indent=2) + "\n")
    write_compare_md(args.out, result)
    print(json.dumps({"speedup": result["speedup_points_per_s"], "runs": runs}))
    ok = all(r["errors"] == 0 and r["health"]["errors"] == 0 for r in runs.values())
    return 0 if ok else 1


def write_compare_md(out: Path, result: dict) -> None:
    m = result["machine"]
    rows = [
        "| | " + " | ".join(result["runs"]) + " |",
        "|---|" + "---|" * len(result["runs"]),
    ]

    def row(name: str, fn) -> None:
        rows.append(f"| {name} | " + " | ".join(fn(r) for r in result["runs"].values()) + " |")

    row("load average before", lambda r: str(r["load_average_before"]))
    row("hktex_engine imported from", lambda r: f"`{r.get('engine_imported_from', '?')}`")
    row("requests / errors", lambda r: f"{r['requests']} / {r['errors']}")
    row("throughput", lambda r: f"{r['requests_per_s']} req/s, {r['points_per_s']:,} points/s")
    row("latency p50 / p99 / max", lambda r: f"{r['p50_ms']} / {r['p99_ms']} / {r['max_ms']} ms")
    row("server CPU during the load", lambda r: f"{r['server_cpu_s']} s")
    row("cores the server kept busy", lambda r: str(r["server_cores_busy"]))
    row("points per server CPU-second", lambda r: f"{r['points_per_server_cpu_s']:,}")
    row(
        "/v1/health during the load: n / errors",
        lambda r: f"{r['health']['requests']} / {r['health']['errors']}",
    )
    row(
        "/v1/health p50 / p99 / max",
        lambda r: f"{r['health']['p50_ms']} / {r['health']['p99_ms']} / {r['health']['max_ms']} ms",
    )
    q = next(iter(result["runs"].values()))
    md = [
        "# Service benchmark: albedo queries, old vs new server (issue 11)",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {m['platform']}, {m['cpus']} CPUs, Python {m['python']}, load average at "
        f"start {m['load_average_1min']} (a shared machine: other work ran beside it)  ",
        f"Date: {result['date']}",
        "",
        f"Kernel set: {result['kernelset']['kernels']} seeded kernels on "
        f"{result['kernelset']['vertices']:,} vertices; {q['clients']} concurrent clients, "
        f"{q['points_per_request']:,} points per NPY request, {q['duration_s']} s each.",
        "",
        *rows,
        "",
        f"Throughput new / old: **{result['speedup_points_per_s']}x**.",
    ]
    (out / "service.md").write_text("\n".join(md) + "\n")


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
    parser.add_argument(
        "--compare", metavar="REV", help="old server code at this git revision vs the current"
    )
    parser.add_argument("--kernels", type=int, default=1200, help="seeded kernels (--compare)")
    parser.add_argument(
        "--with-engine",
        action="store_true",
        help="--compare: the old side runs the engine of REV too (the whole old product)",
    )
    args = parser.parse_args(argv)
    command = "python benchmarks/service.py " + shlex.join(
        argv if argv is not None else sys.argv[1:]
    )
    if args.compare:
        return compare(args, command)
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
