"""Mitsuba 3 rendering with a PyTorch albedo on the surface (ALGORITHM.md section 8).

A kernel set has no UV atlas, so no built-in Mitsuba texture can show it. :class:`RenderScene`
registers a small custom ``mi.Texture`` whose ``eval`` hands the hit's face id
(``si.prim_index``) and barycentrics (``si.uv`` on a mesh without texture coordinates) to a
PyTorch function through ``dr.wrap``; gradients of a rendered image flow back into whatever
torch parameters that function reads (the kernel model's), which is what multi-view fitting
needs. The same scene can carry the mesh's own UV texture (a ``bitmap`` texture) for
comparison and for rendering reference views.

Colour space: albedo functions and texture files give sRGB values in [0, 1]; both paths
convert them to linear with the exact sRGB curve (:func:`srgb_to_linear`) before Mitsuba sees
them, Mitsuba renders linear radiance, and :func:`encode_png` tone-maps (clip) and encodes
sRGB. Scenes live in the mesh file's own units so that user cameras apply unchanged.
"""

from __future__ import annotations

import io
import math
import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from hktex_engine.errors import RenderError

AlbedoFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(face_ids (P,) int64, barycentrics (P, 3)) -> sRGB albedo (P, 3) in [0, 1], torch."""

_VARIANT_LOCK = threading.Lock()
_STATE: dict[str, Any] = {}
_THREAD = threading.local()


# --------------------------------------------------------------------------- variant


def ensure_variant(prefer_cuda: bool | None = None) -> str:
    """Select the Mitsuba AD variant once per process and register our texture plugin.

    ``cuda_ad_rgb`` when a CUDA device is usable (and not declined), else ``llvm_ad_rgb``. The
    choice is process-wide because Mitsuba's variant is global state; later calls return it.
    Dr.Jit's symbolic loops, calls and conditionals are switched off: a PyTorch function
    called from inside a plugin cannot be traced symbolically (STACK-NOTES.md).
    """
    with _VARIANT_LOCK:
        if "variant" not in _STATE:
            _STATE["variant"] = _select_variant(prefer_cuda)
    thread_flags()
    return _STATE["variant"]


def _select_variant(prefer_cuda: bool | None) -> str:
    """Set Mitsuba's process-wide variant and register our plugin (under ``_VARIANT_LOCK``)."""
    try:
        import mitsuba as mi
    except Exception as exc:  # pragma: no cover - import failure is environmental
        raise RenderError(f"cannot import mitsuba/drjit: {exc}") from exc
    want_cuda = torch.cuda.is_available() if prefer_cuda is None else prefer_cuda
    candidates = (["cuda_ad_rgb"] if want_cuda else []) + ["llvm_ad_rgb"]
    errors = []
    for variant in candidates:
        try:
            mi.set_variant(variant)
            mi.Float([0.0, 1.0]) + 1.0  # forces the backend (LLVM / CUDA) to initialise
            break
        except Exception as exc:  # a missing libLLVM/driver surfaces here
            errors.append(f"{variant}: {exc}")
    else:
        raise RenderError(
            "no Mitsuba AD variant loads ("
            + "; ".join(errors)
            + "); on the CPU install libLLVM 19 (apt-get install libllvm19) or set "
            "DRJIT_LIBLLVM_PATH"
        )
    mi.register_texture("hktex_albedo", lambda props: _texture_class()(props))
    _bound_threads()
    return variant


def _bound_threads() -> None:
    """Size Dr.Jit's CPU pool like torch's: ``OMP_NUM_THREADS`` when set (the service sets it
    per job so that concurrent jobs do not oversubscribe the cores), else Dr.Jit's default."""
    raw = os.environ.get("OMP_NUM_THREADS", "")
    if raw.isdigit() and int(raw) >= 1:
        import drjit as dr

        # Never below 2: with a pool of one thread, a render whose texture calls back into
        # PyTorch (dr.wrap) deadlocked (measured: tests/test_render.py hung with
        # OMP_NUM_THREADS=1, ran in 3 s with the default pool).
        dr.set_thread_count(max(2, int(raw)))


def thread_flags() -> None:
    """Switch off Dr.Jit's symbolic loops, calls and conditionals on the calling thread.

    Why per thread: Dr.Jit keeps its JIT flags in thread-local state, so flags set once per
    process leave every other thread symbolic, and the first render there fails inside
    Mitsuba ("jit_var_schedule not permitted", a PyTorch call cannot be traced). Web servers
    and autograd engines call us from pools of threads, so every entry point that makes Dr.Jit
    trace calls this; it is a thread-local check after the first call.
    """
    if getattr(_THREAD, "flags_set", False):
        return
    import drjit as dr

    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)
    dr.set_flag(dr.JitFlag.SymbolicConditionals, False)
    _THREAD.flags_set = True


def render_device() -> torch.device:
    """The torch device matching the Mitsuba variant (albedo functions must answer there)."""
    return torch.device("cuda" if ensure_variant().startswith("cuda") else "cpu")


