"""Stackless interval bisection along rays (seed Sec. 6.4-6.5, Algorithm 7).

A ray segment is reparameterised to s in [0, 1]. The kernels only need a *box test*
``test(s0, s1) -> BoxTest`` that says whether the implicit may vanish for s in
[s0, s1] (an inclusion extension evaluated on that piece of the ray).

t-bisection (per ray, `t_bisect`) keeps the current piece as an integer position k at
depth d: the piece is [k 2^-d, (k+1) 2^-d]. Instead of a stack, moving on to the next
piece pops the levels where both halves were visited: those are the trailing zero bits
of k + 1 (the seed tests the same thing with a float modulus). Integer positions keep
pieces exact down to depth 30, below float32 resolution of s.

K-bisection (per packet, `k_bisect`) marches all rays of a packet through common slabs
of the dominant axis K in lockstep (Sec. 6.4.3): one shared (k, d) and per-ray masks.
"""

from __future__ import annotations

import dataclasses
import functools
import typing

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._lanes import run_rays

MAX_DEPTH = 30  # int32 positions stay exact


class BoxTest(typing.NamedTuple):
    """Outcome of an inclusion test on one piece of a ray (scalars or [P]).

    possible: the enclosure contains an isovalue (a root may lie in the piece).
    finite: the enclosure is bounded (an unbounded one, e.g. at a division asymptote,
      is bisected but never registers a hit, Sec. 6.4.4).
    small: the enclosure is narrower than the range tolerance delta (a hit criterion).
    """

    possible: jax.Array
    finite: jax.Array
    small: jax.Array


class Result(typing.NamedTuple):
    s: jax.Array      # [..] hit parameter in [0, 1] (midpoint of the final piece), inf if none
    hit: jax.Array    # bool
    steps: jax.Array  # int32 iterations


def depth_for(length, eps):
    """Eq. 6.19: the depth whose pieces are at most eps long, d = ceil(log2(L / eps)),
    clamped to [0, MAX_DEPTH]."""
    d = jnp.ceil(jnp.log2(jnp.maximum(length, 1e-30) / eps))
    return jnp.clip(d, 0, MAX_DEPTH).astype(jnp.int32)


def piece_width(d):
    """2^-d as an exact float32 (built from the exponent bits: XLA's exp2 is not exact
    on CPU, and pieces whose widths are off by an ulp leave gaps between them)."""
    return lax.bitcast_convert_type((127 - d.astype(jnp.int32)) << 23, jnp.float32)


def _trailing_zeros(k):
    """Number of trailing zero bits of a positive int32."""
    return lax.population_count((k & -k) - 1)


def piece(k, d):
    """(s0, s1) = (k 2^-d, (k + 1) 2^-d), the piece at integer position k of depth d."""
    w = piece_width(d)
    return k.astype(jnp.float32) * w, (k + 1).astype(jnp.float32) * w


def advance(k, d, accept, descend, floor=0):
    """One move of the stackless walk over the pieces (k, d) of [0, 1] (Algorithm 7).

    accept: stay on the piece (it holds the hit); else descend: go to its first half
    (2k, d + 1); else move on to the next piece k + 1 and pop the levels whose both halves
    are done, the trailing zero bits of k + 1 (the seed's float-modulus test), never above
    depth `floor` (a walk that starts on the 2^floor pieces of that depth).
    Elementwise (scalars or arrays; accept may be a Python bool). Returns (k, d, finished):
    finished when the piece was accepted or the walk moved past s = 1.
    """
    k_next = k + 1
    pop = jnp.minimum(_trailing_zeros(k_next), d - floor)
    k_next, d_next = k_next >> pop, d - pop
    k = jnp.where(accept, k, jnp.where(descend, 2 * k, k_next))
    d = jnp.where(accept, d, jnp.where(descend, d + 1, d_next))
    return k, d, accept | (~descend & ((k_next >> d_next) >= 1))


