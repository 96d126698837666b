"""The contract between long engine tasks and whoever runs them (CLI, worker process).

A task calls ``progress.update(...)`` as it goes and checks ``progress.should_stop()`` at safe
points; it raises :class:`~hktex_engine.errors.Cancelled` when asked to stop. The engine never
knows whether a terminal, a database row or nothing at all is listening.
"""

from __future__ import annotations

from typing import Any, Protocol

from hktex_engine.errors import Cancelled


class Progress(Protocol):
    def update(self, step: int, total: int, **metrics: Any) -> None:
        """Report that ``step`` of ``total`` units are done, with any scalar metrics."""

    def should_stop(self) -> bool:
        """True once the owner asked the task to stop."""


class NullProgress:
    """Progress sink for library calls nobody watches."""

    def update(self, step: int, total: int, **metrics: Any) -> None:
        return None

    def should_stop(self) -> bool:
        return False


def check_cancel(progress: Progress | None) -> None:
    """Raise :class:`Cancelled` if the task's owner asked it to stop."""
    if progress is not None and progress.should_stop():
        raise Cancelled("cancelled by request")
