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

Quantised storage (``save_hkt(..., quantised=True)``, format version 4; versions 2 and 3 are
read too) stores each per-kernel member as bit-packed integer codes (big-endian bit order,
``np.packbits``), with the codes' meaning in the manifest's ``quantisation`` table (see :data:`QUANT_BITS` and docs/kernels.md):
the kernels sorted by face id (stably) and the face ids as differences in the bits the largest
difference needs (version 2: the ids themselves), two barycentrics on the simplex grid, ``theta`` linear over
``[0, pi]``, ``eta`` and ``sharpness`` linear in their logarithm, ``threshold`` at cell
midpoints of ``[0.3, 1]`` (so a code never reaches 1), colours linear per channel over their
own range. Version 4 puts the packed members' deflate streams one after another in a single
stored member ``codes.bin`` and the base colour in the manifest; versions 2 and 3 kept one
``uint8`` ``.npy`` member each. :func:`load_hkt` reads versions 1 to 10; a version-1 file is
written unless quantisation is asked for, so older readers keep reading what they read before.

A set for the layered blend (``KernelConfig.blend = "layered"``, ``kernels.blending``) has one
more member, ``priority``: version 5 is version 1 with it (float16 when compact), version 6
version 4 with its codes as a last stream (linear over the priority's range). A paper set is
never written as 5 or 6, and a reader older than them refuses a layered set by its version
rather than evaluating it with the wrong blend.

A set with a biharmonic scale per kernel (``KernelConfig.sigma = "per_kernel"``) has the
member ``sigma_ratio`` (``sigma_j / sigma_B``, float16 when compact; quantised linear in its
logarithm over ``SIGMA_RATIO_RANGE``, 8 bits: steps of 0.36 %): version 7 is version 1 with
it, version 8 version 4 with its codes as a last stream, each with ``priority`` as well when
the set's blend is layered (``sigma_ratio`` after it). A §4-5 set is never written as 7 or 8,
and a reader older than them refuses such a set by its version.

A set with linear colours (``KernelConfig.colour = "linear"``) has the member
``color_slopes`` (N, 9: each kernel's 3 x 3 slope, channel-major; float16 when compact;
quantised linear per column over the column's own range, like the colours, at the colours'
width unless ``bits`` names its own): version
9 is version 1 with it, version 10 version 4 with its codes as the last stream, each after
``priority`` and ``sigma_ratio`` when the set's blend and scale use them (the manifest's
``blend`` and ``sigma`` say so). Neither a §4-5 set nor a set without slopes is ever written as
9 or 10.

Reading is defensive because a file may come from anyone: members are checked for size before
they are decompressed (zip bombs), ``.npy`` headers are parsed with pickles refused, and
shapes, ranges, finiteness and the mesh / spectral-config hashes are checked before use.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hktex_engine.config import SIGMA_RATIO_RANGE, KernelConfig
from hktex_engine.errors import KernelSetError
from hktex_engine.kernels.model import (
    ETA_RANGE,
    PRIORITY_RANGE,
    SHARPNESS_RANGE,
    THETA_RANGE,
    THRESHOLD_RANGE,
    KernelSet,
)

