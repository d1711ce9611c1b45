"""Bottom-up numpy build of a min/max octree volume from a dense 3-D array (seed Sec. 3.2-3.3).

Everything is vectorised level by level: level k holds the nodes spanning 2^k voxels per
axis (depth D - k), on a grid of ceil(n / 2^k) nodes; a level is reduced from the one below
by padding to even sizes and reshaping to (a, 2, b, 2, c, 2) blocks. Nodes beyond the grid
lie entirely outside the data.

Consolidation. A node is consolidatable when its voxels inside the data are all identical
(NaN == NaN counts; voxels outside the data are wildcards), or, for `variance` > 0, when the
population variance of those voxels (from per-node counts, sums of x and x^2 of the original
voxels, shifted by a global centre against cancellation) is <= `variance`. The highest
consolidatable node on a path becomes a scalar leaf of its parent (the root never does) and
stores the mean of its inside voxels, rounded to the stored dtype. Lossy bound: every voxel
of a leaf with `count` inside voxels differs from the leaf's mean by at most
sqrt(variance * (count - 1)) (the extreme case is one voxel against count - 1 equal ones),
plus the rounding of that mean to the stored dtype (half a unit for integers). Lossless
(variance = 0) leaves are exact. A node with NaN voxels consolidates only if all are NaN.

Min/max tree: computed from the reconstructed field (leaf values broadcast) per cell from
its 8 corners (cells with a non-finite corner are invalid), then reduced up the pyramid.
With `multires` it is the seed's looser multiresolution tree (Sec. 4.2.2, "forward neighbours
at each depth"): a level-k node's range also covers the coarse voxel values of every level
j <= k at the level-j points in its closed box [p 2^k, (p + 1) 2^k]. The corners of every
coarse cell below the node, and the next-level corners they blend towards (`_lod`), are such
points, so culling by this range stays exact at any level of detail.
"""

from __future__ import annotations

import math
import sys
import warnings

import numpy as np

__all__ = ["build_octree", "checked_geometry", "validated"]

_KEPT_DTYPES = tuple(np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "float16",
                                           "float32"))
_MAX_DEPTH = 20  # Morton codes of 3 x 20 bits fit int64; 2^20 voxels per axis is plenty
_PROGRESS_VOXELS = 2**24


# ------------------------------------------------------------------ input conversion


def _float32_rounding_of_ints(values: np.ndarray) -> np.ndarray:
    """float64 [...] exact |x - float32(x)| of integers (float32 keeps 24 significant bits),
    computed on uint64 magnitudes so that 64-bit values are not rounded first."""
    magnitude = np.where(values < 0, (~values).astype(np.uint64) + np.uint64(1),
                         values.astype(np.uint64))
    bit_length = np.zeros(magnitude.shape, np.uint64)
    for bit in range(64):
        bit_length += (magnitude >> np.uint64(bit)) > 0
    dropped = np.maximum(bit_length, np.uint64(24)) - np.uint64(24)
    unit = np.uint64(1) << dropped  # value of the last kept bit
    remainder = magnitude & (unit - np.uint64(1))
    return np.minimum(remainder, unit - remainder).astype(np.float64)


def _to_stored_dtype(data: np.ndarray) -> np.ndarray:
    """Keep small dtypes, map bool -> uint8 and wide numbers -> float32 (warning if lossy)."""
    dtype = data.dtype
    if dtype.kind not in "biuf":
        raise TypeError(f"octree volumes hold real numbers; got dtype {dtype}")
    if dtype.kind == "b":
        return data.astype(np.uint8)
    if dtype.newbyteorder("=") in _KEPT_DTYPES:
        return data.astype(dtype.newbyteorder("="), copy=False)
    with np.errstate(over="ignore", invalid="ignore"):
        converted = data.astype(np.float32)
        if dtype.kind == "f":
            same = (converted == data) | (np.isnan(converted) & np.isnan(data))
            change = np.abs(converted.astype(np.float64) - data.astype(np.float64))
        else:
            change = _float32_rounding_of_ints(data)
            same = change == 0
        if not np.all(same):
            worst = float(np.max(np.where(same, 0.0, change)))
            # stacklevel: the caller of OctreeVolume.from_array (-> build_octree -> here)
            warnings.warn(f"{dtype} voxels stored as float32 changed {np.count_nonzero(~same)}"
                          f" value(s), by at most {worst:.6g}", UserWarning, stacklevel=4)
    return converted


