"""Arbitrary implicit surfaces (seed ch. 6): scenes, kernels and the surface catalogue."""

from . import csg, surfaces
from ._scene import ImplicitSurface

__all__ = ["surfaces", "ImplicitSurface", "csg"]
