"""Three-valued logic on Intervals of bools, and `select_n` / `where` (part of the `ia`
namespace: see `_interval` for the conventions)."""

from __future__ import annotations

import jax.numpy as jnp

from ._interval_type import Interval, as_interval, make


def _truth(certain, possible, *parents) -> Interval:
    return make(certain, possible, *parents)


def lt(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return _truth(a.hi < b.lo, a.lo < b.hi, a, b)


def le(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return _truth(a.hi <= b.lo, a.lo <= b.hi, a, b)


def gt(a, b) -> Interval:
    return lt(b, a)


def ge(a, b) -> Interval:
    return le(b, a)


def eq(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    certain = (a.lo == a.hi) & (b.lo == b.hi) & (a.lo == b.lo)
    return _truth(certain, (a.lo <= b.hi) & (b.lo <= a.hi), a, b)


def ne(a, b) -> Interval:
    return logical_not(eq(a, b))


def logical_and(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return _truth(a.lo & b.lo, a.hi & b.hi, a, b)


def logical_or(a, b) -> Interval:
    a, b = as_interval(a), as_interval(b)
    return _truth(a.lo | b.lo, a.hi | b.hi, a, b)


def logical_not(a) -> Interval:
    a = as_interval(a)
    return _truth(~a.hi, ~a.lo, a)


def certainly(c):
    """True where a three-valued condition is certainly true."""
    return as_interval(c).lo


def possibly(c):
    """True where a three-valued condition may be true."""
    return as_interval(c).hi


is_true = certainly


def is_false(c):
    return ~as_interval(c).hi


def is_unknown(c):
    c = as_interval(c)
    return c.hi & ~c.lo


def select_n(which, *cases) -> Interval:
    """lax.select_n over intervals: the hull of every case whose index `which` may take.

    `which` is a bool/int array or an Interval of them (three-valued when bool).
    """
    which = as_interval(which)
    cases = [as_interval(c) for c in cases]
    w_lo, w_hi = which.lo.astype(jnp.int32), which.hi.astype(jnp.int32)
    lo = hi = None
    flag = which.defined
    for i, c in enumerate(cases):
        take = (w_lo <= i) & (i <= w_hi)
        c_lo = jnp.where(take, c.lo, jnp.nan)
        c_hi = jnp.where(take, c.hi, jnp.nan)
        lo = c_lo if lo is None else jnp.fmin(lo, c_lo)
        hi = c_hi if hi is None else jnp.fmax(hi, c_hi)
        flag = flag & (c.defined | ~take)
    return Interval(lo, hi, flag)


def where(condition, x, y) -> Interval:
    """``x`` where certainly true, ``y`` where certainly false, their hull if unknown."""
    return select_n(condition, y, x)
