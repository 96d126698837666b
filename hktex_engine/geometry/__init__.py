"""Geometry: a mesh file in, a validated and normalised surface out, with what works on it.

Takes OBJ/PLY/OFF/glTF files or arrays; gives ``Mesh`` (merged, validated, normalised,
content-hashed), its discrete operators (cotangent, mass, ALBO), surface sampling and texture
lookup, and the exponential map with parallel transport that moves kernels on the surface.

Sampling and the exp map need torch; their names load on first use (PEP 562), so that mesh
validation (the service's upload check, a fresh process per upload) imports only numpy,
scipy and trimesh.
"""

from typing import Any

from hktex_engine.geometry.mesh import Mesh, load_mesh, load_texture, mesh_from_arrays
from hktex_engine.geometry.operators import (
    albo_stiffness,
    cotangent_stiffness,
    lumped_mass,
    reference_tangent_field,
)

_SAMPLING = (
    "closest_surface_point",
    "farthest_point_sampling",
    "sample_surface",
    "texture_lookup",
)
_GEODESICS = ("SurfaceTracer", "TraceResult")

__all__ = [
    "Mesh",
    "albo_stiffness",
    "cotangent_stiffness",
    "load_mesh",
    "load_texture",
    "lumped_mass",
    "mesh_from_arrays",
    "reference_tangent_field",
    *_SAMPLING,
    *_GEODESICS,
]


def __getattr__(name: str) -> Any:
    if name in _SAMPLING:
        from hktex_engine.geometry import sampling

        return getattr(sampling, name)
    if name in _GEODESICS:
        from hktex_engine.geometry import geodesics

        return getattr(geodesics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
