"""A ``where``'s cases evaluated where they are taken (`jaxiso.arith._branches`), and the
bounds an affine form carries besides itself (`Affine.lo`, `Affine.hi`).

Generated families: activations spelled with ``jnp.where`` against a constant next to
the library rule, networks of several depths and widths, random boxes; soundness against
float64 evaluation of the same spelling at sample points.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from boxes import assert_encloses, sized_boxes_and_points

import jaxiso as ji
from jaxiso import aa
from jaxiso.arith import Interval, _branches
from jaxiso.arith._extend import _call_body

# activation: (spelled with where, the library rule (or a where-free spelling), numpy)
ACTIVATIONS = {
    "elu": (lambda h: jnp.where(h > 0, h, jnp.exp(jnp.minimum(h, 0.0)) - 1.0),
            jax.nn.elu,
            lambda h: np.where(h > 0, h, np.exp(np.minimum(h, 0.0)) - 1.0)),
    "leaky_relu": (lambda h: jnp.where(h > 0, h, 0.01 * h), jax.nn.leaky_relu,
                   lambda h: np.where(h > 0, h, 0.01 * h)),
    "softsign_where": (lambda h: jnp.where(h < 0, h / (1.0 - h), h / (1.0 + h)),
                       jax.nn.soft_sign, lambda h: h / (1.0 + np.abs(h))),
    "relu_where": (lambda h: jnp.where(h > 0, h, 0.0), jax.nn.relu,
                   lambda h: np.where(h > 0, h, 0.0)),
    "clamp_where": (lambda h: jnp.where(h > 0.5, 0.5, jnp.where(h < -0.5, -0.5, h)),
                    lambda h: jnp.clip(h, -0.5, 0.5), lambda h: np.clip(h, -0.5, 0.5)),
    "huber": (lambda h: jnp.where(jnp.abs(h) < 1.0, 0.5 * h * h, jnp.abs(h) - 0.5),
              lambda h: jnp.where(jnp.abs(h) < 1.0, 0.5 * h * h, jnp.abs(h) - 0.5),
              lambda h: np.where(np.abs(h) < 1.0, 0.5 * h * h, np.abs(h) - 0.5)),
}


def _layers(seed, depth, width):
    rng = np.random.default_rng(seed)
    dims = [3] + [width] * depth + [1]
    return [(rng.normal(size=(a, b)).astype(np.float32) * np.float32(np.sqrt(2.0 / a)),
             (rng.normal(size=b) * 0.1).astype(np.float32)) for a, b in zip(dims[:-1], dims[1:])]


def _net(act, layers, xp=jnp):
    def f(x, y, z):
        h = xp.stack([x, y, z])
        for i, (A, b) in enumerate(layers):
            h = (act(h) if i else h) @ A + b
        return h[0]
    return f


def _boxes(seed, n, size):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-1.0, 1.0 - size, size=(3, n)).astype(np.float32)
    return [Interval(jnp.asarray(lo[i]), jnp.asarray(lo[i] + np.float32(size)))
            for i in range(3)]


def _median_width(f, arithmetic, boxes):
    out = jax.jit(ji.extend(f, arithmetic))(*boxes)
    out = aa.to_interval(out) if arithmetic == "affine" else out
    return float(np.median(np.asarray(out.hi - out.lo, np.float64)))


@pytest.mark.parametrize("depth,width", [(2, 16), (4, 8)])
def test_where_spelled_elu_is_as_tight_as_jax_nn_elu_in_interval(depth, width):
    """Interval: each case sees only its side of h, so the where spelling gives the
    library rule's enclosure (the hull of both cases over all of h reached down to h's
    lower end: 3.4-35x wider at depth 2-8 before)."""
    layers = _layers(1, depth, width)
    spelled, library, _ = ACTIVATIONS["elu"]
    boxes = _boxes(2, 64, 0.1)
    w_spelled = _median_width(_net(spelled, layers), "interval", boxes)
    w_library = _median_width(_net(library, layers), "interval", boxes)
    assert w_spelled <= 1.001 * w_library, (w_spelled, w_library)


def test_where_spelled_elu_stays_finite_in_affine_on_a_deep_network():
    """Affine: ``min(h, 0)``'s form reaches above 0 by up to ``-lo hi / (hi - lo)``, and
    ``exp`` of it overflowed on a deep network (every enclosure infinite at 8 x 32);
    its bound (<= 0) and the case evaluated on ``h <= 0`` keep it finite and within a
    small factor of ``jax.nn.elu``'s rule."""
    layers = _layers(3, 8, 32)
    spelled, library, _ = ACTIVATIONS["elu"]
    boxes = _boxes(4, 32, 0.03)
    w_spelled = _median_width(_net(spelled, layers), "affine", boxes)
    w_library = _median_width(_net(library, layers), "affine", boxes)
    assert np.isfinite(w_spelled) and w_spelled <= 2.0 * w_library, (w_spelled, w_library)


