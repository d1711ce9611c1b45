"""Interval arithmetic on batched JAX arrays (Moore; seed Sec. 6.2.2, Eq. 6.4-6.6, 6.18).

An `Interval` encloses a set of reals per array element: `[lo, hi]`, any batch shape.

Conventions (documented once here, relied on everywhere):

* **Empty** intervals have NaN in both endpoints. Every function below maps an empty
  input to an empty output, and `contains` is False for them, so an empty enclosure can
  never register a ray hit. `hull` treats empty as its identity.
* **Domain**: points of a box outside an operation's domain (sqrt or log of negatives,
  fractional powers of negatives) are dropped from the result and `defined` becomes False
  there (IEEE 1788's "defined" decoration, as a bool array). A box wholly outside the
  domain gives the empty interval.
* **Unbounded**: endpoints may be +-inf. Division by an interval containing 0 is unbounded
  (an asymptote, seed Sec. 6.4.4); `0 * inf` inside a product counts as 0, as in interval
  arithmetic, not NaN.
* **Three-valued logic**: comparisons return an `Interval` of bools: [True, True] is
  certainly true, [False, False] certainly false, [False, True] unknown. `logical_and`,
  `logical_or`, `logical_not` and `where` accept them; `where` with an unknown condition
  gives the hull of both branches.
* **Rounding**: these functions round to nearest, as the seed does (Sec. 6.4.1, 6.5.4).
  `widen` pads a result outward by a few ulps; `extend(..., rounding="outward")` applies it
  after every inexact operation.

This module is the `ia` namespace: the type, constructors, queries and rule builders come
from `_interval_type`, the three-valued logic from `_interval_logic`.
"""

from __future__ import annotations

import math
import sys

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._interval_logic import (
    certainly,
    eq,
    ge,
    gt,
    is_false,
    is_true,
    is_unknown,
    le,
    logical_and,
    logical_not,
    logical_or,
    lt,
    ne,
    possibly,
    select_n,
    where,
)
from ._interval_type import (  # noqa: F401 - re-exported: ia is the namespace
    Interval,
    OperatorsMixin,
    as_interval,
    check_endpoints,
    contains,
    empty,
    entire,
    even,
    hull,
    intersect,
    interval,
    is_empty,
    mag,
    make,
    mid,
    mig,
    monotone_decreasing,
    monotone_increasing,
    monotone_on,
    point,
    rad,
    restrict,
    same_nan,
    width,
)

__all__ = [
    "Interval", "interval", "point", "entire", "empty", "as_interval",
    "width", "mid", "rad", "mig", "mag", "contains", "is_empty", "hull", "intersect",
    "add", "sub", "mul", "product_hull", "div", "neg", "abs", "square", "ipow", "pow",
    "sqrt", "cbrt",
    "exp", "log", "sin", "cos", "tan", "tanh", "atan", "atan2", "sinh", "cosh",
    "minimum", "maximum", "clamp", "floor", "ceil", "sign", "fmod",
    "lt", "le", "gt", "ge", "eq", "ne", "logical_and", "logical_or", "logical_not",
    "where", "select_n", "widen",
    "certainly", "possibly", "is_true", "is_false", "is_unknown",
]
# Package-internal, shared by arith's modules (not API): `endpoint_product`,
# `TRIG_MAX_ARG` and `_interval_type`'s `make`, `same_nan`.

_PI = math.pi


# ------------------------------------------------------------------------ arithmetic


