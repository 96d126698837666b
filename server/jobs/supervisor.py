"""The supervisor: claims jobs, runs each in a fresh process, keeps leases, stops on cancel.

One fresh process per job (``python -m hktex_server.jobs.worker_main JOB_ID``, its own session so
the whole process group can be signalled): no CUDA-after-fork hazards, memory returned at
exit, and a hard kill is always possible. Each slot is pinned to a device through
``CUDA_VISIBLE_DEVICES``. The supervisor is a plain loop (``tick``) so tests can drive it
step by step; ``serve`` runs it in a thread, ``hktex worker`` in the foreground.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from hktex_server.jobs import queue as jobqueue
from hktex_server.settings import Settings
from hktex_server.storage.db import Database

log = logging.getLogger("hktex.supervisor")


@dataclass
class _Child:
    claim: jobqueue.Claim
    proc: subprocess.Popen | ForkedJob
    log_file: IO[bytes]
    cancel_seen: float | None = None
    term_sent: float | None = None
    kill_sent: float | None = None


def detect_devices(settings: Settings) -> list[str]:
    """Devices the slots rotate over: the configured list, else the visible GPUs, else cpu."""
    configured = settings.device_list()
    if configured:
        return configured
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        ids = [d.strip() for d in visible.split(",") if d.strip() and d.strip() != "-1"]
        return ids or ["cpu"]
    smi = shutil.which("nvidia-smi")
    if smi:
        try:
            out = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=10).stdout
            n = sum(1 for line in out.splitlines() if line.startswith("GPU "))
            if n:
                return [str(i) for i in range(n)]
        except (OSError, subprocess.SubprocessError):
            pass
    return ["cpu"]


class Supervisor:
    def __init__(self, settings: Settings, db: Database | None = None, name: str = "") -> None:
        self.settings = settings
        self.db = db or Database(settings.resolved_database_url())
        self.name = name or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.slots = settings.workers
        self.devices = detect_devices(settings)
        self.children: dict[str, _Child] = {}
        self.log_dir = Path(settings.data_dir).resolve() / "logs"
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self._next_heartbeat = 0.0
        self._next_reap = 0.0

    # ------------------------------------------------------------ loop

    def run(self, stop: threading.Event) -> None:
        log.info("supervisor %s: %d slot(s) on %s", self.name, self.slots, self.devices)
        if self.settings.warm_jobs:
            from hktex_server.api import validation

            validation.warm_in_background()
        while not stop.is_set():
            try:
                self.tick()
            except Exception:  # a database hiccup must not end the supervisor
                log.exception("supervisor tick failed")
            stop.wait(self.settings.poll_seconds)
        self.shutdown()

    def tick(self) -> None:
        t = time.monotonic()
        self._collect_exited()
        if t >= self._next_heartbeat:
            self._heartbeat()
            self._next_heartbeat = t + self.settings.heartbeat_seconds
        self._enforce_cancels()
        if t >= self._next_reap:
            counts = jobqueue.reap(self.db)
            if any(counts.values()):
                log.info("reaper: %s", counts)
            self._next_reap = t + min(self.settings.heartbeat_seconds, 5.0)
        self._fill_slots()

    def shutdown(self) -> None:
        """Stop children and hand their jobs back to the queue (another supervisor resumes)."""
        for child in list(self.children.values()):
            _signal_group(child.proc, signal.SIGTERM)
        deadline = time.monotonic() + self.settings.kill_grace_seconds
        for child in list(self.children.values()):
            try:
                child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                _signal_group(child.proc, signal.SIGKILL)
                child.proc.wait()
            self._forget(child, "supervisor shut down", refund=True)

    # ------------------------------------------------------------ steps

    def _fill_slots(self) -> None:
        while len(self.children) < self.slots:
            claim = jobqueue.claim(
                self.db,
                self.name,
                self.settings.lease_seconds,
                self.settings.max_running_per_owner,
                self._pick_device(),
            )
            if claim is None:
                return
            self._spawn(claim)

    def _pick_device(self) -> str:
        load = {d: 0 for d in self.devices}
        for child in self.children.values():
            if child.claim.device in load:
                load[child.claim.device] += 1
        return min(self.devices, key=lambda d: load[d])

    def _spawn(self, claim: jobqueue.Claim) -> None:
        env = worker_env(self.settings, claim.device, claim.token)
        cmd = [sys.executable, "-m", "hktex_server.jobs.worker_main", claim.job_id]
        log_path = self.log_dir / f"{claim.job_id}.log"
        log_file = open(log_path, "ab")  # noqa: SIM115
        from hktex_server.api import validation

        # Warm only once the forkserver has preloaded: the first job after a start must not
        # wait for the preloads (longer than a cold start of a light task); it goes cold.
        warm = self.settings.warm_jobs and validation.ready()
        if self.settings.warm_jobs and not warm:
            validation.warm_in_background()
        mode = "warm" if warm else "cold"
        log_file.write(f"--- {time.ctime()} {self.name} device={claim.device} {mode}\n".encode())
        log_file.flush()
        try:
            if warm:
                proc = _fork_job(claim.job_id, env, log_path)
            else:
                proc = subprocess.Popen(
                    cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True
                )
        except OSError as exc:
            log_file.close()
            jobqueue.release(self.db, claim.job_id, claim.token, f"could not start worker: {exc}")
            return
        self.children[claim.job_id] = _Child(claim, proc, log_file)
        jobqueue.set_pid(self.db, claim.job_id, claim.token, proc.pid)
        log.info("job %s (%s) started as pid %d", claim.job_id, claim.task, proc.pid)

    def _collect_exited(self) -> None:
        for child in list(self.children.values()):
            rc = child.proc.poll()
            if rc is not None:
                self._forget(child, f"worker process exited with code {rc}")

    def _forget(self, child: _Child, reason: str, refund: bool = False) -> None:
        claim = child.claim
        state = jobqueue.release(self.db, claim.job_id, claim.token, reason, refund=refund)
        if state is not None:
            log.info("job %s: %s -> %s", child.claim.job_id, reason, state)
        if state in ("failed", "cancelled"):
            from hktex_server.jobs.tasks import drop_checkpoints

            drop_checkpoints(self.settings, claim.job_id)
        child.log_file.close()
        self.children.pop(child.claim.job_id, None)

    def _heartbeat(self) -> None:
        held = {jid: c.claim.token for jid, c in self.children.items()}
        for job_id in jobqueue.heartbeat(self.db, held, self.settings.lease_seconds):
            child = self.children.pop(job_id, None)
            if child is not None:  # the job is someone else's now: never run it twice
                log.warning("job %s: lease lost, killing pid %d", job_id, child.proc.pid)
                _signal_group(child.proc, signal.SIGKILL)
                child.proc.wait()
                child.log_file.close()

    def _enforce_cancels(self) -> None:
        """Cooperative stop first (the worker polls the flag); then SIGTERM, then SIGKILL."""
        flagged = jobqueue.cancel_flags(self.db, list(self.children))
        t = time.monotonic()
        for job_id in flagged:
            child = self.children[job_id]
            if child.cancel_seen is None:
                child.cancel_seen = t
            elapsed = t - child.cancel_seen
            grace, kill_grace = self.settings.cancel_grace_seconds, self.settings.kill_grace_seconds
            if child.term_sent is None and elapsed >= grace:
                _signal_group(child.proc, signal.SIGTERM)
                child.term_sent = t
            elif child.kill_sent is None and elapsed >= grace + kill_grace:
                _signal_group(child.proc, signal.SIGKILL)
                child.kill_sent = t

    def status(self) -> dict:
        return {
            "name": self.name,
            "slots": self.slots,
            "devices": self.devices,
            "running": {jid: c.proc.pid for jid, c in self.children.items()},
        }


THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def worker_env(settings: Settings, device: str | None, token: str) -> dict[str, str]:
    """The environment of one job process.

    Thread counts go in as environment variables because OpenMP, OpenBLAS and MKL read them
    once, when their library loads: setting them inside the child after ``import torch`` or
    ``import numpy`` would be too late for the pools those imports create.
    """
    env = os.environ.copy()
    env["CUDA_VISIBLE_DEVICES"] = "" if device in (None, "cpu") else device
    env["HKTEX_LEASE_TOKEN"] = token  # not on the command line: ps shows argv
    # the job needs no API tokens: keep them out of its environment and its settings
    env.pop("HKTEX_TOKENS", None)
    env["HKTEX_WORKER_SETTINGS"] = settings.model_dump_json(exclude={"tokens"})
    threads = str(settings.threads_per_job())
    for var in THREAD_VARS:
        env[var] = threads
    env["HKTEX_JOB_THREADS"] = threads
    return env


class ForkedJob:
    """A job process forked from the warm forkserver, with the part of ``Popen``'s interface
    the supervisor uses (``pid``, ``poll``, ``wait``). The forkserver reports its exit code;
    the process leads its own process group (``forked_main`` calls ``setsid``)."""

    def __init__(self, proc) -> None:
        self.proc = proc
        self.pid = proc.pid

    def poll(self) -> int | None:
        return self.proc.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self.proc.join(timeout)
        code = self.proc.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(f"job pid {self.pid}", timeout or 0)
        return code


def _fork_job(job_id: str, env: dict[str, str], log_path: Path) -> ForkedJob:
    """Fork the job from the forkserver that already imported the engine (validation's
    context, preloading the job modules): the ~13 s of imports a cold ``python -m`` paid on a
    loaded host become a fork. Raises OSError when the forkserver cannot start it."""
    from hktex_server.api import validation
    from hktex_server.jobs.worker_main import forked_main

    ctx = validation.context()
    proc = ctx.Process(
        target=forked_main, args=(job_id, env, str(log_path)), name=f"hktex-job-{job_id}"
    )
    try:
        proc.start()
    except Exception as exc:  # the forkserver failed to start or to fork
        raise OSError(f"warm fork failed: {exc}") from exc
    return ForkedJob(proc)


def _signal_group(proc: subprocess.Popen | ForkedJob, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


class SupervisorThread:
    """The embedded supervisor of ``hktex serve``: the same loop in a daemon thread."""

    def __init__(self, settings: Settings) -> None:
        self.supervisor = Supervisor(settings)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self.supervisor.run, args=(self._stop,), name="hktex-supervisor", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        self._thread.join(timeout)


def main_loop(settings: Settings) -> int:
    """``hktex worker``: a supervisor in the foreground until SIGINT/SIGTERM."""
    db = Database(settings.resolved_database_url())
    db.migrate()
    sup = Supervisor(settings, db)
    stop = threading.Event()

    def _stop(_sig: int, _frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    print(json.dumps({"supervisor": sup.name, "slots": sup.slots, "devices": sup.devices}))
    sys.stdout.flush()
    sup.run(stop)
    return 0


if __name__ == "__main__":  # python -m hktex_server.jobs.supervisor (settings from the environment)
    _raw = os.environ.get("HKTEX_WORKER_SETTINGS")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    sys.exit(main_loop(Settings.model_validate_json(_raw) if _raw else Settings()))
