"""HKTex engine: the science of Heat Kernel Textures, callable without the server.

Modules are one concept each (see ARCHITECTURE.md in docs/). The public entry points are
re-exported lazily by their modules; import what you need, e.g.
``from hktex_engine.geometry.mesh import load_mesh``.
"""

__version__ = "0.1.0"
