"""`extend`: turn a plain JAX function into its interval or affine extension.

The user's ``f(x, y, z[, w][, params])`` is traced once per input signature with
`jax.make_jaxpr` on scalar points; the jaxpr is then evaluated with the rule of each
primitive (the registry in `_rules`) over `Interval` or `Affine` values, and the whole
evaluation is `vmap`-ped over the batch of boxes. All jaxpr access in jaxiso lives in
this module (version shims too).

Call-like primitives (`jit`/`pjit`, `closed_call`, `custom_jvp_call`, `custom_vjp_call`,
`remat`) are always recursed into, never passed through; `cond` evaluates every branch
and selects/hulls by the index; equations whose inputs are all constants are folded with
``primitive.bind``. Outward rounding widens each inexact result by its rule's ulps.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
import weakref
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

from . import _affine as aa
from . import _branches, _lift
from . import _interval as ia
from ._affine import Affine
from ._array_rules import move_data
from ._interval import Interval
from ._lift import is_lifted, shape_of
from ._rules import (
    ARITHMETICS,
    BY_ARITHMETIC,
    INTERVAL_CALLS,
    NAMED_CALLS,
    NO_RULE,
    RULES,
    register_rule,
)

__all__ = ["extend", "register_rule", "ARITHMETICS", "ROUNDINGS"]

ROUNDINGS = ("fast", "outward")

# The rules of each arithmetic by primitive name (live views of the registry).
_RULES = BY_ARITHMETIC

# Parameter names under which call-like primitives keep their body, across jax versions.
_CALL_JAXPR_KEYS = ("jaxpr", "call_jaxpr", "fun_jaxpr")
_LOOP_PRIMITIVES = ("while", "scan", "fori_loop")


@dataclasses.dataclass(frozen=True)
class _Context:
    arithmetic: str
    outward: bool
    fresh: _FreshSymbols | None = None
    # affine: the sign form of each comparison's result, by id: {id: (result, g)}, with
    # the result true only where g >= 0 and false only where g <= 0 (`_note_sign`)
    signs: dict | None = None


# Elementwise primitives whose affine rules add linearisation error (the error terms
# `_FreshSymbols` turns into noise symbols); linear and structural ones only carry it.
_NONLINEAR = frozenset({"max", "min", "select_n", "exp", "exp2", "expm1", "log", "log1p",
                        "tanh", "logistic", "sin", "cos", "tan", "abs", "sqrt", "rsqrt",
                        "cbrt", "pow", "integer_pow", "square", "mul", "div", "erf", "atan",
                        "asinh", "sinh", "cosh"})


class _FreshSymbols:
    """Noise symbols handed out during one evaluation (affine with ``fresh_symbols``).

    After each nonlinear elementwise equation with a vector result, the `per_op`
    largest finite error terms of that vector become symbols of their own (a static
    block of slots per equation), so the next layer's mixing keeps their correlation
    (a zonotope, as DeepZ / Spelunking's "affine_all", with a budget): their radius is
    unchanged, so the forms enclose the same sets when taken alone. A smooth operation
    (elu, tanh, ...: every neuron whose range is not in a linear stretch has an error)
    takes `_SMOOTH_SHARE` times as many as a kink (relu's max, abs: only neurons whose
    range crosses the kink have one). When the budget is spent, errors stay in the
    error term (AF1)."""

    def __init__(self, first: int, end: int, per_op: int):
        self.first, self.next, self.end, self.per_op = first, first, end, per_op

    @property
    def handed_out(self) -> int:
        return self.next - self.first

    def absorb(self, out, smooth: bool):
        if not (isinstance(out, Affine) and np.ndim(out.center) == 1):
            return out
        want = self.per_op * (_SMOOTH_SHARE if smooth else 1)
        k = min(want, int(np.shape(out.center)[0]), self.end - self.next)
        if k <= 0:
            return out
        base, self.next = self.next, self.next + k
        out = aa.with_symbols(out, self.end)  # a form lifted from constants has fewer
        finite = jnp.isfinite(out.err)
        vals, idx = lax.top_k(jnp.where(finite, out.err, 0.0), k)
        chosen = jnp.arange(out.err.shape[0])[:, None] == idx[None, :]  # [h, k]
        dev = out.dev.at[:, base:base + k].add(jnp.where(chosen, vals[None, :], 0.0))
        err = jnp.where(jnp.any(chosen, axis=1) & finite, 0.0, out.err)
        return dataclasses.replace(out, dev=dev, err=err)


# A smooth operation's share of fresh symbols against a kink's. The sign grid of bunny
# (8 x 64 elu) at 8 symbols per operation left 14.5% of a 64^3 grid possible where
# sampling finds 3.0%; 16 per elu: 6.5%, 24: 4.8%, 32: 4.4%, in 22 / 27 / 30 / 41 s (the
# tighter coarse levels test fewer cells); its default call 1.55 -> 1.37 s from 16 to 24.
# relu networks (fox, hammer, birdcage_occ) gained nothing from 16 per max (1.9 -> 1.7%,
# 8.3 -> 8.2%) and took up to 60% longer. benchmarks/NOTES.md, session 16.
_SMOOTH_SHARE = 3
# kinks: piecewise linear operations, exact where an operand's sign is known
_KINKS = frozenset({"max", "min", "abs", "select_n"})


def extend(f: Callable, arithmetic: str = "interval", rounding: str = "fast",
           n_symbols: int | None = None, fresh_symbols: int = 0,
           fresh_per_op: int = 8) -> Callable:
    """The inclusion extension of a plain-JAX scalar function.

    Args:
      f: ``f(x, y, z, ...)`` or ``f(x, y, z, ..., params)`` written with jax.numpy /
        lax on scalar points, returning one scalar (float, or bool for an inequality;
        a constant is fine).
      arithmetic: "interval" (Moore IA) or "affine" (AF1 reduced affine, Eq. 6.15).
      rounding: "fast" rounds to nearest like the seed (enclosures hold up to float
        rounding); "outward" widens every inexact result by its rounding error in ulps
        (and XLA's subnormal flushing), so enclosures hold against exact arithmetic.
      n_symbols: affine only: number of noise symbols (default: one per Interval
        coordinate, in argument order).
      fresh_symbols: affine only: up to this many more symbols for the error terms of
        nonlinear vector operations (`fresh_per_op` per kink such as relu's max,
        `_SMOOTH_SHARE` times that per smooth operation such as elu or tanh, largest
        errors first; see `_FreshSymbols`): tighter for networks, at a cost per
        evaluation that grows with the symbol count, so the forms carry only the
        symbols the operations take. 0 (default): AF1.

    Returns:
      ``F(*coords, params=None)``: each coordinate is an `Interval`, an `Affine` or a
      point array; their shapes broadcast to the batch shape S. `params` (any pytree of
      arrays or Intervals) is passed to f unbatched. Returns an `Interval` (or `Affine`)
      of shape S enclosing ``f`` on every box (an Interval of bools for an inequality).
      Pure: works eagerly, under `jit` and `vmap`; the jaxpr of f is cached per input
      signature.
    """
    if arithmetic not in ARITHMETICS:
        raise ValueError(f"arithmetic must be one of {ARITHMETICS}, got {arithmetic!r}")
    if rounding not in ROUNDINGS:
        raise ValueError(f"rounding must be one of {ROUNDINGS}, got {rounding!r}")
    if not callable(f):
        raise TypeError(f"extend needs a callable, got {type(f).__name__}")
    if fresh_symbols and arithmetic != "affine":
        raise ValueError("fresh_symbols needs arithmetic='affine'")
    extension = _Extension(f, arithmetic, _Context(arithmetic, rounding == "outward"),
                           n_symbols, fresh_symbols, fresh_per_op)

    @functools.wraps(f)
    def F(*coords, params=None):
        return extension(coords, params)

    return F


class _Extension:
    """`extend`'s F: f's jaxpr (traced once per input signature) evaluated on lifted
    coordinates, vmapped over their flattened batch."""

    def __init__(self, f, arithmetic, ctx, n_symbols, fresh_symbols, fresh_per_op):
        self.f, self.arithmetic, self.ctx = f, arithmetic, ctx
        self.n_symbols, self.fresh_symbols = n_symbols, fresh_symbols
        self.fresh_per_op = fresh_per_op
        self.cache = {}  # input signature -> f's closed jaxpr
        self.used_fresh = {}  # (jaxpr, coordinate kinds) -> fresh symbols operations take

    def __call__(self, coords, params):
        if not coords:
            raise TypeError("F needs at least one coordinate (x, y, z, ...)")
        for i, c in enumerate(coords):
            _lift.check_coordinate(c, i)
        param_leaves, param_tree = jax.tree_util.tree_flatten(params, is_leaf=is_lifted)
        closed = self.trace(coords, param_leaves, param_tree)
        lifted = _lift.lift_coordinates(coords, self.arithmetic, self.ctx.outward,
                                        self.n_symbols)
        batch = np.broadcast_shapes(*[shape_of(c) for c in lifted])
        size = math.prod(batch)
        flat = [_lift.reshape(_lift.broadcast(c, batch), (size,)) for c in lifted]

        def run(flat, fresh):
            return self.run(closed, param_leaves, flat, fresh)

        fresh = self.fresh_symbols
        if self.fresh_symbols:
            # the budget is a cap: the forms carry only the symbols the program's
            # operations take (a dry run counts them), as each one costs in every form
            # per point: the count depends on the program and which coordinates are
            # forms, not on the batch's size (`cache` keeps `closed` alive: ids hold)
            key = (id(closed), tuple(isinstance(c, Affine) for c in flat))
            if key not in self.used_fresh:
                self.used_fresh[key] = _count_fresh(run, flat, self.fresh_symbols)
            fresh = self.used_fresh[key]
        out = run(flat, fresh)[0]
        # outward affine: one more ulp so that the caller's to_interval (centre +- rad,
        # rounded to nearest) still encloses
        out = _round(self.ctx, out, 1.0) if isinstance(out, Affine) else out
        return _lift.reshape(out, batch)

    def trace(self, coords, param_leaves, param_tree):
        """f's closed jaxpr on scalar points of the coordinates' dtypes and the params'
        avals (cached)."""
        key = (tuple(_lift.point_dtype(c) for c in coords), param_tree,
               tuple(_lift.param_aval(p) for p in param_leaves))
        if key not in self.cache:
            n_c = len(coords)

            def flat_f(*leaves):
                params = jax.tree_util.tree_unflatten(param_tree, leaves[n_c:])
                args = leaves[:n_c] if params is None else (*leaves[:n_c], params)
                return self.f(*args)

            avals = [jax.ShapeDtypeStruct((), dt) for dt in key[0]] + list(key[2])
            closed = jax.make_jaxpr(flat_f)(*avals)
            _check_output(closed, self.f)
            self.cache[key] = closed
        return self.cache[key]

    def run(self, closed, param_leaves, flat, fresh):
        """F on the flat batch with `fresh` more symbols (all of them handed out to the
        operations' error terms); returns (out, symbols handed out)."""
        arithmetic, ctx = self.arithmetic, self.ctx
        flat = [aa.with_symbols(c, c.n + fresh) if isinstance(c, Affine) else c
                for c in flat]
        n = flat[0].n if arithmetic == "affine" else 0
        params_in = [_lift.lift_param(p, arithmetic, n) for p in param_leaves]
        symbols = _FreshSymbols(n - fresh, n, self.fresh_per_op) if fresh else None

        def eval_point(point_coords):
            run_ctx = dataclasses.replace(ctx, fresh=symbols if fresh else None,
                                          signs={} if arithmetic == "affine" else None)
            out = _eval_jaxpr(closed.jaxpr, closed.consts,
                              [*point_coords, *params_in], run_ctx)[0]
            return _lift.as_result(out, point_coords, arithmetic)

        return jax.vmap(eval_point)(flat), 0 if symbols is None else symbols.handed_out


def _count_fresh(run, flat, cap: int) -> int:
    """The fresh symbols the operations take from a budget of `cap` (a dry run of
    ``run(flat, cap)``: traced for shapes only)."""
    counted = []
    jax.eval_shape(lambda fl: counted.append(run(fl, cap)[1]) or jnp.zeros(()), flat)
    return counted[0]


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


# ----------------------------------------------------------------- the interpreter


def _closed(j):
    """(jaxpr, consts) from a ClosedJaxpr or an open Jaxpr."""
    if isinstance(j, jcore.ClosedJaxpr):
        return j.jaxpr, j.consts
    return j, ()


def _as_closed(body):
    return body if isinstance(body, jcore.ClosedJaxpr) else jcore.ClosedJaxpr(body, ())


def _call_body(eqn):
    for key in _CALL_JAXPR_KEYS:
        body = eqn.params.get(key)
        if isinstance(body, (jcore.ClosedJaxpr, jcore.Jaxpr)):
            return body
    return None


def _eval_jaxpr(jaxpr, consts, args, ctx: _Context):
    env = {}
    seen = {}  # an equation's key (`_same_equation`) -> its outputs
    plan = _plan(jaxpr)
    pending = {}  # outputs of equations deferred by the plan -> their equation

    def read(v):
        if isinstance(v, jcore.Literal):
            return v.val
        if v not in env and v in pending:  # a deferred equation that is needed after all
            run(pending[v])
        return env[v]

    def run(i):
        eqn = jaxpr.eqns[i]
        sel = plan.selections.get(i)
        if sel is not None and sel.extremum is not None:
            which, a, b = sel.extremum
            outs = _apply(_EXTREMA[which], [read(a), read(b)], ctx)
        elif sel is None:
            invals = [read(v) for v in eqn.invars]
            key = _same_equation(eqn, invals)
            outs = seen.get(key) if key is not None else None
            if outs is None:
                outs = _apply(eqn, invals, ctx)
                if key is not None:
                    seen[key] = outs
        else:
            # a selection of recomputed cases is one activation (elu spelled with
            # where): its cases' errors go into fresh symbols once, at its result, as
            # a smooth operation's (`_FreshSymbols`), not at each step of each case
            quiet = ctx if ctx.fresh is None else dataclasses.replace(ctx, fresh=None)
            outs = _on_stand_in(jaxpr, eqn, sel, read, quiet)
            if outs is None:
                outs = _apply(eqn, _taken_cases(jaxpr, eqn, sel, read, quiet), quiet)
            if ctx.fresh is not None:
                smooth = _smooth_cases(jaxpr, sel)
                outs = [ctx.fresh.absorb(o, smooth) for o in outs]
        for v, o in zip(eqn.outvars, outs):
            env[v] = o

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for i, eqn in enumerate(jaxpr.eqns):
        if i in plan.deferred:
            pending.update((v, i) for v in eqn.outvars)
        else:
            run(i)
    return [read(v) for v in jaxpr.outvars]


_PLANS = weakref.WeakKeyDictionary()  # jaxpr -> its `_branches.plan`


def _plan(jaxpr) -> _branches.Plan:
    if jaxpr not in _PLANS:
        _PLANS[jaxpr] = _branches.plan(jaxpr, _call_body)
    return _PLANS[jaxpr]


class _Primitive(typing.NamedTuple):
    """An equation of one primitive with no params, for `_apply`."""

    primitive: object
    params: dict


# a selection of its compared operands (`_branches.extremum`) is their max or min
_EXTREMA = {"max": _Primitive(lax.max_p, {}), "min": _Primitive(lax.min_p, {})}


def _smooth_cases(jaxpr, sel) -> bool:
    """Does a recomputed case hold a smooth nonlinear operation (or a call, which may)?"""
    names = {jaxpr.eqns[k].primitive.name for case in sel.cases for k in case.slice}
    return bool(names & (_NONLINEAR - _KINKS)) or any(
        _call_body(jaxpr.eqns[k]) is not None for case in sel.cases for k in case.slice)


def _float_lifted(x) -> bool:
    return is_lifted(x) and jnp.issubdtype(
        (x.center if isinstance(x, Affine) else x.lo).dtype, jnp.floating)


def _taken_cases(jaxpr, eqn, sel, read, ctx: _Context) -> list:
    """The operands of a selection, each case recomputed where it is taken
    (`_branches`): the compared operands clipped by each other, its slice re-run."""
    u, v = read(sel.u), read(sel.v)
    clip = [(var, x) for var, x in ((sel.u, u), (sel.v, v))
            if isinstance(var, jcore.Var) and _float_lifted(x)]
    recomputed = {case.position for case in sel.cases} if clip else set()
    invals = [None if k in recomputed else read(w) for k, w in enumerate(eqn.invars)]
    for case in sel.cases if clip else ():
        u_below, v_below = _branches.bounds(sel.comparison, case.taken_when)
        local = {var: _branches.taken_side(x, v if var is sel.u else u,
                                           u_below if var is sel.u else v_below)
                 for var, x in clip}

        def read_local(w):
            return local[w] if isinstance(w, jcore.Var) and w in local else read(w)

        for k in case.slice:
            step = jaxpr.eqns[k]
            outs = _apply(step, [read_local(w) for w in step.invars], ctx)
            local.update(zip(step.outvars, outs))
        invals[case.position] = read_local(eqn.invars[case.position])
    return invals


def _on_stand_in(jaxpr, eqn, sel, read, ctx: _Context):
    """The outputs of an element-by-element selection whose one lifted input is an
    affine form h, evaluated on h's stand-in ``c + r e0 (+ h's error term)`` with
    ``r = sum |dev|`` (one symbol: ``e0 = dev . e / r`` is in [-1, 1] at each element)
    and mapped back by scaling h's deviations: each element's result is a function of
    its own h, so this encloses what the full forms would, as tightly (every rule
    reads a form's centre, radius and error only), with the cases' work on [..., 1]
    instead of [..., n] (8 passes over the deviations of an elu spelled with where
    became 2). None where it does not apply."""
    if ctx.arithmetic != "affine" or not sel.elementwise:
        return None
    lifted = [w for w in sel.inputs if is_lifted(read(w))]
    if len(lifted) != 1 or lifted[0] not in (sel.u, sel.v):
        return None
    root = lifted[0]
    h = read(root)
    if not (isinstance(h, Affine) and _float_lifted(h)):
        return None
    r = jnp.sum(jnp.abs(h.dev), axis=-1)
    local = {root: Affine(h.center, r[..., None], h.err, h.defined, h.lo, h.hi)}

    def read_local(w):
        return local[w] if isinstance(w, jcore.Var) and w in local else read(w)

    compare = jaxpr.eqns[sel.compare]
    local.update(zip(compare.outvars, _apply(compare, [read_local(w) for w in compare.invars],
                                             ctx)))
    outs = _apply(eqn, _taken_cases(jaxpr, eqn, sel, read_local, ctx), ctx)
    if not all(isinstance(o, Affine) and o.n == 1 and o.center.shape == h.center.shape
               for o in outs if is_lifted(o)):
        return None
    return [_from_stand_in(o, h, r) if isinstance(o, Affine) else o for o in outs]


def _from_stand_in(out: Affine, h: Affine, r) -> Affine:
    """A result over h's stand-in symbol as a form over h's symbols: its coefficient
    spread over h's deviations in proportion (the products' rounding, a few ulps of
    the coefficient, joins the error term; where r = 0 the coefficient does)."""
    b = out.dev[..., 0]
    spread = r > 0
    scale = jnp.where(spread, b / jnp.where(spread, r, 1.0), 0.0)
    eps = float(jnp.finfo(b.dtype).eps)
    err = out.err + jnp.where(spread, 4.0 * eps * jnp.abs(b), jnp.abs(b))
    return Affine(out.center, scale[..., None] * h.dev, err, out.defined, out.lo, out.hi)


def _same_equation(eqn, invals):
    """A key that two equations share when they apply one primitive with equal params
    to the same values, or None (effects, unhashable params). Programs as people write
    them repeat subexpressions (a polynomial's ``x**3`` in every term, an SDF's
    ``x * x``); each is extended once, which keeps the extended program -- and its
    compile, ~210 equations per affine product -- to the distinct ones, and keeps
    the repeats correlated (one fresh symbol, not two). The values are held by the
    evaluation's environment, so their ids are unique while the key is used."""
    if eqn.effects:
        return None
    ins = tuple(("value", id(x)) if not isinstance(v, jcore.Literal) else
                ("literal", np.asarray(x).dtype.str, np.asarray(x).tobytes())
                for v, x in zip(eqn.invars, invals))
    try:
        key = (eqn.primitive, ins, tuple(sorted(eqn.params.items())))
        hash(key)
    except TypeError:
        return None
    return key


def _apply(eqn, invals, ctx: _Context) -> list:
    """The outputs of one equation: folded, recursed into, or by its primitive's rule."""
    prim, params = eqn.primitive, eqn.params
    if not any(is_lifted(x) for x in invals):  # constant folding
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
        named = NAMED_CALLS.get(str(params.get("name", "")))
        if named is not None:  # chosen by the context's arithmetic; takes no params
            rule = getattr(named, ctx.arithmetic)
            out = (rule(*invals, body=jcore.jaxpr_as_fun(_as_closed(body))) if named.with_body
                   else rule(*invals))
            if out is not NotImplemented:  # else: the operands it does not cover
                out = _round(ctx, out, *named.rounding(invals, params))
                return [ctx.fresh.absorb(out, True) if ctx.fresh is not None else out]
        jaxpr, consts = _closed(body)
        if ctx.arithmetic == "affine" and str(params.get("name", "")) in INTERVAL_CALLS:
            return _in_interval(jaxpr, consts, invals, ctx)
        return _eval_jaxpr(jaxpr, consts, invals, ctx)
    record = RULES.get(name, NO_RULE)
    if record.same_args is not None and len(invals) == 2 and invals[0] is invals[1]:
        return [_same_var_truth(invals[0], record.same_args)]
    if record.data_operands is not None:
        return move_data(prim, params, invals, record.data_operands)
    # Affine forms carry reals; integer and boolean values stay Intervals, so an
    # equation whose lifted inputs are all Intervals uses the interval rule.
    uses_affine = any(isinstance(x, Affine) for x in invals)
    rule = record.affine if uses_affine else record.interval
    if rule is None:
        raise NotImplementedError(
            f"jaxiso.extend: no {ctx.arithmetic} rule for the JAX primitive '{name}'. "
            f"Register one with jaxiso.register_rule('{name}', rule, "
            f"arithmetic='{ctx.arithmetic}'), or rewrite f without it.")
    sign = _sign_of(ctx, invals[0]) if name == "select_n" and len(invals) == 3 else None
    if sign is not None and getattr(rule, "takes_sign", False):
        out = rule(*invals, sign=sign)
    else:
        out = rule(*invals, **params)
    if ctx.signs is not None and uses_affine:
        _note_sign(ctx, name, invals, out)
    if prim.multiple_results:
        return list(out)
    if ctx.outward:
        out = _round(ctx, out, *record.rounding(invals, params))
    if ctx.fresh is not None and name in _NONLINEAR:
        out = ctx.fresh.absorb(out, name not in _KINKS)
    return [out]


# comparisons whose truth is the sign of a difference: name -> (minuend, subtrahend)
_SIGN_OF = {"gt": (0, 1), "ge": (0, 1), "lt": (1, 0), "le": (1, 0)}


def _note_sign(ctx: _Context, name, invals, out):
    """Remember which form's sign a comparison's (or its negation's) result is, so that
    a `select_n` on it can join its cases by a chord in that form (`aa.select_n`)."""
    if name in _SIGN_OF:
        i, j = _SIGN_OF[name]
        ctx.signs[id(out)] = (out, aa.sub(invals[i], invals[j]))
    elif name == "not" and _sign_of(ctx, invals[0]) is not None:
        ctx.signs[id(out)] = (out, aa.neg(_sign_of(ctx, invals[0])))


def _sign_of(ctx: _Context, cond):
    """The form g of a remembered comparison result `cond` (None if none)."""
    if ctx.signs is None:
        return None
    held = ctx.signs.get(id(cond))
    return held[1] if held is not None and held[0] is cond else None


def _in_interval(jaxpr, consts, invals, ctx: _Context) -> list:
    """A call body evaluated in interval arithmetic on the affine operands' ranges; float
    results come back as affine forms on the error term (correlation not kept)."""
    n = aa.n_of(*invals)
    ranged = [aa.padded_range(x) if isinstance(x, Affine) else x for x in invals]
    outs = _eval_jaxpr(jaxpr, consts, ranged, dataclasses.replace(ctx, arithmetic="interval"))
    return [aa.from_interval(o, None, n)
            if isinstance(o, Interval) and jnp.issubdtype(o.dtype, jnp.floating) else o
            for o in outs]


def _round(ctx: _Context, out, ulps, scale=None):
    """Outward mode: `out` widened by `ulps` (of its magnitude or of `scale`)."""
    if not ctx.outward or (isinstance(ulps, float) and ulps == 0.0) or not is_lifted(out):
        return out
    if isinstance(out, Interval) and not jnp.issubdtype(out.lo.dtype, jnp.floating):
        return out
    return out.ops.widen(out, ulps, scale)


def _same_var_truth(x, value: bool) -> Interval:
    """``x OP x``: `value` everywhere except on empty boxes (certainly false there)."""
    empty = ia.is_empty(x) if isinstance(x, Interval) else aa.is_empty(x)
    truth = jnp.full(shape_of(x), value) & ~empty
    return Interval(truth, truth, x.defined)


def _apply_cond(branches, index, operands, ctx: _Context):
    """Evaluate every branch; select by the (possibly three-valued) index."""
    outs = [_eval_jaxpr(*_closed(br), operands, ctx) for br in branches]
    results = []
    for cases in zip(*outs):
        if not any(is_lifted(c) for c in cases) and not is_lifted(index):
            results.append(lax.select_n(index, *cases) if len(cases) > 1 else cases[0])
        elif any(isinstance(c, Affine) for c in cases):
            results.append(aa.select_n(index, *cases))
        else:
            results.append(ia.select_n(index, *cases))
    return results


# ------------------------------------------------- flat programs (for jaxiso.arith._tape)


def equation_count(jaxpr) -> int:
    """Equations of a jaxpr (or closed jaxpr), those of nested jaxprs included."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else (value,):
                if hasattr(getattr(sub, "jaxpr", sub), "eqns"):
                    n += equation_count(sub)
    return n


def value_elements(f: Callable, n_args: int) -> int:
    """How many numbers f computes per point: the summed sizes of every equation's outputs
    in f's jaxpr on `n_args` float32 scalars (call-like bodies counted inside). A cost
    measure that tells a network (thousands: matvecs) from a polynomial (tens)."""
    avals = [jax.ShapeDtypeStruct((), jnp.float32)] * n_args
    closed = jax.make_jaxpr(f)(*avals)

    def walk(jaxpr):
        total = 0
        for eqn in jaxpr.eqns:
            body = _call_body(eqn)
            if body is not None:
                total += walk(body.jaxpr if isinstance(body, jcore.ClosedJaxpr) else body)
            else:
                total += sum(int(np.prod(v.aval.shape)) for v in eqn.outvars)
        return total

    return walk(closed.jaxpr)


def network_shape(f: Callable, n_args: int) -> tuple[int, int]:
    """(equations, nonlinear vector equations) of f's jaxpr on `n_args` float32 scalars
    (call-like bodies counted inside): networks have few equations, some of them
    nonlinear operations on vectors (activations), where `fresh_symbols` apply; long
    scalar programs have thousands and none."""
    avals = [jax.ShapeDtypeStruct((), jnp.float32)] * n_args
    closed = jax.make_jaxpr(f)(*avals)

    def walk(jaxpr):
        eqns = vectors = 0
        for eqn in jaxpr.eqns:
            body = _call_body(eqn)
            if body is not None:
                e, v = walk(body.jaxpr if isinstance(body, jcore.ClosedJaxpr) else body)
                eqns, vectors = eqns + e, vectors + v
                continue
            eqns += 1
            vectors += (eqn.primitive.name in _NONLINEAR
                        and any(len(v.aval.shape) == 1 and v.aval.shape[0] > 1
                                for v in eqn.outvars))
        return eqns, vectors

    return walk(closed.jaxpr)


def flat_program(f: Callable, n_args: int):
    """f traced on `n_args` float32 scalars and flattened to straight-line nodes.

    Returns (nodes, out): each node is ``("input", k)``, ``("const", value)`` (a numpy
    scalar: literals, closed-over constants and every equation whose inputs are all
    constant, folded with ``primitive.bind``) or ``(primitive name, params, operand node
    indices)``; call-like primitives (jit, custom_jvp/vjp calls) are inlined. `out` is
    the index of the result node. Primitives are not interpreted here: the caller maps
    them (and rejects what it does not know)."""
    avals = [jax.ShapeDtypeStruct((), jnp.float32)] * n_args
    closed = jax.make_jaxpr(f)(*avals)
    _check_output(closed, f)
    nodes: list = []

    def const(value):
        nodes.append(("const", np.asarray(value)))
        return len(nodes) - 1

    def run(jaxpr, consts, args):
        env = {}

        def read(v):
            return const(v.val) if isinstance(v, jcore.Literal) else env[v]

        for v, c in zip(jaxpr.constvars, consts):
            env[v] = const(c)
        for v, a in zip(jaxpr.invars, args):
            env[v] = a
        for eqn in jaxpr.eqns:
            ins = [read(v) for v in eqn.invars]
            body = _call_body(eqn)
            if body is not None and eqn.primitive.name not in _LOOP_PRIMITIVES:
                outs = run(*_closed(body), ins)
            elif all(nodes[i][0] == "const" for i in ins):
                val = eqn.primitive.bind(*[nodes[i][1] for i in ins], **eqn.params)
                vals = val if eqn.primitive.multiple_results else [val]
                outs = [const(np.asarray(v)) for v in vals]
            else:
                if eqn.primitive.multiple_results or len(eqn.outvars) != 1:
                    raise NotImplementedError(
                        f"flat_program: primitive '{eqn.primitive.name}' has several "
                        "results")
                nodes.append((eqn.primitive.name, dict(eqn.params), tuple(ins)))
                outs = [len(nodes) - 1]
            for v, o in zip(eqn.outvars, outs):
                env[v] = o
        return [read(v) for v in jaxpr.outvars]

    inputs = []
    for k in range(n_args):
        nodes.append(("input", k))
        inputs.append(len(nodes) - 1)
    out = run(closed.jaxpr, closed.consts, inputs)[0]
    return nodes, out
