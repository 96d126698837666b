"""One job, one process: ``python -m hktex_server.jobs.worker_main JOB_ID``.

Started by a supervisor with the lease token and the settings in its environment
(``HKTEX_LEASE_TOKEN``, ``HKTEX_WORKER_SETTINGS``). It runs the task, reports progress to
the job row at most about once a second, polls the cancel flag through
``Progress.should_stop`` and writes the final state, all guarded by the lease token. If its
supervisor dies (the process is re-parented) or its lease moves on, it stops without writing
a final state: the reaper re-queues the job and exactly one run publishes a result.

Exit codes: 0 final state written; 3 lease lost / orphaned; 143 terminated by SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import time
import traceback
from typing import Any

from hktex_server.jobs import queue as jobqueue
from hktex_server.settings import Settings
from hktex_server.storage.db import Database, JobRow

EXIT_LOST = 3
EXIT_TERMINATED = 143


class Terminated(BaseException):
    """SIGTERM from the supervisor: unwind (temp files, finally blocks) and exit."""


class DbProgress:
    """Progress sink writing to the job row; implements ``hktex_engine.progress.Progress``."""

    def __init__(
        self,
        db: Database,
        job_id: str,
        token: str,
        write_interval: float = 1.0,
        poll_interval: float = 0.5,
    ) -> None:
        self.db, self.job_id, self.token = db, job_id, token
        self.write_interval, self.poll_interval = write_interval, poll_interval
        self.parent = os.getppid()
        self.lost = False
        self.cancel = False
        self._last_write = 0.0
        self._last_poll = 0.0
        self._pending: dict[str, Any] | None = None

    def update(self, step: int, total: int, **metrics: Any) -> None:
        self._pending = progress_record(step, total, metrics)
        t = time.monotonic()
        if t - self._last_write >= self.write_interval or (total and step >= total):
            self.flush()

    def flush(self) -> None:
        if self._pending is None:
            return
        if not jobqueue.write_progress(self.db, self.job_id, self.token, self._pending):
            self.lost = True
        self._pending = None
        self._last_write = time.monotonic()

    def should_stop(self) -> bool:
        if os.getppid() != self.parent:  # the supervisor died: we are an orphan
            self.lost = True
        t = time.monotonic()
        if not (self.lost or self.cancel) and t - self._last_poll >= self.poll_interval:
            self._last_poll = t
            status = jobqueue.lease_status(self.db, self.job_id, self.token)
            self.lost = status == "lost"
            self.cancel = status == "cancel"
        return self.lost or self.cancel


def progress_record(step: int, total: int, metrics: dict[str, Any]) -> dict[str, Any]:
    """The JSON progress of a job: loss and kernel count promoted, finite scalars kept."""
    metrics = dict(metrics)
    loss = _finite(metrics.pop("loss", None))
    count = None
    for key in ("kernel_count", "kernels", "n_kernels"):
        if key in metrics:
            count = metrics.pop(key)
    stage = metrics.pop("stage", None)
    clean = {k: f for k, v in metrics.items() if (f := _finite(v)) is not None}
    return {
        "step": int(step),
        "total": int(total),
        "stage": str(stage)[:64] if stage is not None else None,
        "loss": loss,
        "kernel_count": int(count) if _finite(count) is not None else None,
        "metrics": clean,
        "updated_at": time.time(),
    }


def _finite(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _on_sigterm(_sig: int, _frame: object) -> None:
    raise Terminated


def run_job(settings: Settings, db: Database, job_id: str, token: str) -> int:
    from hktex_server.jobs import tasks

    from hktex_engine.errors import Cancelled, HKTexError

    with db.read() as s:
        job = s.get(JobRow, job_id)
    if job is None or job.lease_token != token or job.state not in jobqueue.RUNNING_STATES:
        print(f"job {job_id}: not ours to run (lease moved on)", flush=True)
        return EXIT_LOST
    progress = DbProgress(db, job_id, token)
    print(f"job {job_id}: {job.task} attempt {job.attempts}", flush=True)
    try:
        outcome = tasks.run(tasks.TaskContext(settings, db, job, progress))
        progress.flush()
    except Cancelled:
        if progress.lost:
            print(f"job {job_id}: lease lost or orphaned, stopping", flush=True)
            return EXIT_LOST
        jobqueue.finish(db, job_id, token, "cancelled", error="cancelled by request")
        print(f"job {job_id}: cancelled (cooperative stop)", flush=True)
        return 0
    except (HKTexError, ValueError, FileNotFoundError) as exc:  # bad input: no retry helps
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"job {job_id}: failed: {type(exc).__name__}: {message}", flush=True)
        jobqueue.finish(db, job_id, token, "failed", error=f"{type(exc).__name__}: {message}")
        return 0
    except Exception as exc:  # a bug: record it once rather than retry it max_attempts times
        traceback.print_exc()
        jobqueue.finish(
            db, job_id, token, "failed", error=f"internal error: {type(exc).__name__}: {exc}"
        )
        return 0
    if not jobqueue.finish(
        db, job_id, token, "succeeded", result=outcome.result, on_success=outcome.on_success
    ):
        outcome.discard()
        print(f"job {job_id}: finished but the lease had moved on; result dropped", flush=True)
        return EXIT_LOST
    print(f"job {job_id}: succeeded {outcome.result}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hktex_server.jobs.worker_main")
    parser.add_argument("job_id")
    args = parser.parse_args(argv)
    token = os.environ.get("HKTEX_LEASE_TOKEN", "")
    raw = os.environ.get("HKTEX_WORKER_SETTINGS")
    settings = Settings.model_validate_json(raw) if raw else Settings()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    signal.signal(signal.SIGTERM, _on_sigterm)
    # OMP/OpenBLAS/MKL_NUM_THREADS come from the supervisor (supervisor.worker_env): torch,
    # numpy and faiss size their pools from them when the task imports them.
    print(
        f"job {args.job_id}: {os.environ.get('OMP_NUM_THREADS', 'all')} CPU thread(s)", flush=True
    )
    db = Database(settings.resolved_database_url())
    try:
        rc = run_job(settings, db, args.job_id, token)
        if rc == 0:  # a final state was written
            from hktex_server.jobs.tasks import drop_checkpoints

            drop_checkpoints(settings, args.job_id)
        return rc
    except Terminated:
        print(f"job {args.job_id}: terminated", flush=True)
        return EXIT_TERMINATED
    finally:
        db.dispose()


def forked_main(job_id: str, env: dict[str, str], log_path: str) -> None:
    """A job in a process forked from the warm forkserver (``Supervisor._spawn``): the
    equivalent of ``python -m hktex_server.jobs.worker_main JOB_ID`` with ``env`` and its
    output to ``log_path``, minus the seconds of imports (torch, the engine) it inherits.

    The fork is a fresh address space like a new process; ``setsid`` gives it its own process
    group so the supervisor's hard kill (SIGTERM/SIGKILL to the group) works as before. Thread
    counts cannot come from the environment here (the libraries were loaded by the
    forkserver), so they are set through the libraries' own calls.
    """
    os.setsid()
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    os.environ.clear()
    os.environ.update(env)
    set_thread_counts(int(env.get("HKTEX_JOB_THREADS", "0") or 0))
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(main([job_id]))


def set_thread_counts(threads: int) -> None:
    """torch, faiss (OpenMP) and OpenBLAS thread pools to ``threads`` in this process."""
    if threads < 1:
        return
    import ctypes

    try:
        import torch

        torch.set_num_threads(threads)
    except Exception:  # noqa: BLE001 - torch absent: nothing to size
        pass
    try:
        import faiss

        faiss.omp_set_num_threads(threads)
    except Exception:  # noqa: BLE001 - faiss is optional
        pass
    try:  # the OpenBLAS numpy/scipy loaded (what threadpoolctl does, without the dependency)
        with open("/proc/self/maps") as f:
            libs = {line.split()[-1] for line in f if "openblas" in line.lower()}
    except OSError:
        libs = set()
    for lib in libs:
        try:
            handle = ctypes.CDLL(lib)
        except OSError:
            continue
        for name in (
            "openblas_set_num_threads",
            "openblas_set_num_threads64_",
            "scipy_openblas_set_num_threads",
            "scipy_openblas_set_num_threads64_",
        ):
            fn = getattr(handle, name, None)
            if fn is not None:
                fn(threads)
                break


if __name__ == "__main__":
    sys.exit(main())
