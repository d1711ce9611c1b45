"""Instruction tapes: straight-line programs as data, run by one compiled evaluator.

A `Tape` is a program in SSA form: instruction i computes value i from the values named
by its operand indices `a`, `b` (earlier instructions), a constant `imm` or a coordinate
(``var``: `a` is the axis). The opcodes are `OPS`. Because the program is data (int32 and
float32 arrays), one compiled `evaluate` runs any tape of the same padded length: a new
program, or a program pruned for a region of space, costs no new XLA code. Tapes are
padded to bucketed lengths (`bucket`) so that only a few shapes ever compile.

`evaluate` runs a batch of tapes ``[R, L]`` (one per region) on ``[R, P]`` points,
intervals or AF1 affine forms with a `lax.fori_loop` over instructions and a register
file ``[L, R, P]``; each step computes the opcodes the tape set can use (its static
`opset`) and selects per region. Interval and affine semantics are the rules of `ia` and
`aa` (the same functions as `extend`). In interval and affine mode it can also record,
per min/max instruction, which operand the enclosures prove is chosen; `prune` then
rewrites each tape for its region: decided min/max become their operand and instructions
no longer reachable from the output are dropped (the tape is compacted).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._core import pytree_dataclass, static_field
from . import _affine as aa
from . import _interval as ia
from ._affine_type import Affine
from ._affine_type import padded_range as _range
from ._interval import Interval

__all__ = ["OPS", "Tape", "assemble", "from_function", "evaluate", "prune", "allocate",
           "bucket", "longest_bucket", "take_regions", "resize", "with_opset",
           "with_registers", "map_program", "register_bucket", "registers_in_use",
           "highest_register", "narrowed"]

OPS = ("const", "var", "neg", "abs", "square", "sqrt", "exp", "log", "sin", "cos", "ipow",
       "add", "sub", "mul", "div", "min", "max")
CODE = {name: i for i, name in enumerate(OPS)}
CONST, VAR, NEG, ABS, SQUARE, SQRT, EXP, LOG, SIN, COS, IPOW = range(11)
ADD, SUB, MUL, DIV, MIN, MAX = range(11, 17)
FIRST_UNARY, FIRST_BINARY = NEG, ADD
_IPOW_BITS = 10
MAX_IPOW = 2**_IPOW_BITS - 1  # exponents of ipow: bits of repeated squaring


def bucket(n: int, minimum: int = 16, fine: bool = False) -> int:
    """The padded size for n: the next power of two (fine: or 1.5 times one), at least
    `minimum`."""
    p = 1 << max(0, math.ceil(math.log2(max(n, 1))))
    if fine and p >= 4 and 3 * p // 4 >= n:
        p = 3 * p // 4
    return max(minimum, p)


@pytree_dataclass
class Tape:
    """One tape ([L] arrays, scalar n) or a batch of tapes ([L, R] arrays, instruction
    major, and [R] n).

    Attributes:
      op, a, b: int32 opcode and operand indices (``var``: a = coordinate axis).
      imm: float32 constant of ``const`` (the exponent of ``ipow``).
      n: int32 number of instructions in use; the result is instruction n - 1.
      opset: static sorted tuple of the opcodes the tape may contain (the evaluator
        computes only these).
      n_vars: static number of coordinates the program reads (x, y, z[, w]).
      reg: int32 [L, 3] ([L, 3, R]) registers of each instruction: where operand a and
        operand b are read from and where the result is written (`allocate`).
      registers: static size of the register file the evaluator holds (every tape
        derived from this one by pruning needs at most as many, see `allocate`).
    """

    op: jax.Array
    a: jax.Array
    b: jax.Array
    imm: jax.Array
    n: jax.Array
    opset: tuple = static_field()
    n_vars: int = static_field()
    reg: jax.Array | None = None
    registers: int = static_field(0)

    @property
    def length(self) -> int:
        """The padded length L."""
        return self.op.shape[0]

    def uses(self, axis: int) -> bool:
        """Whether the (concrete) tape reads coordinate `axis`."""
        op, a = np.asarray(self.op), np.asarray(self.a)
        return bool(np.any((op == VAR) & (a == axis)))


def assemble(ops, n_vars: int, length: int | None = None) -> Tape:
    """A tape from a list of ``(opname, a, b, imm)`` in SSA order (operands index earlier
    entries; the last entry is the result), padded to `length` (default `bucket`)."""
    n = len(ops)
    if n == 0:
        raise ValueError("an empty program")
    L = bucket(n) if length is None else length
    if L < n:
        raise ValueError(f"length {L} < {n} instructions")
    op = np.zeros(L, np.int32)
    a = np.zeros(L, np.int32)
    b = np.zeros(L, np.int32)
    imm = np.zeros(L, np.float32)
    for i, (name, ai, bi, v) in enumerate(ops):
        code = CODE[name]
        op[i], a[i], b[i], imm[i] = code, ai, bi, v
        if code >= FIRST_UNARY and not ai < i or code >= FIRST_BINARY and not bi < i:
            raise ValueError(f"instruction {i} ({name}) reads a later value")
        if code == VAR and not 0 <= ai < n_vars:
            raise ValueError(f"instruction {i} reads coordinate {ai} of {n_vars}")
    opset = tuple(sorted({CODE[o[0]] for o in ops} | {CONST}))
    reg, used = _allocate_host(op[:n], a[:n], b[:n])
    return Tape(jnp.asarray(op), jnp.asarray(a), jnp.asarray(b), jnp.asarray(imm),
                jnp.asarray(n, jnp.int32), opset, n_vars,
                jnp.asarray(np.pad(reg, [(0, L - n), (0, 0)])), register_bucket(used))


def longest_bucket(tape: Tape) -> int:
    """The bucketed length of a (concrete) batch's longest tape, read on the host."""
    return bucket(int(np.max(np.asarray(tape.n))))


