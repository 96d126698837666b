"""Routes: kernel sets (metadata, file download), batched albedo queries, PNG previews.

Query bodies, both ways (docs/service.md):

- JSON ``{"face_ids": [...], "barycentrics": [[b0, b1, b2], ...]}`` or ``{"points": [[x, y, z]]}``
- ``application/x-npy``: one NPY array; ``?kind=faces`` (default) a ``(P, 4)`` float64 array
  of rows ``[face_id, b0, b1, b2]``, ``?kind=points`` a ``(P, 3)`` array of points in the mesh
  file's units (answered at the closest surface point).

The answer is ``(P, 3)`` colours: NPY float32 when ``Accept`` names ``application/x-npy``,
JSON otherwise. One array per body keeps the binary path to a single ``np.load`` with
``allow_pickle=False`` (no structured dtypes, no pickles from strangers).
"""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from hktex_server.api import schemas
from hktex_server.api.auth import current_owner
from hktex_server.api.meshes import ERRORS
from hktex_server.api.records import kernelset_record, own
from hktex_server.api.uploads import read_body
from hktex_server.state import ServiceState, service
from hktex_server.storage.db import KernelSetRow, SpectraRow
from pydantic import ValidationError
from sqlalchemy import select

router = APIRouter(prefix="/v1", tags=["kernelsets"])

NPY = "application/x-npy"
JSON_BYTES_PER_POINT = 96  # generous: "[0.123456789, ...]" per point plus an id


def _query_body_doc() -> dict:
    schema = schemas.AlbedoRequest.model_json_schema()
    return {
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": schema},
                NPY: {
                    "schema": {"type": "string", "format": "binary"},
                    "description": "(P, 4) float64 [face_id, b0, b1, b2] (kind=faces) or (P, 3) points (kind=points)",
                },
            },
        }
    }


