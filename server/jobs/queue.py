"""The jobs table as a queue: enqueue, claim with a lease, heartbeat, finish, cancel, reap.

Every transition is one short transaction. A claim is a read-decide-write sequence, so it
runs under ``Database.write(lock=True)`` (SQLite ``BEGIN IMMEDIATE``; PostgreSQL rows taken
``FOR UPDATE SKIP LOCKED`` inside an advisory-locked transaction, so the per-owner cap is
exact too). A job's lease carries a random token; only the holder of the current token may
write progress or a final state, so a worker that lost its lease (its supervisor died, the
reaper re-queued the job) can never overwrite the run that replaced it.

Spectra are jobs of their own, one row per (mesh content hash, config hash) made unique by
the database: two fits of one mesh, or two concurrent requests, share one spectra job; a fit
job is claimable only once its spectra row is ``ready``.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from typing import Any

from hktex_server.storage.db import (
    ACTIVE_STATES,
    TERMINAL_STATES,
    Database,
    JobRow,
    SpectraRow,
    new_id,
    now,
)
from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

RUNNING_STATES = ("running", "cancelling")
# tasks that need no ready spectra before they can run
SELF_CONTAINED_TASKS = ("spectra", "sleep")


@dataclass(frozen=True)
class Claim:
    job_id: str
    token: str
    task: str
    device: str | None


def empty_progress() -> dict[str, Any]:
    return {"step": 0, "total": 0, "loss": None, "kernel_count": None, "metrics": {}}


def enqueue(
    session: Session,
    owner: str,
    task: str,
    *,
    params: dict[str, Any] | None = None,
    mesh_id: str | None = None,
    spectra_id: str | None = None,
    views_id: str | None = None,
    priority: int = 0,
    max_attempts: int = 3,
) -> JobRow:
    t = now()
    job = JobRow(
        id=new_id("job"),
        owner=owner,
        task=task,
        state="queued",
        priority=priority,
        mesh_id=mesh_id,
        spectra_id=spectra_id,
        views_id=views_id,
        params=params or {},
        attempts=0,
        max_attempts=max_attempts,
        cancel_requested=False,
        progress=empty_progress(),
        result={},
        created_at=t,
        updated_at=t,
    )
    session.add(job)
    session.flush()
    return job


def count_active(session: Session, owner: str) -> int:
    q = select(func.count()).select_from(JobRow)
    q = q.where(JobRow.owner == owner, JobRow.state.in_(ACTIVE_STATES))
    return int(session.execute(q).scalar_one())


def ensure_spectra(
    db: Database,
    owner: str,
    mesh_id: str,
    mesh_hash: str,
    config: dict[str, Any],
    config_hash: str,
    max_attempts: int,
    priority: int = 0,
) -> SpectraRow:
    """Get-or-create the spectra row of (mesh, config); queue a spectra job unless one is
    ready, queued or running. Safe against concurrent callers in other processes: the unique
    key decides the row, the locked transaction decides the job."""
    for _ in range(3):
        try:
            with db.write(lock=True) as s:
                t = now()
                row = spectra_row(s, mesh_hash, config_hash, config, t)
                if row.state in ("missing", "failed"):
                    job = enqueue(
                        s,
                        owner,
                        "spectra",
                        params={"config": config},
                        mesh_id=mesh_id,
                        spectra_id=row.id,
                        priority=priority,
                        max_attempts=max_attempts,
                    )
                    row.state, row.job_id, row.error, row.updated_at = "queued", job.id, None, t
                s.flush()
                return row
        except IntegrityError:  # another process inserted the same key first: read theirs
            continue
    raise RuntimeError("could not create the spectra record")


def spectra_row(
    s: Session, mesh_hash: str, config_hash: str, config: dict[str, Any], t: float
) -> SpectraRow:
    """The spectra row of (mesh, config), added in state ``missing`` when there is none yet.
    Concurrent creators meet at the unique key: the loser's flush raises IntegrityError and it
    should retry and read the winner's row."""
    row = s.execute(
        select(SpectraRow).where(
            SpectraRow.mesh_hash == mesh_hash, SpectraRow.config_hash == config_hash
        )
    ).scalar_one_or_none()
    if row is None:
        row = SpectraRow(
            id=new_id("spc"),
            mesh_hash=mesh_hash,
            config_hash=config_hash,
            config=config,
            state="missing",
            created_at=t,
            updated_at=t,
        )
        s.add(row)
    return row


