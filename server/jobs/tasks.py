"""What a worker process does for each task type, calling the engine.

The engine is imported lazily, inside the worker process only, so the API process stays
light. Each task returns an :class:`Outcome`: the job's result ids plus a callback that
records the product (spectra row, kernel-set row) in the same transaction that marks the job
succeeded, and a ``discard`` that removes a product nobody will record.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hktex_server.settings import Settings
from hktex_server.storage.blobs import BlobStore, dir_bytes
from hktex_server.storage.db import (
    Database,
    JobRow,
    KernelSetRow,
    MeshRow,
    SpectraRow,
    ViewsRow,
    now,
)
from sqlalchemy.orm import Session


@dataclass
class TaskContext:
    settings: Settings
    db: Database
    job: JobRow
    progress: Any  # hktex_engine.progress.Progress

    @property
    def store(self) -> BlobStore:
        return BlobStore(self.settings.data_dir)


@dataclass
class Outcome:
    result: dict[str, Any]
    on_success: Callable[[Session, JobRow], None] | None = None
    discard: Callable[[], None] = field(default=lambda: None)


def run(ctx: TaskContext) -> Outcome:
    runners = {
        "spectra": run_spectra,
        "fit_uv": run_fit,
        "fit_multiview": run_fit,
        "sleep": run_sleep,
    }
    runner = runners.get(ctx.job.task)
    if runner is None:
        raise ValueError(f"unknown task {ctx.job.task!r}")
    return runner(ctx)


# ---------------------------------------------------------------- spectra


def run_spectra(ctx: TaskContext) -> Outcome:
    from hktex_engine.config import SpectralConfig
    from hktex_engine.spectra.grid import SpectraCache

    row = _get(ctx.db, SpectraRow, ctx.job.spectra_id, "spectra record")
    config = SpectralConfig.from_dict(row.config)
    mesh = _load_mesh_with_hash(ctx, row.mesh_hash)
    cache = SpectraCache(ctx.store.root / "spectra")
    spectra = cache.get_or_compute(mesh, config, progress=ctx.progress)
    path = Path(spectra.path).resolve()
    summary = {
        "n_vertices": int(spectra.vertices.shape[0]),
        "n_faces": int(spectra.faces.shape[0]),
        "k": int(spectra.evals.shape[1]),
        "k_iso": int(spectra.iso_evals.shape[0]),
        "angles": int(len(spectra.grid_theta)),
        "anisotropies": [float(e) for e in spectra.grid_eta],
        "bytes": dir_bytes(path),
        "timings": _json_safe(spectra.manifest.get("timings", {})),
    }
    rel = ctx.store.rel(path)

    def record(s: Session, job: JobRow) -> None:
        target = s.get(SpectraRow, job.spectra_id)
        target.state, target.path, target.summary, target.error = "ready", rel, summary, None
        target.updated_at = now()

    return Outcome({"spectra_id": row.id}, record)


def _load_mesh_with_hash(ctx: TaskContext, mesh_hash: str, prefer_id: str | None = None):
    """The job's own mesh, or any stored mesh with this geometry (the spectra are shared)."""
    from sqlalchemy import select

    from hktex_engine.geometry.mesh import load_mesh

    with ctx.db.read() as s:
        row = (
            s.get(MeshRow, prefer_id or ctx.job.mesh_id) if (prefer_id or ctx.job.mesh_id) else None
        )
        if row is None or row.mesh_hash != mesh_hash:
            row = s.execute(
                select(MeshRow).where(MeshRow.mesh_hash == mesh_hash).limit(1)
            ).scalar_one_or_none()
    if row is None:
        raise FileNotFoundError("the mesh of this job was deleted")
    # spectra need the geometry only: the texture is not decoded
    return load_mesh(
        ctx.store.abs(row.mesh_blob), max_vertices=ctx.settings.max_vertices, read_texture=False
    )


# ---------------------------------------------------------------- fitting


def fit_params(raw: dict[str, Any]):
    """FitParams from the API's params object (its preset, then only the fields given)."""
    from hktex_engine.config import fit_params_from

    return fit_params_from(raw)


