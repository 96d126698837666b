"""The machine a benchmark ran on, recorded the same way by every benchmark.

Imported by the scripts in this folder (run as ``python benchmarks/<name>.py``, so this folder
is on ``sys.path``). Timings on the shared machine are only comparable with the load and the
thread counts beside them, so those are part of the record.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path
from typing import Any


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _ram_gb() -> float | None:
    try:
        kib = Path("/proc/meminfo").read_text().splitlines()[0].split()[1]
    except (OSError, IndexError):
        return None
    return round(int(kib) / 2**20, 1)


def machine_info(**extra: Any) -> dict[str, Any]:
    """Platform, CPU, memory, versions, thread settings and the 1-minute load average now.

    torch's version, threads and CUDA device are recorded only when the benchmark has already
    imported torch (a numpy-only benchmark should not pay torch's import for its record).
    ``extra`` adds benchmark-specific entries (a note, the Mitsuba variant...)."""
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "cpu": _cpu_model(),
        "cpus": os.cpu_count(),
        "ram_gb": _ram_gb(),
        "python": platform.python_version(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default"),
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }
    if "numpy" in sys.modules:
        info["numpy"] = sys.modules["numpy"].__version__
    torch = sys.modules.get("torch")
    if torch is not None:
        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
        info["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    info.update(extra)
    return info


def machine_line(info: dict[str, Any]) -> str:
    """One human line for a results .md file."""
    parts = [f"{info['platform']}, {info['cpu']}, {info['cpus']} CPUs"]
    if info.get("ram_gb") is not None:
        parts.append(f"{info['ram_gb']} GB RAM")
    parts.append(f"Python {info['python']}")
    if "torch" in info:
        parts.append(
            f"torch {info['torch']} ({info['torch_threads']} threads), "
            f"CUDA: {info['cuda'] or 'none'}"
        )
    parts.append(f"BLAS threads {info['blas_threads']}")
    if info.get("load_average_1min") is not None:
        parts.append(f"1-min load average {info['load_average_1min']:.1f} when recorded")
    return ", ".join(parts)
