"""`extend`: soundness on composite functions, recursion into calls, errors, no retrace."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference64
from boxes import assert_encloses

import jaxiso as ji
from jaxiso import aa, ia
from jaxiso.arith import Affine, Interval

ARITH = ["interval", "affine"]


def as_iv(x):
    return aa.to_interval(x) if isinstance(x, Affine) else x


def random_boxes(lo, hi, n, rng, point_fraction=0.1):
    """[n] boxes per axis inside the domain: sizes from 2^-12 to the whole domain."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = (hi - lo) * 2.0 ** -rng.uniform(0, 12, size=(n, 1))
    start = lo + rng.uniform(0, 1, size=(n, 3)) * (hi - lo - size)
    size = np.where(rng.uniform(size=(n, 1)) < point_fraction, 0.0, size)
    blo = start.astype(np.float32)
    bhi = np.maximum((start + size).astype(np.float32), blo)
    return blo, bhi


def points_in(blo, bhi, k, rng):
    t = rng.uniform(0, 1, size=blo.shape[:1] + (k, 3))
    t[:, 0], t[:, 1] = 0.0, 1.0  # two corners
    p = blo[:, None, :] + t * (bhi - blo)[:, None, :]
    return np.clip(p.astype(np.float32), blo[:, None, :], bhi[:, None, :])


def enclose(f, arithmetic, rounding, blo, bhi, **kw):
    F = ji.extend(f, arithmetic, rounding)
    boxes = [Interval(jnp.asarray(blo[:, i]), jnp.asarray(bhi[:, i])) for i in range(3)]
    return as_iv(jax.jit(lambda *b: F(*b, **kw))(*boxes))


def assert_fast_sound(f, arithmetic, blo, bhi, enc, pts, what):
    """Fast mode is sound up to float rounding, and the float32 point program rounds
    differently too (XLA contracts a*b+c into FMAs; transcendentals differ by an ulp
    between fused and unfused code): allow exactly the rounding budget that outward mode
    computes for the same box (its extra width on each side), nothing more."""
    vals = jax.jit(jax.vmap(jax.vmap(lambda p: f(p[0], p[1], p[2]))))(pts)
    out = enclose(f, arithmetic, "outward", blo, bhi)
    lo, hi = np.asarray(enc.lo, np.float64), np.asarray(enc.hi, np.float64)
    # each side's widening counts from 0: outward padding can change which of a
    # selection's joins is kept, and a tighter outward side is no budget to take away
    with np.errstate(invalid="ignore"):
        budget = np.nan_to_num(np.maximum(np.asarray(out.hi, np.float64) - hi, 0.0)
                               + np.maximum(lo - np.asarray(out.lo, np.float64), 0.0),
                               nan=0.0)
    assert_encloses(lo - budget, hi + budget, vals, what)


@pytest.mark.parametrize("rounding", ["fast", "outward"])
@pytest.mark.parametrize("arithmetic", ARITH)
@pytest.mark.parametrize("name", ji.surfaces.names())
def test_catalogue_soundness(name, arithmetic, rounding):
    """Points in each box evaluate inside the enclosure: float32 evaluation of the same
    program for "fast", the independent float64 reference for "outward"."""
    s = ji.surfaces.get(name)
    rng = np.random.default_rng(abs(hash((name, arithmetic, rounding))) % 2**32)
    blo, bhi = random_boxes(s.lo, s.hi, 256, rng)
    f = lambda x, y, z: s.f(x, y, z, s.w)
    enc = enclose(f, arithmetic, rounding, blo, bhi)
    pts = points_in(blo, bhi, 12, rng)
    if rounding == "fast":
        assert_fast_sound(f, arithmetic, blo, bhi, enc, pts, f"{name}/{arithmetic}/fast")
    else:
        p64 = pts.astype(np.float64)
        vals = reference64.SURFACES[name](p64[..., 0], p64[..., 1], p64[..., 2], s.w)
        assert_encloses(enc.lo, enc.hi, vals, f"{name}/{arithmetic}/outward")


@jax.jit
def _helper(v):  # a jit-decorated helper inside the user's function
    return v * v - 0.25


@jax.custom_vjp
def _cv(v):
    return jnp.sin(v) * 2.0


_cv.defvjp(lambda v: (_cv(v), v), lambda v, g: (2.0 * jnp.cos(v) * g,))

