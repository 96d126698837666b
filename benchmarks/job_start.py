"""Job start latency: from a job's claim to its first progress report, cold vs warm processes.

    python benchmarks/job_start.py [--jobs 3] [--out benchmarks/results]

For each mode (``HKTEX_WARM_JOBS=0``: a fresh ``python -m`` per job; ``1``: a fork of the
forkserver that already imported the engine) a ``hktex serve`` with one slot gets ``--jobs``
spectra jobs on a small mesh, one after another (distinct configs, so none is cached). The
latency is the job row's first ``progress.updated_at`` minus its ``started_at`` (the claim):
imports, mesh load and the first step. Writes ``job_start.json`` and ``job_start.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from _machine import machine_info
from hktex_server.demo import spawned_service


def one_mode(warm: bool, jobs: int, work: Path) -> dict:
    from hktex_engine.evaluation.synthetic import icosphere, write_textured_obj

    v, f = icosphere(2)
    obj = write_textured_obj(work / f"ico-{int(warm)}.obj", v, f)
    env = {"HKTEX_WARM_JOBS": "1" if warm else "0", "HKTEX_TOKENS": "", "OMP_NUM_THREADS": "1"}
    latencies, runs = [], []
    with spawned_service(work / f"data-{int(warm)}", 1, env) as url:
        # the forkserver preloads in the background at start; until it is ready jobs go cold
        time.sleep(20.0)
        with httpx.Client(base_url=url, timeout=60) as c:
            mesh = c.post("/v1/meshes", files={"mesh": (obj.name, obj.read_bytes())}).json()
            for i in range(jobs):
                cfg = {"angles": 2, "anisotropies": [1.0, 2.0 + i], "k": 8, "k_iso": 4}
                job_id = c.post(f"/v1/meshes/{mesh['id']}/spectra", json=cfg).json()["job_id"]
                deadline = time.monotonic() + 300
                while time.monotonic() < deadline:
                    job = c.get(f"/v1/jobs/{job_id}").json()
                    first = job["progress"]["updated_at"]
                    if first and job["started_at"]:
                        latencies.append(first - job["started_at"])
                        break
                    if job["state"] in ("failed", "cancelled"):
                        raise RuntimeError(f"job {job_id} {job['state']}: {job['error']}")
                    time.sleep(0.05)
                while c.get(f"/v1/jobs/{job_id}").json()["state"] in ("queued", "running"):
                    time.sleep(0.1)
                runs.append({"job": job_id, "claim_to_first_progress_s": round(latencies[-1], 3)})
    a = np.asarray(latencies)
    return {
        "warm": warm,
        "jobs": runs,
        "median_s": round(float(np.median(a)), 3),
        "max_s": round(float(a.max()), 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--jobs", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    command = "python benchmarks/job_start.py " + shlex.join(
        argv if argv is not None else sys.argv[1:]
    )
    modes = []
    with tempfile.TemporaryDirectory(prefix="hktex-jobstart-") as tmp:
        for warm in (False, True):
            load = os.getloadavg()[0]
            mode = one_mode(warm, args.jobs, Path(tmp))
            mode["load_average_before"] = round(load, 2)
            print(mode, file=sys.stderr)
            modes.append(mode)
    result = {
        "command": command.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(note="one job slot, OMP_NUM_THREADS=1"),
        "modes": modes,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "job_start.json").write_text(json.dumps(result, indent=2) + "\n")
    m = result["machine"]
    md = [
        "# Job start latency: claim to first progress (issue 11)",
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {m['platform']}, {m['cpus']} CPUs, Python {m['python']}, load average at "
        f"start {m['load_average_1min']} (a shared machine)  ",
        f"Date: {result['date']}",
        "",
        "Spectra jobs on an icosphere (162 vertices, tiny grid), one slot, one after another.",
        "",
        "| job process | load before | claim -> first progress, each (s) | median | max |",
        "|---|---|---|---|---|",
    ]
    for mode in modes:
        each = ", ".join(str(r["claim_to_first_progress_s"]) for r in mode["jobs"])
        name = "warm fork (HKTEX_WARM_JOBS=1)" if mode["warm"] else "cold python -m (=0)"
        md.append(
            f"| {name} | {mode['load_average_before']} | {each} | {mode['median_s']} s "
            f"| {mode['max_s']} s |"
        )
    (args.out / "job_start.md").write_text("\n".join(md) + "\n")
    print(json.dumps(modes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
