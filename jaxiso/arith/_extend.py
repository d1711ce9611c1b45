"""`extend`: turn a plain JAX function into its interval or affine extension.

The user's ``f(x, y, z[, w][, params])`` is traced once per input signature with
`jax.make_jaxpr` on scalar points; the jaxpr is then evaluated with one *rule* per
primitive over `Interval` or `Affine` values, and the whole evaluation is `vmap`-ped over
the batch of boxes. All jaxpr access in jaxiso lives in this module (version shims too).

Rules are looked up by primitive name in a per-arithmetic registry filled here from the
kinds of primitive (arithmetic, monotone, even, periodic, domain-restricted, structural,
logic); `register_rule` adds or replaces one. Call-like primitives (`jit`/`pjit`,
`closed_call`, `custom_jvp_call`, `custom_vjp_call`, `remat`) are always recursed into,
never passed through; `cond` evaluates every branch and selects/hulls by the index;
equations whose inputs are all constants are folded with ``primitive.bind``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

from . import _affine as aa
from . import _interval as ia
from ._affine import Affine
from ._interval import Interval

__all__ = ["extend", "register_rule", "ARITHMETICS", "ROUNDINGS"]

ARITHMETICS = ("interval", "affine")
ROUNDINGS = ("fast", "outward")

# rule(*invals, **params) -> value or list of values; invals are Interval/Affine or arrays
_RULES: dict[str, dict[str, Callable]] = {a: {} for a in ARITHMETICS}
# Rounding error of each inexact primitive's result, in ulps; absent means exact.
_ULPS: dict[str, float] = {}
# jit-wrapped library functions with a tighter known extension, by their jit name.
_NAMED_CALLS: dict[str, dict[str, Callable]] = {a: {} for a in ARITHMETICS}

# Parameter names under which call-like primitives keep their body, across jax versions.
_CALL_JAXPR_KEYS = ("jaxpr", "call_jaxpr", "fun_jaxpr")
_LOOP_PRIMITIVES = ("while", "scan", "fori_loop")


def _is_lifted(x) -> bool:
    return isinstance(x, (Interval, Affine))


def register_rule(primitive, rule: Callable, arithmetic: str = "interval") -> None:
    """Register the extension `rule` of a JAX primitive (object or name).

    `rule(*invals, **eqn_params)` receives `Interval` (or `Affine`) values for traced
    inputs and plain arrays for constants, and returns one value (a list for primitives
    with multiple results). `arithmetic` is "interval", "affine" or "both".
    Soundness is the rule's responsibility: every point of the input boxes must map
    inside the result.
    """
    name = primitive if isinstance(primitive, str) else primitive.name
    targets = ARITHMETICS if arithmetic == "both" else (arithmetic,)
    for a in targets:
        if a not in _RULES:
            raise ValueError(f"arithmetic must be one of {ARITHMETICS} or 'both'")
        _RULES[a][name] = rule


# ----------------------------------------------------------------- rule registration


def _drop_params(rule):
    """Adapt ``rule(*invals)`` to the primitive's call (params such as `accuracy` unused)."""
    return functools.wraps(rule)(lambda *invals, **_params: rule(*invals))


def _both(name, ia_rule, aa_rule=None, ulps=None):
    _RULES["interval"][name] = _drop_params(ia_rule)
    _RULES["affine"][name] = _drop_params(aa_rule if aa_rule is not None
                                          else aa._via_interval(ia_rule))
    if ulps is not None:
        _ULPS[name] = ulps


def _div_interval(a, b):
    a, b = ia.as_interval(a), ia.as_interval(b)
    if jnp.issubdtype(a.lo.dtype, jnp.integer):
        # lax.div on integers truncates toward 0: monotone in the real quotient
        q = ia.div(Interval(a.lo.astype(jnp.float32), a.hi.astype(jnp.float32), a.defined),
                   Interval(b.lo.astype(jnp.float32), b.hi.astype(jnp.float32), b.defined))
        big = float(jnp.iinfo(a.lo.dtype).max)
        lo = jnp.clip(jnp.trunc(q.lo), -big, big).astype(a.lo.dtype)
        hi = jnp.clip(jnp.trunc(q.hi), -big, big).astype(a.lo.dtype)
        return Interval(lo, hi, q.defined)
    return ia.div(a, b)