def claim(
    db: Database,
    supervisor: str,
    lease_seconds: float,
    running_cap: int,
    device: str | None,
) -> Claim | None:
    """Take the best claimable job (priority, then age), respecting the per-owner cap."""
    with db.write(lock=True) as s:
        running = dict(
            s.execute(
                select(JobRow.owner, func.count())
                .where(JobRow.state.in_(RUNNING_STATES))
                .group_by(JobRow.owner)
            ).all()
        )
        q = (
            select(JobRow)
            .outerjoin(SpectraRow, JobRow.spectra_id == SpectraRow.id)
            .where(JobRow.state == "queued")
            .where(or_(JobRow.task.in_(SELF_CONTAINED_TASKS), SpectraRow.state == "ready"))
            .order_by(JobRow.priority.desc(), JobRow.created_at, JobRow.id)
            .limit(64)
            .with_for_update(skip_locked=True, of=JobRow)
        )
        for job in s.execute(q).scalars():
            if running.get(job.owner, 0) >= running_cap:
                continue
            t = now()
            token = secrets.token_hex(16)
            job.state = "running"
            job.attempts += 1
            job.lease_owner = supervisor
            job.lease_token = token
            job.lease_expires_at = t + lease_seconds
            job.device = device
            job.started_at = job.started_at or t
            job.updated_at = t
            _sync_spectra(s, job)
            return Claim(job.id, token, job.task, device)
    return None


def set_pid(db: Database, job_id: str, token: str, pid: int) -> None:
    with db.write() as s:
        s.execute(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.lease_token == token)
            .values(pid=pid, updated_at=now())
        )


def heartbeat(db: Database, held: dict[str, str], lease_seconds: float) -> set[str]:
    """Renew the leases in ``held`` ({job_id: token}); returns the ids no longer ours."""
    if not held:
        return set()
    lost = set()
    with db.write() as s:
        t = now()
        for job_id, token in held.items():
            res = s.execute(
                update(JobRow)
                .where(
                    JobRow.id == job_id,
                    JobRow.lease_token == token,
                    JobRow.state.in_(RUNNING_STATES),
                )
                .values(lease_expires_at=t + lease_seconds)
            )
            if res.rowcount == 0:
                lost.add(job_id)
    return lost


def cancel_flags(db: Database, job_ids: list[str]) -> set[str]:
    """Which of these jobs their owners asked to cancel."""
    if not job_ids:
        return set()
    with db.read() as s:
        q = select(JobRow.id).where(JobRow.id.in_(job_ids), JobRow.cancel_requested.is_(True))
        return set(s.execute(q).scalars())


def request_cancel(db: Database, owner: str, job_id: str) -> JobRow | None:
    """Queued: cancelled at once. Running: flagged ``cancelling`` (the supervisor stops it).
    Finished: unchanged. ``None`` when the owner has no such job."""
    with db.write(lock=True) as s:
        job = s.get(JobRow, job_id)
        if job is None or job.owner != owner:
            return None
        t = now()
        if job.state == "queued":
            job.state, job.cancel_requested, job.finished_at = "cancelled", True, t
            job.error = "cancelled by request"
        elif job.state == "running":
            job.state, job.cancel_requested = "cancelling", True
        job.updated_at = t
        _sync_spectra(s, job)
        return job


def write_progress(db: Database, job_id: str, token: str, progress: dict[str, Any]) -> bool:
    """Store progress; False when the lease is no longer this worker's."""
    with db.write() as s:
        res = s.execute(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.lease_token == token)
            .values(progress=progress, updated_at=now())
        )
        return res.rowcount == 1


def lease_status(db: Database, job_id: str, token: str) -> str:
    """ "ok"; "cancel" when the owner asked to stop; "lost" when the lease moved on (the job
    is someone else's now, or gone)."""
    with db.read() as s:
        row = s.execute(
            select(JobRow.cancel_requested, JobRow.lease_token).where(JobRow.id == job_id)
        ).one_or_none()
    if row is None or row[1] != token:
        return "lost"
    return "cancel" if row[0] else "ok"


def finish(
    db: Database,
    job_id: str,
    token: str,
    state: str,
    *,
    error: str | None = None,
    result: dict[str, Any] | None = None,
    on_success: Any = None,
) -> bool:
    """Final state, written only by the lease holder. ``on_success(session, job)`` runs in
    the same transaction (records the spectra or kernel set), so a result is published
    exactly when its job says ``succeeded``."""
    assert state in TERMINAL_STATES
    with db.write(lock=True) as s:
        job = s.get(JobRow, job_id)
        if job is None or job.lease_token != token or job.state not in RUNNING_STATES:
            return False
        if state == "succeeded" and on_success is not None:
            on_success(s, job)
        t = now()
        job.state, job.error, job.finished_at, job.updated_at = state, error, t, t
        if result is not None:
            job.result = result
        job.lease_token = job.lease_expires_at = job.pid = None
        _sync_spectra(s, job)
        return True


