"""Apply the Alembic migrations at startup, from the installed package (no alembic.ini needed).

Several processes (API, supervisors on other hosts) may start at once against one database;
the upgrade runs inside a locked transaction so exactly one of them creates the tables and
the others find the schema at head.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from alembic import command
from alembic.config import Config
from sqlalchemy import text

if TYPE_CHECKING:
    from hktex_server.storage.db import Database

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def alembic_config() -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    return cfg


def upgrade(database: Database) -> None:
    """Bring the schema to head; serialised across processes by the database's own lock."""
    from hktex_server.storage.db import is_sqlite

    cfg = alembic_config()
    conn = database.engine.connect()
    try:
        if is_sqlite(database.engine):
            conn = conn.execution_options(sqlite_immediate=True)
        with conn.begin():
            if not is_sqlite(database.engine):
                conn.execute(text("SELECT pg_advisory_xact_lock(724200)"))
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")
    finally:
        conn.close()
