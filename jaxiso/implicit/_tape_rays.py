"""Level sets of long programs on the tape path: any batch of rays, breadth-first.

`ImplicitSurface` scenes whose program is long (`program.TAPE_CROSSOVER` instructions or
more) run here instead of inlining f's interval extension into XLA (whose compile time and
memory grow with the program). Same answer as t-bisection, found breadth-first:

* A region is a group of consecutive rays (a power of 4 of them) and a slab [s0, s1] of
  each ray's own segment in the box (p + s D, s in [0, 1]). Its box blends the hulls of
  the group's entry points p and exit points p + D at the slab's ends (a ray's point at s
  is (1 - s) p + s (p + D)), padded outward.
* Level by level every surviving region splits into 4 ray groups x 2 slabs (the root,
  one region over all rays, into `root_group(n)`-ray groups x `ROOT_SLABS` slabs), down to
  single rays, then quarters its slab until a piece is at most eps long: the pieces
  t-bisection ends on (dyadic fractions of the segment, Eq. 6.19). Each child is
  classified with its parent's tape in the scene's arithmetic (interval, or affine: one
  noise symbol per axis of a group's box, a single ray's piece exactly on one symbol, its
  parameter); a child whose enclosure holds no isovalue is dropped, the others are
  compacted (bucketed sizes) and get their parent's tape pruned by their own min/max
  choices; once tapes are short (`PRUNE_ABOVE`) children read their parent's tape in
  place (a batch's tapes are a store, each region holds its tape's index, "tid").
* The final pieces are verified like the straight path's (`ImplicitSurface.verify`:
  a sign change of f - iso between the piece's ends, or the first-order distance at its
  midpoint), and each ray keeps its nearest; value and gradient (normal) come from the
  piece's pruned tape at the piece's midpoint (forward-mode through the evaluator).

The driver runs on the host (each level is a jitted call on bucketed shapes), so it needs
concrete inputs: under jit / vmap the scene calls it through `jax.pure_callback`
(`ImplicitSurface.intersect_tape`).
Rays that share a group should be near each other (`render` orders them in Z-order tiles).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import functools
import math
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import DEFAULT_MEMORY_BUDGET, Hits, Rays, unit_or_facing
from ..arith import Affine, Interval, Tape, aa
from ..arith import tape as _tape
from ._bisect import depth_for, piece_width
from ._field import (
    CLOSER_PARTS,
    box_arithmetic,
    changes_sign,
    ray_boxes,
    ray_segments,
    touches,
)
from .program import ambiguous_positions, chunked_eval, gather_children, histogram

__all__ = ["intersect_rays", "ROOT_GROUP", "ROOT_SLABS", "ROOT_GROUPS",
           "batch_limit", "root_group", "tape_tile"]

# The root is one region (all rays, the full tape); its children are groups of
# ROOT_GROUP rays (a 16 x 16 tile in Z-order) x ROOT_SLABS slabs, as MPR's / cast's root
# tiles. With 1024-ray x 4-slab roots, each evaluated with the full tape, CSG-400 at
# 256^2 kept 214 of 252 roots and pruned them only from 8,605 to ~7,000 instructions.
ROOT_GROUP = 256
ROOT_SLABS = 16
# Larger images get larger root groups (ROOT_GROUP x a power of 4, a square of pixels),
# at most ROOT_GROUP_COUNT of them: the full tape is evaluated on groups x ROOT_SLABS
# regions and pruned per group, and for a long program those two steps dominate. Slab
# 1024^2 with 256-ray groups: 65,536 root children took 6.0 s of a 26.8 s call, their
# groups' pruning 5.0 s.
ROOT_GROUP_COUNT = 256
# Roots are groups of at most ROOT_GROUPS x root-group rays (16,384), so that a root's
# children stay a bounded batch however many rays there are.
ROOT_GROUPS = 64
# Tapes padded to at most this many instructions are no longer pruned: on short tapes a
# pruning pass costs more than the instructions it saves (CSG-60 at 96^2: 0.07 s per
# level pruning ~20-instruction tapes padded to 128, more than their evaluation saved).
PRUNE_ABOVE = 128
# Children of tapes at least this long are pruned in two stages (`_shared_prune`).
SHARED_PRUNE_FROM = 2048
_BUDGET = 2**25
# Regions are sorted by tape length and evaluated in this many chunks: the evaluator runs
# each chunk to its longest tape, so sorted chunks skip most of a long tail (pruned tapes
# of one level: mean 34, max 209 instructions on CSG-60).
_CHUNKS = 8    # register-file elements per evaluation chunk (~300 MB)
_PAD = 4.0 * 2.0**-24


@jax.jit
def _segments(rays, lo, hi, t_min, t_max, eps):
    t0, t1, inside, p, D = ray_segments(rays, lo, hi, t_min, t_max)
    fine = piece_width(depth_for(jnp.linalg.norm(D, axis=-1), eps))  # s-length of a piece
    return t0, t1, inside, p, D, fine


def _any_level(r: Interval, iso):
    return jnp.any((r.lo[..., None] <= iso) & (iso <= r.hi[..., None]), axis=-1)


def _undo_idle_splits(s1, amb, chosen, q, h):
    """Where all h depth slabs of a ray group hold a level, the depth split decided
    nothing: the group goes on as one child (the first, stretched over the parent's
    slab) instead of h, its tape pruned only by the min/max choices all h slabs share
    (each proved on its slab, so together on their union). Without this, a field that
    barely varies along the rays (Prospero as a 3D slab seen down z) multiplies its
    regions by h at every level: 368,560 regions at one level of 128^2 to keep 2,055.
    s1, amb [R, q h]; chosen [L, R, q h]."""
    R = amb.shape[0]
    idle = jnp.all(amb.reshape(R, q, h), axis=-1, keepdims=True)          # [R, q, 1]
    k = jnp.arange(h)
    if chosen is not None:  # None: the children will not be pruned
        L = chosen.shape[0]
        c = chosen.reshape(L, R, q, h)
        shared = jnp.where(jnp.all(c == c[..., :1], axis=-1, keepdims=True), c[..., :1], 0)
        chosen = jnp.where(idle[None] & (k == 0), shared.astype(c.dtype),
                           c).reshape(chosen.shape)
    stretched = jnp.broadcast_to(s1.reshape(R, q, h)[..., -1:], (R, q, h))
    s1 = jnp.where(idle & (k == 0), stretched, s1.reshape(R, q, h)).reshape(R, q * h)
    amb = (amb.reshape(R, q, h) & ~(idle & (k > 0))).reshape(R, q * h)
    return s1, amb, chosen


@functools.partial(jax.jit, static_argnames=("G", "q", "h", "arithmetic", "record"))
def _level(tapes, reg, seg, hull, lo, hi, rest, iso, first, G, q, h, arithmetic, record):
    """Split every region (R: groups of G rays, region r running tape reg["tid"][r] of
    the store `tapes`) into q ray groups x h slabs, classify the children with the
    parents' tapes in `arithmetic` ("interval": their boxes; "affine": one noise symbol
    per axis of a group's box, a single ray's piece on one symbol, its parameter); return
    children, which hold a level, their choices (`record`: for pruning, else None),
    counts, and `first` ([rays]: the end of each ray's nearest piece proven to hold a
    root, over every batch so far) updated. hull: `_group_hulls` of the children's
    groups (G / q rays each)."""
    _, _, inside, p, D, fine = seg
    Gc = G // q
    g, s0, s1, valid = _child_slabs(reg, fine, q, h, single=Gc == 1 and q == 1)
    blo, bhi, valid = _group_boxes(hull, g, s0, s1, lo, hi, valid)
    idx = pr = Dr = None
    if Gc == 1:  # single rays: their lines
        idx = g[..., None]                                     # [R, C, 1]
        pr, Dr = p[idx], D[idx]
    boxes = _child_coordinates(arithmetic, blo, bhi, pr, Dr, s0, s1, rest)
    tid = reg["tid"]
    f = chunked_eval(tapes, boxes, record, _BUDGET, _CHUNKS, tid, reg["valid"])
    f, chosen = f if record else (f, None)
    if arithmetic == "affine":
        f = aa.to_interval(f)
    amb = valid & _any_level(f, iso)
    if Gc == 1:
        amb, first = _behind_first_roots(tapes, tid, amb, first, idx, pr, Dr, s0, s1, rest,
                                         iso)
    if Gc > 1 and h > 1:
        s1, amb, chosen = _undo_idle_splits(s1, amb, chosen, q, h)
    unfinished = amb & ((s1 - s0) > fine[g * Gc])
    children = dict(g=g, s0=s0, s1=s1, tid=jnp.broadcast_to(tid[:, None], g.shape))
    return children, amb, chosen, jnp.stack([jnp.sum(valid), jnp.sum(amb),
                                              jnp.sum(unfinished)]), first


def _child_slabs(reg, fine, q, h, single):
    """The children of regions reg ([R] each: ray group g, slab s0..s1, valid): ray groups
    g [R, C] (C = q h) and slabs s0, s1 [R, C], valid [R, C]. `single` (single rays):
    each piece splits into m = min(h, length / last piece) parts, so that every piece ends
    exactly as long as t-bisection's last one (both are powers of 2; a finished piece
    stays whole); fine [rays]: each ray's last piece length."""
    sub, k = (a.reshape(-1) for a in jnp.meshgrid(jnp.arange(q), jnp.arange(h),
                                                 indexing="ij"))
    g = reg["g"][:, None] * q + sub[None]                      # [R, C]
    s0p, s1p = reg["s0"][:, None], reg["s1"][:, None]
    ds = (s1p - s0p) / h
    s0 = s0p + ds * k[None]
    s1 = jnp.where(k[None] == h - 1, s1p, s0p + ds * (k[None] + 1))
    valid = jnp.broadcast_to(reg["valid"][:, None], g.shape)
    if single:
        m = jnp.clip((s1p - s0p) / fine[reg["g"]][:, None], 1, h)
        ds = (s1p - s0p) / m
        s0 = s0p + ds * k[None]
        s1 = jnp.where(k[None] == m - 1, s1p, s0p + ds * (k[None] + 1))
        valid = valid & (k[None] < m)
    return g, s0, s1, valid


