"""The inside of a compute worker process: warm kernel sets, albedo queries, renders, bakes.

The forkserver imports torch and the query engine at service start (``validation.PRELOAD``),
so a new worker is a fork of a process that already holds them: a replacement for a killed
worker is ready in milliseconds, not the seconds of imports. This module itself stays light
(the API process imports it to name ``main`` as the workers' target); the engine is imported
inside the worker.

A worker serves one request at a time over its pipe. Each request runs under
``RLIMIT_AS = current address space + the request's memory budget`` (lowered for the request,
raised again after), so a request that would need more memory fails with ``MemoryError`` (a
422) instead of swapping the machine; after a request that left the worker big (Dr.Jit keeps
render buffers) the worker retires and the pool starts a fresh one.
"""

from __future__ import annotations

import ctypes
import io
import json
import os
import resource
import shutil
import signal
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from hktex_engine.errors import HKTexError, KernelSetError, SpectraError

BARY_TOL = 1e-3
PR_SET_PDEATHSIG = 1


class RequestError(Exception):
    """A request refused for a reason the caller can fix: sent back as ``status``."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status, self.detail = status, detail


class _Warm:
    """One kernel set ready to answer: its spectra (memory-mapped), kernels and query state."""

    def __init__(self, spectra_path: str, hkt_path: str, mesh_hash: str) -> None:
        from hktex_engine.kernels.hkt import load_hkt
        from hktex_engine.kernels.query import AlbedoQuery
        from hktex_engine.spectra.grid import load_spectra

        self.spectra = load_spectra(spectra_path, mmap=True)
        self.kernelset = load_hkt(hkt_path, expect_mesh_hash=mesh_hash)
        self.query = AlbedoQuery(self.spectra, self.kernelset)
        self.n_faces = int(self.spectra.faces.shape[0])


class Worker:
    """The request loop's state: an LRU of warm kernel sets."""

    def __init__(self, cache_size: int) -> None:
        self.cache_size = max(1, cache_size)
        self.cache: OrderedDict[str, _Warm] = OrderedDict()

    def warm(self, kernelset_id: str, spectra_path: str, hkt_path: str, mesh_hash: str) -> _Warm:
        entry = self.cache.get(kernelset_id)
        if entry is None:
            entry = _Warm(spectra_path, hkt_path, mesh_hash)
            self.cache[kernelset_id] = entry
            while len(self.cache) > self.cache_size:
                self.cache.popitem(last=False)
        self.cache.move_to_end(kernelset_id)
        return entry

    def albedo(self, ks: dict, kind: str, face_ids, bary, points, chunk: int, npy: bool) -> bytes:
        """The encoded answer (NPY float32 or JSON), so encoding a big answer also happens
        here rather than on the API's event loop."""
        warm = self.warm(**ks)
        if kind == "points":
            colors = _chunked(warm.query.colors_at_points, len(points), chunk, points)
        else:
            check_faces(face_ids, bary, warm.n_faces)
            colors = _chunked(warm.query.colors, len(face_ids), chunk, face_ids, bary)
        if npy:
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(colors, dtype="<f4"), allow_pickle=False)
            return buf.getvalue()
        body = {"count": int(len(colors)), "colors": colors.tolist()}
        return json.dumps(body, separators=(",", ":")).encode()

    def render(self, ks: dict, width: int, height: int, view: str, spp: int) -> bytes:
        try:
            from hktex_engine.render.mitsuba import render_png
        except Exception as exc:  # mitsuba missing or broken on this host
            raise RequestError(503, f"renderer unavailable: {exc}") from None
        warm = self.warm(**ks)
        try:
            return render_png(
                warm.spectra, warm.kernelset, width=width, height=height, view=view, spp=spp
            )
        except ValueError as exc:
            raise RequestError(422, str(exc)) from None
        except MemoryError:
            raise
        except HKTexError as exc:
            raise RequestError(503, f"render failed: {type(exc).__name__}: {exc}") from None

    def bake(
        self,
        ks: dict,
        mesh: dict | None,
        resolution: int,
        max_vertices: int,
        tmp: str,
        final: str,
    ) -> bytes:
        """Bake every viewer layer into ``tmp`` and publish it as ``final`` (one rename: a
        reader sees all of a bake or none); the answer is its ``bake.json``. ``tmp`` is the
        API's to remove if this worker is killed halfway."""
        done = Path(final) / "bake.json"
        if done.is_file():  # another request (or another API process) was first
            return done.read_bytes()
        warm = self.warm(**ks)
        tmp_dir = Path(tmp)
        tmp_dir.mkdir(parents=True)
        try:
            try:
                write_bake(tmp_dir, warm.spectra, warm.kernelset, mesh, resolution, max_vertices)
            except MemoryError:
                raise
            except (HKTexError, ValueError) as exc:
                raise RequestError(422, f"bake failed: {type(exc).__name__}: {exc}") from None
            Path(final).parent.mkdir(parents=True, exist_ok=True)
            try:
                os.rename(tmp_dir, final)
            except OSError:  # published meanwhile by someone else: theirs wins
                if not done.is_file():
                    raise
        finally:
            shutil.rmtree(tmp_dir, ignore_errors=True)
        return done.read_bytes()


