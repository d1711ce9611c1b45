"""Isosurfaces of tetrahedral meshes (seed ch. 5): the mesh container, the implicit BVH
with 4D bounds, marching-tets isopolygons, and the `TetIsosurface` scene."""

from . import data
from ._bvh import BVH, build_bvh, bvh_stats, memory_report, refit, refit_jax
from ._mesh import TetMesh, from_meshio, from_pyvista, tet_mesh
from ._scene import TetIsosurface

__all__ = ["TetMesh", "tet_mesh", "from_meshio", "from_pyvista", "BVH", "build_bvh",
           "refit", "refit_jax", "bvh_stats", "memory_report", "TetIsosurface", "data"]
