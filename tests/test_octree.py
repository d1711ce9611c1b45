"""Octree volume: lossless round trips, exact min/max tree, layout, lookups, lossy bound, errors.

Every expectation is computed here from the dense array with plain numpy (block means, cell
ranges from the 8 shifted corner arrays, a recursive walk of the documented layout), never
from values the builder produced.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxiso.volume._octree import (
    OctreeVolume,
    cell_corners,
    child_range,
    lookup,
    lookup_coarse,
    lookup_trace,
    neighbor_lookup,
)

# odd, anisotropic, flat and tiny shapes x random small ints / floats / constant blocks
CASES = [((5, 9, 3), "small_ints"), ((5, 9, 3), "floats"), ((5, 9, 3), "blocks"),
         ((1, 4, 6), "small_ints"), ((1, 4, 6), "floats"), ((2, 2, 2), "small_ints"),
         ((2, 2, 2), "floats"), ((17, 3, 8), "small_ints"), ((17, 3, 8), "floats"),
         ((17, 3, 8), "blocks"), ((6, 5, 7), "blocks")]
# module-level jits: one compile per volume structure, reused across the tests
jit_lookup = jax.jit(lookup)
jit_trace = jax.jit(lookup_trace)
jit_neighbor = jax.jit(neighbor_lookup)
jit_coarse = jax.jit(lookup_coarse)
jit_corners = jax.jit(cell_corners)


def octant_bits(c):
    return np.array([(c >> 2) & 1, (c >> 1) & 1, c & 1])


def all_voxels(shape):
    """[nx, ny, nz, 3] int32 coordinates of every voxel."""
    return np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).astype(
        np.int32)


def make_data(shape, kind, seed=0):
    rng = np.random.default_rng(seed)
    if kind == "small_ints":  # lots of consolidation
        return rng.choice(np.array([0, 0, 0, 0, 0, 1, 2], np.int16), size=shape)
    if kind == "blocks":  # 2x2x2 / 4x4x4 constant blocks: interior scalar leaves
        coarse = rng.integers(0, 3, size=tuple(-(-s // 4) for s in shape)).astype(np.uint8)
        return coarse.repeat(4, 0).repeat(4, 1).repeat(4, 2)[: shape[0], : shape[1], : shape[2]]
    return rng.standard_normal(shape).astype(np.float32)


def walk(vol):
    """Recursive walk of the flat arrays checking the documented depth-first sibling-group
    layout. Returns (children: list of (record, octant, corner [3], size, is_real),
    caps: list of (cap index, corner [3]))."""
    depth = vol.depth
    start = np.asarray(vol.child_start)
    offset = np.asarray(vol.child_offset)
    children, caps = [], []
    next_record, next_cap = [1], [0]

    def visit(record, d, corner):
        size = 2 ** (depth - d - 1)
        real = [c for c in range(8) if offset[record, c] >= 0]
        assert [offset[record, c] for c in real] == list(range(len(real)))
        assert np.all(offset[record] >= -1)
        counter = next_cap if d == depth - 2 else next_record
        if real:  # the group of children sits right where the pre-order walk has got to
            assert start[record] == counter[0]
            counter[0] += len(real)
        for c in range(8):
            children.append((record, c, corner + size * octant_bits(c), size, c in real))
        for c in real:
            child_corner = corner + size * octant_bits(c)
            if d == depth - 2:
                caps.append((start[record] + offset[record, c], child_corner))
            else:
                visit(start[record] + offset[record, c], d + 1, child_corner)

    visit(0, 0, np.zeros(3, np.int64))
    assert next_record[0] == vol.n_nodes
    assert next_cap[0] == vol.n_caps
    return children, caps


def brute_cell_ranges(field):
    """Per-cell (min, max) from the 8 shifted corner arrays; +inf/-inf for invalid cells."""
    n = field.shape
    cells = tuple(max(s - 1, 0) for s in n)
    corners = [field[a: a + cells[0], b: b + cells[1], c: c + cells[2]]
               for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    stack = np.stack(corners).astype(np.float64)
    valid = np.all(np.isfinite(stack), axis=0)
    lo = np.where(valid, stack.min(axis=0), np.inf)
    hi = np.where(valid, stack.max(axis=0), -np.inf)
    return lo, hi


def coarse_value(raw, leaves, q, size):
    """float64 level-of-detail voxel of width `size` at q: the value of a scalar leaf at
    least that wide holding q, else the mean of the finite raw voxels of [q, q + size)."""
    for corner, width, value in leaves:
        if width >= size and all(a <= b < a + width for a, b in zip(corner, q)):
            return float(value)
    block = raw[tuple(slice(a, a + size) for a in q)].astype(np.float64)
    block = block[~np.isnan(block)]
    return block.mean() if block.size else np.nan


def coarse_points(corner, size, width, shape):
    """Level points of width `width` in the closed box [corner, corner + size], each axis
    clamped to the last one holding data (where level-of-detail corners are clamped)."""
    axes = []
    for a, n in zip(corner, shape):
        last = (n - 1) // width * width
        axes.append(sorted({min(a + m * width, last) for m in range(size // width + 1)}))
    return [(x, y, z) for x in axes[0] for y in axes[1] for z in axes[2]]


def check_ranges(vol, field, raw=None):
    """Every child's stored range equals the brute-force range of its cells. A multires
    volume stores the looser tree (seed Sec. 4.2.2): joined with every coarse voxel value
    (width 2 .. the child's) at the points of the child's closed box."""
    cell_lo, cell_hi = brute_cell_ranges(field)
    raw = field if raw is None else raw
    children, _ = walk(vol)
    child_min = np.asarray(vol.child_min)
    child_max = np.asarray(vol.child_max)
    value = np.asarray(vol.child_value)
    leaves = [(corner, size, value[r, c]) for r, c, corner, size, real in children
              if not real]
    empty = 0
    for record, c, corner, size, _ in children:
        block = tuple(slice(a, a + size) for a in corner)
        lo, hi = cell_lo[block], cell_hi[block]
        want_lo = lo.min() if lo.size else np.inf
        want_hi = hi.max() if hi.size else -np.inf
        inside = all(a < n for a, n in zip(corner, field.shape))
        if vol.multires and min(field.shape) >= 2 and inside:  # flat arrays have no cells
            seen = [field[q] for q in coarse_points(corner, size, 1, field.shape)]
            width = 2
            while width <= size:
                seen += [coarse_value(raw, leaves, q, width)
                         for q in coarse_points(corner, size, width, field.shape)]
                width *= 2
            seen = np.array(seen, np.float64)
            seen = seen[np.isfinite(seen)]
            if seen.size:
                # coarse means are float64 means rounded to float32, stored rounded outwards
                lo_c, hi_c = np.float32(seen.min()), np.float32(seen.max())
                if np.issubdtype(child_min.dtype, np.integer):
                    lo_c, hi_c = np.floor(lo_c), np.ceil(hi_c)
                elif child_min.dtype != np.float32:
                    lo_c = float(child_min.dtype.type(lo_c))
                    hi_c = float(child_min.dtype.type(hi_c))
                want_lo, want_hi = min(want_lo, lo_c), max(want_hi, hi_c)
        got_lo, got_hi = child_min[record, c], child_max[record, c]
        if want_lo > want_hi:  # no valid cell: empty, encoded min > max
            empty += 1
            assert got_lo > got_hi
            if np.issubdtype(child_min.dtype, np.integer):
                info = np.iinfo(child_min.dtype)
                assert (got_lo, got_hi) == (info.max, info.min)
            else:
                assert (got_lo, got_hi) == (np.inf, -np.inf)
        else:
            assert (float(got_lo), float(got_hi)) == (want_lo, want_hi), (record, c, corner)
    return empty


# ------------------------------------------------------------------------ lossless


@pytest.mark.parametrize("shape, kind", CASES)
def test_lossless_round_trip_and_ranges(shape, kind):
    data = make_data(shape, kind)
    vol = OctreeVolume.from_array(data)
    assert vol.depth == max(2, int(np.ceil(np.log2(max(shape)))))
    got = np.asarray(jit_lookup(vol, all_voxels(shape)))
    np.testing.assert_array_equal(got, data.astype(np.float32))
    back = vol.to_array()
    assert back.dtype == data.dtype
    np.testing.assert_array_equal(back, data)
    check_ranges(vol, data)
    check_ranges(OctreeVolume.from_array(data, multires=False), data)
    _, caps = walk(vol)
    padded = np.zeros(tuple(2 * (-(-s // 2)) for s in shape), data.dtype)
    padded[: shape[0], : shape[1], : shape[2]] = data
    for index, corner in caps:  # caps hold their 8 voxels, 0 outside the data
        want = [padded[tuple(corner + octant_bits(c))] for c in range(8)]
        np.testing.assert_array_equal(np.asarray(vol.caps[index]), want)


def test_scalar_leaves_happen_and_a_constant_volume_has_no_caps():
    vol = OctreeVolume.from_array(make_data((16, 16, 16), "blocks", seed=3))
    assert np.any(np.asarray(vol.child_offset) == -1)
    assert vol.n_caps == 0  # 4x4x4 constant blocks: nothing below depth D-2 is real
    const = OctreeVolume.from_array(np.full((5, 6, 7), 3.5, np.float32))
    assert (const.n_nodes, const.n_caps) == (1, 0)
    np.testing.assert_array_equal(np.asarray(jit_lookup(const, all_voxels((5, 6, 7)))), 3.5)
    np.testing.assert_array_equal(np.asarray(jit_corners(const, jnp.zeros(3, jnp.int32))),
                                  3.5)


def test_lookup_eager_jit_vmap_and_no_retrace():
    data = make_data((6, 5, 7), "small_ints", seed=1)
    vol = OctreeVolume.from_array(data)
    ijk = all_voxels(data.shape).reshape(-1, 3)
    want = data.reshape(-1).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(lookup(vol, ijk)), want)
    np.testing.assert_array_equal(np.asarray(jax.vmap(lambda p: lookup(vol, p))(ijk)), want)
    traces = []

    @jax.jit
    def f(v, p):
        traces.append(1)
        return lookup(v, p)

    np.testing.assert_array_equal(np.asarray(f(vol, ijk)), want)
    np.testing.assert_array_equal(np.asarray(f(vol, ijk[::-1])), want[::-1])
    assert len(traces) == 1


def test_outside_coordinates_give_zero():
    data = np.full((3, 3, 3), 7, np.uint8)
    vol = OctreeVolume.from_array(data)
    ijk = np.array([[3, 0, 0], [-1, 0, 0], [0, 0, 2], [0, 5, 0]], np.int32)
    np.testing.assert_array_equal(np.asarray(jit_lookup(vol, ijk)), [0, 0, 7, 0])


def test_lookup_trace_records_the_path():
    data = make_data((6, 5, 7), "small_ints", seed=2)
    vol = OctreeVolume.from_array(data)
    ijk = all_voxels(data.shape).reshape(-1, 3)
    values, trace = jit_trace(vol, ijk)
    np.testing.assert_array_equal(np.asarray(values), data.reshape(-1))
    trace = np.asarray(trace)
    assert trace.shape == (len(ijk), vol.depth)
    np.testing.assert_array_equal(trace[:, 0], 0)
    start = np.asarray(vol.child_start)
    offset = np.asarray(vol.child_offset)
    for p, row in zip(ijk, trace):  # each entry is the child of the previous one, -1 after
        for d in range(vol.depth - 1):
            c = int(4 * ((p[0] >> (vol.depth - d - 1)) & 1) + 2 * ((p[1] >> (vol.depth - d - 1))
                                                                  & 1)
                    + ((p[2] >> (vol.depth - d - 1)) & 1))
            if row[d] < 0 or offset[row[d], c] < 0:
                assert np.all(row[d + 1:] == -1)
                break
            assert row[d + 1] == start[row[d]] + offset[row[d], c]


def test_neighbor_lookup_matches_the_dense_array():
    rng = np.random.default_rng(4)
    for shape, kind in (((17, 3, 8), "small_ints"), ((6, 5, 7), "floats")):
        data = make_data(shape, kind, seed=5)
        vol = OctreeVolume.from_array(data)
        ijk = np.stack([rng.integers(0, s, 400) for s in shape], -1).astype(np.int32)
        near = np.clip(ijk + rng.integers(-2, 3, ijk.shape), 0, np.array(shape) - 1)
        far = np.stack([rng.integers(0, s, 400) for s in shape], -1)
        _, trace = jit_trace(vol, ijk)
        for target in (near, far, ijk):
            got = np.asarray(jit_neighbor(vol, trace, ijk, target.astype(np.int32)))
            np.testing.assert_array_equal(got, data[tuple(target.T)].astype(np.float32))


def test_cell_corners_match_the_dense_corners():
    data = make_data((5, 9, 3), "small_ints", seed=6)
    vol = OctreeVolume.from_array(data)
    cells = all_voxels((4, 8, 2))
    got = np.asarray(jit_corners(vol, cells))
    want = np.stack([data[a: a + 4, b: b + 8, c: c + 2]
                     for a in (0, 1) for b in (0, 1) for c in (0, 1)], -1)
    np.testing.assert_array_equal(got, want.astype(np.float32))


def test_lookup_coarse_gives_block_means():
    data = make_data((6, 5, 7), "small_ints", seed=7).astype(np.float32)
    data[:4, :4, :4] = 2.0  # one node two levels up is a scalar leaf
    vol = OctreeVolume.from_array(data)
    ijk = all_voxels(data.shape)
    for level in range(1, vol.depth + 1):
        size = 2 ** (vol.depth - level)
        want = np.empty(data.shape)
        for corner in np.ndindex(*(-(-s // size) for s in data.shape)):
            block = tuple(slice(a * size, (a + 1) * size) for a in corner)
            want[block] = data[block].mean()
        got = np.asarray(jit_coarse(vol, ijk, jnp.int32(level)))  # traced level
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    static = jax.jit(lookup_coarse, static_argnums=2)(vol, ijk, vol.depth - 1)
    np.testing.assert_array_equal(np.asarray(static), jit_coarse(vol, ijk, vol.depth - 1))
    with pytest.raises(ValueError, match="level"):
        lookup_coarse(vol, ijk, 0)


def test_multires_off_stores_no_coarse_values():
    data = make_data((6, 5, 7), "small_ints", seed=8)
    vol = OctreeVolume.from_array(data, multires=False)
    assert vol.child_value.dtype == data.dtype
    offset, value = np.asarray(vol.child_offset), np.asarray(vol.child_value)
    assert np.all(value[offset >= 0] == 0)
    np.testing.assert_array_equal(np.asarray(jit_lookup(vol, all_voxels(data.shape))), data)
    with pytest.raises(ValueError, match="multires"):
        lookup_coarse(vol, all_voxels(data.shape), 1)


def test_flat_volume_has_no_cells():
    data = make_data((1, 4, 6), "floats", seed=9)
    vol = OctreeVolume.from_array(data)
    assert np.all(np.asarray(vol.child_min) > np.asarray(vol.child_max))
    assert vol.value_range == (np.inf, -np.inf)
    np.testing.assert_array_equal(np.asarray(jit_lookup(vol, all_voxels(data.shape))), data)


# ------------------------------------------------------------------ lossy and clamping


def test_lossy_leaves_respect_the_variance_bound():
    rng = np.random.default_rng(10)
    x = np.linspace(0, 1, 12)
    smooth = (x[:, None, None] + 0.5 * x[None, :, None] + 0.25 * x[None, None, :])
    data = (smooth + 0.01 * rng.standard_normal(smooth.shape)).astype(np.float32)
    variance = 0.01
    vol = OctreeVolume.from_array(data, variance=variance)
    exact = OctreeVolume.from_array(data)
    assert vol.nbytes < exact.nbytes  # lossy consolidation happened
    recon = vol.to_array()
    np.testing.assert_array_equal(np.asarray(jit_lookup(vol, all_voxels(data.shape))), recon)
    children, _ = walk(vol)
    value = np.asarray(vol.child_value)
    covered = np.zeros(data.shape, bool)
    leaves = 0
    for record, c, corner, size, real in children:
        block = tuple(slice(a, a + size) for a in corner)
        voxels = data[block].astype(np.float64)
        if real or voxels.size == 0:
            continue
        leaves += 1
        covered[block] = True
        assert voxels.var() <= variance * (1 + 1e-9)
        bound = np.sqrt(variance * (voxels.size - 1))
        assert np.all(np.abs(voxels - value[record, c]) <= bound + 1e-6)
        np.testing.assert_allclose(value[record, c], voxels.mean(), rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(recon[block], value[record, c])
    assert leaves > 0
    np.testing.assert_array_equal(recon[~covered], data[~covered])  # caps are exact
    check_ranges(vol, recon, data)  # ranges follow the reconstructed (rendered) field


def test_iso_range_clamps_and_keeps_the_range_exact():
    rng = np.random.default_rng(11)
    data = rng.integers(0, 256, (7, 6, 9)).astype(np.uint8)
    vol = OctreeVolume.from_array(data, iso_range=(64, 127))
    np.testing.assert_array_equal(vol.to_array(), np.clip(data, 64, 127))
    floats = rng.standard_normal((7, 6, 9)).astype(np.float32)
    vol = OctreeVolume.from_array(floats, iso_range=(-0.5, 0.25))
    np.testing.assert_array_equal(vol.to_array(), np.clip(floats, np.float32(-0.5),
                                                          np.float32(0.25)))
    check_ranges(vol, np.clip(floats, np.float32(-0.5), np.float32(0.25)))


# ------------------------------------------------------------------- size and props


def test_compression_and_nbytes():
    n = 32
    g = np.arange(n) - n / 2
    r = np.sqrt(g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2)
    sparse = np.where(r < 6, 100, 0).astype(np.uint8)
    vol = OctreeVolume.from_array(sparse)
    assert vol.compression_ratio > 1
    arrays = (vol.child_start, vol.child_offset, vol.child_value, vol.child_min,
              vol.child_max, vol.caps, vol.spacing, vol.origin)
    assert vol.nbytes == sum(np.asarray(a).nbytes for a in arrays)
    assert vol.raw_nbytes == sparse.nbytes
    assert vol.compression_ratio == sparse.nbytes / vol.nbytes
    wide = OctreeVolume.from_array(sparse.astype(np.float64))
    assert wide.raw_nbytes == sparse.size * 8


def test_dtypes_bounds_and_geometry():
    rng = np.random.default_rng(12)
    data = rng.standard_normal((4, 5, 6)).astype(np.float32)
    vol = OctreeVolume.from_array(data, spacing=(0.5, 1.0, 2.0), origin=(1.0, -2.0, 3.0))
    np.testing.assert_array_equal(np.asarray(vol.lo), [1.0, -2.0, 3.0])
    np.testing.assert_array_equal(np.asarray(vol.hi), [1.0 + 3 * 0.5, -2.0 + 4, 3.0 + 10])
    assert vol.spacing.dtype == jnp.float32 and vol.origin.dtype == jnp.float32
    assert vol.child_start.dtype == jnp.int32 and vol.child_offset.dtype == jnp.int8
    assert vol.child_value.dtype == jnp.float32
    assert vol.value_range == (float(data.min()), float(data.max()))
    lo, hi = child_range(OctreeVolume.from_array(data, multires=False), 0, 0)
    # cells with min corner in [0, 4) reach voxel 4: forward neighbours count too
    assert (float(lo), float(hi)) == (data[:5, :5, :5].min(), data[:5, :5, :5].max())
    loose = child_range(vol, 0, 0)  # multires: the looser tree (checked in check_ranges)
    assert data.min() <= float(loose[0]) <= float(lo) and float(hi) <= float(loose[1])
    assert float(loose[1]) <= data.max()
    jax.tree_util.tree_map(lambda a: a, vol)  # a pytree with static meta


def test_stored_dtypes_and_conversion_warnings():
    rng = np.random.default_rng(13)
    base = rng.integers(0, 3, (4, 3, 5))
    for dtype in (np.uint8, np.int16, np.float32, np.float16, np.int8, np.uint16):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            vol = OctreeVolume.from_array(base.astype(dtype))
        assert vol.caps.dtype == dtype and vol.child_min.dtype == dtype
        np.testing.assert_array_equal(vol.to_array(), base.astype(dtype))
    for dtype in (np.float64, np.int64, np.int32, np.uint32):  # exact: no warning
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            vol = OctreeVolume.from_array(base.astype(dtype))
        assert vol.caps.dtype == np.float32
        np.testing.assert_array_equal(vol.to_array(), base)
    vol = OctreeVolume.from_array(base.astype(bool))
    assert vol.caps.dtype == np.uint8
    np.testing.assert_array_equal(vol.to_array(), base.astype(bool))
    inexact = base.astype(np.float64) + 0.1
    with pytest.warns(UserWarning, match="float32"):
        OctreeVolume.from_array(inexact)
    big = base.astype(np.int64) + 2**24 + 1
    with pytest.warns(UserWarning, match="by at most 1"):
        OctreeVolume.from_array(big)


def test_progress_callback():
    calls = []
    OctreeVolume.from_array(np.zeros((5, 5, 5)), progress=lambda f, m: calls.append(f))
    assert calls and calls[-1] == 1.0 and calls == sorted(calls)


# ----------------------------------------------------------------- errors, missing data


@pytest.mark.parametrize(
    "data, kwargs, error",
    [
        (np.zeros((0, 3, 3)), {}, ValueError),
        (np.zeros((3, 3)), {}, ValueError),
        (np.zeros((2, 2, 2, 2)), {}, ValueError),
        (np.zeros((2, 2, 2), np.complex64), {}, TypeError),
        (np.array([[["a"]]]), {}, TypeError),
        (np.zeros((2, 2, 2)), {"spacing": 0.0}, ValueError),
        (np.zeros((2, 2, 2)), {"spacing": (1.0, -1.0, 1.0)}, ValueError),
        (np.zeros((2, 2, 2)), {"spacing": np.inf}, ValueError),
        (np.zeros((2, 2, 2)), {"iso_range": (2.0, 1.0)}, ValueError),
        (np.zeros((2, 2, 2)), {"variance": -1.0}, ValueError),
    ],
)
def test_bad_input_raises(data, kwargs, error):
    with pytest.raises(error):
        OctreeVolume.from_array(data, **kwargs)


def test_non_finite_voxels_mark_missing_cells():
    rng = np.random.default_rng(14)
    data = rng.standard_normal((9, 6, 5)).astype(np.float32)
    data[2, 3, 1] = np.nan
    data[7, 0, 4] = np.inf
    data[:4, 4:, :] = np.nan  # a whole NaN region may consolidate into a NaN leaf
    vol = OctreeVolume.from_array(data)
    got = np.asarray(jit_lookup(vol, all_voxels(data.shape)))
    np.testing.assert_array_equal(got, data)  # NaN == NaN here; inf kept
    np.testing.assert_array_equal(vol.to_array(), data)
    check_ranges(vol, data)
    tight = OctreeVolume.from_array(data, multires=False)
    assert check_ranges(tight, data) > 0
    lo, hi = child_range(vol, 0, 0)  # the root child holding the NaN: still finite range
    assert np.isfinite(float(lo)) and np.isfinite(float(hi))