def register_bucket(used: int) -> int:
    """The register-file size compiled for a program that needs `used` registers."""
    return bucket(used, 4)


def _allocate_host(op, a, b):
    """Registers of an SSA program (numpy, one tape): the linear scan of `allocate`,
    growing the file as needed. Returns (reg [n, 3], registers used)."""
    n = len(op)
    last = np.full(n, -1, np.int64)
    for i in range(n):
        if op[i] >= FIRST_UNARY:
            last[a[i]] = i
        if op[i] >= FIRST_BINARY:
            last[b[i]] = i
    reg = np.zeros((n, 3), np.int32)
    free: list = []
    used = 0
    for i in range(n):
        for k, x in ((0, a[i]), (1, b[i])):
            if op[i] >= (FIRST_UNARY, FIRST_BINARY)[k]:
                reg[i, k] = reg[x, 2]
                if last[x] == i and not (k == 1 and b[i] == a[i]):
                    free.append(reg[x, 2])
        if free:
            reg[i, 2] = free.pop()
        else:
            reg[i, 2] = used
            used += 1
    return reg, used

# ------------------------------------------------------------- from plain JAX functions

_UNARY_PRIMS = {"neg": "neg", "abs": "abs", "sqrt": "sqrt", "exp": "exp", "log": "log",
                "sin": "sin", "cos": "cos", "square": "square"}
_BINARY_PRIMS = {"add": "add", "sub": "sub", "mul": "mul", "div": "div", "max": "max",
                 "min": "min"}
_IDENTITY_PRIMS = ("copy", "copy_p", "convert_element_type", "reduce_precision")


def from_function(f, n_vars: int) -> Tape:
    """The tape of a plain-JAX scalar function ``f(x0, ..., x{n_vars-1})`` (float32).

    Raises NotImplementedError naming a primitive the tape has no opcode for (comparisons,
    selects, loops, array operations): such functions stay on the straight path."""
    from ._extend import flat_program  # all jaxpr access lives in _extend

    nodes, out = flat_program(f, n_vars)
    ops = _Instructions()
    where: dict = {}  # node index -> tape index
    for k, node in enumerate(nodes):
        index = _emit_node(ops, where, node)
        if index is not None:
            where[k] = index
    if out not in where:
        raise NotImplementedError("tape: the result is not a scalar number")
    return tidy(ops.entries, where[out], n_vars)


class _Instructions:
    """The ``(opname, a, b, imm)`` list of a tape being built (SSA order)."""

    def __init__(self):
        self.entries: list = []

    def emit(self, name, a=0, b=0, imm=0.0) -> int:
        """Append one instruction; its index."""
        self.entries.append((name, a, b, imm))
        return len(self.entries) - 1

    def const(self, value) -> int:
        return self.emit("const", imm=float(value))

    def power(self, x: int, y: int) -> int:
        """x ** y for a Python int y: 1, 1 / x ** -y, x, square or ipow."""
        if y == 0:
            return self.const(1.0)
        if y < 0:
            return self.emit("div", self.const(1.0), self.power(x, -y))
        if y == 1:
            return x
        if y == 2:
            return self.emit("square", x)
        if y > MAX_IPOW:
            raise NotImplementedError(f"tape: integer power {y} > {MAX_IPOW}")
        return self.emit("ipow", x, imm=float(y))


def _emit_node(ops: _Instructions, where: dict, node) -> int | None:
    """Emit the instructions of one `flat_program` node; the tape index of its value, or
    None for a constant the tape does not hold (non-scalar: it may only feed folded
    equations)."""
    kind = node[0]
    if kind == "input":
        return ops.emit("var", node[1])
    if kind == "const":
        v = node[1]
        if v.shape != () or not np.issubdtype(v.dtype, np.floating) and \
                not np.issubdtype(v.dtype, np.integer):
            return None
        return ops.const(v)
    name, params, args = node
    for i in args:
        if i not in where:
            raise NotImplementedError(f"tape: primitive '{name}' reads a non-scalar or "
                                      "non-numeric constant")
    return _emit_primitive(ops, name, params, [where[i] for i in args])


def _emit_primitive(ops: _Instructions, name: str, params, ins) -> int:
    """Emit JAX primitive `name` on the tape values `ins`; the tape index of its result."""
    if name in _IDENTITY_PRIMS:
        dtype = params.get("new_dtype", jnp.float32)
        if dtype is not None and not jnp.issubdtype(dtype, jnp.floating):
            raise NotImplementedError(f"tape: conversion to {dtype}")
        return ins[0]
    if name in _UNARY_PRIMS:
        return ops.emit(_UNARY_PRIMS[name], ins[0])
    if name in _BINARY_PRIMS:
        x, y = ins
        if x == y and name == "mul":
            return ops.emit("square", x)
        if x == y and name == "sub":
            return ops.const(0.0)
        return ops.emit(_BINARY_PRIMS[name], x, y)
    if name == "integer_pow":
        return ops.power(ins[0], int(params["y"]))
    if name == "pow" and ops.entries[ins[1]][0] == "const" and \
            float(ops.entries[ins[1]][3]).is_integer():
        return ops.power(ins[0], int(ops.entries[ins[1]][3]))
    raise NotImplementedError(
        f"tape: no opcode for the JAX primitive '{name}' (the tape knows "
        f"{', '.join(OPS)}); this function stays on the straight path")


