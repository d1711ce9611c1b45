"""Reduced affine arithmetic in Messine's AF1 form (seed Sec. 6.2.5, Eq. 6.14-6.15).

An `Affine` value is ``center + sum_i dev[..., i] * e_i + err * e_{n+1}`` with every
``e in [-1, 1]``: `n` static partial deviations that keep correlations between inputs
(for ray tracing map x, y, z or the ray parameter t to symbols) and one non-negative
accumulated error term. ``n = 1`` is the seed's float3 form (Algorithm 6).

* Affine operations (+, -, scaling) are exact (Eq. 6.15).
* `mul` is Eq. 6.15: ``err = |x0| y_err + |y0| x_err + rad(x) rad(y)``.
* `square` is tighter than ``mul(x, x)``: the quadratic part lies in ``[0, rad^2]``.
* Convex/concave functions (exp, log, sqrt, reciprocal, even powers, x**p, cosh, abs)
  use the Chebyshev linearisation, made sound for any float rounding of the slope by
  bounding the convex error from below with a tangent at the approximate minimiser.
  Near its pole (|hi| > 2 |lo|) the reciprocal uses min-range instead: the chord there is
  so steep that the form's range would reach across 0 (1/x - y "holding" a root beside
  the asymptote); a range touching 0 is unbounded.
* Increasing functions with one inflection at 0 (tanh, atan, logistic, erf, sinh, cbrt)
  take the chord's slope with the residual bounded side by side (Chebyshev's bounds on
  each of the convex and concave sides), or min-range's slope (the least derivative on
  the range) where that leaves the smaller error (`_inflected`).
* sin, cos: a first-order Taylor form (Interval on wide boxes, see `_sinusoid`).
* tan, floor, ceil, sign, fmod fall back to `Interval` (centre and error only,
  correlation lost), as the seed does for its GPU RAA (Sec. 6.5.4); constant operands
  stay exact points there. `extend` runs the bodies of jnp.remainder / floor_divide /
  divmod in interval arithmetic (`_rules.INTERVAL_CALLS`).
* min/max return an operand exactly where their difference has a sign, and else
  ``b + relu(a - b)`` with relu's chord (`relu`), so a neuron that is off drops its error.
* Comparisons return the three-valued `Interval` of bools of the interval module; `where`
  keeps the chosen branch exactly and, where the condition is unknown, joins the cases
  as one form (their mean, the error covering half their difference; by a chord in the
  compared difference when `extend` passes it), or their hull where that is tighter.
* Forms over fewer noise symbols (constants lifted with one) meet others padded with
  zero deviations (`with_symbols`): every rule lifts its operands to one symbol count.

Empty results carry a NaN error term (and centre), and so does a NaN constant (the piece
of a domain where f is NaN has no surface, as in IA); an overflowed form whose centre
became NaN but whose error term did not is the entire line, not empty. Unbounded forms
have an infinite `err`; an infinite point (inf * [1, 2]) keeps an infinite centre.

This module is the `aa` namespace: the type and conversions come from `_affine_type`.
"""

from __future__ import annotations

import math
import sys

import jax
import jax.numpy as jnp
import jax.scipy.special
import numpy as np

from . import _interval as ia
from ._affine_type import (  # noqa: F401 - re-exported: aa is the namespace
    Affine,
    all_defined,
    as_affine,
    bounded,
    from_interval,
    guard,
    guard_unbounded,
    interval_fallback,
    is_empty,
    is_finite,
    lift,
    n_of,
    padded_range,
    radius,
    select,
    to_interval,
    with_symbols,
)
from ._interval import Interval

__all__ = [
    "Affine", "from_interval", "to_interval", "as_affine", "with_symbols", "radius",
    "add", "sub", "neg", "mul", "div", "recip", "square", "ipow", "pow", "sqrt", "exp",
    "log", "expm1", "log1p", "abs", "cosh", "sinh", "tanh", "atan", "cbrt", "logistic",
    "erf", "sin", "cos",
    "tan", "floor", "ceil", "sign", "fmod", "minimum", "maximum", "clamp", "lt", "le", "gt",
    "ge", "eq", "ne", "select_n", "where", "widen",
]
# Package-internal, shared by arith's modules (not API): `chebyshev`, `via_interval` and
# `_affine_type`'s helpers imported above (`padded_range`, `lift`, `n_of`, `select`, ...).


# ------------------------------------------------------------------ affine operations


def _broadcast(x: Affine, shape) -> Affine:
    shape = tuple(shape)
    if shape == jnp.shape(x.center) == jnp.shape(x.err) == jnp.shape(x.dev)[:-1]:
        return x
    def part(a):
        return jnp.broadcast_to(a, shape)

    return Affine(part(x.center), jnp.broadcast_to(x.dev, tuple(shape) + x.dev.shape[-1:]),
                  part(x.err), part(x.defined), part(x.lo), part(x.hi))


def _shifted(a, c, sign: float):
    """a + sign * c for a constant c (not lifted): the centre moves, nothing else (adding
    the zero deviations and error of a lifted constant is not free in XLA)."""
    c = jnp.asarray(c, a.center.dtype)
    shape = jnp.broadcast_shapes(jnp.shape(a.center), jnp.shape(c))
    # a NaN constant makes the empty form (NaN error term), as `as_affine` does
    err = a.err + jnp.where(jnp.isnan(c), jnp.nan, 0.0).astype(c.dtype)
    err = jnp.broadcast_to(err, jnp.broadcast_shapes(jnp.shape(a.err), jnp.shape(c)))
    return _broadcast(Affine(a.center + sign * c, a.dev, err, a.defined,
                             a.lo + sign * c, a.hi + sign * c), shape)


def _is_const(x) -> bool:
    return not isinstance(x, (Affine, Interval))


