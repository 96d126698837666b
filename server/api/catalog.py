"""Routes: the owner's kernel sets and visible spectra as lists (what the dashboard shows).

Until now a kernel set was reachable only through the job that made it and a spectra record
only by id; a person looking at the service wants the list. Owner scoping is the same as
for single records: an owner's own kernel sets, and the spectra of geometry it uploaded.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from hktex_server.api import schemas
from hktex_server.api.auth import current_owner
from hktex_server.api.meshes import ERRORS
from hktex_server.api.records import kernelset_record, spectra_record
from hktex_server.state import ServiceState, service
from hktex_server.storage.db import KernelSetRow, MeshRow, SpectraRow
from pydantic import BaseModel
from sqlalchemy import select

router = APIRouter(prefix="/v1", tags=["catalog"])


class KernelSetList(BaseModel):
    items: list[schemas.KernelSetRecord]


class SpectraList(BaseModel):
    items: list[schemas.SpectraRecord]


@router.get("/kernelsets", response_model=KernelSetList, responses=ERRORS)
def list_kernelsets(
    limit: int = Query(200, ge=1, le=1000),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> KernelSetList:
    """The owner's kernel sets, newest first."""
    q = (
        select(KernelSetRow)
        .where(KernelSetRow.owner == owner)
        .order_by(KernelSetRow.created_at.desc())
        .limit(limit)
    )
    with svc.db.read() as s:
        return KernelSetList(
            items=[kernelset_record(r, loss_curve=False) for r in s.execute(q).scalars()]
        )


@router.get("/spectra", response_model=SpectraList, responses=ERRORS)
def list_spectra(
    limit: int = Query(200, ge=1, le=1000),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> SpectraList:
    """Spectra of the geometry the owner uploaded (shared per mesh content), newest first."""
    mine = select(MeshRow.mesh_hash).where(MeshRow.owner == owner)
    q = (
        select(SpectraRow)
        .where(SpectraRow.mesh_hash.in_(mine))
        .order_by(SpectraRow.created_at.desc())
        .limit(limit)
    )
    with svc.db.read() as s:
        return SpectraList(items=[spectra_record(r) for r in s.execute(q).scalars()])
