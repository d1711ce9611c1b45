"""The rule registry of `extend`: one `Rule` record per JAX primitive, by name.

A record holds the primitive's interval rule, its affine rule and its rounding model;
records are made by helpers for kinds of primitive (correctly rounded, exact, monotone on
a domain, parametrised monotone, comparison, data movement). A rule is
``rule(*invals, **eqn_params)``: invals are `Interval` (or `Affine`) values of batch
shape S for traced inputs and plain arrays for constants; it returns one value (a list
for primitives with several results). `register_rule` adds or replaces a rule.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, MutableMapping

import jax
import jax.numpy as jnp
from jax import lax

from . import _affine as aa
from . import _array_rules as ar
from . import _interval as ia
from . import _ulps
from ._interval import Interval

__all__ = ["Rule", "RULES", "NAMED_CALLS", "INTERVAL_CALLS", "BY_ARITHMETIC", "ARITHMETICS",
           "register_rule"]

ARITHMETICS = ("interval", "affine")


@dataclasses.dataclass(frozen=True)
class Rule:
    """What `extend` knows about one primitive.

    Attributes:
      interval: the rule over Intervals (None: none registered).
      affine: the rule used when some input is an Affine (None: none registered);
        integer and boolean values stay Intervals in affine mode.
      ulps: rounding error of the result in ulps (0: exact), or a model
        ``ulps(invals, params)`` returning a float or an array of the result's shape.
      scale: ``scale(invals, params)``, the magnitude the rounding error grows with when
        it exceeds the result's (sums, dots: the terms'), or None.
      same_args: comparisons: the truth of ``x OP x`` for one variable x (decided exactly,
        no dependency problem), or None.
      data_operands: primitives that only move data: the slice of their operands that
        carry values (the primitive is applied to each component; the others are
        constant indices), or None.
      with_body: named calls only: the rule is called with ``body=fn``, the library
        function itself on points (to read constants such as elu's alpha from it).
    """

    interval: Callable | None = None
    affine: Callable | None = None
    ulps: float | Callable = 0.0
    scale: Callable | None = None
    same_args: bool | None = None
    data_operands: slice | None = None
    with_body: bool = False  # named calls: the rule also gets ``body=`` its point function

    def rounding(self, invals, params):
        """(ulps, scale) of the result for these operands."""
        ulps = self.ulps(invals, params) if callable(self.ulps) else self.ulps
        scale = self.scale(invals, params) if self.scale is not None else None
        return ulps, scale


NO_RULE = Rule()
RULES: dict[str, Rule] = {}
# jit-wrapped library functions with a tighter rule than their body, by their jit name;
# these rules take no params.
NAMED_CALLS: dict[str, Rule] = {}
# jit-wrapped library functions that affine mode evaluates in interval arithmetic on the
# ranges of their operands (the result lifted back on the error term): piecewise bodies
# that branch on the sign of a remainder. An interval-fallback result carries its range
# as centre +- radius, padded by an ulp, so a remainder in [0, r] would compare with 0 as
# "unknown" and select the hull of both branches (x // 0.5 an extra step wide).
INTERVAL_CALLS: frozenset[str] = frozenset({"remainder", "floor_divide", "divmod"})


class _ArithmeticView(MutableMapping):
    """The rules of one arithmetic by primitive name: a live view of `RULES`."""

    def __init__(self, arithmetic: str):
        self.arithmetic = arithmetic

    def __getitem__(self, name):
        rule = getattr(RULES.get(name, NO_RULE), self.arithmetic)
        if rule is None:
            raise KeyError(name)
        return rule

    def __setitem__(self, name, rule):
        RULES[name] = dataclasses.replace(RULES.get(name, NO_RULE), **{self.arithmetic: rule})

    def __delitem__(self, name):
        self[name]  # KeyError if absent
        record = dataclasses.replace(RULES[name], **{self.arithmetic: None})
        if record == NO_RULE:
            del RULES[name]
        else:
            RULES[name] = record

    def __iter__(self):
        return iter([n for n, r in RULES.items() if getattr(r, self.arithmetic) is not None])

    def __len__(self):
        return sum(1 for _ in self)


BY_ARITHMETIC = {a: _ArithmeticView(a) for a in ARITHMETICS}


def register_rule(primitive, rule: Callable, arithmetic: str = "interval") -> None:
    """Register the extension `rule` of a JAX primitive (object or name).

    `rule(*invals, **eqn_params)` receives `Interval` (or `Affine`) values for traced
    inputs and plain arrays for constants, and returns one value (a list for primitives
    with multiple results). `arithmetic` is "interval", "affine" or "both". The rounding
    model of a built-in primitive is kept (a new primitive counts as exact).
    Soundness is the rule's responsibility: every point of the input boxes must map
    inside the result.
    """
    name = primitive if isinstance(primitive, str) else primitive.name
    targets = ARITHMETICS if arithmetic == "both" else (arithmetic,)
    for a in targets:
        if a not in BY_ARITHMETIC:
            raise ValueError(f"arithmetic must be one of {ARITHMETICS} or 'both'")
        BY_ARITHMETIC[a][name] = rule


# ------------------------------------------------------------- helpers for the kinds


def _drop_params(rule):
    """Adapt ``rule(*invals)`` to the primitive's call (params such as `accuracy` unused)."""
    return functools.wraps(rule)(lambda *invals, **_params: rule(*invals))


def _elementwise(name, ia_rule, aa_rule=None, **fields):
    """A primitive whose rules ignore its params; the affine rule defaults to the
    interval rule on the affine range (correlation not kept)."""
    aa_rule = aa.via_interval(ia_rule) if aa_rule is None else aa_rule
    RULES[name] = Rule(_drop_params(ia_rule), _drop_params(aa_rule), **fields)


def _monotone_with_params(name, fn):
    """A non-decreasing ``fn(x, **params)`` (rounding to a format or an integer)."""

    def interval_rule(x, **params):
        return ia.monotone_increasing(lambda v: fn(v, **params))(x)

    def affine_rule(x, **params):
        return aa.via_interval(ia.monotone_increasing(lambda v: fn(v, **params)))(x)

    RULES[name] = Rule(interval_rule, affine_rule)


def _div_interval(a, b) -> Interval:
    """ia.div, and lax.div on integers (truncating toward 0: monotone in the quotient)."""
    if not jnp.issubdtype(jnp.result_type(a.lo if isinstance(a, Interval) else a),
                          jnp.integer):
        return ia.div(a, b)  # a constant divisor stays one (`ia.div` scales by it)
    a, b = ia.as_interval(a), ia.as_interval(b)
    as_float = lambda x: Interval(x.lo.astype(jnp.float32), x.hi.astype(jnp.float32),  # noqa: E731
                                  x.defined)
    q = ia.div(as_float(a), as_float(b))
    big = float(jnp.iinfo(a.lo.dtype).max)
    lo = jnp.clip(jnp.trunc(q.lo), -big, big).astype(a.lo.dtype)
    hi = jnp.clip(jnp.trunc(q.hi), -big, big).astype(a.lo.dtype)
    return Interval(lo, hi, q.defined)


# ---------------------------------------------------------------- elementwise tables

# Correctly rounded. add_any sums tangents in derivative jaxprs (Mitchell's gradient test).
for _name, _ia, _aa in (("add", ia.add, aa.add), ("add_any", ia.add, aa.add),
                        ("sub", ia.sub, aa.sub), ("mul", ia.mul, aa.mul),
                        ("div", _div_interval, aa.div),
                        ("sqrt", ia.sqrt, aa.sqrt), ("square", ia.square, aa.square)):
    _elementwise(_name, _ia, _aa, ulps=_ulps.CORRECTLY_ROUNDED)

# Exact.
for _name, _ia, _aa in (("neg", ia.neg, aa.neg), ("abs", ia.abs, aa.abs),
                        ("max", ia.maximum, aa.maximum), ("min", ia.minimum, aa.minimum),
                        ("floor", ia.floor, aa.floor), ("ceil", ia.ceil, aa.ceil),
                        ("sign", ia.sign, aa.sign), ("clamp", ia.clamp, aa.clamp)):
    _elementwise(_name, _ia, _aa)

_monotone_with_params("round", lax.round)
_monotone_with_params("reduce_precision", lax.reduce_precision)
_elementwise("rem", ia.fmod, aa.fmod, ulps=1.0)

# Transcendentals; the exp family's error grows with its argument.
_EXP_LIKE = ("exp", "exp2", "expm1", "sinh", "cosh")


def _transcendental_ulps(name):
    return _ulps.exp_like if name in _EXP_LIKE else _ulps.TRANSCENDENTAL


for _name, _ia, _aa in (("exp", ia.exp, aa.exp), ("log", ia.log, aa.log),
                        ("cbrt", ia.cbrt, aa.cbrt), ("sin", ia.sin, aa.sin),
                        ("cos", ia.cos, aa.cos), ("tan", ia.tan, aa.tan),
                        ("tanh", ia.tanh, aa.tanh), ("atan", ia.atan, aa.atan),
                        ("atan2", ia.atan2, aa.atan2), ("sinh", ia.sinh, aa.sinh),
                        ("cosh", ia.cosh, aa.cosh)):
    _elementwise(_name, _ia, _aa, ulps=_transcendental_ulps(_name))

# Monotone on a domain [lower, upper] (parts outside are dropped and flagged).
for _name, _fn, _lo, _hi, _inc in (
        ("exp2", jnp.exp2, -jnp.inf, jnp.inf, True),
        ("expm1", jnp.expm1, -jnp.inf, jnp.inf, True),
        ("log1p", jnp.log1p, -1.0, jnp.inf, True),
        ("rsqrt", lax.rsqrt, 0.0, jnp.inf, False),
        ("asin", jnp.arcsin, -1.0, 1.0, True),
        ("acos", jnp.arccos, -1.0, 1.0, False),
        ("atanh", jnp.arctanh, -1.0, 1.0, True),
        ("acosh", jnp.arccosh, 1.0, jnp.inf, True),
        ("asinh", jnp.arcsinh, -jnp.inf, jnp.inf, True),
        ("logistic", jax.nn.sigmoid, -jnp.inf, jnp.inf, True),
        ("erf", jax.scipy.special.erf, -jnp.inf, jnp.inf, True)):
    _elementwise(_name, ia.monotone_on(_fn, _lo, _hi, _inc), ulps=_transcendental_ulps(_name))

# convex / concave on their domain (Chebyshev), or inflected at 0 (`aa._inflected`):
# their affine forms keep the correlation
for _name, _aa in (("expm1", aa.expm1), ("log1p", aa.log1p), ("logistic", aa.logistic),
                   ("erf", aa.erf)):
    RULES[_name] = dataclasses.replace(RULES[_name], affine=_drop_params(_aa))

RULES["pow"] = Rule(_drop_params(ia.pow), _drop_params(aa.pow), ulps=_ulps.power)
RULES["integer_pow"] = Rule(lambda x, *, y: ia.ipow(x, y), lambda x, *, y: aa.ipow(x, y),
                            ulps=_ulps.integer_power)

# Three-valued comparisons and logic: Intervals of bools in both arithmetics.
for _name, _ia, _aa, _same in (("lt", ia.lt, aa.lt, False), ("le", ia.le, aa.le, True),
                               ("gt", ia.gt, aa.gt, False), ("ge", ia.ge, aa.ge, True),
                               ("eq", ia.eq, aa.eq, True), ("ne", ia.ne, aa.ne, False)):
    _elementwise(_name, _ia, _aa, same_args=_same)
for _name, _fn in (("and", ia.logical_and), ("or", ia.logical_or), ("not", ia.logical_not)):
    _elementwise(_name, _fn, _fn)
RULES["select_n"] = Rule(_drop_params(ia.select_n), aa.select_n)  # extend passes sign=

# ---------------------------------------------------------------------- array tables

_ONE, _ALL = slice(0, 1), slice(None)
for _name, _operands in (
        ("broadcast_in_dim", _ONE), ("reshape", _ONE), ("squeeze", _ONE),
        ("expand_dims", _ONE), ("transpose", _ONE), ("rev", _ONE), ("slice", _ONE),
        ("dynamic_slice", _ONE), ("gather", _ONE), ("copy", _ONE), ("copy_p", _ONE),
        ("concatenate", _ALL), ("stack", _ALL), ("pad", slice(0, 2)), ("real", _ONE),
        ("optimization_barrier", _ALL)):
    RULES[_name] = Rule(data_operands=_operands)

RULES["convert_element_type"] = Rule(ar.convert_interval, ar.convert_affine)
RULES["reduce_sum"] = Rule(ar.reduce_sum_interval, ar.reduce_sum_affine,
                           ulps=_ulps.reduce_sum, scale=_ulps.sum_scale)
RULES["reduce_max"] = Rule(*ar.reduce_monotone(jnp.max))
RULES["reduce_min"] = Rule(*ar.reduce_monotone(jnp.min))
RULES["dot_general"] = Rule(ar.dot_interval, ar.dot_affine, ulps=_ulps.dot_general,
                            scale=_ulps.dot_scale)

NAMED_CALLS["hypot"] = Rule(ar.hypot_interval, ar.hypot_affine,
                            ulps=2.0 * _ulps.TRANSCENDENTAL)
# x // c: monotone in x by a constant c (its body takes the hull of two steps at a jump);
# returns NotImplemented for other operands, whose body is then evaluated
# jax.nn.elu: its body is where(x > 0, x, alpha * expm1(where(x > 0, 0, x))), whose hull
# across 0 takes expm1 of the whole range (bunny: pieces unbounded, hits lost); elu is
# non-decreasing, and convex for 0 < alpha <= 1 (alpha is read from the body)
NAMED_CALLS["elu"] = Rule(ar.elu_interval, ar.elu_affine, ulps=_ulps.TRANSCENDENTAL,
                          with_body=True)
# jax.nn.softplus: its body max(x, 0) + log1p(exp(-|x|)) loses the correlation between
# the two terms; softplus is increasing and convex
NAMED_CALLS["softplus"] = Rule(ar.softplus_interval, ar.softplus_affine,
                               ulps=_ulps.TRANSCENDENTAL)
# jax.nn.silu: its body x * sigmoid(x) multiplies two forms of x as if unrelated; silu
# has one minimum and bounded curvature
NAMED_CALLS["silu"] = Rule(ar.silu_interval, ar.silu_affine, ulps=_ulps.TRANSCENDENTAL)
NAMED_CALLS["floor_divide"] = Rule(ar.floor_divide_interval, ar.floor_divide_affine,
                                   ulps=0.0)
# jnp.trunc: its body is where(x < 0, ceil, floor), the hull [-1, 1] on a box across 0
# where trunc is 0; trunc itself is non-decreasing
_trunc = ia.monotone_increasing(jnp.trunc)
NAMED_CALLS["trunc"] = Rule(_trunc, aa.via_interval(_trunc))