def _texture_class() -> type:
    """Build the texture class against the active variant's ``mi.Texture`` (one per process)."""
    if "texture_cls" in _STATE:
        return _STATE["texture_cls"]
    import drjit as dr
    import mitsuba as mi

    class TorchAlbedoTexture(mi.Texture):
        """Answers ``albedo_fn(face, bary)`` at each hit, linearised, through ``dr.wrap``.

        ``anchor`` is a zero scalar exposed as a differentiable scene parameter: ``dr.wrap``
        records an AD edge only when an input is grad-enabled, and ``mi.render`` attaches
        the ``prb`` adjoint pass only to scene parameters, so the anchor is how both learn
        that this texture depends on torch state.
        """

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.albedo_fn: AlbedoFn | None = None
            #: set by a plain render on the CPU: repeated hits answered once (:class:`_BounceMemo`)
            self.memo: _BounceMemo | None = None
            self.anchor = mi.Float(0.0)

        def eval(self, si: Any, active: Any = True) -> Any:
            fn = self.albedo_fn
            if fn is None:
                raise RenderError("albedo texture used before an albedo function was set")

            @dr.wrap(source="drjit", target="torch")
            def call(
                face: torch.Tensor,
                b1: torch.Tensor,
                b2: torch.Tensor,
                valid: torch.Tensor,
                anchor: torch.Tensor,
            ):
                memo = self.memo
                if memo is not None and face.device.type == "cpu":
                    out = memo.answer(fn, face, b1, b2, valid)
                    return out[:, 0].contiguous(), out[:, 1].contiguous(), out[:, 2].contiguous()
                # prb replays the plugin inside a no-grad backward; the graph must exist anyway
                with torch.enable_grad():
                    # Mitsuba calls with every lane of the wavefront, most of them dead after
                    # the first bounce; the albedo (the expensive part) runs on live lanes only
                    sel = torch.nonzero(valid.bool()).squeeze(1)
                    out = torch.zeros((face.shape[0], 3), dtype=b1.dtype, device=b1.device)
                    if sel.numel():
                        bary = torch.stack([1.0 - b1[sel] - b2[sel], b1[sel], b2[sel]], dim=1)
                        lin = srgb_to_linear(fn(face[sel].long(), bary)).to(out.dtype)
                        out = out.index_copy(0, sel, lin)
                    out = out + 0.0 * anchor.sum()
                    return out[:, 0].contiguous(), out[:, 1].contiguous(), out[:, 2].contiguous()

            # lanes that missed carry garbage indices and barycentrics (possibly NaN, which a
            # zero weight does not cancel in AD): mask them before torch sees them
            valid = active & si.is_valid()
            face = dr.select(valid, mi.Int32(si.prim_index), 0)
            b1 = dr.select(valid, si.uv.x, 1.0 / 3.0)
            b2 = dr.select(valid, si.uv.y, 1.0 / 3.0)
            r, g, b = call(face, b1, b2, valid, self.anchor)
            return mi.Color3f(r, g, b)

        def eval_1(self, si: Any, active: Any = True) -> Any:
            return dr.mean(self.eval(si, active))

        def mean(self) -> float:
            return 0.5

        def is_spatially_varying(self) -> bool:
            return True

        def traverse(self, callback: Any) -> None:
            callback.put("anchor", self.anchor, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: Any = None) -> None:
            return None

        def to_string(self) -> str:
            return "HKTexTorchAlbedo[]"

    _STATE["texture_cls"] = TorchAlbedoTexture
    return TorchAlbedoTexture


# --------------------------------------------------------------------------- colour


def srgb_to_linear(x: torch.Tensor | np.ndarray) -> Any:
    """The exact sRGB decoding curve (IEC 61966-2-1), on torch or numpy, clamped to [0, 1]."""
    if isinstance(x, torch.Tensor):
        x = x.clamp(0.0, 1.0)
        return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: torch.Tensor | np.ndarray) -> Any:
    """The sRGB encoding curve; clamps to [0, 1] first (our tone map is a plain clip)."""
    if isinstance(x, torch.Tensor):
        x = x.clamp(0.0, 1.0)
        return torch.where(
            x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055
        )
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 1e-12) ** (1 / 2.4) - 0.055
    ).astype(np.float32)


def encode_png(linear_rgb: np.ndarray) -> bytes:
    """Linear radiance (H, W, 3) -> sRGB 8-bit PNG bytes."""
    from PIL import Image

    srgb = linear_to_srgb(np.asarray(linear_rgb, dtype=np.float32))
    u8 = np.round(srgb * 255.0).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(u8, mode="RGB").save(buf, format="PNG")
    return buf.getvalue()


