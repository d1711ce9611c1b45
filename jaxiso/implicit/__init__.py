"""Arbitrary implicit surfaces (seed ch. 6): scenes, kernels and the surface catalogue."""

from . import surfaces
from . import csg
from ._scene import ImplicitSurface

__all__ = ["surfaces", "ImplicitSurface", "csg"]