def _clamped(data: np.ndarray, iso_range) -> np.ndarray:
    """Clamp values to iso_range = (a, b) (Table 3.1): inside values stay exact."""
    lo, hi = (float(v) for v in iso_range)
    if not lo <= hi:
        raise ValueError(f"iso_range must be (a, b) with a <= b, got {iso_range}")
    if data.dtype.kind in "iu":  # the representable values nearest the range, inside it
        info = np.iinfo(data.dtype)
        lo = min(max(math.ceil(lo), info.min), info.max)
        hi = max(min(math.floor(hi), info.max), info.min)
        lo, hi = min(lo, hi), max(lo, hi)
    return np.clip(data, np.asarray(lo).astype(data.dtype), np.asarray(hi).astype(data.dtype))


def _vector3(value, name: str) -> np.ndarray:
    """[3] float32 from a finite real scalar or 3-vector."""
    v = np.asarray(value)
    if v.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a real scalar or 3-vector, got {value!r}")
    if v.shape not in ((), (1,), (3,)):
        raise ValueError(f"{name} must be a scalar or a 3-vector, got shape {v.shape}: "
                         f"{value!r}")
    with np.errstate(over="ignore"):  # beyond float32's range -> inf, rejected below
        v = np.broadcast_to(v.astype(np.float64), (3,)).astype(np.float32)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def checked_geometry(spacing, origin) -> tuple[np.ndarray, np.ndarray]:
    """(spacing, origin) as [3] float32: finite, spacing > 0 (also after the float32 cast,
    which flushes tiny spacings to 0). A zero or negative spacing would map every voxel to
    one point or flip the box (lo > hi), so it is an error, not an empty image."""
    spacing_v = _vector3(spacing, "spacing")
    if not np.all(spacing_v > 0):
        raise ValueError(f"spacing must be > 0 on every axis, got {spacing!r}")
    return spacing_v, _vector3(origin, "origin")


# ------------------------------------------------------------------- pyramid helpers


def _reduce_pairs(a: np.ndarray, op, fill) -> np.ndarray:
    """[a, b, c] -> [ceil(a/2), ceil(b/2), ceil(c/2)]: binary ufunc `op` over 2x2x2 blocks,
    odd sizes padded by `fill`. One axis at a time on strided halves, which numpy runs far
    faster than a multi-axis reduce over a (a, 2, b, 2, c, 2) view."""
    pad = [(0, s % 2) for s in a.shape]
    if any(p for _, p in pad):
        a = np.pad(a, pad, constant_values=fill)
    a = op(a[0::2], a[1::2])
    a = op(a[:, 0::2], a[:, 1::2])
    return op(a[:, :, 0::2], a[:, :, 1::2])