@functools.partial(jax.jit, static_argnames=("largest",))
def _group_hulls(seg, largest):
    """For every group size 1, 4, ..., `largest` (a power of 4): per group of that many
    consecutive rays (those inside the box), the hulls of their segments' entry points p
    and exit points p + D (lo, hi [groups, 3] each) and whether any ray is inside (bool
    [groups]); {size: hulls}. One compiled call, each size from the next finer (the
    groups' hulls one by one compiled once per size: 7 programs at 1024^2)."""
    _, _, inside, p, D, _ = seg
    ok = inside[:, None]
    big = jnp.float32(jnp.inf)
    hulls = []
    for x in (p, p + D):
        hulls += [jnp.where(ok, x, big), jnp.where(ok, x, -big)]
    level = (*hulls, inside)
    by_size, size = {1: level}, 1
    while size < largest:
        size *= 4
        plo, phi, elo, ehi, any_inside = (x.reshape((-1, 4) + x.shape[1:]) for x in level)
        level = (plo.min(1), phi.max(1), elo.min(1), ehi.max(1), any_inside.any(1))
        by_size[size] = level
    return by_size


def _group_boxes(hull, g, s0, s1, lo, hi, valid):
    """The boxes blo, bhi [R, C, 3] of the children (ray groups g [R, C]) over their
    slabs s0..s1 [R, C], padded outward, clipped to [lo, hi]; valid [R, C] kept where a
    ray is inside and the box is not empty. On a slab a ray's point is (1 - s) p + s e
    (entry p, exit e), so the group's points lie between (1 - s) of its entries' hull and
    s of its exits' (`_group_hulls`), exact at the segments' ends and for parallel rays.
    Gathering each child's rays instead cost the slab's 1024^2 root 840 MB of
    temporaries (its 16 slabs share the rays of a group)."""
    plo, phi, elo, ehi, any_inside = (x[g] for x in hull)
    s0, s1 = s0[..., None], s1[..., None]
    blo = jnp.minimum((1 - s0) * plo + s0 * elo, (1 - s1) * plo + s1 * elo)
    bhi = jnp.maximum((1 - s0) * phi + s0 * ehi, (1 - s1) * phi + s1 * ehi)
    # the rounding of the blends and of e = p + D, relative to the ends' magnitude
    size = jnp.maximum(jnp.maximum(jnp.abs(plo), jnp.abs(phi)),
                       jnp.maximum(jnp.abs(elo), jnp.abs(ehi)))
    pad = 2 * _PAD * jnp.where(any_inside[..., None], size, 0.0)
    blo = jnp.maximum(blo - pad, lo)
    bhi = jnp.minimum(bhi + pad, hi)
    return blo, bhi, valid & any_inside & jnp.all(blo <= bhi, axis=-1)