# --------------------------------------------------------------------------- cameras, lights


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the mesh file's units, Mitsuba's convention.

    ``to_world`` maps camera space to world space: the camera looks along its local +Z with
    +Y up and +X to the left (what ``look_at`` builds). ``fov`` is in degrees along
    ``fov_axis``.
    """

    to_world: np.ndarray  # (4, 4)
    fov: float = 40.0
    fov_axis: str = "x"

    def to_dict(self) -> dict:
        return {
            "to_world": np.asarray(self.to_world, dtype=float).tolist(),
            "fov": float(self.fov),
            "fov_axis": self.fov_axis,
        }


def look_at(
    origin: Sequence[float],
    target: Sequence[float],
    up: Sequence[float] = (0.0, 1.0, 0.0),
    fov: float = 40.0,
    fov_axis: str = "x",
) -> Camera:
    """A camera at ``origin`` looking at ``target`` (same frame as Mitsuba's ``look_at``)."""
    o, t, u = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    d = t - o
    if np.linalg.norm(d) == 0:
        raise ValueError("camera origin and target coincide")
    d /= np.linalg.norm(d)
    left = np.cross(u, d)
    if np.linalg.norm(left) < 1e-9:
        raise ValueError("camera up vector is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return Camera(to_world=m, fov=float(fov), fov_axis=fov_axis)


def bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (bounding-box centre) and radius enclosing every vertex."""
    v = np.asarray(vertices, dtype=np.float64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    return centre, float(np.linalg.norm(v - centre, axis=1).max())


def orbit_camera(
    vertices: np.ndarray,
    azimuth: float,
    elevation: float,
    fov: float = 40.0,
    margin: float = 1.1,
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> Camera:
    """A camera on the bounding sphere's orbit, angles in degrees, framing the whole mesh.

    Azimuth turns about ``up`` (0 = looking along -Z from +Z); the distance makes the sphere
    (times ``margin``) fit the field of view, so framing does not depend on the mesh's units.
    """
    centre, radius = bounding_sphere(vertices)
    upv = np.asarray(up, dtype=np.float64)
    upv /= np.linalg.norm(upv)
    # a fixed orthonormal frame around `up`: forward0 is the world axis least aligned with up
    helper = np.eye(3)[np.argmin(np.abs(upv))]
    x_axis = np.cross(upv, helper)
    x_axis /= np.linalg.norm(x_axis)
    z_axis = np.cross(x_axis, upv)
    az, el = math.radians(azimuth), math.radians(elevation)
    direction = math.cos(el) * (math.cos(az) * z_axis + math.sin(az) * x_axis) + math.sin(el) * upv
    distance = margin * max(radius, 1e-9) / math.sin(math.radians(fov) / 2.0)
    origin = centre + distance * direction
    cam_up = upv if abs(math.cos(el)) > 1e-3 else z_axis
    return look_at(origin, centre, cam_up, fov)


def orbit_cameras(
    vertices: np.ndarray,
    n_views: int,
    elevations: Sequence[float] = (20.0, -15.0, 45.0),
    fov: float = 40.0,
    azimuth_offset: float = 0.0,
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> list[Camera]:
    """``n_views`` cameras spread evenly in azimuth, cycling through ``elevations``.

    The azimuth step is the golden angle so that any prefix of the list covers the object
    roughly evenly (held-out views can be the tail of the same list).
    """
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    golden = 180.0 * (3.0 - math.sqrt(5.0))
    return [
        orbit_camera(
            vertices, azimuth_offset + i * golden, elevations[i % len(elevations)], fov, up=up
        )
        for i in range(n_views)
    ]


@dataclass(frozen=True)
class Lighting:
    """Constant environment radiance (``kind="constant"``) or an environment map file.

    ``radiance`` is linear RGB; for an environment map it scales the map. Under a constant
    white environment of radiance 1 a convex diffuse object shows its linear albedo exactly.
    """

    kind: str = "constant"
    radiance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    envmap: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("constant", "envmap"):
            raise ValueError(f"lighting kind must be 'constant' or 'envmap', not {self.kind!r}")
        if self.kind == "envmap" and not self.envmap:
            raise ValueError("an envmap lighting needs a file name")
        object.__setattr__(
            self,
            "radiance",
            tuple(float(r) for r in np.broadcast_to(np.asarray(self.radiance, dtype=float), (3,))),
        )

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"type": self.kind, "radiance": list(self.radiance)}
        if self.envmap:
            d["filename"] = self.envmap
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Lighting:
        return cls(
            kind=d.get("type", "constant"),
            radiance=tuple(np.broadcast_to(np.asarray(d.get("radiance", 1.0), float), (3,))),
            envmap=d.get("filename"),
        )

    def emitter_dict(self) -> dict:
        if self.kind == "constant":
            return {"type": "constant", "radiance": {"type": "rgb", "value": list(self.radiance)}}
        return {"type": "envmap", "filename": str(self.envmap), "scale": float(self.radiance[0])}


# --------------------------------------------------------------------------- scene


@dataclass
class RenderSettings:
    """Integrator and film settings (``prb`` with ``max_depth=3`` as the paper renders)."""

    width: int = 256
    height: int = 256
    spp: int = 16
    max_depth: int = 3
    bsdf: str = "diffuse"  # or "principled" (albedo as base_color)
    lighting: Lighting = field(default_factory=Lighting)

    def __post_init__(self) -> None:
        if not (1 <= self.width <= 8192 and 1 <= self.height <= 8192):
            raise ValueError("image width and height must be in [1, 8192]")
        if self.spp < 1:
            raise ValueError("spp must be >= 1")
        if self.bsdf not in ("diffuse", "principled"):
            raise ValueError("bsdf must be 'diffuse' or 'principled'")


class RenderScene:
    """One mesh in one Mitsuba scene, with either a torch albedo or the mesh's UV texture.

    Build once, render many views: the scene (BVH, kernels compiled by Dr.Jit) is reused and
    only the sensor changes. ``albedo_fn`` may be swapped between renders.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        settings: RenderSettings | None = None,
        albedo_fn: AlbedoFn | None = None,
        corner_uvs: np.ndarray | None = None,
        texture: np.ndarray | None = None,
    ) -> None:
        ensure_variant()
        import mitsuba as mi

        self.settings = settings or RenderSettings()
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError("vertices must be (n, 3) and faces (m, 3)")
        if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError("face indices out of range")
        self.vertices, self.faces = vertices, faces
        self.uv_mode = texture is not None
        #: the last plain render's point cache (``asked`` / ``evaluated`` point counts)
        self.last_cache: _PointCache | None = None
        #: the last one-pass plain render's memo (``asked`` / ``evaluated`` point counts)
        self.last_memo: _BounceMemo | None = None
        if self.uv_mode:
            if corner_uvs is None:
                raise ValueError("a UV-textured scene needs corner_uvs")
            reflectance = self._bitmap_texture(texture)
            self.texture_plugin = None
        else:
            reflectance = mi.load_dict({"type": "hktex_albedo"})
            reflectance.albedo_fn = albedo_fn
            self.texture_plugin = reflectance
        s = self.settings
        if s.bsdf == "diffuse":
            bsdf = mi.load_dict({"type": "diffuse", "reflectance": reflectance})
        else:
            bsdf = mi.load_dict({"type": "principled", "base_color": reflectance})
        shape = self._mi_mesh(vertices, faces, corner_uvs if self.uv_mode else None, bsdf)
        self.scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "prb", "max_depth": int(s.max_depth)},
                "emitter": s.lighting.emitter_dict(),
                "shape": shape,
            }
        )
        self.params = mi.traverse(self.scene)
        self._anchor_key = next((k for k in self.params.keys() if k.endswith(".anchor")), None)

    # ---- construction helpers

    @staticmethod
    def _mi_mesh(V: np.ndarray, F: np.ndarray, corner_uvs: np.ndarray | None, bsdf: Any) -> Any:
        """An ``mi.Mesh`` with faces in the given order (so ``si.prim_index`` is our face id).

        With UVs, every face corner gets its own vertex: seams need per-corner UVs and Mitsuba
        stores UVs per vertex. Mitsuba's bitmap lookup puts v = 0 at the image's top row, the
        OBJ convention at its bottom, hence ``1 - v``.
        """
        import mitsuba as mi

        props = mi.Properties()
        props["bsdf"] = bsdf
        if corner_uvs is not None:
            pos = V[F].reshape(-1, 3)
            idx = np.arange(len(pos), dtype=np.uint32).reshape(-1, 3)
            uv = np.asarray(corner_uvs, dtype=np.float64).reshape(-1, 2).copy()
            uv[:, 1] = 1.0 - uv[:, 1]
        else:
            pos, idx, uv = V, F.astype(np.uint32), None
        mesh = mi.Mesh("hktex_mesh", len(pos), len(idx), props, has_vertex_texcoords=uv is not None)
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(np.ascontiguousarray(pos, dtype=np.float32).ravel())
        p["faces"] = mi.UInt32(np.ascontiguousarray(idx).ravel())
        if uv is not None:
            p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uv, dtype=np.float32).ravel())
        p.update()
        return mesh

    @staticmethod
    def _bitmap_texture(texture: np.ndarray) -> Any:
        """The mesh's sRGB texture, linearised here (raw) so both paths share one curve."""
        import mitsuba as mi

        lin = srgb_to_linear(np.asarray(texture, dtype=np.float32)[..., :3])
        bmp = mi.Bitmap(np.ascontiguousarray(lin))
        return mi.load_dict(
            {
                "type": "bitmap",
                "bitmap": bmp,
                "raw": True,
                "filter_type": "bilinear",
                "wrap_mode": "repeat",
            }
        )

    def sensor(self, camera: Camera, crop: tuple[int, int, int, int] | None = None) -> Any:
        """A perspective sensor for ``camera``; ``crop`` = (x, y, w, h) renders a window."""
        import mitsuba as mi

        s = self.settings
        film: dict[str, Any] = {
            "type": "hdrfilm",
            "width": s.width,
            "height": s.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        }
        if crop is not None:
            x, y, w, h = (int(c) for c in crop)
            film.update(crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
        return mi.load_dict(
            {
                "type": "perspective",
                "fov": float(camera.fov),
                "fov_axis": camera.fov_axis,
                "to_world": mi.ScalarTransform4f(np.asarray(camera.to_world, dtype=np.float64)),
                "film": film,
                "sampler": {"type": "independent", "sample_count": s.spp},
            }
        )

    # ---- rendering

    def render(
        self,
        camera: Camera,
        spp: int | None = None,
        seed: int = 0,
        sensor: Any = None,
        cache: bool = False,
    ) -> np.ndarray:
        """Linear RGB image (H, W, 3) float32; no gradients are tracked.

        ``cache=True`` renders in two passes with the same seed: the first, with a
        placeholder albedo, only records where the texture is asked (with a diffuse BSDF
        and no Russian roulette the paths do not depend on the albedo values); the albedo
        function then runs **once**, on the distinct recorded points; the second pass
        renders with those exact values (:class:`_PointCache`, bit-exact keys; a point the
        second pass asks that the first did not is evaluated on the spot, so the image is
        exact either way). The default evaluates every request as it comes (one pass): with
        the compiled blend the second Mitsuba pass and the keying cost more than the 31 % of
        repeated requests they save (benchmarks/results/render.md: 0.60 s against 1.62 s on
        spot at 128^2, 8 spp); an expensive albedo function may still want the cache."""
        import drjit as dr
        import mitsuba as mi

        thread_flags()
        sensor = sensor if sensor is not None else self.sensor(camera)
        plugin = self.texture_plugin
        inner = plugin.albedo_fn if plugin is not None else None
        spp = spp or self.settings.spp
        self.last_cache = None
        try:
            with dr.suspend_grad():
                if inner is not None and cache:
                    recorder = _HitRecorder()
                    plugin.albedo_fn = recorder
                    mi.render(self.scene, sensor=sensor, spp=spp, seed=seed)
                    self.last_cache = _PointCache(_without_grad(inner))
                    face_ids, bary = recorder.points()
                    if face_ids.numel():
                        self.last_cache(face_ids, bary)  # one call: every distinct point
                    self.last_cache.asked = 0  # count the second pass's requests only
                    plugin.albedo_fn = self.last_cache
                elif inner is not None:
                    plugin.albedo_fn = _without_grad(inner)
                    plugin.memo = self.last_memo = _BounceMemo()
                img = mi.render(self.scene, sensor=sensor, spp=spp, seed=seed)
        finally:
            if inner is not None:
                plugin.albedo_fn = inner
                plugin.memo = None
        return np.array(img, dtype=np.float32)

    def render_torch(
        self,
        camera: Camera,
        spp: int | None = None,
        seed: int = 0,
        sensor: Any = None,
        seed_grad: int | None = None,
    ) -> torch.Tensor:
        """Linear RGB image (H, W, 3) as a torch tensor differentiable w.r.t. the albedo.

        Backward runs Mitsuba's ``prb`` adjoint pass, which re-evaluates the albedo function
        and back-propagates into the torch parameters it reads (their ``.grad`` accumulates).
        The adjoint pass draws its own samples (``seed_grad``, decorrelated from ``seed`` by
        default, which keeps gradients of non-linear losses unbiased).
        """
        if self.uv_mode or self._anchor_key is None:
            raise RenderError("render_torch needs a scene with a torch albedo function")
        sensor = sensor if sensor is not None else self.sensor(camera)
        anchor = torch.zeros(1, device=render_device(), requires_grad=True)
        job = _RenderJob(self, sensor, spp or self.settings.spp, seed, seed_grad)
        return _MitsubaRender.apply(anchor, job)

    def hit_buffer(
        self, camera: Camera, sensor: Any = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Primary hits of the pixel-centre rays: face ids (H, W), barycentrics (H, W, 3), mask.

        Mitsuba does not hand out per-pixel hit records from ``render``, so we cast one ray
        per pixel centre ourselves; masks and the density controller's per-point statistics
        come from here. Faces are -1 where the ray misses. Valid for the UV scene as well
        (barycentrics are then recomputed from the hit point).
        """
        import drjit as dr
        import mitsuba as mi

        thread_flags()
        sensor = sensor if sensor is not None else self.sensor(camera)
        film = sensor.film()
        (w, h), (ox, oy), (fw, fh) = film.crop_size(), film.crop_offset(), film.size()
        ys, xs = np.meshgrid(np.arange(h) + oy, np.arange(w) + ox, indexing="ij")
        pos = mi.Point2f(
            mi.Float(((xs.ravel() + 0.5) / fw).astype(np.float32)),
            mi.Float(((ys.ravel() + 0.5) / fh).astype(np.float32)),
        )
        with dr.suspend_grad():
            n = w * h
            ray, _ = sensor.sample_ray(
                mi.Float(np.zeros(n, np.float32)),
                mi.Float(np.full(n, 0.5, np.float32)),
                pos,
                mi.Point2f(0.5, 0.5),
            )
            si = self.scene.ray_intersect(ray)
            valid = np.array(si.is_valid(), dtype=bool)
            face = np.array(si.prim_index, dtype=np.int64)
            p = np.array(si.p, dtype=np.float64).reshape(3, -1).T if n else np.zeros((0, 3))
        face = np.where(valid, face, -1)
        bary = np.zeros((n, 3), dtype=np.float64)
        if valid.any():
            bary[valid] = _barycentrics(self.vertices, self.faces, face[valid], p[valid])
        return face.reshape(h, w), bary.reshape(h, w, 3), valid.reshape(h, w)


def _without_grad(fn: AlbedoFn) -> AlbedoFn:
    """``fn`` on detached inputs with autograd off (plain renders need values only)."""

    def call(face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return fn(face_ids.detach(), bary.detach())

    return call


def _point_keys(face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Exact identity of surface points, (P, 3) int64: the face and the bit patterns of the
    two barycentrics Mitsuba handed over (the third is derived from them)."""
    b = bary.detach()[:, 1:].contiguous()
    bits = b.view(torch.int32) if b.dtype == torch.float32 else b.view(torch.int64)
    return torch.cat([face_ids.long()[:, None], bits.long()], dim=1)


#: Odd 64-bit multipliers for :func:`_distinct_rows`' hash (any odd constants with mixed bits).
_HASH_MULT = (-7046029254386353131, -4658895280553007687, 1609587929392839161)


def _distinct_rows(keys: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Ids ``inv`` (P,) of the distinct rows of ``keys`` (P, 3) int64 and their count: rows
    ``i`` and ``j`` are equal exactly when ``inv[i] == inv[j]``.

    Why not ``torch.unique(dim=0)``: its row-wise sort took 63 ms a call on 45k points (more
    than the albedo work the cache saves). A 64-bit hash of each row is made distinct with a
    1-D ``unique`` (a few ms); every row is then compared with its group's first row, so a
    hash collision cannot merge two points: it sends the call to the exact row-wise path.
    """
    h = keys[:, 0] * _HASH_MULT[0]
    h = (h ^ (keys[:, 1] * _HASH_MULT[1])) ^ (keys[:, 2] * _HASH_MULT[2])
    h = h ^ (h >> 31)
    _, inv = torch.unique(h, return_inverse=True)
    count = int(inv.max()) + 1 if inv.numel() else 0
    first = torch.full((count,), keys.shape[0], dtype=torch.long, device=keys.device)
    first.scatter_reduce_(0, inv, torch.arange(keys.shape[0], device=keys.device), "amin")
    if bool(torch.all(keys[first[inv]] == keys)):
        return inv, count
    _, inv = torch.unique(keys, dim=0, return_inverse=True)  # a collision: exact and slow
    return inv, int(inv.max()) + 1


class _HitRecorder:
    """A placeholder albedo (0.5 grey) that records every point it is asked about."""

    def __init__(self) -> None:
        self.faces: list[torch.Tensor] = []
        self.barys: list[torch.Tensor] = []

    def __call__(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        self.faces.append(face_ids.detach().clone())
        self.barys.append(bary.detach().clone())
        return torch.full((face_ids.shape[0], 3), 0.5, dtype=bary.dtype, device=bary.device)

    def points(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The distinct recorded points (face ids, barycentrics), bit-exact."""
        if not self.faces:
            return torch.zeros(0, dtype=torch.long), torch.zeros((0, 3))
        f, b = torch.cat(self.faces), torch.cat(self.barys)
        inv, count = _distinct_rows(_point_keys(f, b))
        first = torch.full((count,), len(f), dtype=torch.long, device=f.device)
        first.scatter_reduce_(0, inv, torch.arange(len(f), device=f.device), "amin")
        return f[first], b[first]


def _match_in_order(prev, cur, pos):  # pragma: no cover - compiled by numba
    """``pos[i]``: the row of ``prev`` equal to ``cur[i]`` when ``prev`` is walked in order
    alongside ``cur`` (a greedy subsequence match), else -1. Rows are (face, u bits, v bits)."""
    j = 0
    m = prev.shape[0]
    for i in range(cur.shape[0]):
        if (
            j < m
            and cur[i, 0] == prev[j, 0]
            and cur[i, 1] == prev[j, 1]
            and cur[i, 2] == prev[j, 2]
        ):
            pos[i] = j
            j += 1
        else:
            pos[i] = -1


_MATCH: list = []


def _matcher() -> Callable | None:
    """The compiled :func:`_match_in_order` (None without numba: nothing is reused)."""
    from hktex_engine import jit

    if not jit.HAVE_NUMBA:
        return None
    with jit.LOCK:
        if not _MATCH:
            _MATCH.append(jit.jit(_match_in_order))
    return _MATCH[0]


class _BounceMemo:
    """The plain render's texture answers on the CPU; a bounce's repeated hits answered once.

    ``prb`` asks the texture twice at each bounce: for the emitter sample's BSDF value (the
    lanes whose light sample is valid) and to sample the BSDF (every live lane). Dr.Jit hands
    each call its active lanes compacted in lane order, so the first call's hits come again,
    in the same order, inside the second (measured on spot at 128^2, 8 spp: calls of 13,169,
    29,282, 604 and 1,600 hits; all 13,169 and 604 found again). The memo keeps the last
    call's hits (face and barycentric bits) and answers; the next call walks both in order
    and reuses an answer only where the bits are equal, so a reused value is the very value
    the albedo function gave for the same input, and the rest is evaluated. A linear walk
    instead of hashing (the point cache's keying cost as much as it saved). The glue runs in
    numpy rather than torch: small torch ops inside Mitsuba's callback were measured up to
    ~50x slower than alone (17 ms against 0.3 ms for the sRGB curve on 11,000 points), their
    threads contending with Dr.Jit's.
    """

    def __init__(self) -> None:
        self.keys = np.zeros((0, 3), dtype=np.int32)  # the last call's hits, in order
        self.values = np.zeros((0, 3), dtype=np.float32)  # their linear answers
        self.match = _matcher()
        self.asked = 0
        self.evaluated = 0

    def answer(
        self,
        fn: AlbedoFn,
        face: torch.Tensor,
        b1: torch.Tensor,
        b2: torch.Tensor,
        valid: torch.Tensor,
    ) -> torch.Tensor:
        """Linear albedo (n, 3) float32 for every lane (zero where not ``valid``)."""
        live = np.flatnonzero(valid.detach().numpy())
        u = b1.detach().numpy().astype(np.float32, copy=False)[live]
        v = b2.detach().numpy().astype(np.float32, copy=False)[live]
        f = face.detach().numpy()[live].astype(np.int32)
        keys = np.stack([f, u.view(np.int32), v.view(np.int32)], axis=1)
        values = np.empty((live.size, 3), dtype=np.float32)
        pos = np.full(live.size, -1, dtype=np.int64)
        if self.match is not None and live.size and self.keys.shape[0]:
            self.match(self.keys, keys, pos)
        hit = pos >= 0
        values[hit] = self.values[pos[hit]]
        todo = np.flatnonzero(~hit)
        self.asked += int(live.size)
        self.evaluated += int(todo.size)
        if todo.size:
            us, vs = u[todo], v[todo]
            bary = torch.from_numpy(np.stack([np.float32(1.0) - us - vs, us, vs], axis=1))
            srgb = fn(torch.from_numpy(f[todo].astype(np.int64)), bary)
            values[todo] = srgb_to_linear(srgb.detach().cpu().numpy())
        self.keys, self.values = keys, values
        out = np.zeros((face.shape[0], 3), dtype=np.float32)
        out[live] = values
        return torch.from_numpy(out)


class _PointCache:
    """Answers each distinct surface point once per pass (exact reuse, no approximation).

    Mitsuba asks the texture several times about the same hits within one render (measured
    on a convex sphere, 64 x 64 at 4 spp: 15,337 points asked, 10,340 distinct), and the
    albedo model is what a render waits on. Points are identified bit for bit
    (:func:`_point_keys`), so a reused value is the very value the model gave for the same
    input. With ``tape`` (the adjoint pass of a differentiable render) the fresh values are
    recorded as (model output, detached leaf) pairs and every answer is gathered from the
    leaves, so gradients from every repeat of a point accumulate into its one leaf. Memory:
    one key row and one colour per distinct point of the pass; dropped with the pass.
    """

    def __init__(self, fn: AlbedoFn, tape: list | None = None) -> None:
        self.fn = fn
        self.tape = tape
        self.keys: torch.Tensor | None = None  # (D, 3) distinct points answered so far
        self.table: torch.Tensor | None = None  # (D, 3) their values (leaves with a tape)
        self.asked = 0
        self.evaluated = 0

    def __call__(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        n = face_ids.shape[0]
        self.asked += n
        if n == 0:
            return self._fresh(face_ids, bary)
        keys = _point_keys(face_ids, bary)
        old = 0 if self.keys is None else self.keys.shape[0]
        both = keys if self.keys is None else torch.cat([self.keys, keys])
        inv, count = _distinct_rows(both)
        dev = both.device
        # position of each distinct point in the table: old rows keep theirs, new distinct
        # points are appended in order of first appearance in this batch
        pos = torch.full((count,), -1, dtype=torch.long, device=dev)
        if old:
            pos[inv[:old]] = torch.arange(old, device=dev)
        new_inv = inv[old:]
        first = torch.full((count,), n, dtype=torch.long, device=dev)
        first.scatter_reduce_(0, new_inv, torch.arange(n, device=dev), "amin")
        todo = torch.nonzero(pos < 0).squeeze(1)
        todo = todo[torch.argsort(first[todo])]
        pick = first[todo]
        if pick.numel():
            fresh = self._fresh(face_ids[pick], bary[pick])
            self.evaluated += int(pick.numel())
            pos[todo] = old + torch.arange(pick.numel(), device=dev)
            self.keys = keys[pick] if self.keys is None else torch.cat([self.keys, keys[pick]])
            self.table = fresh if self.table is None else torch.cat([self.table, fresh])
        return self.table[pos[new_inv]]

    def _fresh(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        if self.tape is None:
            return self.fn(face_ids, bary)
        out = self.fn(face_ids, bary)
        leaf = out.detach().requires_grad_(True)
        self.tape.append((out, leaf))
        return leaf


class _RenderJob:
    """One differentiable render: its scene, sensor, sample counts and the albedo tape.

    Why a tape instead of letting ``dr.wrap`` carry the model's graph: the albedo graphs Dr.Jit
    records inside Mitsuba can outlive the step (they hang off AD nodes we do not own), and a
    live graph pins the model parameters' gradient accumulators, which breaks backward once
    density control resizes those parameters. So inside Mitsuba the albedo is a detached leaf;
    the tape keeps (model output, leaf) pairs of the adjoint pass, and we push the leaves'
    gradients into the model ourselves, after which nothing refers to the model's graph.
    """

    def __init__(
        self, scene: RenderScene, sensor: Any, spp: int, seed: int, seed_grad: int | None
    ) -> None:
        self.scene, self.sensor, self.spp, self.seed, self.seed_grad = (
            scene,
            sensor,
            spp,
            seed,
            seed_grad,
        )
        self.recording = False
        self.tape: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.cache: _PointCache | None = None  # per pass: distinct points answered once
        self.image: Any = None

    def albedo(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        # Mitsuba asks about the same hits several times per pass (BSDF evaluation and
        # sampling, replays): the pass's point cache runs the model once per distinct point.
        if self.cache is None:
            if self.recording:
                self.cache = _PointCache(self.inner, tape=self.tape)
            else:
                self.cache = _PointCache(_without_grad(self.inner))
        return self.cache(face_ids, bary)

    def run(self) -> Any:
        import drjit as dr
        import mitsuba as mi

        thread_flags()
        sc = self.scene
        plugin = sc.texture_plugin
        self.inner = plugin.albedo_fn
        if self.inner is None:
            raise RenderError("no albedo function set on the scene")
        anchor = mi.Float(0.0)
        dr.enable_grad(anchor)
        sc.params[sc._anchor_key] = anchor
        sc.params.update()
        plugin.anchor = sc.params[sc._anchor_key]
        extra = {} if self.seed_grad is None else {"seed_grad": int(self.seed_grad)}
        plugin.albedo_fn = self.albedo
        try:
            self.image = mi.render(
                sc.scene,
                params=sc.params,
                sensor=self.sensor,
                spp=self.spp,
                seed=self.seed,
                **extra,
            )
        finally:
            plugin.albedo_fn = self.inner
            self.cache = None
        return self.image

    def backward(self, grad: torch.Tensor) -> None:
        import drjit as dr
        import mitsuba as mi

        thread_flags()  # autograd may run backward on another thread (e.g. CUDA's)
        plugin = self.scene.texture_plugin
        plugin.albedo_fn = self.albedo
        self.recording = True
        self.cache = None
        try:
            weight = mi.TensorXf(grad.detach().to(torch.float32).contiguous())
            dr.backward(self.image * weight)
            outs = [o for o, leaf in self.tape if leaf.grad is not None]
            grads = [leaf.grad for _, leaf in self.tape if leaf.grad is not None]
            if outs:
                torch.autograd.backward(outs, grads)
        finally:
            plugin.albedo_fn = self.inner
            self.recording = False
            self.tape.clear()
            self.cache = None
            self.image = None


class _MitsubaRender(torch.autograd.Function):
    """Torch view of a Mitsuba render: image forward, ``prb`` adjoint backward."""

    @staticmethod
    def forward(ctx: Any, anchor: torch.Tensor, job: _RenderJob) -> torch.Tensor:
        ctx.job = job
        image = job.run()
        return image.torch().clone().to(anchor.device)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[None, None]:
        ctx.job.backward(grad)
        ctx.job = None
        return None, None


def _barycentrics(V: np.ndarray, F: np.ndarray, face: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Barycentrics of points ``p`` in triangles ``F[face]`` (least squares in the plane)."""
    a, b, c = (V[F[face, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - b1 - b2, b1, b2], axis=1), 0.0, 1.0)
    return bary / bary.sum(axis=1, keepdims=True)


# --------------------------------------------------------------------------- entry points


def file_frame_vertices(spectra: Any) -> np.ndarray:
    """Spectra vertices back in the mesh file's units (x_file = (x_norm - t) / s)."""
    return (np.asarray(spectra.vertices, np.float64) - np.asarray(spectra.translation)) / float(
        spectra.scale
    )


def parse_view(view: Any, vertices: np.ndarray, fov: float = 40.0) -> Camera:
    """A camera from a Camera, an ``(azimuth, elevation)`` pair or ``"AZ,EL"`` / view index."""
    if isinstance(view, Camera):
        return view
    if isinstance(view, str):
        parts = [p for p in view.replace(" ", "").split(",") if p]
        try:
            nums = [float(p) for p in parts]
        except ValueError as exc:
            raise ValueError(f"view must be 'AZIMUTH,ELEVATION' or an index, not {view!r}") from exc
        if len(nums) == 1:
            return orbit_cameras(vertices, int(nums[0]) + 1, fov=fov)[int(nums[0])]
        if len(nums) != 2:
            raise ValueError(f"view must be 'AZIMUTH,ELEVATION' or an index, not {view!r}")
        return orbit_camera(vertices, nums[0], nums[1], fov)
    if isinstance(view, int):
        if view < 0:
            raise ValueError("view index must be >= 0")
        return orbit_cameras(vertices, view + 1, fov=fov)[view]
    az, el = view
    return orbit_camera(vertices, float(az), float(el), fov)


def _cameras(views: Any, vertices: np.ndarray) -> tuple[bool, list[Camera]]:
    """(single?, cameras) from one view, a list of views, or a view dataset (``.cameras``)."""
    if hasattr(views, "cameras"):
        return False, list(views.cameras)
    if isinstance(views, list):
        return False, [parse_view(v, vertices) for v in views]
    return True, [parse_view(views, vertices)]


def query_albedo_fn(query: Any) -> AlbedoFn:
    """Wrap an inference ``AlbedoQuery`` (numpy in/out) as a torch albedo function.

    Mitsuba's barycentrics can stray a hair outside the triangle (float32); they are clipped
    and renormalised because the query validates its input strictly.
    """
    n_faces = int(len(query.spectra.faces))

    def fn(face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        f = face_ids.detach().cpu().numpy()
        b = np.clip(bary.detach().cpu().numpy().astype(np.float64), 0.0, 1.0)
        ok = (f >= 0) & (f < n_faces)
        out = np.zeros((len(f), 3), dtype=np.float32)
        if ok.any():
            b_ok = b[ok] / np.maximum(b[ok].sum(1, keepdims=True), 1e-12)
            out[ok] = query.colors(f[ok], b_ok)
        return torch.from_numpy(out).to(face_ids.device)

    return fn


def render_kernelset(
    spectra: Any,
    kernelset: Any,
    views: Sequence[Any] | Any = (30.0, 20.0),
    settings: RenderSettings | None = None,
    seed: int = 0,
    device: str | torch.device | None = None,
) -> np.ndarray | list[np.ndarray]:
    """Render a kernel set on its spectra's mesh: linear RGB (H, W, 3), or a list for a list.

    ``views`` is one view (Camera, (azimuth, elevation), "AZ,EL", index), a list of them, or
    a view dataset (:class:`~hktex_engine.fitting.views.Views`: its cameras, in order).
    """
    from hktex_engine.kernels.query import AlbedoQuery

    query = AlbedoQuery(spectra, kernelset, device=device)
    V = file_frame_vertices(spectra)
    scene = RenderScene(V, spectra.faces, settings, albedo_fn=query_albedo_fn(query))
    single, cams = _cameras(views, V)
    images = [scene.render(c, seed=seed) for c in cams]
    return images[0] if single else images


def render_uv(
    mesh: Any,
    views: Sequence[Any] | Any = (30.0, 20.0),
    settings: RenderSettings | None = None,
    seed: int = 0,
) -> np.ndarray | list[np.ndarray]:
    """Render a textured :class:`~hktex_engine.geometry.mesh.Mesh` with its own UV texture (bitmap)."""
    if not mesh.has_texture:
        raise RenderError("the mesh has no UV texture to render")
    V = mesh.to_file_units(mesh.vertices)
    scene = RenderScene(V, mesh.faces, settings, corner_uvs=mesh.corner_uvs, texture=mesh.texture)
    single, cams = _cameras(views, V)
    images = [scene.render(c, seed=seed) for c in cams]
    return images[0] if single else images


def render_png(
    spectra: Any,
    kernelset: Any,
    width: int = 256,
    height: int = 256,
    view: Any = (30.0, 20.0),
    spp: int = 16,
    lighting: Lighting | None = None,
    device: str | torch.device | None = None,
) -> bytes:
    """One preview as sRGB PNG bytes (what the service's render route returns)."""
    settings = RenderSettings(width=width, height=height, spp=spp, lighting=lighting or Lighting())
    image = render_kernelset(spectra, kernelset, view, settings, device=device)
    return encode_png(image)