def tidy(ops, out: int, n_vars: int) -> Tape:
    """Keep what the output reads; leaves (const, var) first; then assemble."""
    live = np.zeros(len(ops), bool)
    live[out] = True
    for i in range(out, -1, -1):
        if live[i]:
            code = CODE[ops[i][0]]
            if code >= FIRST_UNARY:
                live[ops[i][1]] = True
            if code >= FIRST_BINARY:
                live[ops[i][2]] = True
    # leaves (const, var) just before their first use: a leaf defined early would hold a
    # register until it is read (hoisted constants made CSG-40 need 512 registers, not 36)
    order, placed = [], np.zeros(len(ops), bool)
    for i in range(out + 1):
        code = CODE[ops[i][0]]
        if not live[i] or code < FIRST_UNARY:
            continue
        for k, first in ((1, FIRST_UNARY), (2, FIRST_BINARY)):
            x = ops[i][k]
            if code >= first and CODE[ops[x][0]] < FIRST_UNARY and not placed[x]:
                order.append(x)
                placed[x] = True
        order.append(i)
    if not order:  # the program is a single leaf
        order = [out]
    new = {old: j for j, old in enumerate(order)}
    tidy = []
    for old in order:
        name, a, b, v = ops[old]
        code = CODE[name]
        tidy.append((name, new[a] if code >= FIRST_UNARY else a,
                     new[b] if code >= FIRST_BINARY else b, v))
    return assemble(tidy, n_vars)


# ------------------------------------------------------------------------- evaluation


def _ipow_point(v, n):
    """v ** n for int32 n in [0, MAX_IPOW] by repeated squaring in lax.integer_pow's
    order (bitwise the same products)."""
    acc = jnp.ones_like(v)
    for bit in range(_IPOW_BITS):
        acc = jnp.where(((n >> bit) & 1) == 1, acc * v, acc)
        v = v * v
    return acc


def _point_cases(opset, va, vb, imm, var):
    table = _point_table(va, vb, imm, var)
    return [table[c]() for c in opset]


def _point_table(va, vb, imm, var):
    """opcode -> thunk of its rule on points."""
    n = imm.astype(jnp.int32)
    return {
        CONST: lambda: jnp.broadcast_to(imm, va.shape), VAR: lambda: var,
        NEG: lambda: -va, ABS: lambda: jnp.abs(va), SQUARE: lambda: va * va,
        SQRT: lambda: jnp.sqrt(va), EXP: lambda: jnp.exp(va), LOG: lambda: jnp.log(va),
        SIN: lambda: jnp.sin(va), COS: lambda: jnp.cos(va),
        IPOW: lambda: _ipow_point(va, n), ADD: lambda: va + vb, SUB: lambda: va - vb,
        MUL: lambda: va * vb, DIV: lambda: va / vb, MIN: lambda: jnp.minimum(va, vb),
        MAX: lambda: jnp.maximum(va, vb),
    }


def _ipow_interval(x: Interval, n) -> Interval:
    """ia.ipow with a traced exponent: even powers are even, odd ones monotone."""
    even = (n % 2) == 0
    lo = jnp.where(even, _ipow_point(ia.mig(x), n), _ipow_point(x.lo, n))
    hi = jnp.where(even, _ipow_point(ia.mag(x), n), _ipow_point(x.hi, n))
    return Interval(lo, hi)


def _ipow_affine(x: Affine, n) -> Affine:
    """x ** n with a traced exponent: the interval power on the error term (the
    correlation with x is not kept; `aa.ipow` needs a static exponent)."""
    return aa.from_interval(_ipow_interval(aa.to_interval(x), n), None, x.n)


def _interval_product(a: Interval, b: Interval) -> Interval:
    """`ia.mul` for the evaluator's step: the hull of the four plain endpoint products,
    and `ia.mul` itself (0 x inf = 0, empties kept empty) only in a step where some
    region's hull came out NaN, which is where the two differ (a NaN product needs a NaN,
    or 0 times an infinite, endpoint; XLA's min and max pass NaN on). The guards were 40%
    of a step's time on Prospero's levels (benchmarks/NOTES.md, session 32). Elsewhere the
    two agree up to the sign of a zero bound."""
    lo, hi = ia.product_hull(a, b)

    def guarded(_):
        r = ia.mul(a, b)
        return r.lo, r.hi

    lo, hi = lax.cond(jnp.any(jnp.isnan(lo) | jnp.isnan(hi)), guarded,
                      lambda _: (lo, hi), None)
    return Interval(lo, hi)


def _enclosure_cases(opset, va, vb, imm, var):
    """The rules of the opcodes in `opset` on intervals (`ia`) or affine forms (`aa`)."""
    table = _enclosure_table(va, vb, imm, var)
    return [table[c]() for c in opset]


def _enclosure_table(va, vb, imm, var):
    """opcode -> thunk of its rule on intervals (`ia`) or affine forms (`aa`)."""
    n = imm.astype(jnp.int32)
    if isinstance(va, Affine):
        m, ipow = aa, _ipow_affine
        const = aa.as_affine(jnp.broadcast_to(imm, va.center.shape), va.n)
    else:
        m, ipow = ia, _ipow_interval
        c = jnp.broadcast_to(imm, va.lo.shape)
        const = Interval(c, c)
    return {
        CONST: lambda: const, VAR: lambda: var,
        NEG: lambda: m.neg(va), ABS: lambda: m.abs(va), SQUARE: lambda: m.square(va),
        SQRT: lambda: m.sqrt(va), EXP: lambda: m.exp(va), LOG: lambda: m.log(va),
        SIN: lambda: m.sin(va), COS: lambda: m.cos(va),
        IPOW: lambda: ipow(va, n), ADD: lambda: m.add(va, vb),
        SUB: lambda: m.sub(va, vb), DIV: lambda: m.div(va, vb),
        MUL: lambda: m.mul(va, vb) if m is aa else _interval_product(va, vb),
        MIN: lambda: m.minimum(va, vb), MAX: lambda: m.maximum(va, vb),
    }