def leap(k, d, s_free, d0, d_max):
    """The walk's next piece (k, d) moved on past [its start, s_free), a stretch known to
    hold no root (`t_bisect_lanes`' `ahead`): onto the largest piece (depth d0 to d_max)
    that starts after its start and at most at s_free (at that depth the last such);
    (k, d) itself when there is none. From there the stackless walk covers the rest of
    [0, 1] as usual. Elementwise; returns (k, d, past): past where s_free >= 1 (the walk
    is over)."""
    top = MAX_DEPTH
    start = k << (top - d)  # the piece's start in units of 2^-MAX_DEPTH (exact)
    step = top - d_max  # no piece below depth d_max
    end = jnp.floor(jnp.clip(s_free, 0.0, 1.0) * piece_width(-jnp.int32(top)))
    end = (jnp.minimum(end, 2.0**top - 1).astype(jnp.int32) >> step) << step
    # the multiple of the most trailing zeros in (start, end]: end with the bits below
    # the highest one where start and end differ cleared
    diff = start ^ end
    high = 31 - lax.clz(jnp.maximum(diff, 1))
    target = (end >> high) << high
    zeros = jnp.where(target == 0, top, _trailing_zeros(jnp.maximum(target, 1)))
    depth = jnp.clip(top - zeros, d0, d_max)
    moved = end > start
    k = jnp.where(moved, end >> (top - depth), k)
    d = jnp.where(moved, depth, d)
    return k, d, s_free >= 1.0


# t-bisection: per-ray state (scalars or [P] leaves) for `jaxiso._lanes.run_rays`
_T_RESULTS = ("k", "d", "hit", "steps")
_T_KEYS = _T_RESULTS + ("going", "dmax", "d0")


def _t_start(d_max, active, d_start=0):
    """Per-ray walk state; the walk starts on the pieces of depth min(d_start, d_max)."""
    d_max = jnp.asarray(d_max, jnp.int32)
    active = jnp.asarray(active, bool)
    zeros = jnp.zeros_like(d_max)
    d0 = jnp.minimum(jnp.asarray(d_start, jnp.int32), d_max)
    return dict(k=zeros, d=d0, d0=d0, dmax=d_max, going=active,
                hit=jnp.zeros_like(active), steps=zeros)


def _t_step(test, st, max_steps=None, ahead=None):
    """One t-bisection step of every going ray (elementwise) with steps left (below
    max_steps, None: not checked); other rays come back unchanged. An accepted ray stops
    on (k, d) of its hit piece. ahead: None or ``ahead(st, s) -> s_free`` [..]: the
    ray's stretch [s, s_free) holds no root (e.g. a sign grid's empty cells); a walk
    that moves on to a piece starting at s leaps past it (`leap`)."""
    k, d, go = st["k"], st["d"], st["going"]
    if max_steps is not None:
        go = go & (st["steps"] < max_steps)
    r = _materialized(test(*piece(k, d)))
    accept = r.possible & r.finite & ((d >= st["dmax"]) | r.small)
    descend = r.possible & ~accept & (d < st["dmax"])
    k_new, d_new, finished = advance(k, d, accept, descend, st["d0"])
    if ahead is not None:
        moving = ~accept & ~finished
        k_leap, d_leap, past = leap(k_new, d_new, ahead(st, piece(k_new, d_new)[0]),
                                    st["d0"], st["dmax"])
        k_new = jnp.where(moving, k_leap, k_new)
        d_new = jnp.where(moving, d_leap, d_new)
        finished = finished | (moving & past)
    return dict(st, k=jnp.where(go, k_new, k), d=jnp.where(go, d_new, d),
                going=st["going"] & ~(go & finished), hit=st["hit"] | (go & accept),
                steps=st["steps"] + go.astype(jnp.int32))


