"""Typed records of the HKTex REST API (INTERFACES.md section 4).

These mirror the service's response schemas (``hktex_server.api.schemas``) but are declared here
again on purpose: the client must install without the server (no FastAPI, torch, scipy), so it
cannot import them. Every model ignores unknown fields, so a newer server that adds a field
does not break an older client; a field the client needs and the server lacks is a test
failure in ``tests/test_client.py``, which compares both field sets. Times are Unix epoch
seconds (UTC), as the service sends them.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

JobState = Literal["queued", "running", "cancelling", "succeeded", "failed", "cancelled"]
SpectraState = Literal["missing", "queued", "running", "ready", "failed"]
FINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


class _Record(BaseModel):
    model_config = ConfigDict(extra="ignore", populate_by_name=True, protected_namespaces=())


class MeshRecord(_Record):
    """An uploaded, validated mesh (content-addressed: the same bytes give the same id)."""

    id: str
    name: str = ""
    n_vertices: int = 0
    n_faces: int = 0
    has_texture: bool = False
    content_hash: str = ""
    bytes: int = 0
    checks: dict[str, Any] = Field(default_factory=dict)
    created_at: float | None = None


class SpectraRecord(_Record):
    """Spectra shared per (mesh content, config): ``ready`` when cached, else a job computes."""

    id: str
    state: SpectraState
    mesh_hash: str = ""
    config: dict[str, Any] = Field(default_factory=dict)
    config_hash: str = ""
    job_id: str | None = None
    error: str | None = None
    summary: dict[str, Any] | None = None
    created_at: float | None = None
    updated_at: float | None = None

    @property
    def ready(self) -> bool:
        return self.state == "ready"


class JobProgress(_Record):
    """Where a job is: ``step`` of ``total`` with the latest loss, kernel count and metrics."""

    step: int = 0
    total: int = 0
    stage: str | None = None
    loss: float | None = None
    kernel_count: int | None = None
    metrics: dict[str, float] = Field(default_factory=dict)
    updated_at: float | None = None

    @property
    def fraction(self) -> float:
        return self.step / self.total if self.total else 0.0


class JobResult(_Record):
    kernelset_id: str | None = None
    spectra_id: str | None = None


class JobRecord(_Record):
    """A queued, running or finished job (spectra, fit_uv or fit_multiview)."""

    id: str
    task: str
    state: JobState
    mesh_id: str | None = None
    spectra_id: str | None = None
    views_id: str | None = None
    priority: int = 0
    attempts: int = 0
    max_attempts: int = 1
    cancel_requested: bool = False
    device: str | None = None
    progress: JobProgress = Field(default_factory=JobProgress)
    error: str | None = None
    result: JobResult = Field(default_factory=JobResult)
    params: dict[str, Any] = Field(default_factory=dict)
    created_at: float | None = None
    started_at: float | None = None
    finished_at: float | None = None

    @property
    def done(self) -> bool:
        return self.state in FINAL_STATES

    @property
    def kernelset_id(self) -> str | None:
        return self.result.kernelset_id


class KernelSetRecord(_Record):
    """A fitted kernel set: its provenance, size and metrics."""

    id: str
    job_id: str | None = None
    mesh_id: str | None = None
    spectra_id: str | None = None
    n_kernels: int = 0
    bytes: int = 0
    metrics: dict[str, Any] = Field(default_factory=dict)
    manifest: dict[str, Any] = Field(default_factory=dict)
    created_at: float | None = None


class BakeInfo(_Record):
    """What a viewer bake of a kernel set produced (``GET /v1/kernelsets/{id}/bake``)."""

    kernelset_id: str
    resolution: int
    atlas: str = "mesh"
    coverage: float = 0.0
    layers: list[str] = Field(default_factory=list)
    error_scale: float | None = None
    error_rms: float | None = None
    glb_bytes: int = 0
    seconds: float = 0.0


class ViewsRecord(_Record):
    """An uploaded multi-view dataset (images + cameras) for ``fit_multiview``."""

    id: str
    n_files: int = 0
    bytes: int = 0
    created_at: float | None = None


class Health(_Record):
    status: str


class QueueDepth(_Record):
    queued: int = 0
    running: int = 0


class Info(_Record):
    version: str = ""
    devices: list[str] = Field(default_factory=list)
    workers: int = 0
    queue: QueueDepth = Field(default_factory=QueueDepth)
    owner: str = ""
    limits: dict[str, int] = Field(default_factory=dict)
