"""Routes: a kernel set baked for a 3D viewer: a textured GLB and its UV-space layers.

The dashboard's viewer shows the baked GLB and swaps its base-colour texture between three
layers on the same UV layout: ``kernel`` (the bake), ``original`` (the texture the mesh was
uploaded with, resampled to the bake's size) and ``error`` (a heat map of the two,
``hktex_engine.render.errormap``). One bake makes all of them at once, on a single background
thread (``Baker``), so a bake of seconds never blocks the event loop and two bakes never fight
over two cores; concurrent requests for the same bake wait on the same future. Results are
kept under ``derived/`` in the data dir, keyed by the kernel set's content-addressed file and
the mesh's blobs, so a second look is a file read.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import shutil
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
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
RESPONSES = {409: {"description": "the kernel set's spectra are not available"}, **ERRORS}

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


class Baker:
    """One background thread for bakes, and the bakes in flight by key (deduplicated)."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hktex-bake")
        self._lock = threading.Lock()
        self._running: dict[str, Future] = {}

    def submit(self, key: str, fn, *args) -> Future:
        with self._lock:
            fut = self._running.get(key)
            if fut is None:
                fut = self._pool.submit(fn, *args)
                self._running[key] = fut
                fut.add_done_callback(lambda _f: self._forget(key))
            return fut

    def _forget(self, key: str) -> None:
        with self._lock:
            self._running.pop(key, None)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


def baker(request: Request) -> Baker:
    """FastAPI dependency: the app's baker, made on first use."""
    state = request.app.state
    if getattr(state, "baker", None) is None:
        state.baker = Baker()
    return state.baker


def _lookup(svc: ServiceState, owner: str, kernelset_id: str, resolution: int):
    with svc.db.read() as s:
        ks = own(s, KernelSetRow, kernelset_id, owner, "kernel set")
        spectra = s.get(SpectraRow, ks.spectra_id)
        mesh = s.get(MeshRow, ks.mesh_id) if ks.mesh_id else None
    if spectra is None or spectra.state != "ready" or not spectra.path:
        raise HTTPException(409, detail="the spectra of this kernel set are not available")
    parts = [ks.path, str(resolution)]
    if mesh is not None:
        parts += [mesh.mesh_blob, mesh.texture_blob or ""]
    key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]
    return ks, spectra, mesh, key


def _bake(svc: ServiceState, ks: KernelSetRow, spectra_row, mesh_row, resolution: int, key: str):
    """Bake all layers into ``derived/<key>`` (atomic publish) and return its path."""
    final = svc.store.root / "derived" / key
    if (final / "bake.json").is_file():
        return final
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.render.bake import (
        bake_texture,
        rasterize_uv,
        textured_trimesh,
        write_glb,
        write_png,
    )
    from hktex_engine.render.errormap import DEFAULT_SCALE, error_texture, resample_texture

    start = time.perf_counter()
    warm = svc.queries.get(
        ks.id,
        str(svc.store.abs(spectra_row.path)),
        str(svc.store.abs(ks.path)),
        spectra_row.mesh_hash,
    )
    mesh = None
    if mesh_row is not None:
        texture = svc.store.abs(mesh_row.texture_blob) if mesh_row.texture_blob else None
        mesh = load_mesh(
            svc.store.abs(mesh_row.mesh_blob),
            texture=texture,
            max_vertices=svc.settings.max_vertices,
        )
        if mesh.content_hash != warm.spectra.mesh_hash:
            mesh = None  # not the geometry of these spectra: bake on a fresh atlas
    bake = bake_texture(warm.spectra, warm.kernelset, mesh, resolution)
    tmp = svc.store.temp_dir()
    try:
        write_png(tmp / "kernel.png", bake.texture)
        write_glb(tmp / "model.glb", textured_trimesh(warm.spectra, bake))
        layers, scale, rms = ["kernel"], None, None
        if mesh is not None and mesh.texture is not None and bake.atlas == "mesh":
            original = resample_texture(mesh.texture, resolution)
            write_png(tmp / "original.png", original)
            covered = rasterize_uv(bake.corner_uvs, resolution, resolution)[0] >= 0
            heat, rms = error_texture(bake.texture, original, DEFAULT_SCALE, covered)
            write_png(tmp / "error.png", heat)
            layers += ["original", "error"]
            scale = DEFAULT_SCALE
        meta = {
            "resolution": resolution,
            "atlas": bake.atlas,
            "coverage": round(bake.coverage, 4),
            "layers": layers,
            "error_scale": scale,
            "error_rms": None if rms is None else round(rms, 5),
            "glb_bytes": (tmp / "model.glb").stat().st_size,
            "seconds": round(time.perf_counter() - start, 3),
        }
        (tmp / "bake.json").write_text(json.dumps(meta))  # written last: marks it complete
        svc.store.publish_dir(tmp, "derived", key)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


async def _baked(svc: ServiceState, bakes: Baker, owner: str, kernelset_id: str, res: int):
    res = int(res)
    ks, spectra, mesh, key = await run_in_threadpool(_lookup, svc, owner, kernelset_id, res)
    fut = bakes.submit(key, _bake, svc, ks, spectra, mesh, res, key)
    from hktex_engine.errors import HKTexError

    try:
        return await asyncio.wrap_future(fut)
    except HKTexError as exc:
        raise HTTPException(422, detail=f"bake failed: {type(exc).__name__}: {exc}") from None


@router.get("/kernelsets/{kernelset_id}/bake", response_model=BakeInfo, responses=RESPONSES)
async def bake_info(
    kernelset_id: str,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
    bakes: Baker = Depends(baker),
) -> BakeInfo:
    """Bake the kernel set for the viewer (or reuse the earlier bake) and say what there is."""
    path = await _baked(svc, bakes, owner, kernelset_id, resolution)
    meta = json.loads((path / "bake.json").read_text())
    return BakeInfo(kernelset_id=kernelset_id, **meta)


@router.get(
    "/kernelsets/{kernelset_id}/glb",
    response_class=FileResponse,
    responses={200: {"content": {GLB: {}}}, **RESPONSES},
)
async def get_glb(
    kernelset_id: str,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
    bakes: Baker = Depends(baker),
):
    """The kernel set baked into a textured GLB (mesh file units, sRGB base colour)."""
    path = await _baked(svc, bakes, owner, kernelset_id, resolution)
    return FileResponse(path / "model.glb", media_type=GLB, filename=f"{kernelset_id}.glb")


@router.get(
    "/kernelsets/{kernelset_id}/textures/{layer}",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}, **RESPONSES},
)
async def get_texture(
    kernelset_id: str,
    layer: Layer,
    resolution: Resolution = RESOLUTION,
    owner: str = Depends(current_owner),
    svc: ServiceState = Depends(service),
    bakes: Baker = Depends(baker),
):
    """One UV-space layer of the bake as PNG: ``kernel``, ``original`` or ``error``."""
    path: Path = await _baked(svc, bakes, owner, kernelset_id, resolution)
    file = path / f"{layer}.png"
    if not file.is_file():
        raise HTTPException(
            404,
            detail=f"no {layer!r} layer: the kernel set's mesh has no texture on its own UVs "
            "(or was deleted)",
        )
    return FileResponse(file, media_type="image/png")