# IEEE-correctly rounded basic operations: half an ulp, padded to 1.
# add_any sums tangents in derivative jaxprs (Mitchell's gradient test)
for _name, _ia, _aa in (("add", ia.add, aa.add), ("add_any", ia.add, aa.add),
                        ("sub", ia.sub, aa.sub), ("mul", ia.mul, aa.mul),
                        ("div", _div_interval, aa.div),
                        ("sqrt", ia.sqrt, aa.sqrt), ("square", ia.square, aa.square)):
    _both(_name, _ia, _aa, ulps=2.0)

# Exact operations.
for _name, _ia, _aa in (("neg", ia.neg, aa.neg), ("abs", ia.abs, aa.abs),
                        ("max", ia.maximum, aa.maximum), ("min", ia.minimum, aa.minimum),
                        ("floor", ia.floor, aa.floor), ("ceil", ia.ceil, aa.ceil),
                        ("sign", ia.sign, aa.sign)):
    _both(_name, _ia, _aa)

_both("clamp", ia.clamp, aa.clamp)


def _round_rule(x, **params):
    fn = ia.monotone_increasing(lambda v: lax.round(v, **params))
    return aa._via_interval(fn)(x) if isinstance(x, Affine) else fn(x)


_RULES["interval"]["round"] = _RULES["affine"]["round"] = _round_rule


def _reduce_precision_rule(x, **params):
    fn = ia.monotone_increasing(lambda v: lax.reduce_precision(v, **params))
    return aa._via_interval(fn)(x) if isinstance(x, Affine) else fn(x)


_RULES["interval"]["reduce_precision"] = _RULES["affine"]["reduce_precision"] = (
    _reduce_precision_rule)
_both("rem", ia.fmod, aa.fmod, ulps=1.0)

# Transcendentals from XLA: a few ulps (measured worst cases are in tests/benchmarks).
_TRANSCENDENTAL_ULPS = 8.0
for _name, _ia, _aa in (("exp", ia.exp, aa.exp), ("log", ia.log, aa.log),
                        ("cbrt", ia.cbrt, aa.cbrt), ("sin", ia.sin, aa.sin),
                        ("cos", ia.cos, aa.cos), ("tan", ia.tan, aa.tan),
                        ("tanh", ia.tanh, aa.tanh), ("atan", ia.atan, aa.atan),
                        ("atan2", ia.atan2, aa.atan2), ("sinh", ia.sinh, aa.sinh),
                        ("cosh", ia.cosh, aa.cosh)):
    _both(_name, _ia, _aa, ulps=_TRANSCENDENTAL_ULPS)

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
    _both(_name, ia.monotone_on(_fn, _lo, _hi, _inc), ulps=_TRANSCENDENTAL_ULPS)


def _integer_pow(x, *, y):
    return ia.ipow(x, y) if isinstance(x, Interval) else aa.ipow(x, y)


_RULES["interval"]["integer_pow"] = _integer_pow
_RULES["affine"]["integer_pow"] = _integer_pow
_RULES["interval"]["pow"] = _drop_params(ia.pow)
_RULES["affine"]["pow"] = _drop_params(aa.pow)
_ULPS["pow"] = _TRANSCENDENTAL_ULPS


def _integer_pow_ulps(params) -> float:
    # repeated squaring rounds ~log2|y| times, but each squaring doubles the relative
    # error carried in, so the total is about |y| ulps (superquadric: x**500)
    return 2.0 * abs(int(params["y"])) + 2.0


# Three-valued comparisons and logic: Interval of bools in both arithmetics.
for _name, _ia, _aa in (("lt", ia.lt, aa.lt), ("le", ia.le, aa.le), ("gt", ia.gt, aa.gt),
                        ("ge", ia.ge, aa.ge), ("eq", ia.eq, aa.eq), ("ne", ia.ne, aa.ne)):
    _both(_name, _ia, _aa)