FORMAT = "hktex-kernels"
VERSION = 10
#: The version a plain (unquantised) file is written as; readers of version 1 read it.
PLAIN_VERSION = 1
#: Version 2: quantised members, face ids as plain codes. Version 3 (what is written): the
#: same, with the kernels sorted by face id (stable) and the face ids stored as differences,
#: which zip to ~1-3 bits instead of ~13 (measured -1.1 to -1.3 bytes per kernel).
QUANTISED_V2 = 2
QUANTISED_V3 = 3
#: Version 4 (what is written): version 3's codes in one stored member, ``codes.bin`` (each
#: packed member's own raw deflate stream, one after another in :data:`PACKED` order; their
#: lengths are the manifest's ``streams``), the base colour in the manifest, the manifest
#: without indentation. The same numbers; ~1.2-1.4 KB less per file (seven zip entries and
#: ``.npy`` headers fewer), which is most of a small set's overhead.
QUANTISED_VERSION = 4
#: The layered blend's versions: 1 and 4 with a ``priority`` member (see the module doc).
PLAIN_LAYERED_VERSION = 5
QUANTISED_LAYERED_VERSION = 6
LAYERED_VERSIONS = (PLAIN_LAYERED_VERSION, QUANTISED_LAYERED_VERSION)
#: A per-kernel sigma's versions: 1 and 4 with a ``sigma_ratio`` member (and ``priority``
#: before it when the blend is layered; see the module doc).
PLAIN_SIGMA_VERSION = 7
QUANTISED_SIGMA_VERSION = 8
SIGMA_VERSIONS = (PLAIN_SIGMA_VERSION, QUANTISED_SIGMA_VERSION)
#: Linear colours' versions: 1 and 4 with a ``color_slopes`` member (after the other
#: extensions' members the manifest names; see the module doc).
PLAIN_LINEAR_VERSION = 9
QUANTISED_LINEAR_VERSION = 10
LINEAR_VERSIONS = (PLAIN_LINEAR_VERSION, QUANTISED_LINEAR_VERSION)
QUANTISED_VERSIONS = (
    QUANTISED_V2,
    QUANTISED_V3,
    QUANTISED_VERSION,
    QUANTISED_LAYERED_VERSION,
    QUANTISED_SIGMA_VERSION,
    QUANTISED_LINEAR_VERSION,
)
#: Versions whose codes sit in one ``codes.bin`` member (version 4's layout).
STREAM_VERSIONS = (
    QUANTISED_VERSION,
    QUANTISED_LAYERED_VERSION,
    QUANTISED_SIGMA_VERSION,
    QUANTISED_LINEAR_VERSION,
)
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
#: Version 4's one member: the packed members' deflate streams, stored (not compressed again).
CODES_MEMBER = "codes.bin"
#: The per-kernel members a quantised file packs, in their stored order.
PACKED = tuple(name for name in MEMBERS if name != "base_color")
#: A layered set's members: the paper's and one priority per kernel.
LAYERED_MEMBERS: dict[str, int] = {**MEMBERS, "priority": 0}
#: Every member a file may hold (the extensions' in their stored order, last).
ALL_MEMBERS: dict[str, int] = {**LAYERED_MEMBERS, "sigma_ratio": 0, "color_slopes": 9}
#: Members quantised per column over each column's own range (the manifest's table holds
#: their ``lo`` / ``hi`` lists).
COLUMN_CODED = ("colors", "color_slopes")
COLOR_SPACES = ("srgb", "linear")
#: Refuse kernel counts beyond this (a fit's budget is ~70k; 10M is far past any real set).
MAX_KERNELS = 10_000_000
MAX_MANIFEST_BYTES = 1 << 20
#: An ``.npy`` header is at most this long for our arrays (format v1 pads to 64-byte blocks).
NPY_HEADER_BYTES = 4096
#: Default code widths of the quantised format (face ids: the bits their largest difference
#: needs). Chosen on fitted sets (docs/decisions.md, benchmarks/results/hkt_quantised*.md):
#: the quantised albedo stays ~58-60 dB from the exact one, so a fit of up to ~42 dB loses
#: <= 0.1 dB. Narrower widths (7/6/6/9/5/7: -1.1 bytes per kernel) measured 51.9 dB from the
#: exact albedo: fine for a 32 dB fit (+0.008 dB), 0.2-0.3 dB on a 40 dB one; ``bits=`` asks.
QUANT_BITS: dict[str, int] = {
    "barycentrics": 8,
    "theta": 8,
    "eta": 8,
    "threshold": 10,
    "sharpness": 8,
    "colors": 8,
}
#: The layered blend's priority (``bits={"priority": b}`` overrides): 8 bits over [-8, 8] is
#: a step of 0.063, a share off by at most 3 % between two kernels of neighbouring codes.
PRIORITY_BITS = 8
#: A per-kernel sigma's ratio (``bits={"sigma_ratio": b}`` overrides): 8 bits over the log of
#: [0.4, 2.5], a step of 0.72 % in sigma (0.36 % at most off), a footprint's radius likewise.
SIGMA_RATIO_BITS = 8
#: Colour slopes (``bits={"color_slopes": b}`` overrides; else the colours' width): 8 bits
#: over each column's range.
SLOPE_BITS = 8
#: How each member's codes map to values: (map, lo, hi); colours carry per-channel ranges.
_QUANT_MAPS: dict[str, tuple[str, float, float]] = {
    "theta": ("linear", THETA_RANGE[0], THETA_RANGE[1]),
    "eta": ("log", ETA_RANGE[0], ETA_RANGE[1]),
    "threshold": ("mid", THRESHOLD_RANGE[0], 1.0),
    "sharpness": ("log", SHARPNESS_RANGE[0], SHARPNESS_RANGE[1]),
    "priority": ("linear", PRIORITY_RANGE[0], PRIORITY_RANGE[1]),
    "sigma_ratio": ("log", SIGMA_RATIO_RANGE[0], SIGMA_RATIO_RANGE[1]),
}
_COMPACT_FLOATS = {
    "barycentrics": np.float16,
    "theta": np.float16,
    "eta": np.float16,
    "threshold": np.float32,
    "sharpness": np.float16,
    "colors": np.float16,
    "base_color": np.float32,
    "priority": np.float16,  # 4e-3 at |beta| = 8 at most: a share changes by < 0.4 %
    "sigma_ratio": np.float16,  # relative 4.9e-4: a footprint's radius by as much
    # relative 4.9e-4: at most 32 x 0.1 x 4.9e-4 = 1.6e-3 of colour across a footprint 0.1
    # wide, under half an 8-bit step
    "color_slopes": np.float16,
}


