"""The `Interval` type: constructors, queries and rule builders (monotone, even,
restricted to a domain). The conventions and the operations are in `_interval`, the
`ia` namespace, which re-exports everything here.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

# Package-internal, shared by arith's modules (not API): `make`, `same_nan` and the
# operators' module `OperatorsMixin.ops`.


class OperatorsMixin:
    """Python operators dispatching to the pure functions of the module in `ops`
    (shared by `Interval` and `Affine`; comparisons are three-valued)."""

    ops = None  # the arithmetic module; set after it is defined

    def __add__(self, o): return self.ops.add(self, o)
    def __radd__(self, o): return self.ops.add(o, self)
    def __sub__(self, o): return self.ops.sub(self, o)
    def __rsub__(self, o): return self.ops.sub(o, self)
    def __mul__(self, o): return self.ops.mul(self, o)
    def __rmul__(self, o): return self.ops.mul(o, self)
    def __truediv__(self, o): return self.ops.div(self, o)
    def __rtruediv__(self, o): return self.ops.div(o, self)
    def __neg__(self): return self.ops.neg(self)
    def __pos__(self): return self
    def __abs__(self): return self.ops.abs(self)
    def __lt__(self, o): return self.ops.lt(self, o)
    def __le__(self, o): return self.ops.le(self, o)
    def __gt__(self, o): return self.ops.gt(self, o)
    def __ge__(self, o): return self.ops.ge(self, o)

    def __pow__(self, exponent):
        if isinstance(exponent, (int, np.integer)):
            return self.ops.ipow(self, int(exponent))
        return self.ops.pow(self, exponent)

    def __bool__(self):
        raise TypeError(f"a {type(self).__name__} has no single truth value; use "
                        "certainly(), possibly() or contains()")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False)
class Interval(OperatorsMixin):
    """A batch of closed intervals ``[lo, hi]``.

    Attributes:
      lo, hi: arrays of the same shape (any batch shape); NaN marks an empty interval.
      defined: bool array of that shape; False where some point of the input box was
        outside the domain of an operation (and was dropped). Defaults to all True.

    Build a checked interval from user data with `interval(lo, hi)`; the bare
    constructor does no validation (it must accept tracers and pytree placeholders).
    Operators ``+ - * / ** < <= > >= & | ~`` and ``abs``/unary minus dispatch to the
    functions of this module.
    """

    lo: jax.Array
    hi: jax.Array
    defined: jax.Array = None

    def __post_init__(self):
        if self.defined is None:
            shape = np.broadcast_shapes(np.shape(self.lo), np.shape(self.hi))
            object.__setattr__(self, "defined", jnp.ones(shape, bool))

    __array_ufunc__ = None  # make numpy defer to our reflected operators

    @property
    def shape(self):
        return np.broadcast_shapes(np.shape(self.lo), np.shape(self.hi))

    @property
    def dtype(self):
        return jnp.result_type(self.lo, self.hi)

    @property
    def ndim(self):
        return len(self.shape)

    def __getitem__(self, index):
        return Interval(_bcast(self.lo, self)[index], _bcast(self.hi, self)[index],
                        _bcast(self.defined, self)[index])

    def __repr__(self):
        return f"Interval(lo={self.lo!r}, hi={self.hi!r}, defined={self.defined!r})"

    # three-valued logic (comparisons and arithmetic come from OperatorsMixin)
    def __and__(self, other): return self.ops.logical_and(self, other)
    def __rand__(self, other): return self.ops.logical_and(other, self)
    def __or__(self, other): return self.ops.logical_or(self, other)
    def __ror__(self, other): return self.ops.logical_or(other, self)
    def __invert__(self): return self.ops.logical_not(self)
    def __rpow__(self, base): return self.ops.pow(base, self)


def _bcast(x, like: Interval):
    return jnp.broadcast_to(x, like.shape)


# --------------------------------------------------------------------------- building


def interval(lo, hi, dtype=None) -> Interval:
    """Checked constructor for user data: ``lo <= hi``, no NaN (concrete inputs only)."""
    lo, hi = jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)
    check_endpoints(lo, hi)
    shape = jnp.broadcast_shapes(lo.shape, hi.shape)
    return Interval(jnp.broadcast_to(lo, shape), jnp.broadcast_to(hi, shape))


def check_endpoints(lo, hi, what="interval"):
    """Raise ValueError for NaN endpoints or lo > hi (skipped for traced values)."""
    if isinstance(lo, jax.core.Tracer) or isinstance(hi, jax.core.Tracer):
        return
    lo_np, hi_np = np.broadcast_arrays(np.atleast_1d(lo), np.atleast_1d(hi))
    if np.isnan(lo_np).any() or np.isnan(hi_np).any():
        raise ValueError(f"{what}: endpoints must not be NaN (an empty input box is not "
                         "allowed; NaN marks empty results only)")
    bad = np.argwhere(lo_np > hi_np)
    if bad.size:
        i = tuple(int(k) for k in bad[0])
        raise ValueError(f"{what}: needs lo <= hi, but at index {i} lo={lo_np[i]} > "
                         f"hi={hi_np[i]} ({len(bad)} such elements)")


def point(x) -> Interval:
    """The degenerate interval ``[x, x]``."""
    x = jnp.asarray(x)
    return Interval(x, x)


def as_interval(x) -> Interval:
    """An Interval unchanged; anything array-like as a point interval."""
    return x if isinstance(x, Interval) else point(x)


def entire(shape=(), dtype=jnp.float32) -> Interval:
    return Interval(jnp.full(shape, -jnp.inf, dtype), jnp.full(shape, jnp.inf, dtype))


def empty(shape=(), dtype=jnp.float32) -> Interval:
    nan = jnp.full(shape, jnp.nan, dtype)
    return Interval(nan, nan, jnp.zeros(shape, bool))


def make(lo, hi, *parents: Interval, defined=None) -> Interval:
    """Result interval whose `defined` flag is the AND of its parents' (and `defined`)."""
    flag = defined
    for p in parents:
        flag = p.defined if flag is None else flag & p.defined
    if flag is None:
        flag = jnp.ones(jnp.broadcast_shapes(jnp.shape(lo), jnp.shape(hi)), bool)
    else:
        flag = jnp.broadcast_to(flag, jnp.broadcast_shapes(jnp.shape(lo), jnp.shape(flag)))
    return Interval(lo, hi, flag)


