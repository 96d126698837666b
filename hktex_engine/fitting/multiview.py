"""Multi-view fitting: kernels learned from images through Mitsuba (ALGORITHM.md section 8).

:class:`MultiViewObjective` is the :class:`~hktex_engine.fitting.loop.Objective` the shared fit loop
runs: each step renders a random crop of a random training view with the ``prb`` integrator
(``max_depth = 3``), the kernel model as the diffuse albedo, and compares it with the photo
after the same log-then-gamma tone map, on the pixels the dataset's mask keeps. The rays'
primary hits (cast by us, see :meth:`RenderScene.hit_buffer`) are the points whose errors and
final kernels the density controller needs.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hktex_engine.config import FitParams
from hktex_engine.errors import SpectraError, ViewsError
from hktex_engine.fitting.loop import PointStats, run_fit
from hktex_engine.fitting.uv import FitResult, kernelset_bytes, spectra_bytes
from hktex_engine.fitting.views import Views
from hktex_engine.progress import Progress
from hktex_engine.render.mitsuba import (
    RenderScene,
    RenderSettings,
    file_frame_vertices,
    linear_to_srgb,
    render_device,
    srgb_to_linear,
)

TONEMAP_GAMMA = 2.2
#: Training views rendered for the final metrics (evenly spread over the dataset).
EVAL_VIEWS = 8


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """Log-then-gamma tone map of linear radiance, applied to both images before the loss.

    ``T(x) = log(1 + x) ** (1 / 2.2)``: the log compresses highlights, the gamma spreads dark
    values the way the eye (and an sRGB file) does, so dark albedo is not under-weighted. The
    small offset keeps the gradient finite at black. (Our reading of "log-then-gamma".)
    """
    return (torch.log1p(x.clamp_min(0.0)) + 1e-4) ** (1.0 / TONEMAP_GAMMA)


@dataclass(frozen=True)
class MultiViewOptions:
    """Renderer-side knobs of multi-view fitting (the rest is :class:`FitParams`).

    ``crop`` is the side of the square pixel window rendered per step (rays per step =
    crop² · spp); ``center_momentum`` 0.9 and the threshold init range U(0.7, 1) are the
    reference defaults for multi-view.
    """

    crop: int = 64
    spp: int = 4
    max_depth: int = 3
    center_momentum: float = 0.9
    init_threshold: tuple[float, float] = (0.7, 1.0)
    oversample: int = 4


@dataclass
class MultiViewBatch:
    view: int
    x: int
    y: int
    seed: int


class MultiViewObjective:
    """Renders a crop of one training view per step and scores it against the photo."""

    def __init__(self, scene: RenderScene, views: Views, options: MultiViewOptions) -> None:
        self.scene = scene
        self.views = views
        self.options = options
        dev = render_device()
        self.targets = torch.from_numpy(srgb_to_linear(views.images)).to(dev)  # (N, H, W, 3)
        self.masks = torch.from_numpy(views.masks).to(dev)
        self.crop_w = min(options.crop, views.width)
        self.crop_h = min(options.crop, views.height)
        self.sensors = [
            scene.sensor(cam, crop=(0, 0, self.crop_w, self.crop_h)) for cam in views.cameras
        ]
        # pixels a crop may be centred on: masked pixels only, so each crop sees the mesh
        self._masked = [np.argwhere(m) for m in views.masks]

    def sample(self, step: int, rng: np.random.Generator) -> MultiViewBatch:
        view = int(rng.integers(len(self.views)))
        cy, cx = self._masked[view][int(rng.integers(len(self._masked[view])))]
        x = int(np.clip(cx - self.crop_w // 2, 0, self.views.width - self.crop_w))
        y = int(np.clip(cy - self.crop_h // 2, 0, self.views.height - self.crop_h))
        return MultiViewBatch(view, x, y, int(rng.integers(1, 2**31 - 1)))

    def _sensor(self, batch: MultiViewBatch) -> Any:
        import mitsuba as mi

        sensor = self.sensors[batch.view]
        p = mi.traverse(sensor)
        p["film.crop_offset"] = mi.ScalarPoint2u(batch.x, batch.y)
        p.update()
        return sensor

    def loss(
        self, model: torch.nn.Module, batch: MultiViewBatch
    ) -> tuple[torch.Tensor, PointStats]:
        sensor = self._sensor(batch)
        self.scene.texture_plugin.albedo_fn = model.albedo
        cam = self.views.cameras[batch.view]
        img = self.scene.render_torch(cam, spp=self.options.spp, seed=batch.seed, sensor=sensor)
        ys = slice(batch.y, batch.y + self.crop_h)
        xs = slice(batch.x, batch.x + self.crop_w)
        target = self.targets[batch.view, ys, xs]
        mask = self.masks[batch.view, ys, xs]
        err = (tonemap(img) - tonemap(target)).abs()  # (h, w, 3)
        loss = err[mask].mean()
        stats = self._point_stats(model, cam, sensor, err.detach(), mask)
        return loss, stats

    def _point_stats(
        self, model: Any, cam: Any, sensor: Any, err: torch.Tensor, mask: torch.Tensor
    ) -> PointStats:
        """Primary hits inside the mask, their per-pixel L1 error and final kernels."""
        face, bary, hit = self.scene.hit_buffer(cam, sensor=sensor)
        dev = err.device
        keep = torch.from_numpy(hit).to(dev) & mask
        f = torch.from_numpy(face).to(dev)[keep]
        b = torch.from_numpy(bary).to(dev, torch.float32)[keep]
        with torch.no_grad():
            _, aux = model.albedo(f, b, return_aux=True)
        return PointStats(
            l1_error=err[keep].mean(dim=1),
            topk=aux["indices"],
            rho=aux["rho"],
            face_ids=f,
            bary=b,
        )


# --------------------------------------------------------------------------- initialisation


def backprojected_colors(
    scene: RenderScene, views: Views, points: np.ndarray, radiance: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """sRGB albedo estimates at ``points`` (file units) from the nearest seen pixel.

    Under a white environment a diffuse surface's pixel is about albedo x radiance (exact on
    convex parts), so dividing by the radiance gives a first albedo guess. Returns the colours
    and a flag per point: False where no view saw anything within reach (those get the mean).
    """
    from scipy.spatial import cKDTree

    if (scene.settings.width, scene.settings.height) != (views.width, views.height):
        raise ValueError("the scene's film size must equal the views' image size")
    pts, cols = [], []
    for i, cam in enumerate(views.cameras):
        face, bary, hit = scene.hit_buffer(cam, sensor=scene.sensor(cam))
        keep = hit & views.masks[i]
        if not keep.any():
            continue
        tri = scene.vertices[scene.faces[face[keep]]]  # (P, 3, 3)
        pts.append(np.einsum("pk,pkd->pd", bary[keep], tri))
        cols.append(srgb_to_linear(views.images[i][keep]) / np.maximum(radiance, 1e-6))
    if not pts:
        raise ViewsError("no view's mask covers the mesh: nothing to fit")
    seen_pts, seen_cols = np.concatenate(pts), np.concatenate(cols)
    dist, idx = cKDTree(seen_pts).query(points)
    spacing = np.sqrt(np.ptp(scene.vertices, axis=0).max() ** 2 / max(len(seen_pts), 1)) * 4
    return linear_to_srgb(np.clip(seen_cols[idx], 0, 1)), dist <= max(spacing, 1e-9)


def initial_model(
    spectra: Any,
    scene: RenderScene,
    views: Views,
    params: FitParams,
    options: MultiViewOptions,
    rng: np.random.Generator,
    device: torch.device,
) -> Any:
    """Centres by farthest-point sampling of area-uniform samples; colours back-projected."""
    from hktex_engine.geometry.sampling import farthest_point_sampling, sample_surface
    from hktex_engine.kernels.model import HeatKernelModel
    from hktex_engine.spectra.interpolation import SpectralField

    V, F = np.asarray(spectra.vertices, np.float64), np.asarray(spectra.faces, np.int64)
    n = int(params.kernels)
    face_s, bary_s = sample_surface(V, F, max(n * options.oversample, n), rng)
    pick = farthest_point_sampling(np.einsum("pk,pkd->pd", bary_s, V[F[face_s]]), n, rng)
    face_ids, bary = face_s[pick], bary_s[pick]
    pts_file = np.einsum("pk,pkd->pd", bary, scene.vertices[scene.faces[face_ids]])
    radiance = np.asarray(views.lighting.radiance, dtype=np.float64)
    colors, seen = backprojected_colors(scene, views, pts_file, radiance)
    base = colors[seen].mean(axis=0) if seen.any() else np.full(3, 0.5)
    residual = np.where(seen[:, None], colors - base, 0.0)
    lo, hi = options.init_threshold
    field_ = SpectralField(spectra, device=device)
    return HeatKernelModel(
        field_,
        face_ids,
        bary,
        theta=rng.uniform(0.0, np.pi, n),
        eta=1.0 + 99.0 * rng.random(n),
        threshold=rng.uniform(lo, hi, n),
        sharpness=10.0 + 40.0 * rng.random(n),
        colors=np.clip(residual, -1.0, 1.0),
        base_color=np.clip(base, 0.0, 1.0),
        config=params.kernel,
    )


# --------------------------------------------------------------------------- the task


def views_fingerprint(views: Views) -> str:
    """Hash of cameras and images: a checkpoint only resumes on the same dataset."""
    h = hashlib.sha256()
    h.update(json.dumps([c.to_dict() for c in views.cameras], sort_keys=True).encode())
    h.update(np.ascontiguousarray(views.images).tobytes())
    h.update(np.ascontiguousarray(views.masks).tobytes())
    return h.hexdigest()


def evaluate_views(
    scene: RenderScene, views: Views, spp: int = 16, seed: int = 12345
) -> dict[str, float]:
    """Mean PSNR / SSIM (sRGB, masked pixels only) of the scene's renders against ``views``."""
    from hktex_engine.evaluation.metrics import psnr, ssim

    ps, ss = [], []
    for i, cam in enumerate(views.cameras):
        img = linear_to_srgb(scene.render(cam, spp=spp, seed=seed + i))
        ps.append(psnr(img, views.images[i], mask=views.masks[i]))
        ss.append(ssim(img, views.images[i], mask=views.masks[i]))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}


