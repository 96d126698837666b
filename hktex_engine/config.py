"""Configuration records shared by the engine, the CLI and the service.

Reference defaults are those of ALGORITHM.md; each record hashes to a stable key so caches and
kernel-set files can refuse a mismatch instead of silently misreading.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace
from typing import Literal


def stable_hash(payload: dict) -> str:
    """SHA-256 of a canonical JSON rendering (sorted keys, no whitespace)."""
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class SpectralConfig:
    """What decides a spectra artefact: the grid and its numerics.

    ``angles`` nodes span [0, pi] with both ends; ``anisotropies`` are eta values (grid
    coordinate s = ln(1 + eta)). ``k`` defaults to 128, not ALGORITHM.md's 256 nor the 64 it
    was: with the default preset (at t = 0.06245, its diffusion time until the twenty-first
    pass of docs/fitting.md; at 0.0156, K = 256 scored blub -0.36 dB, twenty-second pass) and
    its full 5,000 steps, full default fits on K = 128 against K = 64 (docs/fitting.md, seventh
    pass) scored blub +2.49 dB, bob +0.97 (its paper views from -2.23 to +0.13 dB against
    vertex colours of twice the bytes), spot +0.11, marble +0.09, CesiumMan +0.00, for ~1.25x
    the fit time and 2x the spectra: small
    features (eyes a few hundredths of the mesh wide) are drawn better; K = 256 did worse on
    blub (41.55 dB against 42.65). (At 400 steps of an early configuration 256 had scored no
    better than 64.) The ``earlier`` preset (t = 8.133e-4) needs 256
    (:data:`PRESET_SPECTRA_K`). ``rotation`` is the alignment mode: "block" (Procrustes inside
    clusters of near-equal eigenvalues; every column stays an eigenvector) or "full" (one
    K x K Procrustes as the reference implementation does). "full" was measured to
    interpolate markedly better between nodes (docs/spectra.md, Decisions).
    """

    angles: int = 7
    anisotropies: tuple[float, ...] = (1.0, 5.0, 15.0, 30.0, 60.0, 100.0, 200.0)
    k: int = 128
    k_iso: int = 65
    rotation: Literal["block", "full"] = "block"
    evecs_dtype: Literal["float16", "float32"] = "float16"
    tangent_field: Literal["axis_smoothed", "curvature"] = "axis_smoothed"

    def __post_init__(self) -> None:
        object.__setattr__(self, "anisotropies", tuple(float(a) for a in self.anisotropies))
        if self.angles < 2:
            raise ValueError("angles must be >= 2 (both ends of [0, pi] are nodes)")
        if len(self.anisotropies) < 1 or any(a < 0 for a in self.anisotropies):
            raise ValueError("anisotropies must be a non-empty list of values >= 0")
        if list(self.anisotropies) != sorted(set(self.anisotropies)):
            raise ValueError("anisotropies must be strictly ascending")
        if self.k < 2 or self.k_iso < 3:
            raise ValueError("k must be >= 2 and k_iso >= 3")
        if self.rotation not in ("block", "full"):
            raise ValueError("rotation must be 'block' or 'full'")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["anisotropies"] = list(self.anisotropies)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SpectralConfig:
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        if "anisotropies" in known:
            known["anisotropies"] = tuple(known["anisotropies"])
        return cls(**known)

    def key(self) -> str:
        """Stable hash identifying this configuration (part of the spectra cache key)."""
        return stable_hash(self.to_dict())


@dataclass(frozen=True)
class KernelConfig:
    """Constants of kernel evaluation (ALGORITHM.md section 4-5), stored in every .hkt.

    ``blend`` picks the colour rule: ``"paper"`` is ALGORITHM.md §5's normalised average;
    ``"layered"`` (our extension, ``kernels.blending``) gives each kernel a learnable
    priority, so a small kernel can win over the large ones under it. ``sigma`` picks the
    biharmonic decay's scale: ``"uniform"`` is §4's one ``sigma_b`` for every kernel;
    ``"per_kernel"`` (our extension) gives kernel ``j`` its own ``sigma_j = sigma_b * s_j``
    with a learnt ratio ``s_j`` in :data:`SIGMA_RATIO_RANGE` (docs/fitting.md, fourteenth
    and fifteenth passes), stored as the ``.hkt`` member ``sigma_ratio``. ``colour`` picks
    what a kernel carries: ``"constant"`` is §4's one residual colour ``a_j``; ``"linear"``
    (our extension) adds a slope ``G_j`` (3 x 3) so the kernel's colour at ``y`` is
    ``a_j + G_j (x(y) - x(c_j))``, positions in the spectra's normalised frame, learnt from
    ``FitParams.slope_start`` and stored as the ``.hkt`` member ``color_slopes``
    (docs/fitting.md, eighteenth pass).
    """

    diffusion_time: float = 8.133e-4
    sigma_b: float = 0.05
    k_search: int = 100
    k_blend: int = 10
    blend: Literal["paper", "layered"] = "paper"
    sigma: Literal["uniform", "per_kernel"] = "uniform"
    colour: Literal["constant", "linear"] = "constant"

    def __post_init__(self) -> None:
        if self.blend not in BLENDS:
            raise ValueError(f"blend must be one of {BLENDS}, not {self.blend!r}")
        if self.sigma not in SIGMAS:
            raise ValueError(f"sigma must be one of {SIGMAS}, not {self.sigma!r}")
        if self.colour not in COLOURS:
            raise ValueError(f"colour must be one of {COLOURS}, not {self.colour!r}")

    def to_dict(self) -> dict:
        """The fields; ``sigma`` only when per kernel and ``colour`` only when linear, so a
        §4-5 set's manifest is as before."""
        d = asdict(self)
        if self.sigma == "uniform":
            del d["sigma"]
        if self.colour == "constant":
            del d["colour"]
        return d

    @property
    def per_kernel_sigma(self) -> bool:
        return self.sigma == "per_kernel"

    @property
    def linear_colour(self) -> bool:
        return self.colour == "linear"