def _materialized(r: BoxTest) -> BoxTest:
    """The test's outcome as one array computed once. XLA CPU fused the enclosure into
    every state leaf's update (k, d, going, hit: four copies of one ~880-instruction
    loop for the affine Barth sextic) and drops optimization barriers before fusion; a
    scatter is never fused into its users, so they read its result."""
    code = (r.possible.astype(jnp.int32) | (r.finite.astype(jnp.int32) << 1)
            | (r.small.astype(jnp.int32) << 2))
    flat = code.reshape(-1)
    at = jnp.arange(flat.shape[0])
    flat = jnp.zeros_like(flat).at[at].set(flat, unique_indices=True, indices_are_sorted=True)
    code = flat.reshape(code.shape)
    return BoxTest((code & 1) != 0, (code & 2) != 0, (code & 4) != 0)


def _t_result(out) -> Result:
    s = (out["k"].astype(jnp.float32) + 0.5) * piece_width(out["d"])
    return Result(jnp.where(out["hit"], s, jnp.inf), out["hit"], out["steps"])


def _walking(max_steps: int):
    """busy for `run_rays`: the ray walks and has steps left (a walk after a failed
    verification starts with the steps of the walks before it)."""
    return lambda st: st["going"] & (st["steps"] < max_steps)


def first_verified(verify, k, d, levels: int, rays=()):
    """(ok, k, d): where ``verify(*rays, s0, s1)`` establishes a root in the piece (k, d).
    levels 0: (k, d) itself. Otherwise verify is called with ``parts=2^levels`` and
    returns (ok, part): the hit is that part of the piece (its piece at depth d +
    levels), or the whole piece where part is -1 (a root found another way than in a
    part). ok False: no root (k, d unchanged). k, d: [...]; rays: per-ray arrays [..., *]
    that verify takes before the piece."""
    if levels == 0:
        return verify(*rays, *piece(k, d)), k, d
    ok, part = verify(*rays, *piece(k, d), parts=2**levels)
    sub = part >= 0
    return (ok, jnp.where(ok & sub, (k << levels) + part, k),
            jnp.where(ok & sub, d + levels, d))


def _verified_rounds(run, verify, state, max_steps: int):
    """Run the walk (`run`: state -> state, which steps a going ray only while its step
    count is below max_steps), then check each ray's accepted piece with `verify` (state
    -> (ok, k, d): ok where a root is established there, in the piece (k, d) it names,
    `first_verified`); a ray whose piece fails moves on to the next piece and walks
    again, until no ray does or its steps reach max_steps (then it reports no hit).
    Every walk costs each ray it moves at least a step, so max_steps bounds the rounds."""
    if verify is None:
        return run(state)

    def body(carry):
        r, st = carry
        out = run(st)
        ok, k_hit, d_hit = verify(out)
        bad = out["hit"] & ~ok
        no = jnp.zeros_like(bad)
        k_next, d_next, end = advance(out["k"], out["d"], no, no, out["d0"])
        k = jnp.where(bad, k_next, jnp.where(out["hit"], k_hit, out["k"]))
        d = jnp.where(bad, d_next, jnp.where(out["hit"], d_hit, out["d"]))
        return r + 1, dict(out, k=k, d=d, hit=out["hit"] & ~bad,
                           going=bad & ~end & (out["steps"] < max_steps))

    def cond(carry):
        r, st = carry
        return (r == 0) | jnp.any(st["going"])

    _, out = lax.while_loop(cond, body, (jnp.int32(0), state))
    return out


