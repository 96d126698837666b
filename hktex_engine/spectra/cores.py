"""How many worker processes a spectra computation gets: the cores no one else is using now.

Kept apart from the solver and the grid because it reads the machine, not the mesh, and the
command line samples it before the heavy imports (so it imports nothing but the standard
library).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class CpuSample:
    """The machine's CPU counters and this process's CPU time at one instant."""

    total: int  # all jiffies over all cores (/proc/stat)
    idle: int  # idle + iowait jiffies
    own_s: float  # this process's CPU seconds
    wall_s: float  # time.monotonic()


def cpu_sample() -> CpuSample | None:
    """Now's counters, or None where there is no ``/proc/stat``."""
    try:
        with open("/proc/stat") as fh:
            fields = [int(x) for x in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return CpuSample(sum(fields), idle, time.process_time(), time.monotonic())


def _busy_cores(window_s: float = 0.25, since: CpuSample | None = None) -> float | None:
    """Cores other processes keep busy: the machine's non-idle share of CPU time since
    ``since`` (or over a fresh ``window_s``), times the core count, less this process's own
    CPU time over the same window (None where there is no ``/proc/stat``).

    Why not the 1-minute load average alone: it lags by a minute, so a command started
    right after other work (a benchmark's previous step, a finished fit) saw a busy
    machine that was idle by then and ran one worker instead of two. Why ``since``: the
    command takes its first sample before it loads the mesh, so the window is time it
    spends anyway (a quarter second of sleep was ~5 % of ``hktex spectra`` on a 7k-vertex
    mesh); its own work in that window is subtracted, so it does not count itself.
    """
    a = since or cpu_sample()
    if a is None:
        return None
    remaining = window_s - (time.monotonic() - a.wall_s)
    if remaining > 0:
        time.sleep(remaining)
    b = cpu_sample()
    if b is None or b.total <= a.total:
        return None
    cores = os.cpu_count() or 1
    busy = (1.0 - (b.idle - a.idle) / (b.total - a.total)) * cores
    own = (b.own_s - a.own_s) / max(b.wall_s - a.wall_s, 1e-9)
    return max(0.0, busy - own)


def auto_workers(nodes: int | None = None, since: CpuSample | None = None) -> int:
    """Worker processes for independent node solves: the cores this process may use that
    are not busy now (affinity count minus the cores other processes kept busy over the
    last quarter second or since ``since``, or minus the 1-minute load average where that
    cannot be read), rounded, at least 1, at most ``nodes``. On an idle 2-core machine that
    is 2; with a fit running, 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    busy = _busy_cores(since=since)
    if busy is None:
        try:
            busy = os.getloadavg()[0]
        except OSError:  # pragma: no cover
            busy = 0.0
    free = max(1, min(cores, int(round(cores - busy))))
    return free if nodes is None else max(1, min(free, nodes))
