"""Routes: meshes (upload, list, read, delete), their spectra, and view datasets.

A mesh upload is validated while the uploader waits (the user learns at once why a mesh is
refused), in a child process with a hard timeout (``validation.py``) so the event loop keeps
serving and a parser stuck on hostile bytes is killed, not left running.
"""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path

from fastapi import APIRouter, Body, Depends, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from hktex_server.api import schemas
from hktex_server.api.auth import current_owner
from hktex_server.api.records import (
    mesh_record,
    not_found,
    own,
    spectra_record,
    views_record,
    visible_spectra,
)
from hktex_server.api.uploads import ArchiveError, extract_zip, receive_files, remove_parts
from hktex_server.jobs import queue as jobqueue
from hktex_server.state import ServiceState, service
from hktex_server.storage.db import (
    ACTIVE_STATES,
    JobRow,
    KernelSetRow,
    MeshRow,
    SpectraRow,
    ViewsRow,
    new_id,
    now,
)
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

router = APIRouter(prefix="/v1", tags=["meshes"])

MESH_SUFFIXES = {".obj", ".ply", ".off", ".glb", ".gltf", ".stl"}
ERRORS = {
    400: {"description": "malformed request body"},
    401: {"description": "missing or invalid bearer token"},
    404: {"description": "no such resource (or another owner's)"},
    413: {"description": "upload larger than the configured limit"},
    415: {"description": "wrong content type"},
    422: {"description": "invalid input, with the reason"},
}


def _multipart(fields: dict[str, str], required: list[str]) -> dict:
    props = {
        name: {"type": "string", "format": "binary", "description": d} for name, d in fields.items()
    }
    schema = {"type": "object", "properties": props, "required": required}
    return {
        "requestBody": {"required": True, "content": {"multipart/form-data": {"schema": schema}}}
    }


@router.post(
    "/meshes",
    status_code=201,
    response_model=schemas.MeshRecord,
    responses={
        200: {"description": "the same content was uploaded before", "model": schemas.MeshRecord},
        **ERRORS,
    },
    openapi_extra=_multipart(
        {"mesh": "OBJ, PLY, OFF, STL, GLB or glTF file", "texture": "albedo image (optional)"},
        ["mesh"],
    ),
)
async def upload_mesh(
    request: Request,
    response: Response,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> schemas.MeshRecord:
    """Upload and validate a mesh (201); the same content again answers 200 with its id."""
    parts = await receive_files(
        request, svc.store, {"mesh", "texture"}, svc.settings.max_upload_bytes
    )
    try:
        if "mesh" not in parts:
            raise HTTPException(422, detail="the multipart body has no 'mesh' file")
        mesh_part, texture_part = parts["mesh"], parts.get("texture")
        suffix = mesh_part.path.suffix
        if suffix and suffix not in MESH_SUFFIXES:
            raise HTTPException(422, detail=f"unsupported mesh format {suffix!r}")
        if mesh_part.size == 0:
            raise HTTPException(422, detail="the mesh file is empty")
        content_key = await run_in_threadpool(_content_key, mesh_part, texture_part, suffix)
        existing = _uploaded_before(svc, MeshRow, owner, content_key)
        if existing is not None:
            response.status_code = 200
            return mesh_record(existing)
        mesh = await _validate(
            svc, mesh_part.path, texture_part.path if texture_part else None, suffix
        )
        row, created = await run_in_threadpool(
            _store_mesh, svc, owner, content_key, mesh, mesh_part, texture_part, suffix
        )
        if not created:
            response.status_code = 200
        return mesh_record(row)
    finally:
        remove_parts(parts)


def _uploaded_before(
    svc: ServiceState, table: type[MeshRow] | type[ViewsRow], owner: str, content_key: str
) -> MeshRow | ViewsRow | None:
    """The owner's earlier upload of the same content (uploads are unique per owner and
    content key), or None."""
    with svc.db.read() as s:
        return s.execute(
            select(table).where(table.owner == owner, table.content_key == content_key)
        ).scalar_one_or_none()


def _insert_upload(svc: ServiceState, row: MeshRow | ViewsRow) -> tuple[MeshRow | ViewsRow, bool]:
    """Insert an upload's row: (row, True); when a concurrent upload of the same content won
    the unique key, (the winner's row, False)."""
    try:
        with svc.db.write() as s:
            s.add(row)
    except IntegrityError:
        winner = _uploaded_before(svc, type(row), row.owner, row.content_key)
        if winner is None:  # the conflict was another key: not a lost race
            raise
        return winner, False
    return row, True


def _content_key(mesh_part, texture_part, suffix: str) -> str:
    """Identity of an upload: its bytes (mesh, texture) and the format its suffix names."""
    key = hashlib.sha256()
    for part in (mesh_part, texture_part):
        key.update(_digest(part.path).encode() if part is not None else b"-")
    key.update(suffix.encode())
    return key.hexdigest()


def _digest(path: Path) -> str:
    from hktex_server.storage.blobs import file_sha256

    return file_sha256(path)


async def _validate(svc: ServiceState, path: Path, texture: Path | None, suffix: str):
    """The engine's validation in a killable child process (``validation.py``): 422 with the
    reason, or when it overruns ``validate_timeout_seconds``."""
    from hktex_server.api.validation import InvalidMesh, ValidationTimeout, validate_mesh

    try:
        return await run_in_threadpool(
            validate_mesh,
            path,
            texture,
            svc.settings.max_vertices,
            suffix.lstrip(".") or None,
            svc.settings.validate_timeout_seconds,
        )
    except ValidationTimeout as exc:
        raise HTTPException(422, detail=str(exc)) from None
    except InvalidMesh as exc:
        detail = str(exc) if exc.input_error else f"unreadable mesh: {exc}"
        raise HTTPException(422, detail=detail) from None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:500] or type(exc).__name__


