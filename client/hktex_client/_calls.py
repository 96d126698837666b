"""What each API route sends and how its answer is read, independent of sync or async I/O.

The sync and async clients only execute a :class:`Call`; keeping the route table in one place
means the two clients cannot drift apart (one definition per route, two thin executors).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

import httpx
import numpy as np

from hktex_client.errors import error_for
from hktex_client.models import (
    BakeInfo,
    Health,
    Info,
    JobRecord,
    KernelSetRecord,
    MeshRecord,
    SpectraRecord,
    ViewsRecord,
)
from hktex_client.npy import NPY_MEDIA_TYPE, face_query_array, from_npy_bytes, to_npy_bytes

T = TypeVar("T")
API = "/v1"


@dataclass
class Call(Generic[T]):
    """One HTTP exchange: the request to send and the parser of a successful answer."""

    method: str
    path: str
    parse: Callable[[httpx.Response], T]
    params: dict[str, Any] | None = None
    json: Any = None
    content: bytes | None = None
    headers: dict[str, str] = field(default_factory=dict)
    uploads: list[tuple[str, Path, str]] = field(default_factory=list)  # (field, path, type)
    stream_to: Path | None = None  # download the body to this file instead of memory


def raise_for_status(response: httpx.Response) -> None:
    """Raise the typed error of an error answer, carrying the server's reason."""
    if response.status_code < 400:
        return
    try:
        body = response.json()
    except ValueError:
        body = None
    raise error_for(
        response.status_code,
        body,
        method=response.request.method,
        url=str(response.request.url),
        text=response.text if body is None else "",
    )


def _model(cls: type[T]) -> Callable[[httpx.Response], T]:
    return lambda r: cls.model_validate(r.json())  # type: ignore[attr-defined]


def _items(payload: Any) -> list[Any]:
    """A list answer, bare or wrapped as ``{"items": [...]}`` (paginated listings)."""
    if isinstance(payload, dict):
        for key in ("items", "meshes", "jobs", "results"):
            if isinstance(payload.get(key), list):
                return payload[key]
    if isinstance(payload, list):
        return payload
    raise ValueError(f"expected a list answer, got {type(payload).__name__}")


def _model_list(cls: type[T]) -> Callable[[httpx.Response], list[T]]:
    return lambda r: [cls.model_validate(x) for x in _items(r.json())]  # type: ignore[attr-defined]


def _none(_: httpx.Response) -> None:
    return None