for _name, _fn in (("and", ia.logical_and), ("or", ia.logical_or), ("not", ia.logical_not)):
    _RULES["interval"][_name] = _RULES["affine"][_name] = _drop_params(_fn)

# x OP x for the same variable: decided exactly (no dependency problem).
_SAME_VAR_TRUTH = {"eq": True, "le": True, "ge": True, "ne": False, "lt": False, "gt": False}


def _select_n(which, *cases, **_):
    if any(isinstance(c, Affine) for c in cases):
        return aa.select_n(which, *cases)
    return ia.select_n(which, *cases)


_RULES["interval"]["select_n"] = _RULES["affine"]["select_n"] = _select_n


# ------------------------------------------------------------- structural primitives

# Number of leading operands that carry data; the rest (indices) must be constants.
_STRUCTURAL = {
    "broadcast_in_dim": 1, "reshape": 1, "squeeze": 1, "expand_dims": 1,
    "transpose": 1, "rev": 1, "slice": 1, "dynamic_slice": 1, "gather": 1,
    "copy": 1, "copy_p": 1, "concatenate": None, "stack": None, "pad": 2,
    "real": 1, "optimization_barrier": None,
}


def _structural(prim, params, invals):
    n_data = _STRUCTURAL[prim.name]
    n_data = len(invals) if n_data is None else n_data
    data, rest = invals[:n_data], invals[n_data:]
    if any(_is_lifted(r) for r in rest):
        raise NotImplementedError(
            f"jaxiso.extend: '{prim.name}' with a box-dependent index is not supported; "
            "indices must not depend on x, y, z (use jnp.where/select instead)")
    bind = lambda *xs: prim.bind(*xs, *rest, **params)  # noqa: E731
    if any(isinstance(d, Affine) for d in data):
        data = aa._lift(*data)
        devs = jax.vmap(bind, in_axes=-1, out_axes=-1)(*[d.dev for d in data])
        return Affine(bind(*[d.center for d in data]), devs, bind(*[d.err for d in data]),
                      bind(*[d.defined for d in data]))
    data = [ia.as_interval(d) for d in data]
    return Interval(bind(*[d.lo for d in data]), bind(*[d.hi for d in data]),
                    bind(*[jnp.broadcast_to(d.defined, jnp.shape(d.lo)) for d in data]))


def _convert_element_type(x, *, new_dtype, **params):
    cast = lambda v: lax.convert_element_type(v, new_dtype)  # noqa: E731
    if isinstance(x, Affine):
        if jnp.dtype(new_dtype) == x.center.dtype:
            return x
        # a precision change rounds centre + sum(dev e) as a whole, not term by term:
        # go through the (monotone) interval conversion
        iv = aa._range(x)
        out = Interval(cast(iv.lo), cast(iv.hi), iv.defined)
        return aa.from_interval(out, None, x.n) if jnp.issubdtype(new_dtype, jnp.floating) \
            else out
    # monotone non-decreasing for float->float, bool->number, float->int (truncation)
    return Interval(cast(x.lo), cast(x.hi), x.defined)


_RULES["interval"]["convert_element_type"] = _RULES["affine"]["convert_element_type"] = (
    _convert_element_type)


def _axes_kw(params):
    return tuple(params["axes"])


def _reduce_sum(x, **params):
    axes = _axes_kw(params)
    if isinstance(x, Affine):
        dev_axes = tuple(a if a >= 0 else a - 1 for a in axes)
        return Affine(jnp.sum(x.center, axes), jnp.sum(x.dev, dev_axes),
                      jnp.sum(x.err, axes), jnp.all(x.defined, axes))
    return Interval(jnp.sum(x.lo, axes), jnp.sum(x.hi, axes), jnp.all(x.defined, axes))


def _reduce_monotone(reducer):
    def rule(x, **params):
        axes = _axes_kw(params)
        iv = aa._range(x) if isinstance(x, Affine) else x
        out = Interval(reducer(iv.lo, axes), reducer(iv.hi, axes), jnp.all(iv.defined, axes))
        return aa.from_interval(out, None, x.n) if isinstance(x, Affine) else out

    return rule