def run_fit(ctx: TaskContext) -> Outcome:
    from hktex_engine.fitting.loop import loss_curve
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import load_spectra

    job = ctx.job
    spectra_row = _get(ctx.db, SpectraRow, job.spectra_id, "spectra record")
    if spectra_row.state != "ready" or not spectra_row.path:
        raise ValueError(f"spectra {spectra_row.id} are not ready ({spectra_row.state})")
    mesh_row = _get(ctx.db, MeshRow, job.mesh_id, "mesh")
    store = ctx.store
    texture = store.abs(mesh_row.texture_blob) if mesh_row.texture_blob else None
    mesh = load_mesh(
        store.abs(mesh_row.mesh_blob), texture=texture, max_vertices=ctx.settings.max_vertices
    )
    spectra = load_spectra(store.abs(spectra_row.path), expect_mesh_hash=mesh.content_hash)
    params = fit_params(job.params.get("params", {}))
    checkpoints = checkpoint_dir(ctx.settings, job.id)  # a retried job resumes from here
    if job.task == "fit_uv":
        from hktex_engine.fitting.uv import fit_uv

        extra = {}
        eval_points = job.params.get("params", {}).get("eval_points")
        eval_points = eval_points or ctx.settings.fit_eval_points
        if eval_points is not None:
            extra["eval_points"] = int(eval_points)
        result = fit_uv(
            mesh, spectra, params, progress=ctx.progress, checkpoint_dir=checkpoints, **extra
        )
    else:
        from hktex_engine.fitting.multiview import fit_multiview
        from hktex_engine.fitting.views import load_views

        views_row = _get(ctx.db, ViewsRow, job.views_id, "views dataset")
        views = load_views(store.abs(views_row.path))
        result = fit_multiview(
            mesh, spectra, views, params, progress=ctx.progress, checkpoint_dir=checkpoints
        )
    tmp = store.temp_path(".hkt")
    save_hkt(result.kernelset, tmp)
    rel, _digest, size = store.publish_file(tmp, "kernelsets", ".hkt")
    kernelset_id = f"kst_{job.id.removeprefix('job_')}"
    metrics = _json_safe(dict(result.metrics or {}))
    # The record, not the .hkt: the curve would add bytes to every file and no reader needs it.
    last_step = int(metrics.get("steps") or len(result.losses))
    metrics["loss_curve"] = _json_safe(loss_curve(result.losses, last_step))  # NaN -> null
    n_kernels = len(result.kernelset)
    ks = result.kernelset
    manifest = _json_safe(
        {
            "mesh_hash": ks.mesh_hash,
            "config_hash": ks.config_hash,
            "color_space": ks.color_space,
            "kernel_config": ks.kernel_config.to_dict(),
            "task": job.task,
        }
    )

    def record(s: Session, done: JobRow) -> None:
        s.add(
            KernelSetRow(
                id=kernelset_id,
                owner=done.owner,
                job_id=done.id,
                mesh_id=done.mesh_id,
                spectra_id=done.spectra_id,
                path=rel,
                bytes=size,
                n_kernels=n_kernels,
                metrics=metrics,
                manifest=manifest,
                created_at=now(),
            )
        )

    return Outcome({"kernelset_id": kernelset_id, "spectra_id": spectra_row.id}, record)


# ---------------------------------------------------------------- test task


def run_sleep(ctx: TaskContext) -> Outcome:
    """Internal test task (only with ``enable_test_tasks``): sleeps in steps, so the queue,
    cancel, kill and reaper tests do not depend on the engine's speed. ``ignore_cancel``
    makes it deaf to the cooperative stop, to exercise SIGTERM/SIGKILL."""
    from hktex_engine.progress import check_cancel

    if not ctx.settings.enable_test_tasks:
        raise ValueError("the 'sleep' task is only available with HKTEX_ENABLE_TEST_TASKS=1")
    p = ctx.job.params
    steps, seconds = int(p.get("steps", 10)), float(p.get("seconds", 1.0))
    marker = p.get("marker")
    if marker:  # lets a test count how many processes ever ran this job
        with open(marker, "a") as f:
            gpus = os.environ.get("CUDA_VISIBLE_DEVICES", "?")
            f.write(f"{ctx.job.id} {ctx.job.attempts} {gpus or '-'}\n")
    if p.get("ignore_sigterm"):  # a process wedged in native code: only SIGKILL stops it
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    for step in range(steps):
        if not p.get("ignore_cancel"):
            check_cancel(ctx.progress)
        time.sleep(seconds / max(steps, 1))
        ctx.progress.update(step + 1, steps, loss=1.0 / (step + 1), kernels=step)
    if p.get("crash"):  # a worker dying without a word (segfault, OOM kill)
        os._exit(int(p["crash"]))
    if p.get("fail"):
        raise ValueError(str(p["fail"]))
    return Outcome({})


# ---------------------------------------------------------------- helpers


def checkpoint_dir(settings: Settings, job_id: str) -> Path:
    return Path(settings.data_dir).resolve() / "checkpoints" / job_id


def drop_checkpoints(settings: Settings, job_id: str) -> None:
    """Once a job is final its checkpoints serve nobody (a new job has a new id)."""
    shutil.rmtree(checkpoint_dir(settings, job_id), ignore_errors=True)


def _get(db: Database, model: type, key: str | None, what: str):
    with db.read() as s:
        row = s.get(model, key) if key else None
    if row is None:
        raise FileNotFoundError(f"{what} {key!r} no longer exists")
    return row


def _json_safe(value: Any) -> Any:
    """Metrics as JSON: numpy scalars to floats, non-finite numbers to None."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, bool | str) or value is None:
        return value
    try:
        f = float(value)
    except (TypeError, ValueError):
        return str(value)
    if isinstance(value, int):
        return value
    return f if math.isfinite(f) else None
