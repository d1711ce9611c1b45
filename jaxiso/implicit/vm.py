"""Implicit programs in the `.vm` text format of fidget / the Prospero challenge.

One instruction per line, ``name opcode args...``: `args` name earlier instructions (or,
for ``const``, give a number); the last instruction is the result. Blank lines and lines
starting with ``#`` are comments. `load_vm` reads such a file (or text) into a `VMProgram`,
a plain-jnp function ``f(x, y, z)`` that every jaxiso arithmetic extends: use it as
``ji.ImplicitSurface(load_vm("prospero.vm"), lo, hi)`` (a 2D program, one without
``var-z``, is extruded along z).
"""

from __future__ import annotations

import dataclasses
import os

import jax.numpy as jnp
import numpy as np

__all__ = ["VMProgram", "load_vm", "OPCODES"]

_UNARY = {
    "neg": jnp.negative, "abs": jnp.abs, "square": jnp.square, "sqrt": jnp.sqrt,
    "recip": jnp.reciprocal, "exp": jnp.exp, "ln": jnp.log, "sin": jnp.sin, "cos": jnp.cos,
    "tan": jnp.tan, "asin": jnp.arcsin, "acos": jnp.arccos, "atan": jnp.arctan,
    "floor": jnp.floor, "ceil": jnp.ceil, "round": jnp.round, "copy": lambda a: a,
}
_BINARY = {
    "add": jnp.add, "sub": jnp.subtract, "mul": jnp.multiply, "div": jnp.divide,
    "min": jnp.minimum, "max": jnp.maximum, "atan2": jnp.arctan2,
}
_VARS = {"var-x": 0, "var-y": 1, "var-z": 2}
OPCODES = ("const",) + tuple(_VARS) + tuple(_UNARY) + tuple(_BINARY)


@dataclasses.dataclass(frozen=True, eq=False)  # identity hash: a scene's static f
class VMProgram:
    """A straight-line program: ``ops[i] = (opcode, operands)`` with operands indices of
    earlier instructions (a float for ``const``, the axis for ``var-*``).

    Attributes:
      ops: tuple of (opcode, tuple) per instruction.
      names: the instruction names of the file, for messages.
      source: where it came from (path or "<text>").
    """

    ops: tuple
    names: tuple
    source: str = "<text>"

    def __len__(self) -> int:
        return len(self.ops)

    @property
    def variables(self) -> tuple:
        """The coordinates the program reads, e.g. ("x", "y")."""
        return tuple(sorted({op[len("var-"):] for op, _ in self.ops if op in _VARS}))

    def counts(self) -> dict:
        """Instructions per opcode."""
        out: dict = {}
        for op, _ in self.ops:
            out[op] = out.get(op, 0) + 1
        return out

    def __call__(self, x, y, z):
        """The program's value at (x, y, z) (z ignored by 2D programs)."""
        coords = (x, y, z)
        vals = []
        for op, args in self.ops:
            if op == "const":
                v = jnp.float32(args[0])
            elif op in _VARS:
                v = coords[args[0]]
            elif op in _UNARY:
                v = _UNARY[op](vals[args[0]])
            else:
                v = _BINARY[op](vals[args[0]], vals[args[1]])
            vals.append(v)
        return vals[-1]


def load_vm(source) -> VMProgram:
    """Read a `.vm` program from a path (str / PathLike) or from its text (a str with a
    newline). Raises ValueError naming the line of a malformed or unsupported
    instruction."""
    if isinstance(source, str) and "\n" in source:
        text, where = source, "<text>"
    else:
        where = os.fspath(source)
        try:
            with open(where, encoding="utf-8") as fh:
                text = fh.read()
        except UnicodeDecodeError as e:
            raise ValueError(f"{where}: not a text .vm program ({e})") from None
    return parse_vm(text, where)


def parse_vm(text: str, where: str = "<text>") -> VMProgram:
    index: dict = {}
    ops, names = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue

        def fail(why, lineno=lineno, line=line):
            raise ValueError(f"{where} line {lineno}: {why}: {line.strip()!r}")

        if len(words) < 2:
            fail("expected 'name opcode args...'")
        name, op, args = words[0], words[1], words[2:]
        if name in index:
            fail(f"{name!r} is defined twice (first on instruction {index[name] + 1})")
        if op == "const":
            if len(args) != 1:
                fail("const takes one number")
            value = _number(args[0])
            if value is None:
                fail(f"const value {args[0]!r} is not a number")
            if not np.isfinite(value):
                fail(f"const value {args[0]!r} is not finite")
            operands = (value,)
        elif op in _VARS:
            if args:
                fail(f"{op} takes no operands")
            operands = (_VARS[op],)
        elif op in _UNARY or op in _BINARY:
            arity = 1 if op in _UNARY else 2
            if len(args) != arity:
                fail(f"{op} takes {arity} operand{'s' * (arity > 1)}, got {len(args)}")
            missing = [a for a in args if a not in index]
            if missing:
                fail(f"operand {missing[0]!r} is not defined on an earlier line")
            operands = tuple(index[a] for a in args)
        else:
            fail(f"unsupported opcode {op!r} (supported: {', '.join(OPCODES)})")
        index[name] = len(ops)
        ops.append((op, operands))
        names.append(name)
    if not ops:
        raise ValueError(f"{where}: no instructions")
    return VMProgram(tuple(ops), tuple(names), where)


def _number(word: str):
    try:
        return float(word)
    except ValueError:
        return None