_RULES["interval"]["reduce_sum"] = _RULES["affine"]["reduce_sum"] = _reduce_sum
_RULES["interval"]["reduce_max"] = _RULES["affine"]["reduce_max"] = _reduce_monotone(jnp.max)
_RULES["interval"]["reduce_min"] = _RULES["affine"]["reduce_min"] = _reduce_monotone(jnp.min)


def _reduce_sum_ulps(params, in_shape) -> float:
    return 1.0 + float(np.prod([in_shape[a] for a in params["axes"]], dtype=float))


def _dot_general(lhs, rhs, **params):
    """Dot with one constant operand: exact mid-radius form ``A m +- |A| r``."""
    if _is_lifted(lhs) and _is_lifted(rhs):
        raise NotImplementedError(
            "jaxiso.extend: dot_general/matmul between two box-dependent operands is not "
            "supported; write the products out elementwise (x * y) instead")
    left = _is_lifted(lhs)
    box, const = (lhs, rhs) if left else (rhs, lhs)
    dot = (lambda b, c: lax.dot_general(b, c, **params)) if left else (
        lambda b, c: lax.dot_general(c, b, **params))
    if isinstance(box, Affine):
        devs = jax.vmap(lambda d: dot(d, const), in_axes=-1, out_axes=-1)(box.dev)
        return Affine(dot(box.center, const), devs, dot(box.err, jnp.abs(const)),
                      _all_defined(dot, box.defined, const))
    m, r = ia.mid(box), ia.rad(box)
    big = jnp.finfo(m.dtype).max
    center = dot(m, const)
    radius = dot(jnp.minimum(r, big), jnp.abs(const))
    unbounded = dot(jnp.isinf(r).astype(m.dtype), (const != 0).astype(m.dtype)) > 0
    radius = jnp.where(unbounded, jnp.inf, radius)
    return Interval(center - radius, center + radius, _all_defined(dot, box.defined, const))


def _all_defined(dot, defined, const):
    undefined = dot((~defined).astype(jnp.float32), jnp.ones_like(const, jnp.float32))
    return undefined == 0


_RULES["interval"]["dot_general"] = _RULES["affine"]["dot_general"] = _dot_general


# --------------------------------------------------- library functions with known rules


def _hypot_interval(x, y):
    return ia.sqrt(ia.add(ia.square(ia.as_interval(x)), ia.square(ia.as_interval(y))))


def _hypot_affine(x, y):
    x, y = aa._lift(x, y)
    return aa.sqrt(aa.add(aa.square(x), aa.square(y)))


# jnp.hypot guards 0/0 with where(); its plain formula is the tight, sound extension.
_NAMED_CALLS["interval"]["hypot"] = _hypot_interval
_NAMED_CALLS["affine"]["hypot"] = _hypot_affine


# ----------------------------------------------------------------- the interpreter


class _Context:
    def __init__(self, arithmetic: str, outward: bool):
        self.arithmetic = arithmetic
        self.outward = outward
        self.rules = _RULES[arithmetic]
        self.named = _NAMED_CALLS[arithmetic]


def _closed(j):
    """(jaxpr, consts) from a ClosedJaxpr or an open Jaxpr."""
    if isinstance(j, jcore.ClosedJaxpr):
        return j.jaxpr, j.consts
    return j, ()


def _call_body(eqn):
    for key in _CALL_JAXPR_KEYS:
        body = eqn.params.get(key)
        if isinstance(body, (jcore.ClosedJaxpr, jcore.Jaxpr)):
            return body
    return None