#: The colour rules a kernel set may use (``KernelConfig.blend``).
BLENDS = ("paper", "layered")
#: How the biharmonic scale is given (``KernelConfig.sigma``).
SIGMAS = ("uniform", "per_kernel")
#: A per-kernel ``sigma_j / sigma_b``'s box: the probe's (docs/fitting.md, fourteenth pass),
#: where the learnt ratios had median 1.3 and p90 2.3.
SIGMA_RATIO_RANGE = (0.4, 2.5)
#: What a kernel's colour is (``KernelConfig.colour``).
COLOURS = ("constant", "linear")
#: A colour slope's box, per entry, in colour per unit of the normalised frame (a mesh in a
#: box of side 2): across a footprint 0.1 wide the colour may change by up to 3.2, far past
#: what a [0, 1] texture needs; the bound only keeps hostile files finite and decodable.
SLOPE_RANGE = (-32.0, 32.0)


@dataclass(frozen=True)
class DensityRules:
    """Density control (ALGORITHM.md section 7); fractions of the total steps T.

    ``stats`` says how the window's statistics are reduced: ``"mean"`` (our first reading:
    a kernel's error and contribution averaged over the points it served) or
    ``"step_sum"`` (ALGORITHM.md §7b, both configurations of the authors: summed over the
    points of each step, then averaged over the window's steps, so they grow with points
    per step and with a kernel's footprint). ``prune_at`` lists explicit prune fractions
    (§7b: 0.2 and 0.4) instead of the ``prune_from``/``until``/``every`` range.
    """

    prune_from: float = 0.2
    prune_until: float = 0.6
    prune_every: float = 0.1
    prune_at: tuple[float, ...] = ()
    densify_from: float = 0.05
    densify_until: float = 0.7
    densify_every: float = 0.04
    window: float = 0.05
    min_hits_fraction: float = 0.02
    min_contribution: float = 0.07
    error_threshold: float = 0.0208
    max_growth: float = 0.4
    floor: int = 100
    split_size: float = 0.235
    split_offset: float = 0.2
    split_shrink: float = 1.6
    stats: Literal["mean", "step_sum"] = "mean"

    def __post_init__(self) -> None:
        object.__setattr__(self, "prune_at", tuple(float(f) for f in self.prune_at))
        if self.stats not in ("mean", "step_sum"):
            raise ValueError("density stats must be 'mean' or 'step_sum'")


