"""Routes: fitting jobs (submit, list, read, cancel) and their progress as Server-Sent Events."""

from __future__ import annotations

import asyncio
import json
import time

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from hktex_server.api import schemas
from hktex_server.api.auth import current_owner
from hktex_server.api.meshes import ERRORS, request_spectra, spectral_config
from hktex_server.api.records import job_record, not_found, own
from hktex_server.jobs import queue as jobqueue
from hktex_server.state import ServiceState, service
from hktex_server.storage.db import TERMINAL_STATES, JobRow, MeshRow, ViewsRow
from sqlalchemy import select

router = APIRouter(prefix="/v1", tags=["jobs"])

SSE_POLL_SECONDS = 0.5
# API fit fields that are arguments of the fit function, not members of FitParams
EXTRA_FIT_FIELDS = ("eval_points",)
SSE_KEEPALIVE_SECONDS = 15.0


@router.post(
    "/jobs",
    status_code=202,
    response_model=schemas.JobRecord,
    responses={429: {"description": "too many active jobs for this owner"}, **ERRORS},
)
def create_job(
    body: schemas.JobCreate,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> schemas.JobRecord:
    """Queue a fit. Its spectra are requested too (shared and deduplicated); the fit becomes
    claimable once they are ready."""
    config = spectral_config(body.spectra)
    with svc.db.read() as s:
        mesh = own(s, MeshRow, body.mesh_id, owner, "mesh")
        if body.views_id is not None:
            own(s, ViewsRow, body.views_id, owner, "views dataset")
        if jobqueue.count_active(s, owner) >= svc.settings.max_jobs_per_owner:
            raise HTTPException(
                429, detail=f"at most {svc.settings.max_jobs_per_owner} active jobs per owner"
            )
    if body.task == "fit_uv" and not mesh.has_texture:
        raise HTTPException(
            422, detail="fit_uv needs a mesh uploaded with a texture (or one embedding it)"
        )
    params = body.params.model_dump(exclude_none=True)
    _check_params(params)
    spectra = request_spectra(svc, owner, mesh, config, body.priority)
    with svc.db.write(lock=True) as s:
        own(s, MeshRow, mesh.id, owner, "mesh")  # deleted meanwhile? (deletes take this lock)
        if jobqueue.count_active(s, owner) >= svc.settings.max_jobs_per_owner:
            raise HTTPException(
                429, detail=f"at most {svc.settings.max_jobs_per_owner} active jobs per owner"
            )
        job = jobqueue.enqueue(
            s,
            owner,
            body.task,
            params={"params": params, "spectra": config.to_dict()},
            mesh_id=mesh.id,
            spectra_id=spectra.id,
            views_id=body.views_id,
            priority=body.priority,
            max_attempts=svc.settings.max_attempts,
        )
        return job_record(job)


def _check_params(params: dict) -> None:
    from hktex_engine.config import fit_params_from

    try:
        fp = fit_params_from({k: v for k, v in params.items() if k not in EXTRA_FIT_FIELDS})
    except (TypeError, ValueError) as exc:
        raise HTTPException(422, detail=f"invalid fit params: {exc}") from None
    if fp.max_kernels is not None and fp.max_kernels < fp.kernels:
        raise HTTPException(422, detail="max_kernels must be >= kernels")


@router.get("/jobs", response_model=schemas.JobList, responses=ERRORS)
def list_jobs(
    state: schemas.JobState | None = Query(None),
    limit: int = Query(200, ge=1, le=1000),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> schemas.JobList:
    q = select(JobRow).where(JobRow.owner == owner)
    if state is not None:
        q = q.where(JobRow.state == state)
    q = q.order_by(JobRow.created_at.desc()).limit(limit)
    with svc.db.read() as s:
        return schemas.JobList(items=[job_record(r) for r in s.execute(q).scalars()])


@router.get("/jobs/{job_id}", response_model=schemas.JobRecord, responses=ERRORS)
def get_job(job_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)):
    with svc.db.read() as s:
        return job_record(own(s, JobRow, job_id, owner, "job"))


@router.post(
    "/jobs/{job_id}/cancel", response_model=schemas.JobRecord, status_code=202, responses=ERRORS
)
def cancel_job(
    job_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    """Queued: cancelled at once. Running: ``cancelling`` until the worker stops (cooperative
    stop, then SIGTERM, then SIGKILL). Finished: unchanged."""
    job = jobqueue.request_cancel(svc.db, owner, job_id)
    if job is None:
        raise not_found("job", job_id)
    return job_record(job)


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/event-stream": {}}, "description": "progress events"},
        **ERRORS,
    },
)
async def job_events(
    job_id: str,
    request: Request,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
):
    """``event: progress`` with the job record whenever it changes; ``event: end`` with the
    final record, then the stream closes. Comment lines keep idle connections alive."""

    def load() -> schemas.JobRecord:
        with svc.db.read() as s:
            return job_record(own(s, JobRow, job_id, owner, "job"))

    first = await run_in_threadpool(load)  # 404 before the stream starts

    async def stream():
        record, last_key, seq = first, None, 0
        last_sent = time.monotonic()
        while True:
            key = (
                record.state,
                record.progress.updated_at,
                record.cancel_requested,
                record.attempts,
            )
            if key != last_key:
                seq += 1
                last_key, last_sent = key, time.monotonic()
                final = record.state in TERMINAL_STATES
                yield _event("end" if final else "progress", seq, record)
                if final:
                    return
            elif time.monotonic() - last_sent > SSE_KEEPALIVE_SECONDS:
                last_sent = time.monotonic()
                yield ": keep-alive\n\n"
            await asyncio.sleep(SSE_POLL_SECONDS)
            if await request.is_disconnected():
                return
            try:
                record = await run_in_threadpool(load)
            except HTTPException:  # deleted meanwhile (with its mesh): nothing more to say
                return

    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(stream(), media_type="text/event-stream", headers=headers)


def _event(name: str, seq: int, record: schemas.JobRecord) -> str:
    data = json.dumps(record.model_dump(mode="json"), separators=(",", ":"))
    return f"event: {name}\nid: {seq}\ndata: {data}\n\n"
