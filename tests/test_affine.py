"""Reduced affine arithmetic (AF1): Eq. 6.15 by hand, conversions, correlation, rules."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji
from jaxiso import aa, ia
from jaxiso.arith import Affine


def form(c, devs, err=0.0):
    return Affine(jnp.float32(c), jnp.asarray(devs, jnp.float32), jnp.float32(err))


def test_conversions_eq_6_8_and_6_9():
    x = aa.from_interval(ia.interval(1.0, 3.0), symbol=1, n=3)
    assert float(x.center) == 2.0 and x.dev.tolist() == [0.0, 1.0, 0.0]
    assert float(x.err) == 0.0
    back = aa.to_interval(x)
    assert (float(back.lo), float(back.hi)) == (1.0, 3.0)
    e = aa.from_interval(ia.interval(-1.0, 1.0), symbol=None, n=2)
    assert e.dev.tolist() == [0.0, 0.0] and float(e.err) == 1.0
    u = aa.from_interval(ia.interval(0.0, jnp.inf), symbol=0, n=1)
    assert float(u.err) == jnp.inf and u.dev.tolist() == [0.0]
    with pytest.raises(ValueError):
        aa.from_interval(ia.interval(0.0, 1.0), symbol=3, n=3)


def test_mul_is_eq_6_15():
    # x = 2 + 1 e1 + 0.5 e3(err), y = -1 + 0.25 e1 + 1 e2 + 0.25 err
    x = form(2.0, [1.0, 0.0], 0.5)
    y = form(-1.0, [0.25, 1.0], 0.25)
    p = aa.mul(x, y)
    assert float(p.center) == -2.0                                  # x0 y0
    assert p.dev.tolist() == [2.0 * 0.25 + (-1.0) * 1.0, 2.0 * 1.0]  # x0 y_i + y0 x_i
    # |x0| y_err + |y0| x_err + rad(x) rad(y) = 2*.25 + 1*.5 + 1.5*1.5
    assert float(p.err) == pytest.approx(0.5 + 0.5 + 2.25)


def test_affine_ops_exact_and_correlated():
    x = form(1.0, [0.5, 0.0])
    y = form(0.0, [0.0, 2.0])
    s = aa.sub(aa.add(x, y), y)         # (x + y) - y == x exactly
    assert float(s.center) == 1.0 and s.dev.tolist() == [0.5, 0.0]
    assert float(s.err) == 0.0
    assert float(aa.to_interval(aa.sub(x, x)).hi) == 0.0
    k = aa.mul(3.0, x)
    assert float(k.center) == 3.0 and k.dev.tolist() == [1.5, 0.0]


def test_square_is_tighter_than_self_product():
    x = form(0.0, [1.0])
    sq = aa.to_interval(aa.square(x))
    pr = aa.to_interval(aa.mul(x, form(0.0, [1.0])))
    assert float(sq.lo) >= -0.5 and float(sq.hi) == 1.0
    assert float(sq.hi - sq.lo) < float(pr.hi - pr.lo)


NONLINEAR = {
    "exp": (aa.exp, jnp.exp, (-2.0, 1.5)), "log": (aa.log, jnp.log, (0.1, 4.0)),
    "sqrt": (aa.sqrt, jnp.sqrt, (0.0, 4.0)), "recip+": (aa.recip, lambda v: 1 / v, (0.5, 3.0)),
    "recip-": (aa.recip, lambda v: 1 / v, (-3.0, -0.5)),
    "ipow4": (lambda v: aa.ipow(v, 4), lambda v: v**4, (-1.0, 2.0)),
    "ipow3": (lambda v: aa.ipow(v, 3), lambda v: v**3, (-1.0, 2.0)),
    "ipow5+": (lambda v: aa.ipow(v, 5), lambda v: v**5, (0.5, 2.0)),
    "pow2.5": (lambda v: aa.pow(v, 2.5), lambda v: v**2.5, (0.0, 2.0)),
    "pow0.3": (lambda v: aa.pow(v, 0.3), lambda v: v**0.3, (0.1, 2.0)),
    "cosh": (aa.cosh, jnp.cosh, (-1.0, 2.0)), "sinh": (aa.sinh, jnp.sinh, (-1.0, 2.0)),
    "tanh": (aa.tanh, jnp.tanh, (-1.0, 2.0)), "atan": (aa.atan, jnp.arctan, (-3.0, 1.0)),
    "cbrt": (aa.cbrt, jnp.cbrt, (-1.0, 8.0)), "abs": (aa.abs, jnp.abs, (-1.0, 3.0)),
    "logistic": (aa.logistic, jax.nn.sigmoid, (-3.0, 1.0)),
    "erf": (aa.erf, jax.scipy.special.erf, (-0.5, 2.0)),
    "sin": (aa.sin, jnp.sin, (-1.0, 3.0)), "cos": (aa.cos, jnp.cos, (-1.0, 3.0)),
    "max": (lambda v: aa.maximum(v, 0.5), lambda v: jnp.maximum(v, 0.5), (-1.0, 2.0)),
    "min": (lambda v: aa.minimum(v, 0.5), lambda v: jnp.minimum(v, 0.5), (-1.0, 2.0)),
}


@pytest.mark.parametrize("name", sorted(NONLINEAR))
def test_nonlinear_rules_enclose_along_the_symbol(name):
    """g(x(e)) for e in [-1, 1] lies inside the affine result evaluated at the same e
    (a stronger property than interval inclusion: the correlation is right too)."""
    fn, point, (lo, hi) = NONLINEAR[name]
    x = aa.from_interval(ia.interval(lo, hi), symbol=0, n=1)
    out = jax.jit(fn)(x)
    e = np.linspace(-1.0, 1.0, 2001, dtype=np.float32)
    xs = np.float32(x.center) + np.float32(x.dev[0]) * e
    vals = np.asarray(jax.jit(point)(xs), np.float64)
    line = float(out.center) + float(out.dev[0]) * e.astype(np.float64)
    slack = float(out.err) + 4e-7 * (np.abs(vals) + 1e-30)
    finite = np.isfinite(vals)
    assert (np.abs(vals - line)[finite] <= slack[finite]).all(), name
    # and it is a real linearisation, not just the interval: error below the range width
    rng = np.nanmax(vals[finite]) - np.nanmin(vals[finite])
    if name not in ("sin", "cos"):     # these fall back to Interval by design
        assert float(out.err) < 0.75 * rng + 1e-6, name


_ERF64 = np.vectorize(math.erf)
# float64 references written apart from the rules: (rule, g, g', inflection value)
INFLECTED = {
    "tanh": (aa.tanh, np.tanh, lambda v: 1.0 / np.cosh(v) ** 2),
    "atan": (aa.atan, np.arctan, lambda v: 1.0 / (1.0 + v * v)),
    "logistic": (aa.logistic, lambda v: 1.0 / (1.0 + np.exp(-v)),
                 lambda v: np.exp(-np.abs(v)) / (1.0 + np.exp(-np.abs(v))) ** 2),
    "erf": (aa.erf, _ERF64, lambda v: 2.0 / math.sqrt(math.pi) * np.exp(-v * v)),
    "sinh": (aa.sinh, np.sinh, np.cosh),
    "cbrt": (aa.cbrt, np.cbrt, lambda v: 1.0 / (3.0 * np.cbrt(v * v))),
}


def _random_ranges(rng, k):
    """k ranges (lo, hi) of every kind: straddling 0, one-sided, narrow, wide, points."""
    centre = rng.uniform(-4.0, 4.0, k) * rng.choice([1.0, 0.1, 0.0], k, p=[0.7, 0.2, 0.1])
    radius = 10.0 ** rng.uniform(-5.0, 0.8, k)
    radius[rng.random(k) < 0.05] = 0.0
    return (centre - radius).astype(np.float32), (centre + radius).astype(np.float32)


@pytest.mark.parametrize("name", sorted(INFLECTED))
def test_inflected_rules_enclose_and_beat_min_range(name):
    """Over 400 random ranges each: the form encloses g along its symbol (float64 g on
    1,001 points of each range), and its error is never above min-range's (the least
    derivative's slope, computed here in float64) by more than rounding, and below half
    of it on ranges that straddle 0 and reach where g bends."""
    rule, g, dg = INFLECTED[name]
    rng = np.random.default_rng(11)
    lo, hi = _random_ranges(rng, 400)
    if name == "sinh":  # float32 sinh overflows past 89
        lo, hi = np.clip(lo, -20, 20), np.clip(hi, -20, 20)
    x = aa.from_interval(ia.Interval(jnp.asarray(lo), jnp.asarray(hi)), symbol=0, n=1)
    out = jax.jit(rule)(x)
    c, d, err = (np.asarray(v, np.float64) for v in (out.center, out.dev[:, 0], out.err))
    e = np.linspace(-1.0, 1.0, 1001)
    xc, xd = np.asarray(x.center, np.float64), np.asarray(x.dev[:, 0], np.float64)
    xs = xc[:, None] + xd[:, None] * e           # the points of each range, float64
    vals = g(xs)
    line = c[:, None] + d[:, None] * e
    slack = err[:, None] + 1e-6 * (np.abs(vals) + 1e-30)
    assert (np.abs(vals - line) <= slack).all(), name
    assert (np.asarray(out.lo) <= vals.min(axis=1) + 1e-6).all()
    assert (np.asarray(out.hi) >= vals.max(axis=1) - 1e-6).all()
    # min-range in float64: slope g'(v) at the range's largest |v| (sinh: smallest)
    a, b = xs[:, 0], xs[:, -1]
    mag = np.maximum(np.abs(a), np.abs(b))
    mig = np.where((a <= 0) & (b >= 0), 0.0, np.minimum(np.abs(a), np.abs(b)))
    alpha = dg(mig) if name == "sinh" else dg(mag)
    ends = np.stack([g(a) - alpha * a, g(b) - alpha * b])
    min_range = 0.5 * (ends.max(0) - ends.min(0))
    ok = np.isfinite(min_range) & (hi > lo)
    # both pad their bounds by a few float32 ulps of the magnitudes involved
    rounding = 1e-5 * (np.abs(g(a)) + np.abs(g(b)) + np.abs(alpha) * (np.abs(a) + np.abs(b)))
    assert (err[ok] <= min_range[ok] + rounding[ok] + 1e-6).all(), name
    bends = ok & (a < 0) & (b > 0) & (hi - lo > 1.0) & (hi - lo < 6.0)
    if name not in ("sinh", "cbrt"):  # their bends are at the ends / at 0
        assert bends.sum() > 20
        assert np.median(err[bends] / min_range[bends]) < 0.5, name


def test_sigmoid_networks_keep_their_correlation():
    """A 3-layer sigmoid network on a small box: the form's width is a small multiple of
    the true range (the interval rule lost the correlation: many times wider)."""
    rng = np.random.default_rng(3)
    A1, A2 = rng.normal(size=(3, 16)), rng.normal(size=(16, 16)) / 4
    a3 = rng.normal(size=16) / 4

    def net(x, y, z):
        h = jax.nn.sigmoid(jnp.stack([x, y, z]) @ A1)
        return jax.nn.sigmoid(h @ A2) @ a3

    box = [ia.interval(0.2, 0.3), ia.interval(-0.1, 0.0), ia.interval(0.4, 0.5)]
    r = ji.extend(net, "affine")(*box)
    r_iv = ji.extend(net, "interval")(*box)
    g = np.stack(np.meshgrid(*[np.linspace(b.lo, b.hi, 21) for b in box]), -1).reshape(-1, 3)
    vals = np.asarray(jax.vmap(lambda p: net(*p))(jnp.asarray(g, jnp.float32)), np.float64)
    lo, hi = float(aa.to_interval(r).lo), float(aa.to_interval(r).hi)
    assert lo <= vals.min() and vals.max() <= hi
    true = vals.max() - vals.min()
    assert hi - lo < 1.5 * true
    assert float(r_iv.hi - r_iv.lo) > 3 * (hi - lo)


def test_where_keeps_branch_exactly_when_certain():
    x = form(1.0, [0.5])
    c = aa.gt(x, 0.0)                       # certainly true on [0.5, 1.5]
    out = aa.where(c, aa.mul(2.0, x), form(-9.0, [0.0]))
    assert out.dev.tolist() == [1.0] and float(out.center) == 2.0
    u = aa.where(aa.gt(x, 1.0), x, form(-9.0, [0.0]))   # unknown: hull of both
    iv = aa.to_interval(u)
    assert float(iv.lo) <= -9.0 and float(iv.hi) >= 1.5


def test_empty_propagates_in_affine():
    e = aa.sqrt(form(-5.0, [1.0]))           # wholly negative: empty
    assert np.isnan(float(e.err)) and np.isnan(float(aa.to_interval(e).lo))
    for op in (lambda v: aa.mul(v, form(1.0, [1.0])), aa.square, aa.exp,
               lambda v: aa.add(v, 1.0), lambda v: aa.mul(v, 0.0),
               lambda v: aa.mul(v, form(0.0, [0.0])), lambda v: aa.sub(v, v)):
        out = aa.to_interval(op(e))
        assert np.isnan(float(out.lo)) and np.isnan(float(out.hi))
    # an overflowed centre with a finite error term is the entire line, not empty
    big = form(3e38, [3e38])
    s = aa.to_interval(aa.add(big, big))
    assert float(s.hi) == np.inf


def test_constant_shift_moves_the_centre_only():
    """x + c and x - c for a constant c (a network's bias): exact in the centre, the
    deviations and error unchanged, broadcast to c's shape; a NaN constant gives the empty
    form (NaN error term), as `as_affine` makes it."""
    x = form(1.0, [0.5], 0.25)
    b = jnp.asarray([1.0, -2.0, 0.5], jnp.float32)
    for out, sign in ((aa.add(x, b), 1.0), (aa.add(b, x), 1.0), (aa.sub(x, b), -1.0)):
        assert out.center.tolist() == (1.0 + sign * np.asarray(b)).tolist()
        assert out.dev.shape == (3, 1) and out.dev[:, 0].tolist() == [0.5] * 3
        assert out.err.tolist() == [0.25] * 3
    empty = aa.to_interval(aa.add(x, jnp.asarray([0.0, jnp.nan], jnp.float32)))
    assert float(empty.lo[0]) == 0.25 and np.isnan(float(empty.lo[1]))
    assert np.isnan(float(empty.hi[1]))


def test_overflowed_point_stays_a_point_not_the_whole_line():
    # x^500 overflows float32 to [inf, inf] beyond |x| ~ 1.19: in affine form that must
    # stay +inf (a box that cannot hold a root), not centre 0 with infinite error
    iv = aa.to_interval(aa.from_interval(ji.interval(jnp.inf, jnp.inf), 0, 1))
    assert float(iv.lo) == np.inf and float(iv.hi) == np.inf
    F = ji.extend(lambda x, y, z: x**500 + 0.5 * jnp.abs(y) ** 35 + 0.5 * z**4 - 1.0, "affine")
    r = aa.to_interval(F(ji.interval(1.3, 1.4), ji.interval(-0.1, 0.1), ji.interval(0.0, 0.2)))
    assert not bool(ia.contains(r, 0.0))


@pytest.mark.parametrize("lhs_shape, rhs_shape, dims", [
    ((3, 4), (4, 5), (((1,), (0,)), ((), ()))),
    ((2, 3, 4), (2, 4, 5), (((2,), (1,)), ((0,), (0,)))),
    ((2, 6, 3), (3, 2, 7), (((2,), (0,)), ((0,), (1,)))),
    ((5, 4, 3), (3, 4), (((1, 2), (1, 0)), ((), ())))])
def test_dot_defined_flags_as_a_reduction(lhs_shape, rhs_shape, dims):
    """An output entry of a dot with a box operand is defined when every box entry it
    sums is: the reduction equals the count of undefined entries by a second dot (the
    former rule), box on either side, with batch and several contracting axes."""
    from jax import lax

    from jaxiso.arith._array_rules import _all_defined
    rng = np.random.default_rng(0)
    for box_is_lhs in (True, False):
        box_shape, const_shape = (lhs_shape, rhs_shape) if box_is_lhs else (rhs_shape,
                                                                            lhs_shape)
        defined = rng.random(box_shape) > 0.15
        undefined = (~defined).astype(np.float32)
        ones = np.ones(const_shape, np.float32)
        count = (lax.dot_general(undefined, ones, dims) if box_is_lhs
                 else lax.dot_general(ones, undefined, dims))
        got = _all_defined(jnp.asarray(defined), box_is_lhs, box_shape, const_shape, dims)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(count) == 0)


def test_relu_of_an_interval_and_broadcast_zero():
    """max(x, 0) with x an Interval (lifted to the error term) and a zero of a larger
    shape: the relu rule, broadcast to the zero's shape."""
    out = aa.maximum(ji.interval(-1.0, 2.0), jnp.zeros(3))
    iv = aa.to_interval(out)
    assert iv.lo.shape == (3,) and out.dev.shape == (3, 1)
    assert np.all(np.asarray(iv.lo) <= 0.0) and np.all(np.asarray(iv.hi) >= 2.0)
