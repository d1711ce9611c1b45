"""Hypothesis strategies for batches of boxes and points inside them (shared by tests)."""

import numpy as np
from hypothesis import strategies as st

BATCH = 48           # boxes per hypothesis example (fixed: one jit compile per rule)
POINTS = 24          # sample points per box, endpoints included

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).tiny)

_special = st.sampled_from([0.0, -0.0, 1.0, -1.0, 0.5, -2.0, 1e-30, -1e-30, 1e-3, 3.0,
                            1e30, -1e30, 3.14159, 1.5707964, -4.712389, np.inf, -np.inf])
_moderate = st.floats(-8.0, 8.0, width=32, allow_subnormal=False)
_any = st.floats(width=32, allow_nan=False, allow_subnormal=False)
endpoint = st.one_of(_moderate, _moderate, _special, _any)


@st.composite
def box(draw, tiny_ok=True):
    """(lo, hi) with lo <= hi: straddling 0, tiny, huge and infinite boxes."""
    kind = draw(st.sampled_from(["two", "two", "tiny", "point"]))
    a = draw(endpoint)
    if kind == "point" and np.isfinite(a):
        return a, a
    if kind == "tiny" and np.isfinite(a) and abs(a) >= 1e-30:
        b = float(np.nextafter(np.float32(a), np.float32(np.inf), dtype=np.float32))
        b = float(np.nextafter(np.float32(b), np.float32(np.inf), dtype=np.float32))
        return (a, b) if np.isfinite(b) else (a, a)
    b = draw(endpoint)
    lo, hi = min(a, b), max(a, b)
    if lo == np.inf or hi == -np.inf:   # {+inf} / {-inf} are not sets of reals
        return -1.0, 1.0
    return lo, hi


def boxes(n=BATCH):
    return st.lists(box(), min_size=n, max_size=n).map(
        lambda bs: (np.array([b[0] for b in bs], np.float32),
                    np.array([b[1] for b in bs], np.float32)))


def sample_points(lo, hi, rng, k=POINTS):
    """[n, k] float32 points inside each [lo, hi]: endpoints, 0 and the extremes of
    trig functions where inside, uniform samples of the finite part."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    flo = np.clip(lo, -F32_MAX, F32_MAX)
    fhi = np.clip(hi, -F32_MAX, F32_MAX)
    t = rng.uniform(0.0, 1.0, size=lo.shape + (k,))
    pts = flo[:, None] + t * (fhi - flo)[:, None]
    # log-spread samples reach both tiny and huge magnitudes in wide boxes
    mags = np.exp(rng.uniform(-20, 40, size=lo.shape + (k,)))
    signs = np.where(rng.uniform(size=lo.shape + (k,)) < 0.5, -1.0, 1.0)
    spread = signs * mags
    use_spread = rng.uniform(size=lo.shape + (k,)) < 0.3
    pts = np.where(use_spread & (spread >= flo[:, None]) & (spread <= fhi[:, None]), spread, pts)
    pts[:, 0], pts[:, 1] = flo, fhi
    special = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2, 1.0, -1.0])
    for j, s in enumerate(special):
        inside = (lo <= s) & (s <= hi)
        pts[:, 2 + j] = np.where(inside, s, pts[:, 2 + j])
    pts = pts.astype(np.float32)
    # XLA on CPU flushes subnormals to zero; points are kept normal (or 0)
    pts = np.where(np.abs(pts) < F32_TINY, np.float32(0.0), pts)
    # rounding to float32 may step outside; clamp back onto the box
    return np.clip(pts, lo.astype(np.float32)[:, None], hi.astype(np.float32)[:, None])


def assert_encloses(lo, hi, values, what, ulps=0.0):
    """Every non-NaN value (per box row) must lie in [lo, hi], allowing `ulps` float32
    ulps of the value (0 = none): the rounding budget of a fast-mode rule whose point
    function is not correctly rounded (XLA's transcendentals)."""
    lo = np.asarray(lo, np.float64)[:, None]
    hi = np.asarray(hi, np.float64)[:, None]
    v = np.asarray(values, np.float64)
    with np.errstate(invalid="ignore"):
        slack = np.where(np.isfinite(v), ulps * (np.abs(v) * 2.0**-23 + F32_TINY), 0.0)
    with np.errstate(invalid="ignore"):
        ok = np.isnan(v) | ((lo <= v + slack) & (v - slack <= hi))
    # At a pole (x/0) IEEE picks +-inf by the sign bit of the zero; an unbounded
    # enclosure stands for the pole whichever sign the point evaluation took.
    ok |= np.isinf(v) & (np.isinf(lo) | np.isinf(hi))
    if not ok.all():
        i, j = np.argwhere(~ok)[0]
        raise AssertionError(
            f"{what}: {int((~ok).sum())} violations; e.g. box row {i}: value {v[i, j]!r} "
            f"not in [{lo[i, 0]!r}, {hi[i, 0]!r}]")


def sized_boxes_and_points(rng, n, k, max_halvings):
    """n float32 boxes in [-1, 1]^3 of edge 2^-u, u uniform in [0, max_halvings], and k
    float64 points in each (its two corners first): (lo [3, n], hi [3, n], pts [n, k, 3])."""
    size = 2.0 ** -rng.uniform(0, max_halvings, size=n)
    lo = rng.uniform(-1, 1, size=(3, n)) * (1 - size)
    lo, hi = lo.astype(np.float32), (lo + size).astype(np.float32)
    t = rng.uniform(size=(n, k, 3))
    t[:, 0], t[:, 1] = 0.0, 1.0
    pts = lo.T[:, None].astype(np.float64) + t * (hi - lo).T[:, None].astype(np.float64)
    return lo, hi, pts
