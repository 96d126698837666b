"""UV fitting: learn a kernel set from a mesh's own albedo texture (ALGORITHM.md section 8).

Supervision is free and exact: any surface point's target is the bilinear lookup of the
texture at its interpolated UV, so each step draws fresh area-uniform points (no fixed
training set to overfit) and the loss is smooth-L1 with beta = 1 (half the squared error for
colours in [0, 1]). The loop itself (optimiser, density control, checkpoints) is the shared
one of :mod:`hktex_engine.fitting.loop`.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from hktex_engine.config import DEFAULT_PRESET, FitParams, fit_preset
from hktex_engine.errors import SpectraError, TextureError
from hktex_engine.evaluation.metrics import psnr, storage_bytes, surface_samples
from hktex_engine.fitting.colour_solve import solve_colours
from hktex_engine.fitting.error_sampling import ErrorSampler, weighted_batch
from hktex_engine.fitting.loop import LoopResult, PointStats, run_fit
from hktex_engine.geometry.geodesics import SurfaceTracer
from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.sampling import (
    farthest_point_sampling,
    points_from_barycentric,
    sample_surface,
    texture_gradient_energy,
    texture_lookup,
    uv_at,
)
from hktex_engine.kernels.model import HeatKernelModel, KernelSet
from hktex_engine.progress import Progress
from hktex_engine.spectra.grid import Spectra
from hktex_engine.spectra.interpolation import SpectralField, resolve_device

#: EVALUATION.md: surface PSNR on 60,000 area-uniform points with a fixed seed
EVAL_POINTS = 60_000
EVAL_SEED = 0
#: Points the quantised widths are chosen on (their own seed: the score stays on the evaluation
#: points, which the choice never saw).
QUANT_CHOICE_POINTS = 20_000
#: Points the colour solve is validated on before it is kept (their own seed, as above).
VALIDATION_POINTS = 20_000
#: points per no-grad evaluation chunk (bounded memory: P x K_s x G dot products)
EVAL_CHUNK = 4096
#: points per kernel for the final colour solve (``FitParams.polish_colors``): ~2-3 x K_c
#: samples per unknown colour keep the solve well determined without dominating the fit time
POLISH_POINTS_PER_KERNEL = 30
#: seed-stream label of the error sampler's point pool (independent of the loop's rng)
POOL_STREAM = 0x5A3


@dataclass
class FitResult:
    """A fitted kernel set with its metrics (PSNR, bytes, kernel count, speed) and timings."""

    kernelset: KernelSet
    metrics: dict
    timings: dict
    losses: list[float] = field(default_factory=list)
    density_events: list[dict] = field(default_factory=list)


def point_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    params: FitParams,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """The fit's loss over a batch of (P, 3) colours, as ``params`` names it.

    ``loss_sum_rgb`` sums over the channels and averages over points (ALGORITHM.md §7b),
    otherwise the mean runs over all 3P elements (our first reading); the two differ by
    exactly a factor 3, which matters for the centres' plain SGD (Adam is scale-free).
    ``weights`` (P,): importance weights of the points (error sampling), mean 1 in expectation.
    """
    if params.loss == "mse":
        per = (pred - target) ** 2
    else:
        per = torch.nn.functional.smooth_l1_loss(pred, target, beta=1.0, reduction="none")
    per = per.sum(dim=1) if params.loss_sum_rgb else per.mean(dim=1)
    return (per * weights).mean() if weights is not None else per.mean()


class UVObjective:
    """Area-uniform points each step; target = the texture at their UV; the params' loss."""

    def __init__(
        self,
        mesh: Mesh,
        n_points: int,
        device: torch.device,
        dtype: torch.dtype,
        params: FitParams | None = None,
    ):
        self.mesh = mesh
        self.n_points = int(n_points)
        self.device = device
        self.dtype = dtype
        self.params = params or fit_preset(DEFAULT_PRESET)
        self.sampler: ErrorSampler | None = None
        if self.params.sampling == "error":
            # its own stream, so the pool does not shift the loop's draws (resume replays them)
            pool_rng = np.random.default_rng([self.params.seed, POOL_STREAM])
            # never more points than the fit will draw: the rest could only ever score unseen
            draws = max(1, self.params.steps) * self.n_points
            pool = min(self.params.sampling_pool, draws)
            self.sampler = ErrorSampler(mesh, pool, self.params.sampling_mix, pool_rng)
        self.warmup_steps = int(round(self.params.sampling_warmup * self.params.steps))

    def sample(self, step: int, rng: np.random.Generator):
        if self.sampler is not None:
            driven = step >= self.warmup_steps
            return weighted_batch(self.sampler, self.n_points, rng, driven, self.device, self.dtype)
        face_ids, bary = sample_surface(self.mesh.vertices, self.mesh.faces, self.n_points, rng)
        target = texture_lookup(self.mesh.texture, uv_at(self.mesh.corner_uvs, face_ids, bary))
        return (
            torch.as_tensor(face_ids, device=self.device),
            torch.as_tensor(bary, device=self.device, dtype=self.dtype),
            torch.as_tensor(np.asarray(target, np.float64), device=self.device, dtype=self.dtype),
        )

    def loss(self, model: HeatKernelModel, batch) -> tuple[torch.Tensor, PointStats]:
        face_ids, bary, target = batch[:3]
        weights = batch[3] if len(batch) > 3 else None
        pred, aux = model.albedo(face_ids, bary, return_aux=True)
        loss = point_loss(pred, target, self.params, weights)
        residual = pred.detach() - target
        if self.sampler is not None:
            self.sampler.update(batch[4], residual.norm(dim=1).cpu().numpy())
        err = residual.abs().mean(dim=1)
        stats = PointStats(err, aux["indices"], aux["rho"].detach(), face_ids, bary, weights)
        return loss, stats

    def state_arrays(self) -> dict[str, np.ndarray]:
        """What a checkpoint must keep of the objective (the sampler's scores)."""
        return self.sampler.state_arrays() if self.sampler is not None else {}

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        if self.sampler is not None:
            self.sampler.load_state_arrays(arrays)


