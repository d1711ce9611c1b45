"""Octree volume as a pytree of flat arrays, and jit-able point location (seed Sec. 3.3, App. A).

Layout (Knoll 2009, App. A.1). The octree covers integer voxel coordinates [0, 2^D)^3 with
D = `depth`; `data[i, j, k]` sits at world `origin + (i, j, k) * spacing`. A node at depth d
(root d = 0) spans 2^(D-d) voxels per axis. Child octant c = 4 bx + 2 by + bz, where bx is
bit D-d-1 of the voxel's x coordinate for a child of a depth-d node.

- Interior records, one per node at depths 0..D-2, root = record 0: `child_start` [M] int32,
  `child_offset` [M, 8] int8, `child_value` [M, 8], `child_min` / `child_max` [M, 8].
  Child c of record r is record `child_start[r] + child_offset[r, c]` (depth <= D-3) or cap
  `child_start[r] + child_offset[r, c]` (depth D-2); offset -1 marks a scalar leaf whose value
  is `child_value[r, c]`. The children of a node are contiguous (offsets 0, 1, ... in octant
  order, leaves skipped); sibling groups are laid out depth-first: record 0 is the root, then
  the root's children, then the children of its first non-leaf child, and so on (pre-order
  of the parents). Caps likewise, so caps appear in Morton order.
- Caps [K, 8]: the 8 voxels of each node at depth D-1 (voxels outside the data are 0).
- `child_min` / `child_max`: range of the field over the valid cells whose min corner lies in
  the child; an empty range (no valid cell) is min > max. A cell is valid when its 8 corners
  are inside the data and finite, so NaN/inf voxels mark missing data that is never hit.
  A `multires` volume stores the looser tree (seed Sec. 4.2.2): joined with the coarse voxel
  values at every level point of the child's closed box, which bounds every level-of-detail
  corner below it (`_build`).

The lookups take int32 coordinates of any batch shape [..., 3], unroll the static depth and
return float32 (they are jitted, so eager calls compile once per volume structure);
coordinates outside the data give 0 (the seed's convention for voxels outside the volume).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._core import pytree_dataclass, static_field
from ._build import build_octree

__all__ = ["OctreeVolume", "lookup", "lookup_trace", "neighbor_lookup", "lookup_coarse",
           "cell_corners", "child_range", "CORNER_OFFSETS"]

# corner c = 4a + 2b + c of a cell sits at voxel ijk + (a, b, c)
CORNER_OFFSETS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], np.int32)


@pytree_dataclass
class OctreeVolume:
    """A min/max octree volume (see the module docstring for the exact format).

    Build with `OctreeVolume.from_array(data, ...)` (= `_build.build_octree`).
    """

    child_start: jax.Array  # [M] int32
    child_offset: jax.Array  # [M, 8] int8, -1 = scalar leaf
    child_value: jax.Array  # [M, 8] float32 if multires else stored dtype
    child_min: jax.Array  # [M, 8] stored dtype
    child_max: jax.Array  # [M, 8] stored dtype
    caps: jax.Array  # [K, 8] stored dtype
    spacing: jax.Array  # [3] float32
    origin: jax.Array  # [3] float32
    shape: tuple[int, int, int] = static_field()
    depth: int = static_field()
    multires: bool = static_field()
    # itemsize of the array the user gave (for raw_nbytes); 0 means the stored dtype's
    raw_itemsize: int = static_field(0)

    @classmethod
    def from_array(cls, data, *, spacing=1.0, origin=0.0, variance=0.0, iso_range=None,
                   multires=True, progress=None) -> OctreeVolume:
        """Build from a 3-D array; see `jaxiso.volume._build.build_octree` (numpy; only
        the result lives on device)."""
        fields = build_octree(data, spacing=spacing, origin=origin, variance=variance,
                              iso_range=iso_range, multires=multires, progress=progress)
        arrays = {k: jnp.asarray(v) for k, v in fields.items() if isinstance(v, np.ndarray)}
        return cls(**{**fields, **arrays})

    @property
    def dtype(self):
        """The stored dtype of voxel values (caps, ranges)."""
        return self.caps.dtype

    @property
    def n_nodes(self) -> int:
        """M, the number of interior records (depths 0..D-2)."""
        return int(self.child_start.shape[0])

    @property
    def n_caps(self) -> int:
        """K, the number of caps (nodes at depth D-1 holding 8 voxels)."""
        return int(self.caps.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of all arrays of the structure."""
        arrays = (self.child_start, self.child_offset, self.child_value, self.child_min,
                  self.child_max, self.caps, self.spacing, self.origin)
        return int(sum(a.nbytes for a in arrays))

    @property
    def raw_nbytes(self) -> int:
        """Bytes of the dense array the volume was built from (its original dtype)."""
        itemsize = self.raw_itemsize or np.dtype(self.dtype).itemsize
        return math.prod(self.shape) * itemsize

    @property
    def compression_ratio(self) -> float:
        """raw_nbytes / nbytes (> 1 means the octree is smaller than the dense array)."""
        return self.raw_nbytes / self.nbytes

    @property
    def lo(self) -> jax.Array:
        """[3] float32 world-space min corner of the valid cells (the voxel grid's box)."""
        return jnp.asarray(self.origin, jnp.float32)

    @property
    def hi(self) -> jax.Array:
        """[3] float32 world-space max corner of the valid cells: origin + (n - 1) spacing."""
        extent = np.maximum(np.asarray(self.shape) - 1, 0).astype(np.float32)
        return jnp.asarray(self.origin, jnp.float32) + extent * self.spacing

    @property
    def value_range(self) -> tuple[float, float]:
        """(min, max) of the field over all valid cells (multires: over all finite voxels,
        the looser tree's root range); (inf, -inf) when there is no cell."""
        lo = np.asarray(self.child_min[0], np.float64)
        hi = np.asarray(self.child_max[0], np.float64)
        if not np.any(lo <= hi):
            return math.inf, -math.inf
        keep = lo <= hi
        return float(lo[keep].min()), float(hi[keep].max())

    def to_array(self) -> np.ndarray:
        """[nx, ny, nz] numpy reconstruction of the stored field (in the stored dtype)."""
        return _to_array(self)


