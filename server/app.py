"""The FastAPI application: ``create_app(settings)``.

Startup applies migrations, then (when ``workers > 0``) starts the embedded supervisor thread
so ``hktex serve`` alone is a working service. Unexpected engine errors that still reach a
route are turned into a specific 4xx when they are the caller's fault (HKTexError,
ValueError), never a 500 for bad input.
"""

from __future__ import annotations

import threading
from contextlib import asynccontextmanager
from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.responses import JSONResponse
from hktex_server import web
from hktex_server.api import schemas, validation
from hktex_server.api.assets import router as assets_router
from hktex_server.api.auth import current_owner
from hktex_server.api.catalog import router as catalog_router
from hktex_server.api.compute import ComputePool
from hktex_server.api.jobs import router as jobs_router
from hktex_server.api.kernelsets import router as kernelsets_router
from hktex_server.api.meshes import router as meshes_router
from hktex_server.jobs import queue as jobqueue
from hktex_server.jobs.supervisor import SupervisorThread, detect_devices
from hktex_server.settings import Settings
from hktex_server.state import ServiceState, service
from hktex_server.storage.blobs import BlobStore
from hktex_server.storage.db import Database


def package_version() -> str:
    try:
        return version("hktex")
    except PackageNotFoundError:
        return "0+unknown"


system = APIRouter(prefix="/v1", tags=["system"])


@system.get("/health", response_model=schemas.Health)
def health() -> schemas.Health:
    return schemas.Health()


@system.get("/info", response_model=schemas.Info)
def info(owner: str = Depends(current_owner), svc: ServiceState = Depends(service)) -> schemas.Info:
    st = svc.settings
    return schemas.Info(
        version=package_version(),
        devices=svc.devices,
        workers=svc.workers,
        queue=schemas.QueueDepth(**jobqueue.queue_depth(svc.db)),
        owner=owner,
        limits={
            "max_upload_bytes": st.max_upload_bytes,
            "max_vertices": st.max_vertices,
            "max_batch_points": st.max_batch_points,
            "max_json_batch_points": st.max_json_batch_points,
            "max_jobs_per_owner": st.max_jobs_per_owner,
            "max_running_per_owner": st.max_running_per_owner,
            "max_render_samples": st.max_render_samples,
            "max_queued_per_owner": st.max_queued_per_owner,
            "compute_workers": st.compute_workers_resolved(),
            "compute_timeout_seconds": int(st.compute_timeout_seconds),
            "compute_memory_bytes": st.compute_memory_bytes,
        },
    )


def create_app(settings: Settings | None = None, start_supervisor: bool | None = None) -> FastAPI:
    """The app; ``start_supervisor`` defaults to ``settings.workers > 0``."""
    settings = settings or Settings()
    tokens = settings.token_owners()
    run_supervisor = settings.workers > 0 if start_supervisor is None else start_supervisor

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        db = Database(settings.resolved_database_url())
        db.migrate()
        app.state.svc = ServiceState(
            settings=settings,
            db=db,
            store=BlobStore(settings.data_dir),
            workers=settings.workers if run_supervisor else 0,
            devices=detect_devices(settings),
            compute=ComputePool(settings),
        )
        threading.Thread(target=validation.warm, name="hktex-validation-warm", daemon=True).start()
        app.state.svc.compute.start()
        thread = SupervisorThread(settings) if run_supervisor else None
        if thread is not None:
            thread.start()
        try:
            yield
        finally:
            app.state.svc.compute.close()
            if thread is not None:
                thread.stop()
            db.dispose()

    app = FastAPI(
        title="HKTex",
        version=package_version(),
        description="Heat Kernel Textures: UV-free albedo fitting and queries on triangle meshes.",
        lifespan=lifespan,
        docs_url=None,  # served offline by hktex_server.web (no CDN)
        redoc_url=None,
    )
    app.state.tokens = tokens
    app.state.settings = settings
    app.include_router(system)
    app.include_router(meshes_router)
    app.include_router(jobs_router)
    app.include_router(kernelsets_router)
    app.include_router(catalog_router)
    app.include_router(assets_router)
    web.install(app)
    _error_handlers(app)
    return app


def _error_handlers(app: FastAPI) -> None:
    from hktex_engine.errors import HKTexError, KernelSetError, QueryError, SpectraError

    @app.exception_handler(HKTexError)
    async def _engine_error(_request: Request, exc: HKTexError) -> JSONResponse:
        code = 409 if isinstance(exc, SpectraError | KernelSetError) else 422
        if isinstance(exc, QueryError):
            code = 422
        return JSONResponse({"detail": f"{type(exc).__name__}: {exc}"}, status_code=code)

    @app.exception_handler(ValueError)
    async def _value_error(_request: Request, exc: ValueError) -> JSONResponse:
        return JSONResponse({"detail": f"invalid input: {exc}"}, status_code=422)
