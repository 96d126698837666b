"""Content-addressed blob store under the data dir.

A blob's name is the SHA-256 of its bytes, so equal uploads share one file and a half-written
file can never be mistaken for a finished one: everything is written to ``tmp/`` first and
published with an atomic ``os.replace`` (directories: ``os.rename``, manifest written last by
whoever produced them). Paths stored in the database are relative to the data dir, so a data
dir can move (or be mounted at another path on another host).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import uuid
from pathlib import Path

CHUNK = 1 << 20


class BlobStore:
    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.tmp = self.root / "tmp"
        self.tmp.mkdir(parents=True, exist_ok=True)

    def temp_path(self, suffix: str = "") -> Path:
        """A fresh path on the same filesystem as the store (so the final rename is atomic)."""
        return self.tmp / f"{uuid.uuid4().hex}{suffix}"

    def temp_dir(self) -> Path:
        return Path(tempfile.mkdtemp(dir=self.tmp))

    def abs(self, rel: str) -> Path:
        return self.root / rel

    def rel(self, path: Path) -> str:
        return str(Path(path).resolve().relative_to(self.root))

    def publish_file(self, tmp_file: Path, kind: str, suffix: str = "") -> tuple[str, str, int]:
        """Move a finished temp file into ``kind/ab/<sha256><suffix>``; returns (rel, sha, bytes).

        If the blob exists already (same content) the temp file is dropped.
        """
        digest = file_sha256(tmp_file)
        size = tmp_file.stat().st_size
        final = self.root / kind / digest[:2] / f"{digest}{suffix}"
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():
            tmp_file.unlink(missing_ok=True)
        else:
            os.replace(tmp_file, final)
        return self.rel(final), digest, size

    def publish_dir(self, tmp_dir: Path, kind: str, key: str) -> str:
        """Rename a finished temp directory to ``kind/<key>``; an existing one wins."""
        final = self.root / kind / key
        final.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(tmp_dir, final)
        except OSError:
            if not final.is_dir():
                raise
            shutil.rmtree(tmp_dir, ignore_errors=True)
        return self.rel(final)

    def delete(self, rel: str | None) -> None:
        if not rel:
            return
        path = self.abs(rel)
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


def dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())
