"""Typed records of the HKTex REST API (INTERFACES.md section 4).

These mirror the service's response schemas (``hktex_server.schemas``) but are declared here
again on purpose: the client must install without the server (no FastAPI, torch, scipy), so it
cannot import them. Every model ignores unknown fields, so a newer server that adds a field
does not break an older client; a field the client needs and the server lacks is a test
failure in ``tests/test_client.py``, which runs both against each other.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

JobState = Literal["queued", "running", "cancelling", "succeeded", "failed", "cancelled"]
FINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


class _Record(BaseModel):
    model_config = ConfigDict(extra="ignore", populate_by_name=True, protected_namespaces=())


class MeshRecord(_Record):
    """An uploaded, validated mesh (content-addressed: the same bytes give the same id)."""

    id: str
    name: str | None = None
    n_vertices: int | None = None
    n_faces: int | None = None
    has_texture: bool = False
    has_uvs: bool | None = None
    content_hash: str | None = None
    size_bytes: int | None = None
    checks: dict[str, Any] = Field(default_factory=dict)
    created_at: datetime | None = None


class SpectralConfigIn(_Record):
    """A spectral config as the API takes it; every field optional (server defaults apply)."""

    angles: int | None = None
    anisotropies: list[float] | None = None
    k: int | None = None
    k_iso: int | None = None


class SpectraRecord(_Record):
    """A spectra artefact for (mesh, config): ``ready`` when cached, else computed by a job."""

    id: str
    mesh_id: str | None = None
    state: str
    config: dict[str, Any] = Field(default_factory=dict)
    job_id: str | None = None
    summary: dict[str, Any] = Field(default_factory=dict)
    error: str | None = None
    created_at: datetime | None = None

    @property
    def ready(self) -> bool:
        return self.state in ("ready", "succeeded")


class JobProgress(_Record):
    """Where a job is: ``step`` of ``total`` with the latest loss and metrics."""

    step: int = 0
    total: int = 0
    loss: float | None = None
    kernels: int | None = None
    metrics: dict[str, Any] = Field(default_factory=dict)
    message: str | None = None
    updated_at: datetime | None = None

    @property
    def fraction(self) -> float:
        return self.step / self.total if self.total else 0.0


class JobRecord(_Record):
    """A queued, running or finished job (spectra, fit_uv or fit_multiview)."""

    id: str
    task: str
    state: JobState
    mesh_id: str | None = None
    progress: JobProgress = Field(default_factory=JobProgress)
    error: str | None = None
    spectra_id: str | None = None
    kernelset_id: str | None = None
    result: dict[str, Any] = Field(default_factory=dict)
    attempts: int | None = None
    created_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None

    @property
    def done(self) -> bool:
        return self.state in FINAL_STATES


class KernelSetRecord(_Record):
    """A fitted kernel set: its provenance, size and metrics."""

    id: str
    mesh_id: str | None = None
    spectra_id: str | None = None
    job_id: str | None = None
    n_kernels: int | None = None
    size_bytes: int | None = None
    metrics: dict[str, Any] = Field(default_factory=dict)
    manifest: dict[str, Any] = Field(default_factory=dict)
    created_at: datetime | None = None


class Health(_Record):
    status: str


class Info(_Record):
    version: str | None = None
    devices: list[Any] = Field(default_factory=list)
    workers: int | None = None
    queue_depth: int | None = None
    limits: dict[str, Any] = Field(default_factory=dict)