@dataclass(frozen=True)
class FitParams:
    """Fitting parameters (ALGORITHM.md sections 6-8), reference defaults.

    Field names mirror the CLI flags and the API's ``params`` object. ``loss`` is the point
    loss (``"smooth_l1"``, beta 1, or ``"mse"``); ``loss_sum_rgb`` sums it over the three
    channels before averaging over points (§7b: the authors' reduction; a mean over all
    3P elements makes the centres' SGD gradient 3x smaller). ``init`` picks the initial
    threshold/sharpness distributions (``"earlier"``: eps ~ U(0.9, 1), k ~ 10 + 40U;
    ``"later"``: eps ~ 0.3 + 0.7 U^0.7, k ~ 10 + 40 U^0.5). ``polish_colors`` solves the
    colours exactly by least squares for the final footprints after the last step
    (the albedo is linear in them; ``fitting/colour_solve.py``). ``sampling`` picks the
    training points: ``"uniform"`` draws fresh area-uniform points every step; ``"error"``
    draws from a fixed pool of ``sampling_pool`` area-uniform points (at most the fit's
    steps x points per step), a share ``sampling_mix``
    uniformly and the rest in proportion to each point's last residual (after the first
    ``sampling_warmup`` fraction of the steps, uniform until then), weighted so the loss stays
    the surface mean (``fitting/error_sampling.py``).
    """

    kernels: int = 10_000
    max_kernels: int | None = None  # default 7 x kernels
    steps: int = 10_000
    points_per_step: int = 512
    seed: int = 0
    lr_colors: float = 0.0112
    lr_theta: float = 0.005
    lr_eta: float = 0.005
    lr_threshold: float = 0.0089
    lr_sharpness: float = 0.0055
    lr_base: float = 0.001
    lr_centers: float = 0.099
    lr_priority: float = 0.02
    #: Adam's rate on ``log(sigma_j / sigma_b)`` (``KernelConfig.sigma = "per_kernel"`` only)
    lr_sigma: float = 0.01
    #: a per-kernel sigma stays sigma_B (every ratio 1) before this fraction of the steps
    sigma_start: float = 0.0
    #: the layered blend's priorities stay 0 (the paper's blend) before this fraction of steps
    priority_start: float = 0.0
    #: Adam's rate on the colour slopes (``KernelConfig.colour = "linear"`` only): the colours'
    #: rate times 20, so a slope moves a footprint ~0.05 across by about what a colour step does
    lr_slopes: float = 0.12
    #: linear colours' slopes stay 0 (§4's flat colours) before this fraction of the steps;
    #: 0.4, the per-kernel sigma's measured start, measured for them too (docs/fitting.md,
    #: eighteenth pass)
    slope_start: float = 0.4
    center_momentum: float = 0.0
    lr_decay_every: int = 1000
    lr_decay: float = 0.5
    densify: bool = True
    checkpoint_every: int = 500
    kernel: KernelConfig = field(default_factory=KernelConfig)
    budget_factor: float = 7.0
    loss: Literal["smooth_l1", "mse"] = "smooth_l1"
    loss_sum_rgb: bool = False
    init: Literal["earlier", "later"] = "earlier"
    density: DensityRules = field(default_factory=DensityRules)
    polish_colors: bool = False
    sampling: Literal["uniform", "error"] = "uniform"
    sampling_pool: int = 1_000_000
    sampling_mix: float = 0.5
    sampling_warmup: float = 0.05

    def __post_init__(self) -> None:
        if self.sampling not in ("uniform", "error"):
            raise ValueError("sampling must be 'uniform' or 'error'")
        if not 0.0 < self.sampling_mix <= 1.0 or not 0.0 <= self.sampling_warmup <= 1.0:
            raise ValueError("sampling_mix must be in (0, 1] and sampling_warmup in [0, 1]")
        if self.sampling_pool < 1:
            raise ValueError("sampling_pool must be >= 1")
        if isinstance(self.kernel, dict):
            object.__setattr__(self, "kernel", KernelConfig(**self.kernel))
        if isinstance(self.density, dict):
            object.__setattr__(self, "density", DensityRules(**self.density))
        if self.loss not in ("smooth_l1", "mse"):
            raise ValueError("loss must be 'smooth_l1' or 'mse'")
        if self.init not in ("earlier", "later"):
            raise ValueError("init must be 'earlier' or 'later'")

    @property
    def budget(self) -> int:
        if self.max_kernels is not None:
            return self.max_kernels
        return int(round(self.budget_factor * self.kernels))


