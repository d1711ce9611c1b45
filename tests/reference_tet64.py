"""Independent float64 numpy reference for ray-isosurface hits in tetrahedral meshes.

Brute force, no acceleration structure, deliberately not importing jaxiso, so tests can check
the BVH traversal and the isopolygon intersection against it.

Method (`first_hits`): each tet's barycentric coordinates are affine functions
lambda_i(x) = g_i . x + h_i, built from the plane of the face opposite vertex i (cross
products, float64). Along a ray lambda_i(t) = alpha_i + beta_i t, so the ray's parameter
interval inside the tet is where every lambda_i(t) >= -tol (closed half-spaces, `tol` a tiny
barycentric slack, so a ray through a shared face, edge or vertex is inside every tet meeting
there and no hit is lost to rounding). That interval is intersected with [t_min, t_max] and
the clip box; the linear field is evaluated at both ends from the barycentric coordinates and
the linear equation f(t) = iso solved on it. An end value within `value_tol` (relative to
the tet's largest |value - iso|) of the isovalue counts as a root there, because "exactly at
iso" does not survive rounding in the barycentric evaluation, nor the slack `tol` (which
can extrapolate f by ~4 tol times the tet's value spread). The answer is the nearest root
over all tets and isovalues. Only exact, conservative culling happens first: tets whose value
range holds no isovalue, and (ray, tet) pairs whose ray line misses the tet's bounding sphere.

Limitations, by design:
  * with tol > 0 a ray passing within ~tol * (tet size) outside a tet still sees it, so a hit
    can lie that far outside its tet; `tet` is one of the tets at the hit point (ties between
    tets sharing a face go to the lowest index among the tets kept after culling, i.e. the
    lowest original index);
  * a tet with one value throughout has no surface (its level set is all of it or nothing);
  * a ray whose range ends within value_tol of a surface (relative, in value) counts as a hit
    at that end;
  * tets with |6 volume| <= 1e-10 * (longest edge)^3 are skipped;
  * a ray with an all-zero direction is a miss.
"""

import numpy as np

_FACES = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # face opposite vertex i
_TET_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_DEGENERATE_REL = 1e-10
# ray x tet pairs per chunk of the bounding-sphere pass (a few [rays, tets] float64 arrays)
_CHUNK_ELEMENTS = 2**18


