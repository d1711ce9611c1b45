"""Render layer: cameras, the execution plan, `intersect`, shading and images."""

from .._camera import Camera
from .._core import Hits, Plan, Rays, Scene
from ._distributed import intersect, process_mesh, spans_processes, to_global, to_host
from ._image import Image, save_png
from ._plan import (
    from_tiles,
    from_zorder,
    morton_order,
    plan_for,
    to_tiles,
    to_zorder,
)
from ._render import Light, Shading, render

__all__ = ["Camera", "Rays", "Hits", "Plan", "Scene", "plan_for", "intersect", "render",
           "Light", "Shading", "Image", "save_png", "to_tiles", "from_tiles",
           "morton_order", "to_zorder", "from_zorder", "process_mesh", "spans_processes",
           "to_global", "to_host"]
