"""The jobs-table queue with real worker processes: claims, cancel, kill, reaper, retries,
fair share, spectra deduplication. SQLite always; PostgreSQL when HKTEX_TEST_PG_URL is set.

The internal ``sleep`` task stands in for the engine so these tests measure the queue, not
the science; markers it writes count how many processes ever ran a job.
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter

import pytest
from hktex_server.jobs import queue as jobqueue
from hktex_server.storage.db import JobRow, SpectraRow

from tests.server_support import (
    BACKENDS,
    SupervisorInThread,
    add_sleep_job,
    database_url,
    drop_schema,
    fast_settings,
    job,
    kill_group,
    migrated,
    start_supervisor_process,
    wait_for,
)


def _backend(name, tmp_path):
    settings = fast_settings(tmp_path, database_url(name, tmp_path))
    return settings, migrated(settings)


@pytest.fixture(params=BACKENDS)
def backend(request, tmp_path):
    """Both databases: for claims and transitions, where the SQL differs."""
    settings, db = _backend(request.param, tmp_path)
    yield settings, db
    db.dispose()
    drop_schema(settings.resolved_database_url())


@pytest.fixture(
    params=["sqlite", pytest.param("postgres", marks=[pytest.mark.postgres, pytest.mark.slow])]
)
def proc_backend(request, tmp_path):
    """Process-lifecycle tests: the database only stores what they exercise, so PostgreSQL
    repeats them in the slow run only (keeps the default suite short)."""
    settings, db = _backend(request.param, tmp_path)
    yield settings, db
    db.dispose()
    drop_schema(settings.resolved_database_url())


def _log(settings, job_id) -> str:
    return (settings.data_dir.resolve() / "logs" / f"{job_id}.log").read_text()


def _state(db, job_id):
    return job(db, job_id).state


def test_concurrent_claims_never_hand_out_a_job_twice(backend, tmp_path):
    """Four claimers on separate connections race over 60 jobs: each is claimed once."""
    settings, db = backend
    ids = [add_sleep_job(db, owner=f"o{i % 3}") for i in range(60)]
    claimed: list[str] = []
    lock = threading.Lock()

    def claimer(name: str) -> None:
        from hktex_server.storage.db import Database

        own_db = Database(settings.resolved_database_url())
        while (c := jobqueue.claim(own_db, name, 30, running_cap=1000, device="cpu")) is not None:
            with lock:
                claimed.append(c.job_id)
        own_db.dispose()

    threads = [threading.Thread(target=claimer, args=(f"s{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert sorted(claimed) == sorted(ids)
    assert max(Counter(claimed).values()) == 1


def test_two_supervisor_processes_run_each_job_once(backend, tmp_path):
    settings, db = backend
    marker = tmp_path / "runs.txt"
    ids = [add_sleep_job(db, steps=1, seconds=0.05, marker=str(marker)) for _ in range(6)]
    procs = [start_supervisor_process(settings.model_copy(update={"workers": 2})) for _ in range(2)]
    try:
        wait_for(lambda: all(_state(db, j) == "succeeded" for j in ids), 90, "all jobs done")
    finally:
        for p in procs:
            kill_group(p.pid)
            p.wait()
    runs = Counter(line.split()[0] for line in marker.read_text().splitlines())
    assert runs == dict.fromkeys(ids, 1)


def test_progress_and_success(proc_backend):
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=4, seconds=0.4)
    with SupervisorInThread(settings):
        wait_for(lambda: _state(db, jid) == "succeeded", 30, "success")
    row = job(db, jid)
    assert row.progress["step"] == 4 and row.progress["total"] == 4
    assert row.progress["loss"] == pytest.approx(0.25)
    assert row.progress["kernel_count"] == 3
    assert row.attempts == 1 and row.lease_token is None and row.finished_at >= row.started_at


def test_cancel_running_job_stops_cooperatively(proc_backend):
    settings, db = proc_backend
    # A generous grace: on a loaded machine 1 s could expire while the worker is still
    # writing its final state, and SIGTERM would then (rightly) be logged.
    settings = settings.model_copy(update={"cancel_grace_seconds": 20.0})
    jid = add_sleep_job(db, steps=200, seconds=40)
    with SupervisorInThread(settings):
        wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
        assert jobqueue.request_cancel(db, "local", jid).state == "cancelling"
        wait_for(lambda: _state(db, jid) == "cancelled", 30, "cancelled")
    assert job(db, jid).error == "cancelled by request"
    log = _log(settings, jid)
    assert "cancelled (cooperative stop)" in log and "terminated" not in log


def test_cancel_deaf_job_is_terminated(proc_backend):
    """A task that never polls the flag is stopped by SIGTERM after the grace period."""
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=200, seconds=40, ignore_cancel=True)
    with SupervisorInThread(settings):
        wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
        jobqueue.request_cancel(db, "local", jid)
        wait_for(lambda: _state(db, jid) == "cancelled", 30, "cancelled")
    log = _log(settings, jid)
    assert "terminated" in log and "cooperative" not in log  # SIGTERM after the grace period


def test_cancel_wedged_job_is_killed(proc_backend):
    """Deaf to the flag and to SIGTERM: SIGKILL of the process group ends it."""
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=200, seconds=40, ignore_cancel=True, ignore_sigterm=True)
    with SupervisorInThread(settings):
        wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
        jobqueue.request_cancel(db, "local", jid)
        wait_for(lambda: _state(db, jid) == "cancelled", 30, "cancelled")
    log = _log(settings, jid)
    assert "terminated" not in log and "cooperative" not in log


def test_cancel_queued_job_is_immediate(backend):
    _settings, db = backend
    jid = add_sleep_job(db)
    assert jobqueue.request_cancel(db, "local", jid).state == "cancelled"
    assert jobqueue.request_cancel(db, "someone-else", jid) is None


def test_killed_worker_and_supervisor_job_requeued_and_finished_elsewhere(proc_backend, tmp_path):
    settings, db = proc_backend
    marker = tmp_path / "runs.txt"
    jid = add_sleep_job(db, steps=30, seconds=3, marker=str(marker))
    first = start_supervisor_process(settings)
    try:
        pid = wait_for(lambda: job(db, jid).pid, 60, "worker pid")
        wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
    finally:
        kill_group(pid)  # the job's process group ...
        kill_group(first.pid)  # ... and its supervisor: nobody will report the death
        first.wait()
    assert _state(db, jid) == "running"  # as far as the database knows
    with SupervisorInThread(settings, name="second"):
        wait_for(lambda: _state(db, jid) == "succeeded", 60, "re-run to success")
    row = job(db, jid)
    assert row.attempts == 2
    assert [line.split()[1] for line in marker.read_text().splitlines()] == ["1", "2"]


@pytest.mark.slow
def test_orphaned_worker_stops_and_job_runs_once_more(proc_backend, tmp_path):
    """Supervisor killed, worker alive: the worker notices and quits, never finishing twice."""
    settings, db = proc_backend
    marker = tmp_path / "runs.txt"
    jid = add_sleep_job(db, steps=30, seconds=3, marker=str(marker))
    first = start_supervisor_process(settings)
    pid = wait_for(lambda: job(db, jid).pid, 60, "worker pid")
    wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
    os.kill(first.pid, 9)
    first.wait()
    wait_for(lambda: not _alive(pid), 10, "orphan to exit")
    with SupervisorInThread(settings, name="second"):
        wait_for(lambda: _state(db, jid) == "succeeded", 60, "re-run")
    assert len(marker.read_text().splitlines()) == 2


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (not yet reaped by init) counts as gone
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_crashing_job_retried_then_failed(proc_backend):
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=1, seconds=0, crash=9, max_attempts=2)
    with SupervisorInThread(settings):
        wait_for(lambda: _state(db, jid) == "failed", 60, "failure")
    row = job(db, jid)
    assert row.attempts == 2
    assert "exited with code 9" in row.error and "gave up after 2" in row.error


def test_bad_input_fails_once_without_retry(proc_backend):
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=1, seconds=0, fail="no such thing")
    with SupervisorInThread(settings):
        wait_for(lambda: _state(db, jid) == "failed", 30, "failure")
    row = job(db, jid)
    assert row.attempts == 1 and row.error == "ValueError: no such thing"


def test_fair_share_priority_and_per_owner_cap(backend):
    _settings, db = backend
    a1 = add_sleep_job(db, owner="alice")
    a2 = add_sleep_job(db, owner="alice")
    b1 = add_sleep_job(db, owner="bob")
    hi = add_sleep_job(db, owner="carol", priority=5)
    order = []
    while (c := jobqueue.claim(db, "s", 30, running_cap=1, device="cpu")) is not None:
        order.append(c.job_id)
    assert order == [hi, a1, b1]  # alice's second waits for her first
    assert _state(db, a2) == "queued"


def test_expired_lease_is_reaped(backend):
    _settings, db = backend
    jid = add_sleep_job(db)
    claim = jobqueue.claim(db, "gone", lease_seconds=-1, running_cap=9, device="cpu")
    assert claim.job_id == jid
    assert jobqueue.reap(db)["requeued"] == 1
    row = job(db, jid)
    assert row.state == "queued" and "lease expired" in row.error
    # the old holder can no longer write anything
    assert not jobqueue.write_progress(db, jid, claim.token, {"step": 1})
    assert not jobqueue.finish(db, jid, claim.token, "succeeded")


def test_spectra_deduplicated_and_fit_waits_for_them(backend):
    settings, db = backend
    results = []

    def ask():
        results.append(jobqueue.ensure_spectra(db, "alice", "m1", "meshhash", {"k": 8}, "cfg", 3))

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({r.id for r in results}) == 1
    with db.read() as s:
        spectra_jobs = s.query(JobRow).filter(JobRow.task == "spectra").all()
        assert len(spectra_jobs) == 1
    spectra_id = results[0].id
    with db.write() as s:
        fit = jobqueue.enqueue(s, "alice", "fit_uv", spectra_id=spectra_id, priority=10).id
    first = jobqueue.claim(db, "s", 30, 9, "cpu")
    assert first.task == "spectra"  # the fit has higher priority but must wait
    assert jobqueue.claim(db, "s", 30, 9, "cpu") is None

    def ready(s, _job):
        s.get(SpectraRow, spectra_id).state = "ready"

    assert jobqueue.finish(db, first.job_id, first.token, "succeeded", on_success=ready)
    assert jobqueue.claim(db, "s", 30, 9, "cpu").job_id == fit


def test_failed_spectra_fail_their_fits(backend):
    _settings, db = backend
    row = jobqueue.ensure_spectra(db, "alice", "m1", "h", {}, "c", 1)
    with db.write() as s:
        fit = jobqueue.enqueue(s, "alice", "fit_uv", spectra_id=row.id).id
    claim = jobqueue.claim(db, "s", 30, 9, "cpu")
    jobqueue.finish(db, claim.job_id, claim.token, "failed", error="MeshError: bad")
    with db.read() as s:
        assert s.get(SpectraRow, row.id).state == "failed"
    jobqueue.reap(db)
    assert "spectra failed: MeshError: bad" in job(db, fit).error
    # asking again re-queues the spectra
    again = jobqueue.ensure_spectra(db, "alice", "m1", "h", {}, "c", 1)
    assert again.id == row.id and again.state == "queued" and again.job_id != claim.job_id


def test_progress_writes_are_throttled(backend, monkeypatch):
    from hktex_server.jobs import worker_main

    _settings, db = backend
    jid = add_sleep_job(db)
    claim = jobqueue.claim(db, "s", 30, 9, "cpu")
    writes = []
    real = jobqueue.write_progress
    monkeypatch.setattr(jobqueue, "write_progress", lambda *a: writes.append(a) or real(*a))
    progress = worker_main.DbProgress(db, jid, claim.token)
    for step in range(1, 500):
        progress.update(step, 1000, loss=float("nan"), kernels=step, psnr=30.0, stage="grid")
    progress.flush()
    assert 1 <= len(writes) <= 3
    stored = job(db, jid).progress
    assert stored["step"] == 499 and stored["loss"] is None and stored["metrics"] == {"psnr": 30.0}
    assert stored["stage"] == "grid" and stored["kernel_count"] == 499
    assert not progress.should_stop()
    jobqueue.request_cancel(db, "local", jid)
    time.sleep(progress.poll_interval)
    assert progress.should_stop() and not progress.lost


def test_slots_pinned_to_devices(proc_backend, tmp_path):
    settings, db = proc_backend
    marker = tmp_path / "runs.txt"
    ids = [add_sleep_job(db, steps=5, seconds=1.0, marker=str(marker)) for _ in range(2)]
    with SupervisorInThread(settings.model_copy(update={"workers": 2, "devices": "3,5"})):
        wait_for(lambda: all(_state(db, j) == "succeeded" for j in ids), 60, "both jobs")
    seen = {line.split()[0]: line.split()[2] for line in marker.read_text().splitlines()}
    assert sorted(seen.values()) == ["3", "5"]  # one job per device, concurrently
    assert all(job(db, j).device == seen[j] for j in ids)


def test_supervisor_shutdown_hands_jobs_back_without_using_an_attempt(proc_backend):
    settings, db = proc_backend
    jid = add_sleep_job(db, steps=100, seconds=30, max_attempts=1)
    with SupervisorInThread(settings):
        wait_for(lambda: job(db, jid).pid, 30, "worker pid")
    row = job(db, jid)
    assert row.state == "queued" and row.attempts == 0 and "shut down" in row.error


def test_migrations_match_the_models(backend):
    """A model change without its Alembic migration fails here (autogenerate finds a diff)."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext
    from hktex_server.storage.db import Base

    _settings, db = backend
    db.migrate()  # idempotent: a second start finds the schema at head
    with db.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []


