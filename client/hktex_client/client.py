"""The synchronous and asynchronous HKTex clients.

Both execute the same route table (``_calls``); they differ only in how bytes move. Uploads
and downloads stream (a multi-hundred-MB mesh or spectra archive never sits whole in memory);
albedo queries speak NPY by default because large batches are the point of that route.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np

from hktex_client import _calls as calls
from hktex_client.errors import JobFailed, ServerError, WaitTimeout
from hktex_client.models import (
    FINAL_STATES,
    BakeInfo,
    Health,
    Info,
    JobRecord,
    KernelSetRecord,
    MeshRecord,
    SpectraRecord,
    ViewsRecord,
)
from hktex_client.sse import ServerSentEvent, aiter_events, iter_events

T = TypeVar("T")
DEFAULT_TIMEOUT = httpx.Timeout(120.0, connect=10.0)


def _headers(token: str | None) -> dict[str, str]:
    headers = {"User-Agent": "hktex-client/0.1"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers


def _partial_path(dest: Path) -> Path:
    return dest.with_name(f".{dest.name}.part-{os.getpid()}")


def _build_request(
    http: httpx.Client | httpx.AsyncClient, call: calls.Call, stack: contextlib.ExitStack
) -> httpx.Request:
    """The request of a route-table call, its upload files opened on ``stack`` (so they stay
    open while the body streams and close with it); the same for both clients."""
    files = {
        name: (p.name, stack.enter_context(p.open("rb")), kind) for name, p, kind in call.uploads
    }
    return http.build_request(
        call.method,
        call.path,
        params=call.params,
        json=call.json,
        content=call.content,
        files=files or None,
        headers=call.headers or None,
    )


def _final_from_event(event: ServerSentEvent) -> bool:
    """True when an event says its job reached a final state (the stream may end there)."""
    if event.event in ("end", "done", "close"):
        return True
    try:
        data = event.json()
    except ValueError:
        return False
    return isinstance(data, dict) and data.get("state") in FINAL_STATES


def _record_from_event(event: ServerSentEvent) -> JobRecord | None:
    """The job record an event carries (``progress``/``end`` events), else None."""
    try:
        data = event.json()
    except ValueError:
        return None
    if not isinstance(data, dict) or "state" not in data:
        return None
    return JobRecord.model_validate(data)


def _chunks(n: int, chunk_size: int | None) -> list[slice]:
    if not chunk_size or n <= chunk_size:
        return [slice(0, n)]
    return [slice(i, min(i + chunk_size, n)) for i in range(0, n, chunk_size)]


def _slice_query(kwargs: dict[str, Any], sl: slice) -> dict[str, Any]:
    return {k: (None if v is None else np.asarray(v)[sl]) for k, v in kwargs.items()}


class Client:
    """Synchronous HKTex client; use as a context manager or call ``close()``.

    ``Client("http://127.0.0.1:8000", token="...")``. Every method raises a subclass of
    :class:`~hktex_client.errors.HKTexAPIError` on an error answer.
    """

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
        transport: httpx.BaseTransport | None = None,
        retries: int = 2,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        # ``retries`` re-tries only failed connection attempts (nothing was sent), so it is
        # safe for every method, including uploads and job submissions.
        self._http = httpx.Client(
            base_url=self.base_url,
            headers=_headers(token),
            timeout=timeout,
            transport=transport or httpx.HTTPTransport(retries=retries),
        )

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- execution -------------------------------------------------------------------------

    def _run(self, call: calls.Call[T]) -> T:
        with contextlib.ExitStack() as stack:
            request = _build_request(self._http, call, stack)
            response = self._http.send(request, stream=call.stream_to is not None)
            try:
                if call.stream_to is not None:
                    if response.status_code >= 400:
                        response.read()
                        calls.raise_for_status(response)
                    self._save(response, call.stream_to)
                else:
                    calls.raise_for_status(response)
                return call.parse(response)
            finally:
                response.close()

    @staticmethod
    def _save(response: httpx.Response, dest: Path) -> None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = _partial_path(dest)
        try:
            with part.open("wb") as fh:
                for chunk in response.iter_bytes(1 << 20):
                    fh.write(chunk)
            part.replace(dest)  # a reader never sees a half-written file
        finally:
            part.unlink(missing_ok=True)

    # ---- service ---------------------------------------------------------------------------

    def health(self) -> Health:
        return self._run(calls.health())

    def info(self) -> Info:
        return self._run(calls.info())

    # ---- meshes ----------------------------------------------------------------------------

    def upload_mesh(self, path: str | Path, texture: str | Path | None = None) -> MeshRecord:
        """Upload a mesh file (OBJ, PLY, GLB/glTF, OFF) and optional texture, streamed."""
        return self._run(calls.upload_mesh(path, texture))

    def list_meshes(self) -> list[MeshRecord]:
        return self._run(calls.list_meshes())

    def get_mesh(self, mesh_id: str) -> MeshRecord:
        return self._run(calls.get_mesh(mesh_id))

    def delete_mesh(self, mesh_id: str) -> None:
        self._run(calls.delete_mesh(mesh_id))

    # ---- spectra ---------------------------------------------------------------------------

    def request_spectra(self, mesh_id: str, **config: Any) -> SpectraRecord:
        """Ask for spectra (``angles``, ``anisotropies``, ``k``, ``k_iso``; all optional)."""
        return self._run(calls.request_spectra(mesh_id, config))

    def get_spectra(self, spectra_id: str) -> SpectraRecord:
        return self._run(calls.get_spectra(spectra_id))

    def download_spectra(self, spectra_id: str, dest: str | Path) -> Path:
        """Stream the spectra archive to ``dest`` (written atomically)."""
        return self._run(calls.download_spectra(spectra_id, Path(dest)))

    # ---- jobs ------------------------------------------------------------------------------

    def submit_job(
        self,
        mesh_id: str,
        task: str,
        spectra: dict[str, Any] | None = None,
        params: dict[str, Any] | None = None,
        views_id: str | None = None,
        priority: int | None = None,
    ) -> JobRecord:
        """Queue a job (``task`` "fit_uv" or "fit_multiview"); 202 with its record."""
        return self._run(calls.submit_job(mesh_id, task, spectra, params, views_id, priority))

    def fit_uv(
        self,
        mesh_id: str,
        spectra: dict[str, Any] | None = None,
        priority: int | None = None,
        **params: Any,
    ) -> JobRecord:
        """Queue a UV fit (``kernels``, ``max_kernels``, ``steps``, ``seed``, ...)."""
        return self.submit_job(mesh_id, "fit_uv", spectra, params, priority=priority)

    def fit_multiview(
        self,
        mesh_id: str,
        views_id: str,
        spectra: dict[str, Any] | None = None,
        priority: int | None = None,
        **params: Any,
    ) -> JobRecord:
        """Queue a multi-view fit on views uploaded with :meth:`upload_views`."""
        return self.submit_job(
            mesh_id, "fit_multiview", spectra, params, views_id=views_id, priority=priority
        )

    def upload_views(self, path: str | Path) -> ViewsRecord:
        """Upload a multi-view dataset archive (images + cameras), streamed."""
        return self._run(calls.upload_views(path))

    def get_views(self, views_id: str) -> ViewsRecord:
        return self._run(calls.get_views(views_id))

    def get_job(self, job_id: str) -> JobRecord:
        return self._run(calls.get_job(job_id))

    def list_jobs(self, state: str | None = None, limit: int | None = None) -> list[JobRecord]:
        """Own jobs, newest first; ``state`` filters (e.g. "running")."""
        return self._run(calls.list_jobs(state, limit))

    def cancel_job(self, job_id: str) -> JobRecord:
        return self._run(calls.cancel_job(job_id))

    def wait(
        self,
        job_id: str,
        timeout: float = 600.0,
        poll: float = 0.5,
        raise_on_failure: bool = True,
    ) -> JobRecord:
        """Poll until the job is final; raise :class:`JobFailed` unless it succeeded."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                job = self.get_job(job_id)
            except (httpx.TransportError, ServerError):
                # A restarting service or a dropped connection is not the job's failure:
                # the queue keeps the job, so keep polling until the deadline.
                if time.monotonic() >= deadline:
                    raise
                time.sleep(poll)
                continue
            if job.done:
                if raise_on_failure and job.state != "succeeded":
                    raise JobFailed(job)
                return job
            if time.monotonic() >= deadline:
                raise WaitTimeout(job, timeout)
            time.sleep(min(poll, max(0.0, deadline - time.monotonic())))

    def stream_events(self, job_id: str) -> Iterator[ServerSentEvent]:
        """Server-Sent Events of a job's progress; ends once the job is final."""
        timeout = httpx.Timeout(self._http.timeout.connect, read=None)
        with self._http.stream(
            "GET",
            calls.job_events_path(job_id),
            headers={"Accept": "text/event-stream"},
            timeout=timeout,
        ) as response:
            if response.status_code >= 400:
                response.read()
                calls.raise_for_status(response)
            for event in iter_events(response.iter_lines()):
                yield event
                if _final_from_event(event):
                    return

    def watch(self, job_id: str) -> Iterator[JobRecord]:
        """The job's record each time it changes (from the event stream), the final one last."""
        for event in self.stream_events(job_id):
            record = _record_from_event(event)
            if record is not None:
                yield record

    # ---- kernel sets -----------------------------------------------------------------------

    def get_kernelset(self, kernelset_id: str) -> KernelSetRecord:
        return self._run(calls.get_kernelset(kernelset_id))

    def delete_kernelset(self, kernelset_id: str) -> None:
        """Delete a kernel set (its file goes once no other record holds the same bytes)."""
        self._run(calls.delete_kernelset(kernelset_id))

    def download_kernelset(self, kernelset_id: str, path: str | Path) -> Path:
        """Stream the ``.hkt`` file to ``path`` (written atomically)."""
        return self._run(calls.download_kernelset(kernelset_id, Path(path)))

    def list_kernelsets(self, limit: int | None = None) -> list[KernelSetRecord]:
        """This owner's kernel sets, newest first."""
        return self._run(calls.list_kernelsets(limit))

    def list_spectra(self, limit: int | None = None) -> list[SpectraRecord]:
        """Spectra of the geometry this owner uploaded, newest first."""
        return self._run(calls.list_spectra(limit))

    def bake(self, kernelset_id: str, resolution: int = 512) -> BakeInfo:
        """Bake the kernel set for viewing (256, 512 or 1024 texels; cached by the service)."""
        return self._run(calls.bake(kernelset_id, resolution))

    def download_glb(self, kernelset_id: str, path: str | Path, resolution: int = 512) -> Path:
        """The kernel set baked into a textured GLB, streamed to ``path``."""
        return self._run(calls.download_glb(kernelset_id, Path(path), resolution))

    def bake_layer(self, kernelset_id: str, layer: str, resolution: int = 512) -> bytes:
        """One UV-space layer of the bake as PNG: ``kernel``, ``original`` or ``error``."""
        return self._run(calls.bake_layer(kernelset_id, layer, resolution))

    def albedo(
        self,
        kernelset_id: str,
        face_ids: Any = None,
        barycentrics: Any = None,
        points: Any = None,
        binary: bool = True,
        chunk_size: int | None = None,
    ) -> np.ndarray:
        """Colours ``(P, 3)`` at (face, barycentrics) pairs or at points in file units.

        ``binary`` sends and receives NPY (fast, exact); ``chunk_size`` splits a batch larger
        than the service's limit into sequential requests.
        """
        query = {"face_ids": face_ids, "barycentrics": barycentrics, "points": points}
        parts = [
            self._run(calls.albedo(kernelset_id, binary=binary, **_slice_query(query, sl)))
            for sl in _chunks(calls.query_size(face_ids, barycentrics, points), chunk_size)
        ]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def render(
        self,
        kernelset_id: str,
        width: int | None = None,
        height: int | None = None,
        view: Any = None,
    ) -> bytes:
        """A PNG preview of the kernel set on its mesh."""
        return self._run(calls.render(kernelset_id, width, height, view))


