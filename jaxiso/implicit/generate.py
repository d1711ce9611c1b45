"""Seeded CSG programs for tests and benchmarks: unions and differences of boxes, spheres,
capsules and tori, as `VMProgram`s (so one object is both a plain-JAX ``f(x, y, z)`` for
the straight path and a program the tape path reads directly).

Each primitive is a signed distance bound (exact for spheres, capsules and tori; the box
uses ``max(|x - c| - h)``, exact inside); the model is ``f_0``, then ``min(f, f_i)``
(union) or ``max(f, -f_i)`` (difference) in turn: a chain as deep as the model is long,
the case per-region pruning is for.
"""

from __future__ import annotations

import numpy as np

from .vm import VMProgram

__all__ = ["csg_program", "KINDS"]

KINDS = ("sphere", "box", "capsule", "torus")


class _Builder:
    def __init__(self):
        self.ops: list = []
        self.consts: dict = {}
        self.vars = [self.emit("var-x", (0,)), self.emit("var-y", (1,)),
                     self.emit("var-z", (2,))]

    def emit(self, op, args):
        self.ops.append((op, tuple(args)))
        return len(self.ops) - 1

    def const(self, v):
        v = float(np.float32(v))
        if v not in self.consts:
            self.consts[v] = self.emit("const", (v,))
        return self.consts[v]

    def sub_c(self, a, c):
        return self.emit("sub", (a, self.const(c)))

    def add(self, a, b):
        return self.emit("add", (a, b))

    def length(self, parts):
        acc = self.emit("square", (parts[0],))
        for p in parts[1:]:
            acc = self.add(acc, self.emit("square", (p,)))
        return self.emit("sqrt", (acc,))

    def sphere(self, c, r):
        d = [self.sub_c(v, ci) for v, ci in zip(self.vars, c)]
        return self.sub_c(self.length(d), r)

    def box(self, c, h):
        d = [self.sub_c(self.emit("abs", (self.sub_c(v, ci),)), hi)
             for v, ci, hi in zip(self.vars, c, h)]
        return self.emit("max", (self.emit("max", (d[0], d[1])), d[2]))

    def capsule(self, a, b, r):
        ab = np.asarray(b, np.float64) - np.asarray(a, np.float64)
        inv = 1.0 / float(ab @ ab)
        pa = [self.sub_c(v, ai) for v, ai in zip(self.vars, a)]
        dot = None
        for p, k in zip(pa, ab):
            term = self.emit("mul", (p, self.const(k * inv)))
            dot = term if dot is None else self.add(dot, term)
        h = self.emit("max", (self.emit("min", (dot, self.const(1.0))), self.const(0.0)))
        d = [self.emit("sub", (p, self.emit("mul", (h, self.const(k))))) for p, k in zip(pa, ab)]
        return self.sub_c(self.length(d), r)

    def torus(self, c, big, small, axis):
        d = [self.sub_c(v, ci) for v, ci in zip(self.vars, c)]
        ring = [d[i] for i in range(3) if i != axis]
        q = self.sub_c(self.length(ring), big)
        return self.sub_c(self.length([q, d[axis]]), small)


def csg_program(n: int, seed: int = 0, extent: float = 1.0, difference: float = 0.25,
                kinds=KINDS) -> VMProgram:
    """A random CSG model of `n` primitives inside [-extent, extent]^3.

    Args:
      n: number of primitives (each 8..25 instructions; 400 give about 7,000).
      seed: numpy seed (same seed, same program).
      extent: half-size of the cube the primitives' centres lie in (their sizes scale
        with it; the model stays within about 1.3 * extent).
      difference: probability that a primitive is subtracted instead of added (never
        the first).
      kinds: primitive kinds to draw from (`KINDS`).
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    rng = np.random.default_rng(seed)
    bld = _Builder()
    size = extent * min(0.35, 1.2 / n ** (1 / 3))
    f = None
    for _ in range(n):
        kind = kinds[rng.integers(len(kinds))]
        c = rng.uniform(-extent, extent, 3) * 0.85
        if kind == "sphere":
            g = bld.sphere(c, size * rng.uniform(0.4, 1.0))
        elif kind == "box":
            g = bld.box(c, size * rng.uniform(0.3, 0.9, 3))
        elif kind == "capsule":
            a = c + rng.normal(size=3) * size
            g = bld.capsule(c, a, size * rng.uniform(0.15, 0.35))
        else:
            big = size * rng.uniform(0.5, 0.9)
            g = bld.torus(c, big, big * rng.uniform(0.2, 0.4), int(rng.integers(3)))
        if f is None:
            f = g
        elif rng.uniform() < difference:
            f = bld.emit("max", (f, bld.emit("neg", (g,))))
        else:
            f = bld.emit("min", (f, g))
    names = tuple(f"_{i:x}" for i in range(len(bld.ops)))
    return VMProgram(tuple(bld.ops), names, f"csg_program({n}, seed={seed})")
