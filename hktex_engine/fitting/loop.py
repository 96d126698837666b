"""The shared fit loop (ALGORITHM.md sections 6-8), used by UV and multi-view fitting.

A task supplies an :class:`Objective`: it draws a batch (``sample``) and turns the model's
albedo on that batch into a scalar loss plus per-point statistics (``loss``). Everything else
is common and lives here: the optimiser step, density control, refreshing the model's query
state after centres move, progress reports (at most ~1/s), cooperative cancellation, periodic
atomic checkpoints and resume from the latest one.

Why the objective returns per-point statistics rather than the loop re-evaluating the model:
a renderer-based objective only knows its points (ray hits) and their errors after rendering,
and density control needs exactly those points' final top-K_c kernels and responses.

Resume is bitwise: every source of state the loop consumes (model rows, optimiser state,
density statistics, the numpy generator's state, the step) is checkpointed; nothing else in
the loop draws random numbers.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from hktex_engine.config import FitParams
from hktex_engine.errors import Cancelled, HKTexError
from hktex_engine.fitting.density import DensityController, load_rows
from hktex_engine.fitting.optimise import KERNEL_ATTRIBUTES, KernelOptimiser, Tracer
from hktex_engine.progress import Progress, check_cancel

CHECKPOINT_FORMAT = "hktex-fit-checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(HKTexError):
    """A checkpoint directory belongs to another fit (other mesh, params or task)."""


@dataclass
class PointStats:
    """Per-point facts one loss evaluation learned, for density control.

    ``l1_error`` is the mean absolute RGB error per point (P,); ``topk`` the indices of the
    point's final K_c kernels (P, K_c), -1 where fewer exist; ``rho`` their responses (P, K_c).
    ``face_ids``/``bary`` locate the points (ray hits for a renderer) and are optional.
    ``weights`` (P,): importance weights of points not drawn uniformly (error sampling), so
    the density statistics stay estimates of the uniform ones; None means 1 each.
    """

    l1_error: torch.Tensor
    topk: torch.Tensor
    rho: torch.Tensor
    face_ids: torch.Tensor | None = None
    bary: torch.Tensor | None = None
    weights: torch.Tensor | None = None


class Objective(Protocol):
    """What a fitting task provides to :func:`run_fit`."""

    def sample(self, step: int, rng: np.random.Generator) -> Any:
        """Draw the batch for ``step`` using only ``rng`` (so resume reproduces it)."""

    def loss(self, model: torch.nn.Module, batch: Any) -> tuple[torch.Tensor, PointStats]:
        """Differentiable scalar loss of ``model`` on ``batch`` and its per-point stats."""


@dataclass
class LoopResult:
    """What the loop did: final step, seconds spent in this call, loss/kernel-count history."""

    steps: int
    seconds: float
    steps_run: int
    resumed_from: int | None
    losses: list[float] = field(default_factory=list)
    kernel_counts: list[int] = field(default_factory=list)
    density_events: list[dict] = field(default_factory=list)

    @property
    def steps_per_second(self) -> float:
        return self.steps_run / self.seconds if self.seconds > 0 else float("nan")


LOSS_CURVE_POINTS = 200


def loss_curve(
    losses: list[float], last_step: int, max_points: int = LOSS_CURVE_POINTS
) -> list[list[float]]:
    """``[step, loss]`` pairs for a record or a plot: each the mean loss over one of at most
    ``max_points`` runs of consecutive steps, at the run's last step.

    Why this exists: progress reaches a client at most once a second, so a fit faster than
    that (a small test, a fast GPU) reports one loss, and a long one reports thousands of
    raw, noisy values. A stored curve of means has a fixed size and keeps the trend. The
    steps count back from ``last_step``: a resumed fit's ``losses`` hold only the steps it ran.
    """
    values = np.asarray(losses, dtype=np.float64)
    if values.size == 0:
        return []
    first = int(last_step) - values.size + 1
    chunks = np.array_split(np.arange(values.size), min(int(max_points), values.size))
    return [[first + int(c[-1]), float(values[c].mean())] for c in chunks]


@contextlib.contextmanager
def _deterministic(enabled: bool) -> Iterator[None]:
    """``torch.use_deterministic_algorithms`` (warn only) while the loop runs, when ``enabled``;
    the caller's setting is restored afterwards either way."""
    previous = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
    )
    if enabled:
        torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])


