"""Request and response models of the REST API (INTERFACES.md section 4).

These models are the API's contract: the client package mirrors them and the checked-in
OpenAPI document is generated from them, so a field here is a promise. Times are Unix epoch
seconds (float, UTC); ids are opaque strings. Floats in requests must be finite: JSON allows
``NaN`` through Python's parser, and a NaN barycentric must be a 422, not a garbage colour.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

JobState = Literal["queued", "running", "cancelling", "succeeded", "failed", "cancelled"]
SpectraState = Literal["missing", "queued", "running", "ready", "failed"]
TaskName = Literal["fit_uv", "fit_multiview"]


class _Strict(BaseModel):
    """Requests: unknown fields are an error (a typo must not silently fall back to a default),
    and values keep their JSON type: pydantic's lax mode would read ``false`` as ``0.0``,
    ``"5"`` as ``5`` and ``1`` as ``true``, silently changing what the caller meant. Strict
    mode still takes a JSON integer where a number is declared (``[1, 5]`` anisotropies), but
    not ``1.0`` where an integer is declared."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


# ---------------------------------------------------------------- requests


class SpectralConfigIn(_Strict):
    """Spectral grid and numerics; every field optional (engine defaults, ALGORITHM.md)."""

    angles: int | None = Field(None, ge=2, le=64)
    anisotropies: list[Annotated[float, Field(ge=0, le=10_000)]] | None = Field(
        None, min_length=1, max_length=64, description="eta values of the grid, ascending"
    )
    k: int | None = Field(None, ge=2, le=2048)
    k_iso: int | None = Field(None, ge=3, le=2048)
    rotation: Literal["block", "full"] | None = None
    evecs_dtype: Literal["float16", "float32"] | None = None
    tangent_field: Literal["axis_smoothed", "curvature"] | None = None


class FitParamsIn(_Strict):
    """Fitting parameters; every field optional (the preset's values, FitParams)."""

    preset: (
        Literal["default", "compact", "earlier", "later", "layered", "dense", "sigma"] | None
    ) = Field(
        None,
        description="base configuration (ALGORITHM.md §7b; 'default' = later + colour solve"
        " + error sampling + the measured changes of docs/fitting.md, densification"
        " threshold 0.012; 'compact' = default with the later threshold 0.0237: 23-36 %"
        " smaller files, 0.7-1.6 dB less on blub and spot, 0-0.2 on bob; 'layered' = the"
        " default with the layered blend, priorities trained late: +0.1 to +1.0 dB on four"
        " meshes, -0.7 to -0.9 on bob, .hkt versions 5/6;"
        " 'dense' = threshold 0.012 at the earlier t = 0.06245; 'sigma' = the default with a"
        " biharmonic scale learnt per kernel (as sigma 'per_kernel'): +0.1 to +1.7 dB over"
        " the default, .hkt versions 7/8, which a reader of ALGORITHM.md §4-5 cannot score);"
        " the other fields override it",
    )
    polish_colors: bool | None = Field(
        None, description="solve the colours by least squares for the final footprints"
    )
    sampling: Literal["uniform", "error"] | None = Field(
        None,
        description="training points: fresh area-uniform ones each step, or drawn from a pool "
        "in proportion to their residual (weighted so the loss stays the surface mean)",
    )
    blend: Literal["paper", "layered"] | None = Field(
        None,
        description="colour rule: ALGORITHM.md §5's average, or 'layered' (a learnable priority"
        " per kernel, .hkt version 5/6; docs/kernels.md)",
    )
    sigma: Literal["uniform", "per_kernel"] | None = Field(
        None,
        description="biharmonic scale: ALGORITHM.md §4's one sigma_B, or 'per_kernel' (learnt from"
        " 0.4 of the steps unless sigma_start is given; .hkt versions 7/8, which a §4-5 reader"
        " cannot score; with preset 'dense' the pair above the MLP on blub, docs/fitting.md)",
    )
    colour: Literal["constant", "linear"] | None = Field(
        None,
        description="kernel colour: ALGORITHM.md §4's constant residual, or 'linear' (a colour"
        " slope per kernel, trained from slope_start of a UV fit; .hkt versions 9/10, which a"
        " §4-5 reader cannot score; docs/fitting.md)",
    )
    kernels: int | None = Field(None, ge=1, le=1_000_000)
    max_kernels: int | None = Field(None, ge=1, le=5_000_000)
    steps: int | None = Field(None, ge=0, le=10_000_000)
    points_per_step: int | None = Field(None, ge=1, le=1_000_000)
    seed: int | None = Field(None, ge=0, le=2**31 - 1)
    densify: bool | None = None
    checkpoint_every: int | None = Field(None, ge=1, le=10_000_000)
    lr_colors: float | None = Field(None, gt=0, le=10)
    lr_theta: float | None = Field(None, gt=0, le=10)
    lr_eta: float | None = Field(None, gt=0, le=10)
    lr_threshold: float | None = Field(None, gt=0, le=10)
    lr_sharpness: float | None = Field(None, gt=0, le=10)
    lr_base: float | None = Field(None, gt=0, le=10)
    lr_centers: float | None = Field(None, gt=0, le=10)
    lr_priority: float | None = Field(None, gt=0, le=10)
    lr_sigma: float | None = Field(
        None, gt=0, le=10, description="'sigma' preset: Adam's rate on each log(sigma_j / sigma_B)"
    )
    sigma_start: float | None = Field(
        None,
        ge=0,
        le=1,
        description="'sigma' preset: fraction of the steps before the scales train",
    )
    priority_start: float | None = Field(
        None, ge=0, le=1, description="layered blend: fraction of the steps before priorities train"
    )
    lr_slopes: float | None = Field(
        None, gt=0, le=100, description="linear colours: Adam's rate on the colour slopes"
    )
    slope_start: float | None = Field(
        None,
        ge=0,
        lt=1,
        description="linear colours: fraction of the steps before the slopes train (0.4)",
    )
    eval_points: int | None = Field(
        None, ge=100, le=1_000_000, description="surface points for the final metrics (fit_uv)"
    )