def _select(opset, o, cases):
    """cases[position of o in opset] per region (o: [R], cases: [R, P, ...] each)."""
    if len(cases) == 1:
        return cases[0]
    which = jnp.asarray(_opcode_positions(opset))[o].reshape((-1,) + (1,) * (cases[0].ndim - 1))
    return lax.select_n(jnp.broadcast_to(which, cases[0].shape), *cases)


def _choice(o, va, vb):
    """1 where the enclosures prove min/max takes its first operand, 2 the second, else 0
    (intervals compare bounds; affine forms bound the difference, which keeps their
    correlation)."""
    o = o[:, None]
    if isinstance(va, Affine):
        d = _range(aa.sub(va, vb))  # a - b, padded as aa.minimum / aa.maximum do
        first = jnp.where(o == MIN, d.hi <= 0, d.lo >= 0)
        second = jnp.where(o == MIN, d.lo >= 0, d.hi <= 0)
    else:
        first = jnp.where(o == MIN, va.hi <= vb.lo, va.lo >= vb.hi)
        second = jnp.where(o == MIN, vb.hi <= va.lo, vb.lo >= va.hi)
    pick = jnp.where(first, 1, jnp.where(second, 2, 0)).astype(jnp.int8)
    return jnp.where((o == MIN) | (o == MAX), pick, jnp.int8(0))


def evaluate(tape: Tape, coords, record: bool = False, index=None, active=None):
    """Run a batch of tapes on points, intervals or affine forms.

    Args:
      tape: a batch of tapes ([L, R] arrays, [R] n); with `index`, a store of tapes
        ([L, S] arrays) of which region r runs tape index[r].
      coords: `tape.n_vars` coordinates, each a float32 array, an `Interval` or an AF1
        `Affine` form (all with the same noise symbols), broadcastable to [R, P] (all of
        one kind).
      record: interval / affine mode only: also return the min/max choices, int8
        [L, R, P] (1: the first operand is proved to be chosen on that box, 2: the
        second, 0: both possible or not a min/max).
      index: None, or int32 [R]: each region's tape in the store (regions that share a
        tape read it in place, without a copy per region).
      active: None, or bool [R]: regions to run (the others run no instruction and
        return garbage; a batch padded at its end then costs what its real regions do).

    Returns the program's value [R, P] (an array, an Interval or an Affine), and the
    choices if `record`. Pure; jit it with the tape as an argument (its `opset`/`n_vars`/
    `registers` static). The register file [registers, R, parts x P] holds every part of a
    value side by side (points 1, intervals 2, affine forms with n symbols n + 4): its
    size does not grow with the program's length. Every step computes the rule of each
    opcode in `opset` and selects; with affine rules that is 8-9x the interval cost on
    CPU (benchmarks/NOTES.md, Session 8), not (n + 2) / 2.
    """
    kind = _coordinate_kind(coords, tape.n_vars, record)
    L, R = tape.op.shape
    if tape.reg is None:
        raise ValueError("the tape has no registers (`allocate`)")
    view = _View(tape, None if index is None else jnp.asarray(index, jnp.int32))
    R = view.regions
    K = tape.registers
    cstack = _coordinate_parts(coords, kind, R)
    n_sym = coords[0].n if kind is Affine else 0
    rows = jnp.arange(R)
    # one register file: the value's parts side by side
    packing = _Packing(kind, len(cstack), cstack[0].shape[-1], n_sym)
    regs = jnp.zeros((K, R, packing.parts * packing.width), jnp.float32)
    choices = jnp.zeros((L, R, packing.width), jnp.int8) if record else None
    n = view.n() if active is None else jnp.where(active, view.n(), 0)
    step = functools.partial(_step, view, n, packing, cstack, rows, record)
    regs, choices = lax.fori_loop(0, jnp.max(n), step, (regs, choices))
    last = jnp.clip(n - 1, 0, L - 1)
    out_reg = tape.reg[last, 2, view.columns(rows)]
    result = packing.unpack(regs[jnp.clip(out_reg, 0, K - 1), rows])
    if record:
        return result, choices
    return result


def _coordinate_kind(coords, n_vars: int, record: bool) -> type:
    """The one type of `evaluate`'s coordinates (an array type, Interval or Affine)."""
    if len(coords) != n_vars:
        raise ValueError(f"the tape reads {n_vars} coordinates, got {len(coords)}")
    kind = type(coords[0])
    if any(type(c) is not kind for c in coords) and kind in (Interval, Affine):
        raise TypeError("the coordinates must all be points, all Intervals or all Affine")
    if record and kind not in (Interval, Affine):
        raise ValueError("record=True needs interval or affine coordinates")
    return kind


