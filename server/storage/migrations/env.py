"""Alembic environment: runs on the connection hktex_server.storage.migrate hands over, or on the URL
of alembic.ini when a developer runs the alembic command line."""

from __future__ import annotations

from alembic import context
from hktex_server.storage.db import Base
from sqlalchemy import create_engine

target_metadata = Base.metadata
config = context.config


def _run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata)
    with context.begin_transaction():
        context.run_migrations()


connection = config.attributes.get("connection")
if connection is not None:
    _run(connection)
else:
    with create_engine(config.get_main_option("sqlalchemy.url")).connect() as conn:
        _run(conn)
