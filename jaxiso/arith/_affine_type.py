"""The `Affine` (AF1) type: conversion to and from Intervals and the shared helpers of
the affine rules. The conventions and the operations are in `_affine`, the `aa`
namespace, which re-exports everything here.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import _interval as ia
from ._interval import Interval, OperatorsMixin

# Package-internal, shared by arith's modules (not API): `is_empty`, `padded_range`,
# `n_of`, `lift`, `all_defined`, `interval_fallback`, `select`, `is_finite`, `guard`,
# `guard_unbounded`.


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False)
class Affine(OperatorsMixin):
    """A batch of AF1 affine forms (operators as for `Interval`).

    Attributes:
      center: [*S] central values.
      dev: [*S, n] partial deviations, one per noise symbol (n is static).
      err: [*S] non-negative accumulated error (the AF1 ``e_{n+1}`` term).
      defined: [*S] bool, as for `Interval` (False where a domain part was dropped).
      lo, hi: [*S] bounds known besides the form (default -inf, inf): the values are
        the form's that lie in ``[lo, hi]``. A rule whose interval result is cheap sets
        them (``min(h, 0) <= 0`` where the form's range reaches above 0, so that
        ``exp`` of it does not overflow); a case of a ``where`` is bounded where it is
        taken (`_branches`). `to_interval` and `padded_range` clip by them, so every
        rule linearises over the values only; a rule that ignores them is still sound.
    """

    center: jax.Array
    dev: jax.Array
    err: jax.Array
    defined: jax.Array = None
    lo: jax.Array = None
    hi: jax.Array = None

    def __post_init__(self):
        # defaults only for the fields left out: JAX rebuilds the pytree with every
        # field given, sometimes as placeholders that are no arrays (explaining a jit
        # cache miss), which must not be read here
        if self.defined is None:
            object.__setattr__(self, "defined", jnp.ones(np.shape(self.center), bool))
        for name, end in (("lo", -jnp.inf), ("hi", jnp.inf)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, jnp.full(np.shape(self.center), end,
                                                        jnp.result_type(self.center)))

    __array_ufunc__ = None

    @property
    def n(self) -> int:
        return int(np.shape(self.dev)[-1])

    @property
    def shape(self):
        return np.shape(self.center)

    def __getitem__(self, index):
        s = self.shape
        idx = index if isinstance(index, tuple) else (index,)
        def part(a):
            return jnp.broadcast_to(a, s)[index]

        return Affine(part(self.center),
                      jnp.broadcast_to(self.dev, s + (self.n,))[idx + (Ellipsis, slice(None))],
                      part(self.err), part(self.defined), part(self.lo), part(self.hi))

    def __repr__(self):
        return (f"Affine(center={self.center!r}, dev={self.dev!r}, err={self.err!r}, "
                f"defined={self.defined!r}, lo={self.lo!r}, hi={self.hi!r})")


# ----------------------------------------------------------------------- conversion


def is_empty(x: Affine):
    return jnp.isnan(x.err)


def radius(x: Affine):
    """rad(x) = sum |dev_i| + err (Eq. 6.10 with the AF1 error term)."""
    return jnp.sum(jnp.abs(x.dev), axis=-1) + x.err


def to_interval(x: Affine) -> Interval:
    """Eq. 6.9: ``[center - rad, center + rad]``, clipped by the bounds."""
    return _clipped(x, *_form_range(x))


def _form_range(x: Affine):
    """The form's own ``center -+ rad`` (an overflowed form: the whole line)."""
    r = radius(x)
    lo, hi = x.center - r, x.center + r
    # inf - inf from an overflowed form is not empty: only a NaN error term means empty
    overflow = ~is_empty(x)
    lo = jnp.where(jnp.isnan(lo) & overflow, -jnp.inf, lo)
    hi = jnp.where(jnp.isnan(hi) & overflow, jnp.inf, hi)
    return lo, hi


def _clipped(x: Affine, lo, hi) -> Interval:
    """[lo, hi] clipped by the form's bounds; where rounding left the two disjoint (both
    enclose the values: it cannot be otherwise) the range is kept unclipped."""
    c_lo, c_hi = jnp.maximum(lo, x.lo), jnp.minimum(hi, x.hi)
    keep = c_lo <= c_hi
    return Interval(jnp.where(keep, c_lo, lo), jnp.where(keep, c_hi, hi), x.defined)


def padded_range(x: Affine) -> Interval:
    """`to_interval` padded by an ulp of ``|center| + rad``: the range the rules work on.
    Rounding ``center +- rad`` to nearest can cut into the set (far from 0 the centre
    cannot even hold a small endpoint), so internal conversions pad all but exact points."""
    lo, hi = _form_range(x)
    finfo = jnp.finfo(jnp.result_type(x.center))
    pad = float(finfo.eps) * jnp.abs(x.center) + float(finfo.eps) * radius(x) + float(
        finfo.tiny)  # two terms: their sum could overflow near the float32 maximum
    # overflowed (NaN: iv is already entire), an infinite point or any exact point
    # (centre +- 0 is not rounded: floor(x) = [k, k] must compare with 0 as IA does)
    point = (x.err == 0) & jnp.all(x.dev == 0, axis=-1)
    pad = jnp.where(jnp.isnan(x.center) | jnp.isinf(x.center) | point, 0.0, pad)
    return _clipped(x, lo - pad, hi + pad)


def bounded(x: Affine, iv: Interval) -> Affine:
    """x with its bounds narrowed to `iv` too (an enclosure of x's values)."""
    return dataclasses.replace(x, lo=jnp.fmax(x.lo, iv.lo), hi=jnp.fmin(x.hi, iv.hi))