def _eval_jaxpr(jaxpr, consts, args, ctx: _Context):
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        outs = _apply(eqn, invals, ctx)
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _apply(eqn, invals, ctx: _Context):
    prim, params = eqn.primitive, eqn.params
    if not any(_is_lifted(x) for x in invals):  # constant folding
        out = prim.bind(*invals, **params)
        return list(out) if prim.multiple_results else [out]
    name = prim.name
    if name == "cond":
        return _apply_cond(params["branches"], invals[0], invals[1:], ctx)
    if name in _LOOP_PRIMITIVES:
        raise NotImplementedError(
            f"jaxiso.extend: loops ('{name}') over box-dependent values cannot be "
            "extended; unroll the loop in Python or register a rule for the whole "
            "function with jaxiso.register_rule")
    body = _call_body(eqn)
    if body is not None:
        named = ctx.named.get(str(params.get("name", "")))
        if named is not None:
            return [_round(ctx, named(*invals), 2.0 * _TRANSCENDENTAL_ULPS)]
        jaxpr, consts = _closed(body)
        return _eval_jaxpr(jaxpr, consts, invals, ctx)
    if name in _SAME_VAR_TRUTH and len(invals) == 2 and invals[0] is invals[1]:
        return [_same_var_truth(invals[0], _SAME_VAR_TRUTH[name])]
    if name in _STRUCTURAL:
        return [_structural(prim, params, invals)]
    # Affine forms carry reals; integer and boolean values stay Intervals, so an
    # equation whose lifted inputs are all Intervals uses the interval rule.
    rules = ctx.rules
    if ctx.arithmetic == "affine" and not any(isinstance(x, Affine) for x in invals):
        rules = _RULES["interval"]
    rule = rules.get(name)
    if rule is None:
        raise NotImplementedError(
            f"jaxiso.extend: no {ctx.arithmetic} rule for the JAX primitive '{name}'. "
            f"Register one with jaxiso.register_rule('{name}', rule, "
            f"arithmetic='{ctx.arithmetic}'), or rewrite f without it.")
    out = rule(*invals, **params)
    if prim.multiple_results:
        return list(out)
    scale = _term_scale(name, params, invals) if ctx.outward else None
    return [_round(ctx, out, _ulps_of(name, params, invals), scale)]


def _term_scale(name, params, invals):
    """For sums and dots the rounding error scales with the terms, not the (possibly
    cancelled) result: the sum of the terms' magnitudes."""
    if name == "reduce_sum":
        x = aa._range(invals[0]) if isinstance(invals[0], Affine) else invals[0]
        return jnp.sum(ia.mag(x), tuple(params["axes"]))
    if name == "dot_general":
        left = _is_lifted(invals[0])
        box, const = (invals[0], invals[1]) if left else (invals[1], invals[0])
        m = ia.mag(aa._range(box) if isinstance(box, Affine) else box)
        big = jnp.finfo(m.dtype).max
        m, c = jnp.minimum(m, big), jnp.abs(const).astype(m.dtype)
        return (lax.dot_general(m, c, **params) if left
                else lax.dot_general(c, m, **params))
    return None


def _ulps_of(name, params, invals):
    if name in _EXP_LIKE:
        return _exp_ulps(invals[0])
    if name == "pow":
        return _pow_ulps(*invals)
    if name == "integer_pow":
        return _integer_pow_ulps(params)
    if name == "reduce_sum":
        return _reduce_sum_ulps(params, _shape_of(invals[0]))
    if name == "dot_general":
        (contract, _), _ = params["dimension_numbers"]
        box = invals[0] if _is_lifted(invals[0]) else invals[1]
        shape = _shape_of(invals[0]) if box is invals[0] else np.shape(invals[0])
        return 2.0 + float(np.prod([shape[a] for a in contract], dtype=float))
    return _ULPS.get(name, 0.0)


# XLA's float32 exp family reduces the argument in float32: its relative error grows
# like |x| ulps (the condition number of exp), measured ~8e-6 relative at x = 59.
_EXP_LIKE = ("exp", "exp2", "expm1", "sinh", "cosh")


def _exp_ulps(x):
    x = aa._range(x) if isinstance(x, Affine) else ia.as_interval(x)
    m = ia.mag(x)
    return _TRANSCENDENTAL_ULPS + 2.0 * jnp.where(jnp.isfinite(m), m, 0.0)