def _children(grid: np.ndarray, pos: np.ndarray, fill) -> np.ndarray:
    """[R, 8] entries of the level grid below parents at positions pos [R, 3] (octant
    4bx + 2by + bz); children beyond the grid (wholly outside the data) get `fill`.

    Regroups the whole grid into octant rows (one contiguous copy), then gathers rows: much
    faster than a scattered 3-D fancy gather of 8 R entries."""
    parents = tuple(-(-s // 2) for s in grid.shape)
    pad = [(0, 2 * p - s) for s, p in zip(grid.shape, parents)]
    if any(p for _, p in pad):
        grid = np.pad(grid, pad, constant_values=fill)
    rows = grid.reshape(parents[0], 2, parents[1], 2, parents[2], 2).transpose(0, 2, 4, 1, 3, 5)
    rows = rows.reshape(-1, 8)
    return rows[np.ravel_multi_index(tuple(pos.T), parents)]


def _upsample(grid: np.ndarray, shape) -> np.ndarray:
    """Repeat every entry 2x per axis, cropped to `shape`."""
    up = grid.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    return up[: shape[0], : shape[1], : shape[2]]


def _inside_counts(n, level: int) -> np.ndarray:
    """[ceil(n/2^k)...] number of data voxels inside each node of the level (no reduction)."""
    size = 2**level
    per_axis = [np.clip(m - np.arange(-(-m // size)) * size, 0, size) for m in n]
    return per_axis[0][:, None, None] * per_axis[1][None, :, None] * per_axis[2][None, None, :]


def _morton(pos: np.ndarray, depth: int) -> np.ndarray:
    """[R] int64 Morton codes of full-resolution voxel coordinates pos [R, 3], x highest."""
    code = np.zeros(len(pos), np.int64)
    for bit in range(depth):
        for axis in range(3):
            code |= ((pos[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return code


# --------------------------------------------------------------------- statistics


def _level_stats(x: np.ndarray, levels: int, centre: float, report):
    """Per-level node statistics of voxels x (float32 [n], NaN = missing) for k = 1..levels.

    Returns a list indexed by k of dicts: count (inside voxels), finite_count (non-NaN),
    vmin / vmax (ignoring NaN; NaN if none), sum / sumsq of (x - centre) over non-NaN voxels.
    """
    n = x.shape
    nan = np.isnan(x)
    shifted = np.where(nan, 0.0, x.astype(np.float64) - centre)
    cur = dict(finite=(~nan).astype(np.int32), vmin=x, vmax=x, sum=shifted,
               sumsq=shifted * shifted)
    stats = [None]
    for k in range(1, levels + 1):
        nxt = dict(
            finite=_reduce_pairs(cur["finite"], np.add, 0),
            vmin=_reduce_pairs(cur["vmin"], np.fmin, np.nan),
            vmax=_reduce_pairs(cur["vmax"], np.fmax, np.nan),
            sum=_reduce_pairs(cur["sum"], np.add, 0.0),
            sumsq=_reduce_pairs(cur["sumsq"], np.add, 0.0),
        )
        nxt["count"] = _inside_counts(n, k)
        stats.append(nxt)
        cur = nxt
        report(0.5 * k / levels, f"level {k}/{levels} statistics")
    return stats


def _consolidatable(s: dict, variance: float) -> np.ndarray:
    """bool grid: the node's inside voxels may become one scalar leaf."""
    count, finite = s["count"], s["finite"]
    all_nan = finite == 0  # includes nodes wholly outside the data
    identical = (finite == count) & (s["vmin"] == s["vmax"])
    if variance <= 0:
        return all_nan | identical
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s["sum"] / finite
        var = np.maximum(s["sumsq"] / finite - mean * mean, 0.0)
    return all_nan | identical | ((finite == count) & (var <= variance))


def _node_means(s: dict, centre: float) -> np.ndarray:
    """float64 grid: mean of the non-NaN inside voxels (NaN if none; 0 wholly outside)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = centre + s["sum"] / s["finite"]
    mean = np.where(s["finite"] > 0, mean, np.nan)
    return np.where(s["count"] > 0, mean, 0.0)


def _leaf_values(s: dict, centre: float, dtype: np.dtype) -> np.ndarray:
    """float32 grid of scalar-leaf values, exactly representable in the stored dtype."""
    exact = np.where(s["vmin"] == s["vmax"], s["vmin"], np.nan)  # identical: no rounding
    mean = np.where(np.isnan(exact), _node_means(s, centre), exact)
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        mean = np.clip(np.rint(np.nan_to_num(mean)), info.min, info.max)
    with np.errstate(over="ignore"):
        return mean.astype(dtype).astype(np.float32)


# ------------------------------------------------------------------- cell ranges


def _cell_ranges(field: np.ndarray):
    """Per-voxel (min, max) over the cell whose min corner is that voxel; float32 [n] with
    +inf / -inf for voxels that are no valid cell's min corner (last slab, non-finite)."""
    n = field.shape
    lo = np.full(n, np.inf, np.float32)
    hi = np.full(n, -np.inf, np.float32)
    if min(n) < 2:
        return lo, hi
    cmin, cmax, valid = field, field, np.isfinite(field)
    for axis in range(3):  # separable: pairs along x, then y, then z
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        cmin = np.minimum(cmin[a], cmin[b])
        cmax = np.maximum(cmax[a], cmax[b])
        valid = valid[a] & valid[b]
    cells = tuple(slice(0, m - 1) for m in n)
    lo[cells] = np.where(valid, cmin, np.inf)
    hi[cells] = np.where(valid, cmax, -np.inf)
    return lo, hi


def _range_pyramid(lo: np.ndarray, hi: np.ndarray, levels: int):
    """Lists indexed by k of per-node cell ranges for k = 0..levels."""
    los, his = [lo], [hi]
    for _ in range(levels):
        los.append(_reduce_pairs(los[-1], np.minimum, np.inf))
        his.append(_reduce_pairs(his[-1], np.maximum, -np.inf))
    return los, his


def _coarse_value_ranges(values, levels: int):
    """Lists indexed by k = 0..levels of per-node (min, max) over the values a level of
    detail can read in a level-k node's closed box [p 2^k, (p + 1) 2^k]: the finite
    `values[j]` (the level-j voxel grid, j <= k) at the level-j points in that box;
    +inf / -inf where there are none. A running pyramid: the closed boxes of the level-j
    points (each point with its forward neighbours), reduced up a level and joined with the
    next level's points."""
    los, his = [], []
    for k in range(levels + 1):
        v = values[k]
        lo = _forward_reduce(np.where(np.isfinite(v), v, np.inf).astype(np.float32),
                             np.minimum, np.inf)
        hi = _forward_reduce(np.where(np.isfinite(v), v, -np.inf).astype(np.float32),
                             np.maximum, -np.inf)
        if k:
            lo = np.minimum(lo, _reduce_pairs(los[-1], np.minimum, np.inf))
            hi = np.maximum(hi, _reduce_pairs(his[-1], np.maximum, -np.inf))
        los.append(lo)
        his.append(hi)
    return los, his


def _forward_reduce(a: np.ndarray, op, fill) -> np.ndarray:
    """op over each entry and its forward neighbours (+0/+1 per axis), `fill` past the end."""
    for axis in range(3):
        pad = [(0, 0)] * 3
        pad[axis] = (0, 1)
        shifted = np.pad(a, pad, constant_values=fill)
        a = op(a, np.take(shifted, np.arange(1, a.shape[axis] + 1), axis=axis))
    return a


def _as_stored_range(a: np.ndarray, dtype: np.dtype, empty: str) -> np.ndarray:
    """float32 range ends -> stored dtype, rounded outwards (coarse means of the looser tree
    fall between stored values): `empty` = "max" for the min ends (down; empty -> the
    largest value), "min" for the max ends (up). For integers +-inf -> iinfo.max / .min."""
    down = empty == "max"
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        a = np.where(np.isinf(a), info.max if down else info.min,
                     np.floor(a) if down else np.ceil(a))
        return a.astype(dtype)
    stored = a.astype(dtype)
    inward = stored > a if down else stored < a
    return np.where(inward, np.nextafter(stored, dtype.type(-np.inf if down else np.inf)),
                    stored).astype(dtype)


# ----------------------------------------------------------------------- the build


def _progress_reporter(progress, n_voxels: int):
    """A callable(fraction, message) honouring `progress` (None = auto for big builds)."""
    if callable(progress):
        return progress
    if progress is None:
        progress = n_voxels > _PROGRESS_VOXELS
    if not progress:
        return lambda fraction, message: None

    def report(fraction, message):
        end = "\n" if fraction >= 1 else ""
        print(f"\roctree build {100 * fraction:5.1f}% {message:<40}", end=end,
              file=sys.stderr, flush=True)

    return report


def validated(data, what: str = "octree volumes") -> np.ndarray:
    """np.asarray(data), checked to be a non-empty 3-D array of real numbers (complex data
    is a TypeError: casting would silently drop the imaginary part)."""
    data = np.asarray(data)
    if data.dtype.kind not in "biuf":
        raise TypeError(f"{what} hold real numbers; got dtype {data.dtype}")
    if data.ndim != 3:
        raise ValueError(f"{what} need a 3-D array, got shape {data.shape}")
    if data.size == 0:
        raise ValueError(f"{what} need a non-empty array, got shape {data.shape}")
    return data


def build_octree(data, *, spacing=1.0, origin=0.0, variance=0.0, iso_range=None,
                 multires=True, progress=None) -> dict:
    """The fields of an `OctreeVolume` (numpy arrays and static values; the structure
    itself is made by `OctreeVolume.from_array`) from a dense array `data` [nx, ny, nz]
    (x = first index).

    spacing, origin: scalar or 3-vector (spacing > 0). variance: consolidation threshold
    (0 = lossless; see the module docstring for the error bound). iso_range (a, b): clamp
    values first, keeping [a, b] exact (seed Table 3.1). multires: store coarse averages of
    real children in `child_value` (float32) for level of detail. progress: None prints a
    one-line progress to stderr for builds over 2^24 voxels, True/False forces it, a
    callable(fraction, message) receives it instead.

    Stored dtype: uint8/int8/uint16/int16/float16/float32 as given; bool -> uint8; other
    ints and floats -> float32, with a UserWarning naming the largest change if any value
    changes. Raises TypeError for other dtypes, ValueError for empty or non-3-D arrays,
    spacing <= 0 or non-finite, variance < 0, iso_range with a > b. A flat array (some
    n = 1) builds fine but has no cells: every child range is empty.
    """
    raw = validated(data)
    spacing_v, origin_v = checked_geometry(spacing, origin)
    variance = float(variance)
    if not variance >= 0:
        raise ValueError(f"variance must be >= 0, got {variance}")
    n = raw.shape
    depth = max(2, math.ceil(math.log2(max(n))))
    if depth > _MAX_DEPTH:
        raise ValueError(f"volume of shape {n} needs depth {depth} > {_MAX_DEPTH}")
    report = _progress_reporter(progress, raw.size)

    stored = raw
    if iso_range is not None:
        stored = _clamped(raw.astype(np.uint8) if raw.dtype.kind == "b" else raw, iso_range)
    stored = _to_stored_dtype(stored)  # called here: its warning's stacklevel counts on it
    dtype = stored.dtype
    x = stored.astype(np.float32, copy=False)  # every stored dtype is exact in float32
    finite = x[np.isfinite(x)]
    centre = 0.5 * (float(finite.min()) + float(finite.max())) if finite.size else 0.0

    stats = _level_stats(x, depth - 1, centre, report)
    alive, leaf, field, coarse_values = _consolidate(x, stats, depth, variance, centre,
                                                     dtype, multires)
    report(0.6, "reconstructed field")
    range_lo, range_hi = _min_max_tree(field, coarse_values, depth, multires)
    report(0.75, "min/max tree")

    records, caps = _assemble(alive, leaf, stats, field, range_lo, range_hi, depth, dtype,
                              centre, multires)
    report(1.0, f"done: {len(records['child_start'])} records, {len(caps)} caps")

    return dict(records, caps=caps, spacing=spacing_v, origin=origin_v,
                shape=tuple(int(s) for s in n), depth=depth, multires=bool(multires),
                raw_itemsize=int(raw.dtype.itemsize))


def _consolidate(x, stats, depth, variance, centre, dtype, multires):
    """Top down: a node is alive (a record or cap) when no ancestor was a leaf and it does
    not consolidate itself; the highest consolidatable node of a path becomes a scalar leaf.
    Sets ``stats[k]["leaf_value"]``. Returns (alive, leaf) by level, the reconstructed field
    (float32 voxels, leaf values broadcast) and coarse_values: level k -> what
    `lookup_coarse` reads there (NaN: no data; filled with `multires` only)."""
    n = x.shape
    shapes = [n] + [s["count"].shape for s in stats[1:]]  # shapes[k]: node grid of level k
    alive = {depth: np.ones((1, 1, 1), bool)}
    leaf = {}
    field_value = np.zeros((1, 1, 1), np.float32)
    covered = np.zeros((1, 1, 1), bool)
    coarse_values = {}
    for k in range(depth - 1, 0, -1):
        parent_alive = _upsample(alive[k + 1], shapes[k])
        cons = _consolidatable(stats[k], variance)
        leaf[k] = parent_alive & cons
        alive[k] = parent_alive & ~cons
        stats[k]["leaf_value"] = _leaf_values(stats[k], centre, dtype)
        field_value = _upsample(field_value, shapes[k])
        covered = _upsample(covered, shapes[k])
        field_value = np.where(leaf[k], stats[k]["leaf_value"], field_value)
        covered |= leaf[k]
        if multires:  # a leaf's value inside it, the node's mean elsewhere
            value = np.where(covered, field_value, _node_means(stats[k], centre))
            coarse_values[k] = np.where(stats[k]["count"] > 0, value, np.nan)
    field = np.where(_upsample(covered, n), _upsample(field_value, n), x)
    coarse_values[0] = field
    return alive, leaf, field, coarse_values


def _min_max_tree(field, coarse_values, depth, multires):
    """(range_lo, range_hi) by level: the node cell ranges of the reconstructed field,
    loosened with `multires` to cover the coarse values (the module docstring)."""
    cell_lo, cell_hi = _cell_ranges(field)
    range_lo, range_hi = _range_pyramid(cell_lo, cell_hi, depth - 1)
    if multires and min(field.shape) >= 2:  # a flat array has no cells, coarse or fine
        loose_lo, loose_hi = _coarse_value_ranges(coarse_values, depth - 1)
        range_lo = [np.minimum(a, b) for a, b in zip(range_lo, loose_lo)]
        range_hi = [np.maximum(a, b) for a, b in zip(range_hi, loose_hi)]
    return range_lo, range_hi


def _assemble(alive, leaf, stats, field, range_lo, range_hi, depth, dtype, centre, multires):
    """Flat record and cap arrays in the depth-first sibling-group layout.

    alive[k] / leaf[k]: bool node grids of level k; stats[k]: level statistics; field: the
    reconstructed float32 voxels; range_lo/hi[k]: node cell ranges. Returns (records dict of
    [M] / [M, 8] arrays, caps [K, 8]).
    """
    levels = range(depth, 1, -1)  # the levels of records, root first
    positions = [np.argwhere(alive[k]).astype(np.int64) for k in levels]
    # children alive per record, their ranks among siblings
    kids_alive = np.concatenate([_children(alive[k - 1], p, False)
                                 for k, p in zip(levels, positions)])
    rank = np.cumsum(kids_alive, axis=1) - 1
    child_start = _child_starts(positions, kids_alive.sum(axis=1), depth)
    index, grid_index, grid_start = _record_index(alive, positions, rank, child_start, depth)

    m = len(index)
    child_value_dtype = np.float32 if multires else dtype
    out = dict(
        child_start=np.zeros(m, np.int32),
        child_offset=np.zeros((m, 8), np.int8),
        child_value=np.zeros((m, 8), child_value_dtype),
        child_min=np.zeros((m, 8), dtype),
        child_max=np.zeros((m, 8), dtype),
    )
    out["child_start"][index] = child_start
    out["child_offset"][index] = np.where(kids_alive, rank, -1)
    first = 0
    for k, pos in zip(levels, positions):
        rows = index[first:first + len(pos)]
        first += len(pos)
        _fill_children(out, rows, pos, leaf[k - 1], stats[k - 1], range_lo[k - 1],
                       range_hi[k - 1], dtype, centre, multires)
    return out, _caps(alive[1], field, grid_index[2], grid_start[2], rank, dtype)


def _child_starts(positions, n_kids, depth):
    """[M] where each record's sibling group of children starts (records in level order,
    root first): groups placed in pre-order of their parents (Morton code, then depth),
    records after the root, caps (children of level-2 records) from 0."""
    level_of = np.concatenate([np.full(len(p), k, np.int64)
                               for k, p in zip(range(depth, 1, -1), positions)])
    pos_of = np.concatenate(positions)
    morton = _morton(pos_of << level_of[:, None], depth)
    preorder = np.lexsort((-level_of, morton))  # ancestors (higher level) first
    is_cap_parent = level_of == 2
    child_start = np.empty(len(level_of), np.int64)
    for parents, first in ((~is_cap_parent, 1), (is_cap_parent, 0)):
        sizes = np.where(parents, n_kids, 0)[preorder]
        starts = first + np.cumsum(sizes) - sizes
        child_start[preorder[parents[preorder]]] = starts[parents[preorder]]
    return child_start


def _record_index(alive, positions, rank, child_start, depth):
    """(index, grid_index, grid_start): the record index of every record (root 0, else its
    parent's child_start + rank), and per level k the grids of level-order rows and of
    child_start (the parents' side of the lookups)."""
    index = np.zeros(len(child_start), np.int64)
    grid_index = {depth: np.zeros((1, 1, 1), np.int64)}
    grid_start = {}
    offset_of_level = np.cumsum([0] + [len(p) for p in positions])
    for i, k in enumerate(range(depth, 1, -1)):
        sl = slice(offset_of_level[i], offset_of_level[i + 1])
        pos = positions[i]
        if k < depth:
            parent, octant = _parent_and_octant(pos)
            parent_row = grid_index[k + 1][parent]
            index[sl] = grid_start[k + 1][parent] + rank[parent_row, octant]
        grid_index[k] = np.full(alive[k].shape, -1, np.int64)
        grid_index[k][tuple(pos.T)] = np.arange(sl.start, sl.stop)  # row in level-order
        grid_start[k] = np.zeros(alive[k].shape, np.int64)
        grid_start[k][tuple(pos.T)] = child_start[sl]
    return index, grid_index, grid_start


def _parent_and_octant(pos):
    """The parent grid index (a tuple for indexing) and the octant of nodes pos [N, 3]."""
    octant = 4 * (pos[:, 0] & 1) + 2 * (pos[:, 1] & 1) + (pos[:, 2] & 1)
    return tuple((pos >> 1).T), octant


def _fill_children(out, rows, pos, kid_leaves, s, lo, hi, dtype, centre, multires):
    """The child values and ranges of the records `rows` at grid positions pos, from
    their children's level: leaf grid, statistics `s` and cell ranges lo / hi."""
    kid_leaf = _children(kid_leaves, pos, True)
    leaf_value = _children(s["leaf_value"], pos, 0.0)
    coarse = _children(_node_means(s, centre), pos, 0.0) if multires else 0.0
    out["child_value"][rows] = np.where(kid_leaf, leaf_value, coarse).astype(
        out["child_value"].dtype)
    out["child_min"][rows] = _as_stored_range(_children(lo, pos, np.inf), dtype, "max")
    out["child_max"][rows] = _as_stored_range(_children(hi, pos, -np.inf), dtype, "min")


def _caps(alive, field, grid_index, grid_start, rank, dtype):
    """caps [K, 8]: the voxels of the alive level-1 nodes (children of level-2 records),
    numbered by their parent's child_start + rank."""
    cap_pos = np.argwhere(alive).astype(np.int64)
    caps = np.zeros((len(cap_pos), 8), dtype)
    if len(cap_pos):
        parent, octant = _parent_and_octant(cap_pos)
        cap_index = grid_start[parent] + rank[grid_index[parent], octant]
        caps[cap_index] = _children(field, cap_pos, 0.0).astype(dtype)
    return caps