def t_bisect(test, d_max, active, max_steps: int, verify=None, ahead=None,
             verify_levels: int = 0) -> Result:
    """Stackless bisection of one ray's segment (call under vmap for a packet: one
    batched loop, until the packet's slowest ray is done).

    Args:
      test: ``test(s0, s1) -> BoxTest`` for this ray.
      d_max: int32 depth at which a possible piece counts as a hit (Eq. 6.19).
      active: bool, False for rays that miss the domain.
      max_steps: static bound on loop iterations (a ray that runs out reports no hit).
      verify: None (a piece whose enclosure holds an isovalue at depth d_max is the hit,
        the seed's rule) or ``verify(s0, s1) -> bool``: such a piece is the hit only when
        verify establishes a root in it; otherwise the walk goes on past it.
      ahead: None or ``ahead(s) -> s_free``: [s, s_free) holds no root (`_t_step`).
      verify_levels: with verify, the walk accepts pieces verify_levels above d_max, and
        verify (called with ``parts=2^verify_levels``) finds the hit among their pieces
        at d_max (point evaluations in place of the enclosures' last levels near a
        surface, `first_verified`).
    """
    leap_past = None if ahead is None else (lambda st, s: ahead(s))
    d_walk = _walk_depth(d_max, verify, verify_levels)

    def run(st):
        return run_rays(functools.partial(_t_step, test, max_steps=max_steps,
                                          ahead=leap_past),
                        _walking(max_steps), st, _T_KEYS,
                        max_steps=max_steps, steps="steps")

    check = None if verify is None else (
        lambda st: first_verified(verify, st["k"], st["d"], verify_levels))
    return _t_result(_verified_rounds(run, check, _t_start(d_walk, active), max_steps))


def _walk_depth(d_max, verify, levels: int):
    """The depth walks accept at: verify_levels above d_max (at least 0) with verify."""
    if verify is None or levels == 0:
        return d_max
    return jnp.maximum(jnp.asarray(d_max, jnp.int32) - levels, 0)


def k_bisect(test, k_enter, k_exit, d_max, active, max_steps: int, verify=None) -> Result:
    """Packet bisection in lockstep along the dominant axis K (Sec. 6.4.3).

    The packet's K range [K0, K1] (union of its rays' ranges) is bisected with one shared
    (k, d); piece k at depth d is the slab [K0 + k w, K0 + (k+1) w] with w = (K1-K0) 2^-d,
    visited in the marching direction. Each ray tests its own part of the slab.

    Args:
      test: ``test(s0, s1) -> BoxTest`` vectorised over the packet, with s in the rays'
        own [0, 1] segment parameters ([P] each).
      k_enter, k_exit: [P] the rays' K coordinates at s = 0 and s = 1.
      d_max: [P] int32 per-ray depth for the precision eps (Eq. 6.16-6.17: the packet
        uses the deepest).
      active: [P] bool.
      verify: None or ``verify(s0, s1) -> [P] bool`` (as in `t_bisect`): a ray accepts
        a piece only where it holds; elsewhere it goes on with the packet.
    Returns per-ray `Result` ([P]).
    """
    K0, span, d_stop = _k_range(k_enter, k_exit, d_max, active)
    dk = k_exit - k_enter
    safe_dk = jnp.where(dk == 0.0, 1.0, dk)

    def pieces(k, d):
        u0, u1 = piece(k, d)
        a = K0 + span * u0
        b = K0 + span * u1
        s_a = (a - k_enter) / safe_dk
        s_b = (b - k_enter) / safe_dk
        s0 = jnp.clip(jnp.minimum(s_a, s_b), 0.0, 1.0)
        s1 = jnp.clip(jnp.maximum(s_a, s_b), 0.0, 1.0)
        inside = (jnp.maximum(s_a, s_b) >= 0.0) & (jnp.minimum(s_a, s_b) <= 1.0)
        return s0, s1, inside

    def cond(state):
        k, d, live, hit, s_hit, steps = state
        return jnp.any(live) & (steps < max_steps)

    def body(state):
        k, d, live, hit, s_hit, steps = state
        s0, s1, inside = pieces(k, d)
        r = test(s0, s1)
        cand = live & inside & r.possible
        accept = cand & r.finite & ((d >= d_stop) | r.small)
        if verify is not None:
            accept = accept & verify(s0, s1)
        hit = hit | accept
        s_hit = jnp.where(accept, 0.5 * (s0 + s1), s_hit)
        live = live & ~accept
        descend = jnp.any(cand & ~accept) & (d < d_stop)
        k, d, end = advance(k, d, False, descend)  # the shared piece is never accepted
        return k, d, live & ~end, hit, s_hit, steps + 1

    n = k_enter.shape
    init = (jnp.int32(0), jnp.int32(0), active, jnp.zeros(n, bool),
            jnp.full(n, jnp.inf, jnp.float32), jnp.int32(0))
    k, d, live, hit, s_hit, steps = lax.while_loop(cond, body, init)
    return Result(s_hit, hit, jnp.broadcast_to(steps, n))