def write_bake(
    out: Path, spectra, kernelset, mesh_files: dict | None, resolution: int, max_vertices: int
) -> dict:
    """The kernel layer (PNG), the textured GLB and, for a mesh textured on its own UVs, the
    original and error layers, into ``out``; ``bake.json`` (written last) describes them."""
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.render.bake import (
        bake_texture,
        rasterize_uv,
        textured_trimesh,
        write_glb,
        write_png,
    )
    from hktex_engine.render.errormap import DEFAULT_SCALE, error_texture, resample_texture

    start = time.perf_counter()
    mesh = None
    if mesh_files is not None:
        mesh = load_mesh(
            mesh_files["mesh_path"],
            texture=mesh_files.get("texture_path"),
            max_vertices=max_vertices,
        )
        if mesh.content_hash != spectra.mesh_hash:
            mesh = None  # not the geometry of these spectra: bake on a fresh atlas
    bake = bake_texture(spectra, kernelset, mesh, resolution)
    write_png(out / "kernel.png", bake.texture)
    write_glb(out / "model.glb", textured_trimesh(spectra, bake))
    layers, scale, rms = ["kernel"], None, None
    if mesh is not None and mesh.texture is not None and bake.atlas == "mesh":
        original = resample_texture(mesh.texture, resolution)
        write_png(out / "original.png", original)
        covered = rasterize_uv(bake.corner_uvs, resolution, resolution)[0] >= 0
        heat, rms = error_texture(bake.texture, original, DEFAULT_SCALE, covered)
        write_png(out / "error.png", heat)
        layers += ["original", "error"]
        scale = DEFAULT_SCALE
    meta = {
        "resolution": resolution,
        "atlas": bake.atlas,
        "coverage": round(bake.coverage, 4),
        "layers": layers,
        "error_scale": scale,
        "error_rms": None if rms is None else round(rms, 5),
        "glb_bytes": (out / "model.glb").stat().st_size,
        "seconds": round(time.perf_counter() - start, 3),
    }
    (out / "bake.json").write_text(json.dumps(meta))  # written last: marks it complete
    return meta


def check_views(root: str) -> bytes:
    """Read and validate a views dataset (decoding every image), or say why not (422)."""
    from hktex_engine.fitting.views import load_views

    try:
        load_views(root)
    except (HKTexError, ValueError) as exc:
        raise RequestError(422, f"{type(exc).__name__}: {' '.join(str(exc).split())}") from None
    except MemoryError:
        raise
    except Exception as exc:  # an image decoder failing on hostile bytes is still bad input
        detail = " ".join(str(exc).split())[:500]
        raise RequestError(
            422, f"unreadable views dataset: {type(exc).__name__}: {detail}"
        ) from None
    return b"ok"


