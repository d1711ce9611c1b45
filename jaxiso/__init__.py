"""jaxiso: ray tracing implicit surfaces in JAX (after Knoll 2009).

Layers, bottom up: the core (`Rays`, `Hits`, `Plan`, the `Scene` protocol), inclusion
arithmetic (`Interval`, `Affine`, `extend`, `register_rule`), scenes (`ImplicitSurface`,
`CSG`, `VolumeIsosurface` over `OctreeVolume` / `MacrocellGrid`, `TetIsosurface` over
`TetMesh`), and the render layer (`Camera`, `plan_for`, `intersect`, `render`,
`save_png`). `surfaces` is the catalogue of the seed's test surfaces; `distributed` joins
a multi-process run (`initialize`, `process_mesh`); `enable_cache` keeps compiled programs
on disk for later processes.
"""

from . import arith, distributed
from ._cache import enable_cache
from ._core import Hits, Plan, Rays, Scene
from .arith import Affine, Interval, aa, extend, ia, interval, register_rule
from .implicit import ImplicitSurface, clear_caches, surfaces
from .implicit.csg import CSG
from .render import (
    Camera,
    Image,
    Light,
    Shading,
    from_tiles,
    intersect,
    plan_for,
    render,
    save_png,
    to_tiles,
)
from .tetra import TetIsosurface, TetMesh, tet_mesh
from .volume import MacrocellGrid, OctreeVolume, VolumeIsosurface, VolumeSequence, lod_for

__version__ = "0.3.0"

__all__ = ["Interval", "interval", "Affine", "extend", "register_rule", "ia", "aa",
           "arith", "distributed", "surfaces", "ImplicitSurface", "CSG", "Camera", "Rays",
           "Hits", "Image",
           "Scene", "Plan", "plan_for",
           "Light", "Shading", "intersect", "render", "save_png", "to_tiles",
           "from_tiles", "OctreeVolume", "VolumeIsosurface", "MacrocellGrid",
           "VolumeSequence", "lod_for", "TetMesh", "tet_mesh", "TetIsosurface", "enable_cache",
           "clear_caches",
           "__version__"]