class JobCreate(_Strict):
    """A fitting job. ``views_id`` (from POST /v1/views) is required for ``fit_multiview``."""

    mesh_id: str = Field(min_length=1, max_length=64)
    task: TaskName = "fit_uv"
    spectra: SpectralConfigIn = Field(default_factory=SpectralConfigIn)
    params: FitParamsIn = Field(default_factory=FitParamsIn)
    views_id: str | None = Field(None, min_length=1, max_length=64)
    priority: int = Field(0, ge=-100, le=100, description="higher runs first")

    @model_validator(mode="after")
    def _views_for_multiview(self) -> JobCreate:
        if self.task == "fit_multiview" and not self.views_id:
            raise ValueError("fit_multiview needs views_id (upload the views with POST /v1/views)")
        return self


#: Face ids are int32 in the engine; anything past this cannot name a face (and a JSON integer
#: past 64 bits must be a 422, not an OverflowError in numpy).
MAX_FACE_ID = 2**31 - 1
#: Coordinates beyond this overflow float32 arithmetic in the closest-point search; no mesh
#: file in any unit is that large.
MAX_COORDINATE = 1e15

FaceId = Annotated[int, Field(ge=0, le=MAX_FACE_ID)]
Barycentric = Annotated[float, Field(ge=-1.0, le=2.0)]
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]


class AlbedoRequest(_Strict):
    """Either surface locations (``face_ids`` + ``barycentrics``) or ``points`` in file units.

    Every number is range-checked here, so out-of-range values are a 422 naming the field
    (face ids fit int32, barycentrics lie near [0, 1], coordinates are finite and bounded)."""

    face_ids: list[FaceId] | None = None
    barycentrics: list[list[Barycentric]] | None = None
    points: list[list[Coordinate]] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> AlbedoRequest:
        by_face = self.face_ids is not None or self.barycentrics is not None
        if by_face == (self.points is not None):
            raise ValueError(
                "give either face_ids + barycentrics, or points (not both, not neither)"
            )
        if by_face and (self.face_ids is None or self.barycentrics is None):
            raise ValueError("face_ids and barycentrics go together")
        return self


# ---------------------------------------------------------------- responses


class MeshRecord(BaseModel):
    id: str
    name: str
    n_vertices: int
    n_faces: int
    has_texture: bool
    content_hash: str = Field(description="hash of the canonical geometry (keys spectra caches)")
    bytes: int = Field(description="uploaded bytes (mesh + texture)")
    checks: dict[str, Any] = Field(description="validation checks passed and mesh statistics")
    created_at: float


class MeshList(BaseModel):
    items: list[MeshRecord]


class SpectraRecord(BaseModel):
    """Spectra are shared per (mesh content, config); ``job_id`` is set while one computes."""

    id: str
    mesh_hash: str
    config: dict[str, Any]
    config_hash: str
    state: SpectraState
    job_id: str | None = None
    error: str | None = None
    summary: dict[str, Any] | None = None
    created_at: float
    updated_at: float


class JobProgress(BaseModel):
    step: int = 0
    total: int = 0
    stage: str | None = Field(None, description='phase of the task, e.g. "grid", "fit"')
    loss: float | None = None
    kernel_count: int | None = None
    metrics: dict[str, float] = Field(default_factory=dict)
    updated_at: float | None = None


class JobResult(BaseModel):
    kernelset_id: str | None = None
    spectra_id: str | None = None


class JobRecord(BaseModel):
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
    created_at: float
    started_at: float | None = None
    finished_at: float | None = None


class JobList(BaseModel):
    items: list[JobRecord]


class KernelSetRecord(BaseModel):
    id: str
    job_id: str | None = None
    mesh_id: str | None = None
    spectra_id: str
    n_kernels: int
    bytes: int = Field(description="size of the .hkt file as stored")
    metrics: dict[str, Any] = Field(
        default_factory=dict,
        description="the fit's metrics (surface_psnr, kernels, steps, bytes_*, ...); "
        "GET /v1/kernelsets/{id} adds loss_curve: at most 200 [step, mean loss] pairs "
        "over the whole fit (null where a step's loss was not finite); lists leave it out",
    )
    manifest: dict[str, Any] = Field(default_factory=dict)
    created_at: float


class ViewsRecord(BaseModel):
    id: str
    n_files: int
    bytes: int = Field(description="uncompressed bytes of the extracted dataset")
    created_at: float


class AlbedoResponse(BaseModel):
    count: int
    colors: list[list[float]] = Field(description="(P, 3) RGB in the kernel set's colour space")


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class QueueDepth(BaseModel):
    queued: int
    running: int


class Info(BaseModel):
    version: str
    devices: list[str]
    workers: int
    queue: QueueDepth
    owner: str
    limits: dict[str, int]
