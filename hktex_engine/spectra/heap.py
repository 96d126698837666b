"""Letting a process that exists for one spectra grid keep the memory it frees, for reuse.

A node solve allocates and frees the same few arrays again and again (the Krylov basis, the
blocks of right-hand sides, SuperLU's factor). glibc's allocator hands blocks above its
mmap threshold back to the kernel when they are freed and trims the top of its heap, so
every node touched fresh pages: ~3,500-4,000 page faults a node on a 2,930-vertex mesh, 8 ms
of system time of a 92 ms solve. With freed memory kept (the thresholds raised) a node took
0.0876 s instead of 0.0914-0.0933, with ~30 faults (one core, K = 128, 12 nodes, measured
2026-12-07 through the same settings as glibc tunables).

Only for processes that end with the grid (the ``hktex spectra`` command, a grid's worker
processes): a long-lived service process keeps glibc's adaptive defaults, because a memory
kept here is not returned to the system before the process ends. No library exposes
``mallopt``; ctypes reaches it where the C library has it (glibc), and elsewhere nothing
changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

#: Blocks up to this size come from the heap instead of their own mapping: glibc's largest
#: allowed threshold on 64-bit systems (a Krylov basis of 2,930 x 384 doubles is 9 MB).
MMAP_THRESHOLD = 32 << 20
#: Free memory at the top of the heap kept rather than trimmed.
TRIM_THRESHOLD = 1 << 30


def keep_freed_memory() -> bool:
    """Raise this process's allocator thresholds so freed blocks are reused, not unmapped.
    Returns whether the C library took both settings."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - a C library without mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    mmap_ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
    trim_ok = mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    return mmap_ok and trim_ok
