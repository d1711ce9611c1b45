"""Independent float64 numpy reference ray tracer for implicit surfaces.

Used by tests to check the JAX ray tracer; deliberately does not import jaxiso.

Method (`first_roots`): clip each ray to the axis-aligned box with the slab method, intersect
with [t_min, t_max], sample g_i = f - iso_i at `samples` + 1 uniformly spaced points of the
clipped segment [t0, t1], take the first sample interval in which some g_i changes sign (or is
exactly 0 at a sample), and refine that bracket by plain float64 bisection.

Limitations (why tests compare the JAX tracer with a tolerance, not exactly):
  * it only sees sign changes, so roots of even multiplicity (a ray tangent to the surface, a
    double root of f - iso) are invisible, and a ray that grazes a surface so closely that both
    crossings fall in one sample interval reports no hit (or a later one);
  * features thinner than the sample spacing (t1 - t0) / samples, e.g. two roots in one
    interval, are likewise missed;
  * NaN samples never count as a sign change: a root at the edge of a NaN region is only found
    if a finite sample lies on each side of it; a NaN met during bisection is treated like a
    sign opposite to the bracket's left end (the bracket moves towards smaller t), so a bracket
    whose interior touches a NaN region may converge to the NaN boundary;
  * accuracy in t is the bisection width, eps * (t1 - t0), not the float64 unit roundoff;
  * a ray with an all-zero direction (infinite clipped segment) is reported as a miss.
"""

import numpy as np

# points evaluated per pass over (rays x samples); bounds memory to a few times 32 MiB
_POINT_BUDGET = 2**22
_MAX_BISECTIONS = 200


def camera_rays(eye, target, up, fov_deg, width, height):
    """Pinhole camera rays, float64, row-major: returns (origins [H*W,3], directions [H*W,3]).

    Row 0 is the top of the image. Convention (shared with the JAX camera, keep exact):
        forward = normalize(target - eye)
        right   = normalize(cross(forward, up))
        true_up = cross(right, forward)
        aspect  = W / H,  s = tan(radians(fov_deg) / 2)   (fov_deg is the *vertical* fov)
        for pixel (i row, j col):
            d = forward + ((j + 0.5) / W * 2 - 1) * s * aspect * right
                        + (1 - (i + 0.5) / H * 2) * s * true_up
        direction = normalize(d); origin = eye.
    Pixel (i, j) is element i * W + j.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right)
    true_up = np.cross(right, forward)
    s = np.tan(np.radians(float(fov_deg)) / 2)
    aspect = width / height
    jj = np.arange(width, dtype=np.float64)
    ii = np.arange(height, dtype=np.float64)
    u = ((jj + 0.5) / width * 2 - 1) * s * aspect          # [W]
    v = (1 - (ii + 0.5) / height * 2) * s                  # [H]
    d = (forward[None, None, :] + u[None, :, None] * right[None, None, :]
         + v[:, None, None] * true_up[None, None, :])      # [H, W, 3]
    d = d.reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    origins = np.broadcast_to(eye, d.shape).copy()
    return origins, d


def clip_to_box(lo, hi, origins, directions, t_min=0.0, t_max=np.inf):
    """Slab clipping. Returns (t0 [N], t1 [N], valid [N]); valid iff t0 <= t1, both finite.

    The box is closed. A zero direction component leaves that slab unconstrained if the origin
    lies inside it (boundary included) and makes the ray miss otherwise.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    n = o.shape[0]
    t0 = np.full(n, float(t_min))
    t1 = np.full(n, float(t_max))
    valid = np.ones(n, dtype=bool)
    for a in range(3):
        da, oa = d[:, a], o[:, a]
        par = da == 0
        valid &= ~(par & ((oa < lo[a]) | (oa > hi[a])))
        safe = np.where(par, 1.0, da)
        ta = (lo[a] - oa) / safe
        tb = (hi[a] - oa) / safe
        near = np.where(par, -np.inf, np.minimum(ta, tb))
        far = np.where(par, np.inf, np.maximum(ta, tb))
        t0 = np.maximum(t0, near)
        t1 = np.minimum(t1, far)
    valid &= (t0 <= t1) & np.isfinite(t0) & np.isfinite(t1)
    return t0, t1, valid


