"""Kernel sets and their evaluation (ALGORITHM.md sections 4 and 5).

:class:`KernelSet` is the plain numpy record a ``.hkt`` file holds. :class:`HeatKernelModel`
holds the same kernels as torch parameters on a device and evaluates albedo at surface points:

    h_j(y) = sum_k exp(-t lambda_k) phi_k(c_j) phi_k(y)      spectrum at (theta_j, s_j)
    w_j(y) = exp(-d_B(c_j, y)^2 / (2 sigma_B^2))
    r_j(y) = h_j(y) w_j(y) / h_j(c_j)
    rho_j(y) = S(r_j(y); eps_j, k_j)
    albedo(y) = clamp(a_0 + sum_{top K_c} rho_j a_j / max(1, sum rho_j), 0, 1)

or, with ``KernelConfig.blend = "layered"``, the layered blend of ``kernels.blending`` (a
learnable priority per kernel decides the shares where kernels overlap), and with
``KernelConfig.sigma = "per_kernel"`` a scale ``sigma_j = sigma_B s_j`` per kernel in ``w_j``
(the learnt ratio ``s_j`` is the row ``log_sigma = log s_j``).

Evaluation for P points and K_s candidates each: the point's eigenfunctions on every grid node
``Phi_y`` (P, G, K) come from three contiguous vertex rows; each kernel's spectral coefficients
``coef_j = exp(-t lambda^j) * phi^j(c_j)`` (K,) are per kernel; one batched matmul gives
``coef_j . Phi_y[g]`` for all G nodes and the four bilinear nodes of kernel j are picked from
it. That trades G/4 times more multiply-adds than strictly needed for dense BLAS instead of a
(P, K_s, 4, K) gather, which measured slower (docs/kernels.md, "Decisions").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import torch
from torch import nn

from hktex_engine.config import SIGMA_RATIO_RANGE, SLOPE_RANGE, KernelConfig
from hktex_engine.errors import KernelSetError
from hktex_engine.kernels import blending, fused_blend, fused_pairs, fused_rank, fused_terms
from hktex_engine.kernels.knn import CandidateSearch
from hktex_engine.kernels.ranking import nearest_by_rule, select_by_rule
from hktex_engine.kernels.tables import (
    FaceTables,
    VertexTables,
    all_face_tables,
    build_tables,
    face_tables,
    point_distances,
    point_responses,
    star_radius,
)
from hktex_engine.spectra.interpolation import RowCache, SpectralField

THETA_RANGE = (0.0, math.pi)
ETA_RANGE = (1.0, 200.0)
#: The threshold's range is [0.3, 1); projection keeps it a hair below 1.
THRESHOLD_RANGE = (0.3, 1.0 - 1e-4)
SHARPNESS_RANGE = (10.0, 200.0)
COLOR_RANGE = (-1.0, 1.0)
PRIORITY_RANGE = blending.PRIORITY_RANGE
#: ``log(sigma_j / sigma_B)``'s box (``KernelConfig.sigma = "per_kernel"``).
LOG_SIGMA_RANGE = (math.log(SIGMA_RATIO_RANGE[0]), math.log(SIGMA_RATIO_RANGE[1]))
BASE_RANGE = (0.0, 1.0)
#: How ``h_j(y)`` is computed without gradients: "auto" picks per batch between the node
#: matmul ("bmm") and shared (vertex, kernel) pairs ("vertex"); see ``_h_by_vertex_pairs``.
PAIR_PATH = "auto"
#: Relative cost of one gathered eigenvector row against one matmul row (measured, see docs).
VERTEX_PATH_COST = 24
#: (vertex, kernel) pairs per gathered block in the vertex path.
PAIR_CHUNK = 16384
#: Points per checkpointed chunk when a differentiable batch is larger than this.
GRAD_CHUNK_POINTS = 1024
#: Bytes the training path may keep of the centres' gathered eigenvector rows between steps
#: (12 K per kernel: 123 MB for 10k kernels at K = 256 float32); above it they are gathered
#: each step.
ROWS_CACHE_BYTES = 256 * 2**20
#: Extra nearest centres fetched before the exact per-pair cut to ``K_s`` (see ``_exact_cut``).
KNN_MARGIN = 8
#: No-grad queries through per-vertex candidate tables (``kernels.tables``): "auto" (whole-
#: mesh tables when built, else per batch when it has this many points per distinct vertex),
#: "always" or "never" (the per-point KNN path).
TABLE_PATH = "auto"
TABLE_POINTS_PER_VERTEX = 2.0
#: The same when the per-point path ranks compiled (CPU float32, ``kernels.fused_rank``,
#: float16 grids read in place). Since the tables are built compiled too
#: (``kernels.fused_tables``) a batch's own cost ~35 us a vertex against ~12 us a point on
#: the per-point path, so they pay from ~3-5 points per distinct vertex (measured
#: 2026-12-06, 8,192-vertex torus, 10,000 kernels, points on a strip of faces, one call:
#: per-point faster at 2.2 per vertex, 0.031 against 0.037 s; tables at 6.1, 0.023 against
#: 0.028, and at 34, 0.085 against 0.258; docs/kernels.md, "Candidate tables, compiled").
TABLE_POINTS_PER_VERTEX_COMPILED = 4.0
#: Largest whole-mesh candidate tables :meth:`HeatKernelModel.prepare_tables` keeps.
TABLES_MAX_BYTES = 1024 * 2**20
#: Relative round-off of the index's distances (float32 ``|q|^2 + |c|^2 - 2 q.c``) against
#: ``|q|^2 + max |c|^2``; generous, it only decides when a row is cut over all centres.
CUT_ROUNDOFF = 1e-5
#: Bytes of one chunk of per-pair differences in :func:`_exhaustive_cut`.
EXHAUSTIVE_CHUNK_BYTES = 32 * 2**20
#: Builds of the compiled search's cluster grouping between fresh assignments (the others
#: keep the last assignment and recompute centroids and radii; any grouping is exact).
CLUSTER_REGROUP = 50
#: Tolerance on barycentric rows (sum to one, no negative entries) when validating.
BARY_TOL = 1e-3


@dataclass
class KernelSet:
    """A kernel set as stored in a ``.hkt`` file (INTERFACES.md section 2), numpy arrays."""

    face_ids: np.ndarray  # (N,) int64, faces of the normalised mesh
    barycentrics: np.ndarray  # (N, 3), rows sum to one
    theta: np.ndarray  # (N,) in [0, pi]
    eta: np.ndarray  # (N,) in [1, 200]
    threshold: np.ndarray  # (N,) in [0.3, 1)
    sharpness: np.ndarray  # (N,) in [10, 200]
    colors: np.ndarray  # (N, 3) residuals in [-1, 1]
    base_color: np.ndarray  # (3,) in [0, 1]
    kernel_config: KernelConfig = field(default_factory=KernelConfig)
    #: (N,) in PRIORITY_RANGE for the layered blend (kernel_config.blend); None for the paper's
    priority: np.ndarray | None = None
    #: (N,) ``sigma_j / sigma_B`` in SIGMA_RATIO_RANGE when kernel_config.sigma is
    #: "per_kernel"; None for §4's one sigma_B
    sigma_ratio: np.ndarray | None = None
    #: (N, 9) colour slopes ``G_j`` (row-major: channel, then normalised-frame axis) in
    #: SLOPE_RANGE when kernel_config.colour is "linear"; None for §4's constant colours
    color_slopes: np.ndarray | None = None
    mesh_hash: str = ""
    config_hash: str = ""
    color_space: str = "srgb"
    fitting: dict = field(default_factory=dict)
    extras: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(np.asarray(self.face_ids).shape[0])

    def validate(self, n_faces: int | None = None) -> None:
        """Raise :class:`KernelSetError` unless shapes, ranges and finiteness all hold."""
        n = len(self)
        shapes = {
            "face_ids": (n,),
            "barycentrics": (n, 3),
            "theta": (n,),
            "eta": (n,),
            "threshold": (n,),
            "sharpness": (n,),
            "colors": (n, 3),
            "base_color": (3,),
        }
        for name, shape in shapes.items():
            arr = np.asarray(getattr(self, name))
            if arr.shape != shape:
                raise KernelSetError(f"member {name!r} has shape {arr.shape}, expected {shape}")
            if arr.dtype.kind not in "biuf":
                raise KernelSetError(f"member {name!r} has non-numeric dtype {arr.dtype}")
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                raise KernelSetError(f"member {name!r} contains NaN or infinity")
        if n == 0:
            raise KernelSetError("the kernel set is empty")
        self._validate_extensions(n)
        if np.asarray(self.face_ids).dtype.kind == "f":
            raise KernelSetError("member 'face_ids' must be integers")
        fid = np.asarray(self.face_ids)
        if fid.min() < 0 or (n_faces is not None and fid.max() >= n_faces):
            raise KernelSetError(
                f"face ids out of range [0, {n_faces if n_faces is not None else 'inf'})"
            )
        bary = np.asarray(self.barycentrics, dtype=np.float64)
        if bary.min() < -BARY_TOL or np.abs(bary.sum(axis=1) - 1).max() > BARY_TOL:
            raise KernelSetError("barycentrics must be non-negative rows summing to one")
        eps = 1e-3  # float16 storage rounds the range ends by less than this (relative)
        _check_range("theta", self.theta, THETA_RANGE[0] - eps, THETA_RANGE[1] + eps)
        _check_range("eta", self.eta, ETA_RANGE[0] * (1 - eps), ETA_RANGE[1] * (1 + eps))
        _check_range("threshold", self.threshold, THRESHOLD_RANGE[0] - eps, 1.0 - 1e-7)
        _check_range(
            "sharpness",
            self.sharpness,
            SHARPNESS_RANGE[0] * (1 - eps),
            SHARPNESS_RANGE[1] * (1 + eps),
        )
        _check_range("colors", self.colors, COLOR_RANGE[0] - eps, COLOR_RANGE[1] + eps)
        _check_range("base_color", self.base_color, BASE_RANGE[0] - eps, BASE_RANGE[1] + eps)

    def _validate_extensions(self, n: int) -> None:
        """The extensions' rows: present exactly when the config uses them (a layered set's
        ``priority``, a per-kernel-sigma set's ``sigma_ratio``, a linear-colour set's
        ``color_slopes``), finite values per kernel in range (float16 storage rounds the ends
        by less than the slack)."""
        lo_p, hi_p = PRIORITY_RANGE
        lo_s, hi_s = SIGMA_RATIO_RANGE
        cfg = self.kernel_config
        rows = (
            ("priority", cfg.blend == "layered", "the layered blend", (n,),
             (lo_p - 1e-2, hi_p + 1e-2)),
            ("sigma_ratio", cfg.per_kernel_sigma, "a per-kernel-sigma set", (n,),
             (lo_s * (1 - 1e-3), hi_s * (1 + 1e-3))),
            ("color_slopes", cfg.linear_colour, "a linear-colour set", (n, 9),
             (SLOPE_RANGE[0] * (1 + 1e-3), SLOPE_RANGE[1] * (1 + 1e-3))),
        )  # fmt: skip
        for name, used, owner, shape, (lo, hi) in rows:
            values = getattr(self, name)
            if values is None:
                if used:
                    raise KernelSetError(f"a kernel set of {owner} needs member {name!r}")
                continue
            if not used:
                raise KernelSetError(f"member {name!r} belongs to {owner} only")
            arr = np.asarray(values)
            if arr.shape != shape or arr.dtype.kind != "f" or not np.all(np.isfinite(arr)):
                raise KernelSetError(f"member {name!r} must be {shape} finite floats")
            _check_range(name, arr, lo, hi)


def _check_range(name: str, values: np.ndarray, lo: float, hi: float) -> None:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size and (arr.min() < lo or arr.max() > hi):
        raise KernelSetError(
            f"member {name!r} out of range: [{arr.min():.6g}, {arr.max():.6g}] not in "
            f"[{lo:.6g}, {hi:.6g}]"
        )


def soft_step(x: torch.Tensor, eps: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``S(x; eps, k)``: a sigmoid rescaled so S(0) = 0 and S(1) = 1, clamped to [0, 1]."""
    low = torch.sigmoid(-k * eps)
    high = torch.sigmoid(k * (1 - eps))
    return torch.clamp((torch.sigmoid(k * (x - eps)) - low) / (high - low), 0.0, 1.0)


