"""Helpers for the service tests: a real uvicorn on a free loopback port, supervisors as
threads or separate processes, fast queue timings, and database URLs (SQLite, PostgreSQL)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
from hktex_server.jobs import queue as jobqueue
from hktex_server.settings import Settings
from hktex_server.storage.db import Database, JobRow

PG_URL = os.environ.get("HKTEX_TEST_PG_URL")
BACKENDS = ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def database_url(backend: str, tmp_path: Path) -> str:
    """SQLite in tmp_path, or a fresh schema on the test PostgreSQL (skips when unset)."""
    if backend == "sqlite":
        return f"sqlite:///{tmp_path / 'hktex.db'}"
    if not PG_URL:
        pytest.skip("HKTEX_TEST_PG_URL is not set")
    from sqlalchemy import create_engine, text

    schema = f"t_{uuid.uuid4().hex[:12]}"
    engine = create_engine(PG_URL)
    with engine.begin() as conn:
        conn.execute(text(f"CREATE SCHEMA {schema}"))
    engine.dispose()
    sep = "&" if "?" in PG_URL else "?"
    return f"{PG_URL}{sep}options=-csearch_path%3D{schema}"


def drop_schema(url: str) -> None:
    """Remove the per-test PostgreSQL schema ``database_url`` made (no-op for SQLite)."""
    if "search_path%3D" not in url:
        return
    from sqlalchemy import create_engine, text

    schema = url.rsplit("search_path%3D", 1)[1]
    engine = create_engine(PG_URL)
    with engine.begin() as conn:
        conn.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))
    engine.dispose()


def fast_settings(tmp_path: Path, url: str, **over) -> Settings:
    base = dict(
        data_dir=tmp_path / "data",
        database_url=url,
        workers=1,
        devices="cpu",
        lease_seconds=3.0,
        heartbeat_seconds=0.5,
        poll_seconds=0.1,
        cancel_grace_seconds=1.0,
        kill_grace_seconds=1.0,
        max_attempts=3,
        enable_test_tasks=True,
    )
    base.update(over)
    return Settings(**base)


def migrated(settings: Settings) -> Database:
    db = Database(settings.resolved_database_url())
    db.migrate()
    return db


def add_sleep_job(
    db: Database, owner: str = "local", max_attempts: int = 3, priority: int = 0, **params
) -> str:
    """Queue the internal test task directly (it is not reachable over HTTP)."""
    with db.write() as s:
        row = jobqueue.enqueue(
            s, owner, "sleep", params=params, max_attempts=max_attempts, priority=priority
        )
        return row.id


def job(db: Database, job_id: str) -> JobRow:
    with db.read() as s:
        return s.get(JobRow, job_id)


def wait_for(pred: Callable[[], object], timeout: float = 30.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout}s waiting for {what}")


class SupervisorInThread:
    def __init__(self, settings: Settings, name: str = "") -> None:
        from hktex_server.jobs.supervisor import Supervisor

        self.sup = Supervisor(settings, name=name)
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self.sup.run, args=(self.stop_event,), daemon=True)

    def __enter__(self) -> SupervisorInThread:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop_event.set()
        self.thread.join(30)


def start_supervisor_process(settings: Settings) -> subprocess.Popen:
    env = os.environ.copy()
    env["HKTEX_WORKER_SETTINGS"] = settings.model_dump_json()
    return subprocess.Popen(
        [sys.executable, "-m", "hktex_server.jobs.supervisor"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


class LiveServer:
    """``create_app`` under a real uvicorn in a thread, on a free loopback port."""

    def __init__(self, settings: Settings, start_supervisor: bool = False) -> None:
        import uvicorn
        from hktex_server.app import create_app

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        app = create_app(settings, start_supervisor=start_supervisor)
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> LiveServer:
        self.thread.start()
        wait_for(lambda: self.server.started, 30, "uvicorn to start")
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)


# A tiny spectral grid: seeding a kernel set costs about a second, no job needed.
SEED_SPECTRA = {"angles": 3, "anisotropies": [1.0, 10.0], "k": 16, "k_iso": 9}


def seed_kernelset(
    url: str,
    data_dir: Path,
    obj: Path,
    headers: dict | None = None,
    owner: str = "local",
    database_url: str | None = None,
) -> dict[str, str]:
    """A real mesh, spectra and kernel set in a running service without running a job.

    The mesh is uploaded over HTTP; its spectra are computed here into the service's spectra
    cache (which ``POST /spectra`` adopts as ready); a random kernel set is published to its
    blob store with a row, as a finished fit leaves them. Returns the ids.
    """
    import httpx
    from hktex_server.storage.blobs import BlobStore
    from hktex_server.storage.db import KernelSetRow, new_id, now

    from hktex_engine.config import SpectralConfig
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.kernels.model import KernelSet
    from hktex_engine.spectra.grid import SpectraCache
    from tests.kernels_support import random_kernels

    with httpx.Client(base_url=url, headers=headers or {}, timeout=60) as c:
        r = c.post("/v1/meshes", files={"mesh": (obj.name, obj.read_bytes(), "text/plain")})
        assert r.status_code in (200, 201), r.text
        mesh = r.json()
        config = SpectralConfig.from_dict(SEED_SPECTRA)
        spectra = SpectraCache(Path(data_dir) / "spectra").get_or_compute(load_mesh(obj), config)
        r = c.post(f"/v1/meshes/{mesh['id']}/spectra", json=SEED_SPECTRA)
        assert r.status_code == 200, r.text
        spectra_id = r.json()["id"]
    k = random_kernels(spectra, 12)
    ks = KernelSet(
        face_ids=k["face_ids"],
        barycentrics=k["bary"],
        theta=k["theta"],
        eta=k["eta"],
        threshold=k["threshold"],
        sharpness=k["sharpness"],
        colors=k["colors"],
        base_color=k["base_color"],
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
    )
    store = BlobStore(Path(data_dir))
    tmp = store.temp_path(".hkt")
    save_hkt(ks, tmp)
    rel, _digest, size = store.publish_file(tmp, "kernelsets", ".hkt")
    ks_id = new_id("kst")
    db = Database(database_url or f"sqlite:///{Path(data_dir) / 'hktex.db'}")
    with db.write() as s:
        s.add(
            KernelSetRow(
                id=ks_id,
                owner=owner,
                job_id=None,
                mesh_id=mesh["id"],
                spectra_id=spectra_id,
                path=rel,
                bytes=size,
                n_kernels=len(ks),
                metrics={},
                manifest={"seeded": True},
                created_at=now(),
            )
        )
    db.dispose()
    return {
        "mesh_id": mesh["id"],
        "spectra_id": spectra_id,
        "kernelset_id": ks_id,
        "n_faces": str(mesh["n_faces"]),
    }