def _eval(f, o, d, t, w):
    """f at o + t d; o, d [n,3], t [n, ...] -> float64 array of t's shape."""
    shape = t.shape
    ex = (slice(None),) + (None,) * (t.ndim - 1)
    with np.errstate(all="ignore"):
        x = o[:, 0][ex] + t * d[:, 0][ex]
        y = o[:, 1][ex] + t * d[:, 1][ex]
        z = o[:, 2][ex] + t * d[:, 2][ex]
        v = f(x, y, z, w)
    return np.broadcast_to(np.asarray(v, dtype=np.float64), shape)


def _first_interval(f, o, d, t0, t1, iso, w, samples):
    """First sample interval with a sign change / exact zero of any g_i, for n rays.

    Returns (k [n] int, -1 if none; qual [n, m] bool, which isovalues qualify in interval k;
    ga, gb [n, m] the g values at samples k and k+1)."""
    n, m = o.shape[0], iso.shape[0]
    k_found = np.full(n, -1, dtype=np.int64)
    qual = np.zeros((n, m), dtype=bool)
    ga = np.zeros((n, m))
    gb = np.zeros((n, m))
    active = np.arange(n)
    k0 = 0
    while k0 < samples and active.size:
        nb = max(1, min(samples - k0, _POINT_BUDGET // max(1, active.size * m) - 1))
        ks = np.arange(k0, k0 + nb + 1, dtype=np.float64)            # samples k0 .. k0+nb
        a0, a1 = t0[active], t1[active]
        t = a0[:, None] + (a1 - a0)[:, None] * (ks / samples)[None, :]  # [na, nb+1]
        v = _eval(f, o[active], d[active], t, w)
        g = v[:, :, None] - iso[None, None, :]                        # [na, nb+1, m]
        with np.errstate(invalid="ignore"):
            q = (g[:, :-1] * g[:, 1:] < 0) | (g[:, :-1] == 0) | (g[:, 1:] == 0)  # [na, nb, m]
        anyq = q.any(axis=2)                                          # [na, nb]
        hit = anyq.any(axis=1)
        first = np.argmax(anyq, axis=1)
        rows = np.nonzero(hit)[0]
        fi = first[rows]
        ids = active[rows]
        k_found[ids] = k0 + fi
        qual[ids] = q[rows, fi]
        ga[ids] = g[rows, fi]
        gb[ids] = g[rows, fi + 1]
        active = active[~hit]
        k0 += nb
    return k_found, qual, ga, gb


def _bisect(f, o, d, a, b, ga, iso, w, tol_world):
    """Plain bisection of g = f - iso on [a, b] (all arrays [p]); sign(g(a)) = sign(ga) != 0.

    Stops per bracket when its world length |d| (b - a) <= tol_world, or when float64 can no
    longer split it."""
    sa = np.sign(ga)
    dn = np.linalg.norm(d, axis=1)
    act = dn * (b - a) > tol_world
    for _ in range(_MAX_BISECTIONS):
        idx = np.nonzero(act)[0]
        if idx.size == 0:
            break
        ai, bi = a[idx], b[idx]
        mid = ai + 0.5 * (bi - ai)
        sm = np.sign(_eval(f, o[idx], d[idx], mid, w) - iso[idx])
        zero = sm == 0                                  # exact root: collapse the bracket
        right = (sm == sa[idx]) & ~zero                 # root lies in [mid, b]
        stuck = (mid <= ai) | (mid >= bi)               # no float64 between a and b
        a[idx] = np.where(stuck, ai, np.where(right | zero, mid, ai))
        b[idx] = np.where(stuck, bi, np.where(right, bi, mid))  # opposite sign, zero or NaN
        act[idx] = ~stuck & (dn[idx] * (b[idx] - a[idx]) > tol_world[idx])
    return 0.5 * (a + b)


def first_roots(f, lo, hi, origins, directions, *, isovalues=(0.0,), w=0.0, t_min=0.0,
                t_max=np.inf, eps=2.0**-22, samples=4096, chunk=4096):
    """First crossing of each ray with the level sets f = iso_i inside the box [lo, hi].

    f(x, y, z, w): vectorised float64 numpy function (NaN allowed; NaN samples never count as
    a sign change). lo, hi: 3-tuples. origins, directions: [N, 3] (directions need not be unit;
    point = o + t d). The ray is clipped to the box (slab method) and to [t_min, t_max], giving
    [t0, t1]; g_i = f - iso_i is sampled at `samples` + 1 uniform points of it, the first
    interval where any g_i changes sign (or is exactly 0 at a sample) is refined by bisection
    until its world length |d| dt <= eps * |d| (t1 - t0), and the bracket midpoint is returned.
    An exact zero at a sample returns that sample's t. If several isovalues qualify in the same
    first interval each is refined and the smallest t wins (ties: lowest index).

    Returns (t [N] float64, inf for no hit; which [N] int64, index of the isovalue hit, -1 for
    none). See the module docstring for limitations.
    """
    o_all = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d_all = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    iso = np.asarray(isovalues, dtype=np.float64).reshape(-1)
    samples = int(samples)
    if samples < 1 or iso.size == 0:
        raise ValueError("need samples >= 1 and at least one isovalue")
    n, m = o_all.shape[0], iso.size
    t_out = np.full(n, np.inf)
    which_out = np.full(n, -1, dtype=np.int64)
    t0_all, t1_all, valid_all = clip_to_box(lo, hi, o_all, d_all, t_min, t_max)
    for c0 in range(0, n, int(chunk)):
        sel = np.nonzero(valid_all[c0:c0 + chunk])[0] + c0
        if sel.size == 0:
            continue
        o, d, t0, t1 = o_all[sel], d_all[sel], t0_all[sel], t1_all[sel]
        k, qual, ga, gb = _first_interval(f, o, d, t0, t1, iso, w, samples)
        hit = k >= 0
        # candidate roots per (ray, isovalue); inf where that isovalue does not qualify
        cand = np.full((sel.size, m), np.inf)
        ka = t0[:, None] + (t1 - t0)[:, None] * (k[:, None] / samples)
        kb = t0[:, None] + (t1 - t0)[:, None] * ((k[:, None] + 1) / samples)
        ka, kb = np.broadcast_to(ka, cand.shape), np.broadcast_to(kb, cand.shape)
        qual &= hit[:, None]
        za = qual & (ga == 0)
        zb = qual & (gb == 0) & ~za
        br = qual & ~za & ~zb                     # strict sign change: bisect
        cand[za] = ka[za]
        cand[zb] = kb[zb]
        r, i = np.nonzero(br)
        if r.size:
            tol_world = eps * np.linalg.norm(d[r], axis=1) * (t1[r] - t0[r])
            cand[r, i] = _bisect(f, o[r], d[r], ka[r, i].copy(), kb[r, i].copy(), ga[r, i],
                                 iso[i], w, tol_world)
        best = np.argmin(cand, axis=1)
        tb = cand[np.arange(sel.size), best]
        ok = np.isfinite(tb)
        t_out[sel[ok]] = tb[ok]
        which_out[sel[ok]] = best[ok]
    return t_out, which_out


def first_change(member, origins, directions, t0, t1, *, w=0.0, eps=2.0**-22, samples=4096):
    """First change of a boolean membership along each ray inside its own segment [t0, t1].

    For CSG references: `member(x, y, z, w)` is a vectorised float64 numpy predicate (e.g.
    ``(se < 0) & (sc >= 0)`` for the region whose boundary is drawn); t0, t1 [N] are
    per-ray segment ends (inf or t0 > t1: no segment). member is sampled at `samples` + 1
    uniform points of [t0, t1]; the first sample interval whose two ends differ is refined
    by bisection on member (keeping ends of different membership) until its world length
    |d| dt <= eps |d| (t1 - t0), and the bracket midpoint is returned. Same limitations
    as `first_roots` (changes thinner than the sample spacing are missed).

    Returns t [N] float64, inf where member never changes on the segment.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    t0 = np.asarray(t0, dtype=np.float64).reshape(-1)
    t1 = np.asarray(t1, dtype=np.float64).reshape(-1)
    n = o.shape[0]
    t_out = np.full(n, np.inf)
    sel = np.nonzero(np.isfinite(t0) & np.isfinite(t1) & (t0 < t1))[0]
    if sel.size == 0:
        return t_out

    def m(idx, t):
        return _eval(lambda x, y, z, w: member(x, y, z, w).astype(np.float64),
                     o[idx], d[idx], t, w) > 0.5

    per = max(1, _POINT_BUDGET // (int(samples) + 1))
    ks = np.arange(int(samples) + 1, dtype=np.float64) / samples
    for c0 in range(0, sel.size, per):
        idx = sel[c0:c0 + per]
        a0, a1 = t0[idx], t1[idx]
        t = a0[:, None] + (a1 - a0)[:, None] * ks[None, :]
        v = m(idx, t)
        ch = v[:, :-1] != v[:, 1:]
        found = ch.any(axis=1)
        k = np.argmax(ch, axis=1)
        rows = np.nonzero(found)[0]
        if rows.size == 0:
            continue
        r_idx = idx[rows]
        a = t[rows, k[rows]].copy()
        b = t[rows, k[rows] + 1].copy()
        ma = v[rows, k[rows]]
        tol = eps * (t1[r_idx] - t0[r_idx])
        act = (b - a) > tol
        for _ in range(_MAX_BISECTIONS):
            j = np.nonzero(act)[0]
            if j.size == 0:
                break
            mid = a[j] + 0.5 * (b[j] - a[j])
            same = m(r_idx[j], mid) == ma[j]
            stuck = (mid <= a[j]) | (mid >= b[j])
            a[j] = np.where(stuck | ~same, a[j], mid)
            b[j] = np.where(stuck | same, b[j], mid)
            act[j] = ~stuck & ((b[j] - a[j]) > tol[j])
        t_out[r_idx] = 0.5 * (a + b)
    return t_out


def shell_segments(o, d, r_in, r_out):
    """Per ray (|d| = 1, t >= 0) the parameter ranges inside the shell
    r_in < |o + t d| < r_out, before and after the inner ball (empty when a > b)."""
    b = np.einsum("ij,ij->i", o, d)
    c = np.einsum("ij,ij->i", o, o)

    def ball(r):
        disc = b * b - (c - r * r)
        sq = np.sqrt(np.maximum(disc, 0.0))
        return np.where(disc > 0, -b - sq, np.inf), np.where(disc > 0, -b + sq, -np.inf)

    a_out, b_out = ball(r_out)
    a_in, b_in = ball(r_in)
    miss_in = ~np.isfinite(a_in)
    first = (np.maximum(a_out, 0.0), np.where(miss_in, b_out, a_in))
    second = (np.where(miss_in, np.inf, np.maximum(b_in, 0.0)),
              np.where(miss_in, -np.inf, b_out))
    return first, second


def catalogue_first_hits(name, f, parts, lo, hi, o, d, *, isovalues=(0.0,), w=0.0,
                         eps=2.0**-22):
    """First hit t (inf: none) of float64 rays with a catalogue entry, from its float64
    function f (reference64.SURFACES) or, for the CSG entries, its parts
    (reference64.CSG_PARTS): icos.csg draws the lattice ic inside the shell, whose walls
    only trim (first sign change of ic inside it); sesc.csg is the boundary of
    {se < 0} and {sc >= 0} (first change of membership)."""
    if name == "icos.csg":
        ic = parts["ic"]
        r_in = np.sqrt(parts["sphere_inner"](0.0, 0.0, 0.0))  # written r^2 - |p|^2
        r_out = np.sqrt(parts["sphere_outer"](0.0, 0.0, 0.0))
        t0, t1, _ = clip_to_box(lo, hi, o, d)
        out = np.full(o.shape[0], np.inf)
        for a, b in shell_segments(o, d, r_in, r_out):
            t = first_change(lambda x, y, z, w: ic(x, y, z, w) < 0, o, d,
                             np.maximum(a, t0), np.minimum(b, t1), w=w, eps=eps)
            out = np.where(np.isfinite(out), out, t)
        return out
    if name == "sesc.csg":
        se, sc = parts["se"], parts["sc"]
        t0, t1, ok = clip_to_box(lo, hi, o, d)
        return first_change(lambda x, y, z, w: (se(x, y, z, w) < 0) & (sc(x, y, z, w) >= 0),
                            o, d, np.where(ok, t0, np.inf), t1, w=w, eps=eps)
    t, _ = first_roots(f, lo, hi, o, d, isovalues=isovalues, w=w, eps=eps)
    return t