def save_hkt(
    kernelset: KernelSet,
    path: str | Path,
    compact: bool = True,
    quantised: bool = False,
    bits: dict[str, int] | None = None,
) -> Path:
    """Validate and write ``kernelset`` to ``path`` atomically (temporary file + rename).

    ``quantised=True`` writes the version-4 format (``bits`` overrides :data:`QUANT_BITS`
    per member); otherwise version 1, ``compact`` choosing narrow dtypes or float32/int64.
    """
    path = Path(path)
    payload = encode_hkt(kernelset, compact, quantised, bits)  # validates before any disk write
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(payload)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def hkt_bytes(
    kernelset: KernelSet,
    compact: bool = True,
    quantised: bool = False,
    bits: dict[str, int] | None = None,
) -> dict[str, int]:
    """Storage of a kernel set: ``raw`` (sum of the stored arrays) and ``zip`` (the file)."""
    if quantised:
        ks = sorted_by_face(kernelset)
        arrays, _ = _quantised_arrays(ks, _bits(ks, bits))
    else:
        arrays = _stored_arrays(kernelset, compact)
    raw = sum(a.nbytes for a in arrays.values())
    return {"raw": int(raw), "zip": len(encode_hkt(kernelset, compact, quantised, bits))}


def encode_hkt(
    kernelset: KernelSet,
    compact: bool,
    quantised: bool = False,
    bits: dict[str, int] | None = None,
) -> bytes:
    """The whole ``.hkt`` file in memory (a kernel set is a few MB at most), as
    :func:`save_hkt` writes it; ``load_hkt(io.BytesIO(...))`` reads it back."""
    kernelset.validate()
    if kernelset.color_space not in COLOR_SPACES:
        raise KernelSetError(f"color_space must be one of {COLOR_SPACES}")
    extra: dict = {}
    streams = b""
    if quantised:
        kernelset = sorted_by_face(kernelset)
        members, extra["quantisation"] = _quantised_arrays(kernelset, _bits(kernelset, bits))
        extra["base_color"] = [float(x) for x in members.pop("base_color")]  # float32, exact
        # each packed member deflated on its own (its own Huffman tables: one deflate of them
        # all measured +810 B on a 2,216-kernel set), one after another in one stored entry
        parts = [_deflate(members[name].tobytes()) for name in _packed(*_kinds(kernelset))]
        extra["streams"] = [len(p) for p in parts]
        streams = b"".join(parts)
        arrays = {}
    else:
        arrays = _stored_arrays(kernelset, compact)
    manifest = {
        "format": FORMAT,
        "version": _version(quantised, *_kinds(kernelset)),
        "count": len(kernelset),
        "mesh_hash": kernelset.mesh_hash,
        "config_hash": kernelset.config_hash,
        **kernelset.kernel_config.to_dict(),
        "color_space": kernelset.color_space,
        "fitting": kernelset.fitting,
        "extras": kernelset.extras,
        **({"dtypes": {name: str(arr.dtype) for name, arr in arrays.items()}} if arrays else {}),
        **extra,
    }
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        if quantised:
            zf.writestr(zipfile.ZipInfo(CODES_MEMBER), streams, compress_type=zipfile.ZIP_STORED)
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(f"{name}.npy", buf.getvalue())
        # a quantised file is about size: its manifest without indentation
        layout = {"separators": (",", ":")} if quantised else {"indent": 1}
        zf.writestr("manifest.json", json.dumps(manifest, default=_json_default, **layout))
    return out.getvalue()


