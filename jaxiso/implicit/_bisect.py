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

import typing

import jax
import jax.numpy as jnp
from jax import lax

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


def t_bisect(test, d_max, active, max_steps: int) -> Result:
    """Stackless bisection of one ray's segment (call under vmap for a packet).

    Args:
      test: ``test(s0, s1) -> BoxTest`` for this ray.
      d_max: int32 depth at which a possible piece counts as a hit (Eq. 6.19).
      active: bool, False for rays that miss the domain.
      max_steps: static bound on loop iterations (a ray that runs out reports no hit).
    """

    def cond(state):
        k, d, done, hit, steps = state
        return ~done & (steps < max_steps)

    def body(state):
        k, d, done, hit, steps = state
        w = piece_width(d)
        s0 = k.astype(jnp.float32) * w
        s1 = (k + 1).astype(jnp.float32) * w
        r = test(s0, s1)
        accept = r.possible & r.finite & ((d >= d_max) | r.small)
        descend = r.possible & ~accept & (d < d_max)
        # move on: k + 1, then pop the levels whose both halves are done
        k_next = k + 1
        pop = jnp.minimum(_trailing_zeros(k_next), d)
        k_next, d_next = k_next >> pop, d - pop
        k = jnp.where(accept, k, jnp.where(descend, 2 * k, k_next))
        d = jnp.where(accept, d, jnp.where(descend, d + 1, d_next))
        finished = accept | (~descend & (d_next == 0))
        return k, d, done | finished, hit | accept, steps + 1

    init = (jnp.int32(0), jnp.int32(0), ~active, jnp.bool_(False), jnp.int32(0))
    k, d, done, hit, steps = lax.while_loop(cond, body, init)
    hit = hit & done
    w = piece_width(d)
    s = jnp.where(hit, (k.astype(jnp.float32) + 0.5) * w, jnp.inf)
    return Result(s, hit, steps)


