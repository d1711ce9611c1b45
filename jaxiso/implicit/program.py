"""Long implicit programs as instruction tapes, and the steps of the tape path that work
on batches of tapes.

Programs of thousands of operations (CSG of hundreds of primitives, Prospero) cannot be
inlined into XLA: compile time and memory grow with their length. Here a program is an
instruction tape (`jaxiso.arith._tape.Tape`, data) run by one compiled evaluator per
bucketed length. `tape_of` turns a `VMProgram` or a plain-JAX ``f(x, y, z[, w])`` into a
tape; `long_program_tape` decides whether a scene's f is long enough for the tape path
(`TAPE_CROSSOVER`). The tape path itself (breadth-first ray groups with per-region
pruning, MPR / fidget style) is `_tape_rays`, reached through the default
`jaxiso.intersect` / `jaxiso.render` of an `ImplicitSurface`; the helpers here
(`chunked_eval`, `gather_children`, `ambiguous_positions`, `histogram`) are its shared
steps.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..arith import Affine, Interval, Tape
from ..arith import tape as _tape
from ._field import as_field
from ._memo import BoundedCache
from .vm import VMProgram

__all__ = ["tape_of", "evaluate_points", "evaluate_intervals", "TAPE_CROSSOVER",
           "prefers_tape", "long_program_tape", "chunked_eval", "gather_children",
           "ambiguous_positions", "histogram"]

# Program length (tape instructions) from which the tape path is chosen over the straight
# (inlined) path: see benchmarks/bench_programs.py (crossover section) and NOTES.
TAPE_CROSSOVER = 1024


def prefers_tape(tape: Tape) -> bool:
    """Whether a program of this length should run on the tape path."""
    return int(tape.n) >= TAPE_CROSSOVER


# f -> its tape, or None (not a tape program): built once per function (tracing a long
# program takes seconds); bounded, emptied by `jaxiso.clear_caches`
_TAPES = BoundedCache("tapes of long programs", 16)


def long_program_tape(f, params_tree=None) -> Tape | None:
    """The tape of ``f(x, y, z[, w][, params])`` when it is a program the tape path should
    run (at least `TAPE_CROSSOVER` instructions, every operation a tape opcode), else None.
    `params_tree`: None (f takes no params) or the treedef of a params pytree of scalar
    leaves, which become coordinates 4, 5, ... of the tape. Built once per function
    (tracing a long program takes seconds)."""
    return _TAPES.get((f, params_tree), lambda: _long_tape(f, params_tree))


def _long_tape(f, params_tree):
    try:
        with jax.ensure_compile_time_eval():  # concrete even when asked under a jit trace
            tape = tape_of(f, params_tree)
    except (NotImplementedError, TypeError, ValueError):
        return None  # array code, selects...: the straight path runs it
    return tape if prefers_tape(tape) else None


# --------------------------------------------------------------------------- tapes

_VM_UNARY = {"neg": "neg", "abs": "abs", "square": "square", "sqrt": "sqrt", "exp": "exp",
             "ln": "log", "sin": "sin", "cos": "cos"}
_VM_BINARY = {"add": "add", "sub": "sub", "mul": "mul", "div": "div", "min": "min",
              "max": "max"}
_VARS = {"var-x": 0, "var-y": 1, "var-z": 2}


def tape_of(f, params_tree=None) -> Tape:
    """The tape of a program: a `VMProgram`, or a plain-JAX ``f(x, y, z)`` /
    ``f(x, y, z, w)`` on scalars; with `params_tree` (the treedef of a pytree of scalar
    params) ``f(x, y, z[, w], params)``, whose params leaves become coordinates 4, 5, ...
    Coordinates are x, y, z, w (then the params). Raises NotImplementedError for an
    operation the tape has no opcode for."""
    if isinstance(f, Tape):
        return f
    if isinstance(f, VMProgram) and params_tree is None:
        return _vm_tape(f)
    if params_tree is None:
        g = as_field(f, False)
        return _tape.from_function(lambda x, y, z, w: g(x, y, z, w, ()), 4)
    g = as_field(f, True)
    n = params_tree.num_leaves

    def flat(x, y, z, w, *leaves):
        return g(x, y, z, w, jax.tree_util.tree_unflatten(params_tree, leaves))

    return _tape.from_function(flat, 4 + n)


def _vm_tape(prog: VMProgram) -> Tape:
    ops, where = [], []
    for i, (op, args) in enumerate(prog.ops):
        if op == "const":
            ops.append(("const", 0, 0, float(args[0])))
        elif op in _VARS:
            ops.append(("var", _VARS[op], 0, 0.0))
        elif op == "copy":
            where.append(where[args[0]])
            continue
        elif op == "recip":
            ops.append(("const", 0, 0, 1.0))
            ops.append(("div", len(ops) - 1, where[args[0]], 0.0))
        elif op in _VM_UNARY:
            ops.append((_VM_UNARY[op], where[args[0]], 0, 0.0))
        elif op in _VM_BINARY:
            x, y = where[args[0]], where[args[1]]
            if x == y and op == "mul":
                ops.append(("square", x, 0, 0.0))
            else:
                ops.append((_VM_BINARY[op], x, y, 0.0))
        else:
            raise NotImplementedError(
                f"{prog.source}: instruction {i + 1} ({prog.names[i]} {op}) has no tape "
                f"opcode (the tape runs {', '.join(sorted(_VM_UNARY) + sorted(_VM_BINARY))})")
        where.append(len(ops) - 1)
    return _tape.tidy(ops, where[-1], 4)


@functools.partial(jax.jit, static_argnames=("record",))
def evaluate_tapes(tape, coords, record=False):
    """`_tape.evaluate` jitted (one compiled evaluator per opset, padded length and
    register count)."""
    return _tape.evaluate(tape, coords, record)


def evaluate_points(tape: Tape, x, y, z, w=0.0):
    """The program at points (arrays broadcasting to one shape S), through the tape
    (one compiled evaluator per padded length). Returns float32 [S]."""
    x, y, z, w = jnp.broadcast_arrays(*(jnp.asarray(v, jnp.float32) for v in (x, y, z, w)))
    shape = x.shape
    one = _tape.take_regions(tape, jnp.zeros(1, jnp.int32))
    out = evaluate_tapes(one, [v.reshape(1, -1) for v in (x, y, z, w)])
    return out.reshape(shape)


def evaluate_intervals(tape: Tape, x: Interval, y: Interval, z: Interval, w=0.0) -> Interval:
    """The program's interval extension (`ia` rules) on boxes of one shape S."""
    w = w if isinstance(w, Interval) else Interval(jnp.float32(w), jnp.float32(w))
    shape = jnp.broadcast_shapes(*[jnp.shape(c.lo) for c in (x, y, z)])
    flat = [Interval(jnp.broadcast_to(c.lo, shape).reshape(1, -1),
                     jnp.broadcast_to(c.hi, shape).reshape(1, -1)) for c in (x, y, z)]
    one = _tape.take_regions(tape, jnp.zeros(1, jnp.int32))
    out = evaluate_tapes(one, flat + [w])
    return Interval(out.lo.reshape(shape), out.hi.reshape(shape))


