"""Stackless ray traversal of a min/max hierarchy over voxel cells (seed Sec. 3.3.3, 4.4).

One `lax.while_loop` over a packet of rays [P] (or persistent lanes with refill over a
whole image, `jaxiso._lanes`). Each iteration, every active ray
  1. locates the current voxel cell `v` in the hierarchy, going down until a node whose
     [min, max] holds no isovalue (culled) or a cell to intersect (`Hierarchy.locate`);
  2. if it reached a cell, intersects the trilinear patch exactly (`_cell`), under a
     `lax.cond` so that packets where no ray reached a cell skip that work;
  3. otherwise (or on a miss) moves to the exit of the culled node or the cell.
Positions are integer voxel coordinates carried in the state, so a step never depends on
re-rounding a world-space point; the exit face of the node decides the next cell.

The hierarchy is pluggable: the octree volume (restart from the root, or neighbour
finding from the parent trace, Sec. 3.3.2.2) and the dense macrocell grid baseline
(Parker et al., Sec. 3.5.1) share everything below `locate`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._lanes import run_rays
from . import _cell

__all__ = ["traverse", "voxel_ray"]


def voxel_ray(origin, spacing, o, d):
    """World rays o + t d [P, 3] in voxel coordinates: q(t) = q0 + t dq (t unchanged)."""
    inv = 1.0 / spacing
    return (o - origin) * inv, d * inv


def _exit(q0, dq, lo, size, v):
    """Leave the cube [lo, lo + size] (voxel coords, int [P, 3]) along q0 + t dq: the exit
    t [P] and the integer cell just beyond the exit face(s). Axes the ray does not leave
    through keep the coordinate of the exit point, clamped to the cube (rounding must not
    move a ray sideways out of the node it is crossing)."""
    hi = lo + size
    plane = jnp.where(dq > 0, hi, lo).astype(jnp.float32)
    safe = jnp.where(dq == 0, 1.0, dq)
    t_axis = jnp.where(dq == 0, jnp.inf, (plane - q0) / safe)
    t_out = jnp.min(t_axis, axis=-1)
    leaving = t_axis == t_out[:, None]
    beyond = jnp.where(dq > 0, hi, lo - 1)
    along = jnp.floor(q0 + t_out[:, None] * dq).astype(jnp.int32)
    along = jnp.clip(along, lo, hi - 1)
    nxt = jnp.where(leaving, beyond, jnp.where(jnp.isfinite(t_out)[:, None], along, v))
    return t_out, nxt


# corners (c = 4a + 2b + c) on each face of the unit cell: _FACES[axis, side] -> [8] bool
_FACES = np.array([[[((c >> (2 - axis)) & 1) == side for c in range(8)] for side in (0, 1)]
                   for axis in range(3)])
_ON_FACE = 1e-5  # local-coordinate distance from a face that counts as on it


def _iso_face(corners, u, isovalues):
    """([P] bool, [P] int32): the local point u [P, 3] lies on a face of the cell whose four
    corners [P, 8] all equal an isovalue (which one: the first)."""
    equal = corners[:, :, None] == isovalues[None, None, :]                 # [P, 8, K]
    found = jnp.zeros(corners.shape[:1] + isovalues.shape, bool)
    for axis in range(3):
        for side in (0, 1):
            face = jnp.all(jnp.where(_FACES[axis, side][None, :, None], equal, True), axis=1)
            near = jnp.abs(u[:, axis] - side) <= _ON_FACE
            found = found | (face & near[:, None])
    return jnp.any(found, axis=-1), jnp.argmax(found, axis=-1).astype(jnp.int32)


def traverse(hierarchy, isovalues, q0, dq, t_start, t_end, *, method="neubauer",
             max_steps=None, lanes=None, offset=None):
    """First root of the trilinear field = any isovalue along each ray of a packet.

    Args:
      hierarchy: an object with `shape` (voxels per axis, static), `init(P)` -> extra
        state, `locate(extra, v, restart)` -> (bits [P] int32, at_cell [P] bool,
        extra), `cell(extra, v)` -> corners [P, 8] float32, and `ancestor(extra, v,
        v_next, bits)` -> extra (where to resume locating after a move).
      isovalues: [K] float32.
      q0, dq: [P, 3] rays in voxel coordinates.
      t_start, t_end: [P] the part of each ray to search (already clipped to the cells).
      method: cell root finder, "neubauer" | "analytic" (`_cell.first_root_multi`).
      max_steps: iteration bound per ray (default: enough to cross every cell once).
      lanes: None: one `while_loop` over the packet (until its slowest ray is done); an
        int: the rays run on that many persistent lanes with refill (`jaxiso._lanes`),
        for packets of a whole image. Same results.
      offset: None, or [3] int32: the hierarchy's cell (0, 0, 0) is cell `offset` of the
        frame q0 and dq are given in (a brick of a larger volume traced in the whole
        volume's voxel frame, so that its seams see the same float32 planes and entry t).

    Returns:
      t [P] (inf on a miss), hit [P], which [P] int32 (isovalue index, -1 on a miss),
      cell [P, 3] int32 (min corner of the hit cell, hierarchy indices), size [P] int32 (its edge in
      voxels, 1 unless level of detail chose a coarse cell), steps [P] int32.
    """
    shape = hierarchy.shape
    n_cells = jnp.array([max(s - 1, 0) for s in shape], jnp.int32)
    if max_steps is None:
        max_steps = 4 * sum(shape) + 64
    offset = jnp.zeros(3, jnp.int32) if offset is None else jnp.asarray(offset, jnp.int32)
    state = _start(hierarchy, n_cells, q0, dq, t_start, t_end, isovalues.shape[0], offset)

    def step(s):
        return _step(hierarchy, isovalues, method, n_cells, offset, s)

    out = run_rays(step, lambda s: s["going"], state, _RESULTS, max_steps=max_steps,
                   steps="steps", lanes=lanes)
    return tuple(out[k] for k in _RESULTS)


_RESULTS = ("t_hit", "hit", "which", "cell", "size", "steps")


def _start(hierarchy, n_cells, q0, dq, t_start, t_end, n_iso, offset):
    """Per-ray traversal state [P, ...] at the entry point. `side` [P, K] is the sign of
    F - isovalue where the ray left the last cell it intersected (0: not known yet)."""
    p = q0.shape[0]
    start = q0 + jnp.maximum(t_start, 0.0)[:, None] * dq
    start = jnp.where(jnp.isfinite(t_start)[:, None], q0 + t_start[:, None] * dq, start)
    v0 = jnp.clip(jnp.floor(start).astype(jnp.int32) - offset, 0,
                  jnp.maximum(n_cells - 1, 0))
    going = (t_start <= t_end) & jnp.all(n_cells > 0)
    return dict(q0=q0, dq=dq, t_end=t_end, t=jnp.where(going, t_start, jnp.inf), v=v0,
                going=going, hit=jnp.zeros(p, bool), t_hit=jnp.full(p, jnp.inf, jnp.float32),
                which=jnp.full(p, -1, jnp.int32), cell=v0, size=jnp.ones(p, jnp.int32),
                steps=jnp.zeros(p, jnp.int32), side=jnp.zeros((p, n_iso), jnp.int8),
                extra=hierarchy.init(p))


def _step(hierarchy, isovalues, method, n_cells, offset, s):
    """One traversal iteration of every ray of the state (rays not going are unchanged).
    Cells are indexed in the hierarchy (v, lo); q0 and dq are in the frame where the
    hierarchy's cell 0 is `offset`."""
    q0, dq, t_end = s["q0"], s["dq"], s["t_end"]
    p = q0.shape[0]
    live, v, t = s["going"], s["v"], s["t"]
    bits, at_cell, extra = hierarchy.locate(s["extra"], v, live)
    at_cell = at_cell & live
    size = jnp.left_shift(1, bits)
    lo = jnp.left_shift(jnp.right_shift(v, bits[:, None]), bits[:, None])
    t_out, v_next = _exit(q0, dq, lo + offset, size[:, None], v + offset)
    v_next = v_next - offset

    def intersect_cells(_):
        corners = hierarchy.cell(extra, lo, bits)
        return _cell_hits(corners, isovalues, method, s, lo + offset, size, t_out,
                          at_cell)

    t_root, found, which, side = jax.lax.cond(
        jnp.any(at_cell), intersect_cells,
        lambda _: (jnp.full(p, jnp.inf, jnp.float32), jnp.zeros(p, bool),
                   jnp.full(p, -1, jnp.int32), s["side"]), None)
    outside = jnp.any((v_next < 0) | (v_next >= n_cells), axis=-1)
    moving = live & ~found
    t_new = jnp.where(moving, jnp.maximum(t_out, t), t)
    still = moving & ~outside & (t_new <= t_end)
    extra = hierarchy.ancestor(extra, v, v_next, jnp.where(still, bits, 0))
    return dict(
        s, t=t_new, v=jnp.where(still[:, None], v_next, v), going=still,
        hit=s["hit"] | found, t_hit=jnp.where(found, t_root, s["t_hit"]),
        which=jnp.where(found, which, s["which"]),
        cell=jnp.where(found[:, None], lo, s["cell"]),
        size=jnp.where(found, size, s["size"]),
        steps=s["steps"] + live.astype(jnp.int32), side=side, extra=extra)


def _cell_hits(corners, isovalues, method, s, lo, size, t_out, at_cell):
    """(t_root, found, which, side) [P] of the rays of state `s` at their cells, the cubes
    [lo, lo + size] (in the rays' frame; size > 1 for a coarse, LOD, cell) with corners
    [P, 8], which they leave at t_out; rays not `at_cell` find nothing and keep their
    side."""
    q0, dq, t_end, t = s["q0"], s["dq"], s["t_end"], s["t"]
    scale = size.astype(jnp.float32)[:, None]
    s1 = jnp.maximum(jnp.minimum(t_out, t_end) - t, 0.0)
    p0 = jnp.clip((q0 + t[:, None] * dq - lo.astype(jnp.float32)) / scale, 0.0, 1.0)
    # relative to the cell's smallest corner: data with a large offset (CT values
    # ~1000 +- 1) keep their precision in the cubic's coefficients
    low = jnp.min(corners, axis=-1, keepdims=True)
    coeffs = _cell.ray_cubic(corners - low, p0, dq / scale)
    iso_rel = isovalues[None, :] - low
    s_root, found, which = _cell.first_root_multi(coeffs, iso_rel, s1, method=method)
    p1 = p0 + (s1 / scale[:, 0])[:, None] * dq / scale
    at_entry, k_entry, at_exit, k_exit, side = _face_roots(
        corners, coeffs, iso_rel, isovalues, s["side"], s1, p0, p1, found)
    s_root = jnp.where(at_entry, 0.0, jnp.where(found, s_root, s1))
    which = jnp.where(at_entry, k_entry, jnp.where(found, which, k_exit))
    found = found | at_entry | at_exit
    # a constant cell has no surface (its level set is all of it or nothing)
    varying = jnp.max(corners, axis=-1) > jnp.min(corners, axis=-1)
    found = found & at_cell & varying
    side = jnp.where(at_cell[:, None], side, s["side"])
    return jnp.where(found, t + s_root, jnp.inf), found, which.astype(jnp.int32), side


def _face_roots(corners, coeffs, iso_rel, isovalues, last_side, s1, p0, p1, found):
    """Roots on the cell's entry and exit faces that the root finder cannot see:
    (at_entry, k_entry, at_exit, k_exit) [P] (k: which isovalue) and side [P, K], the
    signs of F - isovalue at the exit (`last_side`: at the last cell's exit).

    Watertight across cells: the field is continuous, but this cell's value at its
    entry face and the last cell's at its exit face are two float32 evaluations of
    it. A root within rounding of the shared face can fall outside both cells'
    [0, s1] (a crack: one pixel of a 64^2 sample of the 256^3 mixing layer). A sign change
    between the last exit and this entry is a root at the entry, and a sign change
    over this cell that the root finder missed is a root at its exit
    (the root finder evaluates its ends its own way)."""
    a = _cell.normalise(coeffs, s1)
    entry = jnp.sign(coeffs[:, :1] - iso_rel)                        # [P, K]
    exit_ = jnp.sign(_cell.horner(a, 1.0)[:, None] - iso_rel)
    # (an end exactly at the isovalue is a root too: the closed rule)
    crack = (last_side.astype(jnp.float32) * entry < 0) | (entry == 0)
    missed = ~found[:, None] & ((entry * exit_ < 0) | (exit_ == 0))
    side = jnp.where(jnp.isfinite(exit_), exit_, 0.0).astype(jnp.int8)
    # a face whose 4 corners all equal an isovalue carries F = iso exactly, but a
    # float32 point on it rarely evaluates to exactly iso: where the ray enters or
    # leaves through such a face (the edge of a plateau of voxels at the isovalue,
    # common in integer data) the root is the face itself
    at_entry, k_entry = _iso_face(corners, p0, isovalues)
    at_exit, k_exit = _iso_face(corners, p1, isovalues)
    at_entry = at_entry | jnp.any(crack, axis=-1)
    k_entry = jnp.where(jnp.any(crack, axis=-1), jnp.argmax(crack, axis=-1), k_entry)
    at_exit = at_exit | jnp.any(missed, axis=-1)
    k_exit = jnp.where(jnp.any(missed, axis=-1), jnp.argmax(missed, axis=-1), k_exit)
    return at_entry, k_entry, at_exit, k_exit, side