@dataclasses.dataclass(frozen=True)
class _Packing:
    """How `evaluate` holds a value in a register-file row [R, parts x width]: its parts
    ([R, width] each) side by side: a point's value, an interval's (lo, hi), an affine
    form's (center, dev_0, ..., dev_{n_sym-1}, err, lo, hi). The form's bounds are kept:
    without them a chain of min/max grows its forms' error by a factor each step
    (Prospero's affine enclosures reached 1e38 where its intervals stayed within 0.4)."""

    kind: type
    parts: int
    width: int
    n_sym: int

    def value(self, p):
        """The value of parts p ([R, width] each)."""
        if self.kind is Interval:
            return Interval(p[0], p[1])
        if self.kind is Affine:
            n = self.n_sym
            return Affine(p[0], jnp.stack(p[1:1 + n], axis=-1), p[1 + n], None, p[2 + n],
                          p[3 + n])
        return p[0]

    def unpack(self, row):
        """The value of a register-file row [R, parts x width]."""
        P = self.width
        return self.value([row[:, c * P:(c + 1) * P] for c in range(self.parts)])

    def selected(self, opset, o, cases):
        """The parts ([R, width] each) of the case that each region's opcode o ([R])
        selects among `cases` (one value per opcode of `opset`)."""
        if self.kind is Interval:
            return [_select(opset, o, [c.lo for c in cases]),
                    _select(opset, o, [c.hi for c in cases])]
        if self.kind is Affine:
            dev = _select(opset, o, [c.dev for c in cases])
            return ([_select(opset, o, [c.center for c in cases])]
                    + [dev[..., k] for k in range(self.n_sym)]
                    + [_select(opset, o, [getattr(c, k) for c in cases])
                       for k in ("err", "lo", "hi")])
        return [_select(opset, o, cases)]


class _View(NamedTuple):
    """The tapes `evaluate` runs: a batch ([L, R], index None) or a store read at index
    [R]."""

    tape: Tape
    index: jax.Array | None

    @property
    def regions(self) -> int:
        return self.tape.op.shape[1] if self.index is None else self.index.shape[0]

    def n(self):
        return self.tape.n if self.index is None else self.tape.n[self.index]

    def row(self, x):
        """Row x [S] of a field at instruction i, per region [R]."""
        return x if self.index is None else x[self.index]

    def columns(self, rows):
        return rows if self.index is None else self.index


def _step(view: _View, n, packing: _Packing, cstack, rows, record: bool, i, carry):
    """Instruction i of every tape (`evaluate`'s loop body): read the operands, compute,
    write the result's register; with `record`, store the min/max choices [R, P] at i.
    carry: (register file [K, R, parts x P], choices [L, R, P] or None)."""
    regs, choices = carry
    tape = view.tape
    K = tape.registers
    # int32 whatever the store's width (`narrowed` tapes hold int8 / int16)
    o, a = (view.row(x[i]).astype(jnp.int32) for x in (tape.op, tape.a))
    ra, rb, rd = (jnp.clip(view.row(tape.reg[i, k]).astype(jnp.int32), 0, K - 1)
                  for k in range(3))
    rd = jnp.where(i < n, rd, K)  # past a tape's end: written nowhere
    imm = view.row(tape.imm[i])[:, None]
    if record:
        # both operands by one gather into a fresh [2, R, C P] array: read as two
        # slices fused into their readers, the choices' store made XLA copy the
        # whole register file twice a step (Prospero's root, 1024 boxes: 75 us a
        # step, against 10 us so; without choices the slices are faster, 3.7 us)
        ab = regs[jnp.stack([ra, rb]), rows[None]]
        A, B = packing.unpack(ab[0]), packing.unpack(ab[1])
    else:
        A, B = packing.unpack(regs[ra, rows]), packing.unpack(regs[rb, rows])
    var = packing.value([c[jnp.clip(a, 0, tape.n_vars - 1), rows] for c in cstack])
    if view.regions == 1 and len(tape.opset) > 1:
        out = _one_region_parts(tape.opset, packing.kind, o, A, B, imm, var)
    else:
        rule = _enclosure_cases if packing.kind in (Interval, Affine) else _point_cases
        out = packing.selected(tape.opset, o, rule(tape.opset, A, B, imm, var))
    regs = regs.at[rd, rows].set(jnp.concatenate(out, axis=-1), mode="drop")
    if record:
        choices = lax.dynamic_update_index_in_dim(choices, _choice(o, A, B), i, 0)
    return regs, choices


def _one_region_parts(opset, kind, o, A, B, imm, var):
    """The parts of a single region's result (R = 1, e.g. a root shared by all its
    children): only the opcode's own rule runs (lax.switch), not every rule of the opset
    (Prospero's root level: 1.35 s of 4.3 s at 128^2 before)."""
    table = _enclosure_table if kind in (Interval, Affine) else _point_table
    cases = [lambda c=c: _flat_parts(table(A, B, imm, var)[c]()) for c in opset]
    return lax.switch(jnp.asarray(_opcode_positions(opset))[o[0]], cases)


def _opcode_positions(opset):
    """opcode -> its position in `opset` (numpy int32 [len(OPS)], 0 for the others)."""
    lookup = np.zeros(len(OPS), np.int32)
    lookup[list(opset)] = np.arange(len(opset))
    return lookup


def _flat_parts(v):
    """A value's parts ([R, P] each) in the register file's order."""
    if isinstance(v, Interval):
        return [v.lo, v.hi]
    if isinstance(v, Affine):
        return [v.center] + [v.dev[..., k] for k in range(v.n)] + [v.err, v.lo, v.hi]
    return [v]