def add(a, b) -> Affine:
    if _is_const(b) and isinstance(a, Affine):
        return _shifted(a, b, 1.0)
    if _is_const(a) and isinstance(b, Affine):
        return _shifted(b, a, 1.0)
    a, b = lift(a, b)
    # no overflow guard needed: an overflowed centre with a finite error term reads as
    # the entire line in `to_interval` / `padded_range`
    return Affine(a.center + b.center, a.dev + b.dev, a.err + b.err, all_defined(a, b),
                  *_bounds_sum(a.lo, a.hi, b.lo, b.hi))


def _bounds_sum(a_lo, a_hi, b_lo, b_hi):
    """Bounds of a sum from its terms' bounds (a where-case's ``h <= 0`` stays known in
    ``h - 0`` and ``h + k``); a NaN (``inf - inf``) is no bound."""
    lo, hi = a_lo + b_lo, a_hi + b_hi
    return jnp.where(jnp.isnan(lo), -jnp.inf, lo), jnp.where(jnp.isnan(hi), jnp.inf, hi)


def neg(a) -> Affine:
    (a,) = lift(a)
    return Affine(-a.center, -a.dev, a.err, a.defined, -a.hi, -a.lo)


def sub(a, b) -> Affine:
    if a is b:
        zero = jnp.where(is_empty(a), jnp.nan, 0.0)
        return Affine(zero, jnp.zeros_like(a.dev), zero, a.defined)
    if _is_const(b) and isinstance(a, Affine):
        return _shifted(a, b, -1.0)
    a, b = lift(a, b)
    return Affine(a.center - b.center, a.dev - b.dev, a.err + b.err, all_defined(a, b),
                  *_bounds_sum(a.lo, a.hi, -b.hi, -b.lo))


def _is_point(x: Affine):
    return (x.err == 0) & jnp.all(x.dev == 0, axis=-1)


def mul(a, b) -> Affine:
    """AF1 product, Eq. 6.15."""
    if a is b:
        return square(a)
    if not isinstance(a, (Affine, Interval)):
        a, b = b, a
    if not isinstance(b, (Affine, Interval)):  # constant factor: an exact affine scaling
        (a,) = lift(a)
        k = ia.static_factor(b)
        if k is not None:  # a finite nonzero coefficient: nothing to guard but overflow
            k = k.astype(a.center.dtype)
            return guard_unbounded(Affine(k * a.center, k[..., None] * a.dev,
                                          np.abs(k) * a.err, a.defined), a,
                                   fallback=ia.mul(padded_range(a), k))
        k = jnp.asarray(b, a.center.dtype)
        # a NaN factor gives no value (empty), as in interval arithmetic
        return guard_unbounded(Affine(k * a.center, k[..., None] * a.dev,
                                      ia.endpoint_product(jnp.abs(k), a.err), a.defined), a,
                               as_affine(k, a.n), fallback=ia.mul(padded_range(a), k))
    a, b = lift(a, b)
    c = a.center * b.center
    dev = a.center[..., None] * b.dev + b.center[..., None] * a.dev
    err = (ia.endpoint_product(jnp.abs(a.center), b.err)
           + ia.endpoint_product(jnp.abs(b.center), a.err)
           + ia.endpoint_product(radius(a), radius(b)))
    return guard_unbounded(Affine(c, dev, err, all_defined(a, b)), a, b,
                           fallback=ia.mul(padded_range(a), padded_range(b)))


def square(a) -> Affine:
    """Tight AF1 square: ``(x0 + L)^2 = x0^2 + 2 x0 L + L^2`` with ``L^2 in [0, R^2]``."""
    (a,) = lift(a)
    r = radius(a)
    half_r2 = 0.5 * r * r
    c = a.center * a.center + half_r2
    dev = 2.0 * a.center[..., None] * a.dev
    err = 2.0 * ia.endpoint_product(jnp.abs(a.center), a.err) + half_r2
    return guard_unbounded(Affine(c, dev, err, a.defined), a, fallback=ia.square(padded_range(a)))


def _linearized(x: Affine, alpha, d_lo, d_hi, fallback_iv: Interval, defined) -> Affine:
    """``alpha * x + [d_lo, d_hi]`` as an affine form (the new error joins `err`)."""
    zeta = 0.5 * (d_lo + d_hi)
    delta = 0.5 * (d_hi - d_lo)
    out = Affine(alpha * x.center + zeta, alpha[..., None] * x.dev,
                 ia.endpoint_product(jnp.abs(alpha), x.err) + delta, defined)
    # every component is finite when this bound on their magnitudes is (rounding is
    # monotone); it reads per-element coefficients only, so XLA computes each component
    # of the result on its own (a test on the result itself fused all of them into each)
    bound = jnp.abs(alpha) * (jnp.abs(x.center) + radius(x)) + jnp.abs(zeta) + delta
    # the interval result bounds the values too (exp of a form reaching above its
    # bound stays finite where it is taken: `Affine.lo`)
    return bounded(select(jnp.isfinite(bound), out, interval_fallback(fallback_iv, x.n)),
                   fallback_iv)


# Relative safety margin (in f32 ulps) on linearisation errors: the endpoint values,
# the slope and the intercepts are each rounded, so pad delta by a few ulps of the
# magnitudes involved. Cheap, and keeps the "fast" mode sound up to final rounding.
_LIN_ULPS = 8.0


def _pad(delta_terms, dtype, ulps=None):
    eps = float(jnp.finfo(dtype).eps)
    ulps = _LIN_ULPS if ulps is None else ulps
    return ulps * eps * delta_terms + float(jnp.finfo(dtype).tiny)