def _pow_ulps(x, y):
    """XLA computes x**y as exp(y log x): its error grows with |y log x| ulps."""
    x, y = (aa._range(v) if isinstance(v, Affine) else ia.as_interval(v) for v in (x, y))
    with jax.numpy_dtype_promotion("standard"):
        logs = jnp.maximum(jnp.abs(jnp.log(jnp.abs(x.lo))), jnp.abs(jnp.log(jnp.abs(x.hi))))
    logs = jnp.where(jnp.isfinite(logs), logs, 0.0)
    growth = jnp.where(jnp.isfinite(ia.mag(y)), ia.mag(y), 0.0) * logs
    return _TRANSCENDENTAL_ULPS + 2.0 * growth


def _shape_of(x):
    if isinstance(x, Interval):
        return jnp.shape(x.lo)
    if isinstance(x, Affine):
        return jnp.shape(x.center)
    return np.shape(x)


def _round(ctx: _Context, out, ulps: float, scale=None):
    if not ctx.outward or (isinstance(ulps, float) and ulps == 0.0) or not _is_lifted(out):
        return out
    if isinstance(out, Interval) and not jnp.issubdtype(out.lo.dtype, jnp.floating):
        return out
    if isinstance(out, Interval):
        return ia.widen(out, ulps, scale)
    return aa.widen(out, ulps, scale)


def _same_var_truth(x, value: bool):
    shape = _shape_of(x)
    empty = ia.is_empty(x) if isinstance(x, Interval) else aa._is_empty(x)
    truth = jnp.full(shape, value) & ~empty  # empty boxes: certainly false
    return Interval(truth, truth, x.defined)


def _apply_cond(branches, index, operands, ctx: _Context):
    """Evaluate every branch; select by the (possibly three-valued) index."""
    outs = []
    for br in branches:
        jaxpr, consts = _closed(br)
        outs.append(_eval_jaxpr(jaxpr, consts, operands, ctx))
    results = []
    for k in range(len(outs[0])):
        cases = [o[k] for o in outs]
        if not any(_is_lifted(c) for c in cases) and not _is_lifted(index):
            results.append(lax.select_n(index, *cases) if len(cases) > 1 else cases[0])
        else:
            results.append(_select_n(index, *cases))
    return results


# -------------------------------------------------------------------------- extend


def _check_coordinate(x, i):
    if isinstance(x, Interval):
        ia.check_endpoints(x.lo, x.hi, what=f"extend: coordinate {i}")
    elif isinstance(x, Affine):
        if not isinstance(x.center, jax.core.Tracer) and not isinstance(x.err, jax.core.Tracer):
            if np.isnan(np.asarray(x.center)).any() or (np.asarray(x.err) < 0).any():
                raise ValueError(f"extend: coordinate {i} is an Affine form with NaN "
                                 "centre or negative error term")
    else:
        arr = np.asarray(x) if not isinstance(x, jax.core.Tracer) else None
        if arr is not None and arr.dtype.kind == "f" and np.isnan(arr).any():
            raise ValueError(f"extend: coordinate {i} contains NaN")


def _subnormal_sign(v):
    """+1 / -1 where v is a nonzero subnormal, else 0, read from the bits: XLA on CPU
    treats subnormal operands as 0 (DAZ), so arithmetic tests cannot see them."""
    if v.dtype != jnp.float32:
        return jnp.zeros(v.shape, jnp.int32)
    bits = lax.bitcast_convert_type(v, jnp.int32)
    subnormal = ((bits & 0x7F800000) == 0) & ((bits & 0x7FFFFFFF) != 0)
    return jnp.where(subnormal, jnp.where(bits < 0, -1, 1), 0)


def _flush_subnormals_outward(x: Interval) -> Interval:
    """Round subnormal endpoints outward to 0 / +-tiny (CPU XLA flushes them to 0)."""
    lo, hi = jnp.asarray(x.lo), jnp.asarray(x.hi)
    if not jnp.issubdtype(lo.dtype, jnp.floating):
        return x
    tiny = float(jnp.finfo(lo.dtype).tiny)
    s_lo, s_hi = _subnormal_sign(lo), _subnormal_sign(hi)
    lo = jnp.where(s_lo > 0, 0.0, jnp.where(s_lo < 0, -tiny, lo))
    hi = jnp.where(s_hi > 0, tiny, jnp.where(s_hi < 0, 0.0, hi))
    return Interval(lo, hi, x.defined)


