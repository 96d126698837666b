"""Fidelity and storage measures, exactly as EVALUATION.md defines them.

One implementation for every table (fitting metrics, baselines, benchmarks, service job
metrics), so numbers computed by different modules can be set side by side.
"""

from __future__ import annotations

import io
import os
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from skimage.metrics import structural_similarity

from hktex_engine.errors import TextureError
from hktex_engine.geometry.mesh import Mesh
from hktex_engine.geometry.sampling import sample_surface, texture_lookup, uv_at

#: zlib level used for every "zip" byte count: the maximum, as `zip -9` would.
ZIP_LEVEL = 9

AlbedoFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _masked(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None) -> tuple:
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"pred {pred.shape} and target {target.shape} differ in shape")
    if mask is None:
        return pred, target
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != pred.shape[: mask.ndim]:
        raise ValueError(f"mask {mask.shape} does not match the leading dims of {pred.shape}")
    if not mask.any():
        raise ValueError("the mask selects no pixels")
    return pred[mask], target[mask]


def psnr(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0
) -> float:
    """Peak signal-to-noise ratio in dB over all channels of the (masked) pixels or points.

    ``mask`` covers the leading dimensions (an (H, W) mask for (H, W, 3) images, a (P,) mask
    for (P, 3) point colours). Identical inputs give ``inf``.
    """
    p, t = _masked(pred, target, mask)
    mse = float(np.mean((p - t) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def ssim(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0
) -> float:
    """Structural similarity of two (H, W[, C]) images; with a mask, the SSIM map's mean over it.

    The map comes from scikit-image (uniform 7x7 window, its defaults). Without a mask this is
    scikit-image's mean SSIM; with one, the map (averaged over channels) is averaged over the
    masked pixels, so background pixels cannot flatter any method.
    """
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape or pred.ndim not in (2, 3):
        raise ValueError(
            f"ssim needs two equal (H, W[, C]) images, got {pred.shape}, {target.shape}"
        )
    channel_axis = -1 if pred.ndim == 3 else None
    mean, full = structural_similarity(
        pred, target, data_range=data_range, channel_axis=channel_axis, full=True
    )
    if mask is None:
        return float(mean)  # scikit-image's own mean (it crops the window-wide border)
    if pred.ndim == 3:
        full = full.mean(axis=-1)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != full.shape:
        raise ValueError(f"mask {mask.shape} does not match image {full.shape}")
    if not mask.any():
        raise ValueError("the mask selects no pixels")
    return float(full[mask].mean())


def storage_bytes(
    source: str | os.PathLike | bytes | np.ndarray | Mapping[str, np.ndarray],
) -> dict[str, int]:
    """Raw and zip-compressed (deflate, level 9) sizes of stored data, as the paper counts them.

    - bytes or a plain file: raw = its length; zip = its deflated length.
    - a zip archive (``.hkt``, ``.npz``): raw = the sum of its members' uncompressed sizes;
      zip = the sum of those members deflated at level 9 (independent of how it was written).
    - an array or a mapping of arrays: raw = their ``nbytes``; zip = each array's bytes
      deflated, summed.
    Container overhead (zip headers, npy headers) is not counted in ``zip``: it is the same
    few dozen bytes for every method and would blur small baselines.
    """
    if isinstance(source, np.ndarray):
        return _arrays_bytes([source])
    if isinstance(source, Mapping):
        return _arrays_bytes(list(source.values()))
    if isinstance(source, bytes | bytearray | memoryview):
        data = bytes(source)
        if zipfile.is_zipfile(io.BytesIO(data)):
            return _zip_members_bytes(zipfile.ZipFile(io.BytesIO(data)))
        return {"raw": len(data), "zip": _deflated(data)}
    path = Path(source)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            return _zip_members_bytes(zf)
    data = path.read_bytes()
    return {"raw": len(data), "zip": _deflated(data)}


def _deflated(data: bytes) -> int:
    # Raw deflate stream (wbits=-15): what a zip member holds, without zlib's 6-byte wrapper.
    comp = zlib.compressobj(ZIP_LEVEL, zlib.DEFLATED, -15)
    return len(comp.compress(data) + comp.flush())


def _arrays_bytes(arrays: list[np.ndarray]) -> dict[str, int]:
    raw = sum(int(np.asarray(a).nbytes) for a in arrays)
    zipped = sum(_deflated(np.ascontiguousarray(a).tobytes()) for a in arrays)
    return {"raw": raw, "zip": zipped}


def _zip_members_bytes(zf: zipfile.ZipFile) -> dict[str, int]:
    raw = 0
    zipped = 0
    for info in zf.infolist():
        data = zf.read(info)
        raw += len(data)
        zipped += _deflated(data)
    return {"raw": raw, "zip": zipped}


def surface_samples(
    mesh: Mesh, n_points: int = 60000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The evaluation points of EVALUATION.md and their targets: (face_ids, bary, rgb).

    Area-uniform with ``np.random.default_rng(seed)``; the target is the bilinear, wrapped,
    v-flipped lookup of the full-resolution texture at the interpolated corner UV.
    """
    if not mesh.has_texture:
        raise TextureError("surface PSNR needs a mesh with corner UVs and a texture")
    face_ids, bary = sample_surface(mesh.vertices, mesh.faces, n_points, seed)
    target = texture_lookup(mesh.texture, uv_at(mesh.corner_uvs, face_ids, bary))
    return face_ids, bary, target


def surface_psnr(mesh: Mesh, albedo_fn: AlbedoFn, n_points: int = 60000, seed: int = 0) -> float:
    """Surface PSNR (dB): ``albedo_fn(face_ids, bary) -> (P, 3)`` against the texture."""
    face_ids, bary, target = surface_samples(mesh, n_points, seed)
    pred = np.asarray(albedo_fn(face_ids, bary), dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"albedo_fn returned shape {pred.shape}, expected {target.shape}")
    return psnr(pred, target)