def _store_mesh(
    svc, owner, content_key, mesh, mesh_part, texture_part, suffix
) -> tuple[MeshRow, bool]:
    store = svc.store
    mesh_rel, _, mesh_bytes = store.publish_file(mesh_part.path, "meshes", suffix)
    tex_rel, tex_bytes = None, 0
    if texture_part is not None:
        tex_rel, _, tex_bytes = store.publish_file(
            texture_part.path, "textures", texture_part.path.suffix
        )
    row = MeshRow(
        id=new_id("msh"),
        owner=owner,
        name=(mesh_part.filename or "mesh")[-255:],
        content_key=content_key,
        mesh_hash=mesh.content_hash,
        mesh_blob=mesh_rel,
        texture_blob=tex_rel,
        n_vertices=mesh.n_vertices,
        n_faces=mesh.n_faces,
        has_texture=bool(mesh.has_texture),
        bytes=mesh_bytes + tex_bytes,
        checks={
            "readable": True,
            "finite": True,
            "non_degenerate": True,
            "manifold": True,
            "connected": True,
            "vertex_limit": svc.settings.max_vertices,
            "has_uvs": mesh.has_uvs,
            "scale": float(mesh.scale),
            "format": suffix.lstrip(".") or "sniffed",
        },
        created_at=now(),
    )
    return _insert_upload(svc, row)


@router.get("/meshes", response_model=schemas.MeshList, responses=ERRORS)
def list_meshes(owner: str = Depends(current_owner), svc: ServiceState = Depends(service)):
    with svc.db.read() as s:
        rows = s.execute(
            select(MeshRow).where(MeshRow.owner == owner).order_by(MeshRow.created_at.desc())
        ).scalars()
        return schemas.MeshList(items=[mesh_record(r) for r in rows])


