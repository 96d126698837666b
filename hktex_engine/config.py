"""Configuration records shared by the engine, the CLI and the service.

Reference defaults are those of ALGORITHM.md; each record hashes to a stable key so caches and
kernel-set files can refuse a mismatch instead of silently misreading.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from typing import Literal


def stable_hash(payload: dict) -> str:
    """SHA-256 of a canonical JSON rendering (sorted keys, no whitespace)."""
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class SpectralConfig:
    """What decides a spectra artefact: the grid and its numerics.

    ``angles`` nodes span [0, pi] with both ends; ``anisotropies`` are eta values (grid
    coordinate s = ln(1 + eta)). ``rotation`` is the alignment mode: "block" (Procrustes inside
    clusters of near-equal eigenvalues; every column stays an eigenvector) or "full" (one
    K x K Procrustes as the reference implementation does). "full" was measured to
    interpolate markedly better between nodes (docs/spectra.md, Decisions).
    """

    angles: int = 7
    anisotropies: tuple[float, ...] = (1.0, 5.0, 15.0, 30.0, 60.0, 100.0, 200.0)
    k: int = 256
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
    """Constants of kernel evaluation (ALGORITHM.md section 4-5), stored in every .hkt."""

    diffusion_time: float = 8.133e-4
    sigma_b: float = 0.05
    k_search: int = 100
    k_blend: int = 10

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FitParams:
    """Fitting parameters (ALGORITHM.md sections 6-8), reference defaults.

    Field names mirror the CLI flags and the API's ``params`` object.
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
    center_momentum: float = 0.0
    lr_decay_every: int = 1000
    lr_decay: float = 0.5
    densify: bool = True
    checkpoint_every: int = 500
    kernel: KernelConfig = field(default_factory=KernelConfig)

    @property
    def budget(self) -> int:
        return self.max_kernels if self.max_kernels is not None else 7 * self.kernels