def _chunked(fn, n: int, chunk: int, *arrays) -> np.ndarray:
    out = np.empty((n, 3), dtype=np.float32)
    for start in range(0, n, chunk):
        sl = slice(start, start + chunk)
        out[sl] = fn(*(a[sl] for a in arrays))
    return out


def check_faces(face_ids: np.ndarray, bary: np.ndarray, n_faces: int) -> None:
    if len(face_ids) and (face_ids.min() < 0 or face_ids.max() >= n_faces):
        bad = int(face_ids[(face_ids < 0) | (face_ids >= n_faces)][0])
        raise RequestError(422, f"face id {bad} is out of range 0..{n_faces - 1}")
    if len(bary) and (bary.min() < -BARY_TOL or np.abs(bary.sum(axis=1) - 1).max() > BARY_TOL):
        raise RequestError(422, "barycentrics must be >= 0 and sum to 1 per row")


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _limit_memory(budget: int) -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    soft = _address_space() + budget
    if hard != resource.RLIM_INFINITY:
        soft = min(soft, hard)
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _unlimit_memory() -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (hard, hard))


def _die_with_parent() -> None:
    """SIGKILL when the forkserver goes (it goes when the API process goes, even by SIGKILL):
    a worker in the middle of a long render must not outlive the service."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:  # not Linux/glibc: the pipe's EOF still ends an idle worker
        pass


def handle(worker: Worker, kind: str, payload: dict[str, Any], memory: int) -> tuple:
    """One request: ``("ok", bytes)`` or ``("error", status, detail)``."""
    _limit_memory(memory)
    try:
        if kind == "albedo":
            return ("ok", worker.albedo(**payload))
        if kind == "render":
            return ("ok", worker.render(**payload))
        if kind == "views":
            return ("ok", check_views(**payload))
        if kind == "bake":
            return ("ok", worker.bake(**payload))
        if kind == "ping":  # a liveness probe; ``seconds`` (at most 5) holds the worker
            time.sleep(min(max(float(payload.get("seconds", 0.0)), 0.0), 5.0))
            return ("ok", str(os.getpid()).encode())
        return ("error", 400, f"unknown compute request {kind!r}")
    except RequestError as exc:
        return ("error", exc.status, exc.detail)
    except MemoryError:
        worker.cache.clear()  # whatever half-built state the failure left must go
        return (
            "error",
            422,
            f"the request needs more than its memory budget ({memory // 2**20} MiB): "
            "ask for fewer points, pixels or samples",
        )
    except (SpectraError, KernelSetError) as exc:
        return ("error", 409, f"{type(exc).__name__}: {exc}")
    except (HKTexError, ValueError) as exc:
        return ("error", 422, f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # noqa: BLE001 - a bug or a broken host: the caller gets a 503
        return ("error", 503, f"compute failed: {type(exc).__name__}: {exc}")
    finally:
        _unlimit_memory()


def main(conn: Any, threads: int, cache_size: int, recycle_bytes: int, nice: int = 0) -> None:
    """The worker's loop until its pipe closes or it grows past ``recycle_bytes``.

    ``nice`` lowers the worker's CPU priority: when queries saturate the cores, the API
    process (health checks, metadata, uploads, the event loop that answers everyone) must
    still be scheduled first."""
    _die_with_parent()
    if nice:
        os.nice(nice)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the API process's to handle
    import torch

    torch.set_num_threads(max(1, threads))
    try:
        import faiss

        faiss.omp_set_num_threads(max(1, threads))
    except Exception:  # noqa: BLE001 - faiss is optional (torch KNN fallback)
        pass
    from hktex_engine.kernels import fused_blend

    fused_blend.warm()  # built in the forkserver already (compute_preload): milliseconds here
    worker = Worker(cache_size)
    while True:
        try:
            kind, payload, memory = conn.recv()
        except (EOFError, OSError):
            return
        reply = handle(worker, kind, payload, memory)
        retire = resident_bytes() > recycle_bytes
        try:
            conn.send((*reply, retire))
        except (BrokenPipeError, OSError):
            return
        if retire:
            return
