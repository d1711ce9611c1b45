"""The min/max hierarchies `traverse` walks: the octree volume and the dense macrocell grid.

Each is built per packet inside `intersect_packet` from the scene's arrays and the
isovalues, and answers `locate`, `cell` and `ancestor` for `_traverse.traverse`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from .._core import pytree_dataclass
from . import _octree
from ._build import checked_geometry, validated
from ._lod import LevelOfDetail

__all__ = ["OctreeCells", "GridCells", "holds_any"]


def holds_any(vmin, vmax, isovalues):
    """[P] bool: the cells of a node with range [vmin, vmax] may hold a surface: some
    isovalue lies in the range and the range is not a single value (then every cell is
    constant, and a constant cell has no surface). An empty range (min > max) holds none."""
    vmin = vmin.astype(jnp.float32)[..., None]
    vmax = vmax.astype(jnp.float32)[..., None]
    return jnp.any((vmin <= isovalues) & (isovalues <= vmax) & (vmin < vmax), axis=-1)


def _octant(v, bit):
    """Child octant 4 bx + 2 by + bz of voxels v [P, 3] at bit position `bit` [] or [P]."""
    b = jnp.right_shift(v, jnp.asarray(bit)[..., None]) & 1
    return 4 * b[:, 0] + 2 * b[:, 1] + b[:, 2]


@dataclasses.dataclass(frozen=True)
class OctreeCells:
    """Traversal of an `OctreeVolume` (seed Sec. 3.3.3).

    Going down from depth `start` the ray's voxel picks a child per level; a child whose
    [min, max] holds no isovalue is culled; a scalar leaf or a cap holding one gives the
    cell to intersect. `neighbor=False` restarts at the root after every move;
    `neighbor=True` resumes at the deepest common ancestor of the old and new voxel (the
    highest differing coordinate bit), read from the parent trace of the last descent
    (Sec. 3.3.2.2). With `lod`, a node whose cells are smaller than the pixel footprint
    there is intersected as one coarse cell (Sec. 4.4).
    """

    volume: _octree.OctreeVolume
    isovalues: jax.Array
    neighbor: bool = False
    lod: LevelOfDetail | None = None

    @property
    def shape(self):
        return self.volume.shape

    def init(self, p):
        return dict(trace=jnp.zeros((p, max(self.volume.depth - 1, 1)), jnp.int32),
                    start=jnp.zeros(p, jnp.int32))

    def locate(self, extra, v, live):
        vol = self.volume
        depth = vol.depth
        trace, start = extra["trace"], extra["start"]
        rec = jnp.take_along_axis(trace, start[:, None], axis=1)[:, 0]
        rec = jnp.where(start == 0, 0, rec)
        p = v.shape[0]
        first = jnp.min(jnp.where(live, start, depth - 2)) if self.neighbor else 0

        def level(d, carry):
            rec, going, bits, at_cell, trace = carry
            active = going & (d >= start)
            b = depth - 1 - d  # the child holds 2^b cells per axis
            c = _octant(v, b)
            holds = holds_any(vol.child_min[rec, c], vol.child_max[rec, c], self.isovalues)
            off = vol.child_offset[rec, c].astype(jnp.int32)
            bottom = (off < 0) | (d == depth - 2)
            coarse = jnp.zeros_like(active)
            if self.lod is not None:
                lo = jnp.left_shift(jnp.right_shift(v, b), b)
                centre = lo + jnp.left_shift(1, b) // 2
                coarse = self.lod.stops(vol, centre.astype(jnp.float32), b)
                # A multires volume's [min, max] is the looser tree (`_build`): it bounds
                # every coarse or blended corner of the node's descendants. A coarse stop's
                # own corners blend with the next level up, beyond that bound, so it is
                # never culled: the cell test itself rejects it.
            cull = active & ~holds & ~coarse
            cell = active & ~cull & (bottom | coarse)
            bits = jnp.where(cull | (cell & coarse), b, bits)
            trace = trace.at[:, d].set(jnp.where(active, rec, trace[:, d]))
            down = active & ~cull & ~cell
            rec = jnp.where(down, vol.child_start[rec] + off, rec)
            return rec, going & ~(cull | cell), bits, at_cell | cell, trace

        carry = (rec, live, jnp.zeros(p, jnp.int32), jnp.zeros(p, bool), trace)
        _, _, bits, at_cell, trace = jax.lax.fori_loop(first, depth - 1, level, carry)
        return bits, at_cell, dict(trace=trace, start=start)

    def cell(self, extra, lo, bits):
        if self.lod is None:
            return _octree.cell_corners(self.volume, lo)
        return self.lod.corners(self.volume, lo, bits)

    def ancestor(self, extra, v, v_next, bits):
        if not self.neighbor:
            return extra
        diff = jnp.bitwise_or.reduce(jnp.bitwise_xor(v, v_next), axis=-1)
        common = self.volume.depth - 1 - _octree.highest_bit(diff.astype(jnp.int32))
        start = jnp.clip(common, 0, max(self.volume.depth - 2, 0))
        return dict(trace=extra["trace"], start=start.astype(jnp.int32))


@pytree_dataclass
class MacrocellGrid:
    """Dense voxels with min/max macrocell grids (Parker et al., seed Sec. 3.5.1): the
    baseline the octree is measured against.

    Attributes:
      data: [nx, ny, nz] float32 voxels.
      ranges: per macrocell level (coarse first), (min, max) arrays over the cells of
        each 2^level-wide macrocell; empty macrocells have min > max.
      spacing, origin: [3] float32.
      levels: static macrocell widths as powers of two, coarse first.
    """

    data: jax.Array
    ranges: tuple
    spacing: jax.Array
    origin: jax.Array
    levels: tuple = dataclasses.field(metadata=dict(static=True))

    @property
    def shape(self):
        return tuple(self.data.shape)

    @property
    def nbytes(self) -> int:
        leaves = jax.tree_util.tree_leaves((self.data, self.ranges))
        return int(sum(a.size * a.dtype.itemsize for a in leaves))

    @staticmethod
    def from_array(data, *, spacing=1.0, origin=0.0, levels=(5, 3)):
        """Macrocell grids of widths 2^level cells (coarse first) over dense float32 data;
        cells with a non-finite corner are empty, as in the octree.

        data: a non-empty 3-D array of real numbers (TypeError for complex or other
        dtypes). spacing, origin: finite scalars or 3-vectors, spacing > 0. levels: an int
        or ints in [1, MAX_LEVEL]; duplicates are merged. Bad values raise ValueError."""
        import numpy as np

        data = validated(data, "macrocell grids").astype(np.float32)
        spacing, origin = checked_geometry(spacing, origin)
        levels = _checked_levels(levels)
        lo, hi = _cell_ranges(data)
        ranges = []
        for k in levels:
            w = 1 << k
            ranges.append((_block_reduce(lo, w, np.minimum, np.inf),
                           _block_reduce(hi, w, np.maximum, -np.inf)))
        return MacrocellGrid(jnp.asarray(data), tuple((jnp.asarray(a), jnp.asarray(b))
                                                      for a, b in ranges),
                             jnp.asarray(spacing), jnp.asarray(origin), levels)


# Widest macrocell 2^MAX_LEVEL cells: as deep as the octree goes (`_build._MAX_DEPTH`), and
# shifts of int32 voxel coordinates by more than 31 bits are undefined.
MAX_LEVEL = 20


def _checked_levels(levels) -> tuple:
    """Distinct macrocell levels, coarse first, each an int in [1, MAX_LEVEL]."""
    import numpy as np

    arr = np.atleast_1d(np.asarray(levels))
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iuf"):
        raise TypeError(f"levels must be an int or a sequence of ints, got {levels!r}")
    bad = [v for v in arr.tolist() if not (1 <= v <= MAX_LEVEL and v == int(v))]
    if bad:
        raise ValueError(f"levels must be ints in [1, {MAX_LEVEL}] (macrocells 2^level cells "
                         f"wide), got {levels!r} (bad: {bad})")
    return tuple(sorted({int(v) for v in arr.tolist()}, reverse=True))


def _cell_ranges(data):
    """min/max over the 8 corners of every cell [nx-1, ny-1, nz-1]; non-finite -> empty."""
    import numpy as np

    corners = [data[a:data.shape[0] - 1 + a, b:data.shape[1] - 1 + b,
                    c:data.shape[2] - 1 + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    stack = np.stack(corners)
    finite = np.all(np.isfinite(stack), axis=0)
    return (np.where(finite, stack.min(axis=0), np.inf),
            np.where(finite, stack.max(axis=0), -np.inf))


def _block_reduce(a, w, op, fill):
    """ufunc `op` over blocks of w^3 entries of `a`: [ceil(n / w)] per axis (at least 1,
    `fill` where an axis is empty). One axis at a time with `reduceat`, which never pads, so
    a macrocell much wider than the volume costs no memory."""
    import numpy as np

    for axis, n in enumerate(a.shape):
        if n == 0:
            shape = list(a.shape)
            shape[axis] = 1
            a = np.full(shape, fill, np.float32)
        else:
            a = op.reduceat(a, np.arange(0, n, w), axis=axis)
    return a.astype(np.float32)


@dataclasses.dataclass(frozen=True)
class GridCells:
    """Traversal of a `MacrocellGrid`: the coarsest macrocell holding no isovalue is
    skipped whole, otherwise cells are intersected one by one."""

    grid: MacrocellGrid
    isovalues: jax.Array

    @property
    def shape(self):
        return self.grid.shape

    def init(self, p):
        return {}

    def locate(self, extra, v, live):
        p = v.shape[0]
        bits = jnp.zeros(p, jnp.int32)
        going = live
        for k, (vmin, vmax) in zip(self.grid.levels, self.grid.ranges):
            m = jnp.right_shift(v, k)
            holds = holds_any(vmin[m[:, 0], m[:, 1], m[:, 2]], vmax[m[:, 0], m[:, 1], m[:, 2]],
                              self.isovalues)
            bits = jnp.where(going & ~holds, k, bits)
            going = going & holds
        return bits, going, extra

    def cell(self, extra, lo, bits):
        data = self.grid.data
        hi = jnp.array(data.shape, jnp.int32) - 1
        corners = []
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    q = jnp.minimum(lo + jnp.array([a, b, c], jnp.int32), hi)
                    corners.append(data[q[:, 0], q[:, 1], q[:, 2]])
        return jnp.stack(corners, axis=-1)

    def ancestor(self, extra, v, v_next, bits):
        return extra
