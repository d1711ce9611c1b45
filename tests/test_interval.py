"""Interval arithmetic: exact sign tables, soundness (hypothesis), emptiness, logic."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from boxes import assert_encloses, boxes, sample_points
from hypothesis import given

from jaxiso import ia, interval
from jaxiso.arith import Interval

INF = np.inf
N, M, P, Z = (-3.0, -2.0), (-1.0, 2.0), (2.0, 4.0), (0.0, 0.0)
N2 = (-4.0, -2.0)


def iv(a):
    return interval(np.float32(a[0]), np.float32(a[1]))


def ends(x):
    return float(x.lo), float(x.hi)


# Hand-derived products/quotients of the sign classes (negative, mixed, positive, zero).
MUL_TABLE = [
    (P, P, (4, 16)), (P, N, (-12, -4)), (P, M, (-4, 8)), (N, P, (-12, -4)),
    (N, N, (4, 9)), (N, M, (-6, 3)), (M, P, (-4, 8)), (M, N, (-6, 3)), (M, M, (-2, 4)),
    (Z, P, (0, 0)), (Z, M, (0, 0)), (Z, (-INF, INF), (0, 0)), ((0, 2), (1, INF), (0, INF)),
    ((0, 2), (-INF, INF), (-INF, INF)), ((-2, 0), (1, INF), (-INF, 0)),
    ((1, 2), (-INF, -1), (-INF, -1)),
]
DIV_TABLE = [
    (P, P, (0.5, 2)), (P, N2, (-2, -0.5)), (N, P, (-1.5, -0.5)), (M, P, (-0.5, 1)),
    (M, N2, (-1, 0.5)), (N, N2, (0.5, 1.5)), (Z, P, (0, 0)),
    (P, M, (-INF, INF)), (P, (0, 2), (1, INF)), (P, (-2, 0), (-INF, -1)),
    (N, (0, 2), (-INF, -1)), (M, (0, 2), (-INF, INF)), (P, Z, (-INF, INF)),
    ((1, 2), (0, 2), (0.5, INF)),
]


@pytest.mark.parametrize("a,b,expected", MUL_TABLE)
def test_mul_sign_table(a, b, expected):
    assert ends(ia.mul(iv(a), iv(b))) == expected


@pytest.mark.parametrize("a,b,expected", DIV_TABLE)
def test_div_sign_table(a, b, expected):
    assert ends(ia.div(iv(a), iv(b))) == expected


def test_same_object_dependency_rules():
    x = iv(M)
    assert ends(x * x) == (0, 4)            # square, not [-2, 4]
    assert ends(x * iv(M)) == (-2, 4)        # a different variable
    assert ends(x - x) == (0, 0)
    assert ends(ia.ipow(x, 3)) == (-1, 8)
    assert ends(ia.ipow(iv(N), 2)) == (4, 9)
    assert ends(ia.ipow(iv(M), 4)) == (0, 16)
    assert ends(ia.ipow(iv(P), -1)) == (0.25, 0.5)


def test_domain_drop_and_empty():
    s = ia.sqrt(iv((-4.0, 9.0)))
    assert ends(s) == (0, 3) and not bool(s.defined)
    s = ia.sqrt(iv((-4.0, -1.0)))
    assert bool(ia.is_empty(s)) and not bool(ia.contains(s, 0.0))
    lg = ia.log(iv((-1.0, 1.0)))
    assert ends(lg) == (-INF, 0) and not bool(lg.defined)
    p = ia.pow(iv((-1.0, 4.0)), 0.5)
    assert ends(p) == (0, 2) and not bool(p.defined)
    assert bool(ia.is_empty(ia.pow(iv((-3.0, -1.0)), 0.5)))
    assert bool(ia.sqrt(iv((1.0, 4.0))).defined)


def _empty_batch():
    return Interval(jnp.full(3, jnp.nan), jnp.full(3, jnp.nan))


UNARY_RULES = {
    "neg": ia.neg, "abs": ia.abs, "square": ia.square, "sqrt": ia.sqrt, "cbrt": ia.cbrt,
    "exp": ia.exp, "log": ia.log, "sin": ia.sin, "cos": ia.cos, "tan": ia.tan,
    "tanh": ia.tanh, "atan": ia.atan, "sinh": ia.sinh, "cosh": ia.cosh,
    "floor": ia.floor, "sign": ia.sign, "recip": ia.recip,
    "ipow3": lambda x: ia.ipow(x, 3), "ipow4": lambda x: ia.ipow(x, 4),
    "ipow-2": lambda x: ia.ipow(x, -2), "pow0.5": lambda x: ia.pow(x, 0.5),
}
BINARY_RULES = {
    "add": ia.add, "sub": ia.sub, "mul": ia.mul, "div": ia.div, "min": ia.minimum,
    "max": ia.maximum, "fmod": ia.fmod, "pow": ia.pow,
    "clamp": lambda x, y: ia.clamp(-1.0, x, y),
}


@pytest.mark.parametrize("name", sorted(UNARY_RULES))
def test_empty_in_empty_out_unary(name):
    out = UNARY_RULES[name](_empty_batch())
    assert np.isnan(out.lo).all() and np.isnan(out.hi).all()
    assert not ia.contains(out, 0.0).any()


@pytest.mark.parametrize("name", sorted(BINARY_RULES))
def test_empty_in_empty_out_binary(name):
    full = interval(jnp.array([-1.0, 0.0, 2.0]), jnp.array([1.0, 0.0, 3.0]))
    for args in ((_empty_batch(), full), (full, _empty_batch())):
        out = BINARY_RULES[name](*args)
        assert np.isnan(out.lo).all() and np.isnan(out.hi).all(), name


# jnp point functions evaluated on the same float32 points (fast-mode soundness)
POINT_UNARY = {
    "neg": jnp.negative, "abs": jnp.abs, "square": jnp.square, "sqrt": jnp.sqrt,
    "cbrt": jnp.cbrt, "exp": jnp.exp, "log": jnp.log, "sin": jnp.sin, "cos": jnp.cos,
    "tan": jnp.tan, "tanh": jnp.tanh, "atan": jnp.arctan, "sinh": jnp.sinh,
    "cosh": jnp.cosh, "floor": jnp.floor, "sign": jnp.sign, "recip": lambda v: 1.0 / v,
    "ipow3": lambda v: v**3, "ipow4": lambda v: v**4, "ipow-2": lambda v: v**-2,
    "pow0.5": lambda v: jnp.power(v, 0.5),
}
POINT_BINARY = {
    "add": jnp.add, "sub": jnp.subtract, "mul": jnp.multiply, "div": jnp.divide,
    "min": jnp.minimum, "max": jnp.maximum, "fmod": jnp.fmod, "pow": jnp.power,
    "clamp": lambda x, y: jnp.minimum(jnp.maximum(x, -1.0), y),
}


# Fast mode rounds to nearest: XLA's float32 transcendentals are not correctly rounded
# and not always monotone by an ulp, so a point value may sit an ulp or two outside the
# endpoint values. That budget is allowed here; outward mode (test_outward_*) allows none.
FAST_ULPS = {name: 2.0 for name in ("cbrt", "exp", "log", "sin", "cos", "tan", "tanh",
                                    "atan", "sinh", "cosh", "pow0.5")}


@functools.cache
def _jitted(name):
    """(enclosure, point) functions per rule, compiled once for the fixed batch shape."""
    if name in UNARY_RULES:
        rule = UNARY_RULES[name]
        return (jax.jit(lambda a, b: rule(Interval(a, b))), jax.jit(POINT_UNARY[name]))
    rule = BINARY_RULES[name]
    return (jax.jit(lambda a, b, c, d: rule(Interval(a, b), Interval(c, d))),
            jax.jit(POINT_BINARY[name]))


@pytest.mark.parametrize("name", sorted(UNARY_RULES))
@given(bx=boxes())
def test_unary_soundness_fast(name, bx):
    lo, hi = bx
    enclosure, point = _jitted(name)
    enc = enclosure(lo, hi)
    vals = point(sample_points(lo, hi, np.random.default_rng(0)))
    assert_encloses(enc.lo, enc.hi, vals, name, ulps=FAST_ULPS.get(name, 0.0))


@pytest.mark.parametrize("name", sorted(BINARY_RULES))
@given(bx=boxes(), by=boxes())
def test_binary_soundness_fast(name, bx, by):
    (xlo, xhi), (ylo, yhi) = bx, by
    enclosure, point = _jitted(name)
    enc = enclosure(xlo, xhi, ylo, yhi)
    rng = np.random.default_rng(1)
    vals = point(sample_points(xlo, xhi, rng), sample_points(ylo, yhi, rng))
    assert_encloses(enc.lo, enc.hi, vals, name)


def test_three_valued_comparisons_and_where():
    x = iv(M)
    assert ia.is_unknown(x < 0.0) and ia.certainly(x < 3.0) and ia.is_false(x > 2.5)
    assert ia.certainly(x <= 2.0) and ia.is_unknown(x >= 2.0)
    assert ia.is_unknown(ia.eq(x, 0.0)) and ia.certainly(ia.eq(iv(Z), 0.0))
    both = (x < 0.0) & (x < 3.0)
    assert ia.is_unknown(both)
    assert ia.is_false((x > 2.5) & (x < 0.0)) and ia.certainly((x < 3.0) | (x > 9.0))
    assert ia.certainly(~(x > 2.5))
    w = ia.where(x < 0.0, iv((10.0, 11.0)), iv((-5.0, -4.0)))
    assert ends(w) == (-5, 11)                      # unknown: hull of both branches
    assert ends(ia.where(x < 3.0, iv((10.0, 11.0)), iv((-5.0, -4.0)))) == (10, 11)
    assert ends(ia.where(x > 2.5, iv((10.0, 11.0)), iv((-5.0, -4.0)))) == (-5, -4)
    # an undefined (empty) branch that is not taken does not pollute the result
    e = ia.sqrt(iv((-2.0, -1.0)))
    assert ends(ia.where(x < 3.0, iv((1.0, 2.0)), e)) == (1, 2)
    assert ends(ia.where(x < 0.0, iv((1.0, 2.0)), e)) == (1, 2)   # hull ignores empty


def test_trig_extrema_and_poles():
    assert ends(ia.sin(iv((0.0, 3.0)))) == pytest.approx((0.0, 1.0), abs=1e-6)
    assert ends(ia.cos(iv((3.0, 3.5))))[0] == -1.0
    lo, hi = ends(ia.tan(iv((1.5, 1.6))))
    assert lo == -INF and hi == INF
    lo, hi = ends(ia.tan(iv((0.1, 1.5))))
    assert np.isfinite(lo) and np.isfinite(hi)
    assert ends(ia.sin(iv((0.0, 100.0)))) == (-1.0, 1.0)


def test_fmod_cases():
    assert ends(ia.fmod(iv((5.5, 5.75)), 2.0)) == (1.5, 1.75)      # one period: exact
    lo, hi = ends(ia.fmod(iv((1.0, 7.0)), 2.0))
    assert lo == 0.0 and hi == 2.0
    lo, hi = ends(ia.fmod(iv((-7.0, 1.0)), 2.0))
    assert lo == -2.0 and hi == 1.0


def test_interval_constructor_validation():
    with pytest.raises(ValueError, match="lo <= hi"):
        interval(np.array([0.0, 2.0]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="NaN"):
        interval(np.nan, 1.0)
    with pytest.raises(TypeError):
        bool(iv(M) < 0.0)


def test_pytree_jit_vmap_and_widen():
    x = interval(jnp.linspace(-1, 1, 8), jnp.linspace(0, 2, 8))
    leaves = jax.tree_util.tree_leaves(x)
    assert len(leaves) == 3
    f = lambda v: ia.exp(v * v - 1.0)
    eager = f(x)
    jitted = jax.jit(f)(x)
    mapped = jax.vmap(f)(x)
    for out in (jitted, mapped):  # fusion may change exp by an ulp, nothing more
        np.testing.assert_allclose(out.lo, eager.lo, rtol=3e-7)
        np.testing.assert_allclose(out.hi, eager.hi, rtol=3e-7)
    w = ia.widen(eager, 1.0)
    assert (w.lo < eager.lo).all() and (w.hi > eager.hi).all()
    inf_lo = ia.widen(Interval(jnp.float32(jnp.inf), jnp.float32(jnp.inf)))
    assert np.isfinite(inf_lo.lo) and inf_lo.hi == np.inf


# Float64 references of the same operations (numpy), for outward-rounding soundness.
NP_UNARY = {
    "neg": np.negative, "abs": np.abs, "square": np.square, "sqrt": np.sqrt,
    "cbrt": np.cbrt, "exp": np.exp, "log": np.log, "sin": np.sin, "cos": np.cos,
    "tan": np.tan, "tanh": np.tanh, "atan": np.arctan, "sinh": np.sinh, "cosh": np.cosh,
    "floor": np.floor, "sign": np.sign, "recip": lambda v: 1.0 / v,
    "ipow3": lambda v: v**3, "ipow4": lambda v: v**4, "ipow-2": lambda v: v**-2.0,
    "pow0.5": lambda v: np.power(v, 0.5),
}
NP_BINARY = {
    "add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide,
    "min": np.minimum, "max": np.maximum, "fmod": np.fmod, "pow": np.power,
    "clamp": lambda x, y: np.minimum(np.maximum(x, -1.0), y),
}


@functools.cache
def _outward(name, arithmetic):
    """jit(extend(point function, arithmetic, rounding="outward")) for one rule, giving
    an Interval (affine results are converted)."""
    import jaxiso as ji

    def as_iv(out):
        return ji.aa.to_interval(out) if arithmetic == "affine" else out

    if name in POINT_UNARY:
        F = ji.extend(lambda x: POINT_UNARY[name](x), arithmetic, "outward")
        return jax.jit(lambda a, b: as_iv(F(Interval(a, b))))
    F = ji.extend(lambda x, y: POINT_BINARY[name](x, y), arithmetic, "outward")
    return jax.jit(lambda a, b, c, d: as_iv(F(Interval(a, b), Interval(c, d))))


def _np64(fn, *args):
    with np.errstate(all="ignore"):
        return fn(*[np.asarray(a, np.float64) for a in args])


@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
@pytest.mark.parametrize("name", sorted(NP_UNARY))
@given(bx=boxes())
def test_outward_soundness_against_float64_unary(name, arithmetic, bx):
    lo, hi = bx
    enc = _outward(name, arithmetic)(lo, hi)
    vals = _np64(NP_UNARY[name], sample_points(lo, hi, np.random.default_rng(2)))
    assert_encloses(enc.lo, enc.hi, vals, f"outward {arithmetic} {name}")


@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
@pytest.mark.parametrize("name", sorted(NP_BINARY))
@given(bx=boxes(), by=boxes())
def test_outward_soundness_against_float64_binary(name, arithmetic, bx, by):
    (xlo, xhi), (ylo, yhi) = bx, by
    enc = _outward(name, arithmetic)(xlo, xhi, ylo, yhi)
    rng = np.random.default_rng(3)
    vals = _np64(NP_BINARY[name], sample_points(xlo, xhi, rng), sample_points(ylo, yhi, rng))
    assert_encloses(enc.lo, enc.hi, vals, f"outward {arithmetic} {name}")


def test_tanh_encloses_near_saturation_where_xla_tanh_is_not_monotone():
    # XLA's float32 tanh steps down by up to 6 ulps near +-1 (found by
    # test_unary_soundness_fast: [-0.99999976, -0.99999982] on a box near -7.89); every
    # box between neighbouring floats must stay ordered and hold float64 tanh and XLA's
    # own value at both ends
    x = np.linspace(-10.0, 10.0, 400_001).astype(np.float32)
    lo, hi = x[:-1], x[1:]
    enc = jax.jit(lambda a, b: ia.tanh(Interval(a, b)))(lo, hi)
    enc_lo, enc_hi = np.asarray(enc.lo, np.float64), np.asarray(enc.hi, np.float64)
    assert (enc_lo <= enc_hi).all()
    for ends in (lo, hi):
        true = np.tanh(ends.astype(np.float64))
        ours = np.asarray(jax.jit(jnp.tanh)(ends), np.float64)
        for v in (true, ours):
            assert (enc_lo <= v).all() and (v <= enc_hi).all()
    assert enc_lo.min() >= -1.0 and enc_hi.max() <= 1.0