def initial_kernelset(
    mesh: Mesh,
    spectra: Spectra,
    params: FitParams,
    rng: np.random.Generator,
    threshold_range: tuple[float, float] = (0.9, 1.0),
) -> KernelSet:
    """The starting kernels of ALGORITHM.md section 8 (UV fitting).

    Centres: farthest-point sampling over area-uniform candidates (even coverage), then half of
    them re-drawn among the candidates in proportion to the squared texture gradient (kernels
    where the detail is). Colours: the texture at the centres, their mean as ``a_0`` and the
    residuals as ``a_j``. Shape attributes drawn from the reference distributions.
    """
    n = int(params.kernels)
    n_cand = int(min(max(4 * n, 8 * 1024), 200_000))
    cand_f, cand_b = sample_surface(mesh.vertices, mesh.faces, n_cand, rng)
    pts = points_from_barycentric(mesh.vertices, mesh.faces, cand_f, cand_b)
    n = min(n, n_cand)
    chosen = farthest_point_sampling(pts, n, rng)
    cand_uv = uv_at(mesh.corner_uvs, cand_f, cand_b)
    energy = texture_lookup(texture_gradient_energy(mesh.texture)[..., None], cand_uv)[:, 0]
    energy = np.clip(energy, 0.0, None)
    n_redraw = n // 2
    if n_redraw and energy.sum() > 0:
        free = np.setdiff1d(np.arange(n_cand), chosen)
        p = energy[free] / energy[free].sum() if energy[free].sum() > 0 else None
        k = min(n_redraw, int(np.count_nonzero(energy[free])) if p is not None else 0)
        if k:
            replace_at = rng.choice(n, size=k, replace=False)
            chosen = chosen.copy()
            chosen[replace_at] = rng.choice(free, size=k, replace=False, p=p)
    face_ids, bary = cand_f[chosen], cand_b[chosen]
    colors = np.asarray(texture_lookup(mesh.texture, cand_uv[chosen]), dtype=np.float64)
    base = colors.mean(axis=0)
    theta, eta = rng.uniform(0.0, np.pi, n), 1.0 + 99.0 * rng.random(n)
    if params.init == "later":  # ALGORITHM.md §7b: softer, more varied footprints
        threshold = 0.3 + 0.7 * rng.random(n) ** 0.7
        sharpness = 10.0 + 40.0 * rng.random(n) ** 0.5
    else:
        lo, hi = threshold_range
        threshold, sharpness = rng.uniform(lo, hi, n), 10.0 + 40.0 * rng.random(n)
    return KernelSet(
        face_ids=face_ids.astype(np.int64),
        barycentrics=bary,
        theta=theta,
        eta=eta,
        threshold=np.minimum(threshold, 1.0 - 1e-4),
        sharpness=sharpness,
        colors=np.clip(colors - base, -1.0, 1.0),
        base_color=np.clip(base, 0.0, 1.0),
        kernel_config=params.kernel,
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
        # every kernel starts on one layer: the layered blend begins as the paper's
        priority=np.zeros(n) if params.kernel.blend == "layered" else None,
        # every kernel starts at sigma_B: a per-kernel sigma begins as §4's one
        sigma_ratio=np.ones(n) if params.kernel.per_kernel_sigma else None,
        # and with flat colours: linear ones begin as §4's (their slopes train from
        # ``slope_start``)
        color_slopes=np.zeros((n, 9)) if params.kernel.linear_colour else None,
    )