def _k_range(k_enter, k_exit, d_max, active):
    """(K0, span, d_stop) of a K-bisection packet: the start of its K range in the
    marching direction, the signed range K1 - K0, and the shared depth that gives every
    active ray pieces no longer than its eps (Eq. 6.16-6.17)."""
    big = jnp.float32(3e38)
    lo = jnp.minimum(k_enter, k_exit)
    hi = jnp.maximum(k_enter, k_exit)
    forward = jnp.sum(jnp.where(active, k_exit - k_enter, 0.0)) >= 0.0
    K0 = jnp.where(forward, jnp.min(jnp.where(active, lo, big)),
                   jnp.max(jnp.where(active, hi, -big)))
    K1 = jnp.where(forward, jnp.max(jnp.where(active, hi, -big)),
                   jnp.min(jnp.where(active, lo, big)))
    span = K1 - K0
    # the slab width at depth d is |span| 2^-d; a ray needs its piece (in s) <= its eps
    ratio = jnp.abs(span) / jnp.maximum(jnp.abs(k_exit - k_enter), 1e-30)
    d_need = jnp.where(active, d_max + jnp.ceil(jnp.log2(jnp.maximum(ratio, 1.0))), 0)
    return K0, span, jnp.clip(jnp.max(d_need), 0, MAX_DEPTH).astype(jnp.int32)

# The pilot of `start_depth`: this many rays, depths 0..PILOT_DEPTH.
PILOT_RAYS = 64
PILOT_DEPTH = 7