def same_nan(lo, hi, *srcs):
    """Propagate emptiness of `srcs` into both endpoints (one mechanism for all rules)."""
    bad = None
    for s in srcs:
        b = jnp.isnan(s)
        bad = b if bad is None else bad | b
    return jnp.where(bad, jnp.nan, lo), jnp.where(bad, jnp.nan, hi)


# ---------------------------------------------------------------------------- queries


def width(x: Interval):
    return x.hi - x.lo


def mid(x: Interval):
    """Midpoint; finite endpoint for half-unbounded intervals, 0 for the entire line."""
    m = 0.5 * x.lo + 0.5 * x.hi
    m = jnp.where(jnp.isinf(x.lo) & jnp.isfinite(x.hi), x.hi, m)
    m = jnp.where(jnp.isinf(x.hi) & jnp.isfinite(x.lo), x.lo, m)
    return jnp.where(jnp.isinf(x.lo) & jnp.isinf(x.hi), 0.0, m)


def rad(x: Interval):
    """Radius about `mid` (covers both endpoints after rounding)."""
    m = mid(x)
    return jnp.maximum(x.hi - m, m - x.lo)


def mig(x: Interval):
    """Mignitude: the smallest |v| over the interval."""
    return jnp.abs(jnp.clip(0.0, x.lo, x.hi))


def mag(x: Interval):
    """Magnitude: the largest |v| over the interval."""
    return jnp.maximum(-x.lo, x.hi)


def contains(x: Interval, value=0.0):
    """True where ``lo <= value <= hi`` (False for empty intervals)."""
    return (x.lo <= value) & (value <= x.hi)


def is_empty(x: Interval):
    return jnp.isnan(x.lo) | jnp.isnan(x.hi)


def hull(a, b) -> Interval:
    """Smallest interval containing both (empty is the identity)."""
    a, b = as_interval(a), as_interval(b)
    return make(jnp.fmin(a.lo, b.lo), jnp.fmax(a.hi, b.hi), a, b)


def intersect(a, b) -> Interval:
    """Intersection; empty (NaN) where the two are disjoint."""
    a, b = as_interval(a), as_interval(b)
    lo, hi = jnp.maximum(a.lo, b.lo), jnp.minimum(a.hi, b.hi)
    lo, hi = same_nan(lo, hi, jnp.where(lo > hi, jnp.nan, 0.0))
    return make(lo, hi, a, b)


# --------------------------------------------------------------------- rule builders


def monotone_increasing(fn):
    """Interval rule of a non-decreasing function: ``[fn(lo), fn(hi)]``."""

    def rule(x):
        x = as_interval(x)
        return make(fn(x.lo), fn(x.hi), x)

    return rule


def monotone_decreasing(fn):
    """Interval rule of a non-increasing function: ``[fn(hi), fn(lo)]``."""

    def rule(x):
        x = as_interval(x)
        return make(fn(x.hi), fn(x.lo), x)

    return rule


def even(fn):
    """Rule of an even function that is non-decreasing on [0, inf): ``fn(|x|)``."""

    def rule(x):
        x = as_interval(x)
        return make(fn(mig(x)), fn(mag(x)), x)

    return rule


def restrict(x: Interval, lower=-jnp.inf, upper=jnp.inf) -> Interval:
    """Drop the part of `x` outside ``[lower, upper]`` (the domain), flagging it."""
    x = as_interval(x)
    inside = (x.lo >= lower) & (x.hi <= upper)
    lo, hi = jnp.maximum(x.lo, lower), jnp.minimum(x.hi, upper)
    lo, hi = same_nan(lo, hi, jnp.where(lo > hi, jnp.nan, 0.0))
    return make(lo, hi, x, defined=inside)


def monotone_on(fn, lower=-jnp.inf, upper=jnp.inf, increasing=True):
    """Rule of a function monotone on its domain ``[lower, upper]`` (sqrt, log, ...)."""
    inner = monotone_increasing(fn) if increasing else monotone_decreasing(fn)
    return lambda x: inner(restrict(x, lower, upper))
