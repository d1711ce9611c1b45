"""Large implicit programs: tapes, breadth-first ray casting with per-region pruning.

Programs of thousands of operations (CSG of hundreds of primitives, Prospero) cannot be
inlined into XLA: compile time and memory grow with their length. Here a program is an
instruction tape (`jaxiso.arith._tape.Tape`, data) run by one compiled evaluator, and rays
are cast the way MPR / fidget render such programs:

1. The screen is cut into tiles, each tile's depth range into slabs; every region (tile x
   slab: a frustum piece, whose bounding box is the hull of its 8 corners) is classified
   with the tape in interval arithmetic: empty (f > 0), full (f < 0) or ambiguous.
2. Ambiguous regions are compacted (bucketed sizes) and split (tiles g x g, slabs h); each
   child runs the tape of its parent, which was pruned with the parent's own intervals:
   min/max whose operand intervals decide the choice become that operand and everything
   that no longer reaches the output is dropped. Full regions set a per-tile front; regions
   wholly behind it are dropped.
3. Rays of the last ambiguous tiles are sampled at points along their slab (the last
   tape), the first sign change is refined, and each pixel keeps its nearest hit.

The solid is ``f < 0`` clipped to the box [lo, hi]: a ray that enters the box inside the
solid hits at the box (so a 2D program such as Prospero, viewed along z, shows its
inside). `cast` is the entry point; `tape_of` turns a `VMProgram` or a plain-JAX
``f(x, y, z[, w])`` into a tape.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..arith import _tape
from ..arith._affine_type import Affine
from ..arith._interval import Interval
from ..arith._tape import Tape
from ._field import as_field, clip_to_box
from ._memo import BoundedCache
from .vm import VMProgram

__all__ = ["tape_of", "Schedule", "ProgramHits", "cast", "default_schedule",
           "evaluate_points", "evaluate_intervals", "TAPE_CROSSOVER", "prefers_tape"]

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


# ------------------------------------------------------------------------ schedules


@dataclasses.dataclass(frozen=True)
class Schedule:
    """How `cast` subdivides.

    Attributes:
      root_tile: pixels per side of the root tiles (a power of two).
      root_slabs: depth slabs per root tile.
      splits: per level (g, h): every ambiguous tile splits into g x g tiles and its slab
        into h slabs (the product of the g is root_tile / final tile).
      samples: point samples per ray and slab in the final stage (1: the slab's entry
        point only, for programs constant along the rays).
      rounds: refinement rounds of the first sign change (each divides the bracket by
        samples - 1).
    """

    root_tile: int = 16
    root_slabs: int = 16
    splits: tuple = ((2, 2), (2, 2), (2, 2))
    samples: int = 8
    rounds: int = 2

    @property
    def final_tile(self) -> int:
        t = self.root_tile
        for g, _ in self.splits:
            t //= g
        return t


def default_schedule(extruded: bool, size: int) -> Schedule:
    """A schedule for an image of `size` pixels a side: 2D (extruded along the rays:
    MPR's 64 -> 8 -> pixels) or 3D (16-pixel tiles x 16 slabs, three 2x2x2 splits,
    8 samples per ray in 2 x 2-pixel tiles)."""
    if extruded:
        root = 64 if size >= 512 else 32
        return Schedule(root_tile=root, root_slabs=1, splits=((root // 8, 1),), samples=1,
                        rounds=0)
    return Schedule()


# --------------------------------------------------------------------------- casting


@dataclasses.dataclass
class ProgramHits:
    """First hits of a camera's rays on the solid f < 0 clipped to the box.

    Attributes:
      t: [H, W] ray parameter (unit directions), inf where no hit.
      hit: [H, W] bool.
      stats: per-level work and tape lengths, timings (seconds, host clock after
        `block_until_ready`), the schedule.
    """

    t: jax.Array
    hit: jax.Array
    stats: dict


def _camera_frame(cam):
    """(eye, forward, right * scale * aspect, up * scale) as one [4, 3] array."""
    aspect = cam.width / cam.height
    return jnp.stack([cam.eye, cam.forward, cam.right * (cam.scale * aspect),
                      cam.up * cam.scale]).astype(jnp.float32)


def _uv(i, j, H, W):
    return ((j.astype(jnp.float32) + 0.5) / W * 2.0 - 1.0,
            1.0 - (i.astype(jnp.float32) + 0.5) / H * 2.0)


def _origin_dir(frame, u, v, ortho):
    """Ray origin and (forward-normalised) direction at screen coordinates (u, v)."""
    eye, fwd, ru, uv = frame[0], frame[1], frame[2], frame[3]
    off = u[..., None] * ru + v[..., None] * uv
    if ortho:
        return eye + off, jnp.broadcast_to(fwd, off.shape)
    return jnp.broadcast_to(eye, off.shape), fwd + off


@functools.partial(jax.jit, static_argnames=("H", "W", "Hp", "Wp", "ortho"))
def _pixels(frame, lo, hi, H, W, Hp, Wp, ortho):
    """Per padded pixel: s0, s1 of the box (in forward-distance units), inside, |D|."""
    i, j = jnp.meshgrid(jnp.arange(Hp), jnp.arange(Wp), indexing="ij")
    u, v = _uv(i, j, H, W)
    o, D = _origin_dir(frame, u, v, ortho)
    s0, s1, inside = clip_to_box(o.reshape(-1, 3), D.reshape(-1, 3), lo, hi, 0.0, jnp.inf)
    inside = inside.reshape(Hp, Wp) & (i < H) & (j < W)
    return (jnp.where(inside, s0.reshape(Hp, Wp), jnp.inf),
            jnp.where(inside, s1.reshape(Hp, Wp), -jnp.inf), inside,
            jnp.linalg.norm(D, axis=-1))


def _tile_ranges(s0, s1, T):
    Hp, Wp = s0.shape
    return (s0.reshape(Hp // T, T, Wp // T, T).min(axis=(1, 3)),
            s1.reshape(Hp // T, T, Wp // T, T).max(axis=(1, 3)))


_PAD = 4.0 * 2.0**-24


def _region_boxes(frame, lo, hi, ty, tx, T, s0, s1, H, W, ortho):
    """Interval coordinates of the regions' bounding boxes (clipped to [lo, hi]) and
    whether they are non-empty. The frustum piece is multilinear in (u, v, s), so its
    extremes are at the 8 corners."""
    i0 = jnp.minimum(ty * T, H - 1)
    i1 = jnp.minimum(ty * T + T - 1, H - 1)
    j0 = jnp.minimum(tx * T, W - 1)
    j1 = jnp.minimum(tx * T + T - 1, W - 1)
    pts = []
    for ii in (i0, i1):
        for jj in (j0, j1):
            u, v = _uv(ii, jj, H, W)
            o, D = _origin_dir(frame, u, v, ortho)
            for s in (s0, s1):
                pts.append(o + s[..., None] * D)
    pts = jnp.stack(pts)
    blo, bhi = pts.min(axis=0), pts.max(axis=0)
    pad = _PAD * jnp.maximum(jnp.abs(blo), jnp.abs(bhi))
    blo = jnp.maximum(blo - pad, lo)
    bhi = jnp.minimum(bhi + pad, hi)
    ok = jnp.all(blo <= bhi, axis=-1)
    return [Interval(blo[..., k], bhi[..., k]) for k in range(3)], ok


def _lead(c):
    """A coordinate's value array (points), lower bounds or centres."""
    return c.lo if isinstance(c, Interval) else c.center if isinstance(c, Affine) else c


