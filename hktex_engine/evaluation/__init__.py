"""Evaluation: how a texture is judged (EVALUATION.md) and what it is judged against.

Takes a mesh and colours at surface points; gives PSNR/SSIM and the surface protocol,
storage bytes, the paper's view protocol (rendered views), the baselines (vertex colours,
UV texture at scale, positional-encoding MLP), and small deterministic synthetic meshes for
tests and the demo.
"""

from hktex_engine.evaluation.baselines import MLPBaseline, UVTextureBaseline, VertexColorBaseline
from hktex_engine.evaluation.metrics import psnr, ssim, storage_bytes, surface_psnr, surface_samples
from hktex_engine.evaluation.paper_views import PaperViews, PaperViewSettings, paper_view_scores
from hktex_engine.evaluation.synthetic import (
    cylinder,
    grid_patch,
    icosphere,
    textured_demo,
    torus,
)

__all__ = [
    "MLPBaseline",
    "PaperViewSettings",
    "PaperViews",
    "UVTextureBaseline",
    "VertexColorBaseline",
    "cylinder",
    "grid_patch",
    "icosphere",
    "paper_view_scores",
    "psnr",
    "ssim",
    "storage_bytes",
    "surface_psnr",
    "surface_samples",
    "textured_demo",
    "torus",
]