def release(db: Database, job_id: str, token: str, reason: str, refund: bool = False) -> str | None:
    """A worker process ended without a final state (crash, kill): cancel, retry or fail.
    ``refund`` gives the attempt back (an orderly supervisor shutdown is not the job's
    fault). Returns the new state, or None when the job was not ours any more."""
    with db.write(lock=True) as s:
        job = s.get(JobRow, job_id)
        if job is None or job.lease_token != token or job.state not in RUNNING_STATES:
            return None
        if refund:
            job.attempts = max(0, job.attempts - 1)
        return _requeue_or_fail(s, job, reason)


def reap(db: Database) -> dict[str, int]:
    """Recover jobs whose lease expired (their supervisor died) and fail jobs whose spectra
    failed. Any supervisor may run this; it is idempotent."""
    counts = {
        "requeued": 0,
        "failed": 0,
        "cancelled": 0,
        "dependents_failed": 0,
        "spectra_requeued": 0,
    }
    with db.write(lock=True) as s:
        t = now()
        expired = (
            s.execute(
                select(JobRow).where(
                    JobRow.state.in_(RUNNING_STATES),
                    or_(JobRow.lease_expires_at.is_(None), JobRow.lease_expires_at < t),
                )
            )
            .scalars()
            .all()
        )
        for job in expired:
            state = _requeue_or_fail(s, job, "lease expired (worker or supervisor lost)")
            counts["requeued" if state == "queued" else state] += 1
        orphans = s.execute(
            select(JobRow, SpectraRow)
            .join(SpectraRow, JobRow.spectra_id == SpectraRow.id)
            .where(JobRow.state == "queued", JobRow.task.not_in(SELF_CONTAINED_TASKS))
            .where(SpectraRow.state == "failed")
        ).all()
        for job, spectra in orphans:
            if spectra.state != "failed":  # re-queued for an earlier job of this loop
                continue
            canceller = _cancelled_by(s, spectra)
            if canceller is not None and canceller != job.owner:
                # shared spectra: one owner's cancel must not fail another owner's fit
                _requeue_spectra(s, spectra, job)
                counts["spectra_requeued"] += 1
                continue
            job.state, job.finished_at, job.updated_at = "failed", t, t
            job.error = f"spectra failed: {spectra.error or 'unknown error'}"
            counts["dependents_failed"] += 1
    return counts


def _cancelled_by(s: Session, spectra: SpectraRow) -> str | None:
    """The owner who cancelled the spectra's last job, if it ended by a cancel."""
    last = s.get(JobRow, spectra.job_id) if spectra.job_id else None
    return last.owner if last is not None and last.state == "cancelled" else None


def _requeue_spectra(s: Session, spectra: SpectraRow, waiting: JobRow) -> None:
    job = enqueue(
        s,
        waiting.owner,
        "spectra",
        params={"config": spectra.config},
        mesh_id=waiting.mesh_id,
        spectra_id=spectra.id,
        priority=waiting.priority,
        max_attempts=waiting.max_attempts,
    )
    spectra.state, spectra.job_id, spectra.error, spectra.updated_at = "queued", job.id, None, now()


def _requeue_or_fail(s: Session, job: JobRow, reason: str) -> str:
    t = now()
    if job.cancel_requested:
        job.state, job.error = "cancelled", "cancelled by request"
    elif job.attempts >= job.max_attempts:
        job.state = "failed"
        job.error = f"{reason}; gave up after {job.attempts} attempt(s)"
    else:
        job.state, job.error = "queued", f"attempt {job.attempts}: {reason}"
    if job.state != "queued":
        job.finished_at = t
    job.lease_token = job.lease_owner = job.lease_expires_at = job.pid = None
    job.updated_at = t
    _sync_spectra(s, job)
    return job.state


def _sync_spectra(s: Session, job: JobRow) -> None:
    """Keep a spectra row's state in step with the job computing it."""
    if job.task != "spectra" or job.spectra_id is None:
        return
    row = s.get(SpectraRow, job.spectra_id)
    if row is None or row.job_id != job.id:
        return
    mapping = {"queued": "queued", "running": "running", "cancelling": "running"}
    if job.state in mapping:
        row.state = mapping[job.state]
    elif job.state in ("failed", "cancelled"):
        row.state, row.error = "failed", job.error or job.state
    row.updated_at = now()


def queue_depth(db: Database) -> dict[str, int]:
    with db.read() as s:
        rows = dict(
            s.execute(
                select(JobRow.state, func.count())
                .where(JobRow.state.in_(ACTIVE_STATES))
                .group_by(JobRow.state)
            ).all()
        )
    return {
        "queued": int(rows.get("queued", 0)),
        "running": int(rows.get("running", 0) + rows.get("cancelling", 0)),
    }
