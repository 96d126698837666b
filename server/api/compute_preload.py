"""Imported by the forkserver (``validation.PRELOAD``): builds the engine's compiled query
code once there, so every compute worker forked from it starts with it ready.

Without this, each worker would import numba and load the compiled blend
(``hktex_engine.kernels.fused_blend``) at its start: ~1-2 s, and several seconds on a loaded
host, where a replacement for a killed worker is otherwise ready in milliseconds.
"""

from hktex_engine.kernels import fused_blend

fused_blend.warm()
