"""Data-distributed volumes: one brick of the voxels per device, nearest hit by a
collective minimum of `t` (docs/distributed.md, "Split the data"; OSPRay's MPI module is the
anchor: every rank renders its own brick, first hits composite by depth).

A volume of n voxel planes per axis is cut by a brick grid (gx, gy, gz) into
gx * gy * gz bricks; along each axis neighbouring bricks share one voxel plane, so every
cell (between two planes) lies in exactly one brick and a seam's cells need nothing from
the next brick. Each brick is its own `VolumeIsosurface` (its own min/max octree, origin
moved to the brick's first voxel, clip box cut to the brick's cells); the bricks are
stacked over a one-axis mesh by `jaxiso._split.stack_parts` (brick k, in C order over
the grid, on device k), so the whole volume never exists on one device, and a process
reads and builds only the bricks of its own devices: `data` may be a np.memmap, an h5py
or zarr dataset, or a `SampledField` that computes just the voxels asked for.

Tracing and compositing are `jaxiso._split.SplitScene`'s: every device traces all rays
through its own brick and `nearest_hits` keeps the nearest hit per ray (a `pmin` of t,
one `psum` carrying hit, normal, surface and steps).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from .._core import pytree_dataclass, static_field
from .._split import SPLIT_LANES_FROM, SplitScene, local_parts, nearest_hits, stack_parts
from ._octree import OctreeVolume
from ._scene import VolumeIsosurface

__all__ = ["BrickedVolume", "brick_bounds", "brick_grid", "brick_volume", "nearest_hits",
           "SampledField"]

# kept under its first name (bricks were the first split scene)
BRICK_LANES_FROM = SPLIT_LANES_FROM


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


def brick_grid(shape, grid) -> list[tuple[tuple[int, int], ...]]:
    """Per brick (C order over `grid`), its voxel ranges ((x0, x1), (y0, y1), (z0, z1)),
    each from `brick_bounds` along its axis (an axis cut into 1 brick keeps all planes)."""
    grid = _grid3(grid)
    per_axis = [brick_bounds(int(n), g) for n, g in zip(shape, grid)]
    return [tuple(per_axis[a][i] for a, i in enumerate(idx))
            for idx in np.ndindex(*grid)]


def _grid3(grid) -> tuple[int, int, int]:
    g = tuple(int(x) for x in np.broadcast_to(np.asarray(grid), (3,)))
    if any(x < 1 for x in g) or len(np.shape(grid)) > 1:
        raise ValueError(f"grid must be 3 positive brick counts, got {grid!r}")
    return g


class SampledField:
    """A volume defined by a function, read brick by brick: an array-like of `shape`
    whose slices `fn` computes on demand (so a process builds its brick without the
    whole array ever existing).

    fn(i, j, k) gets integer voxel indices as broadcasting arrays (np.ix_ of the slice's
    ranges) and returns the values there (any array broadcastable to the slice's shape);
    world coordinates are ``origin + index * spacing``.
    """

    def __init__(self, fn, shape, dtype=np.float32):
        self.fn = fn
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValueError(f"SampledField needs a 3-D shape, got {shape!r}")

    def __getitem__(self, index) -> np.ndarray:
        if not isinstance(index, tuple):
            index = (index,)
        index = index + (slice(None),) * (3 - len(index))
        if len(index) != 3 or not all(isinstance(s, slice) for s in index):
            raise TypeError(f"SampledField reads slices only, got {index!r}")
        ranges = [np.arange(n)[s] for n, s in zip(self.shape, index)]
        values = np.asarray(self.fn(*np.ix_(*ranges)), self.dtype)
        return np.broadcast_to(values, tuple(len(r) for r in ranges)).copy()


def _read_brick(data, ranges) -> np.ndarray:
    """The voxels ranges [(start, stop)] * 3 of `data` (any array-like that slices: only
    this brick is read); planes past the end of an axis repeat its last one
    (`_brick_scene` clips them off)."""
    index = tuple(slice(a, min(b, n)) for (a, b), n in zip(ranges, data.shape))
    brick = np.asarray(data[index])
    pad = [(0, b - min(b, n)) for (a, b), n in zip(ranges, data.shape)]
    if any(p for _, p in pad):
        brick = np.pad(brick, pad, mode="edge")
    return brick


def _brick_scene(data, ranges, isovalues, spacing, origin, clip_box, options,
                 build) -> VolumeIsosurface:
    """The `VolumeIsosurface` of one brick: its own octree, origin at its first voxel,
    clip box = the user's box cut to the brick's real cells, rays traced in the whole
    volume's voxel frame."""
    n = np.asarray(data.shape)
    start = np.array([a for a, _ in ranges])
    stop = np.array([b for _, b in ranges])
    brick_origin = origin + start * spacing
    vol = OctreeVolume.from_array(_read_brick(data, ranges), spacing=spacing,
                                  origin=brick_origin, progress=False, **build)
    lo = brick_origin.astype(np.float32)
    hi = (origin + (np.minimum(stop, n) - 1) * spacing).astype(np.float32)
    if clip_box is not None:
        c_lo, c_hi = (np.broadcast_to(np.asarray(c, np.float32), (3,)) for c in clip_box)
        lo, hi = np.maximum(lo, c_lo), np.minimum(hi, c_hi)
    if np.any(lo > hi):  # the clip box misses this brick: a box past the whole volume
        lo = hi = (origin + n * spacing).astype(np.float32)
    # rays in the whole volume's voxel frame: the same float32 planes at the seams
    frame = (origin.astype(np.float32), start.astype(np.int32))
    return VolumeIsosurface(vol, isovalues, clip_box=(lo, hi), frame=frame, **options)


def brick_volume(data, isovalues, mesh: Mesh, *, grid=None, axis: int = 0, spacing=1.0,
                 origin=0.0, clip_box=None, variance=0.0, iso_range=None,
                 **options) -> BrickedVolume:
    """A `BrickedVolume` of `data` [nx, ny, nz], one brick per device of `mesh` (a
    one-axis Mesh, possibly over several processes).

    data: any array-like with `.shape` that slices (numpy, np.memmap, h5py, zarr, a
      `SampledField`); each process reads only the voxels of its own devices' bricks.
    grid: bricks per axis (gx, gy, gz) with gx * gy * gz == the mesh's device count;
      brick k (C order over the grid) goes to device k. None: all bricks along `axis`.
    isovalues, clip_box, options (method, traversal, normals, max_steps): as
      `VolumeIsosurface`; variance, iso_range: as `OctreeVolume.from_array`.
    The octrees are built on the host, one brick at a time. Level of detail is not
    supported here (each brick's coarse levels would need the neighbour's voxels).
    """
    n_dev = int(mesh.devices.size)
    mine = local_parts(mesh)
    if len(data.shape) != 3:
        raise ValueError(f"need 3-D data, got shape {data.shape}")
    if grid is None:
        if not 0 <= axis < 3:
            raise ValueError(f"axis must be in 0..2, got {axis}")
        grid = tuple(n_dev if a == axis else 1 for a in range(3))
    grid = _grid3(grid)
    if math.prod(grid) != n_dev:
        raise ValueError(f"grid {grid} has {math.prod(grid)} bricks for {n_dev} devices")
    if options.get("lod") is not None:
        raise ValueError("level of detail is not supported on a BrickedVolume")
    if options.get("normals") == "central":
        raise ValueError("a BrickedVolume uses trilinear normals (central differences "
                         "would read voxels of the neighbouring brick)")
    shape = tuple(int(s) for s in data.shape)
    bricks = brick_grid(shape, grid)
    spacing3 = np.broadcast_to(np.asarray(spacing, np.float64), (3,))
    origin3 = np.broadcast_to(np.asarray(origin, np.float64), (3,))
    build = dict(variance=variance, iso_range=iso_range)
    scenes = [_brick_scene(data, bricks[k], isovalues, spacing3, origin3, clip_box,
                           options, build) for k in mine]
    lo = origin3.astype(np.float32)
    hi = (origin3 + (np.asarray(shape) - 1) * spacing3).astype(np.float32)
    if clip_box is not None:
        lo = np.maximum(lo, np.broadcast_to(np.asarray(clip_box[0], np.float32), (3,)))
        hi = np.minimum(hi, np.broadcast_to(np.asarray(clip_box[1], np.float32), (3,)))
    return BrickedVolume(parts=stack_parts(scenes, mesh), box_lo=jnp.asarray(lo),
                         box_hi=jnp.asarray(hi),
                         offset=jnp.float32(1e-3 * np.min(spacing3)), mesh=mesh,
                         grid=grid, shape=shape)


@pytree_dataclass
class BrickedVolume(SplitScene):
    """A volume isosurface split into bricks, one per device of `mesh` (build with
    `brick_volume`); a scene (`jaxiso.Scene`) for `intersect` and `render`.

    Attributes (beyond `SplitScene`'s parts, box_lo, box_hi, offset, mesh):
      grid: bricks per axis (static); shape: the whole volume's shape (static).

    `parts` (alias `bricks`) is a `VolumeIsosurface` whose every array has a leading
    brick axis. Secondary rays leave a surface by a thousandth of a voxel (as one
    volume). Normals are the trilinear patch's ("central" would read across a seam).
    """

    grid: tuple = static_field((1, 1, 1))
    shape: tuple = static_field(())

    def _validate(self):
        if not isinstance(self.parts, VolumeIsosurface):
            raise TypeError("parts must be a stacked VolumeIsosurface (use brick_volume)")
        if self.parts.normals == "central":
            raise ValueError("a BrickedVolume uses trilinear normals (central differences "
                             "would read voxels of the neighbouring brick)")

    @property
    def bricks(self) -> VolumeIsosurface:
        return self.parts

    @property
    def n_bricks(self) -> int:
        return self.n_parts

    def brick_nbytes(self) -> int:
        """Bytes of one brick's arrays (what each device holds of the volume)."""
        return self.part_nbytes()