def barycentric_planes(points, tets):
    """Affine barycentric functions of each tet and its volume.

    Returns (g [T, 4, 3], h [T, 4], six_volume [T]) with lambda_i(x) = g_i . x + h_i, which
    is 1 at vertex i and 0 on the opposite face; six_volume is signed (positive when
    dot(b - a, cross(c - a, d - a)) > 0). Degenerate tets give non-finite g, h.
    """
    p = np.asarray(points, np.float64)[np.asarray(tets, np.int64)]        # [T, 4, 3]
    g = np.empty(p.shape)
    h = np.empty(p.shape[:2])
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, (a, b, c) in enumerate(_FACES):
            normal = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])       # [T, 3]
            height = np.einsum("tk,tk->t", normal, p[:, i] - p[:, a])     # +-6 volume
            g[:, i] = normal / height[:, None]
            h[:, i] = -np.einsum("tk,tk->t", g[:, i], p[:, a])
    six_volume = np.einsum("tk,tk->t", p[:, 1] - p[:, 0],
                           np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    return g, h, six_volume


def _nondegenerate(points, tets, six_volume):
    p = np.asarray(points, np.float64)[np.asarray(tets, np.int64)]
    longest = np.max([np.linalg.norm(p[:, j] - p[:, i], axis=-1) for i, j in _TET_EDGES], 0)
    return np.abs(six_volume) > _DEGENERATE_REL * longest**3


def clip_interval(origins, directions, t_min=0.0, t_max=np.inf, clip_box=None):
    """Per-ray parameter interval [t0, t1] allowed by [t_min, t_max] and a closed box.

    clip_box: None or (lo [3], hi [3]). A zero direction component leaves that slab open when
    the origin lies in it and empties the interval otherwise. Returns (t0 [N], t1 [N]); an
    empty interval has t0 > t1.
    """
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    t0 = np.full(o.shape[0], float(t_min))
    t1 = np.full(o.shape[0], float(t_max))
    if clip_box is None:
        return t0, t1
    lo, hi = (np.asarray(b, np.float64) for b in clip_box)
    for axis in range(3):
        oa, da = o[:, axis], d[:, axis]
        moving = da != 0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (lo[axis] - oa) / da
            tb = (hi[axis] - oa) / da
        t0 = np.where(moving, np.maximum(t0, np.minimum(ta, tb)), t0)
        t1 = np.where(moving, np.minimum(t1, np.maximum(ta, tb)), t1)
        outside = ~moving & ((oa < lo[axis]) | (oa > hi[axis]))
        t1 = np.where(outside, -np.inf, t1)
    return t0, t1


def _near_pairs(centre, radius, o, d):
    """(ray, tet) pairs whose ray line passes within a tet's bounding sphere [P], [P].

    A conservative, cheap [n, T] pre-filter (matrix products), so the exact per-face test runs
    on few pairs; the margin covers the rounding of the expanded squared distances.
    """
    dd = np.einsum("nk,nk->n", d, d)[:, None]
    oc = o @ centre.T                                                     # [n, T]
    along = d @ centre.T - np.einsum("nk,nk->n", o, d)[:, None]           # (c - o) . d
    oo = np.einsum("nk,nk->n", o, o)[:, None]
    cc = np.einsum("tk,tk->t", centre, centre)[None]
    dist2_dd = (oo - 2.0 * oc + cc) * dd - along**2                       # |(c - o) x d|^2
    margin = 1e-8 * (oo + cc) + 1e-12
    return np.nonzero(dist2_dd <= (radius[None] ** 2 + margin) * dd)


def _ray_tet_intervals(g, h, centre, radius, o, d, t_lo, t_hi, tol):
    """Pairs (ray, tet) whose closed, slack-widened tet interval meets the ray's range.

    Returns (ray [P], tet [P], t0 [P], t1 [P], lambda0 [P, 4], lambda1 [P, 4]): the clipped
    interval and the barycentric coordinates at its ends.
    """
    ray, tet = _near_pairs(centre, radius, o, d)
    alpha = np.einsum("pk,pik->pi", o[ray], g[tet]) + h[tet]              # lambda at t = 0
    beta = np.einsum("pk,pik->pi", d[ray], g[tet])                        # d lambda / dt
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = (-tol - alpha) / beta                                     # lambda_i = -tol
    enter = np.max(np.where(beta > 0, bound, -np.inf), axis=-1, initial=-np.inf)
    leave = np.min(np.where(beta < 0, bound, np.inf), axis=-1, initial=np.inf)
    parallel_outside = np.any((beta == 0) & (alpha < -tol), axis=-1)
    t0 = np.maximum(enter, t_lo[ray])
    t1 = np.minimum(leave, t_hi[ray])
    keep = (t0 <= t1) & ~parallel_outside & np.isfinite(t0) & np.isfinite(t1)
    ray, tet, t0, t1, alpha, beta = ray[keep], tet[keep], t0[keep], t1[keep], alpha[keep], \
        beta[keep]
    return ray, tet, t0, t1, alpha + beta * t0[:, None], alpha + beta * t1[:, None]


def _roots_in_chunk(g, h, centre, radius, vals, o, d, t_lo, t_hi, isovalues, tol, value_tol):
    """Nearest root per ray of a chunk: (t [n], which [n], tet [n]) with inf / -1 for none."""
    ray, tet, t0, t1, lam0, lam1 = _ray_tet_intervals(g, h, centre, radius, o, d, t_lo, t_hi,
                                                      tol)
    v = vals[tet]                                                         # [P, 4]
    # f = v0 + sum_i lambda_i (v_i - v0): exact for a constant field, whatever sum(lambda) is
    dv = v[:, 1:] - v[:, :1]
    constant = np.all(dv == 0, axis=1)
    f0 = v[:, 0] + np.einsum("pi,pi->p", lam0[:, 1:], dv)                 # field at entry
    f1 = v[:, 0] + np.einsum("pi,pi->p", lam1[:, 1:], dv)                 # field at exit

    cand_t, cand_k, cand_tet, cand_ray = [], [], [], []
    for k, iso in enumerate(isovalues):
        slack = value_tol * np.max(np.abs(v - iso), axis=1)
        e0 = np.where(np.abs(f0 - iso) <= slack, 0.0, f0 - iso)
        e1 = np.where(np.abs(f1 - iso) <= slack, 0.0, f1 - iso)
        # closed rule: a root where f - iso changes sign or is 0 at an end; a tet with one
        # value throughout has no surface (its level set is all of it or nothing)
        crosses = (((e0 <= 0) & (e1 >= 0)) | ((e0 >= 0) & (e1 <= 0))) & ~constant
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(e0 != e1, e0 / (e0 - e1), 0.0)   # equal ends: both 0, root at entry
        t = t0 + np.clip(s, 0.0, 1.0) * (t1 - t0)
        cand_t.append(t[crosses])
        cand_k.append(np.full(crosses.sum(), k))
        cand_tet.append(tet[crosses])
        cand_ray.append(ray[crosses])
    cand_t, cand_k, cand_tet, cand_ray = (np.concatenate(c) for c in
                                          (cand_t, cand_k, cand_tet, cand_ray))
    # per ray the nearest t; ties to the lower isovalue index, then the lower tet index
    order = np.lexsort((cand_tet, cand_k, cand_t, cand_ray))
    first = order[np.r_[True, cand_ray[order][1:] != cand_ray[order][:-1]]] if order.size \
        else order
    best_t = np.full(o.shape[0], np.inf)
    best_which = np.full(o.shape[0], -1)
    best_tet = np.full(o.shape[0], -1)
    best_t[cand_ray[first]] = cand_t[first]
    best_which[cand_ray[first]] = cand_k[first]
    best_tet[cand_ray[first]] = cand_tet[first]
    return best_t, best_which, best_tet


def first_hits(points, tets, values, rays_o, rays_d, isovalues, *, t_min=0.0, t_max=np.inf,
               clip_box=None, tol=1e-9, value_tol=5e-8):
    """Nearest ray-isosurface hits of a piecewise-linear field on a tet mesh, float64.

    Args:
      points [V, 3], tets [T, 4] (any orientation), values [V]: the mesh and vertex values.
      rays_o, rays_d [N, 3]: rays o + t d (d need not be unit; t is in its units).
      isovalues: scalar or [K].
      t_min, t_max: closed parameter range; clip_box: None or (lo [3], hi [3]) -- only the
        part of each ray inside this closed box is searched.
      tol: barycentric slack of the inside test; value_tol: relative slack of "an end value
        equals the isovalue" (see the module docstring).
    Returns:
      t [N] float64 (inf for a miss), hit [N] bool, which [N] int (index into isovalues, the
      lowest on ties, -1 for a miss), tet [N] int (original tet index, -1 for a miss).
    """
    isovalues = np.atleast_1d(np.asarray(isovalues, np.float64))
    tets = np.asarray(tets, np.int64)
    vals = np.asarray(values, np.float64)[tets]                           # [T, 4]
    g, h, six_volume = barycentric_planes(points, tets)
    # linear interpolation never leaves [min, max] of the vertex values, so a tet whose range
    # holds no isovalue has no root (exact culling, not an approximation)
    vmin, vmax = vals.min(axis=1), vals.max(axis=1)
    holds_iso = np.any((vmin[:, None] <= isovalues) & (isovalues <= vmax[:, None]), axis=1)
    kept = np.flatnonzero(holds_iso & _nondegenerate(points, tets, six_volume))
    g, h, vals = g[kept], h[kept], vals[kept]
    corners = np.asarray(points, np.float64)[tets[kept]]                  # [T', 4, 3]
    centre = corners.mean(axis=1)
    # the tol-widened tet is the tet scaled by 1 + 4 tol about its centroid
    radius = np.linalg.norm(corners - centre[:, None], axis=-1).max(axis=1) * (1 + 4 * tol)

    o = np.asarray(rays_o, np.float64).reshape(-1, 3)
    d = np.asarray(rays_d, np.float64).reshape(-1, 3)
    t_lo, t_hi = clip_interval(o, d, t_min, t_max, clip_box)
    t_hi = np.where(np.any(d != 0, axis=1), t_hi, -np.inf)               # zero direction: miss

    n = o.shape[0]
    t = np.full(n, np.inf)
    which = np.full(n, -1)
    tet = np.full(n, -1)
    if kept.size:
        step = max(1, _CHUNK_ELEMENTS // kept.size)
        for s in range(0, n, step):
            sl = slice(s, s + step)
            t[sl], which[sl], local = _roots_in_chunk(g, h, centre, radius, vals, o[sl], d[sl],
                                                      t_lo[sl], t_hi[sl], isovalues, tol,
                                                      value_tol)
            tet[sl] = np.where(local >= 0, kept[np.maximum(local, 0)], -1)
    hit = np.isfinite(t)
    return t, hit, np.where(hit, which, -1), np.where(hit, tet, -1)


def interpolate(points, tets, values, tet, x):
    """Linear field of tet `tet[n]` at `x[n]` (extrapolated outside it), with barycentrics.

    Solves the 4x4 system [vertices; 1] lambda = [x; 1] per point (independent of
    `barycentric_planes`). Returns (f [N], lambda [N, 4]).
    """
    tets = np.asarray(tets, np.int64)[np.asarray(tet, np.int64)]
    p = np.asarray(points, np.float64)[tets]                              # [N, 4, 3]
    a = np.concatenate([np.swapaxes(p, 1, 2), np.ones((p.shape[0], 1, 4))], axis=1)
    rhs = np.concatenate([np.asarray(x, np.float64), np.ones((p.shape[0], 1))], axis=1)
    lam = np.linalg.solve(a, rhs[..., None])[..., 0]
    return np.einsum("ni,ni->n", lam, np.asarray(values, np.float64)[tets]), lam


def camera_rays(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov=40.0, width=256,
                height=None):
    """float64 pinhole rays with jaxiso's `Camera.look_at` convention, row-major flattened.

    forward = normalize(target - eye), right = normalize(cross(forward, up)),
    true_up = cross(right, forward); pixel (i row from the top, j column) looks along
    normalize(forward + sx tan(fov/2) (W/H) right + sy tan(fov/2) true_up) with
    sx = (j + 0.5) / W * 2 - 1, sy = 1 - (i + 0.5) / H * 2; fov is vertical, degrees.
    Returns (origins [H*W, 3], unit directions [H*W, 3]); pixel (i, j) is row i * W + j.
    """
    height = width if height is None else height
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right)
    true_up = np.cross(right, forward)
    scale = np.tan(np.radians(float(fov)) / 2.0)
    sx = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    sy = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    d = (forward + (sx[None, :, None] * scale * (width / height)) * right
         + (sy[:, None, None] * scale) * true_up).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(eye, d.shape).copy(), d


_STANDARD_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)


