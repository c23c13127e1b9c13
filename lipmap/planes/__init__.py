"""Planar primitives: container, initialization from depth, differentiable renderer, optimization."""
from .primitives import MAX_HITS, R_MAX, R_MIN, Planes
from .render import RenderOutput, lambda_schedule, rasterize_planes, render_planes, render_view
from .io import export_planes_ply, load_planes, save_planes

__all__ = [
    "MAX_HITS",
    "R_MAX",
    "R_MIN",
    "Planes",
    "RenderOutput",
    "lambda_schedule",
    "rasterize_planes",
    "render_planes",
    "render_view",
    "export_planes_ply",
    "load_planes",
    "save_planes",
]
