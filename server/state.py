"""What every route needs, built once per app: settings, database, blob store, compute pool."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from fastapi import Request
from hktex_server.settings import Settings
from hktex_server.storage.blobs import BlobStore
from hktex_server.storage.db import Database


@dataclass
class ServiceState:
    settings: Settings
    db: Database
    store: BlobStore
    workers: int = 0
    devices: list[str] = field(default_factory=list)
    compute: Any = None  # hktex_server.api.compute.ComputePool: queries, renders, bakes


def service(request: Request) -> ServiceState:
    """FastAPI dependency: the app's shared state."""
    return request.app.state.svc