def _kinds(ks: KernelSet) -> tuple[bool, bool, bool]:
    """Which extensions a set uses: (the layered blend, a sigma per kernel, linear colours)."""
    cfg = ks.kernel_config
    return cfg.blend == "layered", cfg.per_kernel_sigma, cfg.linear_colour


def _members(layered: bool, per_sigma: bool = False, linear: bool = False) -> dict[str, int]:
    members = dict(LAYERED_MEMBERS if layered else MEMBERS)
    if per_sigma:
        members["sigma_ratio"] = ALL_MEMBERS["sigma_ratio"]
    if linear:
        members["color_slopes"] = ALL_MEMBERS["color_slopes"]
    return members


def _packed(layered: bool, per_sigma: bool = False, linear: bool = False) -> tuple[str, ...]:
    return tuple(name for name in _members(layered, per_sigma, linear) if name != "base_color")


def written_version(ks: KernelSet, quantised: bool) -> int:
    """The format version :func:`save_hkt` writes ``ks`` as."""
    return _version(quantised, *_kinds(ks))


def _version(quantised: bool, layered: bool, per_sigma: bool = False, linear: bool = False) -> int:
    if linear:
        return QUANTISED_LINEAR_VERSION if quantised else PLAIN_LINEAR_VERSION
    if per_sigma:
        return QUANTISED_SIGMA_VERSION if quantised else PLAIN_SIGMA_VERSION
    if layered:
        return QUANTISED_LAYERED_VERSION if quantised else PLAIN_LAYERED_VERSION
    return QUANTISED_VERSION if quantised else PLAIN_VERSION


def _deflate(data: bytes) -> bytes:
    """A raw deflate stream (no zlib header) at the zip's level."""
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush()


def _inflate(data: bytes, size: int, name: str) -> bytes:
    """Exactly ``size`` bytes from one raw deflate stream, never inflating more than that."""
    d = zlib.decompressobj(-15)
    try:
        out = d.decompress(data, size + 1)
    except zlib.error as exc:
        raise KernelSetError(f"codes of {name!r} are not a deflate stream: {exc}") from exc
    if len(out) != size or not d.eof or d.unused_data:
        raise KernelSetError(f"codes of {name!r} must be {size} packed bytes")
    return out


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable in a .hkt manifest: {type(value).__name__}")


