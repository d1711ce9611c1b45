"""Rules of array-level primitives: data movement, casts, reductions, dot products, and
library functions with a tighter rule than their jaxpr (hypot).

Every rule comes as an interval and an affine variant: `extend` calls the affine one when
some input is an `Affine`. Lifted values have batch shape S (per point of the `vmap`, the
shape of the primitive's operand); the dev of an Affine has a trailing axis [n].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _affine as aa
from . import _interval as ia
from ._affine import Affine
from ._interval import Interval
from ._lift import is_lifted, shape_of


def move_data(prim, params, invals, operands: slice) -> list:
    """Apply a primitive that only moves data (reshape, gather, concatenate, ...) to each
    component of its data operands ``invals[operands]``; the rest (indices) must be
    constants. Returns the list of results (several for optimization_barrier)."""
    data = invals[operands]
    rest = invals[len(data):]
    if any(is_lifted(r) for r in rest):
        raise NotImplementedError(
            f"jaxiso.extend: '{prim.name}' with a box-dependent index is not supported; "
            "indices must not depend on x, y, z (use jnp.where/select instead)")
    def bind(*xs):  # always a list of results
        out = prim.bind(*xs, *rest, **params)
        return list(out) if prim.multiple_results else [out]

    if any(isinstance(d, Affine) for d in data):
        data = aa.lift(*data)
        devs = jax.vmap(bind, in_axes=-1, out_axes=-1)(*[d.dev for d in data])
        return [Affine(*parts) for parts in zip(
            bind(*[d.center for d in data]), devs, bind(*[d.err for d in data]),
            bind(*[d.defined for d in data]), bind(*[d.lo for d in data]),
            bind(*[d.hi for d in data]))]
    data = [ia.as_interval(d) for d in data]
    return [Interval(*parts) for parts in zip(
        bind(*[d.lo for d in data]), bind(*[d.hi for d in data]),
        bind(*[jnp.broadcast_to(d.defined, jnp.shape(d.lo)) for d in data]))]


# ------------------------------------------------------------------------------ casts


def convert_interval(x: Interval, *, new_dtype, **params) -> Interval:
    """Monotone non-decreasing for float->float, bool->number, float->int (truncation)."""
    cast = lambda v: lax.convert_element_type(v, new_dtype)  # noqa: E731
    return Interval(cast(x.lo), cast(x.hi), x.defined)


def convert_affine(x: Affine, *, new_dtype, **params):
    """A precision change rounds centre + sum(dev e) as a whole, not term by term: go
    through the (monotone) interval conversion; a cast to int gives an Interval."""
    if jnp.dtype(new_dtype) == x.center.dtype:
        return x
    out = convert_interval(aa.padded_range(x), new_dtype=new_dtype)
    if jnp.issubdtype(new_dtype, jnp.floating):
        return aa.from_interval(out, None, x.n)
    return out


# ------------------------------------------------------------------------- reductions


def reduce_sum_interval(x: Interval, *, axes, **params) -> Interval:
    axes = tuple(axes)
    return Interval(jnp.sum(x.lo, axes), jnp.sum(x.hi, axes), jnp.all(x.defined, axes))


def reduce_sum_affine(x: Affine, *, axes, **params) -> Affine:
    axes = tuple(axes)
    dev_axes = tuple(a if a >= 0 else a - 1 for a in axes)
    return Affine(jnp.sum(x.center, axes), jnp.sum(x.dev, dev_axes), jnp.sum(x.err, axes),
                  jnp.all(x.defined, axes))


def reduce_monotone(reducer):
    """(interval rule, affine rule) of a reduction monotone in every term (max, min);
    the affine one works on the range (correlation not kept)."""

    def interval_rule(x: Interval, *, axes, **params) -> Interval:
        axes = tuple(axes)
        return Interval(reducer(x.lo, axes), reducer(x.hi, axes), jnp.all(x.defined, axes))

    def affine_rule(x: Affine, *, axes, **params) -> Affine:
        return aa.from_interval(interval_rule(aa.padded_range(x), axes=axes), None, x.n)

    return interval_rule, affine_rule


# ----------------------------------------------------------------------- dot products


def _dot_operands(lhs, rhs, params):
    """(box, const, dot) with ``dot(box, const)`` the primitive in the original order."""
    if is_lifted(lhs) and is_lifted(rhs):
        raise NotImplementedError(
            "jaxiso.extend: dot_general/matmul between two box-dependent operands is not "
            "supported; write the products out elementwise (x * y) instead")
    if is_lifted(lhs):
        return lhs, rhs, lambda b, c: lax.dot_general(b, c, **params)
    return rhs, lhs, lambda b, c: lax.dot_general(c, b, **params)


def _all_defined(defined, box_is_lhs: bool, box_shape, const_shape, dimension_numbers):
    """Each output entry of the dot is defined when every box entry it sums is: `all`
    over the box's contracting axes, laid out as dot_general's output (batch axes, lhs
    free axes, rhs free axes). A reduction, not a second matmul."""
    (lc, rc), (lb, rb) = dimension_numbers
    box_c, box_b = (lc, lb) if box_is_lhs else (rc, rb)
    const_c, const_b = (rc, rb) if box_is_lhs else (lc, lb)
    ok = jnp.broadcast_to(defined, box_shape)
    box_free = [a for a in range(len(box_shape)) if a not in box_c and a not in box_b]
    ok = jnp.all(jnp.transpose(ok, tuple(box_b) + tuple(box_free) + tuple(box_c)),
                 axis=tuple(range(len(box_b) + len(box_free), len(box_shape))))
    const_free = [const_shape[a] for a in range(len(const_shape))
                  if a not in const_c and a not in const_b]
    nb = len(box_b)
    if box_is_lhs:  # (batch, box free, const free)
        ok = ok.reshape(ok.shape + (1,) * len(const_free))
        return jnp.broadcast_to(ok, ok.shape[:nb + len(box_free)] + tuple(const_free))
    # (batch, const free, box free)
    ok = ok.reshape(ok.shape[:nb] + (1,) * len(const_free) + ok.shape[nb:])
    return jnp.broadcast_to(ok, ok.shape[:nb] + tuple(const_free) + ok.shape[nb + len(const_free):])


def _defined_of(lhs, box, const, params):
    return _all_defined(box.defined, is_lifted(lhs), shape_of(box), jnp.shape(const),
                        params["dimension_numbers"])


def dot_interval(lhs, rhs, **params) -> Interval:
    """Dot with one constant operand: exact mid-radius form ``A m +- |A| r``."""
    box, const, dot = _dot_operands(lhs, rhs, params)
    m, r = ia.mid(box), ia.rad(box)
    big = jnp.finfo(m.dtype).max
    center = dot(m, const)
    radius = dot(jnp.minimum(r, big), jnp.abs(const))
    unbounded = dot(jnp.isinf(r).astype(m.dtype), (const != 0).astype(m.dtype)) > 0
    radius = jnp.where(unbounded, jnp.inf, radius)
    return Interval(center - radius, center + radius, _defined_of(lhs, box, const, params))


def dot_affine(lhs, rhs, **params) -> Affine:
    """Dot with one constant operand: linear, so exact on centre and deviations."""
    box, const, dot = _dot_operands(lhs, rhs, params)
    devs = jax.vmap(lambda d: dot(d, const), in_axes=-1, out_axes=-1)(box.dev)
    return Affine(dot(box.center, const), devs, dot(box.err, jnp.abs(const)),
                  _defined_of(lhs, box, const, params))


# ------------------------------------------------------------------ library functions


def hypot_interval(x, y) -> Interval:
    """jnp.hypot guards 0/0 with where(); its plain formula is the tight, sound rule."""
    return ia.sqrt(ia.add(ia.square(ia.as_interval(x)), ia.square(ia.as_interval(y))))


def hypot_affine(x, y) -> Affine:
    x, y = aa.lift(x, y)
    return aa.sqrt(aa.add(aa.square(x), aa.square(y)))


# jnp.floor_divide by a constant float divisor b is the exact floor(a / b) while
# |a / b| < 2^20: fmod is exact, the branch on the remainder's sign is exact, and the
# quotient (a - fmod) / b rounds by far less than 1/2 before the final round.
_FLOORDIV_EXACT = 2.0**20


def floor_divide_interval(a, b):
    """jnp.floor_divide of floats by a constant divisor: monotone in `a` (non-decreasing
    for b > 0, non-increasing for b < 0), so the values at the endpoints where the
    quotient is exact (see `_FLOORDIV_EXACT`); elsewhere floor of the interval quotient
    widened by its rounding. Its jaxpr branches on the sign of fmod(a, b) and takes the
    hull of two steps on a box across a jump. NotImplemented (the body is evaluated)
    for a box-dependent divisor or integers."""
    if is_lifted(b) or not isinstance(a, Interval):
        return NotImplemented
    b = jnp.asarray(b)
    if not (jnp.issubdtype(a.lo.dtype, jnp.floating) and jnp.issubdtype(b.dtype, jnp.floating)):
        return NotImplemented
    b = b.astype(a.lo.dtype)
    fd_lo, fd_hi = jnp.floor_divide(a.lo, b), jnp.floor_divide(a.hi, b)
    exact_lo = jnp.where(b > 0, fd_lo, fd_hi)
    exact_hi = jnp.where(b > 0, fd_hi, fd_lo)
    # loose but sound: floor(a / b) rounded, the rounding of jnp's quotient allowed for
    q = ia.div(a, ia.point(b))
    eps = float(jnp.finfo(a.lo.dtype).eps)
    big = float(jnp.finfo(a.lo.dtype).max)
    # an overflowed quotient end (+inf lower, -inf upper) stands for a finite real beyond
    # the largest float: bound it by that float (inf - inf would be NaN)
    loose_lo = jnp.where(q.lo == jnp.inf, big,
                         jnp.floor(q.lo) - 2.0 - 8.0 * eps * jnp.abs(q.lo))
    loose_hi = jnp.where(q.hi == -jnp.inf, -big,
                         jnp.floor(q.hi) + 1.0 + 8.0 * eps * jnp.abs(q.hi))
    exact = (jnp.isfinite(b) & (b != 0) & (ia.mag(a) < _FLOORDIV_EXACT * jnp.abs(b)))
    lo = jnp.where(exact, exact_lo, loose_lo)
    hi = jnp.where(exact, exact_hi, loose_hi)
    lo, hi = ia.same_nan(lo, hi, a.lo, a.hi, q.lo)
    return ia.make(lo, hi, a, q)


def floor_divide_affine(a, b):
    """`floor_divide_interval` on the range of `a` (correlation not kept)."""
    if is_lifted(b) or not isinstance(a, Affine):
        return floor_divide_interval(a, b) if isinstance(a, Interval) else NotImplemented
    out = floor_divide_interval(aa.padded_range(a), b)
    return NotImplemented if out is NotImplemented else aa.from_interval(out, None, a.n)


def softplus_interval(x):
    """jax.nn.softplus = log(1 + e^x): increasing, so ``[softplus(lo), softplus(hi)]``."""
    if not isinstance(x, Interval):
        return NotImplemented
    return ia.monotone_increasing(jax.nn.softplus)(x)


def softplus_affine(x):
    """jax.nn.softplus: convex with slope sigmoid(x) in (0, 1), so the Chebyshev
    linearisation keeps the form's correlation. Its body, max(x, 0) + log1p(e^-|x|),
    loses it: the cells of a trained 8 x 64 softplus SDF's sign grid were all possible
    (median width 24 on cells 1/8 wide)."""
    if not isinstance(x, Affine):
        return NotImplemented

    def dg_inv(slope):  # logit: the tangent point of a chord's slope
        s = jnp.clip(slope, 1e-30, 1.0 - 2.0**-24)
        return jnp.log(s) - jnp.log1p(-s)

    iv = aa.padded_range(x)
    return aa.chebyshev(x, jax.nn.softplus, jax.nn.sigmoid, dg_inv, True, iv,
                        ia.monotone_increasing(jax.nn.softplus)(iv))


# silu(x) = x sigmoid(x) falls to its minimum -0.2784645... at x = -1.2784645... (where
# 1 + x (1 - sigmoid(x)) = 0) and rises on both sides of it; |silu''| <= 1/2 (its value
# at 0: silu'' = s (1 - s) (2 - x tanh(x / 2)) with s (1 - s) <= 1/4 and the bracket <= 2
# in absolute value where s (1 - s) is not far smaller)
_SILU_ARGMIN = -1.2784645
_SILU_MIN = -0.27846457  # rounded down
_SILU_CURVATURE = 0.5


def _silu_range(iv: Interval) -> Interval:
    """silu on [lo, hi]: the larger end above, the minimum or the smaller end below."""
    a, b = jax.nn.silu(iv.lo), jax.nn.silu(iv.hi)
    inside = (iv.lo <= _SILU_ARGMIN) & (_SILU_ARGMIN <= iv.hi)
    return Interval(jnp.where(inside, _SILU_MIN, jnp.minimum(a, b)), jnp.maximum(a, b),
                    iv.defined)


def silu_interval(x):
    """jax.nn.silu: its range from its one minimum (its body, x * sigmoid(x), multiplies
    two ranges of x as if unrelated)."""
    if not isinstance(x, Interval):
        return NotImplemented
    return _silu_range(x)


def silu_affine(x):
    """jax.nn.silu by a first-order Taylor form about the centre m: silu(m) + silu'(m) h
    with |remainder| <= h^2 / 4 (|silu''| <= 1/2, |h| <= rad) while that is at most a
    quarter of the radius (rad <= 1), else its range on the error term. The body's
    product x * sigmoid(x) of two forms of x took the deviations of both (a 6 x 32 silu
    net's enclosures were 1,600x its range on ray pieces, 20x with this rule; written
    x / (1 + exp(-x)), 38x: issue 28)."""
    if not isinstance(x, Affine):
        return NotImplemented
    eps = float(jnp.finfo(x.center.dtype).eps)
    m, r = x.center, aa.radius(x)
    sig = jax.nn.sigmoid(m)
    value, slope = m * sig, sig * (1.0 + m * (1.0 - sig))
    delta = (0.5 * _SILU_CURVATURE * r * r
             + 4.0 * eps * (jnp.abs(value) + jnp.abs(slope) * r + 1.0))
    taylor = Affine(value, slope[..., None] * x.dev, jnp.abs(slope) * x.err + delta,
                    x.defined)
    values = _silu_range(aa.padded_range(x))
    hull = aa.interval_fallback(values, x.n)
    # the Taylor form keeps the correlation that the next operations cancel: used while
    # its remainder is small against the radius (as sin's), else the range
    use = aa.is_finite(taylor) & (delta <= 0.25 * r)
    return aa.bounded(aa.select(use, taylor, hull), values)


def _elu_alpha(body, x, rest):
    """elu's alpha from its body, a point function of (x, *rest): elu(-1) = alpha (e^-1 -
    1); None when it is not a concrete non-negative number (a traced or lifted alpha:
    then the body is evaluated instead)."""
    if any(is_lifted(r) for r in rest):
        return None
    try:
        # eagerly even under jit (the body's constants are concrete); the probe has the
        # body's own operand shape
        with jax.ensure_compile_time_eval():
            probe = jnp.full(shape_of(x), -1.0, jnp.float32)
            alpha = float(jnp.ravel(body(probe, *rest)[0])[0]) / float(np.expm1(-1.0))
    except (jax.errors.ConcretizationTypeError, TypeError):
        return None
    return alpha if np.isfinite(alpha) and alpha >= 0 else None


def _elu(alpha):
    return lambda x: jnp.where(x > 0, x, alpha * jnp.expm1(jnp.minimum(x, 0.0)))


def elu_interval(x, *rest, body):
    """jax.nn.elu: non-decreasing for alpha >= 0, so ``[elu(lo), elu(hi)]``."""
    alpha = _elu_alpha(body, x, rest)
    if alpha is None or not isinstance(x, Interval):
        return NotImplemented
    return ia.monotone_increasing(_elu(alpha))(x)


def elu_affine(x, *rest, body):
    """jax.nn.elu with 0 < alpha <= 1: convex (slope alpha e^x below 0, 1 above), so the
    Chebyshev linearisation keeps the form's correlation; other alphas: its monotone
    range on the error term."""
    alpha = _elu_alpha(body, x, rest)
    if alpha is None or not isinstance(x, Affine):
        return NotImplemented
    g = _elu(alpha)
    if not 0 < alpha <= 1:  # not convex: the monotone range, correlation dropped
        return aa.from_interval(ia.monotone_increasing(g)(aa.padded_range(x)), None, x.n)

    def dg(v):
        return jnp.where(v > 0, 1.0, alpha * jnp.exp(jnp.minimum(v, 0.0)))

    def dg_inv(slope):  # the tangent point of a chord's slope (the kink 0 above alpha)
        return jnp.where(slope < alpha, jnp.log(jnp.maximum(slope, 1e-30) / alpha), 0.0)

    def g_dg(v):  # both from one expm1, accurate where elu is near 0 too
        e = jnp.expm1(jnp.minimum(v, 0.0))
        return jnp.where(v > 0, v, alpha * e), jnp.where(v > 0, 1.0, alpha * (e + 1.0))

    def chord(a, b, quotient):
        # below 0 the chord's slope is alpha e^a expm1(b - a) / (b - a): no cancellation
        # of e^b - e^a on a small range (that cancellation, rounded, needed pads of 3 ulps
        # of the magnitudes and 3 eps absolute, which summed through a network's layers
        # were the floor of bunny's enclosures: 0.005 wide on pieces of any length)
        w = b - a
        below = alpha * jnp.exp(jnp.minimum(a, 0.0)) * jnp.expm1(jnp.minimum(w, 80.0)) / w
        return jnp.where(b <= 0, below, quotient)  # across 0 g(b) - g(a) cannot cancel

    # Rounding of the error bounds: every value above has a small relative error (expm1
    # and exp of the width, not differences of e^v), so one ulp of the magnitudes pads it:
    # on 20,000 random forms it then holds float64 elu to 0.58 ulp of the values (2.6
    # without the pad; tests/test_neural.py).
    iv = aa.padded_range(x)
    out = aa.chebyshev(x, g, dg, dg_inv, True, iv, ia.monotone_increasing(g)(iv),
                       g_dg=g_dg, ulps=1.0, chord=chord)
    # on a range >= 0 elu is x itself: exact, no rounding pad (the pads of neurons that
    # are surely on were the floor of a network's enclosure width on small pieces)
    return aa.select(iv.lo >= 0, x, out)
