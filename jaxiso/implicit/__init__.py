"""Arbitrary implicit surfaces (seed ch. 6): scenes, kernels and the surface catalogue."""

from . import csg, surfaces
from ._grid import SignGrid
from ._memo import clear_caches
from ._scene import ImplicitSurface
from .mlp import MLP, load_mlp
from .vm import VMProgram, load_vm

__all__ = ["surfaces", "ImplicitSurface", "csg", "load_vm", "VMProgram", "load_mlp", "MLP",
           "SignGrid", "clear_caches"]