def chebyshev(x: Affine, g, dg, dg_inv, convex, iv: Interval, fallback_iv: Interval,
              g_dg=None, abs_pad=0.0, ulps=None, chord=None):
    """Chebyshev linearisation of a convex (or concave, ``convex=False``) function on the
    range `iv` of `x` (already restricted to the domain).

    The slope is the chord's; the upper error is at the endpoints; the lower error is
    bounded by the tangent at ``xi = dg_inv(slope)`` clipped into the range, which is a
    valid bound for any xi, so rounding in dg_inv cannot break inclusion.

    `g_dg` (optional): ``v -> (g(v), dg(v))`` from one transcendental (its absolute
    rounding bounded by `abs_pad`); a point range then takes slope 0 (its tangent term
    is 0 whatever the slope), so no derivative is evaluated at the range's end.
    `ulps` (default `_LIN_ULPS`): the relative pad of the error bounds, for a rule that
    bounds its own rounding. `chord` (optional): ``(a, b, slope) -> slope`` of the chord
    for ``a < b`` given the difference quotient, for a rule that computes it without the
    cancellation of g(b) - g(a) where that matters.
    """
    a, b = iv.lo, iv.hi
    s = jnp.where(convex, 1.0, -1.0)
    ga, gb = s * g(a), s * g(b)
    w = b - a
    point_slope = s * dg(a) if g_dg is None else jnp.where(jnp.isnan(w), jnp.nan, 0.0)
    chord_slope = (gb - ga) / jnp.where(w > 0, w, 1.0)
    if chord is not None:
        chord_slope = s * chord(a, jnp.where(w > 0, b, a + 1.0), s * chord_slope)
    beta = jnp.where(w > 0, chord_slope, point_slope)
    xi = jnp.clip(dg_inv(s * beta), a, b)
    xi = jnp.where(jnp.isnan(xi), 0.5 * (a + b), xi)
    h_a, h_b = ga - beta * a, gb - beta * b
    g_xi, dg_xi = (g(xi), dg(xi)) if g_dg is None else g_dg(xi)
    hp = s * dg_xi - beta
    d_hi = jnp.maximum(h_a, h_b)
    d_lo = (s * g_xi - beta * xi) + jnp.minimum(ia.endpoint_product(hp, a - xi),
                                                ia.endpoint_product(hp, b - xi))
    pad = _pad(jnp.abs(ga) + jnp.abs(gb) + jnp.abs(beta) * (jnp.abs(a) + jnp.abs(b)),
               a.dtype, ulps) + abs_pad
    d_lo, d_hi = d_lo - pad, d_hi + pad
    # back from s*g to g: alpha = s*beta, interval s*[d_lo, d_hi]
    lo_g = jnp.where(convex, d_lo, -d_hi)
    hi_g = jnp.where(convex, d_hi, -d_lo)
    return _linearized(x, s * beta, lo_g, hi_g, fallback_iv, iv.defined & x.defined)


def _minrange(x: Affine, g, alpha, iv: Interval, fallback_iv: Interval) -> Affine:
    """Min-range linearisation of a monotone g: with `alpha` the derivative of least
    magnitude on the range, ``g - alpha x`` is monotone, so its range is at the ends."""
    a, b = iv.lo, iv.hi
    d_lo, d_hi = _end_residuals(a, b, g(a), g(b), alpha)
    return _linearized(x, alpha, d_lo, d_hi, fallback_iv, iv.defined & x.defined)


def _end_residuals(a, b, ga, gb, alpha):
    """The range of a monotone ``g - alpha x`` on [a, b] (at its ends), padded."""
    h_a, h_b = ga - alpha * a, gb - alpha * b
    pad = _pad(jnp.abs(ga) + jnp.abs(gb) + jnp.abs(alpha) * (jnp.abs(a) + jnp.abs(b)), a.dtype)
    return jnp.minimum(h_a, h_b) - pad, jnp.maximum(h_a, h_b) + pad


# `recip` linearises by Chebyshev only while |hi| <= _RECIP_RATIO |lo| (a range away
# from the pole): there the form's range stays within 2 sqrt(r) - r >= 83% of the least
# value 1/|hi|. Nearer the pole the chord is so steep that the form reaches far past 0
# (below 1/|hi| by (1/sqrt|lo| - 1/sqrt|hi|)^2, the sign lost for r > 4), so `1/x - y`
# would "contain" a root on pieces next to the asymptote; min-range keeps the range.
_RECIP_RATIO = 2.0


def recip(a) -> Affine:
    """1 / a: Chebyshev on a range away from 0, min-range (slope ``-1/mag^2``, the
    form's range is ``[1/hi, 1/lo]``) near the pole, unbounded (interval rule) when the
    range touches 0."""
    (a,) = lift(a)
    iv = padded_range(a)
    positive = iv.lo > 0
    fallback = ia.recip(iv)
    out = chebyshev(a, lambda v: 1.0 / v, lambda v: -1.0 / (v * v),
                    lambda al: jnp.where(positive, 1.0, -1.0) * jnp.sqrt(-1.0 / al),
                    positive, iv, fallback)
    # min-range: g - alpha x is non-increasing for alpha >= -1/mag^2; alpha rounded
    # toward 0 by a few ulps keeps it so
    m = ia.mag(iv)
    eps = float(jnp.finfo(m.dtype).eps)
    alpha = -(1.0 / (m * m)) * (1.0 - 4.0 * eps)
    near_pole = _minrange(a, lambda v: 1.0 / v, alpha, iv, fallback)
    out = select(m <= _RECIP_RATIO * ia.mig(iv), out, near_pole)
    return select((iv.lo > 0) | (iv.hi < 0), out, interval_fallback(fallback, a.n))


def div(a, b) -> Affine:
    if a is b:
        one = jnp.where(is_empty(a), jnp.nan, 1.0)
        res = Affine(one, jnp.zeros_like(a.dev), one - 1.0, a.defined)
        # x / x is 1 except where x may be 0 (undefined there; keep it honest)
        return select(ia.contains(padded_range(a), 0.0),
                      interval_fallback(ia.div(padded_range(a), padded_range(a)), a.n), res)
    if not isinstance(b, (Affine, Interval)):
        # a constant divisor scales exactly (one rounding per term); 0 takes recip's path
        (a,) = lift(a)
        k = ia.static_factor(b)  # the usual x / 8: no recip of the constant to select from
        if k is not None:
            k = k.astype(a.center.dtype)
            return Affine(a.center / k, a.dev / k[..., None], a.err / np.abs(k), a.defined)
        b = jnp.asarray(b, a.center.dtype)
        safe = jnp.where(b == 0, 1.0, b)
        scaled = Affine(a.center / safe, a.dev / safe[..., None], a.err / jnp.abs(safe),
                        a.defined)
        return select(b != 0, scaled, mul(a, recip(b)))
    a, b = lift(a, b)
    return mul(a, recip(b))


