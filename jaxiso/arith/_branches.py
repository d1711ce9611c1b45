"""Cases of a ``where`` evaluated where they are taken.

``jnp.where(h > c, A(h), B(h))`` takes A only where ``h >= c`` and B only where
``h <= c``. Evaluated on the whole box, each case sees all of h: the hull of the two (an
elu written ``where(h > 0, h, exp(min(h, 0)) - 1)``) then reaches down to h's lower end
where the function itself is above -1, and every layer of a network widens it further.
Here each case's equations that depend on h (its slice) are evaluated a second time
with h clipped to the side where the case is taken -- ``[c, inf)`` or ``(-inf, c]``
-- which encloses the case wherever the selection takes it, so the selection of the
clipped cases is as sound as the plain one. In interval arithmetic it is then exactly as
tight as the spelling with a rule of its own (`jax.nn.elu`); an affine form keeps its
deviations and takes the clip as a bound (`Affine.lo`, `Affine.hi`), which the next
rule's linearisation uses.

Both operands of the comparison are restricted where they are lifted floats, each by
the other's range (``u > v`` gives ``u >= lo(v)`` and ``v <= hi(u)``). A slice is at
most `MAX_SLICE` equations, found backwards from the case (a longer case is left as it
is); an operand outside the slice keeps its value, an enclosure there too.

This module reads jaxprs (`plan`: what is clipped and what is recomputed) and clips
values (`taken_side`); `_extend` runs the recomputation with its own rules.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

from . import _affine as aa
from . import _interval as ia
from ._affine import Affine
from ._interval import Interval

# The most equations recomputed per case: an activation's (elu: min, exp, sub) or a
# clamp's is a handful; a longer case is left as it is (each recomputed equation is
# compiled again: the nested wheres of tests/test_affine_where.py took 20,259 affine
# equations with 64 against 7,821 with none; 8,911 with 8).
MAX_SLICE = 8

# comparison -> does "true" bound the first operand below by the second (u >= v)?
_FIRST_BELOW = {"gt": True, "ge": True, "lt": False, "le": False}


@dataclasses.dataclass(frozen=True)
class Case:
    """One case operand of a selection: its position among the equation's operands, the
    selection's truth where it is taken, and the equations (indices into the jaxpr) to
    recompute for it, in order."""

    position: int
    taken_when: bool
    slice: tuple


@dataclasses.dataclass(frozen=True)
class Selection:
    """A selection at some equation: the compared operands ``u OP v`` (made by the
    equation `compare`) and its cases. `inputs`: the variables the comparison, the
    recomputed cases and the other operands read from outside them; `elementwise`: all
    of those equations act element by element (each output element reads the same
    element of each operand), so with one lifted input the selection is a function of
    that input alone, element by element (`_extend` then evaluates it on a one-symbol
    stand-in: the same enclosure at a fraction of the work)."""

    comparison: str
    u: object  # a Var or a Literal
    v: object
    cases: tuple
    compare: int
    predicate: int  # the position of the comparison's result among the operands
    inputs: frozenset
    elementwise: bool
    extremum: tuple | None = None  # ("max" or "min", a, b): the selection is that of a, b


# lax primitives that act element by element (with operands of one shape or scalars)
ELEMENTWISE = frozenset({
    "add", "sub", "mul", "div", "neg", "max", "min", "exp", "exp2", "expm1", "log",
    "log1p", "tanh", "logistic", "sin", "cos", "tan", "abs", "sqrt", "rsqrt", "cbrt",
    "pow", "integer_pow", "square", "erf", "erfc", "atan", "atan2", "asinh", "sinh",
    "cosh", "sign", "select_n", "convert_element_type", "gt", "ge", "lt", "le", "eq",
    "ne", "and", "or", "not", "floor", "ceil", "round", "clamp", "copy", "copy_p",
    "stop_gradient", "rem", "nextafter"})


def _elementwise(eqn, call_body) -> bool:
    """Does `eqn` act element by element (a call: every equation of its body)?"""
    if eqn.primitive.name in ELEMENTWISE:
        return True
    if eqn.primitive.name == "broadcast_in_dim":  # a scalar: each element reads it
        return all(v.aval.shape == () for v in eqn.invars)
    body = call_body(eqn)
    if body is None:
        return False
    inner = body.jaxpr if isinstance(body, jcore.ClosedJaxpr) else body
    shapes = {tuple(v.aval.shape) for v in list(eqn.invars) + list(eqn.outvars)
              if isinstance(v, jcore.Var)}
    return len(shapes - {()}) <= 1 and all(_elementwise(e, call_body) for e in inner.eqns)


def _inputs(eqns, indices, also) -> frozenset:
    """The variables that the equations `indices` and the operands `also` read from
    outside those equations."""
    made = {v for k in indices for v in eqns[k].outvars}
    read = [v for k in indices for v in eqns[k].invars] + list(also)
    return frozenset(v for v in read if isinstance(v, jcore.Var) and v not in made)


def _select_positions(eqn, call_body):
    """{operand position: case index} and the predicate's position, for a ``select_n``
    of two cases or a call whose body is one (``jnp.where`` is a call to ``_where``);
    None otherwise."""
    if eqn.primitive.name == "select_n" and len(eqn.invars) == 3:
        return 0, {1: 0, 2: 1}
    body = call_body(eqn)
    if body is None:
        return None
    inner = body.jaxpr if isinstance(body, jcore.ClosedJaxpr) else body
    if not inner.eqns or inner.eqns[-1].primitive.name != "select_n":
        return None
    *prepare, sel = inner.eqns
    if len(sel.invars) != 3 or list(inner.outvars) != list(sel.outvars):
        return None
    where = {v: k for k, v in enumerate(inner.invars)}
    for e in prepare:  # a where's scalar case converted and broadcast to the shape
        if (e.primitive.name not in _OPERAND_PREPARATION or len(e.invars) != 1
                or not isinstance(e.invars[0], jcore.Var) or e.invars[0] not in where):
            return None
        where[e.outvars[0]] = where[e.invars[0]]
    if not all(isinstance(v, jcore.Var) and v in where for v in sel.invars):
        return None
    return where[sel.invars[0]], {where[sel.invars[1]]: 0, where[sel.invars[2]]: 1}


# equations a call to ``_where`` applies to an operand before its select_n
_OPERAND_PREPARATION = frozenset({"convert_element_type", "broadcast_in_dim"})


def _elementwise_selection(eqn, call_body) -> bool:
    """The selection itself acts element by element (no broadcasting in a call)."""
    return eqn.primitive.name == "select_n" or _elementwise(eqn, call_body)


def _slice(eqns, producer, start, roots, before):
    """Indices (ascending, all < `before`) of the equations between `roots` and `start`
    that depend on a root, or None when there are more than MAX_SLICE (the case is then
    left as it is). Found backwards from `start`, never past the roots' equations."""
    first = min((producer.get(r, -1) for r in roots), default=-1)
    seen, stack, found = set(), [start], []
    while stack:
        k = producer.get(stack.pop())
        if k is None or k <= first or k >= before or k in seen:
            continue
        if len(found) >= 4 * MAX_SLICE:
            return None
        seen.add(k)
        found.append(k)
        stack.extend(v for v in eqns[k].invars
                     if isinstance(v, jcore.Var) and v not in roots)
    depends = set(roots)
    picked = []
    for k in sorted(found):
        if any(isinstance(v, jcore.Var) and v in depends for v in eqns[k].invars):
            picked.append(k)
            depends.update(eqns[k].outvars)
    return tuple(picked) if len(picked) <= MAX_SLICE else None


