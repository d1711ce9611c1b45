"""Sign grids: enclosures of f on the cells of a regular grid over the scene's box, built
once at construction, so that each ray walks only the part of its segment that passes
near a cell where a level can lie (the min/max idea of the seed's volume octrees, Ch. 3,
for functions: the cells' ranges come from the arithmetic, not from samples).

The cells' enclosures are affine forms with three box symbols and fresh noise symbols for
the error terms of the network's nonlinearities (`extend(fresh_symbols=)`): on the
networks of bench_neural, AF1 alone leaves 49-56% of a 64^3 grid possible, the fresh
symbols 1.9-2.3% (fox, hammer; sampled true ranges: 1.7%); bunny's elu layers take 24
symbols each, a relu's 8 (`_extend._SMOOTH_SHARE`): 4.8% (8 each: 14.5%; sampled: 3.0%).
The grid is refined level by level from 16^3, only below cells that hold one of the
scene's isovalues; the others keep their parent's enclosure, so the grid stays sound for
any isovalue (a slider), only looser away from the ones it was built for.
benchmarks/NOTES.md, sessions 12 and 16.
"""

from __future__ import annotations

import hashlib
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from .._core import pytree_dataclass
from ..arith import Interval, aa, extend
from ._memo import BoundedCache
from ._progress import Progress

FIRST_LEVEL = 16
RESOLUTION = 64
FRESH_SYMBOLS = 256  # a cap: the forms carry what the operations take (`extend`)
FRESH_PER_OP = 8
MAX_BOXES = 2**17  # cells tested per level at most (bunny at level 64: ~100k)
BATCH = 4096
SPACING = 0.9  # samples along a ray per cell edge, at least 1 / SPACING (see `segment_span`)
# refining stops when more than this share of a level's cells may hold an isovalue, or
# once a build has taken BUDGET_S (an elu network written with `where` kept 96% of 32^3
# cells possible and took 2 minutes to build: issue 28)
MOSTLY_POSSIBLE = 0.5
BUDGET_S = 30.0
PAD_ULPS = 8.0  # the cells' enclosures are widened by this many ulps of their magnitude


@pytree_dataclass
class SignGrid:
    """Enclosures of f on the cells of the box [lo, hi] cut into [Nx, Ny, Nz] cells.

    Attributes:
      low: [Nx, Ny, Nz] float32 lower bounds of f on each (closed) cell.
      high: [Nx, Ny, Nz] float32 upper bounds (inf / NaN where f may be undefined).
    """

    low: jax.Array
    high: jax.Array

    # the cells' arithmetic: extend(g, "affine", n_symbols=3, fresh_symbols=FRESH_SYMBOLS,
    # fresh_per_op=FRESH_PER_OP) on each cell's box
    FRESH_SYMBOLS: typing.ClassVar[int] = FRESH_SYMBOLS
    FRESH_PER_OP: typing.ClassVar[int] = FRESH_PER_OP

    @property
    def resolution(self) -> tuple:
        return tuple(np.shape(self.low))


_BOUNDS = BoundedCache("compiled sign grid enclosures", 4)  # each holds compiled code


def _box_bounds(g, rounding, key=None):
    """The jitted enclosure of g on boxes; `key` (naming g) reuses it for a rebuild
    (replace(params=...))."""
    return _BOUNDS.get(None if key is None else (key, rounding),
                       lambda: _compile_bounds(g, rounding))


def _compile_bounds(g, rounding):
    F = extend(g, "affine", rounding, n_symbols=3, fresh_symbols=FRESH_SYMBOLS,
               fresh_per_op=FRESH_PER_OP)

    @jax.jit
    def bounds(lo, hi, w, params):
        """Enclosures of g on the boxes [lo, hi] ([B, 3] each): (low [B], high [B])."""
        boxes = [Interval(lo[:, i], hi[:, i]) for i in range(3)]
        r = aa.to_interval(F(*boxes, w, params=params))
        bad = ~r.defined | jnp.isnan(r.lo) | jnp.isnan(r.hi)
        return jnp.where(bad, -jnp.inf, r.lo), jnp.where(bad, jnp.inf, r.hi)

    return bounds


def _possible(low, high, isovalues):
    iso = isovalues.reshape((-1,) + (1,) * low.ndim)
    return np.any((low <= iso) & (iso <= high), axis=0)