def abs(a) -> Affine:  # noqa: A001
    """|x| by its chord: slope ``(|hi|-|lo|)/(hi-lo)``; ``|x| - slope*x`` is >= 0 and
    largest at the ends. Exact (slope +-1) when the range does not straddle 0."""
    (a,) = lift(a)
    iv = padded_range(a)
    lo, hi = iv.lo, iv.hi
    w = hi - lo
    alpha = jnp.where(w > 0, (jnp.abs(hi) - jnp.abs(lo)) / jnp.where(w > 0, w, 1.0),
                      jnp.sign(lo))
    alpha = jnp.clip(alpha, -1.0, 1.0)
    d_hi = jnp.maximum(jnp.abs(lo) - alpha * lo, jnp.abs(hi) - alpha * hi)
    pad = _pad(jnp.abs(lo) + jnp.abs(hi), lo.dtype)
    return _linearized(a, alpha, jnp.zeros_like(d_hi) - pad, d_hi + pad, ia.abs(iv), a.defined)


def relu(a) -> Affine:
    """max(x, 0): exactly x (error term included) where the range is >= 0, exactly 0
    where it is <= 0, and across 0 the chord ``alpha = hi / (hi - lo)``, whose residual
    ``relu(x) - alpha x`` lies in ``[0, -alpha lo]`` (largest at both ends). The form's
    own error term is scaled by alpha, so a neuron that is off drops it entirely: the
    error of a network's layer does not pass through neurons it cannot reach.

    The interval rule takes over where the range is not within a quarter of the float
    range (unbounded, empty, or near overflow); that test reads the range only, so each
    component of the result is computed on its own (a guard on the result's finiteness
    made XLA compute all of them for each: measured 1.5x slower on networks)."""
    (a,) = lift(a)
    iv = padded_range(a)
    lo, hi = iv.lo, iv.hi
    across = (lo < 0) & (hi > 0)
    w = jnp.where(across, hi - lo, 1.0)
    alpha = jnp.where(across, jnp.clip(hi / w, 0.0, 1.0), (lo >= 0).astype(lo.dtype))
    pad = jnp.where(across, _pad(jnp.abs(lo) + jnp.abs(hi), lo.dtype), 0.0)
    half = jnp.where(across, -0.5 * alpha * lo, 0.0)  # residual in [-pad, 2 half + pad]
    out = Affine(alpha * a.center + half, alpha[..., None] * a.dev, alpha * a.err + half + pad,
                 a.defined)
    quarter = 0.25 * float(jnp.finfo(lo.dtype).max)
    moderate = (jnp.abs(lo) < quarter) & (jnp.abs(hi) < quarter)  # False for NaN
    values = ia.maximum(iv, 0.0)
    return bounded(select(moderate, out, interval_fallback(values, a.n)), values)


def _is_concrete(x) -> bool:
    """x is a concrete array (not traced, not lifted)."""
    if isinstance(x, (Affine, Interval, jax.core.Tracer)):
        return False
    try:
        np.asarray(x)
    except (TypeError, ValueError):
        return False
    return True


def _is_zero(x) -> bool:
    """x is a concrete (not traced, not lifted) zero: relu's max(x, 0)."""
    return _is_concrete(x) and bool(np.all(np.asarray(x) == 0))


def maximum(a, b) -> Affine:
    """max(a, b) = b + relu(a - b): exactly a or b where the difference has a sign."""
    if _is_zero(b) or _is_zero(a):  # relu: one rule, no shift and no selects around it
        x, zero = (a, b) if _is_zero(b) else (b, a)
        (x,) = lift(x)
        shape = jnp.broadcast_shapes(jnp.shape(x.center), jnp.shape(zero))
        return _broadcast(relu(x), shape)
    a, b = lift(a, b)
    d = padded_range(sub(a, b))
    out = select(d.lo >= 0, a, select(d.hi <= 0, b, add(b, relu(sub(a, b)))))
    return bounded(out, ia.maximum(padded_range(a), padded_range(b)))


def minimum(a, b) -> Affine:
    """min(a, b) = a - relu(a - b): exactly a or b where the difference has a sign."""
    a, b = lift(a, b)
    d = padded_range(sub(a, b))
    out = select(d.lo >= 0, b, select(d.hi <= 0, a, sub(a, relu(sub(a, b)))))
    return bounded(out, ia.minimum(padded_range(a), padded_range(b)))


def clamp(lower, x, upper) -> Affine:
    return minimum(maximum(x, lower), upper)


def _even_power_inv(n):
    return lambda al: jnp.sign(al) * (jnp.abs(al) / n) ** (1.0 / (n - 1))


def ipow(a, n: int) -> Affine:
    """Integer power: Chebyshev for even n (convex); odd n is convex/concave on one side
    of 0 and ``x * x**(n-1)`` across it."""
    n = int(n)
    (a,) = lift(a)
    if n == 0:
        one = jnp.where(is_empty(a), jnp.nan, 1.0)
        return Affine(one, jnp.zeros_like(a.dev), one - 1.0, a.defined)
    if n < 0:
        return recip(ipow(a, -n))
    if n == 1:
        return a
    if n == 2:
        return square(a)
    iv = padded_range(a)
    g = lambda v: jax.lax.integer_pow(v, n)  # noqa: E731
    dg = lambda v: n * jax.lax.integer_pow(v, n - 1)  # noqa: E731
    fallback = ia.ipow(iv, n)
    if n % 2 == 0:
        return chebyshev(a, g, dg, _even_power_inv(n), True, iv, fallback)
    positive = iv.lo >= 0
    side = chebyshev(a, g, dg, lambda al: jnp.where(positive, 1.0, -1.0)
                     * (jnp.abs(al) / n) ** (1.0 / (n - 1)), positive, iv, fallback)
    across = mul(a, ipow(a, n - 1))
    return select((iv.lo >= 0) | (iv.hi <= 0), side, across)


