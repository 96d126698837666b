"""Database rows to API records, and owner-scoped lookups (another owner's id is a 404)."""

from __future__ import annotations

from fastapi import HTTPException
from hktex_server.api import schemas
from hktex_server.storage.db import JobRow, KernelSetRow, MeshRow, SpectraRow, ViewsRow
from sqlalchemy import select
from sqlalchemy.orm import Session


def not_found(what: str, key: str) -> HTTPException:
    return HTTPException(404, detail=f"no {what} {key!r}")


def own(session: Session, model: type, key: str, owner: str, what: str):
    row = session.get(model, key)
    if row is None or row.owner != owner:
        raise not_found(what, key)
    return row


def visible_spectra(session: Session, spectra_id: str, owner: str) -> SpectraRow:
    """Spectra are shared per mesh content; an owner sees those of geometry it uploaded."""
    row = session.get(SpectraRow, spectra_id)
    if row is not None:
        mine = session.execute(
            select(MeshRow.id)
            .where(MeshRow.owner == owner, MeshRow.mesh_hash == row.mesh_hash)
            .limit(1)
        ).first()
        if mine is not None:
            return row
    raise not_found("spectra", spectra_id)


def mesh_record(row: MeshRow) -> schemas.MeshRecord:
    return schemas.MeshRecord(
        id=row.id,
        name=row.name,
        n_vertices=row.n_vertices,
        n_faces=row.n_faces,
        has_texture=row.has_texture,
        content_hash=row.mesh_hash,
        bytes=row.bytes,
        checks=row.checks,
        created_at=row.created_at,
    )


def spectra_record(row: SpectraRow) -> schemas.SpectraRecord:
    return schemas.SpectraRecord(
        id=row.id,
        mesh_hash=row.mesh_hash,
        config=row.config,
        config_hash=row.config_hash,
        state=row.state,
        job_id=row.job_id,
        error=row.error,
        summary=row.summary,
        created_at=row.created_at,
        updated_at=row.updated_at,
    )


def job_record(row: JobRow) -> schemas.JobRecord:
    progress = dict(row.progress or {})
    progress["metrics"] = {
        k: v for k, v in (progress.get("metrics") or {}).items() if isinstance(v, int | float)
    }
    return schemas.JobRecord(
        id=row.id,
        task=row.task,
        state=row.state,
        mesh_id=row.mesh_id,
        spectra_id=row.spectra_id,
        views_id=row.views_id,
        priority=row.priority,
        attempts=row.attempts,
        max_attempts=row.max_attempts,
        cancel_requested=row.cancel_requested,
        device=row.device,
        progress=schemas.JobProgress(**progress),
        error=row.error,
        result=schemas.JobResult(**(row.result or {})),
        params=row.params or {},
        created_at=row.created_at,
        started_at=row.started_at,
        finished_at=row.finished_at,
    )


def kernelset_record(row: KernelSetRow, loss_curve: bool = True) -> schemas.KernelSetRecord:
    """The API's view of a row. Lists pass ``loss_curve=False``: the curve (up to 200 pairs,
    ~5 KB) is for one set's page, and a dashboard polls its list every few seconds."""
    metrics = dict(row.metrics or {})
    if not loss_curve:
        metrics.pop("loss_curve", None)
    return schemas.KernelSetRecord(
        id=row.id,
        job_id=row.job_id,
        mesh_id=row.mesh_id,
        spectra_id=row.spectra_id,
        n_kernels=row.n_kernels,
        bytes=row.bytes,
        metrics=metrics,
        manifest=row.manifest or {},
        created_at=row.created_at,
    )


def views_record(row: ViewsRow) -> schemas.ViewsRecord:
    return schemas.ViewsRecord(
        id=row.id, n_files=row.n_files, bytes=row.bytes, created_at=row.created_at
    )