TRICKY = {
    "norm": lambda x, y, z: jnp.linalg.norm(jnp.stack([x, y, z])) - 1.0,
    "hypot": lambda x, y, z: jnp.hypot(x, y) - z,
    "relu": lambda x, y, z: jax.nn.relu(x) - jax.nn.relu(-y) + z,
    "p0": lambda x, y, z: jnp.stack([x, y, z])[0] ** 2 - jnp.stack([x, y, z])[2],
    "jit_helper": lambda x, y, z: _helper(x) + _helper(y) * z,
    "custom_vjp": lambda x, y, z: _cv(x) + y,
    "softplus": lambda x, y, z: jax.nn.softplus(x) - y,
    "where": lambda x, y, z: jnp.where(x > 0, jnp.sqrt(jnp.abs(x)), y * z),
    "cond": lambda x, y, z: jax.lax.cond(x > y, lambda: x - y, lambda: z * z),
    "matmul": lambda x, y, z: (jnp.array([[1.0, -2.0, 0.5], [0.0, 1.0, 3.0]])
                               @ jnp.stack([x, y, z]))[1] - x,
    "minmax": lambda x, y, z: jnp.maximum(x, y) - jnp.minimum(y, z) + jnp.clip(z, -0.5, 0.5),
    "trig": lambda x, y, z: jnp.sin(3 * x) * jnp.cos(y) + jnp.tanh(z) + jnp.arctan(x * y),
    "div": lambda x, y, z: x / (y * y + 0.5) - jnp.exp(z) + jnp.log(z * z + 1.0),
    "fmod_floor": lambda x, y, z: jnp.fmod(x * 3.0, 1.0) + jnp.floor(y) + jnp.sign(z),
    "powers": lambda x, y, z: jnp.abs(x) ** 2.5 + jnp.cbrt(y) + z**-2,
    "gather_reduce": lambda x, y, z: (jnp.stack([x, y, z])[jnp.array([0, 2])].sum()
                                      + jnp.max(jnp.stack([x, y * y, z]))
                                      - jnp.min(jnp.concatenate([jnp.stack([x]),
                                                                 jnp.stack([y, z])]))),
    "dynamic_index": lambda x, y, z: jnp.stack([x, y, z])[jnp.array(1)] * x,
}


@pytest.mark.parametrize("arithmetic", ARITH)
@pytest.mark.parametrize("name", sorted(TRICKY))
def test_library_functions_sound(name, arithmetic):
    f = TRICKY[name]
    rng = np.random.default_rng(7)
    blo, bhi = random_boxes((-2.0,) * 3, (2.0,) * 3, 256, rng, point_fraction=0.2)
    enc = enclose(f, arithmetic, "fast", blo, bhi)
    pts = points_in(blo, bhi, 16, rng)
    assert_fast_sound(f, arithmetic, blo, bhi, enc, pts, f"{name}/{arithmetic}")


def test_norm_and_hypot_are_tight_through_the_origin():
    box = ji.interval(-1.0, 1.0)
    out = ji.extend(lambda x, y, z: jnp.linalg.norm(jnp.stack([x, y, z])))(box, box, box)
    assert float(out.lo) == 0.0 and float(out.hi) == pytest.approx(np.sqrt(3.0), rel=1e-6)
    out = ji.extend(lambda x, y, z: jnp.hypot(x, y))(box, box, box)
    assert float(out.lo) == 0.0 and float(out.hi) == pytest.approx(np.sqrt(2.0), rel=1e-6)
    out = ji.extend(lambda x, y, z: jax.nn.relu(x))(box, box, box)
    assert (float(out.lo), float(out.hi)) == (0.0, 1.0)