def add(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return make(a.lo + b.lo, a.hi + b.hi, a, b)


def sub(a, b) -> Interval:
    if a is b:  # x - x is exactly 0 wherever x is defined
        zero = jnp.zeros_like(a.lo)
        return make(*same_nan(zero, zero, a.lo), a)
    a, b = as_interval(a), as_interval(b)
    return make(a.lo - b.hi, a.hi - b.lo, a, b)


def neg(a) -> Interval:
    a = as_interval(a)
    return make(-a.hi, -a.lo, a)


def endpoint_product(u, v):
    """Endpoint product with 0 * inf = 0 (interval convention), NaN kept for empties."""
    p = u * v
    return jnp.where((u == 0) | (v == 0), jnp.zeros_like(p), p)


def static_factor(k):
    """k as a numpy array when it is a concrete finite nonzero constant (a coefficient
    such as 0.3 * x or x / 3: two endpoint operations, no hull of four), else None.
    Checked before any jnp conversion, which stages an operation under a trace."""
    if isinstance(k, (Interval, jax.core.Tracer)):
        return None
    try:
        k = np.asarray(k)
    except (TypeError, ValueError):
        return None
    if not (np.issubdtype(k.dtype, np.floating) or np.issubdtype(k.dtype, np.integer)):
        return None  # objects, bools, complex
    k = k.astype(np.float32) if np.issubdtype(k.dtype, np.integer) else k
    return k if bool(np.all(np.isfinite(k) & (k != 0))) else None


def _scaled(a: Interval, k, op) -> Interval:
    """``op(a, k)`` for a constant k from `static_factor` (op: multiply or divide; one
    rounding per endpoint, as the general rules): monotone in a, decreasing where k < 0."""
    k = k.astype(a.lo.dtype) if k.dtype != a.lo.dtype else k
    u, v = op(a.lo, k), op(a.hi, k)
    if bool(np.all(k > 0)):
        lo, hi = u, v
    elif bool(np.all(k < 0)):
        lo, hi = v, u
    else:
        lo, hi = jnp.minimum(u, v), jnp.maximum(u, v)
    return make(lo, hi, a)


def mul(a, b) -> Interval:
    """Product (Eq. 6.5): hull of the four endpoint products."""
    if a is b:
        return square(a)
    if isinstance(a, Interval) and not isinstance(b, Interval):
        k = static_factor(b)
        if k is not None:
            return _scaled(a, k, jnp.multiply)
    if isinstance(b, Interval) and not isinstance(a, Interval):
        k = static_factor(a)
        if k is not None:
            return _scaled(b, k, jnp.multiply)
    a, b = as_interval(a), as_interval(b)
    lo, hi = product_hull(a, b, endpoint_product)
    # An empty factor times an exact 0 endpoint would give 0: keep it empty.
    lo, hi = same_nan(lo, hi, a.lo, b.lo)
    return make(lo, hi, a, b)


def product_hull(a: Interval, b: Interval, product=jnp.multiply):
    """(lo, hi): the least and greatest of the four endpoint products `product(u, v)`."""
    p = (product(a.lo, b.lo), product(a.lo, b.hi), product(a.hi, b.lo), product(a.hi, b.hi))
    return (jnp.minimum(jnp.minimum(p[0], p[1]), jnp.minimum(p[2], p[3])),
            jnp.maximum(jnp.maximum(p[0], p[1]), jnp.maximum(p[2], p[3])))


def recip(a) -> Interval:
    """1 / a. Contains-zero cases are unbounded (seed Sec. 6.4.4): ``[0, h]`` gives
    ``[1/h, inf]``, ``[l, 0]`` gives ``[-inf, 1/l]``, zero inside (or ``[0, 0]``) gives the
    entire line. 1/0 is undefined, so `defined` is False wherever 0 is in the box."""
    a = as_interval(a)
    inf = jnp.full_like(a.lo, jnp.inf)
    lo = jnp.where(a.hi == 0, -inf, 1.0 / a.hi)  # [l, 0] -> [-inf, 1/l] (either zero sign)
    hi = jnp.where(a.lo == 0, inf, 1.0 / a.lo)   # [0, h] -> [1/h, inf]
    straddle = ((a.lo < 0) & (a.hi > 0)) | ((a.lo == 0) & (a.hi == 0))
    lo = jnp.where(straddle, -inf, lo)
    hi = jnp.where(straddle, inf, hi)
    lo, hi = same_nan(lo, hi, a.lo)
    return make(lo, hi, a, defined=~contains(a, 0.0))


def div(a, b) -> Interval:
    """Quotient: the hull of endpoint quotients ``a_i / b_j``, each rounded once. Where `b`
    contains 0 the matching reciprocal end is infinite (`recip`) and that candidate is
    ``a_i * (+-inf)`` with ``0 * inf = 0``: unbounded (an asymptote, never a hit) and
    flagged undefined."""
    if a is b:  # x / x is 1 wherever it is defined
        return where(contains(a, 0.0), mul(a, recip(a)),
                     make(*same_nan(jnp.ones_like(a.lo), jnp.ones_like(a.lo), a.lo), a))
    if isinstance(a, Interval) and not isinstance(b, Interval):
        k = static_factor(b)
        if k is not None:
            return _scaled(a, k, jnp.divide)
    a, b = as_interval(a), as_interval(b)
    r = recip(b)  # r.lo pairs with b.hi, r.hi with b.lo

    def quotient(u, v, r_end):
        direct = u / v
        return jnp.where(jnp.isinf(r_end) | jnp.isnan(direct), endpoint_product(u, r_end), direct)

    q = (quotient(a.lo, b.hi, r.lo), quotient(a.lo, b.lo, r.hi),
         quotient(a.hi, b.hi, r.lo), quotient(a.hi, b.lo, r.hi))
    lo = jnp.minimum(jnp.minimum(q[0], q[1]), jnp.minimum(q[2], q[3]))
    hi = jnp.maximum(jnp.maximum(q[0], q[1]), jnp.maximum(q[2], q[3]))
    lo, hi = same_nan(lo, hi, a.lo, b.lo)
    return make(lo, hi, a, r)


def abs(a) -> Interval:  # noqa: A001 - mirrors jnp.abs
    a = as_interval(a)
    return make(mig(a), mag(a), a)


def square(a) -> Interval:
    """x**2 with the tight even rule: lower bound 0 when the interval straddles 0."""
    a = as_interval(a)
    lo_m, hi_m = mig(a), mag(a)
    return make(lo_m * lo_m, hi_m * hi_m, a)


def ipow(a, n: int) -> Interval:
    """Integer power (seed Eq. 6.18): even powers are even functions, odd ones monotone."""
    n = int(n)
    a = as_interval(a)
    if n == 0:
        one = jnp.ones_like(a.lo)
        lo, hi = same_nan(one, one, a.lo)
        return make(lo, hi, a)
    if n < 0:
        return recip(ipow(a, -n))
    if n == 1:
        return a
    if n == 2:
        return square(a)
    fn = lambda v: lax.integer_pow(v, n)  # noqa: E731 - exact repeated squaring
    return even(fn)(a) if n % 2 == 0 else monotone_increasing(fn)(a)


def pow(a, b) -> Interval:  # noqa: A001 - mirrors jnp.pow
    """Real power ``a ** b`` (either may be an interval).

    A concrete integer exponent uses `ipow`. Otherwise the base is restricted to
    ``a >= 0`` (the rest is dropped and flagged), where ``a ** b`` is monotone in each
    argument, so the hull of the four corners encloses it. A traced exponent with a
    negative base gives the entire line (jnp.power is real there for integer exponents).
    """
    if not isinstance(b, Interval) and not isinstance(b, jax.core.Tracer):
        b_np = np.asarray(b)
        if b_np.ndim == 0 and np.isfinite(b_np) and float(b_np) == int(b_np):
            return ipow(a, int(b_np))
    exponent_traced = isinstance(b, Interval) or isinstance(b, jax.core.Tracer)
    a, b = as_interval(a), as_interval(b)
    a_pos = restrict(a, 0.0)
    c = [jnp.power(u, v) for u in (a_pos.lo, a_pos.hi) for v in (b.lo, b.hi)]
    lo = jnp.minimum(jnp.minimum(c[0], c[1]), jnp.minimum(c[2], c[3]))
    hi = jnp.maximum(jnp.maximum(c[0], c[1]), jnp.maximum(c[2], c[3]))
    if exponent_traced:
        neg_base = a.lo < 0
        lo = jnp.where(neg_base, -jnp.inf, lo)
        hi = jnp.where(neg_base, jnp.inf, hi)
        lo, hi = same_nan(lo, hi, a.lo, b.lo)
        return make(lo, hi, a, b)
    lo, hi = same_nan(lo, hi, a_pos.lo, b.lo)
    return make(lo, hi, a_pos, b)


sqrt = monotone_on(jnp.sqrt, lower=0.0)
log = monotone_on(jnp.log, lower=0.0)
cbrt = monotone_increasing(jnp.cbrt)
exp = monotone_increasing(jnp.exp)
atan = monotone_increasing(jnp.arctan)
sinh = monotone_increasing(jnp.sinh)
cosh = even(jnp.cosh)
floor = monotone_increasing(jnp.floor)
ceil = monotone_increasing(jnp.ceil)
sign = monotone_increasing(jnp.sign)
for _f, _n in ((sqrt, "sqrt"), (log, "log"), (cbrt, "cbrt"), (exp, "exp"),
               (atan, "atan"), (sinh, "sinh"), (cosh, "cosh"), (floor, "floor"),
               (ceil, "ceil"), (sign, "sign")):
    _f.__name__ = _n
    _f.__doc__ = f"Interval {_n} (monotone/even rule; domain parts dropped and flagged)."

# XLA's float32 tanh is a rational approximation that is off by up to 4.6 ulps and not
# monotone near saturation (measured on 2M points in [-10, 10]: 274,788 steps down, the
# largest 6 ulps), so [tanh(lo), tanh(hi)] can come out inverted (lo > hi: read as
# empty, a root lost). The rule pads by twice that error, so that it holds both the true
# values and XLA's own values at points inside, and stays within [-1, 1].
_TANH_ULPS = 10.0


def tanh(a) -> Interval:
    """Interval tanh: the endpoint values padded by `_TANH_ULPS`, clipped to [-1, 1]."""
    a = as_interval(a)
    padded = widen(Interval(jnp.tanh(a.lo), jnp.tanh(a.hi), a.defined), _TANH_ULPS)
    lo = jnp.maximum(padded.lo, -1.0)
    hi = jnp.minimum(padded.hi, 1.0)
    return make(lo, hi, a)


def atan2(y, x) -> Interval:
    """Interval atan2(y, x), the angle of (x, y) in [-pi, pi]. On a box that holds neither
    the origin nor a piece of the branch cut (x < 0, y = 0) the angle is continuous and
    its extremes lie at corners; otherwise the result is [-pi, pi]."""
    y, x = as_interval(y), as_interval(x)
    corners = jnp.stack([jnp.arctan2(yy, xx) for yy in (y.lo, y.hi) for xx in (x.lo, x.hi)])
    cut = (x.lo < 0) & (y.lo <= 0) & (y.hi >= 0)
    pi = jnp.float32(_PI)
    lo = jnp.where(cut, -pi, jnp.min(corners, axis=0))
    hi = jnp.where(cut, pi, jnp.max(corners, axis=0))
    lo, hi = same_nan(lo, hi, y.lo, x.lo)
    return make(lo, hi, y, x)


# Beyond this magnitude the f32 position of an extremum (error ~|x| 1.5e-7) can miss
# it by more than an ulp of 1 ((|x| 1.5e-7)^2 / 2); answer [-1, 1] there.
TRIG_MAX_ARG = 2.0**11


def periodic(fn, max_at: float, min_at: float, max_value: float, min_value: float,
             period: float = 2.0 * _PI):
    """Rule of a periodic function with one maximum `max_value` (at phase `max_at`) and
    one minimum (at `min_at`) per period: the endpoint values, widened to the extreme value wherever
    the interval holds an extremum; the whole range beyond `TRIG_MAX_ARG`."""

    def rule(a) -> Interval:
        a = as_interval(a)
        f_lo, f_hi = fn(a.lo), fn(a.hi)
        lo, hi = jnp.minimum(f_lo, f_hi), jnp.maximum(f_lo, f_hi)
        has = lambda phase: jnp.ceil((a.lo - phase) / period) * period + phase <= a.hi  # noqa: E731
        wide = ~((a.hi - a.lo) < period) | (mag(a) > TRIG_MAX_ARG)
        hi = jnp.where(has(max_at) | wide, max_value, hi)
        lo = jnp.where(has(min_at) | wide, min_value, lo)
        lo, hi = same_nan(lo, hi, a.lo, a.hi)
        return make(lo, hi, a)

    return rule


cos = periodic(jnp.cos, 0.0, _PI, 1.0, -1.0)
sin = periodic(jnp.sin, 0.5 * _PI, -0.5 * _PI, 1.0, -1.0)
cos.__name__, sin.__name__ = "cos", "sin"
cos.__doc__ = "Interval cos (periodic rule: extrema at 2k pi and (2k+1) pi)."
sin.__doc__ = "Interval sin (periodic rule: extrema at pi/2 + 2k pi and -pi/2 + 2k pi)."


def tan(a) -> Interval:
    """tan: monotone between poles; the entire line if a pole (k+1/2)*pi is inside."""
    a = as_interval(a)
    t_lo, t_hi = jnp.tan(a.lo), jnp.tan(a.hi)
    k_lo = jnp.floor((a.lo - 0.5 * _PI) / _PI)
    k_hi = jnp.floor((a.hi - 0.5 * _PI) / _PI)
    # f32 multiples of pi drift from the true poles; tan itself jumping from + to - is
    # the robust sign that a pole lies between the endpoints.
    pole = ((k_lo != k_hi) | (t_hi < t_lo) | ~((a.hi - a.lo) < _PI)
            | (mag(a) > TRIG_MAX_ARG))
    lo = jnp.where(pole, -jnp.inf, t_lo)
    hi = jnp.where(pole, jnp.inf, t_hi)
    lo, hi = same_nan(lo, hi, a.lo, a.hi)
    return make(lo, hi, a)


def minimum(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return make(jnp.minimum(a.lo, b.lo), jnp.minimum(a.hi, b.hi), a, b)


def maximum(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return make(jnp.maximum(a.lo, b.lo), jnp.maximum(a.hi, b.hi), a, b)


def clamp(lower, x, upper) -> Interval:
    """``min(max(x, lower), upper)`` (argument order of lax.clamp)."""
    return minimum(maximum(x, lower), upper)


def _eps(dtype) -> float:
    """Machine epsilon of a float dtype; 0 for integers (their arithmetic is exact)."""
    return float(jnp.finfo(dtype).eps) if jnp.issubdtype(dtype, jnp.floating) else 0.0


def fmod(a, b) -> Interval:
    """C fmod / lax.rem: ``a - trunc(a / b) * b``, sign of `a`, ``|r| < |b|``.

    Exact (monotone) when a point divisor and `a` stay within one period; otherwise
    bounded by sign(a), ``|r| <= |a|`` and ``|r| < max |b|``.
    """
    a, b = as_interval(a), as_interval(b)
    m = mag(b)
    lo = jnp.where(a.lo >= 0, 0.0, jnp.maximum(a.lo, -m))
    hi = jnp.where(a.hi <= 0, 0.0, jnp.minimum(a.hi, m))
    # fmod is exact in floating point; within one period it is x - const, increasing.
    # No wrap iff the box width plus |remainder at the end nearer 0| stays below |m|
    # (a margin of 4 ulps of |m| covers the rounding of the width).
    r_lo, r_hi = lax.rem(a.lo, b.lo), lax.rem(a.hi, b.lo)
    near_zero = jnp.where(a.lo >= 0, jnp.abs(r_lo), jnp.abs(r_hi))
    span = (a.hi - a.lo) + near_zero
    one_period = ((b.lo == b.hi) & ((a.lo >= 0) | (a.hi <= 0)) & (r_lo <= r_hi)
                  & (span < m * (1.0 - 4.0 * _eps(m.dtype))))
    lo = jnp.where(one_period, r_lo, lo)
    hi = jnp.where(one_period, r_hi, hi)
    # fmod by 0 is undefined: a zero divisor is dropped and flagged, [0, 0] is empty.
    divisor_zero = (b.lo <= 0) & (b.hi >= 0)
    only_zero = jnp.where((b.lo == 0) & (b.hi == 0), jnp.nan, 0.0)
    lo, hi = same_nan(lo, hi, a.lo, b.lo, only_zero)
    return make(lo, hi, a, b, defined=~divisor_zero)



# -------------------------------------------------------------------------- rounding

def widen(a: Interval, ulps: float = 1.0, scale=None) -> Interval:
    """Pad outward by about `ulps` units in the last place of each endpoint (or of
    `scale`, when larger: the terms' magnitude for sums) plus the smallest normal number
    (XLA flushes subnormals to zero on CPU); ``+inf`` lower ends become finite."""
    a = as_interval(a)
    finfo = jnp.finfo(a.lo.dtype)
    rel = jnp.minimum(ulps * float(finfo.eps), 1.0)  # beyond 100% the bound is moot
    tiny = float(finfo.tiny)
    m_lo, m_hi = jnp.abs(a.lo), jnp.abs(a.hi)
    if scale is not None:
        m_lo, m_hi = jnp.maximum(m_lo, scale), jnp.maximum(m_hi, scale)
    lo = a.lo - (m_lo * rel + tiny)
    hi = a.hi + (m_hi * rel + tiny)
    lo = jnp.where(jnp.isinf(a.lo), jnp.nextafter(a.lo, -jnp.inf), lo)
    hi = jnp.where(jnp.isinf(a.hi), jnp.nextafter(a.hi, jnp.inf), hi)
    return Interval(lo, hi, a.defined)



Interval.ops = sys.modules[__name__]