#: ALGORITHM.md §7b, the authors' later configuration (their ablation base, likely Table 1's).
LATER_KERNEL = KernelConfig(diffusion_time=0.06245, sigma_b=0.05, k_search=50, k_blend=30)
LATER_DENSITY = DensityRules(
    prune_at=(0.2, 0.4),
    min_hits_fraction=0.00169,
    densify_from=0.08,
    densify_until=0.7,
    densify_every=0.02,
    error_threshold=0.0237,
    split_size=0.174,
    split_offset=0.15,
    stats="step_sum",
)

#: Named, complete configurations: ``"earlier"`` is ALGORITHM.md §4-8's reference defaults
#: (the authors' earlier UV configuration), ``"later"`` their later one (§7b) as a whole,
#: ``"default"`` (added below) the later one with the colour solve: what a fit uses unnamed.
PRESETS: dict[str, FitParams] = {
    "earlier": FitParams(),
    "later": FitParams(
        kernels=1_000,
        budget_factor=5.0,
        steps=5_000,
        points_per_step=4_096,
        lr_colors=0.00615,
        lr_theta=0.0993,
        lr_eta=0.00467,
        lr_threshold=0.00109,
        lr_sharpness=0.00129,
        lr_base=0.00096,
        lr_centers=0.0991,
        center_momentum=0.9,
        loss="mse",
        loss_sum_rgb=True,
        init="later",
        density=LATER_DENSITY,
        kernel=LATER_KERNEL,
    ),
}