@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
@pytest.mark.parametrize("name", sorted(ACTIVATIONS))
def test_where_spellings_are_sound_against_float64(name, arithmetic):
    """Every spelling, random boxes of many sizes, the same spelling in float64 at
    sample points (corners included)."""
    spelled, _, numpy_act = ACTIVATIONS[name]
    layers = _layers(5, 3, 8)
    lo, hi, pts = sized_boxes_and_points(np.random.default_rng(6), 48, 16, 8)
    boxes = [Interval(jnp.asarray(lo[i]), jnp.asarray(hi[i])) for i in range(3)]
    out = jax.jit(ji.extend(_net(spelled, layers), arithmetic, "outward"))(*boxes)
    out = aa.to_interval(out) if arithmetic == "affine" else out
    layers64 = [(A.astype(np.float64), b.astype(np.float64)) for A, b in layers]
    f64 = _net(numpy_act, layers64, xp=np)
    vals = np.array([[f64(*p) for p in row] for row in pts])
    assert_encloses(out.lo, out.hi, vals, f"{name}/{arithmetic}")


def test_exp_of_a_bounded_minimum_does_not_overflow():
    """A form over [-1000, 1000]: ``min(h, 0)``'s form reaches 500 above 0; its bound
    keeps ``exp`` over the values (<= 0), so the result is finite and within [0, 1]."""
    h = aa.from_interval(ji.interval(-1000.0, 1000.0), 0, 1)
    m = aa.minimum(h, 0.0)
    assert float(aa.to_interval(dataclass_free(m)).hi) > 400.0  # the form alone
    out = aa.to_interval(aa.exp(m))
    assert np.isfinite(float(out.hi)) and float(out.lo) >= 0.0 and float(out.hi) <= 1.0 + 1e-5


def dataclass_free(x):
    """The same form without its bounds."""
    return aa.Affine(x.center, x.dev, x.err, x.defined)


def test_plan_finds_jnp_where_and_leaves_long_cases():
    """`jnp.where` (a call to ``_where``) on a comparison with a constant is planned;
    a case longer than MAX_SLICE equations is left as it is."""
    def short(x):
        return jnp.where(x > 0.5, x, jnp.exp(x) - 1.0)

    def long(x):
        y = x
        for _ in range(_branches.MAX_SLICE + 1):
            y = jnp.sin(y)
        return jnp.where(x > 0.5, x, y)


    for fn, n_slice in ((short, 2), (long, None)):
        jaxpr = jax.make_jaxpr(fn)(1.0).jaxpr
        plan = _branches.plan(jaxpr, _call_body)
        (sel,) = plan.selections.values()
        lengths = {c.taken_when: len(c.slice) for c in sel.cases}
        assert lengths.get(True) == 0  # the compared value itself: clipped, nothing run
        assert lengths.get(False) == n_slice


@pytest.mark.parametrize("depth,width", [(4, 16), (6, 8)])
def test_where_spelled_elu_is_as_tight_as_jax_nn_with_fresh_symbols(depth, width):
    """The sign grid's arithmetic (affine, fresh noise symbols for the activations'
    errors): a where-spelled elu is one smooth activation there, as `jax.nn.elu` is,
    not three operations (min, exp, select) each taking symbols from the budget (an
    8 x 32 net's grid at 16^3 was 86.5% possible against jax.nn's 11.0%; median width
    8.8 against 0.30)."""
    layers = _layers(7, depth, width)
    spelled, library, _ = ACTIVATIONS["elu"]
    boxes = _boxes(8, 64, 0.15)

    def width_of(act):
        F = ji.extend(_net(act, layers), "affine", n_symbols=3, fresh_symbols=96,
                      fresh_per_op=4)
        out = aa.to_interval(jax.jit(F)(*boxes))
        return float(np.median(np.asarray(out.hi - out.lo, np.float64)))

    w_spelled, w_library = width_of(spelled), width_of(library)
    assert w_spelled <= 1.25 * w_library, (w_spelled, w_library)


@pytest.mark.parametrize("name", sorted(ACTIVATIONS))
def test_stand_in_gives_the_full_forms_enclosure(name, monkeypatch):
    """An element-by-element selection of one form h is evaluated on h's one-symbol
    stand-in and mapped back (`_extend._on_stand_in`): the same enclosure as with the
    full forms, up to rounding, with h over many symbols."""
    from jaxiso.arith import _extend
    spelled, _, _ = ACTIVATIONS[name]
    rng = np.random.default_rng(9)
    n, k = 64, 12
    h = aa.Affine(jnp.asarray(rng.normal(size=n), jnp.float32),
                  jnp.asarray(rng.normal(size=(n, k)) * 0.3, jnp.float32),
                  jnp.asarray(rng.uniform(0, 0.05, n), jnp.float32))

    def g(x):
        return spelled(x) - 0.3 * x  # keeps the correlation in view

    with_stand_in = aa.to_interval(ji.extend(g, "affine")(h))
    monkeypatch.setattr(_extend, "_on_stand_in", lambda *a: None)
    full = aa.to_interval(ji.extend(g, "affine")(h))
    scale = 1e-5 * (1.0 + np.abs(np.asarray(full.hi - full.lo)))
    np.testing.assert_array_less(np.abs(np.asarray(with_stand_in.lo - full.lo)), scale)
    np.testing.assert_array_less(np.abs(np.asarray(with_stand_in.hi - full.hi)), scale)