def _stored_arrays(ks: KernelSet, compact: bool) -> dict[str, np.ndarray]:
    arrays = {name: np.asarray(getattr(ks, name)) for name in _members(*_kinds(ks))}
    if not compact:
        out = {n: a.astype(np.float32) for n, a in arrays.items() if n != "face_ids"}
        return {"face_ids": arrays["face_ids"].astype(np.int64), **out}
    fmax = int(arrays["face_ids"].max())
    face_dtype = np.uint16 if fmax <= np.iinfo(np.uint16).max else np.uint32
    out = {"face_ids": arrays["face_ids"].astype(face_dtype)}
    for name, dtype in _COMPACT_FLOATS.items():
        if name in arrays:
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
            n, members = manifest["count"], _members(*_manifest_kinds(manifest))
            if manifest["version"] in QUANTISED_VERSIONS:
                arrays = _read_quantised(zf, manifest, n)
            else:
                arrays = {name: _read_member(zf, name, n, cols) for name, cols in members.items()}
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
    # versions 7-10 say the blend in the manifest; 9-10 the scale as well
    layered = manifest.get("blend", "paper") == "layered"
    named_blend = version in SIGMA_VERSIONS + LINEAR_VERSIONS
    if layered != (version in LAYERED_VERSIONS) and not named_blend:
        raise KernelSetError(
            f"a version-{version} file cannot hold a {manifest.get('blend', 'paper')!r} blend"
        )
    per_sigma = manifest.get("sigma", "uniform") == "per_kernel"
    if per_sigma != (version in SIGMA_VERSIONS) and version not in LINEAR_VERSIONS:
        raise KernelSetError(
            f"a version-{version} file cannot hold a {manifest.get('sigma', 'uniform')!r} sigma"
        )
    linear = manifest.get("colour", "constant") == "linear"
    if linear != (version in LINEAR_VERSIONS):
        raise KernelSetError(
            f"a version-{version} file cannot hold {manifest.get('colour', 'constant')!r} colours"
        )
    return manifest


def _manifest_kinds(manifest: dict) -> tuple[bool, bool, bool]:
    """(layered blend, sigma per kernel, linear colours) of a checked manifest
    (:func:`_read_manifest`)."""
    layered = manifest.get("blend", "paper") == "layered"
    per_sigma = manifest.get("sigma", "uniform") == "per_kernel"
    return layered, per_sigma, manifest["version"] in LINEAR_VERSIONS


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
            blend=str(manifest.get("blend", "paper")),  # versions 1-4 predate the field
            sigma=str(manifest.get("sigma", "uniform")),  # versions 1-6 predate it
            colour=str(manifest.get("colour", "constant")),  # versions 1-8 predate it
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise KernelSetError(f"manifest lacks a valid kernel config: {exc}") from exc
    if not (cfg.diffusion_time > 0 and cfg.sigma_b > 0 and cfg.k_search >= 1 and cfg.k_blend >= 1):
        raise KernelSetError("manifest kernel config must be positive")
    if not np.isfinite([cfg.diffusion_time, cfg.sigma_b]).all():
        raise KernelSetError("manifest kernel config must be finite")
    return cfg


# --------------------------------------------------------------------------- quantised format


def _bits(ks: KernelSet, bits: dict[str, int] | None) -> dict[str, int]:
    """Code widths per member: :data:`QUANT_BITS` overridden by ``bits``, face ids minimal;
    colour slopes follow the colours' width unless given (a ladder of widths that widens the
    colours for a fine fit widens its slopes with them)."""
    out = {
        **QUANT_BITS,
        "priority": PRIORITY_BITS,
        "sigma_ratio": SIGMA_RATIO_BITS,
        "color_slopes": SLOPE_BITS,
    }
    for name, b in (bits or {}).items():
        if name not in out:
            raise KernelSetError(f"no quantisation width for member {name!r}")
        if not isinstance(b, int | np.integer) or not 1 <= int(b) <= 16:
            raise KernelSetError(f"quantisation width of {name!r} must be in [1, 16], not {b!r}")
        out[name] = int(b)
    if "color_slopes" not in (bits or {}):
        out["color_slopes"] = out["colors"]
    out["face_ids"] = max(1, int(_face_deltas(ks.face_ids).max()).bit_length())
    return out