def start_depth(test, p, D, d_max, active):
    """The depth each walk of this batch starts at, from a pilot of PILOT_RAYS of its rays
    (evenly spaced among the active ones): the depth at which the ray's pieces are as
    long as the longest pieces the test excludes at least half the time.

    A walk from depth 0 evaluates every level above that one; on a level whose pieces
    are excluded with probability q, each piece costs 1 + 2 (1 - q) evaluations against 2
    for starting below it, so starting deeper saves while q < 1/2. Networks' affine
    enclosures exclude almost nothing on long pieces (fox: none of ~300 pieces at depths
    0-2), the catalogue's from depth 0. Whether a piece is excluded depends on its length
    in space, not on its share of the segment, and segments cut to a sign grid's span
    differ in length by 10-100x: the pilot's pieces (depths 0..PILOT_DEPTH) are counted by
    their length (octaves), and each ray starts where its pieces reach the longest octave
    excluded at least half the time (of at least PILOT_MIN pieces). The pilot costs
    PILOT_RAYS x 255 evaluations.

    Args as `t_bisect_lanes`' (test vectorised over any batch). Returns int32 [N].
    """
    n = active.shape[0]
    count = jnp.sum(active)
    order = jnp.nonzero(active, size=n, fill_value=0)[0]
    ray = order[(jnp.arange(PILOT_RAYS) * count) // PILOT_RAYS]
    depth = np.concatenate([np.full(2**d, d) for d in range(PILOT_DEPTH + 1)])
    k = np.concatenate([np.arange(2**d) for d in range(PILOT_DEPTH + 1)])
    ray_i = jnp.repeat(ray, depth.size)
    d_i = jnp.tile(jnp.asarray(depth, jnp.int32), PILOT_RAYS)
    s0, s1 = piece(jnp.tile(jnp.asarray(k, jnp.int32), PILOT_RAYS), d_i)
    r = test(p[ray_i], D[ray_i], s0, s1)
    counted = (jnp.repeat(jnp.arange(PILOT_RAYS) < count, depth.size)
               & (d_i <= d_max[ray_i]))
    length = jnp.linalg.norm(D, axis=-1)
    # octave o holds pieces of length in [2^(o - _OCTAVE0), 2^(o + 1 - _OCTAVE0))
    octave = jnp.floor(jnp.log2(jnp.maximum(length[ray_i] * (s1 - s0), 1e-30)))
    o_i = jnp.clip(octave.astype(jnp.int32) + _OCTAVE0, 0, _OCTAVES - 1)
    excluded = jnp.zeros(_OCTAVES).at[o_i].add(counted & ~r.possible)
    pieces = jnp.zeros(_OCTAVES).at[o_i].add(counted)
    good = (excluded >= 0.5 * pieces) & (pieces >= PILOT_MIN)
    best = _OCTAVES - 1 - jnp.argmax(good[::-1])  # the longest good octave
    # none good: the pilot's deepest pieces, as long as the pilot's segments' median's
    fallback = jnp.log2(jnp.maximum(jnp.median(length[ray]), 1e-30)) - PILOT_DEPTH
    top = jnp.where(jnp.any(good), (best + 1 - _OCTAVE0).astype(jnp.float32), fallback)
    d = jnp.ceil(jnp.log2(jnp.maximum(length, 1e-30)) - top)
    return jnp.clip(d, 0, d_max).astype(jnp.int32)


# The pilot's octaves of piece length: 2^-_OCTAVE0 .. 2^(_OCTAVES - _OCTAVE0)
_OCTAVE0 = 24
_OCTAVES = 32
# ... and the fewest pieces an octave needs to count
PILOT_MIN = 16


def t_bisect_lanes(test, p, D, d_max, active, lanes: int | None, max_steps: int,
                   verify=None, d_start=0, min_width: int | None = None, ahead=None,
                   aux=None, verify_levels: int = 0) -> Result:
    """t-bisection of a batch of rays [N] on `lanes` persistent lanes with refill
    (`jaxiso._lanes.run_rays`; rays that miss the domain never enter the queue), or, with
    lanes None, one loop over the batch. Same per-ray step and results as `t_bisect`.
    Refilling every 4 steps was best: measured on the 2-core CPU (Barth sextic, IA,
    512^2, 4096 lanes) every 1 -> 0.42, 2 -> 0.68, 4 -> 0.82, 8 -> 0.80 Mrays/s with
    identical hits (benchmarks/NOTES.md).

    On lanes, accepted pieces are verified between refills (`_settle_hits`): a piece that
    fails sends its lane on along the ray at once, bounded only by max_steps. Without
    lanes, in rounds of walks (`_verified_rounds`).

    Args:
      test: ``test(p, D, s0, s1) -> BoxTest`` vectorised over lanes ([L] / [L, 3]).
      p, D: [N, 3] ray segment start and vector; d_max: [N] int32; active: [N] bool.
      lanes: static number of lanes of the first phase, or None.
      max_steps: static bound on iterations per ray.
      verify: None or ``verify(p, D, s0, s1) -> [n] bool`` (as in `t_bisect`), run on
        accepted pieces only.
      d_start: int32 [] or [N], the depth the walks start at (`start_depth`); pieces
        above it are not tested.
      min_width: static width of the narrowest lane phase (`jaxiso._lanes.run_lanes`;
        None: lanes / 8).
      ahead, aux: None, or ``ahead(aux, s) -> s_free`` and its per-ray data (a pytree of
        [N, ...] leaves): the ray's stretch [s, s_free) holds no root (`_t_step`).
      verify_levels: as in `t_bisect`.
    """
    leap_past = None if ahead is None else (lambda st, s: ahead(st["aux"], s))
    d_max = _walk_depth(d_max, verify, verify_levels)

    def step(st):
        return _t_step(lambda s0, s1: test(st["p"], st["D"], s0, s1), st, max_steps,
                       leap_past)

    state = dict(_t_start(d_max, active, d_start), p=p, D=D)
    if ahead is not None:
        state["aux"] = aux
    if lanes is not None and verify is not None:
        # "sure": the lane's hit piece passed verify; a held piece keeps the lane busy
        state["sure"] = jnp.zeros_like(state["hit"])
        out = run_rays(step, lambda s: s["going"] | (s["hit"] & ~s["sure"]), state,
                       _T_KEYS + ("sure",), max_steps=max_steps, steps="steps", lanes=lanes,
                       settle=functools.partial(_settle_hits, verify, verify_levels),
                       min_width=min_width)
        # a lane that ran out of steps while holding a piece reports no hit
        return _t_result(dict(out, hit=out["hit"] & out["sure"]))

    def run(st):
        out = run_rays(step, _walking(max_steps), st, _T_KEYS, max_steps=max_steps,
                       steps="steps", lanes=lanes, min_width=min_width)
        return dict(out, p=p, D=D) if ahead is None else dict(out, p=p, D=D, aux=aux)

    check = None if verify is None else (
        lambda st: first_verified(verify, st["k"], st["d"], verify_levels, (p, D)))
    return _t_result(_verified_rounds(run, check, state, max_steps))


def _settle_hits(verify, levels, st, live):
    """Verify the pieces that lanes hold (accepted, not yet verified), gathered in chunks
    of `_settle_width`: a verified piece (its first verified piece `levels` deeper,
    `first_verified`) is the lane's hit; a failed one moves the lane's walk on to the
    next piece."""
    n = live.shape[0]
    width = _settle_width(n)

    def chunk(carry):
        st, todo = carry
        lane = jnp.nonzero(todo, size=width, fill_value=n)[0]  # n: no lane
        at = jnp.minimum(lane, n - 1)
        k, d = st["k"][at], st["d"][at]
        ok, k_hit, d_hit = first_verified(verify, k, d, levels, (st["p"][at], st["D"][at]))
        no = jnp.zeros_like(ok)
        k_next, d_next, end = advance(k, d, no, no, st["d0"][at])

        def put(a, v):
            return a.at[lane].set(v, mode="drop")

        st = dict(st, sure=put(st["sure"], ok), hit=put(st["hit"], ok),
                  k=put(st["k"], jnp.where(ok, k_hit, k_next)),
                  d=put(st["d"], jnp.where(ok, d_hit, d_next)),
                  going=put(st["going"], ~ok & ~end))
        return st, put(todo, no)

    held = live & st["hit"] & ~st["sure"]
    return lax.while_loop(lambda c: jnp.any(c[1]), chunk, (st, held))[0]


def _settle_width(lanes: int) -> int:
    """Held pieces verified together (one chunk) on `lanes` lanes: an eighth of them, at
    least 32. A lane holds at the end of its walk, ~1 in 50 steps on the networks, so a
    refill of 4 steps usually needs one chunk; a loose enclosure near the surface (bunny)
    fails pieces by the thousand, and more chunks run."""
    return min(lanes, max(32, lanes // 8))


# ------------------------------------------------------------- the packet driver

@dataclasses.dataclass(frozen=True)
class Bisection:
    """How `run_bisection` drives a packet (the scene's options, resolved).

    method: "t-bisection" or "k-bisection".
    eps: world-space length of the final piece (traced scalar).
    max_steps: static iteration bound (None: enough for eps 2^-22, see `default_steps`).
    lanes: None (packets) or the persistent lanes of t-bisection.
    verify: None or ``verify(p, D, s0, s1)`` (`_field.root_check`).
    heavy: a costly function (a network) on lanes: walks start at the depth
      `start_depth` measures (on the catalogue at 512^2 that gained nothing clear and
      cost 0.4-1.4 s of compile), and its lanes narrow in phases down to 64 (a light
      function's run in one: `_tail_width`); not 32: every phase compiles the walk
      again, and on the networks at 128^2 the 32-lane phase cost 1.3-1.4 s of first
      call and saved 1-2% of the run.
    empty: None or (ahead, aux): stretches of the rays that hold no root, which
      t-bisection's walks leap (`t_bisect_lanes`; K-bisection's shared pieces do not).
    verify_levels: t-bisection's walks with verify accept pieces that many levels above
      d_max and take the first verified of their pieces at d_max (`t_bisect`).
    """

    method: str
    eps: object
    max_steps: int | None = None
    lanes: int | None = None
    verify: object = None
    heavy: bool = False
    empty: tuple | None = None
    verify_levels: int = 0

    def steps(self) -> int:
        """max_steps, or the default: enough for eps 2^-22 with IA on the Barth decic
        (1920 was not); a K-bisection packet visits the union of its rays' pieces."""
        if self.max_steps is not None:
            return self.max_steps
        return 256 * MAX_DEPTH * (8 if self.method == "k-bisection" else 1)


def run_bisection(test, p, D, inside, how: Bisection) -> Result:
    """t- or K-bisection of a packet of ray segments ``p + s D`` (p, D: [P, 3], inside:
    [P]) with a box test ``test(p, D, s0, s1) -> BoxTest``. Returns Result [P]."""
    length = jnp.linalg.norm(D, axis=-1)
    d_max = depth_for(length, how.eps)
    max_steps = how.steps()
    ahead, aux = (None, None) if how.empty is None else how.empty
    if how.method == "t-bisection" and how.lanes is not None:
        d_start = start_depth(test, p, D, d_max, inside) if how.heavy else 0
        return t_bisect_lanes(test, p, D, d_max, inside, how.lanes, max_steps, how.verify,
                              d_start, min_width=_tail_width(how), ahead=ahead,
                              aux=aux, verify_levels=how.verify_levels)
    if how.method == "t-bisection":
        return t_bisect_packet(test, p, D, d_max, inside, max_steps, how.verify,
                               how.empty, how.verify_levels)
    if how.method == "k-bisection":
        return k_bisect_packet(test, p, D, d_max, inside, max_steps, how.verify)
    raise ValueError(f"unknown bisection method {how.method!r}")


def _tail_width(how: Bisection) -> int | None:
    """The narrowest lane phase. Costly functions: a second and third phase of 512 and 64
    lanes (a network's step on 4,096 mostly idle lanes costs more than a phase's
    compile). Light ones: one phase (each phase compiles the walk again; on the 2-core
    CPU a 512-lane tail phase cost polynomials 0.9-1.3 s and affine bretzel4 3-3.5 s of
    first call for frames within noise, 0-8%: benchmarks/NOTES.md, session 34)."""
    return 64 if how.heavy else how.lanes


def t_bisect_packet(test, p, D, d_max, inside, max_steps, verify, empty=None,
                    verify_levels=0) -> Result:
    """Per-ray t-bisection under vmap (one batched loop per packet)."""
    ahead, aux = (None, None) if empty is None else empty

    def one(p, D, d_max, active, aux):
        check = None if verify is None else functools.partial(verify, p, D)
        leap = None if ahead is None else functools.partial(ahead, aux)
        return t_bisect(functools.partial(test, p, D), d_max, active, max_steps, check,
                        leap, verify_levels)
    return jax.vmap(one)(p, D, d_max, inside, aux)


def k_bisect_packet(test, p, D, d_max, inside, max_steps, verify) -> Result:
    """K-bisection for the rays that march coherently along the packet's dominant axis;
    the rest (opposite or too oblique K direction) fall back to t-bisection."""
    length = jnp.linalg.norm(D, axis=-1)
    mean = jnp.sum(jnp.where(inside[:, None], D, 0.0), axis=0)
    axis = jnp.argmax(jnp.abs(mean))
    dk = jnp.take(D, axis, axis=1)
    sign = jnp.sign(jnp.take(mean, axis))
    coherent = inside & (jnp.sign(dk) == sign) & (jnp.abs(dk) >= 0.25 * length)
    k_enter = jnp.take(p, axis, axis=1)
    check = None if verify is None else functools.partial(verify, p, D)
    res_k = k_bisect(lambda s0, s1: test(p, D, s0, s1), k_enter, k_enter + dk,
                     d_max, coherent, max_steps, check)
    res_t = t_bisect_packet(test, p, D, d_max, inside & ~coherent, max_steps, verify)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(coherent, a, b), res_k, res_t)
