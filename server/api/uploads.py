"""Uploads streamed to disk under a size limit, and safe archive extraction.

Why not FastAPI's ``UploadFile``: Starlette spools the *whole* multipart body to disk before
the route runs and has no per-file limit, so a 50 GB upload would fill the disk before we
could say 413. Here the body is parsed as it arrives (python-multipart's push parser), each
file part goes straight into a temp file in the blob store, and the count of bytes stops the
transfer the moment it passes the limit.
"""

from __future__ import annotations

import os
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from fastapi import HTTPException, Request, status
from hktex_server.storage.blobs import BlobStore
from python_multipart.multipart import MultipartParser, parse_options_header


@dataclass
class Part:
    name: str
    filename: str
    path: Path
    size: int = 0
    content_type: str = ""


@dataclass
class _State:
    parts: dict[str, Part] = field(default_factory=dict)
    header_field: bytes = b""
    header_value: bytes = b""
    headers: dict[str, bytes] = field(default_factory=dict)
    current: Part | None = None
    handle: object | None = None
    total: int = 0


class _TooLarge(Exception):
    pass


def too_large(limit: int) -> HTTPException:
    return HTTPException(413, detail=f"request body exceeds {limit} bytes")


def _check_declared_length(request: Request, limit: int) -> None:
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError:
            raise HTTPException(400, detail="malformed Content-Length") from None
        if length > limit:
            raise too_large(limit)


async def receive_files(
    request: Request, store: BlobStore, allowed: set[str], limit: int
) -> dict[str, Part]:
    """Stream a ``multipart/form-data`` body's file parts named in ``allowed`` to temp files.

    Other parts are read and dropped. The caller owns (and must delete) the returned temp
    files. 415 for another content type, 413 past ``limit`` bytes, 400 for a malformed body.
    """
    ctype, options = parse_options_header(request.headers.get("content-type", ""))
    boundary = options.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE, detail="expected multipart/form-data"
        )
    _check_declared_length(request, limit + 64 * 1024)
    state = _State()

    def on_part_begin() -> None:
        state.headers = {}
        state.current = None

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state.header_field += data[start:end]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state.header_value += data[start:end]

    def on_header_end() -> None:
        state.headers[state.header_field.decode("latin-1").lower()] = state.header_value
        state.header_field = state.header_value = b""

    def on_headers_finished() -> None:
        _, disp = parse_options_header(state.headers.get("content-disposition", b""))
        name = disp.get(b"name", b"").decode("utf-8", "replace")
        if name not in allowed:
            return
        if name in state.parts:
            raise ValueError(f"field {name!r} given twice")
        filename = disp.get(b"filename", b"").decode("utf-8", "replace")
        suffix = safe_suffix(filename)
        part = Part(name, filename, store.temp_path(suffix))
        part.content_type = state.headers.get("content-type", b"").decode("latin-1")
        state.parts[name] = state.current = part
        state.handle = open(part.path, "wb")  # noqa: SIM115 - closed in on_part_end/cleanup

    def on_part_data(data: bytes, start: int, end: int) -> None:
        n = end - start
        state.total += n
        if state.total > limit:
            raise _TooLarge
        if state.current is not None:
            state.handle.write(data[start:end])
            state.current.size += n

    def on_part_end() -> None:
        if state.handle is not None:
            state.handle.close()
            state.handle = None

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
        },
    )
    try:
        async for chunk in request.stream():
            parser.write(chunk)
        parser.finalize()
    except _TooLarge:
        _cleanup(state)
        raise too_large(limit) from None
    except Exception as exc:  # python-multipart raises several types on malformed input
        _cleanup(state)
        raise HTTPException(400, detail=f"malformed multipart body: {exc}") from None
    if state.handle is not None:  # body ended inside a part
        _cleanup(state)
        raise HTTPException(400, detail="malformed multipart body: truncated")
    return state.parts


def _cleanup(state: _State) -> None:
    if state.handle is not None:
        state.handle.close()
        state.handle = None
    remove_parts(state.parts)


def remove_parts(parts: dict[str, Part]) -> None:
    for part in parts.values():
        part.path.unlink(missing_ok=True)


def safe_suffix(filename: str) -> str:
    """The file's extension, lower-case, only if it is short and alphanumeric (the suffix
    chooses the mesh reader, and must never carry a path separator into the store)."""
    suffix = PurePosixPath(filename.replace("\\", "/")).suffix.lower()
    if 1 < len(suffix) <= 6 and suffix[1:].isalnum():
        return suffix
    return ""


async def read_body(request: Request, limit: int) -> bytes:
    """The raw body, refused with 413 as soon as it passes ``limit`` bytes."""
    _check_declared_length(request, limit)
    chunks: list[bytes] = []
    total = 0
    async for chunk in request.stream():
        total += len(chunk)
        if total > limit:
            raise too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)


class ArchiveError(ValueError):
    """An archive we refuse: not a zip, unsafe member names, links, or too big unpacked."""

    def __init__(self, message: str, too_big: bool = False) -> None:
        super().__init__(message)
        self.too_big = too_big


def extract_zip(archive: Path, dest: Path, max_bytes: int, max_members: int) -> tuple[int, int]:
    """Extract a zip safely; returns (files, bytes).

    Defends against zip bombs (the declared sizes are checked first, then the bytes actually
    inflated are counted, since headers can lie), path traversal (absolute names, ``..``),
    and links. Leaves ``dest`` removed on failure.
    """
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise ArchiveError(f"not a zip archive: {exc}") from None
    try:
        with zf:
            members = zf.infolist()
            if len(members) > max_members:
                raise ArchiveError(f"archive has {len(members)} members (limit {max_members})")
            if sum(m.file_size for m in members) > max_bytes:
                raise ArchiveError(f"archive unpacks to more than {max_bytes} bytes", True)
            total = files = 0
            for member in members:
                target = _member_target(dest, member)
                if member.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(member) as src, open(target, "wb") as out:
                    while chunk := src.read(1 << 20):
                        total += len(chunk)
                        if total > max_bytes:
                            raise ArchiveError(
                                f"archive unpacks to more than {max_bytes} bytes", True
                            )
                        out.write(chunk)
                files += 1
            return files, total
    except ArchiveError:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    except (  # zlib.error: a corrupt deflate stream (it derives from none of the others)
        zipfile.BadZipFile,
        zlib.error,
        OSError,
        RuntimeError,
        EOFError,
        NotImplementedError,
        ValueError,
    ) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise ArchiveError(f"corrupt zip archive: {exc}") from None


def _member_target(dest: Path, member: zipfile.ZipInfo) -> Path:
    name = member.filename.replace("\\", "/")
    parts = PurePosixPath(name).parts
    if not name or name.startswith("/") or ".." in parts or ":" in name:
        raise ArchiveError(f"unsafe member name {member.filename!r}")
    mode = member.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise ArchiveError(f"links are not allowed in archives ({member.filename!r})")
    target = (dest / os.path.join(*parts)).resolve()
    if not target.is_relative_to(dest.resolve()):
        raise ArchiveError(f"unsafe member name {member.filename!r}")
    return target
