"""Render and export: a kernel set in, pictures and portable assets out.

Takes ``Spectra`` and a ``KernelSet``; gives Mitsuba 3 renders with the kernel albedo as a
differentiable texture (``dr.wrap``), the UV-textured scene for comparison, and bakes to a UV
texture, GLB, OBJ+MTL or vertex colours.
"""

from hktex_engine.render.bake import Bake, bake_texture, vertex_colors, write_glb, write_obj
from hktex_engine.render.mitsuba import (
    Camera,
    Lighting,
    RenderScene,
    RenderSettings,
    orbit_cameras,
    render_kernelset,
    render_png,
    render_uv,
)

__all__ = [
    "Bake",
    "Camera",
    "Lighting",
    "RenderScene",
    "RenderSettings",
    "bake_texture",
    "orbit_cameras",
    "render_kernelset",
    "render_png",
    "render_uv",
    "vertex_colors",
    "write_glb",
    "write_obj",
]