def file_frame_scene(spectra: Any, settings: RenderSettings) -> RenderScene:
    """A torch-albedo scene of the spectra's mesh in the file's units (where cameras live)."""
    return RenderScene(file_frame_vertices(spectra), spectra.faces, settings, albedo_fn=None)


def evaluate_kernelset(
    spectra: Any, kernelset: Any, views: Views, spp: int = 16, seed: int = 12345
) -> dict[str, float]:
    """Held-out evaluation: PSNR / SSIM of a kernel set's renders of ``views`` (masked)."""
    from hktex_engine.kernels.model import HeatKernelModel
    from hktex_engine.spectra.interpolation import SpectralField

    settings = RenderSettings(
        width=views.width, height=views.height, spp=spp, lighting=views.lighting
    )
    scene = file_frame_scene(spectra, settings)
    model = HeatKernelModel.from_kernelset(kernelset, SpectralField(spectra, render_device()))
    scene.texture_plugin.albedo_fn = _frozen(model)
    return evaluate_views(scene, views, spp=spp, seed=seed)


def fit_multiview(
    mesh: Any,
    spectra: Any,
    views: Views,
    params: FitParams,
    progress: Progress | None = None,
    checkpoint_dir: str | Path | None = None,
    device: str | torch.device | None = None,
    options: MultiViewOptions | None = None,
) -> FitResult:
    """Fit a kernel set to ``views`` of ``mesh`` (cameras in the mesh file's units).

    The torch device follows the Mitsuba variant (CUDA with ``cuda_ad_rgb``); ``device`` may
    only confirm it, since the albedo must live where the renderer hands over its hits.
    """
    from hktex_engine.geometry.geodesics import SurfaceTracer

    options = options or MultiViewOptions()
    if params.kernel.linear_colour:
        raise ValueError(
            "linear colours are fitted against a UV texture (measured there only); a multi-view"
            " fit has constant colours (colour 'constant')"
        )
    if mesh is not None and mesh.content_hash != spectra.mesh_hash:
        raise SpectraError("the spectra were computed for another mesh")
    want = views.mesh.get("content_hash") if views.mesh else None
    if want and want != spectra.mesh_hash:
        raise ViewsError("the views were made for another mesh (content hash differs)")
    dev = render_device()
    if device is not None and torch.device(device).type != dev.type:
        raise ValueError(f"multi-view fitting runs on {dev} (the Mitsuba variant's device)")
    t0 = time.perf_counter()
    settings = RenderSettings(
        width=views.width,
        height=views.height,
        spp=options.spp,
        max_depth=options.max_depth,
        lighting=views.lighting,
    )
    scene = file_frame_scene(spectra, settings)
    rng = np.random.default_rng(params.seed)
    model = initial_model(spectra, scene, views, params, options, rng, dev)
    objective = MultiViewObjective(scene, views, options)
    vertices = torch.as_tensor(np.array(spectra.vertices, dtype=np.float32), device=dev)
    faces = torch.as_tensor(np.array(spectra.faces, dtype=np.int64), device=dev)
    frames = torch.as_tensor(np.array(spectra.face_frames, dtype=np.float32), device=dev)
    tracer = SurfaceTracer(spectra.vertices, spectra.faces, device=dev)
    fingerprint = {
        "task": "fit_multiview",
        "mesh": spectra.mesh_hash,
        "spectra": spectra.config_hash,
        "views": views_fingerprint(views),
        "kernels": params.kernels,
        "steps": params.steps,
        "seed": params.seed,
        "options": [options.crop, options.spp, options.max_depth],
    }
    loop = run_fit(
        model,
        objective,
        params,
        tracer,
        vertices,
        faces,
        frames,
        rng=rng,
        progress=progress,
        checkpoint_dir=checkpoint_dir,
        fingerprint=fingerprint,
        momentum=options.center_momentum,
    )
    t_fit = loop.seconds
    scene.texture_plugin.albedo_fn = _frozen(model)
    t1 = time.perf_counter()
    # at most EVAL_VIEWS training views: a photo set of hundreds would cost more than the fit
    shown = views.subset(np.linspace(0, len(views) - 1, min(len(views), EVAL_VIEWS)).astype(int))
    quality = evaluate_views(scene, shown, spp=max(options.spp, 8))
    metrics = {
        "task": "fit_multiview",
        "psnr": quality["psnr"],  # training views, masked pixels, sRGB
        "ssim": quality["ssim"],
        "steps": loop.steps,
        "resumed_from": loop.resumed_from,
        "steps_per_second": loop.steps_per_second,
        "kernels": int(len(model)),
        "final_loss": float(np.mean(loop.losses[-10:])) if loop.losses else None,
        "views": len(views),
        "eval_views": len(shown),
        "resolution": [views.width, views.height],
        "crop": options.crop,
        "spp": options.spp,
        "device": str(dev),
    }
    kernelset = model.to_kernelset(color_space="srgb")
    nbytes = kernelset_bytes(kernelset)
    metrics["bytes_raw"], metrics["bytes_zip"] = nbytes["raw"], nbytes["zip"]
    metrics["bytes_file"] = nbytes["file"]
    metrics["spectra_bytes"] = spectra_bytes(spectra)
    kernelset.fitting = {"task": "fit_multiview", "steps": loop.steps, "metrics": metrics}
    timings = {
        "fit_s": t_fit,
        "eval_s": time.perf_counter() - t1,
        "total_s": time.perf_counter() - t0,
    }
    return FitResult(
        kernelset, metrics, timings, list(loop.losses), list(getattr(loop, "density_events", []))
    )


def _frozen(model: Any) -> Any:
    """The model's albedo without autograd (evaluation renders need no graph)."""

    def fn(face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return model.albedo(face_ids, bary)

    return fn