def _drop_none(d: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


# ---- routes ---------------------------------------------------------------------------------


def health() -> Call[Health]:
    return Call("GET", f"{API}/health", _model(Health))


def info() -> Call[Info]:
    return Call("GET", f"{API}/info", _model(Info))


def upload_mesh(path: str | Path, texture: str | Path | None = None) -> Call[MeshRecord]:
    mesh_path = Path(path)
    if not mesh_path.is_file():
        raise FileNotFoundError(f"no mesh file at {mesh_path}")
    uploads = [("mesh", mesh_path, "application/octet-stream")]
    if texture is not None:
        tex_path = Path(texture)
        if not tex_path.is_file():
            raise FileNotFoundError(f"no texture file at {tex_path}")
        uploads.append(("texture", tex_path, "application/octet-stream"))
    return Call("POST", f"{API}/meshes", _model(MeshRecord), uploads=uploads)


def list_meshes() -> Call[list[MeshRecord]]:
    return Call("GET", f"{API}/meshes", _model_list(MeshRecord))


def get_mesh(mesh_id: str) -> Call[MeshRecord]:
    return Call("GET", f"{API}/meshes/{mesh_id}", _model(MeshRecord))


def delete_mesh(mesh_id: str) -> Call[None]:
    return Call("DELETE", f"{API}/meshes/{mesh_id}", _none)


def request_spectra(mesh_id: str, config: Mapping[str, Any]) -> Call[SpectraRecord]:
    return Call(
        "POST", f"{API}/meshes/{mesh_id}/spectra", _model(SpectraRecord), json=_drop_none(config)
    )


def get_spectra(spectra_id: str) -> Call[SpectraRecord]:
    return Call("GET", f"{API}/spectra/{spectra_id}", _model(SpectraRecord))


def download_spectra(spectra_id: str, dest: Path) -> Call[Path]:
    return Call("GET", f"{API}/spectra/{spectra_id}/archive", lambda r: dest, stream_to=Path(dest))


def submit_job(
    mesh_id: str,
    task: str,
    spectra: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    views_id: str | None = None,
    priority: int | None = None,
) -> Call[JobRecord]:
    body: dict[str, Any] = {"mesh_id": mesh_id, "task": task}
    if spectra is not None:
        body["spectra"] = _drop_none(spectra)
    if params is not None:
        body["params"] = _drop_none(params)
    if views_id is not None:
        body["views_id"] = views_id
    if priority is not None:
        body["priority"] = priority
    return Call("POST", f"{API}/jobs", _model(JobRecord), json=body)


def upload_views(path: str | Path) -> Call[ViewsRecord]:
    archive = Path(path)
    if not archive.is_file():
        raise FileNotFoundError(f"no views archive at {archive}")
    return Call(
        "POST",
        f"{API}/views",
        _model(ViewsRecord),
        uploads=[("archive", archive, "application/octet-stream")],
    )


def get_views(views_id: str) -> Call[ViewsRecord]:
    return Call("GET", f"{API}/views/{views_id}", _model(ViewsRecord))


def get_job(job_id: str) -> Call[JobRecord]:
    return Call("GET", f"{API}/jobs/{job_id}", _model(JobRecord))


def list_jobs(state: str | None = None, limit: int | None = None) -> Call[list[JobRecord]]:
    params = _drop_none({"state": state, "limit": limit})
    return Call("GET", f"{API}/jobs", _model_list(JobRecord), params=params or None)


def cancel_job(job_id: str) -> Call[JobRecord]:
    return Call("POST", f"{API}/jobs/{job_id}/cancel", _model(JobRecord))


def job_events_path(job_id: str) -> str:
    return f"{API}/jobs/{job_id}/events"


def get_kernelset(kernelset_id: str) -> Call[KernelSetRecord]:
    return Call("GET", f"{API}/kernelsets/{kernelset_id}", _model(KernelSetRecord))


def delete_kernelset(kernelset_id: str) -> Call[None]:
    return Call("DELETE", f"{API}/kernelsets/{kernelset_id}", _none)


def download_kernelset(kernelset_id: str, dest: Path) -> Call[Path]:
    return Call(
        "GET", f"{API}/kernelsets/{kernelset_id}/file", lambda r: dest, stream_to=Path(dest)
    )


def list_kernelsets(limit: int | None = None) -> Call[list[KernelSetRecord]]:
    params = _drop_none({"limit": limit})
    return Call("GET", f"{API}/kernelsets", _model_list(KernelSetRecord), params=params or None)


def list_spectra(limit: int | None = None) -> Call[list[SpectraRecord]]:
    params = _drop_none({"limit": limit})
    return Call("GET", f"{API}/spectra", _model_list(SpectraRecord), params=params or None)


def bake(kernelset_id: str, resolution: int = 512) -> Call[BakeInfo]:
    return Call(
        "GET",
        f"{API}/kernelsets/{kernelset_id}/bake",
        _model(BakeInfo),
        params={"resolution": resolution},
    )


def download_glb(kernelset_id: str, dest: Path, resolution: int = 512) -> Call[Path]:
    return Call(
        "GET",
        f"{API}/kernelsets/{kernelset_id}/glb",
        lambda r: dest,
        params={"resolution": resolution},
        stream_to=Path(dest),
    )


def bake_layer(kernelset_id: str, layer: str, resolution: int = 512) -> Call[bytes]:
    return Call(
        "GET",
        f"{API}/kernelsets/{kernelset_id}/textures/{layer}",
        lambda r: r.content,
        params={"resolution": resolution},
        headers={"Accept": "image/png"},
    )


def _colors_from(response: httpx.Response) -> np.ndarray:
    kind = response.headers.get("content-type", "").split(";")[0].strip()
    if kind == NPY_MEDIA_TYPE:
        return from_npy_bytes(response.content)
    payload = response.json()
    colors = payload.get("colors") if isinstance(payload, dict) else payload
    return np.asarray(colors, dtype=np.float32).reshape(-1, 3)


def query_size(face_ids: Any, barycentrics: Any, points: Any) -> int:
    """Number of query rows; raises ValueError on an ambiguous or mismatched query."""
    by_faces = face_ids is not None or barycentrics is not None
    if by_faces == (points is not None):
        raise ValueError("give either face_ids and barycentrics, or points")
    if by_faces:
        if face_ids is None or barycentrics is None:
            raise ValueError("face_ids and barycentrics go together")
        f, b = np.asarray(face_ids), np.asarray(barycentrics)
        if f.ndim != 1 or b.shape != (f.shape[0], 3):
            raise ValueError(
                f"face_ids must be (P,) and barycentrics (P, 3); got {f.shape} and {b.shape}"
            )
        return int(f.shape[0])
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (P, 3); got {p.shape}")
    return int(p.shape[0])


def albedo(
    kernelset_id: str,
    face_ids: Any = None,
    barycentrics: Any = None,
    points: Any = None,
    binary: bool = True,
) -> Call[np.ndarray]:
    """A colour query at (face, barycentric) pairs or at 3-D points (file units)."""
    by_faces = face_ids is not None or barycentrics is not None
    if by_faces == (points is not None):
        raise ValueError("give either face_ids and barycentrics, or points")
    path = f"{API}/kernelsets/{kernelset_id}/albedo"
    accept = NPY_MEDIA_TYPE if binary else "application/json"
    headers = {"Accept": accept}
    if by_faces:
        if face_ids is None or barycentrics is None:
            raise ValueError("face_ids and barycentrics go together")
        rows = face_query_array(np.asarray(face_ids), np.asarray(barycentrics))
        if not binary:
            body = {
                "face_ids": rows[:, 0].astype(np.int64).tolist(),
                "barycentrics": rows[:, 1:].tolist(),
            }
            return Call("POST", path, _colors_from, json=body, headers=headers)
        return _npy_albedo_call(path, rows, "faces", headers)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (P, 3); got {pts.shape}")
    if not binary:
        return Call("POST", path, _colors_from, json={"points": pts.tolist()}, headers=headers)
    return _npy_albedo_call(path, pts, "points", headers)


def _npy_albedo_call(
    path: str, array: np.ndarray, kind: str, headers: dict[str, str]
) -> Call[np.ndarray]:
    """The binary form of an albedo query: the array as an NPY body, ``kind`` telling the
    server how to read its rows (faces: face id + barycentrics; points: x, y, z)."""
    headers["Content-Type"] = NPY_MEDIA_TYPE
    return Call(
        "POST",
        path,
        _colors_from,
        content=to_npy_bytes(array),
        headers=headers,
        params={"kind": kind},
    )


def render(
    kernelset_id: str, width: int | None = None, height: int | None = None, view: Any = None
) -> Call[bytes]:
    params = _drop_none({"width": width, "height": height, "view": view})
    return Call(
        "GET",
        f"{API}/kernelsets/{kernelset_id}/render",
        lambda r: r.content,
        params=params or None,
        headers={"Accept": "image/png"},
    )