def _lead(c):
    """A coordinate's value array (points), lower bounds or centres."""
    return c.lo if isinstance(c, Interval) else c.center if isinstance(c, Affine) else c


# Up to this many instructions x regions a store's tapes are gathered once before an
# evaluation rather than at every step: a few regions of a long tape (the roots: 4 x
# 8,192) paid the step's gathers' fixed cost 7,871 times (slab 1024^2 root 0.45 -> 0.96 s).
_GATHER_ONCE = 2**20


def chunked_eval(tapes, coords, record, budget, min_chunks=1, index=None, active=None):
    """`_tape.evaluate` over region chunks so that its working set (the register file,
    and the choices of `record`) stays within `budget` elements (R is a power of two), in
    at least `min_chunks` chunks (each runs as many instructions as its longest tape:
    regions sorted by tape length gain). `index` (None or [R]): `tapes` is a store and
    region r runs tape index[r] (`_tape.evaluate`); the chunks split the index.
    `active` (None or bool [R]): the regions to run (`_tape.evaluate`)."""
    L = tapes.length
    if index is not None and index.shape[0] * L <= _GATHER_ONCE:
        tapes, index = _tape.take_regions(tapes, index), None
    R = tapes.op.shape[1] if index is None else index.shape[0]
    P = jnp.broadcast_shapes(*[jnp.shape(_lead(c)) for c in coords])[-1]
    # an affine register holds n + 4 parts (form and bounds), an interval 2, a point 1
    parts = (coords[0].n + 4 if isinstance(coords[0], Affine)
             else 2 if isinstance(coords[0], Interval) else 1)
    per_region = tapes.registers * P * parts + (L * P // 4 if record else 0)
    chunks = 1
    while R % (2 * chunks) == 0 and (per_region * (R // chunks) > budget or
                                     chunks < min_chunks):
        chunks *= 2
    if chunks == 1:
        return _tape.evaluate(tapes, coords, record, index, active)
    act = (jnp.ones((chunks, R // chunks), bool) if active is None
           else active.reshape(chunks, R // chunks))

    def split_coord(x):
        x = jnp.broadcast_to(x, (R, 1)) if jnp.ndim(x) == 0 else x
        x = jnp.broadcast_to(x, (R,) + jnp.shape(x)[1:])
        return x.reshape((chunks, R // chunks) + x.shape[1:])

    def split_prog(x):  # [L, ..., R] -> [chunks, L, ..., R / chunks]
        return jnp.moveaxis(x.reshape(x.shape[:-1] + (chunks, R // chunks)), -2, 0)

    cc = jax.tree_util.tree_map(split_coord, coords)
    if index is None:
        ct = _tape.map_program(tapes, split_prog, tapes.n.reshape(chunks, R // chunks))
        out = jax.lax.map(lambda args: _tape.evaluate(args[0], args[1], record,
                                                      active=args[2]), (ct, cc, act))
    else:
        out = jax.lax.map(lambda args: _tape.evaluate(tapes, args[1], record, args[0],
                                                      args[2]),
                          (index.reshape(chunks, R // chunks), cc, act))
    if record:
        val, ch = out
        ch = jnp.moveaxis(ch, 0, 1).reshape((L, R) + ch.shape[3:])
        return jax.tree_util.tree_map(lambda x: x.reshape((R,) + x.shape[2:]), val), ch
    return jax.tree_util.tree_map(lambda x: x.reshape((R,) + x.shape[2:]), out)


def ambiguous_positions(amb, size):
    """Flat positions of the ambiguous children of amb [R, C] (the first `size`, padded
    with 0), int32 [size]. On the host: a jitted `nonzero` compiled once per level shape
    (11 compiles, 3.9 s of the slab's first call at 256^2) for a few kB of work."""
    flat = np.flatnonzero(np.asarray(amb).reshape(-1))[:size]
    return jnp.asarray(np.pad(flat, (0, size - flat.size)).astype(np.int32))


@functools.partial(jax.jit, static_argnames=("size", "copy", "h"))
def gather_children(tapes, children, chosen, where, start, count, size, copy=True,
                    origin=None, h=1):
    """Children where[start:start + size] (those past `count` invalid) of regions whose
    tapes are `tapes` (a store: region r runs tape children["tid"][r]): their regions
    (with "tid", each child's tape in the store returned), that store, and their own
    min/max choices ([L, size]).

    `copy=False`: the children share their parents' tapes (the store is `tapes`, no
    choices: None). `copy=True`: each child gets its parent's tape, without registers
    (about to be pruned, which allocates them anew), in a store of its own ([L, size],
    tid = position); with `origin` ([L', groups]), `tapes` are the children's groups'
    ([L', groups]: a group is h consecutive children of a parent, its tape pruned by
    their shared choices, `prune(..., origins=True)`) and the choices are read at each
    group instruction's origin ([L', size])."""
    C = children["g"].shape[1]
    k = start + jnp.arange(size)
    idx = where[jnp.minimum(k, where.shape[0] - 1)]
    ok = k < count
    r, c = idx // C, idx % C
    reg = {key: v.reshape(-1)[idx] for key, v in children.items()}
    reg["valid"] = ok
    if not copy:
        return tapes, None, reg
    tapes = dataclasses.replace(tapes, reg=None)
    if origin is None:
        parent, choices = _tape.take_regions(tapes, reg["tid"]), chosen[:, r, c]
    else:
        g = r * (C // h) + c // h
        parent, choices = _tape.take_regions(tapes, g), chosen[origin[:, g], r, c]
    parent = dataclasses.replace(parent, n=jnp.where(ok, parent.n, 1))
    reg["tid"] = jnp.arange(size, dtype=jnp.int32)
    return parent, choices, reg


def histogram(n):
    """Counts of tape lengths `n` by power-of-two bins (a level's report)."""
    n = np.asarray(n)
    if n.size == 0:
        return {}
    edges = [0, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384]
    h, _ = np.histogram(n, bins=edges)
    return {f"{lo}-{hi - 1}": int(c) for lo, hi, c in zip(edges[:-1], edges[1:], h) if c}