def pow(a, p) -> Affine:  # noqa: A001
    """``a ** p``: integer p -> `ipow`; constant real p -> Chebyshev on ``a >= 0``
    (convex for p > 1 or p < 0, concave for 0 < p < 1); an interval/affine exponent
    falls back to Interval."""
    (a,) = lift(a)
    if not isinstance(p, (Affine, Interval, jax.core.Tracer)):
        p_np = np.asarray(p)
        if p_np.ndim == 0:
            pf = float(p_np)
            if not np.isfinite(pf):
                return interval_fallback(ia.pow(padded_range(a), pf), a.n)
            if pf == int(pf):
                return ipow(a, int(pf))
            iv = ia.restrict(padded_range(a), 0.0)
            return chebyshev(a, lambda v: v**pf, lambda v: pf * v ** (pf - 1),
                             lambda al: (al / pf) ** (1.0 / (pf - 1)),
                             (pf > 1) or (pf < 0), iv, ia.pow(iv, pf))
    p_iv = padded_range(p) if isinstance(p, Affine) else p
    return interval_fallback(ia.pow(padded_range(a), p_iv), a.n)


def sqrt(a) -> Affine:
    (a,) = lift(a)
    iv = ia.restrict(padded_range(a), 0.0)
    return chebyshev(a, jnp.sqrt, lambda v: 0.5 / jnp.sqrt(v), lambda al: 0.25 / (al * al),
                     False, iv, ia.sqrt(iv))


def log(a) -> Affine:
    (a,) = lift(a)
    iv = ia.restrict(padded_range(a), 0.0)
    return chebyshev(a, jnp.log, lambda v: 1.0 / v, lambda al: 1.0 / al, False, iv,
                     ia.log(iv))


def exp(a) -> Affine:
    (a,) = lift(a)
    iv = padded_range(a)
    return chebyshev(a, jnp.exp, jnp.exp, jnp.log, True, iv, ia.exp(iv))


def expm1(a) -> Affine:
    """e^x - 1: convex and increasing like exp (Chebyshev), accurate near 0 where exp(x)
    - 1 cancels; ``where(h > 0, h, expm1(h))`` (elu) joins two close forms."""
    (a,) = lift(a)
    iv = padded_range(a)
    return chebyshev(a, jnp.expm1, jnp.exp, jnp.log, True, iv,
                     ia.monotone_increasing(jnp.expm1)(iv))


def log1p(a) -> Affine:
    """log(1 + x) on x >= -1: concave and increasing (Chebyshev)."""
    (a,) = lift(a)
    iv = ia.restrict(padded_range(a), -1.0)
    return chebyshev(a, jnp.log1p, lambda v: 1.0 / (1.0 + v), lambda al: 1.0 / al - 1.0,
                     False, iv, ia.monotone_increasing(jnp.log1p)(iv))


def cosh(a) -> Affine:
    (a,) = lift(a)
    iv = padded_range(a)
    return chebyshev(a, jnp.cosh, jnp.sinh, jnp.arcsinh, True, iv, ia.cosh(iv))


def _inflected(x: Affine, g, dg, dg_inv, g0: float, iv: Interval, fallback_iv: Interval,
               convex_left: bool = True) -> Affine:
    """Linearisation of an increasing g whose only inflection is at 0 (point-symmetric
    about (0, g0): convex on one side, concave on the other): the chord's slope m with
    the residual ``r = g - m x`` bounded on each side (Chebyshev's bounds on a side the
    range lies in), or min-range's slope (the least derivative on the range) where that
    leaves the smaller error. ``dg(v, g(v))``: the derivative from the value (tanh: 1 -
    t^2), so the rule evaluates g three times (both ends and where g' = m), as
    min-range did.

    On the convex side r's maximum is at the side's ends and its minimum above r's
    tangent at any point of the side, taken where g' = m (``dg_inv(m) >= 0``, mirrored
    on the left) clipped into the side, so rounding in dg_inv cannot break inclusion;
    the concave side alike, upside down. Against min-range, whose error is nearly the
    whole range once the range reaches where g flattens: tanh on [-1, 1] 0.082 instead
    of 0.34 (the range is 1.52)."""
    a, b = iv.lo, iv.hi
    ga, gb = g(a), g(b)
    w = b - a
    m = jnp.where(w > 0, (gb - ga) / jnp.where(w > 0, w, 1.0), dg(a, ga))
    ra, rb = ga - m * a, gb - m * b
    xs = dg_inv(m)
    xs = jnp.where(jnp.isnan(xs), 0.0, xs)
    gs = g(xs)

    def tangent(sign, lo, g_lo, hi, g_hi, upper):
        """r's tangent at sign * xs clipped into the side [lo, hi] (g there: from gs by
        symmetry, or an end's value), at its highest (upper) or lowest on the side; and
        the magnitude of its terms (for the rounding pad)."""
        at, g_at = sign * xs, g0 + sign * (gs - g0)
        xi = jnp.where(at < lo, lo, jnp.where(at > hi, hi, at))
        gx = jnp.where(at < lo, g_lo, jnp.where(at > hi, g_hi, g_at))
        hp = dg(xi, gx) - m
        ends = (ia.endpoint_product(hp, lo - xi), ia.endpoint_product(hp, hi - xi))
        reach = jnp.maximum(*ends) if upper else jnp.minimum(*ends)
        return gx - m * xi + reach, jnp.abs(gx) + jnp.abs(m * xi) + jnp.abs(reach)

    left, right = a < 0, b > 0
    zero = jnp.zeros_like(a)
    t_left, mag_left = tangent(-1.0, a, ga, jnp.minimum(b, zero), jnp.where(right, g0, gb),
                               upper=not convex_left)
    t_right, mag_right = tangent(1.0, jnp.maximum(a, zero), jnp.where(left, g0, ga), b, gb,
                                 upper=convex_left)
    upper_t = jnp.where(right, t_right, -jnp.inf) if convex_left else jnp.where(
        left, t_left, -jnp.inf)
    lower_t = jnp.where(left, t_left, jnp.inf) if convex_left else jnp.where(
        right, t_right, jnp.inf)
    at0 = jnp.where(left & right, g0, ra)  # r(0) = g(0) where the range holds 0
    d_hi = jnp.maximum(jnp.maximum(ra, rb), jnp.maximum(at0, upper_t))
    d_lo = jnp.minimum(jnp.minimum(ra, rb), jnp.minimum(at0, lower_t))
    pad = _pad(jnp.abs(ga) + jnp.abs(gb) + math.fabs(g0) + jnp.abs(m) * (jnp.abs(a) + jnp.abs(b))
               + jnp.where(left, mag_left, 0.0) + jnp.where(right, mag_right, 0.0), a.dtype)
    d_lo, d_hi = d_lo - pad, d_hi + pad
    alpha, mr_lo, mr_hi = _min_range_bounds(a, b, ga, gb, g0, dg, convex_left)
    chord = (d_hi - d_lo) < (mr_hi - mr_lo)  # NaN (an empty range): min-range, as before
    return _linearized(x, jnp.where(chord, m, alpha), jnp.where(chord, d_lo, mr_lo),
                       jnp.where(chord, d_hi, mr_hi), fallback_iv, iv.defined & x.defined)


