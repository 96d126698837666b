"""The ``.hkt`` kernel-set file (INTERFACES.md section 2).

A zip archive holding one ``.npy`` per member (numpy's ``.npz`` layout, so ``np.load`` opens
it) plus ``manifest.json``. Compact storage (the default) keeps every member and meaning and
only narrows dtypes, which a reader gets back as ordinary numbers without scale factors:

- ``face_ids`` uint16 when the mesh's faces fit (else uint32);
- ``barycentrics``, ``theta``, ``eta``, ``sharpness``, ``colors`` float16 (relative error
  below 5e-4: far under one 8-bit colour step, and a centre moves by < 3e-4 of its face);
- ``threshold`` float32: the soft step is steep near ``eps`` (slope up to ``k/4 = 50``), so a
  float16 threshold near 1 (spacing 4.9e-4) would shift responses visibly;
- ``base_color`` float32.

Reading is defensive because a file may come from anyone: members are checked for size before
they are decompressed (zip bombs), ``.npy`` headers are parsed with pickles refused, and
shapes, ranges, finiteness and the mesh / spectral-config hashes are checked before use.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hktex_engine.config import KernelConfig
from hktex_engine.errors import KernelSetError
from hktex_engine.kernels.model import KernelSet

FORMAT = "hktex-kernels"
VERSION = 1
#: Members and their columns (0 = a vector). ``base_color`` has 3 entries, not one per kernel.
MEMBERS: dict[str, int] = {
    "face_ids": 0,
    "barycentrics": 3,
    "theta": 0,
    "eta": 0,
    "threshold": 0,
    "sharpness": 0,
    "colors": 3,
    "base_color": 0,
}
COLOR_SPACES = ("srgb", "linear")
#: Refuse kernel counts beyond this (a fit's budget is ~70k; 10M is far past any real set).
MAX_KERNELS = 10_000_000
MAX_MANIFEST_BYTES = 1 << 20
#: An ``.npy`` header is at most this long for our arrays (format v1 pads to 64-byte blocks).
NPY_HEADER_BYTES = 4096
_COMPACT_FLOATS = {
    "barycentrics": np.float16,
    "theta": np.float16,
    "eta": np.float16,
    "threshold": np.float32,
    "sharpness": np.float16,
    "colors": np.float16,
    "base_color": np.float32,
}


def save_hkt(kernelset: KernelSet, path: str | Path, compact: bool = True) -> Path:
    """Validate and write ``kernelset`` to ``path`` atomically (temporary file + rename)."""
    path = Path(path)
    payload = _encode(kernelset, compact)  # validates before anything touches the disk
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(payload)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def hkt_bytes(kernelset: KernelSet, compact: bool = True) -> dict[str, int]:
    """Storage of a kernel set: ``raw`` (sum of the stored arrays) and ``zip`` (the file)."""
    raw = sum(a.nbytes for a in _stored_arrays(kernelset, compact).values())
    return {"raw": int(raw), "zip": len(_encode(kernelset, compact))}


def _encode(kernelset: KernelSet, compact: bool) -> bytes:
    """The whole ``.hkt`` file in memory (a kernel set is a few MB at most)."""
    kernelset.validate()
    if kernelset.color_space not in COLOR_SPACES:
        raise KernelSetError(f"color_space must be one of {COLOR_SPACES}")
    arrays = _stored_arrays(kernelset, compact)
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "count": len(kernelset),
        "mesh_hash": kernelset.mesh_hash,
        "config_hash": kernelset.config_hash,
        **kernelset.kernel_config.to_dict(),
        "color_space": kernelset.color_space,
        "fitting": kernelset.fitting,
        "extras": kernelset.extras,
        "dtypes": {name: str(arr.dtype) for name, arr in arrays.items()},
    }
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(f"{name}.npy", buf.getvalue())
        zf.writestr("manifest.json", json.dumps(manifest, indent=1, default=_json_default))
    return out.getvalue()


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable in a .hkt manifest: {type(value).__name__}")


def _stored_arrays(ks: KernelSet, compact: bool) -> dict[str, np.ndarray]:
    arrays = {name: np.asarray(getattr(ks, name)) for name in MEMBERS}
    if not compact:
        out = {n: a.astype(np.float32) for n, a in arrays.items() if n != "face_ids"}
        return {"face_ids": arrays["face_ids"].astype(np.int64), **out}
    fmax = int(arrays["face_ids"].max())
    face_dtype = np.uint16 if fmax <= np.iinfo(np.uint16).max else np.uint32
    out = {"face_ids": arrays["face_ids"].astype(face_dtype)}
    for name, dtype in _COMPACT_FLOATS.items():
        out[name] = arrays[name].astype(dtype)
    return out


def load_hkt(
    path: str | Path | BinaryIO,
    expect_mesh_hash: str | None = None,
    expect_config_hash: str | None = None,
) -> KernelSet:
    """Read and check a ``.hkt`` file; :class:`KernelSetError` says what is wrong with it."""
    try:
        with zipfile.ZipFile(path) as zf:
            manifest = _read_manifest(zf)
            n = manifest["count"]
            arrays = {name: _read_member(zf, name, n, cols) for name, cols in MEMBERS.items()}
    except zipfile.BadZipFile as exc:
        raise KernelSetError(f"not a kernel-set file (not a valid zip archive: {exc})") from exc
    except (OSError, EOFError, zlib.error, zipfile.LargeZipFile) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        raise KernelSetError(f"kernel-set file is truncated or unreadable: {exc}") from exc
    if expect_mesh_hash is not None and manifest.get("mesh_hash") != expect_mesh_hash:
        raise KernelSetError(
            "the kernel set was fitted on another mesh "
            f"(file {str(manifest.get('mesh_hash'))[:12]}, expected {expect_mesh_hash[:12]})"
        )
    if expect_config_hash is not None and manifest.get("config_hash") != expect_config_hash:
        raise KernelSetError(
            "the kernel set was fitted with another spectral config "
            f"(file {str(manifest.get('config_hash'))[:12]}, expected {expect_config_hash[:12]})"
        )
    ks = KernelSet(
        **arrays,
        kernel_config=_kernel_config(manifest),
        mesh_hash=str(manifest.get("mesh_hash", "")),
        config_hash=str(manifest.get("config_hash", "")),
        color_space=manifest["color_space"],
        fitting=manifest.get("fitting") or {},
        extras=manifest.get("extras") or {},
    )
    ks.validate()
    return ks


def _read_manifest(zf: zipfile.ZipFile) -> dict:
    try:
        info = zf.getinfo("manifest.json")
    except KeyError:
        raise KernelSetError("not a kernel-set file (no manifest.json)") from None
    if info.file_size > MAX_MANIFEST_BYTES:
        raise KernelSetError("manifest.json is implausibly large")
    try:
        manifest = json.loads(zf.read(info).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KernelSetError(f"manifest.json is not valid JSON: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise KernelSetError(f"not a kernel-set file (format is not {FORMAT!r})")
    version = manifest.get("version")
    if not isinstance(version, int) or version < 1 or version > VERSION:
        raise KernelSetError(f"unsupported kernel-set version {version!r} (this reader: {VERSION})")
    count = manifest.get("count")
    if not isinstance(count, int) or not 0 < count <= MAX_KERNELS:
        raise KernelSetError(
            f"manifest count {count!r} is not a kernel count in [1, {MAX_KERNELS}]"
        )
    if manifest.get("color_space") not in COLOR_SPACES:
        raise KernelSetError(f"manifest color_space must be one of {COLOR_SPACES}")
    return manifest


def _read_member(zf: zipfile.ZipFile, name: str, n: int, cols: int) -> np.ndarray:
    try:
        info = zf.getinfo(f"{name}.npy")
    except KeyError:
        raise KernelSetError(f"kernel-set file lacks member {name!r}") from None
    rows = 1 if name == "base_color" else n
    limit = NPY_HEADER_BYTES + rows * max(cols, 1) * 8 * (3 if name == "base_color" else 1)
    if info.file_size > limit:
        raise KernelSetError(f"member {name!r} is larger than {n} kernels can need")
    with zf.open(info) as fh:
        data = fh.read(limit + 1)  # never trust the header alone
    if len(data) > limit:
        raise KernelSetError(f"member {name!r} is larger than {n} kernels can need")
    try:
        arr = np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise KernelSetError(f"member {name!r} is not a plain .npy array: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise KernelSetError(f"member {name!r} has unsupported dtype {arr.dtype}")
    expect = (3,) if name == "base_color" else (n, cols) if cols else (n,)
    if arr.shape != expect:
        raise KernelSetError(f"member {name!r} has shape {arr.shape}, expected {expect}")
    if name == "face_ids":
        if arr.dtype.kind == "f":
            raise KernelSetError("member 'face_ids' must be integers")
        return arr.astype(np.int64)
    return arr.astype(np.float64)


def _kernel_config(manifest: dict) -> KernelConfig:
    try:
        cfg = KernelConfig(
            diffusion_time=float(manifest["diffusion_time"]),
            sigma_b=float(manifest["sigma_b"]),
            k_search=int(manifest["k_search"]),
            k_blend=int(manifest["k_blend"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise KernelSetError(f"manifest lacks a valid kernel config: {exc}") from exc
    if not (cfg.diffusion_time > 0 and cfg.sigma_b > 0 and cfg.k_search >= 1 and cfg.k_blend >= 1):
        raise KernelSetError("manifest kernel config must be positive")
    if not np.isfinite([cfg.diffusion_time, cfg.sigma_b]).all():
        raise KernelSetError("manifest kernel config must be finite")
    return cfg