def sorted_by_face(ks: KernelSet) -> KernelSet:
    """The same kernels ordered by face id, stably (the order a quantised file stores).

    Stable, so kernels of one face (clones among them) keep their relative order; only the
    kernel-index key of the tie rule (ALGORITHM.md §5) between kernels of different faces
    changes, and it decides nothing unless their responses and distances are exactly equal.
    """
    order = np.argsort(np.asarray(ks.face_ids), kind="stable")
    if np.array_equal(order, np.arange(order.shape[0])):
        return ks
    per_kernel = {
        name: np.asarray(getattr(ks, name))[order]
        for name in _members(*_kinds(ks))
        if name != "base_color"
    }
    return dataclasses.replace(ks, **per_kernel)


def _face_deltas(face_ids: np.ndarray) -> np.ndarray:
    """Differences of ascending face ids, the first from 0 (all >= 0)."""
    f = np.asarray(face_ids, dtype=np.int64)
    return np.diff(f, prepend=0)


def pack_codes(codes: np.ndarray, bits: int) -> np.ndarray:
    """Unsigned integer codes (< 2**bits) as a ``uint8`` bit stream, ``bits`` per code."""
    c = np.asarray(codes, dtype=np.uint64).ravel()
    shifts = np.arange(bits - 1, -1, -1, dtype=np.uint64)
    planes = ((c[:, None] >> shifts[None, :]) & np.uint64(1)).astype(np.uint8)
    return np.packbits(planes.ravel())


def unpack_codes(data: np.ndarray, count: int, bits: int) -> np.ndarray:
    """Inverse of :func:`pack_codes`: ``count`` codes (int64) from the bit stream."""
    planes = np.unpackbits(np.asarray(data, dtype=np.uint8))[: count * bits].reshape(count, bits)
    weights = (1 << np.arange(bits - 1, -1, -1, dtype=np.int64)).astype(np.int64)
    return planes.astype(np.int64) @ weights