def _min_range_bounds(a, b, ga, gb, g0, dg, convex_left):
    """Min-range for `_inflected`'s g on [a, b]: the least derivative alpha (g' even: at
    the end farthest from 0 where g' falls away from 0, at the nearest end, or 0, where
    it grows; g there by symmetry) and the bounds of ``g - alpha x`` (monotone: its
    ends), padded."""
    far = jnp.abs(a) > jnp.abs(b)
    if convex_left:
        v, gv = jnp.where(far, -a, b), g0 + jnp.where(far, g0 - ga, gb - g0)
    else:
        across = (a < 0) & (b > 0)
        v = jnp.where(across, 0.0, jnp.where(far, jnp.abs(b), jnp.abs(a)))
        gv = jnp.where(across, g0, g0 + jnp.abs(jnp.where(far, gb, ga) - g0))
    alpha = dg(v, gv)
    return (alpha, *_end_residuals(a, b, ga, gb, alpha))


def _inflected_rule(g, dg, dg_inv, g0, interval_rule, convex_left=True, name=None):
    """The affine rule of an inflected g (`_inflected`)."""
    def rule(a) -> Affine:
        (a,) = lift(a)
        iv = padded_range(a)
        return _inflected(a, g, dg, dg_inv, g0, iv, interval_rule(iv), convex_left)

    rule.__name__ = name or g.__name__
    return rule


_TWO_OVER_SQRT_PI = 2.0 / math.sqrt(math.pi)

sinh = _inflected_rule(jnp.sinh, lambda v, s: jnp.sqrt(1.0 + s * s),
                       lambda m: jnp.arccosh(jnp.maximum(m, 1.0)), 0.0, ia.sinh,
                       convex_left=False, name="sinh")
tanh = _inflected_rule(jnp.tanh, lambda v, t: 1.0 - t * t,
                       lambda m: jnp.arctanh(jnp.sqrt(jnp.clip(1.0 - m, 0.0, 1.0))), 0.0,
                       ia.tanh, name="tanh")
atan = _inflected_rule(jnp.arctan, lambda v, _: 1.0 / (1.0 + v * v),
                       lambda m: jnp.sqrt(jnp.maximum(1.0 / m - 1.0, 0.0)), 0.0, ia.atan,
                       name="atan")
# the logistic sigmoid (jax.nn.sigmoid) and erf (jax.nn.gelu, approximate=False)
logistic = _inflected_rule(
    jax.nn.sigmoid, lambda v, s: s * (1.0 - s),
    lambda m: 2.0 * jnp.arctanh(jnp.sqrt(jnp.clip(1.0 - 4.0 * m, 0.0, 1.0))), 0.5,
    ia.monotone_increasing(jax.nn.sigmoid), name="logistic")
erf = _inflected_rule(
    jax.scipy.special.erf, lambda v, _: _TWO_OVER_SQRT_PI * jnp.exp(-v * v),
    lambda m: jnp.sqrt(jnp.maximum(-jnp.log(m / _TWO_OVER_SQRT_PI), 0.0)), 0.0,
    ia.monotone_increasing(jax.scipy.special.erf), name="erf")
cbrt = _inflected_rule(jnp.cbrt, lambda v, c: 1.0 / (3.0 * c * c),
                       lambda m: (1.0 / (3.0 * m)) ** 1.5, 0.0, ia.cbrt, name="cbrt")


def via_interval(fn):
    def rule(*args):
        # constants stay exact points: lifted, `padded_range` would pad them by an ulp, and
        # rules that are exact for a point operand (fmod by a constant within one
        # period) would fall back to their loose bound (x // 0.5, remainder, fmod)
        n = n_of(*args)
        return interval_fallback(
            fn(*[padded_range(x) if isinstance(x, Affine) else ia.as_interval(x) for x in args]), n)

    rule.__name__ = fn.__name__
    rule.__doc__ = f"{fn.__name__} through Interval (correlation not kept)."
    return rule