def _child_coordinates(arithmetic, blo, bhi, pr, Dr, s0, s1, rest):
    """The children's coordinates ([R, C] each) in `arithmetic`: "interval": their boxes
    blo, bhi [R, C, 3]; "affine": a single ray's piece (Gc = 1, lines pr + s Dr
    [R, C, Gc, 3]) on one noise symbol, its parameter, else one symbol per axis of the
    group's box. `rest`: the coordinates after x, y, z, as constants."""
    if arithmetic == "interval":
        boxes = [Interval(blo[..., c], bhi[..., c]) for c in range(3)]
        return boxes + [Interval(v, v) for v in rest]
    if pr is not None:
        # one ray's piece is exactly affine in its one parameter: one noise symbol
        boxes = ray_boxes(pr[..., 0, :], Dr[..., 0, :], s0, s1, "affine")
        return boxes + [aa.as_affine(jnp.broadcast_to(v, s0.shape), 1) for v in rest]
    # a group's box: one noise symbol per axis
    mid, rad = 0.5 * (blo + bhi), 0.5 * (bhi - blo)
    err = _PAD * (jnp.abs(mid) + rad)  # rounding of mid and rad
    boxes = [Affine(mid[..., c], rad[..., c, None] * jnp.eye(3)[c], err[..., c])
             for c in range(3)]
    return boxes + [aa.as_affine(jnp.broadcast_to(v, s0.shape), 3) for v in rest]


def _behind_first_roots(tapes, tid, amb, first, idx, pr, Dr, s0, s1, rest, iso):
    """Single-ray pieces (rays idx [R, C, 1], lines pr + s Dr [R, C, 1, 3], slabs s0..s1
    [R, C], tapes tid [R] of the store `tapes`): a piece whose ends straddle a level holds
    a root, so the ray's pieces behind it cannot hold its first hit (t-bisection would
    never reach them). Returns amb without those pieces and first ([rays]: the end of
    each ray's nearest proven piece) updated."""
    ray = idx[..., 0]
    R, C = s0.shape
    # both ends in one evaluation ([R, 2 C] points): one evaluator loop, compiled once
    ends = pr[..., 0, None, :] + jnp.stack([s0, s1], -1)[..., None] * Dr[..., 0, None, :]
    ends = ends.reshape(R, 2 * C, 3)
    f = _point_eval(tapes, tid, ends[..., 0], ends[..., 1], ends[..., 2], rest,
                    active=jnp.any(amb, axis=1)).reshape(R, C, 2)  # others: unread
    fa, fb = f[..., 0], f[..., 1]
    proven = amb & jnp.any((fa[..., None] - iso) * (fb[..., None] - iso) <= 0, axis=-1)
    n_rays = first.shape[0]
    first = first.at[jnp.where(proven, ray, n_rays)].min(s1, mode="drop")
    return amb & (s0 < first[ray]), first


@jax.jit
def _prune_sorted(tapes, choices):
    """`_tape.prune` in `_CHUNKS` chunks of regions (sorted longest first: each chunk's
    passes run to its own longest tape), and the highest register the pruned tapes use."""
    pruned = _pruned_chunks(tapes, choices)
    return pruned, _tape.highest_register(pruned)