def chunked_eval(tapes, coords, record, budget, min_chunks=1):
    """`_tape.evaluate` over region chunks so that its working set (the register file,
    and the choices of `record`) stays within `budget` elements (R is a power of two), in
    at least `min_chunks` chunks (each runs as many instructions as its longest tape:
    regions sorted by tape length gain)."""
    L, R = tapes.op.shape
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
        return _tape.evaluate(tapes, coords, record)

    def split_coord(x):
        x = jnp.broadcast_to(x, (R, 1)) if jnp.ndim(x) == 0 else x
        x = jnp.broadcast_to(x, (R,) + jnp.shape(x)[1:])
        return x.reshape((chunks, R // chunks) + x.shape[1:])

    def split_prog(x):  # [L, ..., R] -> [chunks, L, ..., R / chunks]
        return jnp.moveaxis(x.reshape(x.shape[:-1] + (chunks, R // chunks)), -2, 0)

    ct = _tape.map_program(tapes, split_prog, tapes.n.reshape(chunks, R // chunks))
    cc = jax.tree_util.tree_map(split_coord, coords)

    def one(args):
        t, c = args
        return _tape.evaluate(t, c, record)

    out = jax.lax.map(one, (ct, cc))
    if record:
        val, ch = out
        ch = jnp.moveaxis(ch, 0, 1).reshape((L, R) + ch.shape[3:])
        return jax.tree_util.tree_map(lambda x: x.reshape((R,) + x.shape[2:]), val), ch
    return jax.tree_util.tree_map(lambda x: x.reshape((R,) + x.shape[2:]), out)


@functools.partial(jax.jit, static_argnames=("gy", "gx", "h", "Tc", "H", "W", "ortho",
                                             "budget"))
def _level(tapes, reg, smap, front, frame, lo, hi, w, gy, gx, h, Tc, H, W, ortho, budget):
    """Split every parent region (R) into P = gy gx h children, classify them with the
    parents' tapes, update the front, cull, and mark the ambiguous children."""
    iy, ix, k = (a.reshape(-1) for a in jnp.meshgrid(jnp.arange(gy), jnp.arange(gx),
                                                   jnp.arange(h), indexing="ij"))
    ty = reg["ty"][:, None] * gy + iy[None]
    tx = reg["tx"][:, None] * gx + ix[None]
    s0p, s1p = reg["s0"][:, None], reg["s1"][:, None]
    ds = (s1p - s0p) / h
    s0 = s0p + ds * k[None]
    s1 = jnp.where(k[None] == h - 1, s1p, s0p + ds * (k[None] + 1))
    Hc, Wc = smap[0].shape
    in_img = (ty < Hc) & (tx < Wc)
    tyc, txc = jnp.minimum(ty, Hc - 1), jnp.minimum(tx, Wc - 1)
    s0 = jnp.maximum(s0, smap[0][tyc, txc])
    s1 = jnp.minimum(s1, smap[1][tyc, txc])
    valid = reg["valid"][:, None] & in_img & (s0 <= s1)
    boxes, ok = _region_boxes(frame, lo, hi, ty, tx, Tc, s0, s1, H, W, ortho)
    valid = valid & ok
    wi = Interval(w, w)
    f, chosen = chunked_eval(tapes, boxes + [wi], True, budget)
    full = valid & (f.hi < 0)
    amb = valid & ~(f.lo > 0) & ~full
    inf = jnp.float32(jnp.inf)
    fs0 = front[0].at[tyc, txc].min(jnp.where(full, s0, inf))
    fs1 = front[1].at[tyc, txc].min(jnp.where(full, s1, inf))
    amb = amb & ~(s0 > fs1[tyc, txc])
    children = dict(ty=ty, tx=tx, s0=s0, s1=s1)
    counts = jnp.stack([jnp.sum(valid), jnp.sum(full), jnp.sum(amb)])
    return children, amb, chosen, (fs0, fs1), counts


def ambiguous_positions(amb, size):
    """Flat positions of the ambiguous children of amb [R, C] (the first `size`, padded
    with 0), int32 [size]. On the host: a jitted `nonzero` compiled once per level shape
    (11 compiles, 3.9 s of the slab's first call at 256^2) for a few kB of work."""
    flat = np.flatnonzero(np.asarray(amb).reshape(-1))[:size]
    return jnp.asarray(np.pad(flat, (0, size - flat.size)).astype(np.int32))


@functools.partial(jax.jit, static_argnames=("length",))
def _resized(tapes, length):
    return _tape.resize(tapes, length)


def _shortest_bucket(tapes):
    """`tapes` cut to the bucketed length of their longest (concrete n), in one compiled
    call (eager slicing compiled each array's slice apart)."""
    return _resized(tapes, _tape.longest_bucket(tapes))


@functools.partial(jax.jit, static_argnames=("size", "registers", "h"))
def gather_children(tapes, children, chosen, where, start, count, size, registers=True,
                    origin=None, h=1):
    """Children where[start:start + size] (those past `count` invalid): their regions,
    their parents' tapes and their own min/max choices ([L, size]). `registers=False`
    leaves the tapes' registers behind (for tapes about to be pruned, which allocates
    them anew: 3 of the 7 arrays a gather would move). With `origin` ([L', groups]),
    `tapes` are the children's groups' ([L', groups]: a group is h consecutive children
    of a parent, its tape pruned by their shared choices, `prune(..., origins=True)`)
    and the choices are read at each group instruction's origin ([L', size])."""
    if not registers:
        tapes = dataclasses.replace(tapes, reg=None)
    C = chosen.shape[2]
    k = start + jnp.arange(size)
    idx = where[jnp.minimum(k, where.shape[0] - 1)]
    ok = k < count
    r, c = idx // C, idx % C
    reg = {key: v.reshape(-1)[idx] for key, v in children.items()}
    reg["valid"] = ok
    if origin is None:
        parent, choices = _tape.take_regions(tapes, r), chosen[:, r, c]
    else:
        g = r * (C // h) + c // h
        parent, choices = _tape.take_regions(tapes, g), chosen[origin[:, g], r, c]
    parent = dataclasses.replace(parent, n=jnp.where(ok, parent.n, 1))
    return parent, choices, reg


# A separate call: fused with the gathers above, XLA laid the tapes out so that the
# pruning loops' row reads were strided (measured 4x slower).
_prune = jax.jit(_tape.prune)


@functools.partial(jax.jit, static_argnames=("T", "M", "rounds", "H", "W", "ortho",
                                             "budget"))
def _final(tapes, reg, pix, frame, w, T, M, rounds, H, W, ortho, budget):
    """Sample every ray of the last tiles along its slab, refine the first point inside
    (f < 0); return (pixel index, hit s) per ray sample set."""
    s0r, s1r, inside, dlen = pix
    Hp, Wp = s0r.shape
    py, px = (a.reshape(-1) for a in jnp.meshgrid(jnp.arange(T), jnp.arange(T),
                                                  indexing="ij"))
    i = reg["ty"][:, None] * T + py[None]
    j = reg["tx"][:, None] * T + px[None]
    ic, jc = jnp.minimum(i, Hp - 1), jnp.minimum(j, Wp - 1)
    a = jnp.maximum(reg["s0"][:, None], s0r[ic, jc])
    b = jnp.minimum(reg["s1"][:, None], s1r[ic, jc])
    ok = reg["valid"][:, None] & (i < H) & (j < W) & inside[ic, jc] & (a <= b)
    u, v = _uv(ic, jc, H, W)
    o, D = _origin_dir(frame, u, v, ortho)  # [R, T*T, 3]
    R, Q = ok.shape

    def values(s):  # s [R, Q, M'] -> f [R, Q, M']
        m = s.shape[-1]
        p = o[:, :, None, :] + s[..., None] * D[:, :, None, :]
        coords = [p[..., c].reshape(R, Q * m) for c in range(3)] + [w]
        return chunked_eval(tapes, coords, False, budget).reshape(R, Q, m)

    if M == 1:
        f = values(a[..., None])[..., 0]
        hit = ok & (f < 0)
        s_hit = a
    else:
        frac = jnp.arange(M, dtype=jnp.float32) / (M - 1)
        s = a[..., None] + (b - a)[..., None] * frac
        neg = values(s) < 0
        hit = ok & jnp.any(neg, axis=-1)
        first = jnp.argmax(neg, axis=-1)
        top = jnp.take_along_axis(s, first[..., None], axis=-1)[..., 0]
        bot = jnp.take_along_axis(s, jnp.maximum(first - 1, 0)[..., None], axis=-1)[..., 0]
        entered = first == 0  # inside at the slab's start
        frac = (jnp.arange(M, dtype=jnp.float32) + 1.0) / M
        for _ in range(rounds):
            s = bot[..., None] + (top - bot)[..., None] * frac
            neg = values(s) < 0
            any_neg = jnp.any(neg, axis=-1)
            first = jnp.argmax(neg, axis=-1)
            ntop = jnp.take_along_axis(s, first[..., None], axis=-1)[..., 0]
            nbot = jnp.where(first == 0, bot, jnp.take_along_axis(
                s, jnp.maximum(first - 1, 0)[..., None], axis=-1)[..., 0])
            upd = any_neg & ~entered
            top, bot = jnp.where(upd, ntop, top), jnp.where(upd, nbot, bot)
        s_hit = jnp.where(entered, a, 0.5 * (bot + top))
    t = jnp.where(hit, s_hit * dlen[ic, jc], jnp.inf)
    img = jnp.full(Hp * Wp, jnp.inf, jnp.float32)
    img = img.at[jnp.where(hit, ic * Wp + jc, Hp * Wp)].min(t, mode="drop")
    return img.reshape(Hp, Wp), jnp.sum(ok)


@functools.partial(jax.jit, static_argnames=("T",))
def _front_hits(front, pix, T):
    s0r, s1r, inside, dlen = pix
    fs0 = jnp.repeat(jnp.repeat(front[0], T, axis=0), T, axis=1)
    c = jnp.maximum(fs0, s0r)
    ok = inside & (c <= s1r)
    return jnp.where(ok, c * dlen, jnp.inf)


def histogram(n):
    """Counts of tape lengths `n` by power-of-two bins (a level's report)."""
    n = np.asarray(n)
    if n.size == 0:
        return {}
    edges = [0, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384]
    h, _ = np.histogram(n, bins=edges)
    return {f"{lo}-{hi - 1}": int(c) for lo, hi, c in zip(edges[:-1], edges[1:], h) if c}


def _block(x):
    return jax.block_until_ready(x)


def cast(f, lo, hi, camera, w=0.0, schedule: Schedule | None = None, prune: bool = True,
         budget: int = 2**25) -> ProgramHits:
    """First hits of `camera`'s rays on the solid ``f < 0`` inside the box [lo, hi].

    Args:
      f: a `VMProgram`, a plain-JAX ``f(x, y, z[, w])`` or a `Tape` (`tape_of`).
      lo, hi: 3-vectors, the box.
      camera: a `jaxiso.Camera` (perspective or orthographic).
      w: the 4th coordinate.
      schedule: subdivision (`default_schedule` for the camera and program: a program
        that does not read the coordinate an axis-aligned orthographic camera looks
        along is cast as 2D).
      prune: shorten tapes per region (False: every region runs the full tape).
      budget: register-file elements per evaluation chunk (memory: 9 bytes each).

    Returns `ProgramHits`. The driver runs on the host: each level is one jitted call
    with bucketed shapes (regions and tape lengths rounded up to powers of two).
    """
    clock = time.perf_counter()
    tape = tape_of(f)
    lo = jnp.asarray(lo, jnp.float32)
    hi = jnp.asarray(hi, jnp.float32)
    w = jnp.float32(w)
    H, W, ortho = camera.height, camera.width, bool(camera.orthographic)
    frame = _camera_frame(camera)
    if schedule is None:
        schedule = _schedule_for(camera, tape)
    levels = _level_tiles(schedule, H, W)
    ny, nx, _, T0 = levels[0]
    Tf = schedule.final_tile
    pix = _pixels(frame, lo, hi, H, W, ny * T0, nx * T0, ortho)
    view = _View(frame, lo, hi, w, H, W, ortho, pix, budget, prune)
    stats = dict(schedule=dataclasses.asdict(schedule), tape_length=int(tape.n),
                 levels=[])
    tapes, reg = _root_region(tape, pix)
    front = None
    for gy, gx, h, Tc in levels:
        tapes, reg, front, row = _cast_level(view, tapes, reg, front, gy, gx, h, Tc)
        stats["levels"].append(row)
    t_final = time.perf_counter()
    img, n_rays = _final(tapes, reg, pix, frame, w, Tf, schedule.samples, schedule.rounds,
                         H, W, ortho, budget)
    t_front = _front_hits(front, pix, Tf)
    t = jnp.minimum(img, t_front)[:H, :W]
    t = _block(t)
    stats["final"] = dict(rays=int(n_rays), seconds=time.perf_counter() - t_final)
    stats["seconds"] = time.perf_counter() - clock
    return ProgramHits(t=t, hit=jnp.isfinite(t), stats=stats)


class _View(NamedTuple):
    """What every level of one `cast` shares: the camera frame [4, 3], the box lo, hi
    [3], w, the image's size and projection, the padded pixels' ranges (`_pixels`) and
    the options."""

    frame: jax.Array
    lo: jax.Array
    hi: jax.Array
    w: jax.Array
    H: int
    W: int
    ortho: bool
    pix: tuple
    budget: int
    prune: bool


def _schedule_for(camera, tape: Tape) -> Schedule:
    """`default_schedule` for the camera and program: 2D when an axis-aligned
    orthographic camera looks along a coordinate the program does not read."""
    fwd = np.abs(np.asarray(camera.forward))
    axis = int(np.argmax(fwd))
    extruded = bool(camera.orthographic) and fwd[axis] > 1 - 1e-6 and not tape.uses(axis)
    return default_schedule(extruded, max(camera.height, camera.width))


def _level_tiles(schedule: Schedule, H: int, W: int) -> list:
    """Per level (gy, gx, h, tile): each region splits into gy x gx tiles of `tile`
    pixels a side and h slabs (the root: the image's ny x nx root tiles)."""
    T0 = schedule.root_tile
    Tf = schedule.final_tile
    if Tf < 1 or T0 % max(Tf, 1):
        raise ValueError(f"schedule splits {schedule.splits} do not divide the root tile "
                         f"{T0}")
    levels = [(-(-H // T0), -(-W // T0), schedule.root_slabs, T0)]
    T = T0
    for g, h in schedule.splits:
        T //= g
        levels.append((g, g, h, T))
    return levels


def _root_region(tape: Tape, pix):
    """The root: one region (the whole image, all depths) with the full tape; (tapes,
    region) with [1] arrays."""
    s_lo = jnp.min(pix[0])
    s_hi = jnp.max(pix[1])
    reg = dict(ty=jnp.zeros(1, jnp.int32), tx=jnp.zeros(1, jnp.int32),
               s0=s_lo[None], s1=s_hi[None], valid=jnp.isfinite(s_hi - s_lo)[None])
    return _tape.take_regions(tape, jnp.zeros(1, jnp.int32)), reg


def _cast_level(view: _View, tapes, reg, front, gy, gx, h, Tc):
    """One level of `cast`: split the regions (gy x gx tiles of Tc pixels, h slabs),
    classify, keep the ambiguous children with their tapes (pruned by their own choices
    when `view.prune`). Returns (tapes, regions, front, the level's stats row)."""
    t_level = time.perf_counter()
    smap = _tile_ranges(view.pix[0], view.pix[1], Tc)
    front = _front_at(front, smap, gy, gx)
    children, amb, chosen, front, counts = _level(
        tapes, reg, smap, front, view.frame, view.lo, view.hi, view.w, gy, gx, h, Tc,
        view.H, view.W, view.ortho, view.budget)
    n_valid, n_full, n_amb = (int(c) for c in np.asarray(counts))
    t_eval = time.perf_counter() - t_level
    size = _tape.bucket(max(n_amb, 1), 8, fine=True)
    tapes, choices, reg = gather_children(tapes, children, chosen,
                                          ambiguous_positions(amb, size), 0, n_amb, size,
                                          not view.prune)
    if view.prune:
        tapes = _shortest_bucket(_prune(tapes, choices))
    n_kept = np.asarray(tapes.n)[:n_amb]
    _block(tapes.op)
    row = dict(
        tile=Tc, regions=n_valid, full=n_full, ambiguous=n_amb, region_bucket=size,
        tape_bucket=tapes.length, tape_mean=float(n_kept.mean()) if n_amb else 0.0,
        tape_max=int(n_kept.max()) if n_amb else 0, tape_hist=histogram(n_kept),
        seconds=time.perf_counter() - t_level, eval_seconds=t_eval)
    return tapes, reg, front, row


def _front_at(front, smap, gy, gx):
    """The per-tile front (fs0, fs1) at a level's tiles (smap: their ranges): none yet
    (inf) at the root, else each parent tile's repeated over its gy x gx children."""
    if front is None:
        return (jnp.full(smap[0].shape, jnp.inf), jnp.full(smap[0].shape, jnp.inf))
    return tuple(jnp.repeat(jnp.repeat(x, gy, axis=0), gx, axis=1) for x in front)