def from_interval(x, symbol: int | None = None, n: int = 1) -> Affine:
    """Eq. 6.8: centre = midpoint, the radius on noise symbol `symbol` (or on the error
    term when `symbol` is None). Unbounded radii always go to the error term."""
    x = ia.as_interval(x)
    c = ia.mid(x)
    r = ia.rad(x)
    # an overflowed point [inf, inf] stays that point (not the whole line): a box where
    # x^500 overflows is rejected as in interval arithmetic
    inf_point = (x.lo == x.hi) & jnp.isinf(x.lo)
    c = jnp.where(inf_point, x.lo, c)
    r = jnp.where(inf_point, 0.0, r)
    finite = jnp.isfinite(r)
    if symbol is None:
        dev = jnp.zeros(np.shape(c) + (n,), c.dtype)
        err = r
    else:
        if not 0 <= symbol < n:
            raise ValueError(f"symbol {symbol} out of range for n={n} noise symbols")
        onehot = jnp.zeros((n,), c.dtype).at[symbol].set(1.0)
        dev = jnp.where(finite, r, 0.0)[..., None] * onehot
        err = jnp.where(finite, 0.0, r)
    return Affine(c, dev, err, x.defined)


def with_symbols(x: Affine, n: int) -> Affine:
    """x over `n` noise symbols: its own are the first ``x.n``, the others get zero
    deviations (the same set). Symbols are numbered alike in every form of one
    evaluation (the coordinates' first, then the fresh ones), so a form with fewer of
    them -- a constant or an Interval lifted with one symbol -- meets a form that took
    fresh ones by this padding. Fewer than ``x.n`` is an error: no symbol is dropped."""
    if x.n == n:
        return x
    if x.n > n:
        raise ValueError(f"an affine form with {x.n} noise symbols cannot have {n}")
    pad = [(0, 0)] * (np.ndim(x.dev) - 1) + [(0, n - x.n)]
    return dataclasses.replace(x, dev=jnp.pad(x.dev, pad))


def as_affine(x, n: int) -> Affine:
    """An Affine over `n` noise symbols (padded with zero deviations: `with_symbols`);
    an Interval on the error term; an array as an exact point."""
    if isinstance(x, Affine):
        return with_symbols(x, n)
    if isinstance(x, Interval):
        return from_interval(x, None, n)
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    # a NaN constant (jnp.where(c, jnp.nan, f), log(-1) folded) is no value at all: the
    # empty form (NaN error term), as the point interval [NaN, NaN] is empty -- not a
    # NaN centre, which reads as an overflow, the entire line
    err = jnp.where(jnp.isnan(x), jnp.nan, jnp.zeros_like(x))
    # the point is its own bounds (so a sum with it keeps the other's: ``h - 0``)
    return Affine(x, jnp.zeros(x.shape + (n,), x.dtype), err, None,
                  jnp.where(jnp.isnan(x), -jnp.inf, x), jnp.where(jnp.isnan(x), jnp.inf, x))


def n_of(*xs) -> int:
    """The symbol count the operands meet at: the largest of their forms' (1 if none)."""
    return max([x.n for x in xs if isinstance(x, Affine)], default=1)


def lift(*xs):
    """The operands as affine forms over one symbol count (`n_of`)."""
    n = n_of(*xs)
    return [as_affine(x, n) for x in xs]


def all_defined(*xs):
    f = xs[0].defined
    for x in xs[1:]:
        f = f & x.defined
    return f


def interval_fallback(iv: Interval, n: int) -> Affine:
    """An Interval result as an affine form with no correlation (error term only)."""
    return from_interval(iv, None, n)


def select(mask, a: Affine, b: Affine) -> Affine:
    return Affine(jnp.where(mask, a.center, b.center),
                  jnp.where(mask[..., None], a.dev, b.dev),
                  jnp.where(mask, a.err, b.err),
                  jnp.where(mask, a.defined, b.defined),
                  jnp.where(mask, a.lo, b.lo), jnp.where(mask, a.hi, b.hi))


def is_finite(x: Affine):
    # one reduction instead of three: the sum is finite iff every term is
    return jnp.isfinite(x.center + x.err + jnp.sum(x.dev, axis=-1))


def guard(result: Affine, fallback_iv: Interval) -> Affine:
    """Use the interval fallback wherever the affine result is not finite."""
    return select(is_finite(result), result, interval_fallback(fallback_iv, result.n))


def guard_unbounded(result: Affine, *inputs: Affine, fallback: Interval | None = None
                    ) -> Affine:
    """Overflow (or inf * 0) in a polynomial operation: the interval result `fallback`
    lifted (an infinite point such as inf * [1, 2] stays that point, so a box where f is
    +inf is rejected as in interval arithmetic) or else the entire line; results of empty
    (NaN) inputs stay empty."""
    empty = is_empty(inputs[0])
    for x in inputs[1:]:
        empty = empty | is_empty(x)
    if fallback is None:
        unbounded = Affine(jnp.zeros_like(result.center), jnp.zeros_like(result.dev),
                           jnp.full_like(result.err, jnp.inf), result.defined)
    else:
        unbounded = interval_fallback(fallback, result.n)
        unbounded = Affine(unbounded.center, unbounded.dev, unbounded.err, result.defined)
    out = select(is_finite(result) | empty, result, unbounded)
    # 0 * (empty) must stay empty: the products above treat 0 * NaN as 0
    return Affine(out.center, out.dev, jnp.where(empty, jnp.nan, out.err), out.defined)