def run_fit(
    model: torch.nn.Module,
    objective: Objective,
    params: FitParams,
    tracer: Tracer,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    face_frames: torch.Tensor,
    *,
    rng: np.random.Generator | None = None,
    progress: Progress | None = None,
    checkpoint_dir: str | Path | None = None,
    fingerprint: dict | None = None,
    momentum: float | None = None,
    on_step: Callable[[int, float], None] | None = None,
    deterministic: bool = True,
    transport_theta: bool = False,
) -> LoopResult:
    """Optimise ``model`` in place for ``params.steps`` steps, resuming from a checkpoint.

    ``vertices``/``faces``/``face_frames`` are the normalised mesh (spectra frame) on the
    model's device; ``tracer`` walks geodesics on the same mesh. ``fingerprint`` (JSON-able)
    identifies the fit; a checkpoint with another fingerprint is refused. ``momentum``
    overrides ``params.center_momentum`` (multi-view uses 0.9). ``deterministic`` runs the
    loop under ``torch.use_deterministic_algorithms`` (restored afterwards): without it the
    parallel scatter-adds of the backward pass sum in a thread-dependent order and two runs
    with one seed differ by float rounding (measured: 3e-8..2e-7 after 8 steps on 2 threads).
    Only on the CPU: CUDA runs are not bitwise reproducible anyway (atomics in many kernels)
    and the setting would make torch warn or fail on ops without a deterministic kernel.
    ``transport_theta`` re-expresses theta when a centre (or a split child) lands in another
    face by parallel-transporting its axis (``optimise.theta_in_faces``). Off by default:
    the kernel of a fixed theta is a continuous function of its centre across an edge (the
    spectral basis is a global field at angle theta from every face's u_ref), re-expressing
    makes it jump, and it measured worse (docs/fitting.md, "Orientation across faces").
    """
    with _deterministic(deterministic and model.base_color.device.type == "cpu"):
        rng = rng if rng is not None else np.random.default_rng(params.seed)
        total = int(params.steps)
        opt = KernelOptimiser(
            model,
            params,
            tracer,
            vertices,
            faces,
            momentum=momentum,
            face_frames=face_frames if transport_theta else None,
        )
        density = DensityController(
            params, total, vertices, faces, face_frames, tracer, transport_theta=transport_theta
        )
        ckpt = Path(checkpoint_dir) if checkpoint_dir is not None else None
        fp = {"format": CHECKPOINT_FORMAT, **(fingerprint or {})}
        start, resumed_from = 0, None
        if ckpt is not None:
            found = latest_checkpoint(ckpt)
            if found is not None:
                start = load_checkpoint(found, model, opt, density, rng, fp, objective)
                resumed_from = start
                model.refresh()
        density.bind(model)
        result = LoopResult(steps=start, seconds=0.0, steps_run=0, resumed_from=resumed_from)
        t0 = time.perf_counter()
        last_report = -1.0
        step = start
        try:
            while step < total:
                check_cancel(progress)
                batch = objective.sample(step, rng)
                opt.zero_grad()
                loss, stats = objective.loss(model, batch)
                loss.backward()
                density.record(stats)
                opt.step(step)  # set_centres invalidates the model's KNN/centre caches itself
                step += 1
                loss_value = float(loss.detach())
                # Drop the autograd graph before kernels are added or removed: a live graph keeps
                # each parameter's gradient accumulator, which remembers the old row count.
                del loss, stats, batch
                if density.act(step, model, opt):
                    model.refresh()
                result.losses.append(loss_value)
                result.kernel_counts.append(int(model.face_ids.shape[0]))
                if on_step is not None:
                    on_step(step, loss_value)
                now = time.perf_counter()
                if progress is not None and (now - last_report >= 1.0 or step == total):
                    progress.update(step, total, loss=loss_value, kernels=result.kernel_counts[-1])
                    last_report = now
                if ckpt is not None and params.checkpoint_every > 0:
                    if step % params.checkpoint_every == 0 and step < total:
                        save_checkpoint(ckpt, step, model, opt, density, rng, fp, objective)
        except Cancelled:
            if ckpt is not None:
                save_checkpoint(ckpt, step, model, opt, density, rng, fp, objective)
            raise
        result.steps = step
        result.density_events = list(density.events)
        result.steps_run = step - start
        result.seconds = time.perf_counter() - t0
        return result


