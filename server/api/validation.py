"""Mesh validation of uploads in a child process with a hard timeout.

Why a process: a parser stuck on hostile bytes cannot be stopped on a thread (Python has no
thread kill), so a thread with a timeout answers the uploader but keeps burning a core and
memory until it finishes, if ever. A process can be killed. Why a forkserver with the engine
preloaded: importing the mesh stack (numpy, scipy, trimesh, PIL) costs ~1.3 s here; forking
from a server that already holds it costs milliseconds, and forking from the single-threaded
forkserver (not from the threaded API process) is safe.

Only a small summary crosses back (the API stores counts, the content hash and the checks;
workers reload the mesh from the stored blob).
"""

from __future__ import annotations

import multiprocessing
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_CTX: Any = None
_CTX_LOCK = threading.Lock()


@dataclass(frozen=True)
class MeshSummary:
    content_hash: str
    n_vertices: int
    n_faces: int
    has_texture: bool
    has_uvs: bool
    scale: float


class ValidationTimeout(Exception):
    """The validation overran its time limit; its process was killed."""


class InvalidMesh(Exception):
    """The mesh was refused; ``input_error`` when the engine named the reason (HKTexError,
    ValueError), else a parser crashed on it."""

    def __init__(self, message: str, input_error: bool) -> None:
        super().__init__(message)
        self.input_error = input_error


#: What the forkserver imports once: the mesh stack for validation, the query engine (numpy,
#: torch) for the compute workers (``compute_child``), and the job code with the engine's
#: spectra and UV fitting for warm job processes (``supervisor._fork_job``); all fork from it.
PRELOAD = [
    "__main__",
    "hktex_engine.geometry.mesh",
    "torch",
    "faiss",  # imported lazily by the KNN and by set_thread_counts: 0.8 s each time otherwise
    "hktex_engine.kernels.query",
    "hktex_server.api.compute_preload",  # the compiled blend, built once for every worker
    "hktex_server.api.compute_child",
    "hktex_server.jobs.worker_main",
    "hktex_server.jobs.tasks",
    "hktex_engine.spectra.grid",
    "hktex_engine.kernels.hkt",
    "hktex_engine.fitting.uv",
]


def context() -> Any:
    """The service's one forkserver context (validation children and compute workers)."""
    global _CTX
    with _CTX_LOCK:
        if _CTX is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(PRELOAD)
            _CTX = ctx
        return _CTX


_context = context


_READY = threading.Event()
_WARMING = threading.Lock()


def _noop() -> None:
    """A child that does nothing: its start proves the forkserver has finished preloading."""


def warm() -> None:
    """Start the forkserver now (a background thread at service start) and fork one empty
    child, so the first upload, compute worker or warm job does not pay its start (the
    preloads: several seconds on a loaded host). Failures only mean the first user starts it."""
    if not _WARMING.acquire(blocking=False):
        return  # another thread is already warming it
    try:
        ctx = context()
        from multiprocessing import forkserver

        forkserver.ensure_running()
        child = ctx.Process(target=_noop, daemon=True, name="hktex-forkserver-probe")
        child.start()
        child.join(300)
        _READY.set()
    except Exception:  # noqa: BLE001 - best effort; the real users report real failures
        pass
    finally:
        _WARMING.release()


def ready() -> bool:
    """Whether the forkserver has preloaded (a fork from it now costs milliseconds)."""
    return _READY.is_set()


def warm_in_background() -> None:
    if not _READY.is_set():
        threading.Thread(target=warm, name="hktex-forkserver-warm", daemon=True).start()


def _child(conn: Any, path: str, texture: str | None, max_vertices: int, file_type: str | None):
    from hktex_engine.errors import HKTexError
    from hktex_engine.geometry.mesh import load_mesh

    try:
        mesh = load_mesh(path, texture=texture, max_vertices=max_vertices, file_type=file_type)
        conn.send(
            (
                "ok",
                MeshSummary(
                    content_hash=mesh.content_hash,
                    n_vertices=int(mesh.n_vertices),
                    n_faces=int(mesh.n_faces),
                    has_texture=bool(mesh.has_texture),
                    has_uvs=mesh.corner_uvs is not None,
                    scale=float(mesh.scale),
                ),
            )
        )
    except BaseException as exc:  # everything goes back as a reason; nothing else to do here
        input_error = isinstance(exc, HKTexError | ValueError)
        conn.send(
            ("error", f"{type(exc).__name__}: {' '.join(str(exc).split())[:500]}", input_error)
        )
    finally:
        conn.close()


def validate_mesh(
    path: Path,
    texture: Path | None,
    max_vertices: int,
    file_type: str | None,
    timeout: float,
) -> MeshSummary:
    """Load and validate ``path`` in a child process; kill it after ``timeout`` seconds.

    Blocking: call it from a worker thread. Raises :class:`ValidationTimeout` or
    :class:`InvalidMesh`.
    """
    ctx = _context()
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=_child,
        args=(sender, str(path), str(texture) if texture else None, max_vertices, file_type),
        daemon=True,
    )
    proc.start()
    sender.close()
    try:
        if not receiver.poll(timeout):
            raise ValidationTimeout(f"mesh validation took longer than {timeout:g} s")
        try:
            message = receiver.recv()
        except EOFError:  # the child died without answering (a parser crash, OOM kill)
            proc.join(5)
            raise InvalidMesh(
                f"unreadable mesh: the validator died (exit code {proc.exitcode})", False
            ) from None
    finally:
        receiver.close()
        if proc.is_alive():
            proc.kill()
        proc.join(5)
    if message[0] == "ok":
        return message[1]
    raise InvalidMesh(message[1], message[2])