def _coordinate_parts(coords, kind, R):
    """The coordinates as a list of parts, each [n_vars, R, P] float32: (x,), (lo, hi) or
    (center, dev_0, ..., dev_{n-1}, err, lo, hi)."""
    if kind is Interval:
        pieces = [(c.lo, c.hi) for c in coords]
    elif kind is Affine:
        n = coords[0].n
        for c in coords:
            if c.n != n:
                raise ValueError(f"affine coordinates with {c.n} and {n} noise symbols")
        pieces = [(c.center, *[c.dev[..., k] for k in range(n)], c.err, c.lo, c.hi)
                  for c in coords]
    else:
        pieces = [(c,) for c in coords]
    shape = jnp.broadcast_shapes((R, 1), *[jnp.shape(x) for p in pieces for x in p])
    return [jnp.stack([jnp.broadcast_to(p[k], shape) for p in pieces]).astype(jnp.float32)
            for k in range(len(pieces[0]))]


# ---------------------------------------------------------------------------- pruning


def prune(tape: Tape, choice, origins: bool = False, registers: bool = True):
    """Each tape of a batch shortened for its region.

    Args:
      tape: [L, R] batch of tapes.
      choice: int8 [L, R] from `evaluate(..., record=True)` on the region (per region,
        one box): 1/2 where a min/max is proved to take its first/second operand.
      origins: also return where each pruned instruction was in `tape` (static).
      registers: assign the pruned tapes' registers (static; False: ``reg`` None, for
        tapes that will be pruned again, whose pruning assigns them).

    Returns the [L, R] batch with decided min/max replaced by their operand, everything
    not reachable from the output dropped, and the rest moved to the front in order (new
    n); with `origins`, (that batch, int32 [L, R]: the instruction's index in `tape`, 0
    past n). On the region, the pruned tape computes the same values as the tape (same
    operations in the same order on the surviving path)."""
    # Three loops over instructions (`_resolve`, `_kept`, `_compact`), each touching O(R)
    # elements per step and carrying a single flat buffer (XLA updates it in place;
    # whole-array gathers and scatters were 10x slower on CPU). Layout [L, R]: step i
    # reads and writes row i.
    op = tape.op
    rows = jnp.arange(op.shape[1], dtype=jnp.int32)
    has_a = op >= FIRST_UNARY
    has_b = op >= FIRST_BINARY
    minmax = (op == MIN) | (op == MAX)
    pick = jnp.where(minmax, choice, 0).astype(jnp.int32)
    resolved, top = _resolve(tape, has_a, has_b, pick, rows)
    keep = _kept(tape.n, pick, has_a, has_b, resolved, rows, top)
    dense, new_n = _compact(tape, has_a, has_b, resolved, keep, rows, top, origins)
    reg = _pruned_registers(dense, new_n, tape.registers) if registers else None
    out = Tape(dense[0], dense[1], dense[2], lax.bitcast_convert_type(dense[3], jnp.float32),
               new_n, tape.opset, tape.n_vars, reg, tape.registers)
    return (out, dense[4]) if origins else out


def _resolve(tape: Tape, has_a, has_b, pick, rows):
    """Pruning's forward pass: each value's resolution (itself, or what a decided min/max
    takes; the operands are earlier, so one pass resolves chains) and the resolved
    operands. pick: int32 [L, R] (1/2: a decided min/max's operand, else 0).

    Returns ((res, a2, b2) int32 [L, R] each, top: the loops' bound, the largest n)."""
    L, R = tape.op.shape
    a, b = tape.a, tape.b
    a_safe = jnp.where(has_a, a, 0)
    b_safe = jnp.where(has_b, b, 0)
    LR = L * R

    def fwd(i, buf):
        ra = buf[a_safe[i] * R + rows]
        rb = buf[b_safe[i] * R + rows]
        res = jnp.where(pick[i] == 1, ra, jnp.where(pick[i] == 2, rb, i))
        buf = lax.dynamic_update_slice(buf, res, (i * R,))
        buf = lax.dynamic_update_slice(buf, jnp.where(has_a[i], ra, a[i]), (LR + i * R,))
        return lax.dynamic_update_slice(buf, jnp.where(has_b[i], rb, b[i]), (2 * LR + i * R,))

    top = jnp.max(tape.n)  # rows past every n are not visited
    buf = lax.fori_loop(0, top, fwd, jnp.zeros(3 * LR, jnp.int32))
    return tuple(buf[k * LR:(k + 1) * LR].reshape(L, R) for k in range(3)), top


def _kept(n, pick, has_a, has_b, resolved, rows, top):
    """Pruning's backward pass: the instructions kept ([L, R] bool): live (read from the
    output through kept instructions' resolved operands), not a decided min/max, and
    within the tape's n ([R])."""
    res, a2, b2 = resolved
    L, R = res.shape
    LR = L * R
    own = pick == 0
    out = res[jnp.clip(n - 1, 0, L - 1), rows]
    srcs = jnp.concatenate([jnp.where(has_a & own, a2, L), jnp.where(has_b & own, b2, L)],
                           axis=1)  # [L, 2R]
    rows2 = jnp.concatenate([rows, rows])

    def back(j, live):
        i = top - 1 - j
        li = lax.dynamic_slice(live, (i * R,), (R,))
        li2 = jnp.concatenate([li, li])
        dest = jnp.where((srcs[i] < L) & (li2 == 1), srcs[i] * R + rows2, LR)
        return live.at[dest].set(1, mode="drop")

    live0 = jnp.zeros(LR, jnp.int8).at[out * R + rows].set(1)
    live = lax.fori_loop(0, top, back, live0).reshape(L, R)
    return (live == 1) & own & (jnp.arange(L)[:, None] < n[None, :])