@torch.no_grad()
def evaluate_albedo(model: HeatKernelModel, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Model albedo (P, 3) in chunks, no autograd: bounded memory for 60k evaluation points."""
    dev, dt = model.base_color.device, model.base_color.dtype
    out = np.empty((len(face_ids), 3), dtype=np.float64)
    for start in range(0, len(face_ids), EVAL_CHUNK):
        sl = slice(start, start + EVAL_CHUNK)
        f = torch.as_tensor(face_ids[sl], device=dev)
        b = torch.as_tensor(bary[sl], device=dev, dtype=dt)
        out[sl] = model.albedo(f, b).cpu().numpy()
    return out


def kernelset_bytes(kernelset: KernelSet) -> dict[str, int]:
    """Raw and zip bytes of the kernel set as a ``.hkt`` file (EVALUATION.md 'Bytes'), and
    of its quantised form at the format's default widths (``save_hkt(..., quantised=True)``;
    :func:`quantisation_for` measures the widths a fit's file uses)."""
    from hktex_engine.kernels.hkt import hkt_bytes, save_hkt

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "k.hkt"
        save_hkt(kernelset, path)
        out = storage_bytes(path)
        out["file"] = path.stat().st_size
    quantised = hkt_bytes(kernelset, quantised=True)
    out["raw_quantised"], out["zip_quantised"] = quantised["raw"], quantised["zip"]
    return out


def guarded_colour_solve(model: HeatKernelModel, mesh: Mesh, rng, eval_points: int) -> dict:
    """The colour solve, kept only if it scores better on validation points of their own
    seed (not the evaluation points) than the optimiser's colours; else those are restored.

    Why: on a long fit the solve can lose (spot, 5,000 steps: 35.58 dB before it, 35.21
    after, on the evaluation points; the optimiser's colours have seen millions of samples,
    the solve some tens of thousands, and its clamp active set and final projection can undo
    part of the least-squares gain); on short fits it gains (docs/fitting.md)."""
    n = min(VALIDATION_POINTS, eval_points)
    val_f, val_b, val_target = surface_samples(mesh, n, EVAL_SEED + 2)
    kept_colors = (model.base_color.detach().clone(), model.colors.detach().clone())
    before = psnr(evaluate_albedo(model, val_f, val_b), val_target)
    polish = solve_colours(model, mesh, POLISH_POINTS_PER_KERNEL * len(model), rng)
    after = psnr(evaluate_albedo(model, val_f, val_b), val_target)
    polish.update(validation_points=n, validation_psnr_before=before, validation_psnr_after=after)
    polish["kept"] = bool(after > before)
    if not polish["kept"]:
        with torch.no_grad():
            model.base_color.copy_(kept_colors[0])
            model.colors.copy_(kept_colors[1])
    return polish


def quantisation_for(mesh, spectra, kernelset, eval_f, eval_b, eval_target) -> dict:
    """The code widths a quantised file of this fit uses (``fitting.quantisation``: chosen
    on their own points, within ``BUDGET_DB``) and what that file scores on the evaluation
    points; ``hktex fit --quantise`` writes it."""
    from hktex_engine.fitting.quantisation import choose_bits
    from hktex_engine.kernels.query import AlbedoQuery

    n = min(QUANT_CHOICE_POINTS, len(eval_f))  # a small evaluation (tests) chooses on as few
    f, b, target = surface_samples(mesh, n, EVAL_SEED + 1)
    choice = choose_bits(spectra, kernelset, f, b, target)
    query = AlbedoQuery(spectra, choice["kernelset"], device="cpu")
    scored = psnr(query.colors(eval_f, eval_b), eval_target)
    return {
        "bits": choice["bits"],
        "bytes": choice["bytes"],
        "surface_psnr": scored,
        "choice_points": n,
        "choice_psnr_exact": choice["psnr_exact"],
        "choice_psnr": choice["psnr"],
        "budget_db": choice["budget_db"],
        "tried": [{"bytes": t["bytes"], "psnr": t["psnr"]} for t in choice["tried"]],
    }


def spectra_bytes(spectra: Spectra) -> int:
    """Bytes of the spectra artefact (its directory when on disk, else its arrays)."""
    if spectra.path is not None and Path(spectra.path).is_dir():
        return int(sum(p.stat().st_size for p in Path(spectra.path).iterdir() if p.is_file()))
    arrays = (spectra.vertices, spectra.faces, spectra.mass, spectra.evals, spectra.evecs)
    arrays += (spectra.iso_evals, spectra.iso_evecs, spectra.face_frames)
    return int(sum(np.asarray(a).nbytes for a in arrays))


def fit_uv(
    mesh: Mesh,
    spectra: Spectra,
    params: FitParams | None = None,
    progress: Progress | None = None,
    checkpoint_dir: str | Path | None = None,
    device: str | torch.device | None = None,
    eval_points: int = EVAL_POINTS,
    *,
    transport_theta: bool = False,
) -> FitResult:
    """Fit a kernel set to ``mesh``'s texture on ``spectra``'s grid.

    ``checkpoint_dir`` makes the fit resumable: a rerun with the same arguments continues
    from the latest checkpoint (and a cancelled fit leaves one). ``eval_points`` sets the
    surface-PSNR sample count (EVALUATION.md: 60,000; tests use fewer). ``transport_theta``
    re-expresses theta when a centre changes face (``fitting.run_fit``; off by default).
    """
    params = params or fit_preset(DEFAULT_PRESET)
    if not mesh.has_texture:
        raise TextureError("UV fitting needs a mesh with UVs and an albedo texture")
    if spectra.mesh_hash and mesh.content_hash and spectra.mesh_hash != mesh.content_hash:
        raise SpectraError("the spectra were computed for another mesh")
    if params.kernels < 1 or params.steps < 0:
        raise ValueError("kernels must be >= 1 and steps >= 0")
    if params.kernel.linear_colour and not 0 <= params.slope_start < 1:
        raise ValueError("linear colours need slope_start in [0, 1): their slopes are trained")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    dev = resolve_device(device)
    rng = np.random.default_rng(params.seed)
    field_ = SpectralField(spectra, device=dev)
    init = initial_kernelset(mesh, spectra, params, rng)
    model = HeatKernelModel.from_kernelset(init, field_)
    tracer = SurfaceTracer(spectra.vertices, spectra.faces, device=dev)
    geo = [torch.as_tensor(np.array(a), device=dev) for a in (spectra.vertices, spectra.faces)]
    frames = torch.as_tensor(np.array(spectra.face_frames), device=dev, dtype=geo[0].dtype)
    timings["init_s"] = time.perf_counter() - t0

    eval_f, eval_b, eval_target = surface_samples(mesh, eval_points, EVAL_SEED)
    t1 = time.perf_counter()
    psnr_init = psnr(evaluate_albedo(model, eval_f, eval_b), eval_target)
    timings["eval_s"] = time.perf_counter() - t1

    objective = UVObjective(mesh, params.points_per_step, dev, field_.dtype, params)
    fingerprint = {
        "task": "fit_uv",
        "mesh": mesh.content_hash,
        "spectra": spectra.config_hash,
        "params": dataclasses.asdict(dataclasses.replace(params, checkpoint_every=0)),
    }
    if transport_theta:  # another trajectory; absent otherwise so older checkpoints resume
        fingerprint["transport_theta"] = True
    loop: LoopResult = run_fit(
        model,
        objective,
        params,
        tracer,
        geo[0],
        geo[1],
        frames,
        rng=rng,
        progress=progress,
        checkpoint_dir=checkpoint_dir,
        fingerprint=fingerprint,
        transport_theta=transport_theta,
    )
    timings["fit_s"] = loop.seconds
    polish = None
    # a linear-colour set trained its colours with its slopes; the constant solve would read
    # its footprints without them (and the joint solve lost on validation points in every fit
    # it was measured on: docs/fitting.md, eighteenth pass)
    if params.polish_colors and not params.kernel.linear_colour and loop.steps > 0:
        t_polish = time.perf_counter()
        # the PSNR the optimiser reached, so the solve's gain (colour, not footprint) is known
        before = psnr(evaluate_albedo(model, eval_f, eval_b), eval_target)
        polish = guarded_colour_solve(model, mesh, rng, len(eval_f))
        polish["surface_psnr_before"] = before
        timings["polish_s"] = time.perf_counter() - t_polish

    t2 = time.perf_counter()
    pred = evaluate_albedo(model, eval_f, eval_b)
    timings["final_eval_s"] = time.perf_counter() - t2
    metrics = {
        "task": "fit_uv",
        "surface_psnr": psnr(pred, eval_target),
        "surface_psnr_initial": psnr_init,
        "eval_points": int(eval_points),
        "kernels": len(model),
        "kernels_initial": len(init),
        "steps": loop.steps,
        "resumed_from": loop.resumed_from,
        "steps_per_second": loop.steps_per_second,
        "final_loss": float(np.mean(loop.losses[-50:])) if loop.losses else None,
        "device": str(dev),
    }
    if polish is not None:
        metrics["colour_solve"] = polish
    kernelset = model.to_kernelset(fitting={"task": "fit_uv", "steps": loop.steps})
    t3 = time.perf_counter()
    nbytes = kernelset_bytes(kernelset)
    metrics["bytes_raw"], metrics["bytes_zip"] = nbytes["raw"], nbytes["zip"]
    metrics["bytes_file"] = nbytes["file"]
    metrics["bytes_raw_quantised"] = nbytes["raw_quantised"]
    metrics["bytes_zip_quantised_default_bits"] = nbytes["zip_quantised"]
    metrics["quantisation"] = quantisation_for(
        mesh, spectra, kernelset, eval_f, eval_b, eval_target
    )
    metrics["bytes_zip_quantised"] = metrics["quantisation"]["bytes"]
    metrics["spectra_bytes"] = spectra_bytes(spectra)
    timings["bytes_s"] = time.perf_counter() - t3
    timings["total_s"] = time.perf_counter() - t0
    kernelset.fitting = {
        "task": "fit_uv",
        "steps": loop.steps,
        "params": fingerprint["params"],
        "metrics": metrics,
    }
    return FitResult(kernelset, metrics, timings, loop.losses, loop.density_events)