def _encode_scalar(x: np.ndarray, kind: str, lo: float, hi: float, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    x = np.asarray(x, dtype=np.float64)
    if kind == "log":
        x, lo, hi = np.log(np.maximum(x, lo)), np.log(lo), np.log(hi)
    t = (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)
    if kind == "mid":
        return np.clip(np.floor(t * (top + 1)), 0, top).astype(np.int64)
    return np.clip(np.round(t * top), 0, top).astype(np.int64)


def _decode_scalar(q: np.ndarray, kind: str, lo: float, hi: float, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    q = np.asarray(q, dtype=np.float64)
    if kind == "mid":
        return lo + (q + 0.5) * (hi - lo) / (top + 1)
    if kind == "log":
        out = np.exp(np.log(lo) + q * (np.log(hi) - np.log(lo)) / top)
    else:
        out = lo + q * (hi - lo) / top
    return np.clip(out, lo, hi)


def _encode_bary(bary: np.ndarray, bits: int) -> np.ndarray:
    """(b1, b2) on the grid ``k / S``, ``S = 2**bits - 1``, with ``q1 + q2 <= S`` (b0 >= 0)."""
    top = (1 << bits) - 1
    b = np.asarray(bary, dtype=np.float64)[:, 1:] * top
    q = np.clip(np.round(b), 0, top).astype(np.int64)
    over = q.sum(axis=1) > top
    # lower the coordinate rounded up the most; one step suffices (each rounds by <= 1/2)
    col = np.argmax(q - b, axis=1)
    q[over, col[over]] -= 1
    return q


def _decode_bary(q: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    b12 = np.asarray(q, dtype=np.float64) / top
    return np.concatenate([1.0 - b12.sum(axis=1, keepdims=True), b12], axis=1)


def _quantised_arrays(ks: KernelSet, bits: dict[str, int]) -> tuple[dict, dict]:
    """Packed members and the manifest's ``quantisation`` table of a kernel set."""
    deltas = _face_deltas(ks.face_ids)
    if (deltas < 0).any():
        raise KernelSetError("a quantised file stores kernels sorted by face id")
    table: dict[str, dict] = {
        "face_ids": {"bits": bits["face_ids"], "map": "delta"},
        "barycentrics": {"bits": bits["barycentrics"], "map": "simplex"},
    }
    arrays = {
        "face_ids": pack_codes(deltas, bits["face_ids"]),
        "barycentrics": pack_codes(
            _encode_bary(ks.barycentrics, bits["barycentrics"]).T, bits["barycentrics"]
        ),
    }
    for name, (kind, lo, hi) in _QUANT_MAPS.items():
        if name not in _members(*_kinds(ks)):
            continue
        table[name] = {"bits": bits[name], "map": kind, "lo": lo, "hi": hi}
        arrays[name] = pack_codes(
            _encode_scalar(getattr(ks, name), kind, lo, hi, bits[name]), bits[name]
        )
    for name in COLUMN_CODED:
        if name in _members(*_kinds(ks)):
            arrays[name], table[name] = _encode_columns(getattr(ks, name), bits[name])
    arrays["base_color"] = np.asarray(ks.base_color, dtype=np.float32)
    return arrays, table


def _encode_columns(values: np.ndarray, bits: int) -> tuple[np.ndarray, dict]:
    """A per-column member (colours, colour slopes): codes linear over each column's own
    range, column-planar, and its quantisation-table entry."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    codes = np.stack(
        [_encode_scalar(v[:, c], "linear", lo[c], hi[c], bits) for c in range(v.shape[1])]
    )  # (columns, N)
    return pack_codes(codes, bits), {
        "bits": bits,
        "map": "linear",
        "lo": lo.tolist(),
        "hi": hi.tolist(),
    }


def _read_quantised(zf: zipfile.ZipFile, manifest: dict, n: int) -> dict[str, np.ndarray]:
    """Members of a version-2, -3, -4, -6 or -8 file, decoded and checked against the
    manifest's table."""
    table = manifest.get("quantisation")
    if not isinstance(table, dict):
        raise KernelSetError("quantised kernel-set file lacks its quantisation table")
    version = manifest["version"]
    names = _packed(*_manifest_kinds(manifest))
    widths: dict[str, int] = {}
    for name in names:
        spec = table.get(name)
        if not isinstance(spec, dict):
            raise KernelSetError(f"quantisation table lacks member {name!r}")
        bits = spec.get("bits")
        limit = 32 if name == "face_ids" else 16
        if not isinstance(bits, int) or not 1 <= bits <= limit:
            raise KernelSetError(f"quantisation width of {name!r} must be in [1, {limit}]")
        widths[name] = bits
    counts = {name: n * _code_count(name) for name in names}
    sizes = {name: -(-counts[name] * widths[name] // 8) for name in names}
    if version in STREAM_VERSIONS:
        packed = _read_streams(zf, manifest.get("streams"), sizes)
        base = np.asarray(manifest.get("base_color"), dtype=object)
        if base.shape != (3,) or not all(isinstance(x, int | float) for x in base):
            raise KernelSetError("manifest base_color must be three numbers")
        if not np.isfinite(base.astype(np.float64)).all():
            raise KernelSetError("manifest base_color must be finite")
        out: dict[str, np.ndarray] = {"base_color": base.astype(np.float64)}
    else:
        packed = {name: _read_packed(zf, name, 8 * sizes[name]) for name in names}
        out = {"base_color": _read_member(zf, "base_color", n, 0)}
    for name in names:
        out[name] = _decode_member(name, table[name], packed[name], counts[name], n, version)
    return out


def _read_streams(zf: zipfile.ZipFile, lengths, sizes: dict[str, int]) -> dict[str, np.ndarray]:
    """The packed members of a version-4, -6 or -8 file: one raw deflate stream each, in
    ``sizes``' order (:data:`PACKED`, then ``priority``, then ``sigma_ratio``), their compressed
    ``lengths`` in the manifest."""
    ok = isinstance(lengths, list) and len(lengths) == len(sizes)
    if not ok or not all(isinstance(x, int) and x > 0 for x in lengths):
        raise KernelSetError(f"manifest streams must be {len(sizes)} positive lengths")
    try:
        info = zf.getinfo(CODES_MEMBER)
    except KeyError:
        raise KernelSetError(f"kernel-set file lacks member {CODES_MEMBER!r}") from None
    # a deflate stream is never more than ~0.1 % + a few bytes larger than its input
    if info.file_size != sum(lengths) or sum(lengths) > 2 * sum(sizes.values()) + 1024:
        raise KernelSetError(f"member {CODES_MEMBER!r} does not hold the manifest's streams")
    data = zf.read(info)
    out, start = {}, 0
    for name, length in zip(sizes, lengths, strict=True):
        raw = _inflate(data[start : start + length], sizes[name], name)
        out[name] = np.frombuffer(raw, dtype=np.uint8)
        start += length
    return out


def _code_count(name: str) -> int:
    """Codes per kernel of a packed member (two barycentrics: the third is implied)."""
    return 2 if name == "barycentrics" else max(ALL_MEMBERS[name], 1)


def _decode_member(
    name: str, spec: dict, data: np.ndarray, count: int, n: int, version: int
) -> np.ndarray:
    """Values of one packed member from its codes and its entry of the quantisation table."""
    bits = spec["bits"]
    codes = unpack_codes(data, count, bits)
    if name == "face_ids":
        kind = "integer" if version == QUANTISED_V2 else "delta"
        if spec.get("map") != kind:
            raise KernelSetError(f"face ids of a version-{version} file are {kind!r} codes")
        return np.cumsum(codes) if kind == "delta" else codes
    if name == "barycentrics":
        q = codes.reshape(2, n).T
        if (q.sum(axis=1) > (1 << bits) - 1).any():
            raise KernelSetError("barycentrics must be non-negative rows summing to one")
        return _decode_bary(q, bits)
    if name in COLUMN_CODED:
        cols = ALL_MEMBERS[name]
        lo, hi = _bounds(spec, name, cols)
        q = codes.reshape(cols, n)
        return np.stack(
            [_decode_scalar(q[c], "linear", lo[c], hi[c], bits) for c in range(cols)], axis=1
        )
    kind, lo_ref, hi_ref = _QUANT_MAPS[name]
    lo, hi = _bounds(spec, name, 1)
    if spec.get("map") != kind or (lo[0], hi[0]) != (lo_ref, hi_ref):
        raise KernelSetError(f"quantisation of {name!r} is not the format's ({kind})")
    return _decode_scalar(codes, kind, lo_ref, hi_ref, bits)


def _bounds(spec: dict, name: str, width: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        lo = np.atleast_1d(np.asarray(spec["lo"], dtype=np.float64))
        hi = np.atleast_1d(np.asarray(spec["hi"], dtype=np.float64))
    except (KeyError, TypeError, ValueError) as exc:
        raise KernelSetError(f"quantisation range of {name!r} is missing or not numbers") from exc
    if lo.shape != (width,) or hi.shape != (width,):
        raise KernelSetError(f"quantisation range of {name!r} must have {width} entries")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all()):
        raise KernelSetError(f"quantisation range of {name!r} must be finite with lo <= hi")
    return lo, hi


def _read_packed(zf: zipfile.ZipFile, name: str, n_bits: int) -> np.ndarray:
    """A packed member: a 1-D ``uint8`` array of exactly ``ceil(n_bits / 8)`` bytes."""
    expect = -(-n_bits // 8)
    try:
        info = zf.getinfo(f"{name}.npy")
    except KeyError:
        raise KernelSetError(f"kernel-set file lacks member {name!r}") from None
    limit = NPY_HEADER_BYTES + expect
    if info.file_size > limit:
        raise KernelSetError(f"member {name!r} is larger than its kernels can need")
    with zf.open(info) as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise KernelSetError(f"member {name!r} is larger than its kernels can need")
    try:
        arr = np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise KernelSetError(f"member {name!r} is not a plain .npy array: {exc}") from exc
    if arr.dtype != np.uint8 or arr.shape != (expect,):
        raise KernelSetError(
            f"member {name!r} must be {expect} packed bytes (uint8), got {arr.dtype} {arr.shape}"
        )
    return arr
