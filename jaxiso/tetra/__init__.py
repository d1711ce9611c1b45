"""Isosurfaces of tetrahedral meshes (seed ch. 5): the mesh container, the implicit BVH
with 4D bounds, marching-tets isopolygons, and the `TetIsosurface` scene.

`traverse` is the BVH traversal kernel itself (what `TetIsosurface.intersect_packet`
runs on one packet), public for the work counters it returns beside the hits (nodes
visited and leaves intersected per ray: benchmarks/bench_tetra.py's Table 5.4 analog);
rendering needs only `TetIsosurface` with `jaxiso.intersect` / `jaxiso.render`.
"""

from . import data
from ._bvh import BVH, build_bvh, bvh_stats, memory_report, refit, refit_jax
from ._mesh import TetMesh, from_meshio, from_pyvista, tet_mesh
from ._scene import TetIsosurface
from ._split import SplitTets, split_tets
from ._traverse import traverse

__all__ = ["TetMesh", "tet_mesh", "from_meshio", "from_pyvista", "BVH", "build_bvh",
           "refit", "refit_jax", "bvh_stats", "memory_report", "TetIsosurface", "traverse",
           "data", "SplitTets", "split_tets"]