@router.get("/meshes/{mesh_id}", response_model=schemas.MeshRecord, responses=ERRORS)
def get_mesh(
    mesh_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    with svc.db.read() as s:
        return mesh_record(own(s, MeshRow, mesh_id, owner, "mesh"))


@router.delete(
    "/meshes/{mesh_id}",
    status_code=204,
    responses={409: {"description": "jobs still use it"}, **ERRORS},
)
def delete_mesh(
    mesh_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
) -> Response:
    """Delete the mesh with everything of its own: its finished jobs and their kernel sets.
    409 while a job of it is queued or running (cancel it first). Shared things go only when
    nothing refers to them any more: blobs (content-addressed, any owner's rows) and the
    spectra of its geometry (no mesh of that content left, no kernel set or job using them)."""
    with svc.db.write(lock=True) as s:
        row = own(s, MeshRow, mesh_id, owner, "mesh")
        busy = s.execute(
            select(JobRow.id)
            .where(JobRow.mesh_id == mesh_id, JobRow.state.in_(ACTIVE_STATES))
            .limit(1)
        ).first()
        if busy is not None:
            raise HTTPException(409, detail=f"job {busy[0]} still uses this mesh; cancel it first")
        kernelsets = list(
            s.execute(
                select(KernelSetRow).where(
                    KernelSetRow.owner == owner, KernelSetRow.mesh_id == mesh_id
                )
            ).scalars()
        )
        jobs = [
            j
            for j in s.execute(
                select(JobRow).where(JobRow.owner == owner, JobRow.mesh_id == mesh_id)
            ).scalars()
        ]
        for dependent in [*kernelsets, *jobs, row]:
            s.delete(dependent)
        s.flush()
        orphaned = [
            blob
            for blob, column in (
                (row.mesh_blob, MeshRow.mesh_blob),
                (row.texture_blob, MeshRow.texture_blob),
                *((k.path, KernelSetRow.path) for k in kernelsets),
            )
            if blob and s.execute(select(column).where(column == blob).limit(1)).first() is None
        ]
        orphaned += _orphaned_spectra(s, row.mesh_hash)
    for blob in orphaned:
        svc.store.delete(blob)
    for job in jobs:
        (svc.store.root / "logs" / f"{job.id}.log").unlink(missing_ok=True)
    return Response(status_code=204)


def _orphaned_spectra(s, mesh_hash: str) -> list[str]:
    """Delete the spectra rows of a geometry no mesh has any more (nothing else can reach
    them: they are found by mesh content); return their directories and archives to remove.
    Rows still used by a kernel set or a job are kept."""
    if s.execute(select(MeshRow.id).where(MeshRow.mesh_hash == mesh_hash).limit(1)).first():
        return []
    paths = []
    for spectra in s.execute(select(SpectraRow).where(SpectraRow.mesh_hash == mesh_hash)).scalars():
        used = (
            s.execute(
                select(KernelSetRow.id).where(KernelSetRow.spectra_id == spectra.id).limit(1)
            ).first()
            or s.execute(select(JobRow.id).where(JobRow.spectra_id == spectra.id).limit(1)).first()
        )
        if used:
            continue
        s.delete(spectra)
        if spectra.path:
            paths.append(spectra.path)
        paths.append(f"archives/{spectra.id}.zip")
    return paths


# ---------------------------------------------------------------- spectra


def spectral_config(body: schemas.SpectralConfigIn):
    from hktex_engine.config import SpectralConfig

    try:
        return SpectralConfig.from_dict(body.model_dump(exclude_none=True))
    except (ValueError, TypeError) as exc:
        raise HTTPException(422, detail=f"invalid spectral config: {exc}") from None


def request_spectra(
    svc: ServiceState, owner: str, mesh: MeshRow, config, priority: int = 0
) -> SpectraRow:
    """The spectra row of (mesh, config); ready at once when the cache holds it on disk,
    else with a queued job (shared with whoever asked first)."""
    cfg = config.to_dict()
    row = jobqueue.ensure_spectra(
        svc.db,
        owner,
        mesh.id,
        mesh.mesh_hash,
        cfg,
        config.key(),
        svc.settings.max_attempts,
        priority,
    )
    return row


@router.post(
    "/meshes/{mesh_id}/spectra",
    response_model=schemas.SpectraRecord,
    status_code=202,
    responses={200: {"description": "ready (cached)", "model": schemas.SpectraRecord}, **ERRORS},
)
def post_spectra(
    mesh_id: str,
    response: Response,
    body: schemas.SpectralConfigIn | None = Body(None),
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> schemas.SpectraRecord:
    """Spectra of a mesh for a config: 200 when ready, 202 with the computing job's id."""
    config = spectral_config(body or schemas.SpectralConfigIn())
    with svc.db.read() as s:
        mesh = own(s, MeshRow, mesh_id, owner, "mesh")
    _adopt_cached(svc, mesh.mesh_hash, config)
    with svc.db.read() as s:
        existing = s.execute(
            select(SpectraRow).where(
                SpectraRow.mesh_hash == mesh.mesh_hash, SpectraRow.config_hash == config.key()
            )
        ).scalar_one_or_none()
    row = (
        existing
        if existing is not None and existing.state == "ready"
        else request_spectra(svc, owner, mesh, config)
    )
    if row.state == "ready":
        response.status_code = 200
    return spectra_record(row)


def _adopt_cached(svc: ServiceState, mesh_hash: str, config) -> None:
    """Spectra already on disk (computed by an earlier job, or the CLI into the same cache)
    become a ready row without a job."""
    from hktex_engine.spectra.grid import SpectraCache

    cache = SpectraCache(svc.store.root / "spectra")
    path = cache.path_for(mesh_hash, config)
    if not (path / "manifest.json").is_file():
        return
    with svc.db.write(lock=True) as s:
        t = now()
        row = jobqueue.spectra_row(s, mesh_hash, config.key(), config.to_dict(), t)
        if row.state in ("missing", "failed"):
            row.state, row.path, row.error, row.updated_at = "ready", svc.store.rel(path), None, t
            row.summary = row.summary or {"adopted_from_cache": True}


@router.get("/spectra/{spectra_id}", response_model=schemas.SpectraRecord, responses=ERRORS)
def get_spectra(
    spectra_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    with svc.db.read() as s:
        return spectra_record(visible_spectra(s, spectra_id, owner))


@router.get(
    "/spectra/{spectra_id}/archive",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/zip": {}}},
        409: {"description": "not ready"},
        **ERRORS,
    },
)
async def get_spectra_archive(
    spectra_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    """The spectra directory as a zip (stored, not deflated: the arrays barely compress)."""
    with svc.db.read() as s:
        row = visible_spectra(s, spectra_id, owner)
    if row.state != "ready" or not row.path:
        raise HTTPException(409, detail=f"spectra {spectra_id} are {row.state}, not ready")
    archive = await run_in_threadpool(_spectra_zip, svc, row)
    return FileResponse(archive, media_type="application/zip", filename=f"{spectra_id}.zip")


def _spectra_zip(svc: ServiceState, row: SpectraRow) -> Path:
    final = svc.store.root / "archives" / f"{row.id}.zip"
    if final.is_file():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    src = svc.store.abs(row.path)
    tmp = svc.store.temp_path(".zip")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for file in sorted(p for p in src.rglob("*") if p.is_file()):
            zf.write(file, arcname=str(file.relative_to(src)))
    tmp.replace(final)
    return final


# ---------------------------------------------------------------- views


@router.post(
    "/views",
    status_code=201,
    response_model=schemas.ViewsRecord,
    responses={
        200: {"description": "the same archive was uploaded before", "model": schemas.ViewsRecord},
        **ERRORS,
    },
    openapi_extra=_multipart(
        {"archive": "zip of a views directory (views.json + images)"}, ["archive"]
    ),
)
async def upload_views(
    request: Request,
    response: Response,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> schemas.ViewsRecord:
    """A multi-view dataset as a zip (checked against zip bombs and unsafe names)."""
    parts = await receive_files(request, svc.store, {"archive"}, svc.settings.max_upload_bytes)
    try:
        if "archive" not in parts:
            raise HTTPException(422, detail="the multipart body has no 'archive' file")
        archive = parts["archive"].path
        content_key = await run_in_threadpool(_digest, archive)
        existing = _uploaded_before(svc, ViewsRow, owner, content_key)
        if existing is not None:
            response.status_code = 200
            return views_record(existing)
        dest, root, files, size = await run_in_threadpool(_extract_views, svc, archive)
        try:
            # decoding the images (a few KB of PNG can claim gigabytes of pixels) happens in
            # a compute worker, under its memory and time budget, not in the API process
            await svc.compute.run(request, owner, "views", {"root": str(root)})
        except BaseException:
            svc.store.delete(svc.store.rel(dest))
            raise
        row = await run_in_threadpool(
            _publish_views, svc, owner, content_key, dest, root, files, size
        )
        return views_record(row)
    finally:
        remove_parts(parts)


def _extract_views(svc: ServiceState, archive: Path) -> tuple[Path, Path, int, int]:
    """Unpack the archive into a temp dir (bounded: ``extract_zip`` counts inflated bytes)."""
    dest = svc.store.temp_dir()
    try:
        files, size = extract_zip(
            archive, dest, svc.settings.max_archive_bytes, svc.settings.max_archive_members
        )
    except ArchiveError as exc:
        raise HTTPException(413 if exc.too_big else 422, detail=str(exc)) from None
    return dest, _dataset_root(dest), files, size


def _publish_views(
    svc: ServiceState, owner: str, content_key: str, dest: Path, root: Path, files: int, size: int
) -> ViewsRow:
    rel = svc.store.publish_dir(dest, "views", content_key)
    if root != dest:
        rel = str(Path(rel) / root.relative_to(dest))
    row = ViewsRow(
        id=new_id("vw"),
        owner=owner,
        content_key=content_key,
        path=rel,
        n_files=files,
        bytes=size,
        created_at=now(),
    )
    return _insert_upload(svc, row)[0]


def _dataset_root(dest: Path) -> Path:
    """The directory holding views.json: the archive's root, or its single top folder."""
    if (dest / "views.json").is_file():
        return dest
    children = [p for p in dest.iterdir() if p.is_dir()]
    if len(children) == 1 and (children[0] / "views.json").is_file():
        return children[0]
    return dest


@router.get("/views/{views_id}", response_model=schemas.ViewsRecord, responses=ERRORS)
def get_views(
    views_id: str, owner: str = Depends(current_owner), svc: ServiceState = Depends(service)
):
    with svc.db.read() as s:
        return views_record(own(s, ViewsRow, views_id, owner, "views dataset"))


__all__ = ["router", "request_spectra", "spectral_config", "not_found"]