@dataclasses.dataclass(frozen=True)
class Plan:
    """selections: {equation index: `Selection`}; deferred: the indices of equations
    whose results only the recomputed cases used (not run unless another use appears:
    each one would be compiled, and take fresh noise symbols, for nothing)."""

    selections: dict
    deferred: frozenset


def plan(jaxpr, call_body) -> Plan:
    """The selections of `jaxpr` on a comparison and what they make unneeded
    (`call_body(eqn)` gives a call equation's body or None)."""
    eqns = jaxpr.eqns
    producer = {v: k for k, e in enumerate(eqns) for v in e.outvars}
    selections = {}
    for i, eqn in enumerate(eqns):
        found = _select_positions(eqn, call_body)
        if found is None:
            continue
        pred_pos, cases = found
        pred = eqn.invars[pred_pos]
        k = producer.get(pred) if isinstance(pred, jcore.Var) else None
        if k is None or eqns[k].primitive.name not in _FIRST_BELOW:
            continue
        u, v = eqns[k].invars
        roots = {w for w in (u, v) if isinstance(w, jcore.Var)}
        made = []
        for pos, index in cases.items():
            var = eqn.invars[pos]
            if not isinstance(var, jcore.Var):
                continue
            sl = () if var in roots else _slice(eqns, producer, var, roots, i)
            if sl or var in roots:
                made.append(Case(pos, bool(index), sl))
        if made:
            steps = sorted({k} | {j for c in made for j in c.slice})
            recomputed = {c.position for c in made}
            others = [w for p, w in enumerate(eqn.invars)
                      if p != pred_pos and p not in recomputed]
            selections[i] = Selection(
                eqns[k].primitive.name, u, v, tuple(made), k, pred_pos,
                _inputs(eqns, steps, others + [u, v]),
                all(_elementwise(eqns[j], call_body) for j in steps)
                and _elementwise_selection(eqn, call_body),
                extremum(eqns[k].primitive.name, u, v, eqn, cases, eqns, producer))
    return Plan(selections, _unneeded(jaxpr, selections))