def _sinusoid(fn, dfn, ia_fn, name):
    """Affine sin / cos by a first-order Taylor form about the centre m:
    fn(m + h) = fn(m) + dfn(m) h + R with |R| <= h^2 / 2 (|fn''| <= 1), |h| <= rad, so
    the error term gets rad^2/2 + |dfn(m)| err + rounding. Where that remainder is not
    small against the radius (wide boxes) or |m| is too large for float32 argument
    reduction, the interval rule is used instead (correlation dropped)."""
    eps = float(jnp.finfo(jnp.float32).eps)
    tiny = float(jnp.finfo(jnp.float32).tiny)

    def rule(x):
        x = as_affine(x, n_of(x))
        m, r = x.center, radius(x)
        s, c = fn(m), dfn(m)
        delta = 0.5 * r * r + 2.0 * eps * (jnp.abs(s) + jnp.abs(c) * r + 1.0) + tiny
        taylor = Affine(s, c[..., None] * x.dev, jnp.abs(c) * x.err + delta, x.defined)
        fallback = interval_fallback(ia_fn(padded_range(x)), x.n)
        use = (delta <= 0.25 * r) & (jnp.abs(m) <= ia.TRIG_MAX_ARG) & is_finite(x)
        return select(use, taylor, fallback)

    rule.__name__ = name
    return rule


sin = _sinusoid(jnp.sin, jnp.cos, ia.sin, "sin")
cos = _sinusoid(jnp.cos, lambda m: -jnp.sin(m), ia.cos, "cos")
atan2 = via_interval(ia.atan2)
tan = via_interval(ia.tan)
floor = via_interval(ia.floor)
ceil = via_interval(ia.ceil)
sign = via_interval(ia.sign)
fmod = via_interval(ia.fmod)


# ----------------------------------------------------------- comparisons and select


def _compare(fn):
    def rule(a, b):
        a, b = lift(a, b)
        return fn(padded_range(a), padded_range(b))

    rule.__name__ = fn.__name__
    rule.__doc__ = f"Three-valued {fn.__name__} on the affine ranges (an Interval of bools)."
    return rule


lt, le, gt, ge, eq, ne = (_compare(f) for f in (ia.lt, ia.le, ia.gt, ia.ge, ia.eq, ia.ne))


def _join(a: Affine, b: Affine) -> Affine:
    """One form holding every value of `a` and of `b` for the same noise symbols: their
    mean ``m = (a + b) / 2`` with the error ``max(a.err, b.err) + |(a - b)'| / 2``, where
    ``(a - b)'`` is the difference without error terms, bounded by ``|centre| + sum |dev|``
    (``a = m + (a - b) / 2`` and ``b = m - (a - b) / 2`` for each value of the symbols,
    and each keeps its own error term). Parts that the cases share cancel in the
    difference, so two branches that nearly agree (where(h > 0, h, expm1(h))) give a
    form almost as tight as either. The rounding of the mean and of the bound is padded
    by ulps of the magnitudes involved. An empty case (NaN error term) adds nothing."""
    half_diff = 0.5 * (jnp.abs(a.center - b.center)
                       + jnp.sum(jnp.abs(a.dev - b.dev), axis=-1))
    scale = jnp.abs(a.center) + jnp.abs(b.center) + radius(a) + radius(b)
    err = jnp.maximum(a.err, b.err) + half_diff + _pad(scale, a.center.dtype, 4.0)
    joined = Affine(0.5 * (a.center + b.center), 0.5 * (a.dev + b.dev), err,
                    a.defined & b.defined)
    return select(is_empty(a), b, select(is_empty(b), a, joined))


def _envelope(slopes, ends, mu, pick):
    """pick (jnp.maximum or jnp.minimum) over the lines ``slope mu + end`` at `mu`."""
    out = slopes[0] * mu + ends[0]
    for sl, e in zip(slopes[1:], ends[1:]):
        out = pick(out, sl * mu + e)
    return out


def _least_width(slopes, hi_i, lo_i, zero):
    """The mu (0 or a crossing of two lines of one envelope) where the upper envelope
    minus the lower is least; the first of equal widths, as an argmin. The candidates
    are scanned one by one (elementwise, one fused loop; stacked as [..., 13, 4]
    arrays this took 40 ms on 4,096 x 32 neurons against 14 ms)."""
    def width(mu):
        w = _envelope(slopes, hi_i, mu, jnp.maximum) - _envelope(slopes, lo_i, mu, jnp.minimum)
        return jnp.where(jnp.isnan(w), jnp.inf, w)

    mu, best = zero, width(zero)
    for ends in (hi_i, lo_i):
        for i in range(4):
            for j in range(i + 1, 4):
                ds = slopes[i] - slopes[j]
                cand = (ends[j] - ends[i]) / jnp.where(ds != 0, ds, 1.0)
                cand = jnp.where((ds != 0) & jnp.isfinite(cand), cand, 0.0)
                w = width(cand)
                better = w < best
                mu, best = jnp.where(better, cand, mu), jnp.where(better, w, best)
    return mu