def test_lost_lease_stops_the_worker(proc_backend):
    """If the lease moves on (reaped, re-claimed elsewhere), this run must stop publishing."""
    from sqlalchemy import update

    settings, db = proc_backend
    jid = add_sleep_job(db, steps=100, seconds=30)
    with SupervisorInThread(settings) as sup:
        pid = wait_for(lambda: job(db, jid).pid, 30, "worker pid")
        wait_for(lambda: job(db, jid).progress["step"] > 0, 30, "progress")
        with db.write() as s:
            s.execute(update(JobRow).where(JobRow.id == jid).values(lease_token="someone-else"))
        wait_for(lambda: not _alive(pid), 30, "the worker to stop")
        wait_for(lambda: jid not in sup.sup.children, 30, "the supervisor to forget it")
    row = job(db, jid)
    assert row.state == "running" and row.lease_token == "someone-else"  # untouched


def test_queue_depth_counts_queued_and_running_jobs(backend):
    """queue_depth against states set by hand: cancelling counts as running, final states and
    cancelled-while-queued jobs count nowhere."""
    _settings, db = backend
    assert jobqueue.queue_depth(db) == {"queued": 0, "running": 0}
    ids = [add_sleep_job(db, "alice") for _ in range(5)]
    assert jobqueue.queue_depth(db) == {"queued": 5, "running": 0}
    first = jobqueue.claim(db, "s", 30, 9, "cpu")
    second = jobqueue.claim(db, "s", 30, 9, "cpu")
    assert jobqueue.queue_depth(db) == {"queued": 3, "running": 2}
    jobqueue.request_cancel(db, "alice", first.job_id)  # running -> cancelling
    assert _state(db, first.job_id) == "cancelling"
    assert jobqueue.queue_depth(db) == {"queued": 3, "running": 2}
    jobqueue.finish(db, second.job_id, second.token, "succeeded")
    queued = [i for i in ids if _state(db, i) == "queued"]
    jobqueue.request_cancel(db, "alice", queued[0])  # queued -> cancelled at once
    assert jobqueue.queue_depth(db) == {"queued": 2, "running": 1}
