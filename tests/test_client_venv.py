"""The light client installs into a clean virtual environment and never pulls in the engine.

Asset tools install ``hktex-client`` next to their own stacks; if importing it dragged in
torch, scipy or mitsuba (directly or through a stray import of the engine), that promise is
broken. The check installs the package the way a user would (pip resolving its declared
dependencies from the configured index) into a venv that has nothing else.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

CLIENT_DIR = Path(__file__).resolve().parents[1] / "client"

PROBE = r"""
import importlib, sys
import hktex_client
from hktex_client import AsyncClient, Client, NotFound, from_npy_bytes, to_npy_bytes
import numpy as np
heavy = [m for m in ("torch", "scipy", "mitsuba", "drjit", "hktex_engine", "hktex_server",
                     "fastapi") if m in sys.modules]
assert not heavy, f"imported heavy modules: {heavy}"
for name in ("torch", "scipy", "mitsuba", "hktex_engine"):
    try:
        importlib.import_module(name)
    except ImportError:
        pass
    else:
        raise AssertionError(f"{name} is importable in the client's clean venv")
a = np.arange(12, dtype=np.float32).reshape(4, 3)
assert np.array_equal(from_npy_bytes(to_npy_bytes(a)), a)
Client("http://127.0.0.1:9").close()
print("client-venv-ok", hktex_client.__version__)
"""


def test_client_installs_and_imports_without_heavy_dependencies(tmp_path: Path) -> None:
    src = tmp_path / "client-src"
    # A copy, so the build never writes into the shared source tree.
    shutil.copytree(
        CLIENT_DIR, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__")
    )
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False, clear=True).create(env_dir)
    py = env_dir / "bin" / "python"
    # The outer pip installs into the new venv (`pip --python`): no ensurepip bootstrap,
    # and the dependencies come from the configured index exactly as a user's would.
    install = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(py),
            "install",
            "-q",
            "--disable-pip-version-check",
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if install.returncode != 0 and "No matching distribution" in install.stderr:
        pytest.skip(f"no package index reachable: {install.stderr.strip()[-300:]}")
    assert install.returncode == 0, install.stderr[-2000:]
    # Run from an empty directory: `python -c` puts the cwd on sys.path, and the repository
    # root would make the engine importable by accident.
    run = subprocess.run(
        [str(py), "-c", PROBE], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "client-venv-ok" in run.stdout