def test_bounds_pass_through_sums_and_constants():
    """A form's bounds survive ``x - c``, ``-x`` and ``x + y`` (so ``min(h, 0)`` of a
    case clipped to ``h <= 0`` is h itself, exactly); a constant is its own bounds."""
    h = aa.from_interval(ji.interval(-2.0, 1.0), 0, 1)
    below = aa.Affine(h.center, h.dev, h.err, h.defined, -jnp.inf, jnp.float32(0.0))
    assert float(aa.sub(below, 0.5).hi) == -0.5
    assert float(aa.neg(below).lo) == 0.0
    assert float(aa.add(below, below).hi) == 0.0
    m = aa.minimum(below, 0.0)
    np.testing.assert_array_equal(np.asarray(m.dev), np.asarray(h.dev))
    assert float(m.err) == 0.0 and float(aa.to_interval(m).hi) <= 0.0
    c = aa.as_affine(jnp.float32(3.0), 1)
    assert float(c.lo) == 3.0 == float(c.hi)


# (written with where, the same with maximum / minimum): the cases are the compared
# operands, on either side, with strict or loose comparisons, constants or forms
EXTREMA = [
    (lambda h, g: jnp.where(h > 0, h, 0.0), lambda h, g: jnp.maximum(h, 0.0)),
    (lambda h, g: jnp.where(h < 0, 0.0, h), lambda h, g: jnp.maximum(h, 0.0)),
    (lambda h, g: jnp.where(0.0 >= h, 0, h), lambda h, g: jnp.maximum(h, 0.0)),
    (lambda h, g: jnp.where(h >= 0.25, h, 0.25), lambda h, g: jnp.maximum(h, 0.25)),
    (lambda h, g: jnp.where(h > 0.5, 0.5, h), lambda h, g: jnp.minimum(h, 0.5)),
    (lambda h, g: jnp.where(h <= g, h, g), lambda h, g: jnp.minimum(h, g)),
    (lambda h, g: jnp.where(g < h, h, g), lambda h, g: jnp.maximum(g, h)),  # max(u, v)
    # u against 0, each case u times a constant: lines through the origin
    (lambda h, g: jax.nn.leaky_relu(h), lambda h, g: jnp.maximum(h, 0.01 * h)),
    (lambda h, g: jnp.where(0 < h, h, 0.2 * h), lambda h, g: jnp.maximum(h, 0.2 * h)),
    (lambda h, g: jnp.where(h > 0, 0.5 * h, 0.0), lambda h, g: jnp.maximum(0.5 * h, 0.0)),
    (lambda h, g: jnp.where(h > 0, h, -h), lambda h, g: jnp.maximum(h, -h)),
    (lambda h, g: jnp.where(h <= 0, 2.0 * h, h), lambda h, g: jnp.minimum(2.0 * h, h)),
]


@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
@pytest.mark.parametrize("k", range(len(EXTREMA)))
def test_a_where_of_its_compared_operands_is_their_max_or_min(k, arithmetic):
    """``where(h > 0, h, 0)`` is relu and ``where(h > c, c, h)`` a clamp: planned as the
    max or min of the compared operands (`_branches.extremum`), they get the max / min
    rule's enclosure exactly, in a network (vectors, the scalar case broadcast inside
    ``_where``) and on scalars; the relu spelled with where ran 8x slower than
    `jnp.maximum` through the default call when it went through the selection rule."""
    spelled, extremum = EXTREMA[k]
    layers = _layers(11, 3, 8)

    def net(act):
        def f(x, y, z):
            h = jnp.stack([x, y, z])
            for i, (A, b) in enumerate(layers):
                h = (act(h, 0.3 * h[::-1]) if i else h) @ A + b
            return h[0]
        return f

    def scalar(act):
        return lambda x, y, z: act(x - 0.3 * y, z * y)

    boxes = _boxes(12, 32, 0.2)
    for make in (net, scalar):
        a = ji.extend(make(spelled), arithmetic)(*boxes)
        b = ji.extend(make(extremum), arithmetic)(*boxes)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_where_of_other_cases_is_no_extremum():
    """Only the compared operands, or lines through the origin compared at 0, make a max
    or min."""
    for fn in [lambda h: jnp.where(h > 0, h, 0.1), lambda h: jnp.where(h > 0.5, h, 0.5 * h),
               lambda h: jnp.where(h > 0, h, h * h), lambda h: jnp.where(h > 0, h, jnp.nan * h),
               lambda h: jnp.where(h > 0, h, 1.0 * h)]:
        jaxpr = jax.make_jaxpr(fn)(jnp.ones(4, jnp.float32)).jaxpr
        sels = list(_branches.plan(jaxpr, _call_body).selections.values())
        assert sels and all(sel.extremum is None for sel in sels)