def _join_on_sign(a: Affine, b: Affine, g: Affine) -> Affine:
    """`_join` for a case `a` taken only where ``g >= 0`` and `b` only where ``g <= 0``
    (``where(p > q, a, b)`` with ``g = p - q``): a chord in g, as relu's.

    With ``g' = g.center + g.dev . e`` (g without its error term), the point's own g lies
    within ``g.err`` of g', so `a` is taken only where ``g' >= -g.err`` and `b` only
    where ``g' <= g.err``. Write the difference ``(a - b)' = kappa g' + rho`` (kappa by
    least squares on the deviations, rho bounded by its centre +- its deviations) and
    the result ``m' + mu g' + [lo, hi]``, m' the cases' mean: a value of `a` is
    ``m' + (kappa/2) g' + rho/2 + a.err u``, of `b` ``m' - (kappa/2) g' - rho/2 +
    b.err u``, so the residual on each side is affine in g' over its half of g's range,
    and [lo, hi] is the hull of both. Its width is convex and piecewise linear in mu:
    the least is at a crossing of two of the end lines, all of which are tried. With
    ``a = h``, ``b = 0``, ``g = h`` this is relu's chord; for cases unrelated to g it is
    no wider than the plain join at mu = 0 (which the caller also tries)."""
    dt = a.center.dtype
    cg, dg = g.center, g.dev
    rg = jnp.sum(jnp.abs(dg), axis=-1)
    g_lo, g_hi = cg - rg, cg + rg
    slack = g.err + _pad(jnp.abs(cg) + radius(g), dt)
    ta = (jnp.clip(-slack, g_lo, g_hi), g_hi)  # g' where `a` may be taken
    tb = (g_lo, jnp.clip(slack, g_lo, g_hi))   # and `b`
    cd, dd = a.center - b.center, a.dev - b.dev
    gg = jnp.sum(dg * dg, axis=-1)
    kappa = jnp.where(gg > 0, jnp.sum(dd * dg, axis=-1) / jnp.where(gg > 0, gg, 1.0), 0.0)
    rho_c = cd - kappa * cg
    rho_r = jnp.sum(jnp.abs(dd - kappa[..., None] * dg), axis=-1)
    # the ends of each side's residual as lines in mu: (kappa/2 -+ ... - mu) t + c
    hi_c = (0.5 * (rho_c + rho_r) + a.err, 0.5 * (rho_r - rho_c) + b.err)
    lo_c = (0.5 * (rho_c - rho_r) - a.err, -0.5 * (rho_c + rho_r) - b.err)
    # four lines per envelope, one per end of the sides, as lists of [...] arrays
    ts = [*ta, *tb]
    sigma = (0.5, 0.5, -0.5, -0.5)
    slopes = [-t for t in ts]
    base = [sg * kappa * t for sg, t in zip(sigma, ts)]
    hi_i = [bs + c for bs, c in zip(base, (hi_c[0], hi_c[0], hi_c[1], hi_c[1]))]
    lo_i = [bs + c for bs, c in zip(base, (lo_c[0], lo_c[0], lo_c[1], lo_c[1]))]

    mu = _least_width(slopes, hi_i, lo_i, jnp.zeros_like(cg))
    hi = _envelope(slopes, hi_i, mu, jnp.maximum)
    lo = _envelope(slopes, lo_i, mu, jnp.minimum)
    scale = (jnp.abs(a.center) + jnp.abs(b.center) + radius(a) + radius(b)
             + jnp.abs(mu) * (jnp.abs(cg) + rg) + jnp.abs(hi) + jnp.abs(lo))
    return Affine(0.5 * (a.center + b.center) + mu * cg + 0.5 * (hi + lo),
                  0.5 * (a.dev + b.dev) + mu[..., None] * dg,
                  0.5 * (hi - lo) + _pad(scale, dt), a.defined & b.defined)


def select_n(which, *cases, sign: Affine | None = None) -> Affine:
    """Exact case where `which` is certain. Elsewhere the cases it may take are joined as
    one form (`_join`: their mean, the error covering half their difference), or their
    interval hull where the join's error term exceeds the hull's radius. A join a little
    wider than the hull keeps the correlation that the next operations cancel: on a
    3 x 32 elu MLP (``where(h > 0, h, exp(min(h, 0)) - 1)``) the enclosure was 1.5x
    narrower so than when the narrower of the two by radius was kept
    (benchmarks/bench_affine_where.py, NOTES session 17).

    `sign` (optional, two cases): a form g with ``which`` true only where ``g >= 0`` and
    false only where ``g <= 0`` (from the comparison that made it: `extend` passes it);
    the join then also tries a chord in g (`_join_on_sign`), as relu's."""
    which = ia.as_interval(which)
    if sign is not None and len(cases) == 2:  # one symbol count for the cases and g
        *cases, sign = lift(*cases, sign)
    else:
        cases, sign = lift(*cases), None
    # the hull as a form (its centre and radius rounded: an ulp more)
    values = ia.select_n(which, *[padded_range(c) for c in cases])
    hull = widen(interval_fallback(values, cases[0].n))
    w_lo, w_hi = which.lo.astype(jnp.int32), which.hi.astype(jnp.int32)
    joined, started = cases[0], w_lo <= 0
    for i, c in enumerate(cases[1:], 1):
        take = (w_lo <= i) & (i <= w_hi)
        joined = select(take, select(started, _join(joined, c), c), joined)
        started = started | take
    if sign is not None:
        chord = _join_on_sign(cases[1], cases[0], _broadcast(sign, hull.shape))
        better = is_finite(chord) & ~(chord.err > joined.err)
        joined = select(better & (w_lo == 0) & (w_hi == 1), chord, joined)
    # the hull where the join's uncorrelated part is wider than the hull itself
    tighter = is_finite(joined) & ~(joined.err > radius(hull))
    out = select(tighter, joined, hull)
    out = bounded(Affine(out.center, out.dev, out.err, hull.defined), values)
    certain = which.lo == which.hi
    for i, c in enumerate(cases):
        out = select(certain & (w_lo == i), c, out)
    return out


select_n.takes_sign = True


def where(condition, x, y) -> Affine:
    return select_n(condition, y, x)


def widen(a: Affine, ulps: float = 1.0, scale=None) -> Affine:
    """Pad the error term by `ulps` of every term's magnitude (plus `scale`, the inputs'
    magnitude for sums, and the smallest normal), covering the rounding of the centre and
    of each deviation."""
    eps = float(jnp.finfo(a.center.dtype).eps)
    tiny = float(jnp.finfo(a.center.dtype).tiny)
    mag = jnp.abs(a.center) + radius(a)
    if scale is not None:
        mag = mag + scale
    step = jnp.minimum(ulps * eps, 1.0)
    err = a.err + step * mag + tiny * (a.n + 2)
    return Affine(a.center, a.dev, err, a.defined, a.lo - step * jnp.abs(a.lo) - tiny,
                  a.hi + step * jnp.abs(a.hi) + tiny)



Affine.ops = sys.modules[__name__]