def extremum(comparison: str, u, v, eqn, cases, eqns, producer) -> tuple | None:
    """("max" or "min", a, b) when the selection is max(a, b) or min(a, b), shaped as its
    result, else None:

    * its cases are the compared operands: ``where(h > 0, h, 0)`` is relu,
      ``where(x > 1, 1, x)`` a clamp (a, b = u, v);
    * u is compared with 0 and each case is u times a constant (u itself included):
      ``where(h >= 0, h, 0.01 h)`` (`jax.nn.leaky_relu`) is max(h, 0.01 h): two lines
      through the origin, the steeper one taken right of it is their max, else min.

    Its enclosure is then the max or min rule's, which keeps an affine form's
    correlations (the selection rule's join or chord keeps fewer, at several times the
    cost). cases: {operand position: case index} (index 1 is taken where the comparison
    is true); eqns, producer: the jaxpr's equations and {variable: its equation}."""
    taken = {index: eqn.invars[pos] for pos, index in cases.items()}
    out = eqn.outvars[0].aval if len(eqn.outvars) == 1 else None
    if set(taken) != {0, 1} or out is None or any(
            isinstance(w, jcore.Var) and w.aval.dtype != out.dtype for w in (u, v)):
        return None
    first_below = _FIRST_BELOW[comparison]  # true: u >= v
    if _is_zero_literal(u) and isinstance(v, jcore.Var):  # 0 < h: h > 0
        u, v, first_below = v, u, not first_below
    if tuple(jnp.broadcast_shapes(u.aval.shape, v.aval.shape)) == tuple(out.shape):
        if _same_operand(taken[1], u) and _same_operand(taken[0], v):
            return ("max" if first_below else "min", u, v)
        if _same_operand(taken[1], v) and _same_operand(taken[0], u):
            return ("min" if first_below else "max", u, v)
    if not (_is_zero_literal(v) and tuple(u.aval.shape) == tuple(out.shape)):
        return None
    slopes = [_slope_of(taken[i], u, eqns, producer) for i in (0, 1)]
    if None in slopes or not np.all(np.isfinite(slopes)) or slopes[0] == slopes[1]:
        return None  # one line (or a NaN slope) is no max or min
    right = 1 if first_below else 0  # the case taken where u >= 0
    steeper_right = slopes[right] > slopes[1 - right]
    return ("max" if steeper_right else "min", taken[1], taken[0])