def _pruned_chunks(tapes, choices):
    L, R = tapes.op.shape
    c = _CHUNKS if R % _CHUNKS == 0 else 1
    if c == 1:
        return _tape.prune(tapes, choices)

    def split(x):  # [L, ..., R] -> [c, L, ..., R / c]
        return jnp.moveaxis(x.reshape(x.shape[:-1] + (c, R // c)), -2, 0)

    def merge(x):
        return jnp.moveaxis(x, 0, -2).reshape(x.shape[1:-1] + (R,))

    parts = _tape.map_program(tapes, split, tapes.n.reshape(c, R // c))
    out = jax.lax.map(lambda args: _tape.prune(*args), (parts, split(choices)))
    return _tape.map_program(out, merge, out.n.reshape(R))


@functools.partial(jax.jit, static_argnames=("length",))
def _longest_first(tapes, reg, length):
    """The regions sorted by their tapes' length, longest first (the store is not moved),
    the store's tapes cut (or padded) to `length` instructions; tapes that will not be
    pruned again held narrow (`_tape.narrowed`: 15 bytes an instruction instead of 28;
    the slab at 1024^2 held five such stores of 32,768 tapes at its peak)."""
    # padding regions last: chunks of them run no instruction (`chunked_eval`'s active)
    order = jnp.argsort(-jnp.where(reg["valid"], tapes.n[reg["tid"]], -1))
    store = _tape.resize(tapes, length)
    if length <= PRUNE_ABOVE:
        store = _tape.narrowed(store)
    return store, {k: v[order] for k, v in reg.items()}


def _point_eval(tapes, tid, x, y, z, rest, budget=_BUDGET, active=None):
    """The tapes tid [n] of the store at points ([n, m] each); `rest`: the coordinates
    after x, y, z (w, scalar params); `budget`: the evaluator's elements; `active`
    (None or bool [n]): the regions to evaluate."""
    return chunked_eval(tapes, [x, y, z, *rest], False, budget, _CHUNKS, tid, active)


def _piece_lines(seg, reg):
    """Each final piece's ray line: points p [n, 3] and directions D [n, 3] (s in [0, 1]
    spans the ray's segment)."""
    _, _, _, p, D, _ = seg
    return p[reg["g"]], D[reg["g"]]


def _values(tapes, tid, rest, q, budget=_BUDGET):
    """The tapes' (tid [n]) values [n, 1] at points q [n, 3]."""
    return _point_eval(tapes, tid, q[:, 0, None], q[:, 1, None], q[:, 2, None], rest,
                       budget)


def _value_grad(tapes, tid, rest, q):
    """The tapes' values [n] and gradients [n, 3] at points q [n, 3]: forward mode, the
    three tangents in one pass of the evaluator (`jax.vmap` over them: the value is
    computed once; three `jvp`s ran the program's loop three times)."""
    basis = jnp.broadcast_to(jnp.eye(3, dtype=q.dtype)[:, None, :], (3,) + q.shape)

    def along(t):
        # the evaluator's budget shared by the value and its three tangents
        return jax.jvp(lambda q: _values(tapes, tid, rest, q, _BUDGET // 4), (q,), (t,))

    v, d = jax.vmap(along, out_axes=(None, 0))(basis)
    return v[:, 0], jnp.moveaxis(d[..., 0], 0, -1)


def _midpoints(seg, reg):
    """Each final piece's midpoint [n, 3]."""
    pr, Dr = _piece_lines(seg, reg)
    return pr + (0.5 * (reg["s0"] + reg["s1"]))[:, None] * Dr


@functools.partial(jax.jit, static_argnames=("policy",))
def _final_checks(tapes, reg, seg, rest, iso, policy):
    """Every final piece's midpoint value fm [n] and gradient [n, 3], and ok [n]: a valid
    piece whose root is established by the sign test (every valid piece for policy
    "none")."""
    pr, Dr = _piece_lines(seg, reg)
    valid = reg["valid"]
    fm, grad = _value_grad(tapes, reg["tid"], rest, _midpoints(seg, reg))
    if policy == "none":
        return fm, grad, valid
    q = pr[:, None, :] + jnp.stack([reg["s0"], reg["s1"]], -1)[..., None] * Dr[:, None, :]
    ends = _point_eval(tapes, reg["tid"], q[..., 0], q[..., 1], q[..., 2], rest)  # [n, 2]
    return fm, grad, valid & changes_sign(ends[..., None] - iso)[:, 0]


@jax.jit
def _final_closer(tapes, reg, seg, rest, iso):
    """Where a final piece's ends show no sign change: a sign change between CLOSER_PARTS
    + 1 points spread over it ([n] bool), a feature thinner than the piece (as in
    `_field.root_check`). A call of its own, made only when some valid piece fails the
    sign test."""
    pr, Dr = _piece_lines(seg, reg)
    frac = jnp.arange(CLOSER_PARTS + 1, dtype=jnp.float32) / CLOSER_PARTS
    s = reg["s0"][:, None] + (reg["s1"] - reg["s0"])[:, None] * frac  # [n, m]
    q = pr[:, None, :] + Dr[:, None, :] * s[..., None]
    f = _point_eval(tapes, reg["tid"], q[..., 0], q[..., 1], q[..., 2], rest)  # [n, m]
    return reg["valid"] & jnp.any(changes_sign(f[..., None] - iso), axis=-1)


@jax.jit
def _final_touching(tapes, reg, seg, rest, iso, fm, grad):
    """The touching test of "sign+distance" on every final piece ([n] bool). A call of
    its own, made only when some valid piece fails the sign test: the Newton steps' foot
    points cost six more forward passes of the tapes."""
    _, Dr = _piece_lines(seg, reg)
    level = iso[jnp.argmin(jnp.abs(fm[:, None] - iso), axis=-1)]
    length = (reg["s1"] - reg["s0"]) * jnp.linalg.norm(Dr, axis=-1)
    return reg["valid"] & touches(lambda q: _value_grad(tapes, reg["tid"], rest, q),
                                  _midpoints(seg, reg), fm, grad, level, length)


@functools.partial(jax.jit, static_argnames=("n_rays",))
def _nearest(reg, ok, fm, grad, n_rays):
    """Each ray's nearest verified piece: (s, value, gradient) per ray [n_rays]."""
    g = reg["g"]
    sm = 0.5 * (reg["s0"] + reg["s1"])
    ray = jnp.where(ok, g, n_rays)
    best = jnp.full(n_rays, jnp.inf, jnp.float32).at[ray].min(sm, mode="drop")
    win = ok & (sm == best[jnp.minimum(g, n_rays - 1)])
    ray = jnp.where(win, g, n_rays)
    value = jnp.zeros(n_rays, jnp.float32).at[ray].set(fm, mode="drop")
    gradient = jnp.zeros((n_rays, 3), jnp.float32).at[ray].set(grad, mode="drop")
    return best, value, gradient


def _final(tapes, reg, seg, rest, iso, policy, n_rays, found):
    """Verify a batch's valid final pieces (host-side driver) in chunks of `FINAL_CHUNK`,
    each on its own tapes cut to one length (so that the checks compile once, whatever
    the batches' sizes: the slab at 1024^2 compiled them for 4 shapes, 3.8 s, and the
    touching and closer checks for 2 each); `found` (best s, value, gradient per ray)
    updated with each ray's nearest verified piece."""
    valid = np.flatnonzero(np.asarray(reg["valid"]))
    if valid.size == 0:
        return found
    longest = int(np.max(np.asarray(tapes.n)[np.asarray(reg["tid"])[valid]]))
    length = max(FINAL_LENGTH, _tape.bucket(longest))
    size = min(FINAL_CHUNK, _tape.bucket(valid.size, _RECHECK_MIN))  # small images: less
    for start in range(0, valid.size, size):
        part = valid[start:start + size]
        idx = np.pad(part, (0, size - part.size), mode="edge").astype(np.int32)
        sub, sub_reg, _ = _pieces_at(tapes, reg, (), jnp.asarray(idx), length)
        sub_reg["valid"] = jnp.asarray(np.arange(size) < part.size)
        fm, grad, ok = _final_checks(sub, sub_reg, seg, rest, iso, policy)
        if policy != "none":
            ok = _recheck(_final_closer, ok, sub, sub_reg, seg, rest, iso)
        if policy == "sign+distance":
            ok = _recheck(_final_touching, ok, sub, sub_reg, seg, rest, iso, fm, grad)
        found = _merge(*found, _nearest(sub_reg, ok, fm, grad, n_rays), n_rays)
    return found


# Final pieces are verified in chunks of this many (fewer: a power of two), on tapes of
# at least FINAL_LENGTH instructions (pruning stops at PRUNE_ABOVE): one compiled shape
# for most scenes.
FINAL_CHUNK = 16384
FINAL_LENGTH = PRUNE_ABOVE


def _recheck(check, ok, tapes, reg, seg, rest, iso, *per_piece):
    """ok [n] with `check` run on the valid pieces that are not ok yet, gathered apart
    (a few grazing pieces of thousands: checking the whole batch cost 6.6 s of the slab's
    26 s call at 1024^2). `per_piece`: more [n, ...] arrays `check` reads."""
    failed = np.flatnonzero(np.asarray(reg["valid"] & ~ok))
    if failed.size == 0:
        return ok
    size = _tape.bucket(failed.size, _RECHECK_MIN)
    idx = jnp.asarray(np.pad(failed, (0, size - failed.size), mode="edge").astype(np.int32))
    sub, sub_reg, sub_rest = _pieces_at(tapes, reg, per_piece, idx)
    passed = check(sub, sub_reg, seg, rest, iso, *sub_rest)
    return ok.at[idx].max(passed)


# Failed pieces are rechecked in batches of at least this many (padded): one compiled
# shape for the usual handful (each new shape compiled the checks for ~1.3 s)
_RECHECK_MIN = 1024


@functools.partial(jax.jit, static_argnames=("length",))
def _pieces_at(tapes, reg, per_piece, idx, length=None):
    """The final pieces at idx [m]: their tapes (one each: the checks then compile for
    [L, m] whatever the batch; cut or padded to `length`, None: kept), regions and
    `per_piece` arrays."""
    sub = {k: v[idx] for k, v in reg.items()}
    own = _tape.take_regions(tapes, sub["tid"])
    if length is not None:
        own = _tape.resize(own, length)
    sub["tid"] = jnp.arange(idx.shape[0], dtype=jnp.int32)
    return own, sub, tuple(x[idx] for x in per_piece)


@jax.jit
def _finish(rays, seg, best, value, gradient, iso, levels):
    t0, t1, inside, _, _, _ = seg
    hit = inside & jnp.isfinite(best)
    t = jnp.where(hit, t0 + best * (t1 - t0), jnp.inf)
    which = jnp.argmin(jnp.abs(value[:, None] - iso[None, :]), axis=-1).astype(jnp.int32)
    normal = unit_or_facing(gradient, rays.direction)
    return Hits(t=t, hit=hit, normal=jnp.where(hit[:, None], normal, 0.0),
                surface=jnp.where(hit, which, -1),
                steps=jnp.where(inside, levels, 0).astype(jnp.int32))


def _split(level: int, root_q: int, group: int):
    """(q, h) of a level: the roots' groups x slabs, ray groups down to single rays, then
    quarters of the pieces."""
    if level == 0:
        return root_q, ROOT_SLABS
    while group > 1 and level > 1:
        group //= 4
        level -= 1
    return (4, 2) if group > 1 else (1, 4)


# Bytes per tape instruction of a batch: a parent's child while it is classified (its
# choice, int8, and the evaluator's share), and a surviving child (its tape: op, a, b,
# imm and three registers, 28 bytes; the pruning pass's buffers, about 40).
BYTES_PER_CHILD_INSTRUCTION = 4
BYTES_PER_SURVIVOR_INSTRUCTION = 72


def _pow2_floor(x: float) -> int:
    return 0 if x < 1 else 1 << (int(x).bit_length() - 1)


def batch_limit(length: int, children: int, budget: int) -> int:
    """How many parent regions of tapes `length` long, with `children` children each, one
    level may classify at once within `budget` bytes (a power of two; 0: not one)."""
    return _pow2_floor(budget / (BYTES_PER_CHILD_INSTRUCTION * length * children))


def survivor_limit(length: int, budget: int) -> int:
    """How many surviving children with tapes `length` long may be gathered and pruned at
    once within `budget` bytes (a power of two; 0: not one)."""
    return _pow2_floor(budget / (BYTES_PER_SURVIVOR_INSTRUCTION * length))


def _too_big(what: str, need: float, level: int, length: int, budget: int):
    return MemoryError(
        f"the tape path needs {need / 2**20:.0f} MB for {what} at level {level} (tapes of "
        f"{length} instructions), over the memory budget of {budget / 2**20:.0f} MB "
        f"(Plan.memory_budget)")


@functools.partial(jax.jit, static_argnames=("size",))
def _take(reg, start, count, size):
    """Regions start .. start + size - 1 of a batch (those past `count` invalid)."""
    idx = jnp.minimum(start + jnp.arange(size), reg["g"].shape[0] - 1)
    ok = (start + jnp.arange(size)) < count
    sub = {k: v[idx] for k, v in reg.items()}
    sub["valid"] = sub["valid"] & ok
    return sub


@functools.partial(jax.jit, static_argnames=("n_rays",))
def _merge(best, value, gradient, found, n_rays):
    """Each ray's nearest hit over the batches so far."""
    b, v, g = found
    win = b < best
    return (jnp.where(win, b, best), jnp.where(win, v, value),
            jnp.where(win[:, None], g, gradient))


def intersect_rays(scene, tape: Tape, rays: Rays, t_min, t_max, stats: dict | None = None,
                   prune: bool = True, budget: int = DEFAULT_MEMORY_BUDGET) -> Hits:
    """First hits of rays [N] (concrete arrays) on the level sets of `scene` (an
    `ImplicitSurface` whose field is `tape`).

    Regions run in batches that fit `budget` bytes (a batch's children, their tapes and
    the pruning pass; the evaluator's chunks keep their own cap, `_BUDGET` elements of
    its register file), depth first:
    a batch's children are done before its siblings, so memory stays near one batch per
    level, whatever the image size. `stats`, when given, receives per-level region counts
    and tape lengths (mean, max, histogram), the register file and the batches run.
    `prune=False` runs every region on the full tape (to measure what pruning buys).
    Raises MemoryError when one region's children do not fit the budget."""
    n = rays.shape[0]
    group, root_q = _root_groups(n, tape.length, budget)
    per_root = root_q * group
    n_pad = -(-n // per_root) * per_root
    padded, t_min, t_max = _padded_rays(rays, t_min, t_max, n_pad)
    seg = _segments(padded, scene.lo, scene.hi, t_min, t_max, scene.eps)
    run = _Run(scene, seg, scene.isovalues, _rest_coordinates(scene, tape.n_vars), root_q,
               group, budget, prune, _group_hulls(seg, group))
    per_level = None if stats is None else {}
    found, batches, depth = _traverse(run, [_root_work(tape, n_pad // per_root, per_root)],
                                      n_pad, per_level)
    if stats is not None:
        stats.update(tape_length=int(tape.n), registers=tape.registers, batches=batches,
                     budget=budget, levels=[_level_stats(per_level[k])
                                            for k in sorted(per_level)])
    hits = _finish(padded, seg, *found, run.iso, jnp.int32(depth))
    hits = jax.block_until_ready(jax.tree_util.tree_map(lambda a: a[:n], hits))
    del run, found, seg  # the batches are freed: their pages go back to the system
    _trim_heap()
    return hits


class _Run(NamedTuple):
    """What every batch of one `intersect_rays` call shares."""

    scene: object  # the ImplicitSurface
    seg: tuple  # `_segments` of the padded rays
    iso: jax.Array  # the isovalues
    rest: tuple  # the coordinates after x, y, z: w, then the scalar params
    root_q: int  # ray groups per root
    group: int  # rays per root group
    budget: int
    prune: bool
    hulls: dict  # rays per group -> the groups' hulls (`_group_hulls`)


def root_group(n: int) -> int:
    """Rays per root group for a batch of n rays: `ROOT_GROUP` (fewer when there are few
    rays), times 4 until there are at most `ROOT_GROUP_COUNT` groups."""
    group = ROOT_GROUP
    while group > 1 and group // 4 >= n:
        group //= 4
    while n > group * ROOT_GROUP_COUNT:
        group *= 4
    return group


def tape_tile(n: int) -> int:
    """The edge of the Z-order tiles an image of n rays runs in on the tape path: a root
    group's square of pixels (16 at least)."""
    return max(16, math.isqrt(root_group(n)))


def _root_groups(n: int, length: int, budget: int):
    """(rays per group, groups per root) for n rays: `root_group` rays x at most
    `ROOT_GROUPS`, fewer for long tapes (`length`), so that one root's children fit the
    budget."""
    group = root_group(n)
    root_q = min(ROOT_GROUPS, _tape.bucket(-(-n // group), 1),
                 max(1, batch_limit(length, ROOT_SLABS, budget)))
    return group, root_q


@functools.partial(jax.jit, static_argnames=("n_pad",))
def _padded_rays(rays: Rays, t_min, t_max, n_pad: int):
    """Rays [N] padded to [n_pad] (copies of the first ray with an empty range
    t_min = 1 > t_max = 0), and t_min, t_max [n_pad]."""
    n = rays.shape[0]
    pad = n_pad - n
    o = jnp.concatenate([rays.origin, jnp.broadcast_to(rays.origin[:1], (pad, 3))])
    d = jnp.concatenate([rays.direction, jnp.broadcast_to(rays.direction[:1], (pad, 3))])
    t_min = jnp.concatenate([jnp.broadcast_to(t_min, (n,)), jnp.ones(pad)])
    t_max = jnp.concatenate([jnp.broadcast_to(t_max, (n,)), jnp.zeros(pad)])
    return Rays(o, d), t_min, t_max


def _rest_coordinates(scene, n_vars: int) -> tuple:
    """The tape's coordinates after x, y, z: w, then the scalar params (tape coordinates
    4, ...), float32 scalars."""
    rest = tuple(jnp.asarray(v, jnp.float32)
                 for v in [scene.w, *jax.tree_util.tree_leaves(scene.params)])
    if len(rest) != n_vars - 3:
        raise ValueError(f"the tape reads {n_vars} coordinates, the scene gives "
                         f"{3 + len(rest)}")
    return rest


def _root_work(tape: Tape, n_roots: int, per_root: int):
    """The first batch of work: (tapes, regions, how many are real, level, rays per
    region) for n_roots roots, each `per_root` rays over their whole segments with the
    full tape."""
    return (*_roots(tape, n_roots), n_roots, 0, per_root)


@functools.partial(jax.jit, static_argnames=("n_roots",))
def _roots(tape: Tape, n_roots: int):
    """The root store (the one full tape) and n_roots regions over whole segments (one
    compiled call: eagerly, each of these small steps compiles on its own)."""
    roots = dict(g=jnp.arange(n_roots, dtype=jnp.int32), s0=jnp.zeros(n_roots),
                 s1=jnp.ones(n_roots), valid=jnp.ones(n_roots, bool),
                 tid=jnp.zeros(n_roots, jnp.int32))
    return _tape.take_regions(tape, jnp.zeros(1, jnp.int32)), roots


def _traverse(run: _Run, work: list, n_pad: int, per_level: dict | None):
    """Run every batch of `work` (a stack, last first) and the children batches it leaves,
    depth first: a batch's children are done before its siblings, so memory stays near
    one batch per level. `per_level` (None: not kept) receives each level's counts.

    Returns ((best s, value, gradient): each ray's nearest hit, [n_pad] arrays), the
    batches run and the depth reached."""
    first, best, value, gradient = _no_hits(n_pad)
    batches = depth = 0
    heap = _Heap()
    while work:
        tapes, reg, count, level, G = work.pop()
        q, h = _split(level, run.root_q, run.group)
        parts = _batch_parts(tapes, reg, count, level, q * h, run.budget)
        if parts:  # too many regions at once: split the batch, first part first
            work.extend((t, r, c, level, G) for t, r, c in reversed(parts))
            continue
        batches += 1
        depth = max(depth, level + 1)
        Gc = G // q
        children, amb, chosen, counts, first = _level(
            tapes, reg, run.seg, run.hulls[Gc], run.scene.lo, run.scene.hi, run.rest,
            run.iso, first, G, q, h, box_arithmetic(run.scene.arithmetic),
            _prunes(run, tapes))
        n_valid, n_amb, n_unfinished = (int(c) for c in counts)
        pieces = (_survivors(run, tapes, children, amb, chosen, n_amb, level, h)
                  if n_amb else [])
        if per_level is not None:
            _count_level(per_level, level, G // q, n_valid, n_amb, pieces)
        for sub, sub_reg, c in reversed(pieces):
            if G // q == 1 and n_unfinished == 0:
                best, value, gradient = _final(sub, sub_reg, run.seg, run.rest, run.iso,
                                               run.scene.verify, n_pad,
                                               (best, value, gradient))
            else:
                work.append((sub, sub_reg, c, level + 1, G // q))
        del children, amb, chosen, pieces
        heap.batch_done()
    return (best, value, gradient), batches, depth


@functools.partial(jax.jit, static_argnames=("n",))
def _no_hits(n: int):
    """(first, best s, value, gradient) of n rays before any batch: no piece proven, no
    hit."""
    far = jnp.full(n, jnp.inf, jnp.float32)
    return far, far, jnp.zeros(n, jnp.float32), jnp.zeros((n, 3), jnp.float32)


def _batch_parts(tapes, reg, count: int, level: int, children: int, budget: int):
    """A batch of `count` regions with `children` children each in parts that fit
    `budget` ((tapes, regions, how many are real) each), or None when it fits whole.
    Raises MemoryError when one region's children do not fit."""
    limit = batch_limit(tapes.length, children, budget)
    if limit == 0:
        raise _too_big(f"one region's {children} children", BYTES_PER_CHILD_INSTRUCTION *
                       tapes.length * children, level, tapes.length, budget)
    if count <= limit:
        return None
    return [(tapes, _take(reg, k, count, limit), min(limit, count - k))
            for k in range(0, count, limit)]


def _survivors(run: _Run, tapes, children, amb, chosen, n_amb: int, level: int,
               h: int) -> list:
    """The n_amb children that hold a level (amb [R, C]: ray groups x h slabs), in parts
    that can be gathered and pruned within the budget: (tapes, regions, how many are
    real) each, the tapes pruned by the children's own choices (long tapes only, and when
    `run.prune`; tapes of `SHARED_PRUNE_FROM` instructions first by the choices each
    ray group's slabs share) and sorted longest first."""
    pruning = _prunes(run, tapes)
    _check_fits(tapes.length, run.budget, level)
    origin = None
    if pruning and tapes.length >= SHARED_PRUNE_FROM and h > 2:
        tapes, origin = _shared_prune(tapes, children["tid"][:, 0], amb, chosen, h,
                                      run.budget)
    part = survivor_limit(tapes.length, run.budget)
    size = min(part, _tape.bucket(n_amb, 8, fine=True))
    where = ambiguous_positions(amb, _tape.bucket(n_amb, 8, fine=True))
    pieces = []
    for start in range(0, n_amb, size):
        sub, choices, sub_reg = gather_children(tapes, children, chosen, where, start,
                                                 n_amb, size, pruning, origin,
                                                 1 if origin is None else h)
        length = sub.length
        if pruning:
            sub = _tape.registers_in_use(*_prune_sorted(sub, choices))
            length = _tape.longest_bucket(sub)
        sub, sub_reg = _longest_first(sub, sub_reg, length)
        pieces.append((sub, sub_reg, min(size, n_amb - start)))
    return pieces


def _prunes(run: _Run, tapes) -> bool:
    """Whether children of regions running `tapes` get their tapes pruned."""
    return run.prune and tapes.length > PRUNE_ABOVE


def _check_fits(length: int, budget: int, level: int):
    if survivor_limit(length, budget) == 0:
        raise _too_big("one region's tape", BYTES_PER_SURVIVOR_INSTRUCTION * length, level,
                       length, budget)


def _shared_prune(tapes, tid, amb, chosen, h: int, budget: int):
    """The first of two pruning stages for children of long tapes: each ray group's tape
    (its parent's) pruned by the choices that all its ambiguous slabs share. A group's h
    slabs share most choices (Prospero's slab: all, it does not read z), so each slab is
    then pruned on a much shorter tape (slab 256^2: the root's children were pruned
    against 7,871 instructions, 1.75 s of a 6.3 s call). amb [R, C], chosen [L, R, C]
    (C = q h, group-major). Returns the groups' tapes [L', R q] (no registers: they are
    pruned again) and the origins of their instructions [L', R q] (`gather_children`
    reads each child's choices there). tid [R]: each parent's tape in the store
    `tapes`."""
    L, R, C = chosen.shape
    groups = R * (C // h)
    consensus, busy = _consensus(amb, chosen, h)
    part = min(survivor_limit(L, budget), _tape.bucket(groups, 1))
    parts = [_group_prune(tapes, tid, consensus, busy, start, part, C // h)
             for start in range(0, groups, part)]
    length = max(_tape.longest_bucket(t) for t, _ in parts)
    return _joined_groups(parts, length, groups)


@functools.partial(jax.jit, static_argnames=("h",))
def _consensus(amb, chosen, h):
    """The choices ([L, groups] int8) shared by every ambiguous slab of each ray group,
    and which groups have one (busy [groups])."""
    L, R, C = chosen.shape
    c = chosen.reshape(L, R * (C // h), h)
    a = amb.reshape(R * (C // h), h)
    busy = jnp.any(a, axis=-1)
    shared = jnp.zeros(c.shape[:2], jnp.int8)
    for v in (1, 2):
        agree = busy & jnp.all(jnp.where(a[None], c == v, True), axis=-1)
        shared = jnp.where(agree, jnp.int8(v), shared)
    return shared, busy


@functools.partial(jax.jit, static_argnames=("size", "q"))
def _group_prune(tapes, tid, consensus, busy, start, size, q):
    """Groups start .. start + size - 1 (past the last: the last again): their parent's
    tape pruned by their shared choices (idle groups to one instruction), without
    registers, and the origins of the pruned instructions."""
    idx = jnp.minimum(start + jnp.arange(size), consensus.shape[1] - 1)
    sub = _tape.take_regions(dataclasses.replace(tapes, reg=None), tid[idx // q])
    sub = dataclasses.replace(sub, n=jnp.where(busy[idx], sub.n, 1))
    return _tape.prune(sub, consensus[:, idx], origins=True, registers=False)


@functools.partial(jax.jit, static_argnames=("length", "groups"))
def _joined_groups(parts, length, groups):
    """The groups' pruned tapes and their origins cut to `length` and joined
    ([length, groups] each)."""
    tapes = [_tape.resize(t, length) for t, _ in parts]
    tapes = jax.tree_util.tree_map(lambda *x: jnp.concatenate(x, axis=-1)[..., :groups],
                                   *tapes)
    return tapes, jnp.concatenate([o[:length] for _, o in parts], axis=-1)[:, :groups]


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None (another C library)."""
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    return trim


def _resident_bytes() -> int | None:
    """This process's resident memory (Linux), or None."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


class _Heap:
    """Hands the heap's free pages back to the system when the process has grown by
    `TRIM_GROWTH` bytes since the last time. The batches' buffers (hundreds of MB, freed
    by XLA) otherwise stay resident in glibc's heaps: the slab at 1024^2 peaked at 2.79
    GB; 1.85 GB with a trim after every batch, which cost 5% of the call (the next
    batch's buffers are fresh pages again); 1.97 GB at 1-2% with this rule."""

    TRIM_GROWTH = 2**28

    def __init__(self):
        self.floor = _resident_bytes()

    def batch_done(self):
        now = _resident_bytes()
        if now is None or self.floor is None or now >= self.floor + self.TRIM_GROWTH:
            self.trim()

    def trim(self):
        _trim_heap()
        self.floor = _resident_bytes()


def _trim_heap():
    """Hand the heap's free pages back to the system (glibc), else nothing."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _count_level(per_level: dict, level: int, rays_per_region: int, n_valid: int,
                 n_amb: int, pieces: list):
    """Add a batch's region counts and its survivors' tape lengths to its level's row."""
    row = per_level.setdefault(level, dict(rays_per_region=rays_per_region, regions=0,
                                           kept=0, lengths=[]))
    row["regions"] += n_valid
    row["kept"] += n_amb
    row["lengths"].extend(np.asarray(sub.n)[np.asarray(r["tid"])[:c]] for sub, r, c in pieces)


def _level_stats(row):
    lengths = row.pop("lengths")
    # a level where no batch kept a region has no lengths to join
    kept = np.concatenate(lengths) if lengths else np.zeros(0, np.int32)
    return dict(row, tape_mean=float(kept.mean()) if kept.size else 0.0,
                tape_max=int(kept.max()) if kept.size else 0, tape_hist=histogram(kept))