def barycentric_gradients(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Gradient of each corner's barycentric coordinate in its face plane: (m, 3, 3).

    ``grad b_i = n x (p_{i+2} - p_{i+1}) / (2 A)``. A loss gradient over barycentrics
    ``g_b`` becomes the 3-D tangent gradient ``sum_i g_b[i] grad b_i``; the part of ``g_b``
    along (1, 1, 1) (which would leave the surface) drops out because the three sum to zero.
    """
    p = vertices[faces]  # (m, 3, 3)
    cross = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    double_area = torch.linalg.norm(cross, dim=1, keepdim=True)
    normal = cross / double_area
    edges = torch.roll(p, shifts=-2, dims=1) - torch.roll(p, shifts=-1, dims=1)  # p_{i+2}-p_{i+1}
    return torch.linalg.cross(normal[:, None, :].expand_as(edges), edges) / double_area[:, None, :]


class HeatKernelModel(nn.Module):
    """Kernel parameters on a device; albedo at surface points (ALGORITHM.md 4-5).

    Parameters (``nn.Parameter``, rows = kernels): ``theta``, ``s`` (= ln(1 + eta), the grid
    coordinate; our choice of parameterisation, so Adam steps are relative in eta),
    ``threshold``, ``sharpness``, ``colors``, ``bary`` (centre barycentrics inside the buffer
    ``face_ids``) and ``base_color`` (``optimise.ATTRIBUTE_LRS`` maps them to their
    ``FitParams.lr_*`` rates). Centres move only by geodesic steps: the optimiser reads
    :meth:`centre_tangent_grad`, traces, and writes back with :meth:`set_centres`.

    Density control changes the kernel count in place with :meth:`select` and :meth:`append`;
    the Parameter objects keep their identity (their ``.data`` is replaced), so an optimiser
    built on them stays valid once its per-parameter state is re-indexed the same way.

    Cached state (per-kernel spectral coefficients for no-grad queries, the KNN index over centre
    embeddings) is rebuilt automatically when any parameter changed in place since it was built
    (tracked through tensor version counters) and by :meth:`refresh`.
    """

    def __init__(
        self,
        field: SpectralField,
        face_ids: torch.Tensor | np.ndarray,
        bary: torch.Tensor | np.ndarray,
        theta: torch.Tensor | np.ndarray,
        eta: torch.Tensor | np.ndarray,
        threshold: torch.Tensor | np.ndarray,
        sharpness: torch.Tensor | np.ndarray,
        colors: torch.Tensor | np.ndarray,
        base_color: torch.Tensor | np.ndarray,
        config: KernelConfig | None = None,
        knn_backend: str = "auto",
        priority: torch.Tensor | np.ndarray | None = None,
        sigma_ratio: torch.Tensor | np.ndarray | None = None,
        color_slopes: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        super().__init__()
        self.field = field
        self.config = config or KernelConfig()
        self.knn_backend = knn_backend
        dev, dt = field.device, field.dtype
        self.register_buffer("face_ids", _long(face_ids, dev))
        self.bary = nn.Parameter(_float(bary, dev, dt))
        self.theta = nn.Parameter(_float(theta, dev, dt))
        self.s = nn.Parameter(torch.log1p(_float(eta, dev, dt)))
        self.threshold = nn.Parameter(_float(threshold, dev, dt))
        self.sharpness = nn.Parameter(_float(sharpness, dev, dt))
        self.colors = nn.Parameter(_float(colors, dev, dt))
        self.base_color = nn.Parameter(_float(base_color, dev, dt))
        if priority is None:  # every kernel on one layer: the layered blend starts as the paper's
            priority = torch.zeros(self.face_ids.shape[0], device=dev, dtype=dt)
        # the paper's blend never reads it: no gradient, no optimiser state
        self.priority = nn.Parameter(_float(priority, dev, dt), requires_grad=self.layered)
        # log(sigma_j / sigma_B): 0 for every kernel is §4's one sigma_B; read and learnt only
        # when the config says per kernel (else no gradient, no optimiser state)
        n = self.face_ids.shape[0]
        log_sigma = (
            torch.zeros(n, device=dev, dtype=dt)
            if sigma_ratio is None
            else torch.log(_float(sigma_ratio, dev, dt))
        )
        self.log_sigma = nn.Parameter(log_sigma, requires_grad=self.per_kernel_sigma)
        # colour slopes (N, 3, 3): read and learnt only when the config says linear (trained
        # from FitParams.slope_start; fitting.colour_solve can also solve them, a measurement)
        slopes = torch.zeros((n, 3, 3), device=dev, dtype=dt)
        if color_slopes is not None:
            slopes = _float(color_slopes, dev, dt).reshape(n, 3, 3)
        self.color_slopes = nn.Parameter(slopes, requires_grad=self.linear_colour)
        self._check_shapes()
        self._generation = 0
        self._cache_key: tuple | None = None
        self._knn_key: tuple | None = None
        self._rows = RowCache(ROWS_CACHE_BYTES)
        self._vtables: VertexTables | None = None
        self._vtables_key: tuple | None = None
        self._vtables_full = False
        self._ftables: FaceTables | None = None
        self._radius: torch.Tensor | None = None
        self._clusters = None
        self._cluster_labels: np.ndarray | None = None
        self._cluster_builds = 0
        self._roster = 0  # bumped when kernels are removed or added (not when they move)
        self._cluster_of = -1

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_kernelset(
        cls, kernelset: KernelSet, field: SpectralField, knn_backend: str = "auto"
    ) -> HeatKernelModel:
        """A model of ``kernelset`` on ``field``'s device; refuses another mesh or grid."""
        spectra = field.spectra
        if kernelset.mesh_hash and kernelset.mesh_hash != spectra.mesh_hash:
            raise KernelSetError("the kernel set was fitted on another mesh")
        if kernelset.config_hash and kernelset.config_hash != spectra.config_hash:
            raise KernelSetError("the kernel set was fitted with another spectral config")
        kernelset.validate(n_faces=field.n_faces)
        bary = np.asarray(kernelset.barycentrics, dtype=np.float64)
        bary = np.clip(bary, 0.0, None)
        bary = bary / bary.sum(axis=1, keepdims=True)  # undo float16 rounding of the rows
        return cls(
            field,
            np.asarray(kernelset.face_ids, dtype=np.int64),
            bary,
            np.asarray(kernelset.theta, dtype=np.float64),
            np.asarray(kernelset.eta, dtype=np.float64),
            np.asarray(kernelset.threshold, dtype=np.float64),
            np.asarray(kernelset.sharpness, dtype=np.float64),
            np.asarray(kernelset.colors, dtype=np.float64),
            np.asarray(kernelset.base_color, dtype=np.float64),
            config=kernelset.kernel_config,
            knn_backend=knn_backend,
            priority=None
            if kernelset.priority is None
            else np.asarray(kernelset.priority, dtype=np.float64),
            sigma_ratio=None
            if kernelset.sigma_ratio is None
            else np.asarray(kernelset.sigma_ratio, dtype=np.float64),
            color_slopes=None
            if kernelset.color_slopes is None
            else np.asarray(kernelset.color_slopes, dtype=np.float64),
        )

    def to_kernelset(
        self, color_space: str = "srgb", fitting: dict | None = None, extras: dict | None = None
    ) -> KernelSet:
        """The parameters as a numpy :class:`KernelSet` tagged with this mesh and grid."""

        def np_(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy()

        return KernelSet(
            face_ids=np_(self.face_ids).astype(np.int64),
            barycentrics=np_(self.bary).astype(np.float64),
            theta=np_(self.theta).astype(np.float64),
            eta=np_(torch.expm1(self.s)).astype(np.float64),
            threshold=np_(self.threshold).astype(np.float64),
            sharpness=np_(self.sharpness).astype(np.float64),
            colors=np_(self.colors).astype(np.float64),
            base_color=np_(self.base_color).astype(np.float64),
            kernel_config=self.config,
            priority=np_(self.priority).astype(np.float64) if self.layered else None,
            sigma_ratio=np_(torch.exp(self.log_sigma)).astype(np.float64)
            if self.per_kernel_sigma
            else None,
            color_slopes=np_(self.color_slopes).reshape(-1, 9).astype(np.float64)
            if self.linear_colour
            else None,
            mesh_hash=self.field.spectra.mesh_hash,
            config_hash=self.field.spectra.config_hash,
            color_space=color_space,
            fitting=dict(fitting or {}),
            extras=dict(extras or {}),
        )

    def _check_shapes(self) -> None:
        n = self.face_ids.shape[0]
        expect = {
            "bary": (n, 3),
            "theta": (n,),
            "s": (n,),
            "threshold": (n,),
            "sharpness": (n,),
            "colors": (n, 3),
            "base_color": (3,),
            "priority": (n,),
            "log_sigma": (n,),
            "color_slopes": (n, 3, 3),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise KernelSetError(f"kernel parameter {name!r} has shape {got}, expected {shape}")
        if n and (self.face_ids.min() < 0 or self.face_ids.max() >= self.field.n_faces):
            raise KernelSetError("kernel centre face ids out of range")

    # ----------------------------------------------------------------- parameters
    def __len__(self) -> int:
        return int(self.face_ids.shape[0])

    @property
    def eta(self) -> torch.Tensor:
        return torch.expm1(self.s)

    @property
    def layered(self) -> bool:
        """Whether colours blend by priority (``kernels.blending``) rather than §5's average."""
        return self.config.blend == "layered"

    @property
    def per_kernel_sigma(self) -> bool:
        """Whether each kernel has its own biharmonic scale (``log_sigma``) or §4's one."""
        return self.config.per_kernel_sigma

    @property
    def linear_colour(self) -> bool:
        """Whether each kernel's colour varies linearly over its footprint (``color_slopes``)."""
        return self.config.linear_colour

    @torch.no_grad()
    def set_color_slopes(self, slopes: torch.Tensor | np.ndarray | None) -> None:
        """Give the kernels colour slopes (N, 3, 3) and make the set linear-colour, or, with
        None, drop them and return to §4's constant colours."""
        colour = "constant" if slopes is None else "linear"
        self.config = replace(self.config, colour=colour)
        dev, dt = self.field.device, self.field.dtype
        n = len(self)
        self.color_slopes.data = (
            torch.zeros((n, 3, 3), device=dev, dtype=dt)
            if slopes is None
            else _float(slopes, dev, dt).reshape(n, 3, 3)
        )
        self.color_slopes.requires_grad_(self.linear_colour)
        self.color_slopes.grad = None
        self._check_shapes()

    def centre_offsets(
        self, kid: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor
    ) -> torch.Tensor:
        """``x(y) - x(c_j)`` (P, K, 3) in the normalised frame, from points ``(face_ids,
        bary)`` to their kernels ``kid`` (P, K), without a graph; padding ids (``rho`` 0)
        read the last kernel's, which the blend weighs by 0. What a colour slope multiplies
        (the model's mix, and the colour solve's slope columns)."""
        k = kid.clamp(max=len(self) - 1)
        x = self.field.positions(face_ids, bary.detach())
        return x[:, None, :] - self.field.positions(self.face_ids, self.bary.detach())[k]

    def sigma_ratio(self, idx: torch.Tensor | None = None) -> torch.Tensor | None:
        """``s_j = sigma_j / sigma_B`` of kernels ``idx`` (all when None), with a graph when
        learnt; None when every kernel has ``sigma_B`` (the callers then divide by the scalar,
        as before). Ratios, not sigmas: ``2 sigma_B^2 s_j^2`` is ``2 sigma_B^2`` exactly at
        ``s_j = 1``, so such a set evaluates bit for bit as the uniform one."""
        if not self.per_kernel_sigma:
            return None
        return torch.exp(self.log_sigma if idx is None else self.log_sigma[idx])

    def priority_of(self, kid: torch.Tensor) -> torch.Tensor | None:
        """The layered blend's priorities of chosen kernels ``kid`` (None for the paper's
        blend); padding ids (``rho`` 0, at or past the count) read the last kernel's, which
        cancels in the shares."""
        if not self.layered:
            return None
        return self.priority[kid.clamp(max=len(self) - 1)]

    @torch.no_grad()
    def project_(self) -> None:
        """Clamp every attribute into its range after an optimiser step."""
        self.theta.clamp_(*THETA_RANGE)
        self.s.clamp_(math.log1p(ETA_RANGE[0]), math.log1p(ETA_RANGE[1]))
        self.threshold.clamp_(*THRESHOLD_RANGE)
        self.sharpness.clamp_(*SHARPNESS_RANGE)
        self.colors.clamp_(*COLOR_RANGE)
        self.base_color.clamp_(*BASE_RANGE)
        self.priority.clamp_(*PRIORITY_RANGE)
        self.log_sigma.clamp_(*LOG_SIGMA_RANGE)
        self.color_slopes.clamp_(*SLOPE_RANGE)
        self.bary.clamp_(min=0.0)
        self.bary.div_(self.bary.sum(dim=1, keepdim=True))

    def centre_tangent_grad(self) -> torch.Tensor:
        """d loss / d centre position, in each centre's face plane (N, 3), from ``bary.grad``."""
        if self.bary.grad is None:
            return torch.zeros_like(self.bary)
        grads = barycentric_gradients(self.field.vertices, self.field.faces[self.face_ids])
        return torch.einsum("nv,nvd->nd", self.bary.grad, grads)

    @torch.no_grad()
    def set_centres(self, face_ids: torch.Tensor, bary: torch.Tensor) -> None:
        """Move centres (after a geodesic step); the caches follow on next use."""
        self.face_ids = _long(face_ids, self.field.device)
        self.bary.data = _float(bary, self.field.device, self.field.dtype)
        self._generation += 1
        self._check_shapes()

    @torch.no_grad()
    def select(self, indices: torch.Tensor | np.ndarray) -> HeatKernelModel:
        """Keep only the kernels at ``indices`` (in that order; repeats clone), in place."""
        idx = _long(indices, self.field.device)
        self._roster += 1
        self.face_ids = self.face_ids[idx]
        for p in self._row_params():
            p.data = p.data[idx]
            p.grad = None
        self._generation += 1
        self._check_shapes()
        return self

    @torch.no_grad()
    def append(
        self,
        face_ids: torch.Tensor | np.ndarray,
        bary: torch.Tensor | np.ndarray,
        theta: torch.Tensor | np.ndarray,
        eta: torch.Tensor | np.ndarray,
        threshold: torch.Tensor | np.ndarray,
        sharpness: torch.Tensor | np.ndarray,
        colors: torch.Tensor | np.ndarray,
        priority: torch.Tensor | np.ndarray | None = None,
        log_sigma: torch.Tensor | np.ndarray | None = None,
        color_slopes: torch.Tensor | np.ndarray | None = None,
    ) -> HeatKernelModel:
        """Add kernels at the end (``eta`` in natural units; ``priority``, ``log_sigma`` and
        the colour slopes 0 unless given)."""
        dev, dt = self.field.device, self.field.dtype
        self._roster += 1
        if priority is None:
            priority = torch.zeros(len(face_ids), device=dev, dtype=dt)
        if log_sigma is None:
            log_sigma = torch.zeros(len(face_ids), device=dev, dtype=dt)
        if color_slopes is None:
            color_slopes = torch.zeros((len(face_ids), 3, 3), device=dev, dtype=dt)
        self.face_ids = torch.cat([self.face_ids, _long(face_ids, dev)])
        new = [
            bary,
            theta,
            torch.log1p(_float(eta, dev, dt)),
            threshold,
            sharpness,
            colors,
            priority,
            log_sigma,
            _float(color_slopes, dev, dt).reshape(-1, 3, 3),
        ]
        for p, rows in zip(self._row_params(), new, strict=True):
            p.data = torch.cat([p.data, _float(rows, dev, dt)])
            p.grad = None
        self._generation += 1
        self._check_shapes()
        return self

    def _row_params(self) -> list[nn.Parameter]:
        return [
            self.bary, self.theta, self.s, self.threshold, self.sharpness, self.colors,
            self.priority, self.log_sigma, self.color_slopes,
        ]  # fmt: skip

    # ----------------------------------------------------------------- caches
    def _version_key(self, params: list[torch.Tensor]) -> tuple:
        # In-place optimiser steps bump a tensor's version; set_centres/select/append bump the
        # generation (they replace tensors, whose fresh version counters could repeat).
        return (self._generation, self.face_ids._version) + tuple(p._version for p in params)

    def refresh(self) -> None:
        """Rebuild the centre responses and the KNN index now (after centres moved)."""
        self._cache_key = None
        self._knn_key = None
        self._ensure_cache()
        self._ensure_knn()

    @torch.no_grad()
    def _ensure_cache(self) -> None:
        key = self._version_key([self.bary, self.theta, self.s])
        if key == self._cache_key:
            return
        self._terms = self._spectral_terms(torch.arange(len(self), device=self.field.device))
        self._cache_key = key

    @torch.no_grad()
    def _ensure_knn(self) -> None:
        key = self._version_key([self.bary])
        if key == self._knn_key:
            return
        self._centre_emb = self._embedding(self.face_ids, self.bary.detach())
        self._knn = None  # the index is built when a search needs it (_index)
        self._clusters = None  # likewise the compiled search's grouping (_nearest)
        self._knn_key = key

    def _embedding(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """``field.embedding_at``, compiled on the CPU in float32 (centres each step)."""
        if fused_terms.available(self.field, bary.dtype) and bary.dtype == self.field.dtype:
            return fused_terms.Embedding.apply(self.field, face_ids, bary)
        return self.field.embedding_at(face_ids, bary)

    def _index(self) -> CandidateSearch:
        """The KNN index over the current centre embeddings (built on first use: training
        steps on the CPU search without it, see :meth:`_nearest`)."""
        self._ensure_knn()
        if self._knn is None:
            self._knn = CandidateSearch(self._centre_emb, backend=self.knn_backend)
        return self._knn

    def _nearest(self, emb_y: torch.Tensor, k_s: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The exact ``k_s`` nearest centres of each point under the tie rule, nearest first:
        ``(cand, d2)``; compiled on the CPU in float32 (no index to rebuild when the centres
        moved), else the index's candidates cut exactly (:func:`_exact_cut`)."""
        self._ensure_knn()
        if self.knn_backend == "auto" and fused_rank.available(emb_y.device, emb_y.dtype):
            if self._clusters is None:
                # the last grouping is kept while the same kernels only move (a little per
                # step); a fresh one every CLUSTER_REGROUP builds, and at once when kernels
                # were removed or added (select/append: stale labels make wide clusters and
                # a long scan, never a wrong answer)
                fresh = self._cluster_builds % CLUSTER_REGROUP == 0
                last = None if fresh or self._cluster_of != self._roster else self._cluster_labels
                self._clusters = fused_rank.Clusters(self._centre_emb, last)
                self._cluster_labels, self._cluster_of = self._clusters.labels, self._roster
                self._cluster_builds += 1
            return fused_rank.nearest(emb_y.detach(), self._clusters, k_s)
        cand = self._index().search(emb_y, k_s + KNN_MARGIN)
        return _exact_cut(emb_y.detach(), self._centre_emb, cand, k_s)

    @torch.no_grad()
    def prepare_tables(self) -> VertexTables | None:
        """Build the candidate tables of every vertex now (dense query workloads: baking,
        rendering, large query batches), if they fit :data:`TABLES_MAX_BYTES`; returns them
        (None when they do not fit: chunks then build their own)."""
        key = self._version_key([self.bary, self.theta, self.s])
        if self._vtables is not None and self._vtables_key == key and self._vtables_full:
            return self._vtables
        self._ensure_cache()
        self._ensure_knn()
        all_v = torch.arange(self.field.n_vertices, device=self.field.device)
        est = self.field.n_vertices * 3 * min(self.config.k_search, len(self)) * 24
        if est > TABLES_MAX_BYTES:
            return None
        self._vtables = self._build_tables(all_v)
        self._vtables_key, self._vtables_full = key, True
        # and every face's list, when they fit beside the vertex tables
        room = TABLES_MAX_BYTES - self._vtables.nbytes
        k_s = min(self.config.k_search, len(self))
        self._ftables = all_face_tables(self.field, self._vtables, k_s, room)
        return self._vtables

    def _build_tables(self, verts: torch.Tensor) -> VertexTables:
        if self._radius is None:
            self._radius = star_radius(self.field)
        k_s = min(self.config.k_search, len(self))
        return build_tables(
            self.field, verts, self._centre_emb, self._terms, k_s, self._radius, self._index
        )

    @torch.no_grad()
    def _tables_for(self, face_ids: torch.Tensor) -> VertexTables | None:
        """Vertex tables covering the faces of a no-grad batch, or None for the per-point path.

        Whole-mesh tables (:meth:`prepare_tables`) are reused while the kernels do not change;
        otherwise a batch builds tables for its own vertices when it has at least
        :data:`TABLE_POINTS_PER_VERTEX` points per distinct vertex
        (:data:`TABLE_POINTS_PER_VERTEX_COMPILED` where the per-point path ranks compiled),
        else the per-point path runs (``TABLE_PATH`` forces either).
        """
        if TABLE_PATH == "never" or face_ids.numel() == 0:
            return None
        self._ensure_cache()
        key = self._version_key([self.bary, self.theta, self.s])
        if self._vtables is not None and self._vtables_full and self._vtables_key == key:
            return self._vtables  # the whole mesh: no need to find this batch's vertices
        verts = torch.unique(self.field.faces[face_ids])
        if self._vtables is not None and self._vtables_key == key:
            if self._vtables.covers(verts):
                return self._vtables
        per_vertex = (
            TABLE_POINTS_PER_VERTEX_COMPILED if self.ranks_compiled() else TABLE_POINTS_PER_VERTEX
        )
        if TABLE_PATH != "always" and face_ids.shape[0] < per_vertex * verts.numel():
            return None
        tables = self._build_tables(verts)
        if not (self._vtables_full and self._vtables_key == key):
            self._vtables, self._vtables_key, self._vtables_full = tables, key, False
            self._ftables = None
        return tables

    def _blend_tables(self, tables, face_ids, bary, return_aux):
        """No-grad albedo from vertex tables (``kernels.tables``): exact ``K_s`` cut and
        ``K_c`` choice by the tie rule on each point's face candidates."""
        n_k = len(self)
        if tables is self._vtables and self._vtables_full and self._ftables is not None:
            ft = self._ftables  # every face's list, built with the whole-mesh tables
        else:
            faces = torch.unique(face_ids)
            ft = face_tables(self.field, tables, faces, min(self.config.k_search, n_k))
        k_s = min(self.config.k_search, n_k)
        if fused_blend.available(self.field.device, self.colors.dtype):
            _, norm, _, _, _ = self._terms
            args = (norm, self.threshold, self.sharpness, self.colors, self.base_color)
            cfg = self.config
            # the compiled blend knows constant colours only: a linear-colour set takes its
            # chosen kernels from it and mixes them here
            ordered = return_aux or self.linear_colour
            out, kid, rho = fused_blend.blend(
                ft, face_ids, bary, *args, cfg.sigma_b, k_s, cfg.k_blend, ordered=ordered,
                priority=self.priority if self.layered else None, ratio=self.sigma_ratio(),
            )  # fmt: skip
            if self.linear_colour:
                out = self._mix(rho.to(self.colors.dtype), kid, face_ids, bary)
            return (out, {"indices": kid, "rho": rho}) if return_aux else out
        row, kid, d2 = point_distances(ft, face_ids, bary)
        # exact K_s cut first (distance, then kernel id; padding gets distinct ids above every
        # kernel's, the rule needs unique ids per row), then responses of those only
        pad_ids = n_k + torch.arange(kid.shape[1], device=kid.device).expand_as(kid)
        tie_id = torch.where(kid < n_k, kid, pad_ids)
        pos = nearest_by_rule(d2, tie_id, k_s)
        d2, kid = d2.gather(1, pos), kid.gather(1, pos)
        h = point_responses(ft, row, pos, bary)
        _, norm, _, _, _ = self._terms
        w = _heat_weight(d2, self.config.sigma_b, self.sigma_ratio(), kid).to(h.dtype)
        r = h * w / norm[kid]
        rho = soft_step(r, self.threshold[kid], self.sharpness[kid])
        top = select_by_rule(rho, d2, kid, min(self.config.k_blend, k_s))
        rho_top, kid = rho.gather(1, top), kid.gather(1, top)
        out = self._mix(rho_top, kid, face_ids, bary)
        if return_aux:
            return out, {"indices": kid, "rho": rho_top}
        return out

    def _spectral_terms(
        self, idx: torch.Tensor, rows: RowCache | None = None
    ) -> tuple[torch.Tensor, ...]:
        """Per-kernel terms for kernels ``idx`` (``rows``: a cache for ``idx = arange(N)``).

        ``coef = exp(-t lambda) phi(c)`` (U, K), ``h(c) = coef . phi(c)`` (U,), the bilinear
        nodes and weights (U, 4) and the centre embeddings (U, D).
        """
        theta, s = self.theta[idx], self.s[idx]
        face_ids, bary = self.face_ids[idx], self.bary[idx]
        if fused_terms.available(self.field, bary.dtype):
            nodes, weights = self.field.nodes(theta, s)
            verts = self.field.faces[face_ids]
            t = self.config.diffusion_time
            table, ridx = fused_terms.row_table(self.field, verts, nodes, rows)
            coef, norm = fused_terms.KernelTerms.apply(
                table, ridx, self.field, nodes, bary, weights, t
            )
            return coef, norm, nodes, weights, self._embedding(face_ids, bary)
        phi_c = self.field.eigenfunctions(face_ids, bary, theta, s, rows)
        lam = self.field.eigenvalues(theta, s)
        coef = torch.exp(-self.config.diffusion_time * lam) * phi_c
        norm = (coef * phi_c).sum(dim=1)
        nodes, weights = self.field.nodes(theta, s)
        return coef, norm, nodes, weights, self.field.embedding_at(face_ids, bary)

    # ----------------------------------------------------------------- evaluation
    def albedo(
        self, face_ids: torch.Tensor, bary: torch.Tensor, return_aux: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Albedo (P, 3) at surface points from the ``K_c`` strongest of ``K_s`` candidates.

        ``aux`` holds ``indices`` (P, K_c) global kernel ids and ``rho`` (P, K_c).
        """
        face_ids = _long(face_ids, self.field.device)
        bary = _query_float(bary, self.field.device, self.field.dtype)
        self._ensure_knn()
        k_s = min(self.config.k_search, len(self))
        if not self._grad_needed() and not (torch.is_grad_enabled() and bary.requires_grad):
            tables = self._tables_for(face_ids)
            if tables is not None:
                return self._blend_tables(tables, face_ids, bary, return_aux)
        emb_y = self._embedding(face_ids, bary.detach())
        cand, d2 = self._nearest(emb_y, k_s)
        return self._blend(face_ids, bary, cand, return_aux, d2)

    def albedo_bruteforce(
        self,
        face_ids: torch.Tensor,
        bary: torch.Tensor,
        return_aux: bool = False,
        exact_search: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Albedo without the KNN index, for tests and tiny sets.

        ``exact_search=False``: every kernel is a candidate (no ``K_s`` cut).
        ``exact_search=True``: the candidates are the exact ``K_s`` nearest centres by the
        tie rule (distance, then kernel index) over all kernels, as :meth:`albedo` defines
        them; the two must then agree exactly.
        """
        face_ids = _long(face_ids, self.field.device)
        bary = _query_float(bary, self.field.device, self.field.dtype)
        if not exact_search:
            return self._blend(face_ids, bary, None, return_aux)
        self._ensure_knn()
        k_s = min(self.config.k_search, len(self))
        emb_y = self.field.embedding_at(face_ids, bary).detach()
        cand, d2 = _exhaustive_cut(emb_y, self._centre_emb, k_s)
        return self._blend(face_ids, bary, cand, return_aux, d2)

    def responses(
        self, face_ids: torch.Tensor, bary: torch.Tensor, cand: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``rho`` (P, C) of candidate kernels ``cand`` (P, C) (all kernels when None).

        Returns ``(rho, cand)``. Differentiable in every kernel parameter when grad is enabled;
        under ``torch.no_grad`` it reuses the cached per-kernel coefficients.
        """
        face_ids = _long(face_ids, self.field.device)
        bary = _query_float(bary, self.field.device, self.field.dtype)
        if cand is None:
            cand = torch.arange(len(self), device=self.field.device).expand(face_ids.shape[0], -1)
        r = self._ratio(face_ids, bary, cand)
        return soft_step(r, self.threshold[cand], self.sharpness[cand]), cand

    def _blend(self, face_ids, bary, cand, return_aux, d2=None):
        if cand is not None and self._grad_needed() and not bary.requires_grad:
            if self._compiled_training():
                out, kid, rho_top = self._train_blend(face_ids, bary, cand, d2)
                return (out, {"indices": kid, "rho": rho_top}) if return_aux else out
            kid, rho_top = self._top_responses(face_ids, bary, cand, d2)
        else:
            if cand is None:
                n = face_ids.shape[0]
                cand = torch.arange(len(self), device=self.field.device).expand(n, -1)
            plain = not self._grad_needed() and not (torch.is_grad_enabled() and bary.requires_grad)
            compiled_rank = self.ranks_compiled()
            if plain and d2 is not None and compiled_rank:
                kid, rho_top = self._ranked_no_grad(face_ids, bary, cand, d2)
            elif not self._grad_needed():
                kid = None
                self._ensure_cache()
                r, d2 = _pair_ratio(
                    face_ids,
                    bary,
                    cand,
                    *self._terms,
                    self.field,
                    self.config.sigma_b,
                    d2=d2,
                    return_d2=True,
                    ratio=self.sigma_ratio(),
                )
                rho = soft_step(r, self.threshold[cand], self.sharpness[cand])
            else:
                kid = None
                rho, cand = self.responses(face_ids, bary, cand)
                if d2 is None:
                    self._ensure_knn()
                    emb_y = self.field.embedding_at(face_ids, bary.detach())
                    d2 = ((emb_y[:, None, :] - self._centre_emb[cand]) ** 2).sum(dim=2)
            if kid is None:
                k_c = min(self.config.k_blend, rho.shape[1])
                pos = select_by_rule(rho.detach(), d2.detach(), cand, k_c)
                rho_top = rho.gather(1, pos)
                kid = cand.gather(1, pos)
        out = self._mix(rho_top, kid, face_ids, bary)
        if return_aux:
            return out, {"indices": kid, "rho": rho_top}
        return out

    def _mix(
        self, rho_top: torch.Tensor, kid: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor
    ) -> torch.Tensor:
        """The colours of points ``(face_ids, bary)`` whose chosen kernels are ``kid`` with
        responses ``rho_top``."""
        colors = self.colors[kid]
        if self.linear_colour:
            colors = colors + self._slope_terms(kid, face_ids, bary)
        return blending.albedo(rho_top, colors, self.base_color, self.priority_of(kid))

    def _slope_terms(
        self, kid: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor
    ) -> torch.Tensor:
        """``G_j (x(y) - x(c_j))`` (P, K_c, 3) of the chosen kernels at the points. The
        offsets carry no gradient to the centres, which keep moving by their footprints' pull
        alone, as ALGORITHM.md §6 has them (a colour never pulls a centre there)."""
        offset = self.centre_offsets(kid, face_ids, bary).to(self.colors.dtype)
        slopes = self.color_slopes[kid.clamp(max=len(self) - 1)]
        return torch.einsum("pkcd,pkd->pkc", slopes, offset)

    def _grad_needed(self) -> bool:
        return torch.is_grad_enabled() and any(p.requires_grad for p in self._row_params())

    def _top_responses(
        self, face_ids: torch.Tensor, bary: torch.Tensor, cand: torch.Tensor, d2: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable ``rho`` of each point's ``K_c`` strongest candidates: (kid, rho).

        Only the top ``K_c`` responses reach the albedo, and ``topk`` is piecewise constant,
        so the gradient of the blend is exactly that of those ``P K_c`` pairs. The ``K_s``
        candidates are ranked without a graph (:func:`_rank_pairs`, which also keeps what the
        selected pairs' backward needs: ``P K_c (K + 4)`` numbers), and only the winners get
        a graph (:class:`_PairResponse`). Per-kernel terms are computed once, with a graph,
        for the batch's unique candidates; their backward touches only rows with gradient.
        """
        uniq, local, terms = self._candidate_terms(cand)
        k_c = min(self.config.k_blend, cand.shape[1])
        detached = [t.detach() for t in terms]
        ratio = self.sigma_ratio(uniq)
        ratio = None if ratio is None else ratio.detach()
        parts = [
            _rank_pairs(
                face_ids[sl],
                bary[sl],
                local[sl],
                d2[sl],
                self.threshold.detach()[uniq],
                self.sharpness.detach()[uniq],
                *detached,
                self.field,
                self.config.sigma_b,
                k_c,
                ratio,
            )
            for sl in _slices(face_ids.shape[0], GRAD_CHUNK_POINTS)
        ]
        top, dots, blend = (torch.cat(x) for x in zip(*parts, strict=True))
        return self._pair_graph(face_ids, bary, uniq, terms, top, dots, blend)

    def _candidate_terms(self, cand: torch.Tensor):
        """``(uniq, local, terms)``: the batch's candidate kernels ``uniq``, ``cand`` as rows
        of them, and their per-kernel terms with a graph (all kernels, from cached rows,
        when most are candidates: training batches)."""
        uniq, local = torch.unique(cand, return_inverse=True)
        if uniq.shape[0] * 2 >= len(self) and self._rows.fits(self.field, len(self)):
            uniq = torch.arange(len(self), device=cand.device)
            return uniq, cand, self._spectral_terms(uniq, self._rows)
        return uniq, local, self._spectral_terms(uniq)

    def blends_from_mesh_tables(self) -> bool:
        """Whether no-grad queries of the current kernels blend compiled from whole-mesh face
        tables (:meth:`prepare_tables`): then a point costs ~100 bytes of working memory,
        not the per-point path's (``AlbedoQuery`` sizes its chunks by it)."""
        key = self._version_key([self.bary, self.theta, self.s])
        built = self._vtables is not None and self._vtables_full and self._vtables_key == key
        compiled_blend = fused_blend.available(self.field.device, self.colors.dtype)
        return built and self._ftables is not None and compiled_blend

    def ranks_compiled(self) -> bool:
        """Whether no-grad per-point queries rank through the compiled loop (CPU float32;
        a float16 grid is read in place, ``fused_rank.ranking_grid``)."""
        return fused_rank.available(self.colors.device, self.colors.dtype) and fused_rank.can_rank(
            self.field
        )

    def _compiled_training(self) -> bool:
        """Training takes the compiled step wherever no-grad ranking does (a float16 grid
        whose float32 copy would pass ``fused_rank.EVECS32_MAX_BYTES`` is read in place)."""
        return self.ranks_compiled()

    @torch.no_grad()
    def _ranked_no_grad(self, face_ids, bary, cand, d2):
        """``(kid, rho)`` of each point's ``K_c`` chosen kernels, compiled (sparse no-grad
        queries: points too few per vertex for candidate tables)."""
        self._ensure_cache()
        coef, norm, nodes, weights, _ = self._terms
        top, _, _, rho = fused_rank.rank_pairs(
            self.field, face_ids, bary, cand, d2, self.threshold, self.sharpness, coef, norm,
            nodes, weights, self.config.sigma_b, self.config.k_blend, keep=False,
            ratio=self.sigma_ratio(),
        )  # fmt: skip
        return top, rho

    def _train_blend(self, face_ids, bary, cand, d2):
        """Albedo of a differentiable batch, compiled (``kernels.fused_rank`` ranks the
        ``K_s`` candidates without a graph, ``kernels.fused_pairs`` blends the chosen ``K_c``
        with an analytic backward): ``(out, kid, rho)``, the same mathematics as
        :meth:`_top_responses` and the blend after it."""
        uniq, local, terms = self._candidate_terms(cand)
        coef, norm, nodes, weights, emb_c = terms
        k_c = min(self.config.k_blend, cand.shape[1])
        attrs = [self.threshold, self.sharpness]
        if uniq.shape[0] != len(self):
            attrs = [a[uniq] for a in attrs]
        ratio = self.sigma_ratio(uniq)
        top, dots, blend, _ = fused_rank.rank_pairs(
            self.field,
            face_ids,
            bary.detach(),
            local,
            d2,
            attrs[0].detach(),
            attrs[1].detach(),
            coef.detach(),
            norm.detach(),
            nodes,
            weights.detach(),
            self.config.sigma_b,
            k_c,
            ratio=None if ratio is None else ratio.detach(),
        )
        emb_y = self._embedding(face_ids, bary.detach())
        scale = fused_pairs.pair_scales(self.config.sigma_b, ratio, uniq.shape[0])
        rho = fused_pairs.PairResponse.apply(
            top, dots, blend, emb_y, scale, coef, norm, weights, emb_c, *attrs[:2]
        )
        kid = uniq[top]
        return self._mix(rho, kid, face_ids, bary), kid, rho.detach()

    def _pair_graph(self, face_ids, bary, uniq, terms, top, dots, blend):
        """``(kid, rho)`` of the chosen pairs ``top`` (rows of ``terms``), with a graph."""
        coef, norm, nodes, weights, emb_c = terms
        h = _PairResponse.apply(coef[top], weights[top], dots, blend)
        emb_y = self.field.embedding_at(face_ids, bary)
        d2_top = ((emb_y[:, None, :] - emb_c[top]) ** 2).sum(dim=2)
        w = _heat_weight(d2_top, self.config.sigma_b, self.sigma_ratio(uniq), top)
        r = h * w / norm[top]
        kid = uniq[top]
        return kid, soft_step(r, self.threshold[kid], self.sharpness[kid])

    def _ratio(
        self, face_ids: torch.Tensor, bary: torch.Tensor, cand: torch.Tensor
    ) -> torch.Tensor:
        """``r_j(y) = h_j(y) w_j(y) / h_j(c_j)`` for candidates (P, C)."""
        if self._grad_needed():
            uniq, local = torch.unique(cand, return_inverse=True)
            terms = self._spectral_terms(uniq)
            ratio = self.sigma_ratio(uniq)
            if face_ids.shape[0] > GRAD_CHUNK_POINTS:
                # Large differentiable batches (multi-view ray batches): recompute each chunk's
                # (P, C, K) intermediates in backward instead of keeping them all alive.
                fn = partial(_ratio_of_rows, field=self.field, sigma_b=self.config.sigma_b)
                extra = () if ratio is None else (ratio,)
                parts = [
                    _Recompute.apply(fn, face_ids[sl], bary[sl], local[sl], *terms, *extra)
                    for sl in _slices(face_ids.shape[0], GRAD_CHUNK_POINTS)
                ]
                return torch.cat(parts)
        else:
            self._ensure_cache()
            terms, local, ratio = self._terms, cand, self.sigma_ratio()
        return _pair_ratio(
            face_ids, bary, local, *terms, self.field, self.config.sigma_b, ratio=ratio
        )


def _pair_ratio(
    face_ids: torch.Tensor,
    bary: torch.Tensor,
    local: torch.Tensor,
    coef: torch.Tensor,
    norm: torch.Tensor,
    nodes: torch.Tensor,
    weights: torch.Tensor,
    emb_c: torch.Tensor,
    field: SpectralField,
    sigma_b: float,
    d2: torch.Tensor | None = None,
    return_d2: bool = False,
    ratio: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """``r`` for points and their candidates ``local`` (rows of the per-kernel terms).

    ``d2``: squared embedding distances (P, C) when the caller has them (the exact candidate
    cut computes them anyway); they must not need a gradient. ``return_d2``: return
    ``(r, d2)`` (the tie rule ranks by both). ``ratio``: per-row ``sigma_j / sigma_b`` (rows
    of the terms) of a per-kernel-sigma set; None: ``sigma_b`` for all.
    """
    h = None
    if not torch.is_grad_enabled() and PAIR_PATH != "bmm":
        h = _h_by_vertex_pairs(face_ids, bary, local, coef, nodes, weights, field)
    if h is None:
        h = _h_by_node_matmul(face_ids, bary, local, coef, nodes, weights, field)
    if d2 is None:
        emb_y = field.embedding_at(face_ids, bary)
        d2 = ((emb_y[:, None, :] - emb_c[local]) ** 2).sum(dim=2)  # squared distance, used once
    r = h * _heat_weight(d2.to(h.dtype), sigma_b, ratio, local) / norm[local]
    return (r, d2) if return_d2 else r


def _ratio_of_rows(*tensors: torch.Tensor, field: SpectralField, sigma_b: float) -> torch.Tensor:
    """:func:`_pair_ratio` of ``(face_ids, bary, local, coef, norm, nodes, weights, emb_c[,
    ratio])``, all positional (what :class:`_Recompute` passes)."""
    ratio = tensors[8] if len(tensors) > 8 else None
    return _pair_ratio(*tensors[:8], field, sigma_b, ratio=ratio)


def _heat_weight(
    d2: torch.Tensor,
    sigma_b: float,
    ratio: torch.Tensor | None = None,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """The biharmonic decay ``w = exp(-d2 / (2 sigma^2))`` per pair: ``sigma_b`` for every
    pair (divided as a scalar, the same bits as ever), or ``sigma_b ratio[rows]`` per pair."""
    if ratio is None:
        return torch.exp(-d2 / (2.0 * sigma_b**2))
    return torch.exp(-d2 / (2.0 * sigma_b**2 * ratio[rows].to(d2.dtype) ** 2))


@torch.no_grad()
def _rank_pairs(
    face_ids,
    bary,
    local,
    d2,
    threshold,
    sharpness,
    coef,
    norm,
    nodes,
    weights,
    emb_c,
    field,
    sigma_b,
    k_c,
    ratio=None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rank all candidates without a graph; keep what the top ``k_c`` pairs' backward needs.

    Returns ``top`` (P, k_c) rows of the per-kernel terms, ``dots`` (P, k_c, 4) =
    ``coef_j . Phi_y[n_jc]`` and ``blend`` (P, k_c, K) = ``sum_c w_jc Phi_y[n_jc]``
    (``dh/dw`` and ``dh/dcoef`` of :class:`_PairResponse`).
    """
    phi_y = field.node_values(face_ids, bary)  # (P, G, K)
    h = _h_by_node_matmul(face_ids, bary, local, coef, nodes, weights, field, phi_y)
    r = h * _heat_weight(d2.to(h.dtype), sigma_b, ratio, local) / norm[local]
    rho = soft_step(r, threshold[local], sharpness[local])
    # tie rule (ALGORITHM.md 5): ``local`` indexes the sorted unique kernels, so its order
    # is the kernel-index order
    top = local.gather(1, select_by_rule(rho, d2, local, k_c))  # (P, k_c)
    p, g, k = phi_y.shape
    rows = torch.arange(p, device=phi_y.device)[:, None, None] * g + nodes[top]  # (P, k_c, 4)
    phi4 = phi_y.view(p * g, k).index_select(0, rows.reshape(-1)).view(p, k_c, -1, k)
    dots = torch.matmul(phi4, coef[top][..., None]).squeeze(-1)  # (P, k_c, 4)
    blend = torch.matmul(weights[top][:, :, None, :], phi4).squeeze(2)  # (P, k_c, K)
    return top, dots, blend


class _PairResponse(torch.autograd.Function):
    """``h = sum_c w_c dots_c`` for selected pairs, with the analytic backward.

    ``dots_c = coef . Phi_y[n_c]`` and ``blend = sum_c w_c Phi_y[n_c]`` were computed at the
    same parameter values by :func:`_rank_pairs`; ``dh/dcoef = blend`` and ``dh/dw_c =
    dots_c``. The point side ``Phi_y`` is a constant here (the caller routes batches whose
    query barycentrics need a gradient through plain autograd instead).
    """

    @staticmethod
    def forward(ctx, coef, weights, dots, blend):  # type: ignore[override]
        ctx.save_for_backward(dots, blend)
        return (weights * dots).sum(dim=2)

    @staticmethod
    def backward(ctx, grad_h):  # type: ignore[override]
        dots, blend = ctx.saved_tensors
        g = grad_h[..., None]
        return g * blend, g * dots, None, None


def _exact_cut(
    emb_y: torch.Tensor, emb_c: torch.Tensor, cand: torch.Tensor, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact ``k`` nearest centres, from a slightly larger candidate list.

    faiss ranks with float32 ``|q|^2 + |c|^2 - 2 q.c`` computed differently for small and
    large query batches, so the ``K_s``-th neighbour (and hence a colour) could depend on the
    rest of the batch. The ``K_s + margin`` candidates are re-ranked by the directly computed
    ``|c - q|^2`` of each pair (elementwise, so the same bits whatever the batch) under the
    tie rule (distance, then kernel index), so the cut is a function of the point alone.
    It is exact when the ``k``-th distance is below the farthest fetched one by more than the
    index's round-off (then no centre left out can be nearer or tied); rows where it is not
    (ties across the margin: clones, symmetric layouts) are cut over all centres instead
    (:func:`_exhaustive_cut`). The distances are the ones ``w_j(y)`` uses, so they are
    computed once. Returns ``(cand (P, k), d2 (P, k))``, nearest first.
    """
    diff = emb_c[cand] - emb_y[:, None, :]
    d2 = (diff * diff).sum(dim=2)
    pos = select_by_rule(-d2, None, cand, k)
    out, out_d2 = cand.gather(1, pos), d2.gather(1, pos)
    if cand.shape[1] >= emb_c.shape[0]:
        return out, out_d2  # every centre was a candidate
    scale = (emb_y * emb_y).sum(dim=1) + (emb_c * emb_c).sum(dim=1).max()
    unsafe = out_d2[:, -1] >= d2.max(dim=1).values - CUT_ROUNDOFF * scale
    rows = torch.nonzero(unsafe).squeeze(1)
    if rows.numel():
        out[rows], out_d2[rows] = _exhaustive_cut(emb_y[rows], emb_c, k)
    return out, out_d2


def _exhaustive_cut(emb_y: torch.Tensor, emb_c: torch.Tensor, k: int):
    """The ``k`` nearest of all centres under the tie rule, by direct per-pair distances
    (chunks of points bounded by :data:`EXHAUSTIVE_CHUNK_BYTES`): ``(cand, d2)``."""
    n = emb_c.shape[0]
    rows = max(1, EXHAUSTIVE_CHUNK_BYTES // max(1, n * emb_c.shape[1] * emb_c.element_size()))
    cands, d2s = [], []
    for sl in _slices(emb_y.shape[0], rows):
        diff = emb_c[None, :, :] - emb_y[sl, None, :]
        d2 = (diff * diff).sum(dim=2)
        kid = torch.arange(n, device=emb_c.device).expand(d2.shape[0], -1)
        pos = select_by_rule(-d2, None, kid, k)
        cands.append(pos)
        d2s.append(d2.gather(1, pos))
    return torch.cat(cands), torch.cat(d2s)


def _h_by_node_matmul(
    face_ids, bary, local, coef, nodes, weights, field, phi_y=None
) -> torch.Tensor:
    """``h_j(y)`` (P, C): ``coef_j . Phi_y[g]`` for every node g, then j's own 4 nodes."""
    if phi_y is None:
        phi_y = field.node_values(face_ids, bary)  # (P, G, K)
    picked = coef.index_select(0, local.reshape(-1)).view(*local.shape, coef.shape[1])
    dots = torch.bmm(picked, phi_y.transpose(1, 2))  # (P, C, G)
    return (dots.gather(2, nodes[local]) * weights[local]).sum(dim=2)


def _h_by_vertex_pairs(face_ids, bary, local, coef, nodes, weights, field) -> torch.Tensor | None:
    """``h_j(y) = sum_v b_v H_j(v)`` with ``H_j(v)`` computed once per (vertex, kernel) pair.

    ``h`` is linear in the query's barycentrics, so dense queries (baking, rendering: many
    points per face, sorted by face) share the vertex values and need 4 K multiply-adds per
    unique pair instead of G K per (point, candidate). Returns None when the pairs are not
    shared enough to pay off (sparse queries), leaving the matmul path to it.
    """
    n_k = coef.shape[0]
    verts = field.faces[face_ids]  # (P, 3)
    keys = verts[:, :, None] * n_k + local[:, None, :]  # (P, 3, C)
    uniq, inverse = torch.unique(keys, return_inverse=True)
    p, c = local.shape
    if (
        PAIR_PATH == "auto"
        and VERTEX_PATH_COST * uniq.shape[0] * nodes.shape[1] > p * c * field.n_nodes
    ):
        return None
    vert, kern = uniq // n_k, uniq % n_k
    values = torch.empty(uniq.shape[0], dtype=coef.dtype, device=coef.device)
    flat_evecs = field.evecs.reshape(-1, field.k)
    for sl in _slices(uniq.shape[0], PAIR_CHUNK):
        j = kern[sl]
        rows = vert[sl, None] * field.n_nodes + nodes[j]  # (u, 4) rows of the (n*G, K) view
        block = flat_evecs.index_select(0, rows.reshape(-1)).view(-1, nodes.shape[1], field.k)
        at_nodes = torch.bmm(block.to(coef.dtype), coef[j, :, None]).squeeze(2)  # (u, 4)
        values[sl] = (at_nodes * weights[j]).sum(dim=1)
    return (values[inverse] * bary.to(coef.dtype)[:, :, None]).sum(dim=1)


class _Recompute(torch.autograd.Function):
    """Activation checkpointing for one chunk: run ``fn`` without a graph, rebuild it in backward.

    Written here rather than ``torch.utils.checkpoint`` because the latter imports
    ``torch._dynamo`` on first use, which cost ~10 s per process on this machine.
    """

    @staticmethod
    def forward(ctx, fn, *tensors):  # type: ignore[override]
        ctx.fn = fn
        ctx.save_for_backward(*tensors)
        with torch.no_grad():
            return fn(*tensors)

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        needs = ctx.needs_input_grad[1:]
        inputs = [
            t.detach().requires_grad_(n) for t, n in zip(ctx.saved_tensors, needs, strict=True)
        ]
        with torch.enable_grad():
            out = ctx.fn(*inputs)
        wanted = [t for t, n in zip(inputs, needs, strict=True) if n]
        grads = iter(torch.autograd.grad(out, wanted, grad_out, allow_unused=True))
        return (None, *(next(grads) if n else None for n in needs))


def _slices(n: int, size: int) -> list[slice]:
    return [slice(start, min(n, start + size)) for start in range(0, n, size)]


def _long(x: torch.Tensor | np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x).to(device, torch.long)


def _query_float(
    x: torch.Tensor | np.ndarray, device: torch.device, dtype: torch.dtype
) -> torch.Tensor:
    """Query inputs keep their autograd history (gradients may flow to query barycentrics)."""
    if torch.is_tensor(x):
        return x.to(device, dtype)
    return torch.as_tensor(np.asarray(x, dtype=np.float64)).to(device, dtype)


def _float(x: torch.Tensor | np.ndarray, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """A copy: parameters must never alias the caller's arrays (``as_tensor`` of a float64
    array on a float64 CPU field would, and optimiser steps would then write into them)."""
    if torch.is_tensor(x):
        return x.detach().to(device, dtype).clone()
    return torch.tensor(np.asarray(x, dtype=np.float64)).to(device, dtype)
