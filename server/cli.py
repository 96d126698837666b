"""The service's commands in ``hktex``: serve, worker, demo.

Flags override the ``HKTEX_*`` environment, which overrides the defaults (Settings).
"""

from __future__ import annotations

import argparse
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hktex_server.settings import Settings


def settings_from(args: argparse.Namespace, **extra: Any) -> Settings:
    # imported here: every ``hktex`` command registers this module's parsers, and pydantic
    # settings cost ~0.1 s of each command's start (a tenth of a small ``hktex spectra``)
    from hktex_server.settings import Settings

    given = {
        "host": getattr(args, "host", None),
        "port": getattr(args, "port", None),
        "data_dir": getattr(args, "data_dir", None),
        "database_url": getattr(args, "database", None),
        "workers": getattr(args, "workers", None),
        "devices": getattr(args, "devices", None),
        **extra,
    }
    return Settings(**{k: v for k, v in given.items() if v is not None})


def cmd_serve(args: argparse.Namespace) -> dict:
    import uvicorn
    from hktex_server.app import create_app

    settings = settings_from(args)
    settings.check_bind()  # ValueError -> one stderr line, exit 2
    app = create_app(settings)
    base = f"http://{settings.host}:{settings.port}"
    print(f"hktex serve: API {base}/v1, dashboard {base}/, docs {base}/docs")
    print(f"hktex serve: data in {settings.data_dir}")
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=args.log_level,
        timeout_graceful_shutdown=settings.shutdown_grace_seconds,
    )
    _prompt_server(config).run()
    return {"stopped": True}


def _abort_compute(app) -> None:
    svc = getattr(app.state, "svc", None)
    if svc is not None and svc.compute is not None:
        svc.compute.abort()


def _prompt_server(config):
    """uvicorn's server, but SIGTERM/SIGINT also fail the in-flight queries and renders at
    once (503): uvicorn waits for open requests before it runs the app's shutdown, and a
    render can take minutes. Streams (job events) get ``shutdown_grace_seconds``."""
    import uvicorn

    class PromptServer(uvicorn.Server):
        def handle_exit(self, sig, frame) -> None:
            super().handle_exit(sig, frame)
            # not in the signal handler itself: abort takes locks the loop may hold
            threading.Thread(target=_abort_compute, args=(config.app,), daemon=True).start()

    return PromptServer(config)


def cmd_worker(args: argparse.Namespace) -> dict:
    from hktex_server.jobs.supervisor import main_loop

    settings = settings_from(args)
    if settings.workers < 1:
        raise ValueError("--workers must be >= 1 for a standalone supervisor")
    main_loop(settings)
    return {"stopped": True}


def cmd_demo(args: argparse.Namespace) -> dict:
    from hktex_server.demo import run_demo

    return run_demo(args)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", type=Path, default=None, help="data directory (HKTEX_DATA_DIR)")
    p.add_argument("--database", default=None, help="SQLAlchemy URL (HKTEX_DATABASE_URL)")
    p.add_argument("--workers", type=int, default=None, help="job slots (HKTEX_WORKERS)")
    p.add_argument("--devices", default=None, help='CUDA ids for the slots, e.g. "0,1"')


def register(subparsers: argparse._SubParsersAction) -> None:
    serve = subparsers.add_parser("serve", help="run the REST API with an embedded supervisor")
    serve.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default 8000)")
    serve.add_argument("--log-level", default="info")
    _common(serve)
    serve.set_defaults(func=cmd_serve)

    worker = subparsers.add_parser("worker", help="run a job supervisor alone (no API)")
    _common(worker)
    worker.set_defaults(func=cmd_worker)

    demo = subparsers.add_parser("demo", help="end-to-end demo through the service and client")
    from hktex_server.demo import register_demo_args

    register_demo_args(demo)
    demo.set_defaults(func=cmd_demo)
