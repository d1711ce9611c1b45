"""jaxiso: ray tracing implicit surfaces in JAX (after Knoll 2009).

Layers: inclusion arithmetic (`Interval`, `Affine`, `extend`, `register_rule`), scenes
(`ImplicitSurface`, CSG), and the render layer (`Camera`, `Rays`, `Hits`, `intersect`,
`render`, `save_png`). `surfaces` is the catalogue of the seed's test surfaces.
Structured volumes (`OctreeVolume`, `VolumeIsosurface`, ...) and tetrahedral meshes
(`TetMesh`, `TetIsosurface`) implement the same scene protocol.
"""

from . import arith
from .arith import Affine, Interval, aa, extend, ia, interval, register_rule
from .implicit import ImplicitSurface, surfaces
from .render import (
    Camera,
    Hits,
    Image,
    Light,
    Rays,
    Shading,
    from_tiles,
    intersect,
    render,
    save_png,
    to_tiles,
)
from .tetra import TetIsosurface, TetMesh, tet_mesh
from .volume import MacrocellGrid, OctreeVolume, VolumeIsosurface, VolumeSequence, lod_for

__version__ = "0.3.0"

__all__ = ["Interval", "interval", "Affine", "extend", "register_rule", "ia", "aa",
           "arith", "surfaces", "ImplicitSurface", "Camera", "Rays", "Hits", "Image",
           "Light", "Shading", "intersect", "render", "save_png", "to_tiles",
           "from_tiles", "OctreeVolume", "VolumeIsosurface", "MacrocellGrid",
           "VolumeSequence", "lod_for", "TetMesh", "tet_mesh", "TetIsosurface", "__version__"]