def k_bisect(test, k_enter, k_exit, d_max, active, max_steps: int) -> Result:
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
    Returns per-ray `Result` ([P]).
    """
    big = jnp.float32(3e38)
    lo = jnp.minimum(k_enter, k_exit)
    hi = jnp.maximum(k_enter, k_exit)
    forward = jnp.sum(jnp.where(active, k_exit - k_enter, 0.0)) >= 0.0
    K0 = jnp.where(forward, jnp.min(jnp.where(active, lo, big)),
                   jnp.max(jnp.where(active, hi, -big)))
    K1 = jnp.where(forward, jnp.max(jnp.where(active, hi, -big)),
                   jnp.min(jnp.where(active, lo, big)))
    span = K1 - K0
    dk = k_exit - k_enter
    safe_dk = jnp.where(dk == 0.0, 1.0, dk)
    # the slab width at depth d is |span| 2^-d; a ray needs its piece (in s) <= its eps
    ratio = jnp.abs(span) / jnp.maximum(jnp.abs(dk), 1e-30)
    d_need = jnp.where(active, d_max + jnp.ceil(jnp.log2(jnp.maximum(ratio, 1.0))), 0)
    d_stop = jnp.clip(jnp.max(d_need), 0, MAX_DEPTH).astype(jnp.int32)

    def pieces(k, d):
        w = piece_width(d)
        a = K0 + span * (k.astype(jnp.float32) * w)
        b = K0 + span * ((k + 1).astype(jnp.float32) * w)
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
        hit = hit | accept
        s_hit = jnp.where(accept, 0.5 * (s0 + s1), s_hit)
        live = live & ~accept
        descend = jnp.any(cand & ~accept) & (d < d_stop)
        k_next = k + 1
        pop = jnp.minimum(_trailing_zeros(k_next), d)
        k_next, d_next = k_next >> pop, d - pop
        end = ~descend & (d_next == 0)
        live = live & ~end
        k = jnp.where(descend, 2 * k, k_next)
        d = jnp.where(descend, d + 1, d_next)
        return k, d, live, hit, s_hit, steps + 1

    n = k_enter.shape
    init = (jnp.int32(0), jnp.int32(0), active, jnp.zeros(n, bool),
            jnp.full(n, jnp.inf, jnp.float32), jnp.int32(0))
    k, d, live, hit, s_hit, steps = lax.while_loop(cond, body, init)
    return Result(s_hit, hit, jnp.broadcast_to(steps, n))


def t_bisect_lanes(test, p, D, d_max, active, lanes: int, max_steps: int) -> Result:
    """t-bisection of a batch of rays [N] on `lanes` persistent lanes with refill.

    A batched while_loop runs until its slowest lane is done; here a lane that finishes
    its ray writes the result and takes the next ray from the queue (rays that miss the
    domain never enter it), so every iteration evaluates `lanes` useful boxes while the
    queue lasts. When it runs dry and few lanes are still busy, their rays move, with
    their (k, d) state, to a narrower loop (lanes / 8, down to 32), so the slow tail does
    not pay for idle lanes. Same per-ray algorithm and results as `t_bisect`.

    Args:
      test: ``test(p, D, s0, s1) -> BoxTest`` vectorised over lanes ([L] / [L, 3]).
      p, D: [N, 3] ray segment start and vector; d_max: [N] int32; active: [N] bool.
      lanes: static number of lanes L of the first phase.
      max_steps: static bound on iterations per ray.
    """
    n = p.shape[0]
    widths = [max(1, min(int(lanes), n))]
    while widths[-1] > 32:
        widths.append(max(32, widths[-1] // 8))
    queue = dict(idx=jnp.argsort(~active, stable=True).astype(jnp.int32),
                 k=jnp.zeros(n, jnp.int32), d=jnp.zeros(n, jnp.int32),
                 steps=jnp.zeros(n, jnp.int32))
    n_queue = jnp.sum(active).astype(jnp.int32)
    out = (jnp.full(n, jnp.inf, jnp.float32), jnp.zeros(n, bool), jnp.zeros(n, jnp.int32))
    for i, width in enumerate(widths):
        last = i == len(widths) - 1
        stop_live = 0 if last else widths[i + 1]
        out, queue, n_queue = _lanes_phase(test, p, D, d_max, queue, n_queue, out, width,
                                           stop_live, max_steps)
    return Result(*out)


def _lanes_phase(test, p, D, d_max, queue, n_queue, out, width: int, stop_live: int,
                 max_steps: int, refill_every: int = 4):
    """Run queued rays (with their bisection state) on `width` lanes until the queue is
    empty and at most `stop_live` lanes are busy; return the busy lanes as a queue.

    Lanes step `refill_every` times between refills (a lane that finishes early idles):
    measured on the 2-core CPU (Barth sextic, IA, 512^2, 4096 lanes) 1 -> 0.42, 2 -> 0.68,
    4 -> 0.82, 8 -> 0.80 Mrays/s with identical hits (benchmarks/NOTES.md)."""
    n = p.shape[0]
    q_len = queue["idx"].shape[0]

    def load(slot):
        live = slot < n_queue
        j = jnp.minimum(slot, q_len - 1)
        idx = queue["idx"][j]
        return dict(idx=idx, live=live, p=p[idx], D=D[idx], dmax=d_max[idx],
                    k=queue["k"][j], d=queue["d"][j], steps=queue["steps"][j],
                    done=jnp.zeros_like(live), hit=jnp.zeros_like(live))

    def step(_, ln):
        k, d = ln["k"], ln["d"]
        busy = ln["live"] & ~ln["done"]
        w = piece_width(d)
        r = test(ln["p"], ln["D"], k.astype(jnp.float32) * w, (k + 1).astype(jnp.float32) * w)
        accept = r.possible & r.finite & ((d >= ln["dmax"]) | r.small)
        descend = r.possible & ~accept & (d < ln["dmax"])
        k_next = k + 1
        pop = jnp.minimum(_trailing_zeros(k_next), d)
        k_next, d_next = k_next >> pop, d - pop
        steps = ln["steps"] + 1
        done = accept | (~descend & (d_next == 0)) | (steps >= max_steps)
        # an accepted ray keeps (k, d) of its hit piece
        k_new = jnp.where(accept, k, jnp.where(descend, 2 * k, k_next))
        d_new = jnp.where(accept, d, jnp.where(descend, d + 1, d_next))
        return dict(ln, k=jnp.where(busy, k_new, k), d=jnp.where(busy, d_new, d),
                    steps=jnp.where(busy, steps, ln["steps"]),
                    done=ln["done"] | (busy & done), hit=ln["hit"] | (busy & accept))

    def cond(st):
        nxt, ln, _ = st
        return (nxt < n_queue) | (jnp.sum(ln["live"] & ~ln["done"]) > stop_live)

    def body(st):
        nxt, ln, (s_out, hit_out, steps_out) = st
        ln = lax.fori_loop(0, refill_every, step, ln)
        finished = ln["live"] & ln["done"]
        # finished rays write their result (the others scatter out of bounds: dropped)
        target = jnp.where(finished, ln["idx"], n)
        w = piece_width(ln["d"])
        s_hit = jnp.where(ln["hit"], (ln["k"].astype(jnp.float32) + 0.5) * w, jnp.inf)
        s_out = s_out.at[target].set(s_hit, mode="drop")
        hit_out = hit_out.at[target].set(ln["hit"], mode="drop")
        steps_out = steps_out.at[target].set(ln["steps"], mode="drop")
        # refill finished lanes from the queue, in lane order
        fresh = load(nxt + jnp.cumsum(finished.astype(jnp.int32)) - 1)
        ln = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finished.reshape((-1,) + (1,) * (old.ndim - 1)),
                                       new, old), fresh, ln)
        return nxt + jnp.sum(finished).astype(jnp.int32), ln, (s_out, hit_out, steps_out)

    state = (jnp.int32(width), load(jnp.arange(width, dtype=jnp.int32)), out)
    _, ln, out = lax.while_loop(cond, body, state)
    busy = ln["live"] & ~ln["done"]
    order = jnp.argsort(~busy, stable=True)
    rest = dict(idx=ln["idx"][order], k=ln["k"][order], d=ln["d"][order],
                steps=ln["steps"][order])
    return out, rest, jnp.sum(busy).astype(jnp.int32)