class AsyncClient:
    """Asynchronous HKTex client (same methods as :class:`Client`, awaitable)."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
        transport: httpx.AsyncBaseTransport | None = None,
        limits: httpx.Limits | None = None,
        retries: int = 2,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        limits = limits or httpx.Limits(max_connections=100, max_keepalive_connections=20)
        self._http = httpx.AsyncClient(
            base_url=self.base_url,
            headers=_headers(token),
            timeout=timeout,
            transport=transport or httpx.AsyncHTTPTransport(retries=retries, limits=limits),
        )

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _run(self, call: calls.Call[T]) -> T:
        with contextlib.ExitStack() as stack:
            request = _build_request(self._http, call, stack)
            response = await self._http.send(request, stream=call.stream_to is not None)
            try:
                if call.stream_to is not None:
                    if response.status_code >= 400:
                        await response.aread()
                        calls.raise_for_status(response)
                    await self._save(response, call.stream_to)
                else:
                    calls.raise_for_status(response)
                return call.parse(response)
            finally:
                await response.aclose()

    @staticmethod
    async def _save(response: httpx.Response, dest: Path) -> None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = _partial_path(dest)
        try:
            with part.open("wb") as fh:
                async for chunk in response.aiter_bytes(1 << 20):
                    fh.write(chunk)
            part.replace(dest)
        finally:
            part.unlink(missing_ok=True)

    async def health(self) -> Health:
        return await self._run(calls.health())

    async def info(self) -> Info:
        return await self._run(calls.info())

    async def upload_mesh(self, path: str | Path, texture: str | Path | None = None) -> MeshRecord:
        return await self._run(calls.upload_mesh(path, texture))

    async def list_meshes(self) -> list[MeshRecord]:
        return await self._run(calls.list_meshes())

    async def get_mesh(self, mesh_id: str) -> MeshRecord:
        return await self._run(calls.get_mesh(mesh_id))

    async def delete_mesh(self, mesh_id: str) -> None:
        await self._run(calls.delete_mesh(mesh_id))

    async def request_spectra(self, mesh_id: str, **config: Any) -> SpectraRecord:
        return await self._run(calls.request_spectra(mesh_id, config))

    async def get_spectra(self, spectra_id: str) -> SpectraRecord:
        return await self._run(calls.get_spectra(spectra_id))

    async def download_spectra(self, spectra_id: str, dest: str | Path) -> Path:
        return await self._run(calls.download_spectra(spectra_id, Path(dest)))

    async def submit_job(
        self,
        mesh_id: str,
        task: str,
        spectra: dict[str, Any] | None = None,
        params: dict[str, Any] | None = None,
        views_id: str | None = None,
        priority: int | None = None,
    ) -> JobRecord:
        return await self._run(calls.submit_job(mesh_id, task, spectra, params, views_id, priority))

    async def fit_uv(
        self,
        mesh_id: str,
        spectra: dict[str, Any] | None = None,
        priority: int | None = None,
        **params: Any,
    ) -> JobRecord:
        return await self.submit_job(mesh_id, "fit_uv", spectra, params, priority=priority)

    async def fit_multiview(
        self,
        mesh_id: str,
        views_id: str,
        spectra: dict[str, Any] | None = None,
        priority: int | None = None,
        **params: Any,
    ) -> JobRecord:
        return await self.submit_job(
            mesh_id, "fit_multiview", spectra, params, views_id=views_id, priority=priority
        )

    async def upload_views(self, path: str | Path) -> ViewsRecord:
        return await self._run(calls.upload_views(path))

    async def get_views(self, views_id: str) -> ViewsRecord:
        return await self._run(calls.get_views(views_id))

    async def get_job(self, job_id: str) -> JobRecord:
        return await self._run(calls.get_job(job_id))

    async def list_jobs(
        self, state: str | None = None, limit: int | None = None
    ) -> list[JobRecord]:
        return await self._run(calls.list_jobs(state, limit))

    async def cancel_job(self, job_id: str) -> JobRecord:
        return await self._run(calls.cancel_job(job_id))

    async def wait(
        self,
        job_id: str,
        timeout: float = 600.0,
        poll: float = 0.5,
        raise_on_failure: bool = True,
    ) -> JobRecord:
        deadline = time.monotonic() + timeout
        while True:
            try:
                job = await self.get_job(job_id)
            except (httpx.TransportError, ServerError):
                if time.monotonic() >= deadline:
                    raise
                await asyncio.sleep(poll)
                continue
            if job.done:
                if raise_on_failure and job.state != "succeeded":
                    raise JobFailed(job)
                return job
            if time.monotonic() >= deadline:
                raise WaitTimeout(job, timeout)
            await asyncio.sleep(min(poll, max(0.0, deadline - time.monotonic())))

    async def stream_events(self, job_id: str) -> AsyncIterator[ServerSentEvent]:
        timeout = httpx.Timeout(self._http.timeout.connect, read=None)
        async with self._http.stream(
            "GET",
            calls.job_events_path(job_id),
            headers={"Accept": "text/event-stream"},
            timeout=timeout,
        ) as response:
            if response.status_code >= 400:
                await response.aread()
                calls.raise_for_status(response)
            async for event in aiter_events(response.aiter_lines()):
                yield event
                if _final_from_event(event):
                    return

    async def watch(self, job_id: str) -> AsyncIterator[JobRecord]:
        async for event in self.stream_events(job_id):
            record = _record_from_event(event)
            if record is not None:
                yield record

    async def get_kernelset(self, kernelset_id: str) -> KernelSetRecord:
        return await self._run(calls.get_kernelset(kernelset_id))

    async def delete_kernelset(self, kernelset_id: str) -> None:
        await self._run(calls.delete_kernelset(kernelset_id))

    async def download_kernelset(self, kernelset_id: str, path: str | Path) -> Path:
        return await self._run(calls.download_kernelset(kernelset_id, Path(path)))

    async def list_kernelsets(self, limit: int | None = None) -> list[KernelSetRecord]:
        return await self._run(calls.list_kernelsets(limit))

    async def list_spectra(self, limit: int | None = None) -> list[SpectraRecord]:
        return await self._run(calls.list_spectra(limit))

    async def bake(self, kernelset_id: str, resolution: int = 512) -> BakeInfo:
        return await self._run(calls.bake(kernelset_id, resolution))

    async def download_glb(
        self, kernelset_id: str, path: str | Path, resolution: int = 512
    ) -> Path:
        return await self._run(calls.download_glb(kernelset_id, Path(path), resolution))

    async def bake_layer(self, kernelset_id: str, layer: str, resolution: int = 512) -> bytes:
        return await self._run(calls.bake_layer(kernelset_id, layer, resolution))

    async def albedo(
        self,
        kernelset_id: str,
        face_ids: Any = None,
        barycentrics: Any = None,
        points: Any = None,
        binary: bool = True,
        chunk_size: int | None = None,
    ) -> np.ndarray:
        query = {"face_ids": face_ids, "barycentrics": barycentrics, "points": points}
        parts = [
            await self._run(calls.albedo(kernelset_id, binary=binary, **_slice_query(query, sl)))
            for sl in _chunks(calls.query_size(face_ids, barycentrics, points), chunk_size)
        ]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    async def render(
        self,
        kernelset_id: str,
        width: int | None = None,
        height: int | None = None,
        view: Any = None,
    ) -> bytes:
        return await self._run(calls.render(kernelset_id, width, height, view))