def marching_tets_case(values4, iso, *, ties_above=False):
    """Isopolygon of one tet, by brute force over its 6 edges.

    A vertex is "above" when value > iso (value >= iso with ties_above). Each edge joining an
    above and a below vertex carries one polygon vertex, so there are 0, 3 or 4.
    Returns (n, edges int [n, 2]): edges[m] = (below vertex, above vertex) of polygon vertex
    m, listed in cyclic order around the polygon (consecutive edges share a tet face) and
    wound so that, in a positively oriented tet, the right-hand normal points towards
    increasing values.
    """
    v = np.asarray(values4, np.float64)
    above = v >= iso if ties_above else v > iso
    crossing = [(i, j) if above[j] else (j, i) for i, j in _TET_EDGES if above[i] != above[j]]
    if not crossing:
        return 0, np.zeros((0, 2), np.int64)
    # walk the cycle: polygon edges lie on tet faces, i.e. join crossing edges sharing a vertex
    order = [crossing.pop(0)]
    while crossing:
        nxt = next(e for e in crossing if set(e) & set(order[-1]))
        crossing.remove(nxt)
        order.append(nxt)
    edges = np.array(order, np.int64)
    # winding depends only on which vertices are above, so check it on the standard tet with
    # values 0 / 1 (any positively oriented tet is an orientation-preserving affine image)
    corners = 0.5 * (_STANDARD_TET[edges[:, 0]] + _STANDARD_TET[edges[:, 1]])
    normal = np.sum(np.cross(corners, np.roll(corners, -1, axis=0)), axis=0)   # Newell
    gradient = above[1:].astype(np.float64) - float(above[0])     # of the 0/1 field there
    if normal @ gradient < 0:
        edges = edges[::-1]
    return len(edges), edges


def marching_tets_cases(*, ties_above=False):
    """All 16 cases: element c is `marching_tets_case` for vertex i above iff bit i of c."""
    cases = []
    for c in range(16):
        bits = np.array([(c >> i) & 1 for i in range(4)], np.float64)
        cases.append(marching_tets_case(bits, 0.5, ties_above=ties_above))
    return cases
