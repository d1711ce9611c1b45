"""Stackless traversal of the implicit BVH (seed Sec. 5.4) with skip pointers.

Nodes are in depth-first pre-order: the left child of an interior node is the next node
and `skip` jumps over a subtree. A ray goes down to the child nearer along the node's
split axis first and leaves a subtree by its octant's escape pointer (`_bvh`). One
`lax.while_loop` runs a packet of rays [P] (or persistent lanes with refill over a whole
image, `jaxiso._lanes`); every iteration each walking ray looks at one node: it enters it
when the ray's box test passes within [t_min, best t so far] and the node's value range
holds an isovalue, otherwise skips it. A ray that enters a leaf takes its escape and waits
until enough of the packet's busy rays wait (`LEAF_FILL`), and then all waiting rays have
their leaves tested together in one pass of the leaf test (under a `lax.cond`; as in Aila
and Laine's 2009 "while-while" GPU traversal: the pass costs as much for one ray as for
the whole packet). The loop ends when every ray has left the last node and has no leaf
waiting.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .._lanes import run_rays
from ._bvh import octant_of, right_first
from ._isopoly import isopolygon_hits

__all__ = ["traverse"]

BOX_SLACK = 2.0**-20  # relative widening of the ray's [near, far] through a node's box
SNAP = 2.0**-20  # vertex values this close to an isovalue, relative to max |value|, equal it
LEAF_FILL = 0.5  # see traverse


def _box_enter(o, inv_d, lo, hi, t0, t1):
    """[P] bool: rays o + t d meet the boxes [lo, hi] [P, 3] for some t in [t0, t1]."""
    ta = (lo - o) * inv_d
    tb = (hi - o) * inv_d
    near = jnp.max(jnp.where(jnp.isnan(ta), -jnp.inf, jnp.minimum(ta, tb)), axis=-1)
    far = jnp.min(jnp.where(jnp.isnan(tb), jnp.inf, jnp.maximum(ta, tb)), axis=-1)
    # widened by a few ulps: a hit on a tet's edge or vertex can lie on the box's face, and
    # the slab arithmetic must not round it out (the test only culls)
    near = near - BOX_SLACK * jnp.abs(near)
    far = far + BOX_SLACK * jnp.abs(far)
    return (jnp.maximum(near, t0) <= jnp.minimum(far, t1))


def traverse(bvh, points, tets, values, isovalues, o, d, t_min, t_max, *, max_steps=None,
             lanes=None, leaf_fill=LEAF_FILL):
    """Nearest crossing of each ray with any isosurface of the linear tets.

    Args:
      bvh: `BVH` with bounds valid for `points`/`values`.
      points [V, 3], tets [T, 4], values [V]: the mesh at one time step.
      isovalues: [K]; o, d: [P, 3]; t_min, t_max: [P].
      max_steps: bound on the nodes a ray visits (default 2 N + 8: every node once).
      lanes: None: one `while_loop` over the packet; an int: persistent lanes with refill
        over the packet (`jaxiso._lanes`; for a whole image). Same results.
      leaf_fill: a ray that enters a leaf waits there until at least this fraction of the
        busy rays wait at a leaf, and then all their leaves are tested at once (one pass
        of the leaf test instead of one per ray). 0 tests as soon as any ray waits, 1 only
        when every busy ray waits. Same results whatever the fraction; the default 0.5
        measured fastest (benchmarks/NOTES.md).

    Returns:
      t [P] (inf on a miss), hit [P], which [P] isovalue index (-1), tet [P] (-1),
      nodes [P] nodes visited, leaves [P] leaves intersected (work counters).
    """
    n_nodes = bvh.links.shape[0]
    if max_steps is None:
        max_steps = 2 * n_nodes + 8
    p = o.shape[0]
    # one snapping distance for the whole mesh (see isopolygon_hits)
    snap = SNAP * jnp.max(jnp.abs(values))
    state = dict(o=o, inv_d=1.0 / d,  # inf on axis-parallel rays: see _box_enter
                 d=d, t_min=t_min, t_max=t_max, octant=octant_of(d),
                 node=jnp.where(t_min <= t_max, 0, n_nodes).astype(jnp.int32),
                 leaf_first=jnp.zeros(p, jnp.int32), leaf_count=jnp.zeros(p, jnp.int32),
                 t=jnp.full(p, jnp.inf, jnp.float32), which=jnp.full(p, -1, jnp.int32),
                 tet=jnp.full(p, -1, jnp.int32), nodes=jnp.zeros(p, jnp.int32),
                 leaves=jnp.zeros(p, jnp.int32))

    def walking(s):
        return (s["node"] < n_nodes) & (s["nodes"] < max_steps)

    def busy(s):
        return walking(s) | (s["leaf_count"] > 0)

    def step(s):
        return _step(bvh, points, tets, values, isovalues, snap, leaf_fill, walking, s)

    # `walking` bounds each ray's nodes; the loop's own bound only guards termination:
    # every iteration tests the waiting rays' leaves or moves a walking ray, at most
    # 2 P max_steps in all (lanes: one more than a ray's bound, so it is never reached)
    bound = min(2 * p * max_steps + 1, 2**31 - 1) if lanes is None else max_steps + 1
    out = run_rays(step, busy, state, _RESULTS, max_steps=bound, steps="nodes",
                   lanes=lanes)
    hit = jnp.isfinite(out["t"])
    return out["t"], hit, out["which"], out["tet"], out["nodes"], out["leaves"]


_RESULTS = ("t", "which", "tet", "nodes", "leaves")


def _leaf_hits(bvh, points, tets, values, isovalues, snap, s):
    """(t [P], isovalue index [P], tet [P]) of the nearest hit among the tets of each ray's
    waiting leaf (`order[leaf_first:][:leaf_count]`; count 0: none) within its [t_min,
    t_max]."""
    slots = jnp.arange(bvh.leaf_size, dtype=jnp.int32)
    o, d, t_min, t_max = s["o"], s["d"], s["t_min"], s["t_max"]
    slot = jnp.minimum(s["leaf_first"][:, None] + slots, bvh.order.shape[0] - 1)
    tet_ids = bvh.order[slot]                                            # [P, L]
    used = slots[None, :] < s["leaf_count"][:, None]
    ids = tets[tet_ids]                                                  # [P, L, 4]
    pts = points[ids]
    vals = values[ids]
    # A tet whose values (widened by the snap) miss an isovalue has no polygon of it, so
    # pass j tests each slot's j-th held isovalue, and only while some slot holds j + 1:
    # as many passes as the most isovalues one tet of the pass holds, not one per
    # isovalue, with the same hits.
    lo, hi = jnp.min(vals, axis=-1)[..., None], jnp.max(vals, axis=-1)[..., None]
    holds = used[..., None] & (isovalues - hi <= 2 * snap) & (lo - isovalues <= 2 * snap)
    rank = jnp.cumsum(holds, axis=-1)                                     # [P, L, K]
    t = jnp.full(used.shape, jnp.inf, jnp.float32)
    k = jnp.full(used.shape, -1, jnp.int32)
    for j in range(isovalues.shape[0]):
        pick = holds & (rank == j + 1)
        has = jnp.any(pick, axis=-1)
        index = jnp.argmax(pick, axis=-1).astype(jnp.int32)
        one = functools.partial(_slot_hits, o, d, pts, vals, ids, isovalues[index], snap,
                                has, t_min, t_max, index, t, k)
        t, k = one() if j == 0 else jax.lax.cond(jnp.any(has), one, lambda: (t, k))
    j = jnp.argmin(t, axis=-1)[:, None]
    return (jnp.take_along_axis(t, j, -1)[:, 0], jnp.take_along_axis(k, j, -1)[:, 0],
            jnp.take_along_axis(tet_ids, j, -1)[:, 0])


def _slot_hits(o, d, pts, vals, ids, iso, snap, used, t_min, t_max, index, best_t,
               best_k):
    """Fold the hits of isovalue `iso` [P, L] (one per leaf slot, scene index `index`)
    into the nearest hit so far per slot (best_t [P, L], best_k [P, L], -1: none): slots
    that are `used`, crossings within the ray's [t_min, t_max]."""
    t, _ = isopolygon_hits(o, d, pts, vals, ids, iso, snap)
    ok = used & (t >= t_min[:, None]) & (t <= t_max[:, None]) & (t < best_t)
    return jnp.where(ok, t, best_t), jnp.where(ok, index, best_k)