# --- checkpoints ----------------------------------------------------------------------------


def _step_dir(root: Path, step: int) -> Path:
    return root / f"step-{step:09d}"


def latest_checkpoint(root: Path) -> Path | None:
    """The complete checkpoint with the highest step (incomplete ones never get this name)."""
    if not root.is_dir():
        return None
    found = sorted(p for p in root.glob("step-*") if (p / "meta.json").is_file())
    return found[-1] if found else None


def save_checkpoint(
    root: Path,
    step: int,
    model: torch.nn.Module,
    opt: KernelOptimiser,
    density: DensityController,
    rng: np.random.Generator,
    fingerprint: dict,
    objective: Objective | None = None,
) -> Path:
    """Write params + optimiser + density stats + rng to ``root/step-N`` atomically.

    The directory is built under a temporary name and renamed into place, so a reader (or a
    resume after a crash) never sees half a checkpoint; older checkpoints are then removed.
    """
    root.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {}
    for name in (*KERNEL_ATTRIBUTES, "base_color"):
        arrays[f"model.{name}"] = getattr(model, name).detach().cpu().numpy()
    arrays.update(opt.state_arrays())
    arrays.update(density.state_arrays())
    if hasattr(objective, "state_arrays"):  # objectives with state of their own (sampler)
        arrays.update(objective.state_arrays())
    meta = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "step": int(step),
        "fingerprint": fingerprint,
        "rng": rng.bit_generator.state,
        "density": density.state_meta(),
    }
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-ckpt-", dir=root))
    try:
        np.savez(tmp / "state.npz", **arrays)
        (tmp / "meta.json").write_text(json.dumps(meta, default=int))
        final = _step_dir(root, step)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in root.glob("step-*"):
        if old != final:
            shutil.rmtree(old, ignore_errors=True)
    return final


def load_checkpoint(
    path: Path,
    model: torch.nn.Module,
    opt: KernelOptimiser,
    density: DensityController,
    rng: np.random.Generator,
    fingerprint: dict,
    objective: Objective | None = None,
) -> int:
    """Restore everything :func:`save_checkpoint` wrote; returns the step to continue from."""
    meta = json.loads((path / "meta.json").read_text())
    if meta.get("format") != CHECKPOINT_FORMAT or meta.get("fingerprint") != json.loads(
        json.dumps(fingerprint, default=int)
    ):
        raise CheckpointError(
            f"checkpoint {path} belongs to another fit; use a fresh checkpoint directory"
        )
    device = model.base_color.device
    with np.load(path / "state.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    n = int(arrays["model.face_ids"].shape[0])
    # checkpoints written before the colour slopes existed hold none: zero slopes are what
    # those fits had
    arrays.setdefault("model.color_slopes", np.zeros((n, 3, 3)))
    rows = {
        name: torch.as_tensor(arrays[f"model.{name}"], device=device) for name in KERNEL_ATTRIBUTES
    }
    load_rows(model, rows)
    with torch.no_grad():
        model.base_color.copy_(torch.as_tensor(arrays["model.base_color"], device=device))
    opt.load_state_arrays(arrays, device)
    density.load_state(arrays, meta["density"], device)
    if hasattr(objective, "load_state_arrays"):
        objective.load_state_arrays(arrays)
    rng.bit_generator.state = meta["rng"]
    return int(meta["step"])