def build_sign_grid(g, lo, hi, w, params, isovalues, rounding="fast",
                    resolution=RESOLUTION, max_boxes=MAX_BOXES, key=None,
                    budget_s=BUDGET_S):
    """The sign grid of ``g(x, y, z, w, params)`` on the box [lo, hi] (concrete values);
    `key` (hashable, naming g) keeps the compiled enclosure for the next build.

    Refined level by level from FIRST_LEVEL^3 up to `resolution`^3; refining stops
    early when the next level would test more than `max_boxes` cells, when more than
    MOSTLY_POSSIBLE of the cells may hold an isovalue (a finer grid would prune little)
    or when the build has taken `budget_s` seconds. Returns (SignGrid, report):
    `resolution`^3 cells holding the finest level's enclosures, and a line saying what
    was built, how long it took and why it stopped."""
    progress = Progress()
    bounds = _box_bounds(g, rounding, key)
    box = (np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    iso = np.asarray(isovalues, np.float32)
    n, tested = FIRST_LEVEL, 0
    low = np.full((1, 1, 1), -np.inf, np.float32)
    high = np.full((1, 1, 1), np.inf, np.float32)
    todo = np.ones((n,) * 3, bool)
    while True:
        low, high = _refine(bounds, box, n, todo, low, high, w, params)
        tested += int(np.count_nonzero(todo))
        progress.say(f"sign grid: {n}^3 level, {tested:,} cells tested")
        possible = _possible(low, high, iso) | ~np.isfinite(low) | ~np.isfinite(high)
        why = _stop(n, resolution, possible, max_boxes, progress.elapsed, budget_s)
        if why is not None:
            break
        n *= 2
        todo = np.repeat(np.repeat(np.repeat(possible, 2, 0), 2, 1), 2, 2)
    share = float(np.mean(_possible(low, high, iso)))
    # always `resolution`^3 cells: a rebuild (replace(params=...)) keeps the shape, so the
    # compiled intersect is reused
    low, high = _upsample(low, resolution), _upsample(high, resolution)
    pad = PAD_ULPS * np.spacing(np.maximum(np.abs(low), np.abs(high)).astype(np.float32))
    grid = SignGrid(jnp.asarray(low - pad), jnp.asarray(high + pad))
    report = (f"sign grid {n}^3: {share:.1%} of the cells may hold the isovalues "
              f"({tested:,} cells tested, {progress.elapsed:.1f} s{why})")
    progress.done(report)
    return grid, report


def _refine(bounds, box, n, todo, low, high, w, params):
    """The enclosures (low, high) upsampled to n^3 cells, those marked in `todo`
    [n, n, n] evaluated on their own boxes."""
    low, high = _upsample(low, n), _upsample(high, n)
    cells = np.argwhere(todo)
    edge = (box[1] - box[0]) / n
    a = (box[0] + cells * edge).astype(np.float32)
    b = (box[0] + (cells + 1) * edge).astype(np.float32)
    low[tuple(cells.T)], high[tuple(cells.T)] = _evaluate(bounds, a, b, w, params)
    return low, high


def _stop(n, resolution, possible, max_boxes, elapsed, budget_s):
    """Why refining stops after the level of n^3 cells (a report suffix; "" at full
    resolution), or None to go on."""
    if 2 * n > resolution:
        return ""
    if 8 * int(np.count_nonzero(possible)) > max_boxes:
        return f"; stopped: {max_boxes:,} cells per level at most"
    if np.mean(possible) > MOSTLY_POSSIBLE:
        return f"; stopped: most cells possible at {n}^3, a finer grid prunes little"
    if elapsed >= budget_s:
        return f"; stopped: time budget {budget_s:.0f} s"
    return None


def _upsample(a, n):
    k = n // a.shape[0]
    return np.repeat(np.repeat(np.repeat(a, k, 0), k, 1), k, 2)


def _evaluate(bounds, a, b, w, params):
    """bounds on the boxes [a, b] in batches of BATCH (one compiled shape)."""
    lows, highs = [], []
    for s in range(0, len(a), BATCH):
        m = min(BATCH, len(a) - s)
        pa = np.zeros((BATCH, 3), np.float32)
        pb = np.zeros((BATCH, 3), np.float32)
        pa[:m], pb[:m] = a[s:s + m], b[s:s + m]
        cl, ch = bounds(pa, pb, w, params)
        lows.append(np.asarray(cl)[:m])
        highs.append(np.asarray(ch)[:m])
    return np.concatenate(lows), np.concatenate(highs)


class Span(typing.NamedTuple):
    """Where along each ray segment ``p + D s`` (s in [0, 1]) its first level crossing
    can lie, from a sign grid (`segment_span`).

    s0, s1: [P] the crossing, if any, lies in [s0, s1].
    inside: [P] bool, False where no stretch of the segment meets a possible cell.
    marks: [P, W] uint32 bits over the K - 1 gaps between the segment's K even samples
      (gap i: s in [i, i + 1] / (K - 1)): set where the gap may hold a crossing (a cell
      it passes may hold an isovalue), clear where it holds none (`free_from`).
    """

    s0: jax.Array
    s1: jax.Array
    inside: jax.Array
    marks: jax.Array


def samples_per_segment(grid: SignGrid) -> int:
    """K = ceil(N / SPACING) + 1 samples (N the grid's largest dimension)."""
    return math.ceil(max(grid.resolution) / SPACING) + 1


def segment_span(grid: SignGrid, lo, hi, isovalues, p, D, inside) -> Span:
    """The part of each ray segment ``p + D s``, s in [0, 1], that holds its first level
    crossing, if any, and the gaps between samples where it may lie.

    Samples every segment at K = ceil(N / SPACING) + 1 even steps (N the grid's largest
    dimension): a segment inside the box moves at most (hi - lo)_i along axis i, so
    consecutive samples are less than a cell apart on every axis. The stretch between
    two samples lies in the box they span, so in the cells between theirs, at most two
    per axis: the gap holds no crossing unless one of the 2 x 2 x 2 cells from the
    lower corner of theirs on is possible (one lookup in a table of such blocks). The
    span runs from the first such gap to the last, or ends earlier at a sample in a cell
    surely on the other side of every isovalue than the segment's start (f - iso changed
    sign before it). Rays with no such gap are no longer inside."""
    shape = np.array(np.shape(grid.low))
    iso = jnp.reshape(isovalues, (-1, 1, 1, 1))
    possible = (jnp.any((grid.low <= iso) & (iso <= grid.high), axis=0)
                | ~jnp.isfinite(grid.low) | ~jnp.isfinite(grid.high))
    block = jax.lax.reduce_window(jnp.pad(possible, ((0, 1), (0, 1), (0, 1))), False,
                                  jax.lax.bitwise_or, (2, 2, 2), (1, 1, 1), "VALID")
    # +1: surely above every isovalue, -1: surely below (NaN bounds compare False: 0)
    side = (jnp.all(grid.low > iso, axis=0).astype(jnp.int32)
            - jnp.all(grid.high < iso, axis=0).astype(jnp.int32))
    k = samples_per_segment(grid)
    cell = (hi - lo) / jnp.asarray(shape, jnp.float32)
    limit = jnp.asarray(shape - 1, jnp.int32)

    def sample(i):
        """The cell index [P, 3] of sample i."""
        x = p + D * (i / (k - 1))
        return jnp.clip(jnp.floor((x - lo) / cell).astype(jnp.int32), 0, limit)

    def at(table, ijk):
        return table[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    cell0 = sample(0)
    start = at(side, cell0)
    words = -(-(k - 1) // 32)

    def step(i, carry):
        first, last, other, prev, marks = carry
        ijk = sample(i)
        # gap i - 1, between samples i - 1 and i
        gap = i - 1
        may = inside & at(block, jnp.minimum(prev, ijk))
        bit = jnp.where(may, jnp.uint32(1) << (gap % 32).astype(jnp.uint32), jnp.uint32(0))
        marks = marks.at[:, gap // 32].set(marks[:, gap // 32] | bit)
        crossed = (start != 0) & (at(side, ijk) == -start) & (other < 0)
        return (jnp.where(may & (first < 0), gap, first), jnp.where(may, gap, last),
                jnp.where(crossed, i, other), ijk, marks)

    none = jnp.full(inside.shape, -1, jnp.int32)
    marks = jnp.zeros(inside.shape + (words,), jnp.uint32)
    first, last, other, _, marks = jax.lax.fori_loop(1, k, step,
                                                     (none, none, none, cell0, marks))
    ds = 1.0 / (k - 1)
    # the gap after `other` too: its cell index may be a rounding off the point's
    s1 = jnp.where(other >= 0, jnp.minimum(last + 1, other + 1), last + 1) * ds
    return Span(jnp.clip(first * ds, 0.0, 1.0), jnp.clip(s1, 0.0, 1.0),
                inside & (first >= 0), marks)


def free_from(marks, u):
    """The sample coordinate (s (K - 1)) where the first gap that may hold a crossing
    starts, at or after the gap holding u ([...] float, sample coordinates; marks
    [..., W] from `segment_span`): a value <= u when u's own gap may; inf when no gap
    after u may. Elementwise over the leading axes."""
    words = marks.shape[-1]
    i0 = jnp.clip(jnp.floor(u), 0, 32 * words).astype(jnp.int32)
    w = jnp.arange(words, dtype=jnp.int32)
    # clear the bits of the gaps before i0 in every word
    below = jnp.clip(i0[..., None] - 32 * w, 0, 32)
    keep = jnp.where(below >= 32, jnp.uint32(0),
                     ~jnp.uint32(0) << jnp.minimum(below, 31).astype(jnp.uint32))
    m = marks & keep
    tz = jax.lax.population_count((m & (~m + jnp.uint32(1))) - jnp.uint32(1))
    gap = jnp.where(m != 0, 32 * w + tz.astype(jnp.int32), 2**30)
    first = jnp.min(gap, axis=-1)
    return jnp.where(first < 2**30, first.astype(jnp.float32), jnp.inf)


def values_key(*trees) -> str:
    """A digest of the arrays in `trees` (grid cache key)."""
    h = hashlib.sha1()
    for x in jax.tree_util.tree_leaves(trees):
        a = np.asarray(x)
        h.update(str((a.shape, a.dtype)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()
