"""Data-distributed volumes: one brick of the voxels per device, nearest hit by a
collective minimum of `t` (DESIGN.md "Past one machine"; OSPRay's MPI module is the
anchor: every rank renders its own brick, first hits composite by depth).

A volume of n voxel planes along `axis` is cut into B bricks that share one voxel plane
with each neighbour, so every cell (between two planes) lies in exactly one brick and a
seam's cells need nothing from the next brick. Each brick is its own `VolumeIsosurface`
(its own min/max octree, origin moved to the brick's first plane, clip box cut to the
brick's cells); the bricks' arrays are stacked along a leading axis [B, ...] that is
sharded over a one-axis mesh, one brick per device, so the whole volume never exists on
one device, and a process builds only the bricks of its own devices.

`BrickedVolume.intersect_packet` traces every ray through every brick (each device its
own) and keeps, per ray, the hit of smallest `t` across the mesh: `nearest_hits`, a
`pmin` of t and of the winning brick's index, then one `psum` that carries the winner's
hit, normal, surface and steps. Scenes never import `render`: the mesh comes from the
caller.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._core import LANES, Hits, Plan, SceneFields, pytree_dataclass, static_field
from ._octree import OctreeVolume
from ._scene import VolumeIsosurface

__all__ = ["BrickedVolume", "brick_bounds", "brick_volume", "nearest_hits"]

# bricks trace on persistent lanes from this many rays on the CPU (one volume: 2^16):
# their packets each wait for a collective (`BrickedVolume.preferred_plan`)
BRICK_LANES_FROM = 2**14


def brick_bounds(n: int, bricks: int) -> list[tuple[int, int]]:
    """Voxel planes [start, stop) of `bricks` bricks over n planes along one axis: each
    brick holds ceil((n - 1) / bricks) cells, so neighbours share one plane (brick k's
    last plane is brick k + 1's first) and all bricks have the same plane count m + 1
    (the last one may reach past n; `brick_volume` repeats the last plane there and clips
    it off). Raises ValueError when a brick would have no cell."""
    if bricks < 1:
        raise ValueError(f"bricks must be >= 1, got {bricks}")
    cells = n - 1
    m = -(-cells // bricks)
    if cells < bricks or m * (bricks - 1) >= cells:
        raise ValueError(f"{n} voxel planes ({cells} cells) cannot be cut into {bricks} "
                         f"bricks of at least one cell each")
    return [(k * m, k * m + m + 1) for k in range(bricks)]


def _read_brick(data, axis: int, start: int, stop: int) -> np.ndarray:
    """Planes [start, stop) of `data` along axis (any array-like that slices, e.g. a
    np.memmap or an h5py dataset: only this brick is read); planes past the end repeat
    the last one (`brick_volume` clips them off)."""
    n = data.shape[axis]
    index = [slice(None)] * 3
    index[axis] = slice(start, min(stop, n))
    brick = np.asarray(data[tuple(index)])
    short = stop - min(stop, n)
    if short:
        pad = [(0, 0)] * 3
        pad[axis] = (0, short)
        brick = np.pad(brick, pad, mode="edge")
    return brick


def _brick_scene(data, axis, bounds, n, isovalues, spacing, origin, clip_box, options,
                 build) -> VolumeIsosurface:
    """The `VolumeIsosurface` of one brick: its own octree, origin at its first plane,
    clip box = the user's box cut to the brick's real cells."""
    start, stop = bounds
    spacing = np.broadcast_to(np.asarray(spacing, np.float32), (3,))
    origin = np.broadcast_to(np.asarray(origin, np.float32), (3,)).copy()
    whole_hi = origin + (np.asarray(data.shape, np.float32) - 1) * spacing
    brick_origin = origin.copy()
    brick_origin[axis] = origin[axis] + start * spacing[axis]
    vol = OctreeVolume.from_array(_read_brick(data, axis, start, stop), spacing=spacing,
                                  origin=brick_origin, progress=False, **build)
    lo, hi = origin.copy(), whole_hi.copy()
    lo[axis] = brick_origin[axis]
    hi[axis] = origin[axis] + min(stop - 1, n - 1) * spacing[axis]
    if clip_box is not None:
        c_lo, c_hi = (np.broadcast_to(np.asarray(c, np.float32), (3,)) for c in clip_box)
        lo, hi = np.maximum(lo, c_lo), np.minimum(hi, c_hi)
    if np.any(lo > hi):  # the clip box misses this brick: a box past the whole volume
        lo = hi = whole_hi + spacing
    return VolumeIsosurface(vol, isovalues, clip_box=(lo, hi), **options)


def _padded(leaf: np.ndarray, shape) -> np.ndarray:
    """leaf zero-padded at the end of every axis to `shape` (extra octree records and caps
    are never reached: no record points at them)."""
    return np.pad(leaf, [(0, s - n) for n, s in zip(leaf.shape, shape)])


def _largest_shapes(leaves_per_brick, mesh: Mesh) -> list[tuple]:
    """Per leaf, the largest shape over all bricks of all processes (an all-gather of
    the few shape numbers through JAX's runtime when the mesh spans processes)."""
    local = np.array([[s for leaf in leaves for s in leaf.shape]
                      for leaves in leaves_per_brick], np.int64).max(axis=0)
    if any(d.process_index != jax.process_index() for d in mesh.devices.flat):
        from jax.experimental import multihost_utils

        local = np.asarray(multihost_utils.process_allgather(local)).reshape(
            -1, local.size).max(axis=0)
    shapes, i = [], 0
    for leaf in leaves_per_brick[0]:
        shapes.append(tuple(int(s) for s in local[i:i + leaf.ndim]))
        i += leaf.ndim
    return shapes


def brick_volume(data, isovalues, mesh: Mesh, *, axis: int = 0, spacing=1.0, origin=0.0,
                 clip_box=None, variance=0.0, iso_range=None, **options) -> BrickedVolume:
    """A `BrickedVolume` of `data` [nx, ny, nz] cut along `axis`, one brick per device
    of `mesh` (a one-axis Mesh, possibly over several processes).

    data: any array-like with `.shape` that slices (numpy, np.memmap, h5py, zarr); each
      process reads only the planes of its own devices' bricks.
    isovalues, clip_box, options (method, traversal, normals, max_steps): as
      `VolumeIsosurface`; variance, iso_range: as `OctreeVolume.from_array`.
    The octrees are built on the host, one brick at a time. Level of detail is not
    supported here (each brick's coarse levels would need the neighbour's voxels).
    """
    if len(mesh.axis_names) != 1:
        raise ValueError(f"bricks go over a mesh with one axis, got {mesh.axis_names}")
    if not 0 <= axis < 3 or len(data.shape) != 3:
        raise ValueError(f"need 3-D data and axis in 0..2, got shape {data.shape}, "
                         f"axis {axis}")
    if options.get("lod") is not None:
        raise ValueError("level of detail is not supported on a BrickedVolume")
    devices = list(mesh.devices.flat)
    n = int(data.shape[axis])
    bounds = brick_bounds(n, len(devices))
    mine = [k for k, d in enumerate(devices) if d.process_index == jax.process_index()]
    build = dict(variance=variance, iso_range=iso_range)
    scenes = [_brick_scene(data, axis, bounds[k], n, isovalues, spacing, origin, clip_box,
                           options, build) for k in mine]
    flat = [jax.tree_util.tree_flatten(s) for s in scenes]
    treedef = flat[0][1]
    leaves = [[np.asarray(x) for x in f[0]] for f in flat]
    shapes = _largest_shapes(leaves, mesh)
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    stacked = []
    for j, shape in enumerate(shapes):
        parts = [jax.device_put(_padded(leaves[i][j], shape)[None], devices[k])
                 for i, k in enumerate(mine)]
        stacked.append(jax.make_array_from_single_device_arrays(
            (len(devices),) + shape, sharding, parts))
    bricks = jax.tree_util.tree_unflatten(treedef, stacked)
    spacing3 = np.broadcast_to(np.asarray(spacing, np.float32), (3,))
    origin3 = np.broadcast_to(np.asarray(origin, np.float32), (3,))
    lo = origin3
    hi = origin3 + (np.asarray(data.shape, np.float32) - 1) * spacing3
    if clip_box is not None:
        lo = np.maximum(lo, np.broadcast_to(np.asarray(clip_box[0], np.float32), (3,)))
        hi = np.minimum(hi, np.broadcast_to(np.asarray(clip_box[1], np.float32), (3,)))
    return BrickedVolume(bricks=bricks, box_lo=jnp.asarray(lo), box_hi=jnp.asarray(hi),
                         spacing=jnp.asarray(spacing3), mesh=mesh, axis=axis,
                         shape=tuple(int(s) for s in data.shape))


def nearest_hits(hits: Hits, axis_name: str) -> Hits:
    """Per ray, the hit of smallest `t` over the devices of mesh axis `axis_name` (call
    inside `shard_map`); ties go to the lowest device index. Every device returns the
    same Hits [P]: the winner's t, hit, normal, surface and steps."""
    t = jax.lax.pmin(hits.t, axis_name)
    me = jax.lax.axis_index(axis_name)
    owner = jax.lax.pmin(jnp.where(hits.t == t, me, jnp.iinfo(jnp.int32).max), axis_name)
    mine = owner == me

    def winner(x):
        keep = mine.reshape(mine.shape + (1,) * (x.ndim - mine.ndim))
        return jnp.where(keep, x, jnp.zeros((), x.dtype))

    hit, normal, surface, steps = jax.lax.psum(
        (winner(hits.hit.astype(jnp.int32)), winner(hits.normal), winner(hits.surface),
         winner(hits.steps)), axis_name)
    return Hits(t=t, hit=hit > 0, normal=normal, surface=surface, steps=steps)


@pytree_dataclass
class BrickedVolume(SceneFields):
    """A volume isosurface split into bricks, one per device of `mesh` (build with
    `brick_volume`); a scene (`jaxiso.Scene`) for `intersect` and `render`.

    Attributes:
      bricks: a `VolumeIsosurface` whose every array has a leading brick axis [B, ...],
        sharded over the mesh axis (brick k on device k).
      box_lo, box_hi: [3] the whole volume's drawn box (replicated).
      spacing: [3] voxel spacing.
      mesh: the one-axis mesh the bricks live on (static).
      axis: the axis the volume is cut along; shape: the whole volume's shape (static).

    Every device traces all rays through its own brick; `nearest_hits` composites them.
    `Hits.steps` is the winning brick's count. Render it with `devices=None` (the rays are
    not split: the data is). Normals are the trilinear patch's ("central" would read
    across a seam).
    """

    bricks: VolumeIsosurface
    box_lo: jax.Array
    box_hi: jax.Array
    spacing: jax.Array
    mesh: Mesh = static_field()
    axis: int = static_field(0)
    shape: tuple = static_field(())

    def _validate(self):
        if not isinstance(self.bricks, VolumeIsosurface):
            raise TypeError("bricks must be a stacked VolumeIsosurface (use brick_volume)")
        if self.bricks.normals == "central":
            raise ValueError("a BrickedVolume uses trilinear normals (central differences "
                             "would read voxels of the neighbouring brick)")

    @property
    def n_bricks(self) -> int:
        return int(self.mesh.devices.size)

    @property
    def lo(self):
        return self.box_lo

    @property
    def hi(self):
        return self.box_hi

    @property
    def offset_scale(self):
        """Secondary rays leave a surface by a thousandth of a voxel (as one volume)."""
        return 1e-3 * jnp.min(self.spacing)

    def coarser(self, factor) -> BrickedVolume:
        """No level of detail on bricks: shadow rays trace the same scene."""
        return self

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """32x32 packets (one collective per 1024 rays) up to 2^14 rays, and on the CPU
        4096 persistent lanes from there (one collective per trace).

        A packet's collective costs far more than its tracing. 2 local processes (gloo,
        one thread each, a loaded 2-core box): 32^2 pixels of a 33^3 volume in 2 bricks,
        frame 344 ms in 8x8 packets, 56 ms in 32x32, 30 ms on 1024 lanes (first call
        13 / 17 / 46 s; one process, whole volume: 12 ms); 128^2 of 96^3: 16x16 packets
        1720 ms, 32x32 868 ms, 4096 lanes 260 ms (first call 17 / 21 / 78 s; one process,
        whole volume: 244 ms). Other backends: packets (unmeasured)."""
        lanes = LANES if backend == "cpu" and n_rays >= BRICK_LANES_FROM else None
        return Plan(tile=32, lanes=lanes)

    def brick_nbytes(self) -> int:
        """Bytes of one brick's arrays (what each device holds of the volume)."""
        return int(sum(leaf.nbytes // leaf.shape[0]
                       for leaf in jax.tree_util.tree_leaves(self.bricks)))

    def with_isovalues(self, isovalues) -> BrickedVolume:
        """The same bricks at other isovalues (same count: no recompile)."""
        iso = np.atleast_1d(np.asarray(isovalues, np.float32))
        if iso.shape != tuple(self.bricks.isovalues.shape[1:]):
            raise ValueError(f"with_isovalues keeps the count {self.bricks.isovalues.shape[1]}"
                             f", got shape {iso.shape}")
        sharding = NamedSharding(self.mesh, PartitionSpec(self.mesh.axis_names[0]))
        stacked = np.broadcast_to(iso, (self.n_bricks,) + iso.shape)
        glob = jax.make_array_from_callback(stacked.shape, sharding, lambda i: stacked[i])
        bricks = copy.copy(self.bricks)
        object.__setattr__(bricks, "isovalues", glob)
        return self.replace(bricks=bricks)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of rays [P] (the scene protocol): every device traces all P rays
        through its own brick, then `nearest_hits` keeps the nearest per ray."""
        axis_name = self.mesh.axis_names[0]
        brick_spec = PartitionSpec(axis_name)

        def one_brick(bricks, rays, t_min, t_max):
            brick = jax.tree_util.tree_map(lambda a: a[0], bricks)
            hits = brick.intersect_packet(rays, t_min, t_max, lanes=lanes)
            return nearest_hits(hits, axis_name)

        specs = (jax.tree_util.tree_map(lambda _: brick_spec, self.bricks),
                 PartitionSpec(), PartitionSpec(), PartitionSpec())
        return jax.shard_map(one_brick, mesh=self.mesh, in_specs=specs,
                             out_specs=PartitionSpec(), check_vma=False)(
            self.bricks, rays, t_min, t_max)