#: ``lr_sharpness`` 0.2 instead of the later configuration's 0.00129: with projected Adam on the
#: raw sharpness that rate moves ``k`` by at most ~2.5 over a whole fit, so every kernel kept
#: its initial 10-50 and edges stayed soft; at 0.2 all five shared meshes gained 0.6-4.5 dB
#: (benchmarks/results/fidelity.md, rows ``default:{"lr_sharpness":0.2}``; docs/fitting.md).
DEFAULT_LR_SHARPNESS = 0.2
#: ``lr_threshold`` 0.0055 instead of the later configuration's 0.00109: once edges sharpen, the
#: level set each kernel cuts (its threshold) has to move with them; in seven paired fits on
#: two VMs 5x the rate gained +0.26..+3.41 dB six times and lost 1.32 dB once (blub, inside its
#: machine-to-machine spread), with 10-18 % fewer kernels surviving (benchmarks/results/
#: fidelity.md; docs/fitting.md, sixth pass; 0.02 on spot: 44.27 dB against 44.13).
DEFAULT_LR_THRESHOLD = 0.0055
#: ``σ_B`` 0.025 instead of the later configuration's 0.05: the biharmonic decay bounds every
#: footprint (``r ≤ w``), and a footprint of radius R cut at the level ``ε = w(R)`` has an edge
#: ``~4σ_B² / (k ε R)`` wide, so discs much under σ_B (blub's eyes: 0.4-0.65 σ_B) came out as
#: blurred caps with ε and k pinned at their bounds. At 0.03 all six meshes gained
#: (+0.28..+3.81 dB surface, views too; docs/fitting.md, eleventh pass); 0.025 gained again on
#: five of six (blub +0.98 over two seeds, CesiumMan +0.55 over three; spot −0.16 over two)
#: and 0.02 lost on both meshes tried (twelfth pass). All within §4-5 as written: σ_B is in
#: every file.
DEFAULT_SIGMA_B = 0.025
#: Diffusion time ``t`` = 0.0156125, a quarter of the later configuration's 0.06245: with σ_B
#: at 0.025 the biharmonic factor cuts every footprint to its size, and a narrower heat kernel
#: keeps more of its anisotropy inside that cut (a footprint's shape comes from ``h``). Paired
#: full default fits on one VM (docs/fitting.md, twenty-first pass): blub +0.44 / +0.58 dB
#: (seeds 0 / 2), bob +0.47, CesiumMan +1.53, marble +0.07, spot −0.18 / −0.67 (seeds 0 / 1);
#: mean +0.43 (seeds averaged), the held-out torus +0.22. The
#: kernel is then truncated at K = 128 (``exp(−t λ_K)`` 0.62-0.86), which the fits absorb.
#: Halving it (0.031) had lost at σ_B 0.05 (seventh pass) and gained +0.28 on blub at 0.025.
DEFAULT_DIFFUSION_TIME = 0.0156125
#: Densification threshold 0.012, half the later configuration's 0.0237: more new kernels
#: where the error is. Paired full fits at the new ``t`` (docs/fitting.md, twenty-second
#: pass): blub +1.15 / +1.08 dB (seeds 0 / 2; over seeds 0-5 48.52 against the MLP's 48.27,
#: above it on four paired seeds of six), spot +0.71 / +1.56 (seeds 0 / 1), the held-out
#: torus +0.16, bob −0.01 / +0.18; CesiumMan and marble identical (their 5,000-kernel budget
#: binds either way); 30-57 % more bytes where it does not bind. ``"compact"`` keeps 0.0237
#: for a user who wants the smaller file.
DEFAULT_ERROR_THRESHOLD = 0.012
PRESETS["default"] = replace(
    PRESETS["later"],
    polish_colors=True,
    sampling="error",
    lr_sharpness=DEFAULT_LR_SHARPNESS,
    lr_threshold=DEFAULT_LR_THRESHOLD,
    kernel=replace(LATER_KERNEL, sigma_b=DEFAULT_SIGMA_B, diffusion_time=DEFAULT_DIFFUSION_TIME),
    density=replace(LATER_DENSITY, error_threshold=DEFAULT_ERROR_THRESHOLD),
)

#: ``"compact"``: the default with the later configuration's densification threshold 0.0237
#: (the default until the twenty-second pass): 23-36 % smaller files where the kernel budget
#: does not bind, for 0.7-1.6 dB less on blub and spot and 0-0.2 on bob (docs/fitting.md,
#: twenty-first and twenty-second passes). Its files are plain §4-5 sets.
PRESETS["compact"] = replace(PRESETS["default"], density=LATER_DENSITY)

#: ``"layered"``: the default with the layered blend (``kernels.blending``), its priorities
#: trained over the last 30 % of the steps only, after density control has placed the
#: footprints. On the present default (docs/fitting.md, twenty-third pass) it gained on spot,
#: CesiumMan, blub, marble and the held-out torus (+0.08..+1.02 dB) and lost on bob (−0.74 /
#: −0.91 over two seeds); on the default of σ_B 0.03 it had gained on spot, bob and CesiumMan
#: (+0.55..+1.07) and lost on blub (−0.90; eleventh pass). It writes ``.hkt`` versions 5/6,
#: which a reader of ALGORITHM.md §5 alone cannot score right (blub at σ_B 0.05: 44.95 dB read
#: as fitted, 39.38 with the priorities dropped): a named choice, not the default.
PRESETS["layered"] = replace(
    PRESETS["default"],
    kernel=replace(PRESETS["default"].kernel, blend="layered"),
    priority_start=0.7,
)