def _compact(tape: Tape, has_a, has_b, resolved, keep, rows, top, origins=False):
    """Pruning's compaction: kept instruction i moves to its region's next free slot with
    its operands renumbered, one scatter per instruction.

    Returns (int32 [4, L, R]: op, a, b and imm's bits, padded with ``const 0``, and with
    `origins` a fifth field: i; new n [R])."""
    L, R = keep.shape
    LR = L * R
    _, a2, b2 = resolved
    imm_bits = lax.bitcast_convert_type(tape.imm, jnp.int32)
    pos, new_n = _new_positions(keep, top)
    new_a = jnp.where(has_a, pos[jnp.where(has_a, a2, 0) * R + rows], tape.a)
    new_b = jnp.where(has_b, pos[jnp.where(has_b, b2, 0) * R + rows], tape.b)
    parts = [tape.op, new_a, new_b, imm_bits]
    if origins:
        parts.append(jnp.broadcast_to(jnp.arange(L, dtype=jnp.int32)[:, None], (L, R)))
    nf = len(parts)
    fields = jnp.stack(parts, axis=1).reshape(L, nf * R)
    F = LR + R  # each field: [L + 1, R], row L for the dropped
    offsets = jnp.repeat(jnp.arange(nf, dtype=jnp.int32) * F, R)
    rows4 = jnp.tile(rows, nf)
    keep4 = jnp.tile(keep, (1, nf))
    pos4 = jnp.tile(pos.reshape(L, R), (1, nf))
    # materialised once: XLA would otherwise sink these broadcasts into the loop body
    fields, offsets, rows4, keep4, pos4 = lax.optimization_barrier(
        (fields, offsets, rows4, keep4, pos4))

    def scatter(i, dense):
        dest = offsets + jnp.where(keep4[i], pos4[i] * R, LR) + rows4
        return dense.at[dest].set(fields[i])

    init = jnp.concatenate([jnp.full(F, CONST, jnp.int32), jnp.zeros((nf - 1) * F, jnp.int32)])
    dense = lax.fori_loop(0, top, scatter, init).reshape(nf, L + 1, R)[:, :L]
    return dense, new_n


def _new_positions(keep, top):
    """Where each kept instruction goes: a running count per region (int32 [L R], flat)
    and the count of kept instructions, the new n [R]."""
    L, R = keep.shape

    def count(i, carry):
        buf, cnt = carry  # the small counters apart: a read-then-write of one buffer
        return (lax.dynamic_update_slice(buf, cnt, (i * R,)),  # made XLA copy it per step
                cnt + keep[i].astype(jnp.int32))

    return lax.fori_loop(0, top, count, (jnp.zeros(L * R, jnp.int32),
                                         jnp.zeros(R, jnp.int32)))


def _pruned_registers(dense, new_n, registers: int):
    """Registers [L, 3, R] of the pruned tapes (dense: op, a, b, ... [4, L, R]) in a file
    of `registers`: each instruction its own register where every pruned tape is at most
    `IN_ORDER_MAX` long and fits the file (no scan: on short tapes it cost more than it
    saved), else the linear scan (`allocate`), which packs a tape's values into the
    registers live at once (Prospero's final pieces: at most 18 of its 256), so that
    `registers_in_use` can cut the evaluator's file. Registers in order on tapes up to
    128 long left the slab's final checks running a file of 256: 2.8 s a batch of 49,152
    pieces, against 0.2 s on 32 registers after a 0.2 s scan (benchmarks/NOTES.md,
    session 32)."""
    L, R = dense.shape[1:]

    def in_order(_):
        return jnp.stack([dense[1], dense[2], jnp.broadcast_to(
            jnp.arange(L, dtype=jnp.int32)[:, None], (L, R))], axis=1)

    return lax.cond(jnp.max(new_n) <= min(registers, IN_ORDER_MAX), in_order,
                    lambda _: allocate(dense[0], dense[1], dense[2], new_n, registers)[0],
                    None)


# Pruned tapes at most this long keep each instruction in its own register (the smallest
# file `registers_in_use` cuts to)
IN_ORDER_MAX = 32