def test_eager_jit_vmap_agree_and_no_retrace():
    calls = []

    def f(x, y, z):
        calls.append(1)
        return x * x * y - jnp.sin(z)

    for arithmetic in ARITH:
        calls.clear()
        F = ji.extend(f, arithmetic)
        lo = jnp.linspace(-1.0, 1.0, 16)
        X = ji.interval(lo, lo + 0.25)
        eager = as_iv(F(X, X, X))
        again = as_iv(F(X, X, X))
        assert len(calls) == 1, "eager second call re-traced f"
        jitted = jax.jit(F)
        j1 = as_iv(jitted(X, X, X))
        j2 = as_iv(jitted(ji.interval(lo - 0.5, lo), X, X))
        assert len(calls) == 1, "jit re-traced f for new values of the same shape"
        vm = as_iv(jax.vmap(F)(X, X, X))
        for out in (again, j1, vm):
            np.testing.assert_allclose(out.lo, eager.lo, rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(out.hi, eager.hi, rtol=1e-6, atol=1e-6)
        assert not np.allclose(j2.lo, j1.lo)


def test_params_arrays_and_intervals_no_retrace():
    calls = []

    def f(x, y, z, p):
        calls.append(1)
        return (x - p["c"][0]) ** 2 + (y - p["c"][1]) ** 2 + z * z - p["r"] ** 2

    F = jax.jit(ji.extend(f))
    X = ji.interval(jnp.array([-0.1, 0.5]), jnp.array([0.1, 0.7]))
    a = F(X, X, X, params={"c": jnp.array([0.0, 0.0]), "r": jnp.float32(1.0)})
    b = F(X, X, X, params={"c": jnp.array([1.0, 1.0]), "r": jnp.float32(0.5)})
    assert len(calls) == 1
    assert ia.contains(a, 0.0).tolist() == [False, True]
    assert float(b.hi[0]) < 0 or float(b.lo[0]) > 0
    r = ji.interval(0.9, 1.1)   # an uncertain radius widens the enclosure
    F2 = ji.extend(f)
    c = F2(X, X, X, params={"c": jnp.array([0.0, 0.0]), "r": r})
    assert float(c.lo[0]) < float(a.lo[0]) and float(c.hi[0]) > float(a.hi[0])


def test_w_coordinate_and_points():
    f = lambda x, y, z, w: x + y + z + w
    out = ji.extend(f)(ji.interval(0.0, 1.0), 2.0, ji.interval(0.0, 1.0), 0.5)
    assert (float(out.lo), float(out.hi)) == (2.5, 4.5)


def test_unsupported_primitive_error_and_register_rule():
    f = lambda x, y, z: jax.lax.erf_inv(x)
    box = ji.interval(-0.5, 0.5)
    with pytest.raises(NotImplementedError, match="erf_inv.*register_rule"):
        ji.extend(f)(box, box, box)
    ji.register_rule("erf_inv", ia.monotone_on(jax.lax.erf_inv, -1.0, 1.0), "both")
    try:
        out = ji.extend(f)(box, box, box)
        assert float(out.lo) == pytest.approx(float(jax.lax.erf_inv(-0.5)))
    finally:
        from jaxiso.arith import _extend
        for table in _extend._RULES.values():
            table.pop("erf_inv", None)


def test_loops_give_clear_error():
    f = lambda x, y, z: jax.lax.fori_loop(0, jnp.int32(x > 0) + 2, lambda i, v: v * x, y)
    box = ji.interval(0.5, 1.0)
    with pytest.raises(NotImplementedError, match="loop"):
        ji.extend(f)(box, box, box)


def test_bad_inputs():
    f = lambda x, y, z: x + y + z
    ok = ji.interval(0.0, 1.0)
    with pytest.raises(ValueError, match="lo <= hi"):
        ji.extend(f)(Interval(jnp.float32(1.0), jnp.float32(0.0)), ok, ok)
    with pytest.raises(ValueError, match="NaN"):
        ji.extend(f)(Interval(jnp.float32(jnp.nan), jnp.float32(0.0)), ok, ok)
    with pytest.raises(ValueError, match="scalar"):
        ji.extend(lambda x, y, z: jnp.stack([x, y]))(ok, ok, ok)
    with pytest.raises(ValueError, match="one scalar"):
        ji.extend(lambda x, y, z: (x, y))(ok, ok, ok)
    with pytest.raises(ValueError, match="arithmetic"):
        ji.extend(f, "taylor")
    with pytest.raises(ValueError, match="rounding"):
        ji.extend(f, rounding="up")


def test_inequality_function_is_three_valued():
    inside = lambda x, y, z: x * x + y * y + z * z < 1.0
    F = ji.extend(inside)
    out = F(ji.interval(jnp.array([0.0, 0.9, 2.0]), jnp.array([0.1, 1.1, 3.0])),
            ji.interval(0.0, 0.1), ji.interval(0.0, 0.1))
    assert out.lo.tolist() == [True, False, False]
    assert out.hi.tolist() == [True, True, False]


def test_division_asymptote_is_unbounded_not_a_finite_hit():
    F = ji.extend(lambda x, y, z: 1.0 / x - y)
    out = F(ji.interval(-0.1, 0.1), ji.interval(0.0, 1.0), 0.0)
    assert float(out.lo) == -np.inf and float(out.hi) == np.inf


def test_outward_widens_and_encloses_exact_constants():
    f = lambda x, y, z: x * 0.1 + y * 0.1 + z * 0.1  # 0.1 is inexact in float32
    box = ji.interval(jnp.float32(0.3), jnp.float32(0.3))
    fast = ji.extend(f)(box, box, box)
    out = ji.extend(f, rounding="outward")(box, box, box)
    assert float(out.lo) < float(fast.lo) <= float(fast.hi) < float(out.hi)
    exact = 3 * float(np.float32(0.3)) * float(np.float32(0.1))
    assert float(out.lo) <= exact <= float(out.hi)


def test_affine_inputs_and_symbols():
    t = Affine(jnp.float32(0.5), jnp.array([0.5]), jnp.float32(0.0))  # t in [0, 1]
    x = 1.0 - 2.0 * t
    y = 3.0 * t
    F = ji.extend(lambda x, y, z: x + 2.0 * y / 3.0, "affine")
    out = F(x, y, 0.0)        # = 1 exactly: correlation through the shared symbol
    iv = aa.to_interval(out)
    assert float(iv.lo) == pytest.approx(1.0) and float(iv.hi) == pytest.approx(1.0)
    box = ji.interval(0.0, 1.0)
    G = ji.extend(lambda x, y, z: x - y, "affine")
    assert float(aa.to_interval(G(box, box, box)).hi) == pytest.approx(1.0)
    G1 = ji.extend(lambda x, y, z: x - x, "affine")
    assert float(aa.to_interval(G1(box, box, box)).hi) == 0.0


def test_review_regressions_cancelling_sums_ints_casts_switch_inf_power():
    """Cases found in review: each failed (unsound or crashed) before its fix."""
    from jax import lax

    one = ji.interval(1.0, 1.0)
    # outward rounding of a sum/dot scales with the terms, not the cancelled result
    f = lambda x: jnp.sum(jnp.stack([jnp.float32(1e8), x, jnp.float32(-1e8)]))
    g = lambda x: jnp.dot(jnp.stack([jnp.float32(1e8), x, jnp.float32(1e8)]),
                          jnp.array([1.0, 1.0, -1.0]))
    for fn in (f, g):
        for arithmetic in ARITH:
            out = as_iv(ji.extend(fn, arithmetic, "outward")(one))
            assert float(out.lo) <= 1.0 <= float(out.hi), (fn, arithmetic)
    # integer division truncates; integer remainder works
    q = ji.extend(lambda x: lax.div(x.astype(jnp.int32), 2).astype(jnp.float32))(
        ji.interval(7.0, 7.5))
    assert (float(q.lo), float(q.hi)) == (3.0, 3.0)
    r = ji.extend(lambda x: (x.astype(jnp.int32) % 3).astype(jnp.float32))(
        ji.interval(6.0, 7.5))
    assert float(r.lo) <= 0.0 and float(r.hi) >= 1.0
    # a precision-changing cast of an affine form is enclosed as a whole
    c = as_iv(ji.extend(lambda x: x.astype(jnp.bfloat16).astype(jnp.float32), "affine",
                        "outward")(ji.interval(1.0025, 1.0045)))
    assert float(c.lo) <= 1.0 and float(c.hi) >= 1.0078125
    rp = ji.extend(lambda x: lax.reduce_precision(x, exponent_bits=8, mantissa_bits=7))(
        ji.interval(1.0025, 1.0045))
    assert float(rp.hi) >= 1.0078125
    # lax.switch on a box-dependent integer index in affine mode
    sw = lambda x: lax.switch(jnp.floor(x).astype(jnp.int32),
                              [lambda v: v, lambda v: 2 * v, lambda v: -v], x)
    out = as_iv(ji.extend(sw, "affine")(ji.interval(1.25, 1.75)))
    assert float(out.lo) <= 2.5 and float(out.hi) >= 3.5
    # infinite / NaN exponents do not crash
    for p in (jnp.inf, jnp.nan):
        for arithmetic in ARITH:
            ji.extend(lambda x: x**p, arithmetic)(ji.interval(0.5, 2.0))


def test_atan2_encloses_sampled_angles_and_handles_the_branch_cut():
    rng = np.random.default_rng(7)
    F = ji.extend(lambda x, y: jnp.arctan2(y, x))
    G = ji.extend(lambda x, y: jnp.arctan2(y, x), "affine")
    c = rng.uniform(-2, 2, (400, 2))
    h = 10 ** rng.uniform(-3, 0.3, (400, 2))
    X = ji.interval(c[:, 0] - h[:, 0], c[:, 0] + h[:, 0])
    Y = ji.interval(c[:, 1] - h[:, 1], c[:, 1] + h[:, 1])
    for r in (F(X, Y), ji.aa.to_interval(G(X, Y))):
        u = rng.uniform(size=(400, 300))
        xs = (c[:, :1] - h[:, :1]) + 2 * h[:, :1] * u
        ys = (c[:, 1:] - h[:, 1:]) + 2 * h[:, 1:] * rng.uniform(size=(400, 300))
        v = np.arctan2(ys, xs)
        assert np.all(v.min(1) >= np.asarray(r.lo) - 1e-6)
        assert np.all(v.max(1) <= np.asarray(r.hi) + 1e-6)
    # a box across the negative x axis spans the cut: [-pi, pi]; away from it, tight
    cut = F(ji.interval(-2.0, -1.0), ji.interval(-0.1, 0.1))
    np.testing.assert_allclose([float(cut.lo), float(cut.hi)], [-np.pi, np.pi], rtol=1e-6)
    q = F(ji.interval(1.0, 2.0), ji.interval(1.0, 2.0))
    np.testing.assert_allclose([float(q.lo), float(q.hi)],
                               [np.arctan2(1, 2), np.arctan2(2, 1)], rtol=1e-6)


def test_repeated_subexpressions_are_extended_once():
    """A polynomial that writes x**3 in every term extends it once (the affine program
    of ten repeats is as long as that of one plus nine adds), and the repeats stay one
    value: x**3 - x**3 encloses exactly 0 in affine arithmetic."""
    import jax
    import jax.numpy as jnp

    from jaxiso.arith import Interval, aa, extend

    def one(x, y, z):
        return x**3 * y

    def ten(x, y, z):
        r = x**3 * y
        for _ in range(9):
            r = r + x**3 * y
        return r

    box = [aa.from_interval(Interval(jnp.full(4, 0.1), jnp.full(4, 0.3)), i, 3)
           for i in range(3)]
    n_one = len(jax.make_jaxpr(extend(one, "affine"))(*box).jaxpr.eqns)
    n_add = len(jax.make_jaxpr(extend(lambda x, y, z: x + y, "affine"))(*box).jaxpr.eqns) - \
        len(jax.make_jaxpr(extend(lambda x, y, z: x, "affine"))(*box).jaxpr.eqns)
    n_ten = len(jax.make_jaxpr(extend(ten, "affine"))(*box).jaxpr.eqns)
    assert n_ten <= n_one + 9 * n_add
    d = extend(lambda x, y, z: x**3 - x**3, "affine")(*box)
    r = jnp.sum(jnp.abs(d.dev), axis=-1) + d.err
    assert float(jnp.max(jnp.abs(d.center))) == 0.0 and float(jnp.max(r)) == 0.0


@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
def test_constant_factors_and_divisors_enclose(arithmetic):
    """A concrete coefficient scales each end (`ia.static_factor`): sound with outward
    rounding for either sign, tiny and huge constants, on the left or right, against
    float64 points of each box (the ends included)."""
    rng = np.random.default_rng(0)
    lo = rng.uniform(-3, 3, 400).astype(np.float32)
    hi = lo + rng.uniform(0, 2, 400).astype(np.float32)
    t = rng.uniform(0, 1, (40, 400))
    t[0], t[1] = 0.0, 1.0
    pts = lo.astype(np.float64) + t * (hi.astype(np.float64) - lo.astype(np.float64))
    for k in (0.3, -0.3, 3, -7, 1e-30, -1e30, 2.0**-20, np.float32(1.5)):
        for fn in (lambda a: a * k, lambda a: a / k, lambda a: k * a):
            r = ji.extend(fn, arithmetic, rounding="outward")(
                Interval(jnp.asarray(lo), jnp.asarray(hi)))
            r = aa.to_interval(r) if arithmetic == "affine" else r
            v = fn(pts)
            assert np.all(v >= np.asarray(r.lo, np.float64)), k
            assert np.all(v <= np.asarray(r.hi, np.float64)), k
    # mixed signs in an array constant, an empty box, 0 * inf
    a = Interval(jnp.asarray([-1.0, 2.0, 0.0]), jnp.asarray([1.0, 3.0, 1.0]))
    r = ia.mul(a, np.array([0.5, -2.0, 4.0], np.float32))
    np.testing.assert_array_equal(np.asarray(r.lo), [-0.5, -6.0, 0.0])
    np.testing.assert_array_equal(np.asarray(r.hi), [0.5, -4.0, 4.0])
    r = ia.mul(Interval(jnp.asarray([0.0, -jnp.inf, jnp.nan]),
                        jnp.asarray([0.0, 1.0, jnp.nan])), 0.5)
    assert np.asarray(r.lo)[:2].tolist() == [0.0, -np.inf] and np.isnan(np.asarray(r.lo)[2])
