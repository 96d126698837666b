"""What every route needs, built once per app: settings, database, blob store, query cache."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

from fastapi import Request
from hktex_server.api.querycache import QueryCache
from hktex_server.settings import Settings
from hktex_server.storage.blobs import BlobStore
from hktex_server.storage.db import Database


@dataclass
class ServiceState:
    settings: Settings
    db: Database
    store: BlobStore
    queries: QueryCache
    render_lock: threading.Semaphore = field(default_factory=lambda: threading.Semaphore(1))
    workers: int = 0
    devices: list[str] = field(default_factory=list)
    compute: Any = None  # hktex_server.api.compute.ComputePool: queries and renders


def service(request: Request) -> ServiceState:
    """FastAPI dependency: the app's shared state."""
    return request.app.state.svc
