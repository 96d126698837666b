"""Geometry: a mesh file in, a validated and normalised surface out, with what works on it.

Takes OBJ/PLY/OFF/glTF files or arrays; gives ``Mesh`` (merged, validated, normalised,
content-hashed), its discrete operators (cotangent, mass, ALBO), surface sampling and texture
lookup, and the exponential map with parallel transport that moves kernels on the surface.

Every name loads on first use (PEP 562), so a submodule costs only its own imports: mesh
validation (the service's upload check, a fresh process per upload) needs no torch, and a
query, which samples but never loads a mesh, needs no scipy or trimesh (~0.15 s of a one-off
``hktex query``).
"""

from importlib import import_module
from typing import Any

#: Public name -> the submodule that defines it.
_EXPORTS = {
    "Mesh": "mesh",
    "load_mesh": "mesh",
    "load_texture": "mesh",
    "mesh_from_arrays": "mesh",
    "albo_stiffness": "operators",
    "cotangent_stiffness": "operators",
    "lumped_mass": "operators",
    "reference_tangent_field": "operators",
    "closest_surface_point": "sampling",
    "farthest_point_sampling": "sampling",
    "sample_surface": "sampling",
    "texture_lookup": "sampling",
    "SurfaceTracer": "geodesics",
    "TraceResult": "geodesics",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value