def _step(bvh, points, tets, values, isovalues, snap, leaf_fill, walking, s):
    """One iteration over the rays of the state: rays waiting at a leaf have it tested when
    enough of them wait (`leaf_fill`); every other walking ray visits one node."""
    n_nodes = bvh.links.shape[0]
    p = s["o"].shape[0]
    waiting = s["leaf_count"] > 0
    walk = walking(s) & ~waiting
    n_wait = jnp.sum(waiting)
    fire = (n_wait > 0) & (n_wait >= leaf_fill * jnp.sum(walk | waiting))
    t_leaf, k_leaf, tet_leaf = jax.lax.cond(
        fire, lambda: _leaf_hits(bvh, points, tets, values, isovalues, snap, s),
        lambda: (jnp.full(p, jnp.inf, jnp.float32), jnp.full(p, -1, jnp.int32),
                 jnp.full(p, -1, jnp.int32)))
    tested = fire & waiting
    better = tested & (t_leaf < s["t"])

    # one float row and one int row per node (`_bvh` layout)
    node = jnp.minimum(s["node"], n_nodes - 1)
    bounds, links = bvh.bounds[node], bvh.links[node]                   # [P, 8], [P, 12]
    lo, hi = bounds[:, :4], bounds[:, 4:]
    holds = jnp.any((lo[:, 3:4] <= isovalues) & (isovalues <= hi[:, 3:4]), axis=-1)
    enter = walk & holds & _box_enter(s["o"], s["inv_d"], lo[:, :3], hi[:, :3], s["t_min"],
                                      jnp.minimum(s["t_max"], s["t"]))
    kind = links[:, 0]
    at_leaf = enter & (kind > 0)
    down = enter & (kind < 0)
    # near child first: the ray's best t then culls more of the far one
    split = jnp.maximum(-kind - 1, 0)
    near = jnp.where(right_first(split, s["octant"]), links[:, 2], node + 1)
    escape = jnp.take_along_axis(links, 4 + s["octant"][:, None], axis=1)[:, 0]
    nxt = jnp.where(down, near, escape)
    # a ray at a leaf moves past it now and waits there until the leaf is tested
    count = jnp.where(tested, 0, jnp.where(at_leaf, kind, s["leaf_count"]))
    first = jnp.where(at_leaf, links[:, 1], s["leaf_first"])
    return dict(s, node=jnp.where(walk, nxt, s["node"]), leaf_first=first, leaf_count=count,
                t=jnp.where(better, t_leaf, s["t"]),
                which=jnp.where(better, k_leaf, s["which"]),
                tet=jnp.where(better, tet_leaf, s["tet"]),
                nodes=s["nodes"] + walk.astype(jnp.int32),
                leaves=s["leaves"] + at_leaf.astype(jnp.int32))