def _point_dtype(x):
    if isinstance(x, Interval):
        dt = jnp.result_type(x.lo, x.hi)
    elif isinstance(x, Affine):
        dt = jnp.result_type(x.center)
    else:
        dt = jnp.result_type(x)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.dtype(jnp.float32)


def _param_aval(x):
    if isinstance(x, Interval):
        return jax.ShapeDtypeStruct(jnp.shape(x.lo), _point_dtype(x))
    if isinstance(x, Affine):
        return jax.ShapeDtypeStruct(jnp.shape(x.center), _point_dtype(x))
    return jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x))


def extend(f: Callable, arithmetic: str = "interval", rounding: str = "fast",
           n_symbols: int | None = None) -> Callable:
    """The inclusion extension of a plain-JAX scalar function.

    Args:
      f: ``f(x, y, z, ...)`` or ``f(x, y, z, ..., params)`` written with jax.numpy /
        lax on scalar points, returning one scalar (float, or bool for an inequality).
      arithmetic: "interval" (Moore IA) or "affine" (AF1 reduced affine, Eq. 6.15).
      rounding: "fast" rounds to nearest like the seed (enclosures hold up to float
        rounding); "outward" widens every inexact result by its rounding error in ulps
        (and XLA's subnormal flushing), so enclosures hold against exact arithmetic.
      n_symbols: affine only: number of noise symbols (default: one per Interval
        coordinate, in argument order).

    Returns:
      ``F(*coords, params=None)``: each coordinate is an `Interval`, an `Affine` or a
      point array; their shapes broadcast to the batch shape S. `params` (any pytree of
      arrays or Intervals) is passed to f unbatched. Returns an `Interval` (or `Affine`)
      of shape S enclosing ``f`` on every box. Pure: works eagerly, under `jit` and
      `vmap`; the jaxpr of f is cached per input signature.
    """
    if arithmetic not in ARITHMETICS:
        raise ValueError(f"arithmetic must be one of {ARITHMETICS}, got {arithmetic!r}")
    if rounding not in ROUNDINGS:
        raise ValueError(f"rounding must be one of {ROUNDINGS}, got {rounding!r}")
    if not callable(f):
        raise TypeError(f"extend needs a callable, got {type(f).__name__}")
    ctx = _Context(arithmetic, rounding == "outward")
    cache = {}

    def trace(coords, param_leaves, param_tree):
        key = (tuple(_point_dtype(c) for c in coords), param_tree,
               tuple(_param_aval(p) for p in param_leaves))
        if key not in cache:
            n_c = len(coords)

            def flat_f(*leaves):
                params = jax.tree_util.tree_unflatten(param_tree, leaves[n_c:])
                args = leaves[:n_c] if params is None else (*leaves[:n_c], params)
                return f(*args)

            avals = [jax.ShapeDtypeStruct((), dt) for dt in key[0]] + list(key[2])
            closed = jax.make_jaxpr(flat_f)(*avals)
            _check_output(closed, f)
            cache[key] = closed
        return cache[key]

    @functools.wraps(f)
    def F(*coords, params=None):
        if not coords:
            raise TypeError("F needs at least one coordinate (x, y, z, ...)")
        for i, c in enumerate(coords):
            _check_coordinate(c, i)
        is_leaf = lambda v: _is_lifted(v)  # noqa: E731
        param_leaves, param_tree = jax.tree_util.tree_flatten(params, is_leaf=is_leaf)
        closed = trace(coords, param_leaves, param_tree)
        lifted = _lift_coordinates(coords, ctx, n_symbols)
        params_in = [_lift_param(p, ctx, lifted) for p in param_leaves]
        batch = np.broadcast_shapes(*[_shape_of(c) for c in lifted])
        lifted = [_broadcast(c, batch) for c in lifted]

        def eval_point(point_coords):
            out = _eval_jaxpr(closed.jaxpr, closed.consts, [*point_coords, *params_in],
                              ctx)[0]
            return _as_result(out, point_coords, ctx)

        size = math.prod(batch)
        flat = [_reshape(c, (size,)) for c in lifted]
        out = jax.vmap(eval_point)(flat)
        # outward affine: one more ulp so that the caller's to_interval (centre +- rad,
        # rounded to nearest) still encloses
        out = _round(ctx, out, 1.0) if isinstance(out, Affine) else out
        return _reshape(out, batch)

    return F


