"""Tet meshes split by a spatial partition, one part per device (docs/distributed.md,
"Split the data"; the tet analog of `jaxiso.volume.brick_volume`).

Each tet goes to exactly one part: the cell of a grid (gx, gy, gz) of centroid
quantiles that holds its centroid. A tet's field is its own (linear in its four
vertices), so a part needs no overlap with its neighbours: the nearest hit over all
parts is the nearest hit over all tets, which the collective minimum of `t`
(`jaxiso._split.nearest_hits`) finds. Each part is a `TetIsosurface` over its own tets
and the vertices they use, with its own BVH, stacked over a one-axis mesh (part k on
device k) by `jaxiso._split.stack_parts`. The mesh itself is read whole by every
process (the partition is computed from it, the same in every process); what each
device holds is one part.

Two details keep a part's hits those of the whole mesh: each part carries one vertex
that no tet uses, with the whole mesh's largest |value| per time step (the traversal's
snapping distance is a fraction of the largest |value| it sees), and padded BVH rows
(parts have different node counts) are empty boxes whose escape pointers end the walk.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from .._core import pytree_dataclass, static_field
from .._split import SplitScene, local_parts, stack_parts, zero_pad
from ._mesh import TetMesh
from ._scene import TetIsosurface

__all__ = ["SplitTets", "split_tets", "tet_partition"]


def tet_partition(points, tets, grid) -> np.ndarray:
    """int [T] part index (C order over `grid`) of each tet: along each axis its
    centroid's slab between the centroids' quantiles k / g (so parts hold about equally
    many tets along each axis)."""
    grid = tuple(int(g) for g in grid)
    centroids = np.asarray(points, np.float64)[np.asarray(tets)].mean(axis=1)
    index = np.zeros(len(centroids), np.int64)
    for a, g in enumerate(grid):
        cuts = np.quantile(centroids[:, a], np.arange(1, g) / g) if g > 1 else []
        index = index * g + np.searchsorted(cuts, centroids[:, a], side="right")
    return index


def _part_mesh(mesh: TetMesh, mask: np.ndarray, scale: np.ndarray) -> TetMesh:
    """The tets `mask` of `mesh` over the vertices they use, plus one unused vertex whose
    values are `scale` [S] (the whole mesh's largest |value| per step)."""
    tets = np.asarray(mesh.tets)[mask]
    used, local = np.unique(tets, return_inverse=True)
    points = np.asarray(mesh.points)[used]
    values = np.asarray(mesh.values)[:, used]
    points = np.concatenate([points, points[:1]])
    values = np.concatenate([values, scale[:, None].astype(values.dtype)], axis=1)
    return TetMesh(points, local.reshape(tets.shape).astype(np.int32), values)


def _pad_tet_part(path, leaf: np.ndarray, shape) -> np.ndarray:
    """Pads a part's leaf to `shape`: BVH rows as empty boxes that escape to the end
    (node count `shape[0]`), everything else with zeros (nothing points at it)."""
    key = jax.tree_util.keystr(path)
    if leaf.ndim == 0:
        return leaf
    extra = shape[0] - leaf.shape[0]
    if key.endswith("bvh.bounds") and extra:
        row = np.array([np.inf] * 4 + [-np.inf] * 4, leaf.dtype)
        return np.concatenate([leaf, np.broadcast_to(row, (extra,) + leaf.shape[1:])])
    if key.endswith("bvh.links"):
        n = shape[0]
        row = np.array([0, 0, 0, n] + [n] * 8, leaf.dtype)
        return np.concatenate([leaf, np.broadcast_to(row, (extra,) + leaf.shape[1:])])
    return zero_pad(path, leaf, shape)


def split_tets(mesh: TetMesh, isovalues, device_mesh: Mesh, *, grid=None, axis: int = 0,
               bvh: str = "bih", leaf_size: int = 8, clip_box=None, time_step: int = 0,
               max_steps=None) -> SplitTets:
    """A `SplitTets` of `mesh`: its tets partitioned in space, one part per device of
    `device_mesh` (a one-axis Mesh, possibly over several processes), each part a
    `TetIsosurface` with its own BVH.

    grid: parts per axis (gx, gy, gz), gx * gy * gz == the device count; part k (C order)
      goes to device k. None: all parts along `axis`.
    isovalues, bvh, leaf_size, clip_box, time_step, max_steps: as `TetIsosurface`
    (flat normals only: smooth ones average gradients across the partition's seams).
    """
    if not isinstance(mesh, TetMesh):
        raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
    n_dev = int(device_mesh.devices.size)
    mine = local_parts(device_mesh)
    if grid is None:
        if not 0 <= axis < 3:
            raise ValueError(f"axis must be in 0..2, got {axis}")
        grid = tuple(n_dev if a == axis else 1 for a in range(3))
    grid = tuple(int(g) for g in grid)
    if len(grid) != 3 or min(grid) < 1 or math.prod(grid) != n_dev:
        raise ValueError(f"grid {grid} must be 3 positive counts with product {n_dev} "
                         f"(the mesh's devices)")
    part = tet_partition(mesh.points, mesh.tets, grid)
    counts = np.bincount(part, minlength=n_dev)
    if np.any(counts == 0):
        raise ValueError(f"grid {grid} leaves parts {np.flatnonzero(counts == 0).tolist()} "
                         f"without tets ({mesh.n_tets} tets)")
    scale = np.max(np.abs(np.asarray(mesh.values, np.float32)), axis=1)
    scenes = []
    for k in mine:
        scene = TetIsosurface(_part_mesh(mesh, part == k, scale), isovalues, bvh=bvh,
                              leaf_size=leaf_size, clip_box=clip_box, time_step=time_step,
                              max_steps=max_steps)
        # refits (with_time_step) are not offered on parts: their level order is dropped
        # so that all parts share one treedef
        tree = dataclasses.replace(scene.bvh, level_sizes=())
        object.__setattr__(scene, "bvh", tree)
        scenes.append(scene)
    used = np.asarray(mesh.points)[np.unique(np.asarray(mesh.tets))]
    lo, hi = used.min(axis=0).astype(np.float32), used.max(axis=0).astype(np.float32)
    offset = np.float32(1e-5 * np.linalg.norm(hi - lo))
    if clip_box is not None:
        lo = np.maximum(lo, np.broadcast_to(np.asarray(clip_box[0], np.float32), (3,)))
        hi = np.minimum(hi, np.broadcast_to(np.asarray(clip_box[1], np.float32), (3,)))
    return SplitTets(parts=stack_parts(scenes, device_mesh, pad=_pad_tet_part),
                     box_lo=jnp.asarray(lo), box_hi=jnp.asarray(hi),
                     offset=jnp.asarray(offset), mesh=device_mesh, grid=grid)


@pytree_dataclass
class SplitTets(SplitScene):
    """A tet-mesh isosurface split in space, one part per device of `mesh` (build with
    `split_tets`); a scene (`jaxiso.Scene`) for `intersect` and `render`.

    Attributes (beyond `SplitScene`'s parts, box_lo, box_hi, offset, mesh):
      grid: parts per axis (static).
    `parts` is a `TetIsosurface` whose every array has a leading part axis.
    """

    grid: tuple = static_field((1, 1, 1))

    def _validate(self):
        if not isinstance(self.parts, TetIsosurface):
            raise TypeError("parts must be a stacked TetIsosurface (use split_tets)")
        if self.parts.normals != "flat":
            raise ValueError("a SplitTets uses flat normals (smooth ones average "
                             "gradients across the partition's seams)")
