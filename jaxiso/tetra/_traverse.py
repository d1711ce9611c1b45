"""Stackless traversal of the implicit BVH (seed Sec. 5.4) with skip pointers.

Nodes are in depth-first pre-order: the left child of an interior node is the next node
and `skip` jumps over a subtree. A ray goes down to the child nearer along the node's
split axis first and leaves a subtree by its octant's escape pointer (`_bvh`). One
`lax.while_loop` runs a packet of rays [P] (or persistent lanes with refill over a whole
image, `jaxiso._lanes`); every iteration each live ray looks at one node: it enters it
when the ray's box test passes within [t_min, best t so far] and the node's value range
holds an isovalue, otherwise skips it. A leaf's tets are intersected (under a `lax.cond`,
only when some ray of the packet is at a leaf) and the ray moves on by its escape; the loop
ends when every ray has left the last node.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._lanes import run_rays
from ._bvh import octant_of, right_first
from ._isopoly import isopolygon_hits

__all__ = ["traverse"]

BOX_SLACK = 2.0**-20  # relative widening of the ray's [near, far] through a node's box
SNAP = 2.0**-20  # vertex values this close to an isovalue, relative to max |value|, equal it


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
             lanes=None):
    """Nearest crossing of each ray with any isosurface of the linear tets.

    Args:
      bvh: `BVH` with bounds valid for `points`/`values`.
      points [V, 3], tets [T, 4], values [V]: the mesh at one time step.
      isovalues: [K]; o, d: [P, 3]; t_min, t_max: [P].
      max_steps: iteration bound per ray (default 2 N + 8, enough to visit every node
        once).
      lanes: None: one `while_loop` over the packet; an int: persistent lanes with refill
        over the packet (`jaxiso._lanes`; for a whole image). Same results.

    Returns:
      t [P] (inf on a miss), hit [P], which [P] isovalue index (-1), tet [P] (-1),
      nodes [P] nodes visited, leaves [P] leaves intersected (work counters).
    """
    n_nodes = bvh.skip.shape[0]
    if max_steps is None:
        max_steps = 2 * n_nodes + 8
    p = o.shape[0]
    # one snapping distance for the whole mesh (see isopolygon_hits)
    snap = SNAP * jnp.max(jnp.abs(values))
    state = dict(o=o, inv_d=1.0 / d,  # inf on axis-parallel rays: see _box_enter
                 d=d, t_min=t_min, t_max=t_max, octant=octant_of(d),
                 node=jnp.where(t_min <= t_max, 0, n_nodes).astype(jnp.int32),
                 t=jnp.full(p, jnp.inf, jnp.float32), which=jnp.full(p, -1, jnp.int32),
                 tet=jnp.full(p, -1, jnp.int32), nodes=jnp.zeros(p, jnp.int32),
                 leaves=jnp.zeros(p, jnp.int32))

    def step(s):
        return _step(bvh, points, tets, values, isovalues, snap, s)

    out = run_rays(step, lambda s: s["node"] < n_nodes, state, _RESULTS,
                   max_steps=max_steps, steps="nodes", lanes=lanes)
    hit = jnp.isfinite(out["t"])
    return out["t"], hit, out["which"], out["tet"], out["nodes"], out["leaves"]


_RESULTS = ("t", "which", "tet", "nodes", "leaves")


def _step(bvh, points, tets, values, isovalues, snap, s):
    """One node visit of every ray of the state (rays past the last node unchanged)."""
    n_nodes = bvh.skip.shape[0]
    leaf_size = bvh.leaf_size
    slots = jnp.arange(leaf_size, dtype=jnp.int32)
    o, d, t_min, t_max = s["o"], s["d"], s["t_min"], s["t_max"]
    p = o.shape[0]
    live = s["node"] < n_nodes
    node = jnp.minimum(s["node"], n_nodes - 1)
    lo, hi = bvh.lo[node], bvh.hi[node]
    holds = jnp.any((lo[:, 3:4] <= isovalues) & (isovalues <= hi[:, 3:4]), axis=-1)
    enter = live & holds & _box_enter(o, s["inv_d"], lo[:, :3], hi[:, :3], t_min,
                                      jnp.minimum(t_max, s["t"]))
    count = bvh.count[node]
    leaf = enter & (count > 0)

    def intersect_leaf(_):
        slot = jnp.minimum(bvh.first[node][:, None] + slots, bvh.order.shape[0] - 1)
        tet_ids = bvh.order[slot]                                    # [P, L]
        used = leaf[:, None] & (slots[None, :] < count[:, None])
        ids = tets[tet_ids]                                          # [P, L, 4]
        pts = points[ids]
        vals = values[ids]
        best_t = jnp.full(tet_ids.shape, jnp.inf, jnp.float32)
        best_k = jnp.full(tet_ids.shape, -1, jnp.int32)
        for k in range(isovalues.shape[0]):
            t_k, _ = isopolygon_hits(o, d, pts, vals, ids, isovalues[k], snap)
            ok = used & (t_k >= t_min[:, None]) & (t_k <= t_max[:, None]) & (t_k < best_t)
            best_t = jnp.where(ok, t_k, best_t)
            best_k = jnp.where(ok, k, best_k)
        j = jnp.argmin(best_t, axis=-1)
        t_leaf = jnp.take_along_axis(best_t, j[:, None], -1)[:, 0]
        k_leaf = jnp.take_along_axis(best_k, j[:, None], -1)[:, 0]
        tet_leaf = jnp.take_along_axis(tet_ids, j[:, None], -1)[:, 0]
        return t_leaf, k_leaf, tet_leaf

    t_leaf, k_leaf, tet_leaf = jax.lax.cond(
        jnp.any(leaf), intersect_leaf,
        lambda _: (jnp.full(p, jnp.inf, jnp.float32), jnp.full(p, -1, jnp.int32),
                   jnp.full(p, -1, jnp.int32)), None)
    better = leaf & (t_leaf < s["t"])
    down = enter & (count == 0)
    # near child first: the ray's best t then culls more of the far one
    left = jnp.minimum(node + 1, n_nodes - 1)
    near = jnp.where(right_first(bvh.split_axis[node].astype(jnp.int32), s["octant"]),
                     bvh.skip[left], left)
    nxt = jnp.where(down, near, bvh.escape[s["octant"], node])
    return dict(s, node=jnp.where(live, nxt, s["node"]),
                t=jnp.where(better, t_leaf, s["t"]),
                which=jnp.where(better, k_leaf, s["which"]),
                tet=jnp.where(better, tet_leaf, s["tet"]),
                nodes=s["nodes"] + live.astype(jnp.int32),
                leaves=s["leaves"] + leaf.astype(jnp.int32))