def allocate(op, a, b, n, registers: int):
    """Registers of a batch of SSA tapes, a linear scan per region (as libfive and fidget
    allocate): at each instruction the operands read for the last time free their
    registers, then the result takes a free one, so the file holds only the values live
    at once.

    Args:
      op, a, b: int32 [L, R] SSA tapes (operands index earlier instructions).
      n: int32 [R] instructions in use.
      registers: the file's size K (static). A tape pruned from a program needs at most
        the registers the program needs: every value live across a kept instruction of the
        pruned tape resolves from a value live across it in the program.

    Returns (reg int32 [L, 3, R]: operand a's, operand b's and the result's register;
    used int32 [R]: the most registers in use at once, > K only if K was too small, when
    the registers are wrong)."""
    L, R = op.shape
    K = registers
    rows = jnp.arange(R, dtype=jnp.int32)
    i_col = jnp.arange(L, dtype=jnp.int32)[:, None]
    act = i_col < n[None, :]
    has_a = act & (op >= FIRST_UNARY)
    has_b = act & (op >= FIRST_BINARY)
    a = jnp.where(has_a, a, 0)
    b = jnp.where(has_b, b, 0)
    # each value's last reader (one scatter; the loop below only reads it)
    last = jnp.full(L * R, -1, jnp.int32)
    last = last.at[jnp.where(has_a, a * R + rows, L * R)].max(
        jnp.broadcast_to(i_col, (L, R)), mode="drop")
    last = last.at[jnp.where(has_b, b * R + rows, L * R)].max(
        jnp.broadcast_to(i_col, (L, R)), mode="drop").reshape(L, R)
    frees_a = has_a & (jnp.take_along_axis(last, a, 0) == i_col)
    frees_b = has_b & (jnp.take_along_axis(last, b, 0) == i_col) & (b != a)
    top = jnp.max(n)

    def step(i, carry):
        # buf: the registers of every instruction, [3 L R] (instruction major: step i
        # writes its own row, reads earlier ones); the free stacks apart, [K R]
        buf, stack, count, used = carry
        ra = buf[(3 * a[i] + 2) * R + rows]
        rb = buf[(3 * b[i] + 2) * R + rows]
        for reg_, frees in ((ra, frees_a[i]), (rb, frees_b[i])):
            stack = stack.at[jnp.where(frees, jnp.minimum(count, K - 1) * R + rows,
                                       K * R)].set(reg_, mode="drop")
            count = count + frees
        take = act[i]
        count = count - take
        d = jnp.where(take, stack[jnp.clip(count, 0, K - 1) * R + rows], 0)
        used = jnp.maximum(used, K - count)
        row = jnp.stack([ra, rb, d]).reshape(-1)
        return lax.dynamic_update_slice(buf, row, (3 * i * R,)), stack, count, used

    stack0 = (K - 1 - jnp.arange(K, dtype=jnp.int32)[:, None]).repeat(R, 1).reshape(-1)
    init = (jnp.zeros(3 * L * R, jnp.int32), stack0, jnp.full(R, K, jnp.int32),
            jnp.zeros(R, jnp.int32))
    buf, _, _, used = lax.fori_loop(0, top, step, init)
    return buf.reshape(L, 3, R), used


def map_program(tape: Tape, fn, n=None) -> Tape:
    """The tape with `fn` applied to each per-instruction array (op, a, b, imm, reg;
    instruction axis first, regions last) and n replaced by `n` (default: kept). A tape
    without registers (`reg` None: one about to be pruned) stays without."""
    return Tape(fn(tape.op), fn(tape.a), fn(tape.b), fn(tape.imm),
                tape.n if n is None else n, tape.opset, tape.n_vars,
                None if tape.reg is None else fn(tape.reg), tape.registers)


def with_opset(tape: Tape, opset) -> Tape:
    """The tape allowed to hold the opcodes of `opset` too (codes or names): tapes that
    share an opset, a padded length and a register count share one compiled evaluator."""
    codes = {CODE[o] if isinstance(o, str) else int(o) for o in opset}
    return dataclasses.replace(tape, opset=tuple(sorted(set(tape.opset) | codes)))


def with_registers(tape: Tape, registers: int) -> Tape:
    """The tape evaluated with a register file of `registers` (at least its own)."""
    if registers < tape.registers:
        raise ValueError(f"the tape needs {tape.registers} registers, got {registers}")
    return dataclasses.replace(tape, registers=int(registers))


def highest_register(tape: Tape):
    """The highest register a batch's instructions use (traced int32 scalar; -1: none)."""
    live = (jnp.arange(tape.length)[:, None] < tape.n[None, :])[:, None, :]  # [L, 1, R]
    return jnp.max(jnp.where(live, tape.reg, -1))


def registers_in_use(tape: Tape, highest=None, minimum: int = IN_ORDER_MAX) -> Tape:
    """A batch of (concrete) tapes with its register file cut to the registers its
    instructions use (`highest`: `highest_register`, computed when None), bucketed (at
    least `minimum`, so that batches share compiled shapes); the evaluator's file, and
    the time each step's gathers and scatters take in it, shrink with it."""
    if tape.reg is None or tape.op.ndim != 2:
        return tape
    if highest is None:
        highest = jax.jit(highest_register)(tape)
    used = int(highest) + 1
    return dataclasses.replace(tape, registers=min(tape.registers, bucket(used, minimum)))


def take_regions(tape: Tape, index) -> Tape:
    """The tapes of a batch at `index` ([R'] ints; a single tape is broadcast)."""
    k = jnp.shape(index)[0]
    if tape.op.ndim == 1:
        return map_program(tape, lambda x: jnp.broadcast_to(x[..., None], x.shape + (k,)),
                           jnp.broadcast_to(tape.n, (k,)))
    return map_program(tape, lambda x: x[..., index], tape.n[index])


NARROW_MAX = 2**15 - 1  # the largest operand index or register an int16 holds


def narrowed(tape: Tape) -> Tape:
    """The tapes with opcodes as int8 and operands and registers as int16 (15 bytes an
    instruction instead of 28), for tapes of at most `NARROW_MAX` instructions and
    registers that are only evaluated (not pruned). `evaluate` reads either width."""
    if tape.length > NARROW_MAX or tape.registers > NARROW_MAX:
        raise ValueError(f"a tape of {tape.length} instructions and {tape.registers} "
                         f"registers does not fit int16 operands")
    return Tape(tape.op.astype(jnp.int8), tape.a.astype(jnp.int16), tape.b.astype(jnp.int16),
                tape.imm, tape.n, tape.opset, tape.n_vars,
                None if tape.reg is None else tape.reg.astype(jnp.int16), tape.registers)


def resize(tape: Tape, length: int) -> Tape:
    """The tapes padded (``const 0``) or cut to `length` instructions (callers cut only
    past every n)."""
    L = tape.length
    if length == L:
        return tape
    if length < L:
        return map_program(tape, lambda x: x[:length])
    return map_program(tape, lambda x: jnp.pad(x, [(0, length - L)] + [(0, 0)] * (x.ndim - 1)))
