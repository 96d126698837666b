"""Metadata database: tables, engine creation, migrations at startup.

SQLite (WAL) is the embedded default; PostgreSQL by URL for several hosts. The jobs table is
the queue (see :mod:`hktex_server.jobs.queue`). Times are Unix epoch floats from the writer's
clock: one host in the default deployment; multi-host deployments need synchronised clocks
(NTP), which leases tolerate to within a few seconds.
"""

from __future__ import annotations

import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    Float,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    text,
)
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

ACTIVE_STATES = ("queued", "running", "cancelling")
TERMINAL_STATES = ("succeeded", "failed", "cancelled")


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex}"


def now() -> float:
    return time.time()


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON}


class MeshRow(Base):
    __tablename__ = "meshes"
    __table_args__ = (UniqueConstraint("owner", "content_key", name="uq_mesh_owner_content"),)

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[str] = mapped_column(String(255))
    content_key: Mapped[str] = mapped_column(String(64))
    mesh_hash: Mapped[str] = mapped_column(String(64), index=True)
    mesh_blob: Mapped[str] = mapped_column(Text)
    texture_blob: Mapped[str | None] = mapped_column(Text, nullable=True)
    n_vertices: Mapped[int] = mapped_column(Integer)
    n_faces: Mapped[int] = mapped_column(Integer)
    has_texture: Mapped[bool] = mapped_column(Boolean)
    bytes: Mapped[int] = mapped_column(Integer)
    checks: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float)


class SpectraRow(Base):
    __tablename__ = "spectra"
    __table_args__ = (UniqueConstraint("mesh_hash", "config_hash", name="uq_spectra_key"),)

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    mesh_hash: Mapped[str] = mapped_column(String(64))
    config_hash: Mapped[str] = mapped_column(String(64))
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    path: Mapped[str | None] = mapped_column(Text, nullable=True)
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)


class JobRow(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        Index("ix_jobs_claim", "state", "priority", "created_at"),
        Index("ix_jobs_owner_state", "owner", "state"),
    )

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    owner: Mapped[str] = mapped_column(String(128))
    task: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16))
    priority: Mapped[int] = mapped_column(Integer, default=0)
    mesh_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    spectra_id: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    views_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    lease_owner: Mapped[str | None] = mapped_column(String(128), nullable=True)
    lease_token: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    pid: Mapped[int | None] = mapped_column(Integer, nullable=True)
    device: Mapped[str | None] = mapped_column(String(32), nullable=True)
    progress: Mapped[dict[str, Any]] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    result: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)


class KernelSetRow(Base):
    __tablename__ = "kernelsets"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    job_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    mesh_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    spectra_id: Mapped[str] = mapped_column(String(64))
    path: Mapped[str] = mapped_column(Text)
    bytes: Mapped[int] = mapped_column(Integer)
    n_kernels: Mapped[int] = mapped_column(Integer)
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON)
    manifest: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float)


class ViewsRow(Base):
    __tablename__ = "views"
    __table_args__ = (UniqueConstraint("owner", "content_key", name="uq_views_owner_content"),)

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    content_key: Mapped[str] = mapped_column(String(64))
    path: Mapped[str] = mapped_column(Text)
    n_files: Mapped[int] = mapped_column(Integer)
    bytes: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[float] = mapped_column(Float)


# ---------------------------------------------------------------- engine


def make_engine(url: str) -> Engine:
    """An engine with SQLite made fit for concurrent processes (WAL, busy timeout, and
    explicit ``BEGIN``/``BEGIN IMMEDIATE`` instead of pysqlite's implicit transactions)."""
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 60, "check_same_thread": False})
        _configure_sqlite(engine)
        return engine
    return create_engine(url, pool_pre_ping=True)


def _configure_sqlite(engine: Engine) -> None:
    # pysqlite starts transactions lazily and never with IMMEDIATE; a claim must take the
    # write lock *before* it reads the queue, else two processes can read the same row.
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        dbapi_conn.isolation_level = None
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA busy_timeout=60000")
        cur.execute("PRAGMA synchronous=NORMAL")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        immediate = conn.get_execution_options().get("sqlite_immediate", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


def is_sqlite(engine: Engine) -> bool:
    return engine.dialect.name == "sqlite"


class Database:
    """Engine plus session factory; ``write()`` is the transaction every mutation uses."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.engine = make_engine(url)
        self._sessions = sessionmaker(bind=self.engine, expire_on_commit=False)

    @contextmanager
    def read(self):
        with self._sessions() as session:
            yield session

    @contextmanager
    def write(self, lock: bool = False):
        """A transaction; ``lock=True`` serialises it against other writers that also lock
        (SQLite: BEGIN IMMEDIATE; PostgreSQL: a transaction-scoped advisory lock), for
        read-decide-write sequences such as claims and get-or-create."""
        conn = self.engine.connect()
        if lock and is_sqlite(self.engine):
            conn = conn.execution_options(sqlite_immediate=True)
        try:
            with Session(bind=conn, expire_on_commit=False) as session, session.begin():
                if lock and not is_sqlite(self.engine):
                    session.execute(text("SELECT pg_advisory_xact_lock(724201)"))
                yield session
        finally:
            conn.close()

    def migrate(self) -> None:
        from hktex_server.storage.migrate import upgrade

        upgrade(self)

    def dispose(self) -> None:
        self.engine.dispose()
