"""Ray-isopolygon intersection inside linear tetrahedra (seed Sec. 5.3).

The field is linear in a tet, so its isosurface there is a planar polygon: the marching-tets
case (which of the 4 vertices lie above the isovalue, 16 cases) names the 3 or 4 edges it
cuts, in cyclic order. The ray hits the polygon where it crosses the plane inside every
edge's half-space. The seed tests the half-spaces in 2D after projecting onto the plane;
here each edge's test is the sign of d . ((a - o) x (b - o)), the same half-space seen from
the ray, because that value is computed from the edge's two points alone: a neighbouring
tet that shares the polygon edge computes the same number with the opposite sign. Edge
points are interpolated from the lower global vertex index to the higher, so both tets
produce bit-identical points.

Those points are rounded to float32, and the side value rounds too, so where the exact
answer is within rounding of 0 (a ray through a polygon corner, or along a silhouette edge
where both polygons sharing it lie on one side as seen from the ray) the signs alone can
reject the ray in every tet around the point. A side within a bound on its rounding
therefore counts as 0 (the ray touches the edge): a ray through a shared edge is accepted
by one of the two tets or, near it, by both, never by neither, and a ray more than a few
float32 roundings outside a polygon is still rejected. Polygons of zero area (the isovalue
touched at a vertex or along a tet edge) and rays parallel to the polygon's plane up to
rounding get no hit there: the tets around them hold the surface.
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
# a polygon edge's side value within this much of its rounding scale counts as 0 (errors
# measured on rays aimed at polygon edges stay below 2^-24 of that scale)
SIDE_ROUNDING = 2.0**-22
# a ray's slope through a tet's field within this much of its magnitude bound counts as 0
SLOPE_ROUNDING = 2.0**-20


def tet_gradient(p, f):
    """Gradient [..., 3] of the linear field with values f [..., 4] at vertices p [..., 4, 3]
    (zero for a flat tet)."""
    return _gradient_and_scale(p, f)[0]


def _gradient_and_scale(p, f):
    """`tet_gradient` [..., 3] and the scale [..., 3] of its rounding: the same sum with
    absolute values, so that g . d is 0 up to rounding where |g . d| <~ eps |d| . scale."""
    e = p[..., 1:, :] - p[..., :1, :]                                   # [..., 3, 3]
    df = f[..., 1:] - f[..., :1]
    c1 = jnp.cross(e[..., 1, :], e[..., 2, :])
    c2 = jnp.cross(e[..., 2, :], e[..., 0, :])
    c3 = jnp.cross(e[..., 0, :], e[..., 1, :])
    det = jnp.sum(e[..., 0, :] * c1, axis=-1)
    num = df[..., 0, None] * c1 + df[..., 1, None] * c2 + df[..., 2, None] * c3
    num_scale = (jnp.abs(df[..., 0, None] * c1) + jnp.abs(df[..., 1, None] * c2)
                 + jnp.abs(df[..., 2, None] * c3))
    ok = (det != 0)[..., None]
    safe_det = jnp.where(ok, det[..., None], 1.0)
    return (jnp.where(ok, num / safe_det, 0.0),
            jnp.where(ok, num_scale / jnp.abs(safe_det), 0.0))


def isopolygon_hits(o, d, p, f, ids, iso, snap=0.0):
    """Ray parameters where rays cross the isosurface `iso` of linear tets, by the closed
    rule: the level set {F = iso} within each tet, including a face, edge or vertex that
    touches the isovalue from one side.

    "Above" is value > iso, except in a tet with no vertex above, where it is value >= iso:
    the > case misses a face at iso whose tet lies below it, the >= case one whose tet lies
    above, and where vertices lie on both sides the two cases give the same polygon (a
    vertex at iso is a point of it either way). A tet with one value throughout has none.

    Args:
      o, d: [P, 3] rays (broadcast against the tet axis M).
      p: [P, M, 4, 3] tet vertex positions; f: [P, M, 4] vertex values; ids: [P, M, 4]
        global vertex indices (they fix the interpolation direction of shared edges).
      iso: scalar isovalue.
      snap: vertex values within `snap` of iso count as equal to it. Pass one value for the
        whole mesh (e.g. 2^-20 of its largest |value|) so that the decision is per vertex
        and neighbours agree: without it a value a rounding away from iso makes polygon
        edges shorter than their points' rounding.

    Returns:
      t [P, M] (inf where the ray misses the polygon or the tet has none), and the
      marching-tets case [P, M] int32 (bit i: vertex i above).
    """
    f = jnp.where(jnp.abs(f - iso) <= snap, iso, f)
    strictly = f > iso
    above = jnp.where(jnp.any(strictly, axis=-1, keepdims=True), strictly, f >= iso)
    above = above.astype(jnp.int32)
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
    # a point's key names what it lies on: its tet edge (global ids, low first), or the
    # vertex itself when it is an end, which every tet edge out of the vertex then agrees on
    key_lo = jnp.where(w == 1, jnp.maximum(ia, ib), jnp.minimum(ia, ib))
    key_hi = jnp.where(w == 0, jnp.minimum(ia, ib), jnp.maximum(ia, ib))
    side, tolerance = _edge_sides(o, d, verts, key_lo, key_hi,
                                  jnp.max(jnp.abs(p), axis=(-2, -1)))
    # a side within rounding of 0 counts as 0: the ray touches that edge
    inside = jnp.all(side >= -tolerance, axis=-1) | jnp.all(side <= tolerance, axis=-1)
    # a polygon collapsed to a point or a segment (the isovalue at a vertex or along a tet
    # edge, the rest on one side) covers nothing: the tets around it hold the surface, if
    # any, and the side test would accept rays near the segment's whole line
    distinct = (key_lo != jnp.roll(key_lo, -1, axis=-1)) | (key_hi != jnp.roll(key_hi, -1,
                                                                                axis=-1))
    has_poly = jnp.sum(distinct, axis=-1) >= 3
    grad, grad_scale = _gradient_and_scale(p, f)
    slope = jnp.sum(grad * d[:, None, :], axis=-1)
    f_o = f[..., 0] + jnp.sum(grad * (o[:, None, :] - p[..., 0, :]), axis=-1)
    # a ray parallel to the plane up to rounding (it lies in it: every side is ~0 too) has
    # no single crossing; its t would be noise. The tets around take it where it leaves
    # the plane.
    parallel = jnp.abs(slope) <= SLOPE_ROUNDING * jnp.sum(
        jnp.abs(d)[:, None, :] * grad_scale, axis=-1)
    ok = inside & has_poly & ~parallel
    t = jnp.where(ok, (iso - f_o) / jnp.where(slope != 0, slope, 1.0), jnp.inf)
    return t, case


def _edge_sides(o, d, verts, key_lo, key_hi, coord_scale):
    """Side of the ray o + t d [P, 3] of each polygon edge, from point k to point k + 1.

    Args:
      verts: [P, M, 4, 3] polygon points in cyclic order (a triangle repeats its 3rd);
        key_lo, key_hi: [P, M, 4] what each lies on (global ids); coord_scale: [P, M]
        largest |coordinate| of the tet (the scale of the points' rounding).

    Returns:
      side [P, M, 4] (one sign inside, exactly 0 on an edge of coinciding points) and
      tolerance [P, M, 4] >= 0, the bound on its rounding.
    """
    # (a - r) . ((b - a) x d), with r the point of the ray nearest a, is computed with the
    # edge's two points a, b in a canonical order (by key) and negated if the polygon runs
    # the other way: a neighbour sharing the edge evaluates the very same expression, so
    # the two values are exact negatives even where the compiler fuses a * b - c * d into
    # FMAs (which breaks the antisymmetry of a plain cross product). It equals
    # d . ((a - o) x (b - o)) for any r on the ray, but a - r is short, so it rounds in
    # proportion to a's distance from the ray, not to its distance from the ray origin
    # (which along a grazing edge swamps the value).
    nxt_lo, nxt_hi = jnp.roll(key_lo, -1, axis=-1), jnp.roll(key_hi, -1, axis=-1)
    forward = ((key_lo < nxt_lo) | ((key_lo == nxt_lo) & (key_hi <= nxt_hi)))[..., None]
    nxt_verts = jnp.roll(verts, -1, axis=-2)
    first = jnp.where(forward, verts, nxt_verts)
    edge = jnp.where(forward, nxt_verts, verts) - first
    dd = d[:, None, None, :]
    first_rel = first - o[:, None, None, :]
    inv_dd = 1.0 / jnp.sum(d * d, axis=-1)[:, None, None, None]
    offset = first_rel - (jnp.sum(first_rel * dd, axis=-1, keepdims=True) * inv_dd) * dd
    normal = jnp.cross(edge, dd)                                         # [P, M, 4, 3]
    side = jnp.sum(offset * normal, axis=-1)
    side = jnp.where(forward[..., 0], side, -side)
    # The bound covers the products (on the short offset) and the rounding of the offset
    # and of the interpolated points, on the scale of a - o and of the tet's coordinates:
    # a shift s of a changes the side by s . normal. A neighbour may compute the bound
    # differently: any bound >= 0 on both sides keeps the shared edge closed.
    abs_normal = jnp.abs(normal)
    bound = (jnp.sum(jnp.abs(first_rel) * abs_normal, axis=-1)
             + 4.0 * coord_scale[..., None] * jnp.sum(abs_normal, axis=-1)
             + _l1(offset) * _l1(edge) * _l1(d)[:, None, None])
    return side, SIDE_ROUNDING * bound


def _l1(v):
    """[...] sum of |components| of v [..., 3]."""
    return jnp.sum(jnp.abs(v), axis=-1)