def _check_output(closed, f):
    outs = closed.out_avals
    name = getattr(f, "__name__", repr(f))
    if len(outs) != 1:
        raise ValueError(f"extend: {name} must return one scalar per point, got "
                         f"{len(outs)} outputs")
    if outs[0].shape != ():
        raise ValueError(f"extend: {name} must return a scalar per point, got shape "
                         f"{outs[0].shape}; reduce it (e.g. jnp.sum) or return one value")
    if not (jnp.issubdtype(outs[0].dtype, jnp.floating) or outs[0].dtype == jnp.bool_):
        raise ValueError(f"extend: {name} must return a float (or bool), got "
                         f"{outs[0].dtype}")


def _lift_coordinates(coords, ctx: _Context, n_symbols):
    outward = ctx.outward
    ivs = []
    for c in coords:
        if isinstance(c, Interval) and outward:
            c = _flush_subnormals_outward(c)
        ivs.append(c)
    if ctx.arithmetic == "interval":
        return [aa._range(c) if isinstance(c, Affine) else ia.as_interval(c)
                for c in ivs]
    given = [c.n for c in ivs if isinstance(c, Affine)]
    if given:
        n = given[0]
        return [_round(ctx, aa.as_affine(c, n), 1.0) for c in ivs]
    k = sum(isinstance(c, Interval) for c in ivs)
    n = max(1, k) if n_symbols is None else int(n_symbols)
    if n < k:
        raise ValueError(f"n_symbols={n} is fewer than the {k} interval coordinates")
    out, s = [], 0
    for c in ivs:
        if isinstance(c, Interval):
            out.append(aa.from_interval(c, s, n))
            s += 1
        else:
            out.append(aa.as_affine(c, n))
    # outward: the midpoint/radius of each box were rounded; pad them by an ulp
    return [_round(ctx, c, 1.0) for c in out]


def _lift_param(p, ctx: _Context, lifted):
    if ctx.arithmetic == "affine" and isinstance(p, Interval):
        return aa.from_interval(p, None, lifted[0].n)
    if ctx.arithmetic == "interval" and isinstance(p, Affine):
        return aa._range(p)
    return p


def _broadcast(x, shape):
    if isinstance(x, Interval):
        return Interval(jnp.broadcast_to(x.lo, shape), jnp.broadcast_to(x.hi, shape),
                        jnp.broadcast_to(x.defined, shape))
    return Affine(jnp.broadcast_to(x.center, shape),
                  jnp.broadcast_to(x.dev, tuple(shape) + (x.n,)),
                  jnp.broadcast_to(x.err, shape), jnp.broadcast_to(x.defined, shape))


def _reshape(x, shape):
    if isinstance(x, Interval):
        return Interval(x.lo.reshape(shape), x.hi.reshape(shape), x.defined.reshape(shape))
    return Affine(x.center.reshape(shape), x.dev.reshape(tuple(shape) + (x.n,)),
                  x.err.reshape(shape), x.defined.reshape(shape))


def _as_result(out, point_coords, ctx: _Context):
    """A constant output (f ignored the boxes) as a point enclosure."""
    if _is_lifted(out):
        if isinstance(out, Interval):
            return Interval(jnp.broadcast_to(out.lo, ()), jnp.broadcast_to(out.hi, ()),
                            jnp.broadcast_to(out.defined, ()))
        return out
    if ctx.arithmetic == "affine" and not jnp.issubdtype(jnp.result_type(out), jnp.bool_):
        return aa.as_affine(jnp.asarray(out, jnp.float32), point_coords[0].n)
    return ia.point(out)