# ---------------------------------------------------------------- numpy reconstruction


def _upsample(grid, shape):
    """Repeat every entry of a 3-D grid 2x per axis, cropped to `shape`."""
    up = grid.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    return up[: shape[0], : shape[1], : shape[2]]


def _to_array(vol: OctreeVolume) -> np.ndarray:
    """Walk the records level by level (vectorised over the nodes of a level)."""
    depth, n = vol.depth, np.asarray(vol.shape)
    child_start = np.asarray(vol.child_start, np.int64)
    child_offset = np.asarray(vol.child_offset, np.int64)
    child_value = np.asarray(vol.child_value)
    caps = np.asarray(vol.caps)
    dtype = caps.dtype
    octant_bits = CORNER_OFFSETS.astype(np.int64)  # octant c -> (bx, by, bz), same order
    records, positions = np.zeros(1, np.int64), np.zeros((1, 3), np.int64)
    values = np.zeros((1, 1, 1), dtype)
    for level in range(depth - 1, 0, -1):  # children of the current records span 2^level
        shape = -(-n // 2**level)
        values = _upsample(values, shape)
        kids = 2 * positions[:, None, :] + octant_bits[None]  # [R, 8, 3]
        offsets = child_offset[records]
        inside = np.all(kids < shape, axis=-1)
        leaf = (offsets < 0) & inside
        at = kids[leaf]
        values[at[:, 0], at[:, 1], at[:, 2]] = child_value[records][leaf].astype(dtype)
        real = offsets >= 0
        positions = kids[real]
        records = (child_start[records][:, None] + offsets)[real]
    # the remaining "records" index caps: their voxels overwrite the upsampled leaf values
    values = _upsample(values, n)
    voxels = (2 * positions[:, None, :] + octant_bits[None]).reshape(-1, 3)
    cap_values = caps[records].reshape(-1)
    inside = np.all(voxels < n, axis=-1)
    voxels = voxels[inside]
    values[voxels[:, 0], voxels[:, 1], voxels[:, 2]] = cap_values[inside]
    return values


# ------------------------------------------------------------------- jit-able lookups


def _octant(ijk, bit):
    """[...] int32 octant 4 bx + 2 by + bz of coordinates ijk [..., 3] at a power-of-two `bit`."""
    b = ((ijk & bit) != 0).astype(jnp.int32)
    return 4 * b[..., 0] + 2 * b[..., 1] + b[..., 2]


def _entry(table, row, col):
    """table[row, col] for a [R, 8] table as one flat clipped gather (a smaller program than
    numpy-style advanced indexing, which also normalises negative indices)."""
    return jnp.take(table.reshape(-1), row * 8 + col, mode="clip")


def _inside(vol, ijk):
    """[...] bool: ijk lies inside the data (not merely inside the octree's cube)."""
    return jnp.all((ijk >= 0) & (ijk < jnp.asarray(vol.shape, jnp.int32)), axis=-1)


def _descend(vol, ijk, start_depth, start_index):
    """Point location (App. A.2.1) from a node at `start_depth` on the path to ijk.

    ijk [..., 3] int32; start_depth [...] int32 in [0, D-1]; start_index [...] int32: the
    record at that depth, or the cap when start_depth == D-1. Returns (values [...] float32,
    trace [..., D] int32): trace[d] = record (d <= D-2) or cap (d = D-1) at depth d for
    d >= start_depth, -1 below a scalar leaf (and for d < start_depth).
    """
    depth = vol.depth
    batch = ijk.shape[:-1]
    start_depth = jnp.broadcast_to(start_depth, batch)
    start_index = jnp.broadcast_to(start_index, batch)
    rec = jnp.where(start_depth <= depth - 2, start_index, 0)  # a valid record either way
    done = jnp.zeros(batch, bool)
    value = jnp.zeros(batch, jnp.float32)
    trace = []
    cap = start_index
    for d in range(depth - 1):
        reached = (d >= start_depth) & ~done
        trace.append(jnp.where(reached, rec, -1))
        c = _octant(ijk, 1 << (depth - d - 1))
        offset = _entry(vol.child_offset, rec, c).astype(jnp.int32)
        leaf = reached & (offset < 0)
        value = jnp.where(leaf, _entry(vol.child_value, rec, c).astype(jnp.float32), value)
        done = done | leaf
        nxt = jnp.take(vol.child_start, rec, mode="clip") + jnp.maximum(offset, 0)
        if d < depth - 2:
            rec = jnp.where(reached & ~leaf, nxt, rec)
        else:
            cap = jnp.where(reached & ~leaf, nxt, cap)
    trace.append(jnp.where(done, -1, cap))
    if vol.caps.shape[0] > 0:  # a volume with no caps (all leaves) has nothing to gather
        voxel = _entry(vol.caps, jnp.where(done, 0, cap), _octant(ijk, 1)).astype(jnp.float32)
        value = jnp.where(done, value, voxel)
    return value, jnp.stack(trace, axis=-1)


@jax.jit
def lookup_trace(vol: OctreeVolume, ijk):
    """Point location from the root, keeping the path (the seed's parent_trace).

    ijk [..., 3] int -> (values [...] float32, trace [..., D] int32) with trace[d] the record
    at depth d (d <= D-2), trace[D-1] the cap, and -1 below a scalar leaf. Values outside the
    data are 0.
    """
    ijk = jnp.asarray(ijk, jnp.int32)
    zero = jnp.zeros(ijk.shape[:-1], jnp.int32)
    value, trace = _descend(vol, ijk, zero, zero)
    return jnp.where(_inside(vol, ijk), value, 0.0), trace


@jax.jit
def lookup(vol: OctreeVolume, ijk):
    """[...] float32 voxel values at integer coordinates ijk [..., 3] (0 outside the data)."""
    return lookup_trace(vol, ijk)[0]


def highest_bit(x):
    """[...] int32 index of the highest set bit of x >= 0 (-1 for 0)."""
    return 31 - jax.lax.clz(x)


@jax.jit
def neighbor_lookup(vol: OctreeVolume, trace, ijk, target_ijk):
    """Neighbour finding (Sec. 3.3.2.2, App. A.2.2): the value at target_ijk [..., 3].

    `trace` [..., D] is `lookup_trace(vol, ijk)[1]`. The deepest common ancestor of ijk and
    the target is at depth D-1-h, h the highest bit where their coordinates differ; the
    search resumes from the deepest recorded ancestor at or above that depth (a -1 entry
    means ijk's path ended in a scalar leaf higher up, which then holds the target too).
    Returns [...] float32, 0 outside the data.
    """
    depth = vol.depth
    ijk = jnp.asarray(ijk, jnp.int32)
    target_ijk = jnp.asarray(target_ijk, jnp.int32)
    trace = jnp.asarray(trace, jnp.int32)
    diff = jnp.bitwise_or.reduce(ijk ^ target_ijk, axis=-1)
    # differing bits above the octree (targets outside its cube) resume from the root
    common = jnp.clip(depth - 1 - highest_bit(diff), 0, depth - 1)
    levels = jnp.arange(depth, dtype=jnp.int32)
    usable = (levels <= common[..., None]) & (trace >= 0)
    start = jnp.max(jnp.where(usable, levels, 0), axis=-1)
    index = jnp.take_along_axis(trace, start[..., None], axis=-1)[..., 0]
    start = jnp.where(index >= 0, start, 0)  # root always usable; guards a malformed trace
    index = jnp.maximum(index, 0)
    value, _ = _descend(vol, target_ijk, start, index)
    return jnp.where(_inside(vol, target_ijk), value, 0.0)


def lookup_coarse(vol: OctreeVolume, ijk, level):
    """[...] float32 value of the depth-`level` node containing voxel ijk [..., 3].

    That is the node's coarse average (multires volumes), or the scalar leaf above it, or
    the voxel itself for level = D. `level` is an int in [1, D] or an int32 array (clipped
    to [1, D]); the root (level 0) stores no value. Coarse averages ignore NaN voxels.
    0 outside the data.
    """
    depth = vol.depth
    if isinstance(level, int | np.integer):
        if not 1 <= level <= depth:
            raise ValueError(f"level must be in [1, {depth}] (the depth), got {level}")
        if level < depth and not vol.multires:
            raise ValueError("coarse levels need a volume built with multires=True")
    return _lookup_coarse(vol, ijk, level)


@jax.jit
def _lookup_coarse(vol, ijk, level):
    """lookup_coarse after the checks; the level is traced (no recompile per level)."""
    depth = vol.depth
    ijk = jnp.asarray(ijk, jnp.int32)
    batch = ijk.shape[:-1]
    level = jnp.broadcast_to(jnp.clip(jnp.asarray(level, jnp.int32), 1, depth), batch)
    rec = jnp.zeros(batch, jnp.int32)
    cap = jnp.zeros(batch, jnp.int32)
    done = jnp.zeros(batch, bool)
    value = jnp.zeros(batch, jnp.float32)
    for d in range(depth - 1):
        c = _octant(ijk, 1 << (depth - d - 1))
        offset = _entry(vol.child_offset, rec, c).astype(jnp.int32)
        stop = ~done & ((offset < 0) | (level == d + 1))
        value = jnp.where(stop, _entry(vol.child_value, rec, c).astype(jnp.float32), value)
        done = done | stop
        nxt = jnp.take(vol.child_start, rec, mode="clip") + jnp.maximum(offset, 0)
        if d < depth - 2:
            rec = jnp.where(done, rec, nxt)
        else:
            cap = jnp.where(done, 0, nxt)
    if vol.caps.shape[0] > 0:
        value = jnp.where(done, value, _entry(vol.caps, cap, _octant(ijk, 1)).astype(jnp.float32))
    return jnp.where(_inside(vol, ijk), value, 0.0)


@jax.jit
def cell_corners(vol: OctreeVolume, ijk):
    """[..., 8] float32 corner values of cell ijk [..., 3]: corner c = 4a + 2b + c at voxel
    ijk + (a, b, c) (Fig. 3.2). Corners outside the data are 0.

    One batched point location of the 8 corners from the root: with batched gathers every
    level is fetched for every lane anyway, so resuming from the trace (`neighbor_lookup`)
    would only add work; it pays off in per-ray loops that stop early.
    """
    ijk = jnp.asarray(ijk, jnp.int32)
    return lookup(vol, ijk[..., None, :] + jnp.asarray(CORNER_OFFSETS))


def child_range(vol: OctreeVolume, record, octant):
    """(min, max) in the stored dtype of child `octant` of `record` (min > max: empty)."""
    return vol.child_min[record, octant], vol.child_max[record, octant]
