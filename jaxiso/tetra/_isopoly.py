"""Ray-isopolygon intersection inside linear tetrahedra (seed Sec. 5.3).

The field is linear in a tet, so its isosurface there is a planar polygon: the marching-tets
case (which of the 4 vertices lie above the isovalue, 16 cases) says which of the 6 edges
it cuts (3 or 4). Each polygon edge lies on a tet face whose vertices are not all on one
side, and joins the points on that face's two cut edges. Orienting every face's segment
with the above-side vertex on its left, seen from outside a positively oriented tet,
chains the segments head to tail around the polygon (`face_segments`), whatever the case.

The ray hits the polygon where it crosses the plane inside every edge's half-space. The
seed tests the half-spaces in 2D after projecting onto the plane; here each edge's test is
the sign of d . ((a - o) x (b - o)), the same half-space seen from the ray, because that
value is computed from the edge's two points alone: a neighbouring tet that shares the
polygon edge computes the same number with the opposite sign. Edge points are
interpolated from the lower global vertex index to the higher, so both tets produce
bit-identical points.

Those points are rounded to float32, and the side value rounds too, so where the exact
answer is within rounding of 0 (a ray through a polygon corner, or along a silhouette edge
where both polygons sharing it lie on one side as seen from the ray) the signs alone can
reject the ray in every tet around the point. A side within a bound on its rounding
therefore counts as 0 (the ray touches the edge): a ray through a shared edge is accepted
by one of the two tets or, near it, by both, never by neither, and a ray more than a few
float32 roundings outside a polygon is still rejected. Polygons of zero area (the isovalue
touched at a vertex or along a tet edge) and rays parallel to the polygon's plane up to
rounding get no hit there: the tets around them hold the surface.

The arithmetic is written per component on arrays of the batch shape (vectors are tuples
of 3 arrays, the 4 vertices, 6 edges and 4 faces unrolled): it is elementwise throughout,
so XLA fuses it into a few loops over the batch instead of one small kernel per step,
which on a CPU cost more than the arithmetic (measured in benchmarks/NOTES.md).
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["TET_EDGES", "FACES", "face_segments", "isopolygon_hits", "tet_gradient"]

TET_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
# the faces as vertex cycles seen from outside a tet with det[p1-p0, p2-p0, p3-p0] > 0
FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
_EDGE_OF = {**{e: k for k, e in enumerate(TET_EDGES)},
            **{(b, a): k for k, (a, b) in enumerate(TET_EDGES)}}
# a polygon edge's side value within this much of its rounding scale counts as 0 (errors
# measured on rays aimed at polygon edges stay below 2^-24 of that scale)
SIDE_ROUNDING = 2.0**-22
# a ray's slope through a tet's field within this much of its magnitude bound counts as 0
SLOPE_ROUNDING = 2.0**-20


def face_segments(above):
    """The polygon's edges, one per tet face, from the vertices' sides.

    Args:
      above: 4 bool arrays (vertex i above the isovalue), broadcast together.

    Returns:
      4 (cut, start, end) triples, one per face of `FACES`: cut (bool) when the face's
      vertices are on both sides, then the segment runs from the point on tet edge
      `start` to the point on edge `end` (indices into `TET_EDGES`, int32 arrays).
    """
    out = []
    for i, j, k in FACES:
        a_i, a_j, a_k = above[i], above[j], above[k]
        lone_i = (a_j == a_k) & (a_i != a_j)
        lone_j = (a_i == a_k) & (a_j != a_i)
        lone_k = (a_i == a_j) & (a_k != a_i)
        lone_above = jnp.where(lone_i, a_i, jnp.where(lone_j, a_j, a_k))
        # the lone vertex's incoming and outgoing cycle edges; the segment enters by the
        # incoming one when the lone vertex is above (it then lies on the left)
        e_ij, e_jk, e_ki = _EDGE_OF[i, j], _EDGE_OF[j, k], _EDGE_OF[k, i]
        e_in = jnp.where(lone_i, e_ki, jnp.where(lone_j, e_ij, e_jk))
        e_out = jnp.where(lone_i, e_ij, jnp.where(lone_j, e_jk, e_ki))
        out.append((lone_i | lone_j | lone_k, jnp.where(lone_above, e_in, e_out),
                    jnp.where(lone_above, e_out, e_in)))
    return out


def tet_gradient(p, f):
    """Gradient [..., 3] of the linear field with values f [..., 4] at vertices p [..., 4, 3]
    (zero for a flat tet)."""
    grad, _ = _gradient_and_scale(_vertices(p), _unstack(f, 4))
    return jnp.stack(grad, axis=-1)


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
    pv = _vertices(p)
    fv = [jnp.where(jnp.abs(x - iso) <= snap, iso, x) for x in _unstack(f, 4)]
    iv = _unstack(ids, 4)
    strictly = [x > iso for x in fv]
    some_strictly = strictly[0] | strictly[1] | strictly[2] | strictly[3]
    above = [jnp.where(some_strictly, s, x >= iso) for s, x in zip(strictly, fv)]
    case = sum(a.astype(jnp.int32) << i for i, a in enumerate(above))
    points = [_edge_point(pv, fv, iv, a, b, iso) for a, b in TET_EDGES]
    o3 = tuple(o[:, None, c] for c in range(3))
    d3 = tuple(d[:, None, c] for c in range(3))
    inside, has_poly = _in_polygon(o3, d3, pv, points, above)
    grad, grad_scale = _gradient_and_scale(pv, fv)
    slope = _dot(grad, d3)
    f_o = fv[0] + _dot(grad, _sub(o3, pv[0]))
    # a ray parallel to the plane up to rounding (it lies in it: every side is ~0 too) has
    # no single crossing; its t would be noise. The tets around take it where it leaves
    # the plane.
    parallel = jnp.abs(slope) <= SLOPE_ROUNDING * _dot(_abs(d3), grad_scale)
    ok = inside & has_poly & ~parallel
    t = jnp.where(ok, (iso - f_o) / jnp.where(slope != 0, slope, 1.0), jnp.inf)
    return t, case


def _in_polygon(o3, d3, pv, points, above):
    """(inside, has_poly) [P, M]: the rays o3 + t d3 pass through the isopolygon (every
    cut face's segment, `face_segments`, sees them on one side; a side within rounding of
    0 counts as 0: the ray touches that edge), and the polygon is one (3 or more distinct
    points) whose isovalue points on the tet edges are `points`."""
    coord_scale = _max([jnp.abs(x) for v in pv for x in v])
    inv_dd = 1.0 / _dot(d3, d3)
    lower, upper, distinct = None, None, 0
    for (i, j, k), (cut, start, end) in zip(FACES, face_segments(above)):
        face_edges = (_EDGE_OF[i, j], _EDGE_OF[j, k], _EDGE_OF[k, i])
        side, tolerance, length = _segment_side(
            o3, d3, inv_dd, _pick(points, start, face_edges),
            _pick(points, end, face_edges), coord_scale)
        # a face that is not cut adds no edge (side 0 passes both tests)
        side = jnp.where(cut, side, 0.0)
        lo_k, hi_k = side >= -tolerance, side <= tolerance
        lower = lo_k if lower is None else lower & lo_k
        upper = hi_k if upper is None else upper & hi_k
        distinct = distinct + (cut & length).astype(jnp.int32)
    # a polygon collapsed to a point or a segment (the isovalue at a vertex or along a tet
    # edge, the rest on one side) covers nothing: the tets around it hold the surface, if
    # any, and the side test would accept rays near the segment's whole line
    return lower | upper, distinct >= 3


def _edge_point(pv, fv, iv, a, b, iso):
    """The isovalue's point on tet edge (a, b), interpolated from its lower global vertex
    id to the higher, and what it lies on: (xyz tuple, key_lo, key_hi), the key being the
    edge's global ids (low first), or the vertex itself (twice) when the point is an end,
    which every tet edge out of that vertex then agrees on."""
    ia, ib = iv[a], iv[b]
    swap = ia > ib
    fa, fb = jnp.where(swap, fv[b], fv[a]), jnp.where(swap, fv[a], fv[b])
    pa = tuple(jnp.where(swap, y, x) for x, y in zip(pv[a], pv[b]))
    pb = tuple(jnp.where(swap, x, y) for x, y in zip(pv[a], pv[b]))
    denom = fb - fa
    w = jnp.where(denom != 0, (iso - fa) / jnp.where(denom != 0, denom, 1.0), 0.0)
    # w is exactly 0 or 1 at an end on the isovalue: return that end bit-exactly
    xyz = tuple(jnp.where(w == 1, y, x + w * (y - x)) for x, y in zip(pa, pb))
    low, high = jnp.minimum(ia, ib), jnp.maximum(ia, ib)
    return xyz, jnp.where(w == 1, high, low), jnp.where(w == 0, low, high)


def _segment_side(o, d, inv_dd, a, b, coord_scale):
    """Side of the ray o + t d of the polygon edge from point a to point b, with its
    rounding bound and whether the two points differ.

    Args:
      o, d: ray tuples; inv_dd: 1 / d.d; a, b: (xyz, key_lo, key_hi) points as made by
        `_edge_point`; coord_scale: largest |coordinate| of the tet (the scale of the
        points' rounding).

    Returns:
      side (one sign inside, exactly 0 for coinciding points), tolerance >= 0 (the bound on
      its rounding) and distinct (bool: the points' keys differ).
    """
    # (a - r) . ((b - a) x d), with r the point of the ray nearest a, is computed with the
    # edge's two points in a canonical order (by key) and negated if the polygon runs the
    # other way: a neighbour sharing the edge evaluates the very same expression, so the
    # two values are exact negatives even where the compiler fuses a * b - c * d into
    # FMAs (which breaks the antisymmetry of a plain cross product). It equals
    # d . ((a - o) x (b - o)) for any r on the ray, but a - r is short, so it rounds in
    # proportion to a's distance from the ray, not to its distance from the ray origin
    # (which along a grazing edge swamps the value).
    (pa, a_lo, a_hi), (pb, b_lo, b_hi) = a, b
    forward = (a_lo < b_lo) | ((a_lo == b_lo) & (a_hi <= b_hi))
    first = tuple(jnp.where(forward, x, y) for x, y in zip(pa, pb))
    edge = _sub(tuple(jnp.where(forward, y, x) for x, y in zip(pa, pb)), first)
    first_rel = _sub(first, o)
    along = _dot(first_rel, d) * inv_dd
    offset = tuple(r - along * c for r, c in zip(first_rel, d))
    normal = _cross(edge, d)
    side = _dot(offset, normal)
    side = jnp.where(forward, side, -side)
    # The bound covers the products (on the short offset) and the rounding of the offset
    # and of the interpolated points, on the scale of a - o and of the tet's coordinates:
    # a shift s of a changes the side by s . normal. A neighbour may compute the bound
    # differently: any bound >= 0 on both sides keeps the shared edge closed.
    abs_normal = _abs(normal)
    bound = (_dot(_abs(first_rel), abs_normal) + 4.0 * coord_scale * _l1(abs_normal)
             + _l1(offset) * _l1(edge) * _l1(d))
    distinct = (a_lo != b_lo) | (a_hi != b_hi)
    return side, SIDE_ROUNDING * bound, distinct


def _gradient_and_scale(pv, fv):
    """Gradient (tuple) of the linear field with values fv (4 arrays) at vertices pv (4
    tuples), and the scale (tuple) of its rounding: the same sum with absolute values, so
    that g . d is 0 up to rounding where |g . d| <~ eps |d| . scale. Zero for a flat tet."""
    e = [_sub(pv[i], pv[0]) for i in (1, 2, 3)]
    df = [fv[i] - fv[0] for i in (1, 2, 3)]
    c = [_cross(e[1], e[2]), _cross(e[2], e[0]), _cross(e[0], e[1])]
    det = _dot(e[0], c[0])
    ok = det != 0
    safe_det = jnp.where(ok, det, 1.0)
    grad, scale = [], []
    for axis in range(3):
        terms = [df[i] * c[i][axis] for i in range(3)]
        grad.append(jnp.where(ok, (terms[0] + terms[1] + terms[2]) / safe_det, 0.0))
        scale.append(jnp.where(ok, (jnp.abs(terms[0]) + jnp.abs(terms[1]) + jnp.abs(terms[2]))
                               / jnp.abs(safe_det), 0.0))
    return tuple(grad), tuple(scale)


def _vertices(p):
    """[..., 4, 3] -> 4 tuples of 3 arrays [...]."""
    return [tuple(p[..., i, c] for c in range(3)) for i in range(4)]


def _unstack(x, n):
    return [x[..., i] for i in range(n)]


def _pick(points, index, candidates):
    """The point (xyz, key_lo, key_hi) of `points` (one per tet edge) at `index`, which is
    one of the 3 edge indices `candidates`."""
    xyz, key_lo, key_hi = points[candidates[0]]
    for k in candidates[1:]:
        here = index == k
        xyz = tuple(jnp.where(here, y, x) for x, y in zip(xyz, points[k][0]))
        key_lo = jnp.where(here, points[k][1], key_lo)
        key_hi = jnp.where(here, points[k][2], key_hi)
    return xyz, key_lo, key_hi


def _sub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _abs(a):
    return tuple(jnp.abs(x) for x in a)


def _l1(a):
    return jnp.abs(a[0]) + jnp.abs(a[1]) + jnp.abs(a[2])


def _max(xs):
    out = xs[0]
    for x in xs[1:]:
        out = jnp.maximum(out, x)
    return out
