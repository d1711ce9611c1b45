"""Ray-isopolygon intersection inside linear tetrahedra (seed Sec. 5.3).

The field is linear in a tet, so its isosurface there is a planar polygon: the marching-tets
case (which of the 4 vertices lie above the isovalue, 16 cases) names the 3 or 4 edges it
cuts, in cyclic order. The ray hits the polygon where it crosses the plane inside every
edge's half-space. The seed tests the half-spaces in 2D after projecting onto the plane;
here each edge's test is the sign of d . ((a - o) x (b - o)), the same half-space seen from
the ray, because that value is computed from the edge's two points alone: a neighbouring
tet that shares the polygon edge computes the same number with the opposite sign, so a ray
through a shared edge is accepted by one of them or (exactly on it) by both, never by
neither. Edge points are interpolated from the lower global vertex index to the higher, so
both tets produce bit-identical points.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["CASE_EDGES", "CASE_SIZES", "isopolygon_hits", "tet_gradient"]

_TET_EDGES = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def _case_table():
    """[16, 4] edge indices (into _TET_EDGES) of each case's polygon in cyclic order
    (the 4th repeats the 3rd for triangles) and [16] polygon sizes (0, 3 or 4). Bit i of
    the case is set when vertex i is above the isovalue (value > iso)."""
    edge_id = {e: k for k, e in enumerate(_TET_EDGES)}
    edge_id.update({(b, a): k for (a, b), k in edge_id.items()})
    table = np.zeros((16, 4), np.int32)
    sizes = np.zeros(16, np.int32)
    for case in range(16):
        above = [v for v in range(4) if case >> v & 1]
        below = [v for v in range(4) if not case >> v & 1]
        if len(above) in (1, 3):
            lone = above[0] if len(above) == 1 else below[0]
            others = [v for v in range(4) if v != lone]
            edges = [edge_id[(lone, v)] for v in others]
            table[case] = edges + edges[-1:]
            sizes[case] = 3
        elif len(above) == 2:
            (a0, a1), (b0, b1) = above, below
            table[case] = [edge_id[(a0, b0)], edge_id[(a0, b1)], edge_id[(a1, b1)],
                           edge_id[(a1, b0)]]
            sizes[case] = 4
    return table, sizes


CASE_EDGES, CASE_SIZES = _case_table()
_EDGE_ENDS = np.array(_TET_EDGES, np.int32)


def tet_gradient(p, f):
    """Gradient [..., 3] of the linear field with values f [..., 4] at vertices p [..., 4, 3]
    (zero for a flat tet)."""
    e = p[..., 1:, :] - p[..., :1, :]                                   # [..., 3, 3]
    df = f[..., 1:] - f[..., :1]
    c1 = jnp.cross(e[..., 1, :], e[..., 2, :])
    c2 = jnp.cross(e[..., 2, :], e[..., 0, :])
    c3 = jnp.cross(e[..., 0, :], e[..., 1, :])
    det = jnp.sum(e[..., 0, :] * c1, axis=-1)
    num = df[..., 0, None] * c1 + df[..., 1, None] * c2 + df[..., 2, None] * c3
    ok = det != 0
    return jnp.where(ok[..., None], num / jnp.where(ok, det, 1.0)[..., None], 0.0)


def isopolygon_hits(o, d, p, f, ids, iso, snap=0.0):
    """Ray parameters where rays cross the isosurface `iso` of linear tets.

    Args:
      o, d: [P, 3] rays (broadcast against the tet axis M).
      p: [P, M, 4, 3] tet vertex positions; f: [P, M, 4] vertex values; ids: [P, M, 4]
        global vertex indices (they fix the interpolation direction of shared edges).
      iso: scalar isovalue.
      snap: vertex values within `snap` of iso count as equal to it (pass one value for
        the whole mesh, e.g. 2^-20 of its largest |value|: the decision is then made per
        vertex and neighbours agree). Without it a value a rounding away from iso makes
        polygon edges shorter than their points' rounding, with sides of random sign.

    Returns:
      t [P, M] (inf where the ray misses the polygon or the tet has none), and the
      marching-tets case [P, M] int32.
    """
    f = jnp.where(jnp.abs(f - iso) <= snap, iso, f)
    above = (f > iso).astype(jnp.int32)
    case = above[..., 0] + 2 * above[..., 1] + 4 * above[..., 2] + 8 * above[..., 3]
    edges = jnp.asarray(CASE_EDGES)[case]                                # [P, M, 4]
    ends = jnp.asarray(_EDGE_ENDS)[edges]                                # [P, M, 4, 2]
    # orient every edge from its lower global vertex id to the higher one
    ia = jnp.take_along_axis(ids, ends[..., 0], axis=-1)
    ib = jnp.take_along_axis(ids, ends[..., 1], axis=-1)
    swap = ia > ib
    lo_end = jnp.where(swap, ends[..., 1], ends[..., 0])
    hi_end = jnp.where(swap, ends[..., 0], ends[..., 1])
    pa = jnp.take_along_axis(p, lo_end[..., None], axis=-2)              # [P, M, 4, 3]
    pb = jnp.take_along_axis(p, hi_end[..., None], axis=-2)
    fa = jnp.take_along_axis(f, lo_end, axis=-1)
    fb = jnp.take_along_axis(f, hi_end, axis=-1)
    denom = fb - fa
    w = jnp.where(denom != 0, (iso - fa) / jnp.where(denom != 0, denom, 1.0), 0.0)
    # w is exactly 0 or 1 at an end on the isovalue: return that end bit-exactly
    verts = jnp.where((w == 1)[..., None], pb, pa + w[..., None] * (pb - pa))  # [P, M, 4, 3]
    rel = verts - o[:, None, None, :]
    # Each polygon edge's side value is computed with its two points in a canonical order
    # (by the global ids of the tet edges they lie on) and negated if the polygon runs the
    # other way: a neighbour sharing the edge evaluates the very same expression, so the
    # two values are exact negatives even where the compiler fuses a * b - c * d into FMAs
    # (which breaks the antisymmetry of a plain cross product).
    key_lo = jnp.minimum(ia, ib)
    key_hi = jnp.maximum(ia, ib)
    nxt = jnp.roll(rel, -1, axis=-2)
    nxt_lo, nxt_hi = jnp.roll(key_lo, -1, axis=-1), jnp.roll(key_hi, -1, axis=-1)
    forward = (key_lo < nxt_lo) | ((key_lo == nxt_lo) & (key_hi <= nxt_hi))
    first = jnp.where(forward[..., None], rel, nxt)
    second = jnp.where(forward[..., None], nxt, rel)
    side = jnp.sum(d[:, None, None, :] * jnp.cross(first, second), axis=-1)   # [P, M, 4]
    side = jnp.where(forward, side, -side)
    # a triangle repeats its 3rd vertex: the 4th edge is degenerate and ignored
    side = jnp.where((jnp.asarray(CASE_SIZES)[case] == 3)[..., None]
                     & (jnp.arange(4) == 2), 0.0, side)
    # an edge whose two points coincide (both on edges out of a vertex at the isovalue)
    # lies on no side: exactly 0, not the rounding left by a fused a * b - c * d
    same = jnp.all(verts == jnp.roll(verts, -1, axis=-2), axis=-1)
    side = jnp.where(same, 0.0, side)
    inside = jnp.all(side >= 0, axis=-1) | jnp.all(side <= 0, axis=-1)
    # a polygon collapsed to a point (the isovalue at a lone vertex) covers nothing
    inside = inside & jnp.any(side != 0, axis=-1)
    has_poly = jnp.asarray(CASE_SIZES)[case] > 0
    grad = tet_gradient(p, f)
    slope = jnp.sum(grad * d[:, None, :], axis=-1)
    f_o = f[..., 0] + jnp.sum(grad * (o[:, None, :] - p[..., 0, :]), axis=-1)
    ok = inside & has_poly & (slope != 0)
    t = jnp.where(ok, (iso - f_o) / jnp.where(slope != 0, slope, 1.0), jnp.inf)
    return t, case
