"""Reference view datasets: images of a known mesh from known cameras (docs/views.md).

A dataset is a directory with ``views.json`` and PNG images (sRGB), optionally one mask PNG
per view (white = the pixel sees the mesh). Cameras are in the mesh file's own units and
Mitsuba's camera convention (:class:`hktex_engine.render.mitsuba.Camera`), so a user can bring
photographs with calibrated cameras as well as our own renders. :func:`load_views` refuses a
malformed dataset with a :class:`~hktex_engine.errors.ViewsError` naming the problem.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hktex_engine.errors import ViewsError
from hktex_engine.render.mitsuba import (
    Camera,
    Lighting,
    RenderScene,
    RenderSettings,
    linear_to_srgb,
    look_at,
    orbit_cameras,
)

VIEWS_FORMAT = "hktex-views"
VIEWS_VERSION = 1


@dataclass
class Views:
    """A loaded view dataset; ``images`` are sRGB float32 in [0, 1], ``masks`` bool."""

    width: int
    height: int
    cameras: list[Camera]
    images: np.ndarray  # (N, H, W, 3) float32 sRGB
    masks: np.ndarray  # (N, H, W) bool; all True for a view without a mask file
    has_mask: list[bool]
    names: list[str]
    lighting: Lighting = field(default_factory=Lighting)
    render: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)
    path: Path | None = None

    def __len__(self) -> int:
        return len(self.cameras)

    def subset(self, indices: list[int] | np.ndarray) -> Views:
        """The views at ``indices`` (e.g. a training / held-out split)."""
        idx = [int(i) for i in indices]
        return Views(
            width=self.width,
            height=self.height,
            cameras=[self.cameras[i] for i in idx],
            images=self.images[idx],
            masks=self.masks[idx],
            has_mask=[self.has_mask[i] for i in idx],
            names=[self.names[i] for i in idx],
            lighting=self.lighting,
            render=dict(self.render),
            mesh=dict(self.mesh),
            path=self.path,
        )


# --------------------------------------------------------------------------- writing


def _save_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path, format="PNG")


def write_views(
    out_dir: str | os.PathLike,
    cameras: list[Camera],
    images_srgb: np.ndarray,
    masks: np.ndarray | None = None,
    lighting: Lighting | None = None,
    render: dict | None = None,
    mesh: dict | None = None,
) -> Path:
    """Write a dataset directory atomically (built aside, renamed into place)."""
    out = Path(out_dir)
    images_srgb = np.asarray(images_srgb, dtype=np.float32)
    n, h, w = images_srgb.shape[:3]
    if len(cameras) != n:
        raise ViewsError(f"{len(cameras)} cameras for {n} images")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    entries = []
    for i, cam in enumerate(cameras):
        name = f"view_{i:03d}"
        entry: dict[str, Any] = {"name": name, "image": f"{name}.png", "camera": cam.to_dict()}
        _save_png(
            tmp / entry["image"], np.round(np.clip(images_srgb[i], 0, 1) * 255).astype(np.uint8)
        )
        if masks is not None:
            entry["mask"] = f"{name}_mask.png"
            _save_png(tmp / entry["mask"], (np.asarray(masks[i], bool) * 255).astype(np.uint8))
        entries.append(entry)
    manifest = {
        "format": VIEWS_FORMAT,
        "version": VIEWS_VERSION,
        "width": int(w),
        "height": int(h),
        "color_space": "srgb",
        "frame": "file",
        "lighting": (lighting or Lighting()).to_dict(),
        "render": render or {},
        "mesh": mesh or {},
        "views": entries,
    }
    (tmp / "views.json").write_text(json.dumps(manifest, indent=1))
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


def render_reference_views(
    mesh: Any,
    out_dir: str | os.PathLike,
    n_views: int = 16,
    resolution: tuple[int, int] = (128, 128),
    spp: int = 64,
    lighting: Lighting | None = None,
    fov: float = 40.0,
    seed: int = 0,
    cameras: list[Camera] | None = None,
) -> Path:
    """Render ``n_views`` orbit views of ``mesh`` with its UV texture and write a dataset.

    Masks come from the pixel-centre rays (hit or miss), so the dataset can be fitted and
    evaluated exactly as a user's photographs with masks would be.
    """
    if not mesh.has_texture:
        raise ViewsError("reference views need a mesh with a UV texture")
    width, height = (int(r) for r in resolution)
    settings = RenderSettings(width=width, height=height, spp=spp, lighting=lighting or Lighting())
    V = mesh.to_file_units(mesh.vertices)
    scene = RenderScene(V, mesh.faces, settings, corner_uvs=mesh.corner_uvs, texture=mesh.texture)
    cams = cameras if cameras is not None else orbit_cameras(V, n_views, fov=fov)
    images, masks = [], []
    for i, cam in enumerate(cams):
        sensor = scene.sensor(cam)
        images.append(linear_to_srgb(scene.render(cam, seed=seed + i, sensor=sensor)))
        masks.append(scene.hit_buffer(cam, sensor=sensor)[2])
    return write_views(
        out_dir,
        cams,
        np.stack(images),
        np.stack(masks),
        settings.lighting,
        render={
            "spp": spp,
            "max_depth": settings.max_depth,
            "integrator": "prb",
            "bsdf": "diffuse",
        },
        mesh={"content_hash": mesh.content_hash, "source_name": mesh.source_name},
    )


# --------------------------------------------------------------------------- reading


def _read_png(path: Path, what: str) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise ViewsError(f"{what} file {path.name!r} is missing")
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise ViewsError(f"{what} file {path.name!r} is not a readable image: {exc}") from None


def _camera(entry: dict, where: str) -> Camera:
    cam = entry.get("camera")
    if not isinstance(cam, dict):
        raise ViewsError(f"{where} has no camera")
    fov = cam.get("fov", entry.get("fov"))
    try:
        fov = float(fov)
    except (TypeError, ValueError):
        raise ViewsError(f"{where}: camera needs a numeric 'fov' in degrees") from None
    if not 0.0 < fov < 180.0:
        raise ViewsError(f"{where}: fov {fov} is not in (0, 180) degrees")
    axis = cam.get("fov_axis", "x")
    if axis not in ("x", "y", "diagonal", "smaller", "larger"):
        raise ViewsError(f"{where}: unknown fov_axis {axis!r}")
    try:
        if "to_world" in cam:
            m = np.asarray(cam["to_world"], dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise ViewsError(f"{where}: to_world must be a finite 4x4 matrix")
            if abs(np.linalg.det(m[:3, :3])) < 1e-12:
                raise ViewsError(f"{where}: to_world is singular")
            return Camera(to_world=m, fov=fov, fov_axis=axis)
        if "origin" in cam and "target" in cam:
            up = cam.get("up", [0.0, 1.0, 0.0])
            vecs = [np.asarray(v, dtype=np.float64) for v in (cam["origin"], cam["target"], up)]
            if any(v.shape != (3,) or not np.all(np.isfinite(v)) for v in vecs):
                raise ViewsError(f"{where}: origin/target/up must be finite 3-vectors")
            return look_at(*vecs, fov=fov, fov_axis=axis)
    except ValueError as exc:
        raise ViewsError(f"{where}: bad camera: {exc}") from None
    raise ViewsError(f"{where}: camera needs 'to_world' or 'origin' and 'target'")


def load_views(path: str | os.PathLike) -> Views:
    """Read and validate a dataset directory; every defect is a :class:`ViewsError`."""
    root = Path(path)
    if not root.is_dir():
        raise ViewsError(f"views directory {str(root)!r} does not exist")
    manifest_path = root / "views.json"
    if not manifest_path.is_file():
        raise ViewsError(f"{str(root)!r} has no views.json")
    try:
        manifest = json.loads(manifest_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ViewsError(f"views.json is not valid JSON: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != VIEWS_FORMAT:
        raise ViewsError(f"views.json is not a {VIEWS_FORMAT!r} manifest")
    if int(manifest.get("version", 0)) > VIEWS_VERSION:
        raise ViewsError(f"views.json version {manifest.get('version')} is newer than supported")
    if manifest.get("color_space", "srgb") != "srgb":
        raise ViewsError("only color_space 'srgb' images are supported")
    try:
        width, height = int(manifest["width"]), int(manifest["height"])
    except (KeyError, TypeError, ValueError):
        raise ViewsError("views.json needs integer 'width' and 'height'") from None
    if width < 1 or height < 1:
        raise ViewsError("image width and height must be positive")
    entries = manifest.get("views")
    if not isinstance(entries, list) or not entries:
        raise ViewsError("views.json lists no views")
    try:
        lighting = Lighting.from_dict(manifest.get("lighting") or {})
    except (ValueError, TypeError) as exc:
        raise ViewsError(f"bad lighting: {exc}") from None
    if lighting.kind == "envmap":
        env = Path(lighting.envmap)
        env = env if env.is_absolute() else root / env
        if not env.is_file():
            raise ViewsError(f"environment map {lighting.envmap!r} is missing")
        lighting = Lighting(kind="envmap", radiance=lighting.radiance, envmap=str(env))
    cams, images, masks, has_mask, names = [], [], [], [], []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise ViewsError(f"view {i} is not an object")
        name = str(entry.get("name", f"view {i}"))
        where = f"view {i} ({name})"
        cams.append(_camera(entry, where))
        if "image" not in entry:
            raise ViewsError(f"{where} names no image")
        img = _read_png(root / str(entry["image"]), f"{where}: image")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.shape[:2] != (height, width):
            raise ViewsError(
                f"{where}: image is {img.shape[1]}x{img.shape[0]}, views.json says {width}x{height}"
            )
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        images.append(img[..., :3].astype(np.float32) / scale)
        if entry.get("mask"):
            m = _read_png(root / str(entry["mask"]), f"{where}: mask")
            if m.ndim == 3:
                m = m[..., 0]
            if m.shape != (height, width):
                raise ViewsError(f"{where}: mask size {m.shape[::-1]} differs from the image's")
            m = m > (m.max() / 2 if m.max() > 0 else 0)
            if not m.any():
                raise ViewsError(f"{where}: mask is empty (no pixel sees the mesh)")
            masks.append(m)
            has_mask.append(True)
        else:
            masks.append(np.ones((height, width), dtype=bool))
            has_mask.append(False)
        names.append(name)
    return Views(
        width=width,
        height=height,
        cameras=cams,
        images=np.stack(images),
        masks=np.stack(masks),
        has_mask=has_mask,
        names=names,
        lighting=lighting,
        render=dict(manifest.get("render") or {}),
        mesh=dict(manifest.get("mesh") or {}),
        path=root,
    )