#: ``"dense"``: the default at the diffusion time its threshold was measured on (``t`` =
#: 0.06245, the twentieth pass's default, where halving the threshold 0.0237 -> 0.012 put
#: more new kernels where the error is). Measured with the full fit
#: (docs/fitting.md, thirteenth pass): blub +0.70 dB over four seeds, spot +1.04 and bob +0.26
#: over two, the torus +0.12, CesiumMan and marble unchanged. The default has had its
#: threshold since the twenty-second pass (at ``t`` = 0.0156125, where blub scores ~1 dB
#: more); ``dense`` stays as measured because ``--preset dense --sigma per_kernel`` is the
#: pair measured in the sixteenth pass (the ``sigma`` preset on the present default is above
#: it on blub and bob, below on spot: twenty-third pass). Its files are plain §4-5 sets.
PRESETS["dense"] = replace(
    PRESETS["default"],
    kernel=replace(PRESETS["default"].kernel, diffusion_time=LATER_KERNEL.diffusion_time),
)

#: ``"sigma"``: the default with a biharmonic scale learnt per kernel (``KernelConfig.sigma =
#: "per_kernel"``): a footprint can then be longer than the one ``sigma_b`` lets it be
#: (blub's eyes). Measured in docs/fitting.md (fourteenth pass: a probe; fifteenth: this
#: preset; sixteenth: the scales learnt from 40 % of the steps, ``SIGMA_PRESET_START``;
#: twenty-third: on the present default, above it on every mesh measured, and above the
#: preset's earlier base on all but one fit). It is exactly ``hktex fit --sigma per_kernel``.
#: Its files are ``.hkt`` versions 7/8, which a reader of §4-5 alone cannot score.
SIGMA_PRESET_START = 0.4
PRESETS["sigma"] = replace(
    PRESETS["default"],
    kernel=replace(PRESETS["default"].kernel, sigma="per_kernel"),
    sigma_start=SIGMA_PRESET_START,
)

#: The preset a fit starts from when none is named: ``"default"``, the authors' later
#: configuration plus the least-squares colour solve and error-driven training points, chosen
#: by measurement (docs/fitting.md, "Choosing the defaults"; benchmarks/results/fidelity.md).
DEFAULT_PRESET = "default"


#: Spectra K a preset needs when the caller names none: the earlier regime's thin kernels
#: (t = 8.133e-4) are truncation-dominated even at 256 (ALGORITHM.md §7b); others use the
#: SpectralConfig default.
PRESET_SPECTRA_K: dict[str, int] = {"earlier": 256}


def spectra_k_for(preset: str | None) -> int:
    """The spectra's K for a fit with ``preset`` (None: the default preset)."""
    return PRESET_SPECTRA_K.get(preset or DEFAULT_PRESET, SpectralConfig().k)


def fit_preset(name: str, **overrides) -> FitParams:
    """The named preset with ``overrides`` applied (unknown names are a ValueError)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    base = PRESETS[name]
    return replace(base, **overrides) if overrides else base


def fit_params_from(values: dict) -> FitParams:
    """FitParams from a flat mapping (CLI flags, the API's ``params``): ``preset`` picks the
    base (default ``DEFAULT_PRESET``), every other known, non-None field overrides it
    (``blend``: the kernel config's colour rule; ``sigma``: its biharmonic scale, where
    ``"per_kernel"`` on a preset that learns none also takes the ``sigma`` preset's start
    unless ``sigma_start`` is given, so ``dense`` + ``per_kernel`` is the measured pair;
    ``colour``: ``"linear"`` trains a colour slope per kernel from ``slope_start``)."""
    given = {
        k: v for k, v in values.items() if v is not None and k in FitParams.__dataclass_fields__
    }
    params = fit_preset(values.get("preset") or DEFAULT_PRESET, **given)
    # KernelConfig fields, flat in flags and the API
    flat = {k: values[k] for k in ("blend", "sigma", "colour") if values.get(k) is not None}
    if flat:
        learnt_before = params.kernel.per_kernel_sigma
        params = replace(params, kernel=replace(params.kernel, **flat))
        if params.kernel.per_kernel_sigma and not learnt_before and "sigma_start" not in given:
            params = replace(params, sigma_start=SIGMA_PRESET_START)
    return params