def _is_zero_literal(x) -> bool:
    return isinstance(x, jcore.Literal) and np.shape(x.val) == () and float(x.val) == 0.0


def _slope_of(case, u, eqns, producer):
    """c where `case` is c u: u itself (1), the literal 0 (0), ``neg`` of u (-1) or
    ``mul`` of u by a scalar literal; else None."""
    if case is u:
        return 1.0
    if _is_zero_literal(case):
        return 0.0
    k = producer.get(case) if isinstance(case, jcore.Var) else None
    if k is not None and eqns[k].primitive.name == "neg" and eqns[k].invars[0] is u:
        return -1.0
    if k is None or eqns[k].primitive.name != "mul":
        return None
    a, b = eqns[k].invars
    other = b if a is u else a if b is u else None
    if not isinstance(other, jcore.Literal) or np.shape(other.val) != ():
        return None
    return float(other.val)


def _same_operand(a, b) -> bool:
    """a and b are one variable, or literals of one scalar value."""
    if isinstance(a, jcore.Var) or isinstance(b, jcore.Var):
        return a is b
    x, y = np.asarray(a.val), np.asarray(b.val)
    return x.shape == y.shape == () and bool(x == y)


def _unneeded(jaxpr, selections) -> frozenset:
    """Equations of the slices (and comparisons) whose every use is a recomputed case
    (a predicate: recomputed on a stand-in, `_extend`) or another such equation
    (latest first: uses come after). They are run only if read after all."""
    replaced = {(i, p) for i, sel in selections.items()
                for p in [c.position for c in sel.cases] + [sel.predicate]}
    uses = {}
    for j, e in enumerate(jaxpr.eqns):
        for pos, w in enumerate(e.invars):
            if isinstance(w, jcore.Var):
                uses.setdefault(w, []).append((j, pos))
    outputs = {w for w in jaxpr.outvars if isinstance(w, jcore.Var)}
    candidates = sorted({k for sel in selections.values() for c in sel.cases
                         for k in c.slice} | {sel.compare for sel in selections.values()},
                        reverse=True)
    unneeded = set()
    for k in candidates:
        if all(w not in outputs and all(j in unneeded or (j, pos) in replaced
                                        for j, pos in uses.get(w, ()))
               for w in jaxpr.eqns[k].outvars):
            unneeded.add(k)
    return frozenset(unneeded)


def bounds(comparison: str, taken_when: bool):
    """Which way each operand is bounded where the comparison is `taken_when`:
    (u's bound is from below, v's bound is from below)."""
    u_below = _FIRST_BELOW[comparison] == taken_when
    return u_below, not u_below


def taken_side(x, other, below: bool):
    """x (a lifted float) where it is >= `other` (`below`) or <= it: an Interval clipped
    at the other's lower (upper) end, empty (NaN) where nothing is left; an Affine
    bounded there (`Affine.lo`, `Affine.hi`). `other` is a lifted value or a point."""
    if isinstance(other, Affine):
        other = aa.padded_range(other)
    o_lo, o_hi = (other.lo, other.hi) if isinstance(other, Interval) else (other, other)
    if isinstance(x, Affine):
        if below:
            return dataclasses.replace(x, lo=jnp.fmax(x.lo, o_lo))
        return dataclasses.replace(x, hi=jnp.fmin(x.hi, o_hi))
    shape = jnp.shape(x.lo)
    side = (Interval(jnp.broadcast_to(o_lo, shape), jnp.full(shape, jnp.inf, x.lo.dtype))
            if below else
            Interval(jnp.full(shape, -jnp.inf, x.lo.dtype), jnp.broadcast_to(o_hi, shape)))
    return ia.intersect(x, side)
