"""Fitting: spectra and a target (a UV texture, or views) in, a fitted kernel set out.

Takes ``Spectra`` with a textured ``Mesh`` or a ``Views`` dataset and ``FitParams``; gives a
``FitResult``. Holds the optimisers (Adam with projection, Riemannian SGD through the exp
map), density control, the shared loop (checkpoints, resume, cancel) and the two objectives.
"""

from hktex_engine.fitting.density import DensityController, DensityRules
from hktex_engine.fitting.loop import LoopResult, Objective, run_fit
from hktex_engine.fitting.multiview import MultiViewOptions, fit_multiview
from hktex_engine.fitting.optimise import KernelOptimiser
from hktex_engine.fitting.uv import FitResult, fit_uv
from hktex_engine.fitting.views import Views, load_views, render_reference_views, write_views

__all__ = [
    "DensityController",
    "DensityRules",
    "FitResult",
    "KernelOptimiser",
    "LoopResult",
    "MultiViewOptions",
    "Objective",
    "Views",
    "fit_multiview",
    "fit_uv",
    "load_views",
    "render_reference_views",
    "run_fit",
    "write_views",
]
