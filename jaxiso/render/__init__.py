"""Render layer: rays, cameras, packets, the scene protocol, shading and images."""

from ._camera import Camera, Rays
from ._image import Image, save_png
from ._render import Light, Shading, render
from ._scene import Hits, from_tiles, intersect, to_tiles

__all__ = ["Camera", "Rays", "Hits", "intersect", "render", "Light", "Shading", "Image",
           "save_png", "to_tiles", "from_tiles"]
