"""Routes: a kernel set baked for a 3D viewer: a textured GLB and its UV-space layers.

The dashboard's viewer shows the baked GLB and swaps its base-colour texture between three
layers on the same UV layout: ``kernel`` (the bake), ``original`` (the texture the mesh was
uploaded with, resampled to the bake's size) and ``error`` (a heat map of the two,
``hktex_engine.render.errormap``). One bake makes all of them at once, in a compute worker
(``compute.py``: the same time and memory budgets, owner queues and kill on disconnect as a
render; ``compute_child.Worker.bake``); concurrent requests for the same bake wait on one task,
killed only when all of them have gone. Results are published by one rename under ``derived/``
in the data dir, keyed by the kernel set's content-addressed file and the mesh's blobs, so a
second look is a file read in the API process.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from enum import IntEnum
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from hktex_server.api.auth import current_owner
from hktex_server.api.meshes import ERRORS
from hktex_server.api.records import own
from hktex_server.state import ServiceState, service
from hktex_server.storage.db import KernelSetRow, MeshRow, SpectraRow
from pydantic import BaseModel, Field

router = APIRouter(prefix="/v1", tags=["kernelsets"])
RESPONSES = {
    409: {"description": "the kernel set's spectra are not available"},
    429: {"description": "too many of your requests are waiting"},
    503: {"description": "over its time budget, or shutting down"},
    **ERRORS,
}

Layer = Literal["kernel", "original", "error"]
GLB = "model/gltf-binary"


# A few fixed sizes, not any integer: each kernel set then has at most three bakes ever (they
# are cached), so a client cannot make the service bake without end by varying the size.
class Resolution(IntEnum):
    """Texture side in texels (query strings parse into it; a Literal of ints would not)."""

    small = 256
    medium = 512
    large = 1024


RESOLUTION = Query(Resolution.medium, description="texture side in texels")


class BakeInfo(BaseModel):
    """What a bake produced; ``layers`` lists the textures available for the viewer."""

    kernelset_id: str
    resolution: Resolution
    atlas: Literal["mesh", "xatlas"] = Field(description="the mesh's own UVs or a fresh atlas")
    coverage: float = Field(description="fraction of texels covered by a triangle")
    layers: list[Layer]
    error_scale: float | None = Field(
        None, description="sRGB RMS error at the top of the error map's ramp"
    )
    error_rms: float | None = Field(
        None, description="RMS error over the covered texels (sRGB; not the surface PSNR)"
    )
    glb_bytes: int
    seconds: float = Field(description="time the bake took when it ran")


def _lookup(svc: ServiceState, owner: str, kernelset_id: str, resolution: int) -> dict:
    """The bake's compute payload (404 for another owner's kernel set, 409 without spectra);
    ``final`` is where the bake lives, keyed by the kernel set's content-addressed file and
    the mesh's blobs."""
    with svc.db.read() as s:
        ks = own(s, KernelSetRow, kernelset_id, owner, "kernel set")
        spectra = s.get(SpectraRow, ks.spectra_id)
        mesh = s.get(MeshRow, ks.mesh_id) if ks.mesh_id else None
    if spectra is None or spectra.state != "ready" or not spectra.path:
        raise HTTPException(409, detail="the spectra of this kernel set are not available")
    parts = [ks.path, str(resolution)]
    mesh_files = None
    if mesh is not None:
        parts += [mesh.mesh_blob, mesh.texture_blob or ""]
        mesh_files = {
            "mesh_path": str(svc.store.abs(mesh.mesh_blob)),
            "texture_path": str(svc.store.abs(mesh.texture_blob)) if mesh.texture_blob else None,
        }
    key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]
    return {
        "ks": {
            "kernelset_id": ks.id,
            "spectra_path": str(svc.store.abs(spectra.path)),
            "hkt_path": str(svc.store.abs(ks.path)),
            "mesh_hash": spectra.mesh_hash,
        },
        "mesh": mesh_files,
        "resolution": resolution,
        "max_vertices": svc.settings.max_vertices,
        "tmp": str(svc.store.temp_path()),  # made by the worker, removed here if it dies
        "final": str(svc.store.root / "derived" / key),
    }


async def _baked(svc: ServiceState, request: Request, owner: str, kernelset_id: str, res: int):
    """The bake's directory: read from ``derived/`` when it exists, else baked in a compute
    worker (time and memory budgets, killed when every client asking for it has gone)."""
    payload = await run_in_threadpool(_lookup, svc, owner, kernelset_id, int(res))
    final = Path(payload["final"])
    if (final / "bake.json").is_file():
        return final
    tmp = payload["tmp"]
    await svc.compute.run(
        request,
        owner,
        "bake",
        payload,
        share=f"bake:{final.name}",
        cleanup=lambda: shutil.rmtree(tmp, ignore_errors=True),
    )
    return final


@router.get("/kernelsets/{kernelset_id}/bake", response_model=BakeInfo, responses=RESPONSES)
async def bake_info(
    request: Request,
    kernelset_id: str,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
) -> BakeInfo:
    """Bake the kernel set for the viewer (or reuse the earlier bake) and say what there is."""
    path = await _baked(svc, request, owner, kernelset_id, resolution)
    meta = json.loads((path / "bake.json").read_text())
    return BakeInfo(kernelset_id=kernelset_id, **meta)


@router.get(
    "/kernelsets/{kernelset_id}/glb",
    response_class=FileResponse,
    responses={200: {"content": {GLB: {}}}, **RESPONSES},
)
async def get_glb(
    request: Request,
    kernelset_id: str,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
):
    """The kernel set baked into a textured GLB (mesh file units, sRGB base colour)."""
    path = await _baked(svc, request, owner, kernelset_id, resolution)
    return FileResponse(path / "model.glb", media_type=GLB, filename=f"{kernelset_id}.glb")


@router.get(
    "/kernelsets/{kernelset_id}/textures/{layer}",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}, **RESPONSES},
)
async def get_texture(
    request: Request,
    kernelset_id: str,
    layer: Layer,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
):
    """One UV-space layer of the bake as PNG: ``kernel``, ``original`` or ``error``."""
    path: Path = await _baked(svc, request, owner, kernelset_id, resolution)
    file = path / f"{layer}.png"
    if not file.is_file():
        raise HTTPException(
            404,
            detail=f"no {layer!r} layer: the kernel set's mesh has no texture on its own UVs "
            "(or was deleted)",
        )
    return FileResponse(file, media_type="image/png")