@router.get("/kernelsets/{kernelset_id}", response_model=schemas.KernelSetRecord, responses=ERRORS)
def get_kernelset(
    kernelset_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    with svc.db.read() as s:
        return kernelset_record(own(s, KernelSetRow, kernelset_id, owner, "kernel set"))


@router.delete("/kernelsets/{kernelset_id}", status_code=204, responses=ERRORS)
def delete_kernelset(
    kernelset_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
) -> Response:
    """Delete a kernel set; its ``.hkt`` file goes unless another record (any owner) holds the
    same bytes (files are content-addressed). The job that made it keeps its record."""
    with svc.db.write(lock=True) as s:
        row = own(s, KernelSetRow, kernelset_id, owner, "kernel set")
        s.delete(row)
        s.flush()
        shared = s.execute(
            select(KernelSetRow.id).where(KernelSetRow.path == row.path).limit(1)
        ).first()
    if shared is None:
        svc.store.delete(row.path)
    return Response(status_code=204)


@router.get(
    "/kernelsets/{kernelset_id}/file",
    response_class=FileResponse,
    responses={200: {"content": {"application/octet-stream": {}}}, **ERRORS},
)
def get_kernelset_file(
    kernelset_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    with svc.db.read() as s:
        row = own(s, KernelSetRow, kernelset_id, owner, "kernel set")
    path = svc.store.abs(row.path)
    if not path.is_file():  # deleted between the lookup and now: not a server error
        raise HTTPException(404, detail=f"kernel set {kernelset_id!r} has no file any more")
    return FileResponse(
        path,
        media_type="application/octet-stream",
        filename=f"{kernelset_id}.hkt",
    )


def _locate(svc: ServiceState, owner: str, kernelset_id: str) -> dict[str, str]:
    """Where a compute worker finds the kernel set (404 for another owner's, 409 if its
    spectra are gone); the worker loads and keeps it warm itself."""
    with svc.db.read() as s:
        row = own(s, KernelSetRow, kernelset_id, owner, "kernel set")
        spectra = s.get(SpectraRow, row.spectra_id)
    if spectra is None or spectra.state != "ready" or not spectra.path:
        raise HTTPException(409, detail="the spectra of this kernel set are not available")
    return {
        "kernelset_id": kernelset_id,
        "spectra_path": str(svc.store.abs(spectra.path)),
        "hkt_path": str(svc.store.abs(row.path)),
        "mesh_hash": spectra.mesh_hash,
    }


@router.post(
    "/kernelsets/{kernelset_id}/albedo",
    response_model=schemas.AlbedoResponse,
    responses={
        200: {"content": {NPY: {}}},
        409: {"description": "spectra unavailable"},
        429: {"description": "too many of your requests are waiting"},
        503: {"description": "over its time budget, or shutting down"},
        **ERRORS,
    },
    openapi_extra=_query_body_doc(),
)
async def albedo(
    kernelset_id: str,
    request: Request,
    kind: Literal["faces", "points"] = Query("faces", description="NPY bodies only"),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
):
    """Colours at surface locations or points, in chunks on a warm query state in a compute
    worker (parallel across workers, fair across owners, bounded in time and memory)."""
    limit_points = svc.settings.max_batch_points
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == NPY:
        body = await read_body(request, limit_points * 4 * 8 + 4096)
        kind, face_ids, bary, points = await run_in_threadpool(_parse_npy, body, kind)
    elif ctype == "application/json":
        limit_points = min(limit_points, svc.settings.max_json_batch_points)
        body = await read_body(request, limit_points * JSON_BYTES_PER_POINT + 4096)
        # parsing 100k JSON points takes ~0.1 s: off the event loop, so others are answered
        kind, face_ids, bary, points = await run_in_threadpool(_parse_json, body)
    else:
        raise HTTPException(415, detail=f"send application/json or {NPY}, not {ctype or 'nothing'}")
    count = len(points) if kind == "points" else len(face_ids)
    if count > limit_points:
        raise HTTPException(
            413, detail=f"{count} points in one {ctype} batch; the limit is {limit_points}"
        )
    ks = await run_in_threadpool(_locate, svc, owner, kernelset_id)
    npy = NPY in request.headers.get("accept", "")
    payload = {
        "ks": ks,
        "kind": kind,
        "face_ids": face_ids,
        "bary": bary,
        "points": points,
        "chunk": svc.settings.query_chunk_points,
        "npy": npy,
    }
    body = await svc.compute.run(request, owner, "albedo", payload)
    return Response(body, media_type=NPY if npy else "application/json")


def _parse_npy(body: bytes, kind: str):
    try:
        arr = np.load(io.BytesIO(body), allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError/EOFError/OSError on garbage
        raise HTTPException(422, detail=f"body is not one NPY array: {exc}") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "iuf":
        raise HTTPException(
            422, detail="the NPY array must be numeric (no structured or object dtype)"
        )
    width = 3 if kind == "points" else 4
    if arr.ndim != 2 or arr.shape[1] != width:
        what = "(P, 3) points" if kind == "points" else "(P, 4) rows [face_id, b0, b1, b2]"
        raise HTTPException(422, detail=f"kind={kind} needs a {what} array, got shape {arr.shape}")
    arr = arr.astype(np.float64)
    _check_finite(arr)
    if kind == "points":
        return kind, None, None, arr
    return kind, _face_ids(arr[:, 0]), arr[:, 1:], None


def _parse_json(body: bytes):
    try:
        req = schemas.AlbedoRequest.model_validate_json(body)
    except ValidationError as exc:
        errors = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()[:5])
        raise HTTPException(422, detail=f"invalid query: {errors}") from None
    if req.points is not None:
        points = _rows(req.points, 3, "points")
        return "points", None, None, points
    bary = _rows(req.barycentrics, 3, "barycentrics")
    face_ids = np.asarray(req.face_ids, dtype=np.int64)
    if len(face_ids) != len(bary):
        raise HTTPException(422, detail=f"{len(face_ids)} face_ids but {len(bary)} barycentrics")
    return "faces", face_ids, bary, None


def _rows(values: list[list[float]], width: int, what: str) -> np.ndarray:
    if any(len(v) != width for v in values):
        raise HTTPException(422, detail=f"every row of {what} needs {width} numbers")
    arr = np.asarray(values, dtype=np.float64).reshape(-1, width)
    _check_finite(arr)
    return arr


def _check_finite(arr: np.ndarray) -> None:
    if not np.isfinite(arr).all():
        raise HTTPException(422, detail="the query holds NaN or infinite values")
    if arr.size and np.abs(arr).max() > schemas.MAX_COORDINATE:
        raise HTTPException(
            422, detail=f"the query holds values beyond +-{schemas.MAX_COORDINATE:g}"
        )


def _face_ids(col: np.ndarray) -> np.ndarray:
    if np.any(col != np.round(col)):
        raise HTTPException(422, detail="face ids must be whole numbers")
    if len(col) and (col.min() < 0 or col.max() > schemas.MAX_FACE_ID):
        raise HTTPException(422, detail=f"face ids out of range 0..{schemas.MAX_FACE_ID}")
    return col.astype(np.int64)


@router.get(
    "/kernelsets/{kernelset_id}/render",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}}},
        429: {"description": "too many of your requests are waiting"},
        503: {"description": "renderer unavailable, over its time budget, or shutting down"},
        **ERRORS,
    },
)
async def render(
    request: Request,
    kernelset_id: str,
    width: int = Query(256, ge=16, le=2048),
    height: int = Query(256, ge=16, le=2048),
    view: str = Query(
        "30,20", max_length=64, description="'AZIMUTH,ELEVATION' degrees, or a view index"
    ),
    spp: int = Query(16, ge=1, le=256),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> Response:
    """A PNG preview (Mitsuba) rendered in a compute worker under the request budgets; the
    render stops when the client disconnects."""
    samples = width * height * spp
    if samples > svc.settings.max_render_samples:
        raise HTTPException(
            422,
            detail=f"width x height x spp = {samples} exceeds the limit "
            f"{svc.settings.max_render_samples}; ask for fewer pixels or samples",
        )
    ks = await run_in_threadpool(_locate, svc, owner, kernelset_id)
    payload = {"ks": ks, "width": width, "height": height, "view": view, "spp": spp}
    png = await svc.compute.run(request, owner, "render", payload)
    return Response(png, media_type="image/png")
