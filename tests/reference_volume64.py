"""Independent float64 brute-force ray caster for isosurfaces of trilinearly interpolated
volumes; the reference the JAX octree traversal is tested against. Imports nothing from jaxiso.

Conventions: ``data[i, j, k]`` is the voxel at world ``origin + (i, j, k) * spacing``; F is
the trilinear interpolant of the voxels over the box [origin, origin + (n - 1) * spacing];
cells touching a non-finite voxel are empty. A ray is ``o + t d`` (d need not be unit).

Method (`first_hits`), per ray, in index space q = (p - origin) / spacing (t is unchanged):
  1. clip the ray to the box [0, n - 1] and to [t_min, t_max] (slab method);
  2. collect every t where it crosses an interior grid plane q_a = i, sort: consecutive
     parameters bound sub-segments each inside one cell, found from the segment's midpoint;
  3. skip cells with a non-finite corner and constant cells (8 equal corners: the level
     set is the whole cell or nothing, not a surface); in the others sample g = F - iso
     at `samples` + 1 uniform points of the segment (both ends included), F from the cell's
     8 corners at the sample's local coordinates;
  4. the first sample where some g is exactly 0, or the first sample interval where some g
     changes sign, over the segments in order, is the hit; a sign change is refined by
     float64 bisection down to float64 resolution (100 halvings).
  Several isovalues: each is refined in its own first interval and the smallest t wins
  (ties: the lowest index).

Limitations (compare with tolerances, and pick test rays away from them):
  * only sign changes are seen, so a ray touching the surface (double root of the cubic
    F - iso along the segment) reports no hit, and two roots closer than the sample spacing
    (segment length / samples) within one cell are both missed;
  * a ray lying exactly in a grid plane is assigned the cell on the + side of that plane
    (the upper cell along the last axis in its final plane) for the NaN rule;
  * a ray with a zero direction, or one that only touches the box (t0 == t1), misses.
"""

import numpy as np

_POINT_BUDGET = 2**20   # sample points evaluated at once: bounds memory to some 100 MB
_BISECTIONS = 100       # halvings from a sample interval reach float64 resolution


def camera_rays(eye, target, up, fov_deg, width, height):
    """Pinhole rays (float64): (origins [H*W, 3], unit directions [H*W, 3]), pixel (row r,
    column c) at element r * W + c, row 0 at the top, fov vertical in degrees:

        forward = normalize(target - eye), right = normalize(forward x up),
        true_up = right x forward,  s = tan(fov / 2)
        ndc_x = (2 (c + 0.5) / W - 1) * s * W / H,   ndc_y = (1 - 2 (r + 0.5) / H) * s
        direction = normalize(forward + ndc_x right + ndc_y true_up)

    the convention of jaxiso's ``Camera.look_at(...).rays()`` (which computes in float32
    and returns [H, W, 3] arrays).
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    s = np.tan(np.deg2rad(float(fov_deg)) / 2.0)
    ndc_x = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * s * width / height
    ndc_y = (1.0 - 2.0 * (np.arange(height) + 0.5) / height) * s
    d = (forward + ndc_x[None, :, None] * right + ndc_y[:, None, None] * true_up)
    d = d.reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.tile(eye, (d.shape[0], 1)), d


def clip_to_index_box(q0, e, shape, t_min=0.0, t_max=np.inf):
    """Slab clipping of q0 + t e [N, 3] to the closed box [0, shape - 1] and [t_min, t_max].

    Returns (t0 [N], t1 [N], valid [N]); valid iff the ray crosses the box over a segment of
    positive length. A zero component of e keeps that slab iff q0 lies in it."""
    hi = np.asarray(shape, np.float64) - 1.0
    n = q0.shape[0]
    t0 = np.full(n, float(t_min))
    t1 = np.full(n, float(t_max))
    valid = np.any(e != 0, axis=1) & np.all(np.isfinite(q0) & np.isfinite(e), axis=1)
    for a in range(3):
        flat = e[:, a] == 0
        valid &= ~flat | ((q0[:, a] >= 0) & (q0[:, a] <= hi[a]))
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (0.0 - q0[:, a]) / e[:, a]
            tb = (hi[a] - q0[:, a]) / e[:, a]
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(flat, t1, np.minimum(t1, np.maximum(ta, tb)))
    valid &= (t0 < t1) & np.isfinite(t0) & np.isfinite(t1)
    return np.where(valid, t0, 0.0), np.where(valid, t1, 0.0), valid


def _segment_bounds(q0, e, t0, t1, shape):
    """Sorted parameters [R, M]: t0, every crossing of an interior plane q_a = i
    (0 < i < n_a - 1) inside (t0, t1), and t1; unused slots hold t1 (empty segments)."""
    parts = [t0[:, None]]
    for a in range(3):
        planes = np.arange(1, shape[a] - 1, dtype=np.float64)
        if planes.size == 0:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (planes[None, :] - q0[:, a, None]) / e[:, a, None]
        inside = (t > t0[:, None]) & (t < t1[:, None])
        parts.append(np.where(inside, t, t1[:, None]))
    parts.append(t1[:, None])
    return np.sort(np.concatenate(parts, axis=1), axis=1)


def _trilinear(corners, u):
    """Trilinear interpolation; corners [..., 8] with corner (di, dj, dk) at 4 di + 2 dj + dk,
    u [..., 3] local coordinates in the cell."""
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    c = [corners[..., m] for m in range(8)]
    x00 = c[0] + ux * (c[4] - c[0])
    x01 = c[1] + ux * (c[5] - c[1])
    x10 = c[2] + ux * (c[6] - c[2])
    x11 = c[3] + ux * (c[7] - c[3])
    y0 = x00 + uy * (x10 - x00)
    y1 = x01 + uy * (x11 - x01)
    return y0 + uz * (y1 - y0)


def _field_along(q0, e, cell, corners, t):
    """F at parameters t [R, G, S] of rays q0, e [R, 3] in cells cell [R, G, 3] (float),
    corners [R, G, 8]."""
    q = q0[:, None, None, :] + t[..., None] * e[:, None, None, :]
    with np.errstate(invalid="ignore"):  # cells with non-finite corners are masked later
        return _trilinear(corners[:, :, None, :], q - cell[:, :, None, :])


def _cells_and_corners(data, q0, e, ta, tb):
    """Cell index [R, G, 3] (int) holding each segment's midpoint and its corners [R, G, 8]."""
    upper = np.asarray(data.shape) - 2
    mid = q0[:, None, :] + (0.5 * (ta + tb))[..., None] * e[:, None, :]
    cell = np.clip(np.floor(mid), 0, upper).astype(np.int64)
    i, j, k = cell[..., 0], cell[..., 1], cell[..., 2]
    corners = np.stack([data[i + di, j + dj, k + dk]
                        for di in (0, 1) for dj in (0, 1) for dk in (0, 1)], axis=-1)
    return cell, corners


def _bisect(q0, e, cell, corners, lo, hi, iso):
    """Root of F - iso in [lo, hi] (arrays [P]; F - iso has opposite nonzero signs at the
    ends) by bisection; returns the bracket midpoint after `_BISECTIONS` halvings."""
    at = lambda t: _field_along(q0, e, cell[:, None], corners[:, None], t[:, None, None])
    sign_lo = np.sign(at(lo)[:, 0, 0] - iso)
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        s = np.sign(at(mid)[:, 0, 0] - iso)
        lo = np.where((s == sign_lo) | (s == 0), mid, lo)
        hi = np.where(s != sign_lo, mid, hi)   # s == 0 collapses the bracket onto mid
    return 0.5 * (lo + hi)


def _first_hits_chunk(data, q0, e, t0, t1, valid, iso, samples):
    """first_hits for a chunk of rays in index space; returns (t [R], which [R])."""
    r = q0.shape[0]
    bounds = _segment_bounds(q0, e, t0, t1, data.shape)
    ta, tb = bounds[:, :-1], bounds[:, 1:]                            # [R, G]
    cell, corners = _cells_and_corners(data, q0, e, ta, tb)
    # a constant cell has no surface (its level set is all of it, or empty)
    constant = np.all(corners == corners[..., :1], axis=-1)
    live = (tb > ta) & valid[:, None] & np.all(np.isfinite(corners), axis=-1) & ~constant
    frac = np.arange(samples + 1) / samples
    ts = ta[..., None] + (tb - ta)[..., None] * frac                  # [R, G, S+1]
    ts[..., -1] = tb                                                  # ends exactly shared
    f = _field_along(q0, e, cell.astype(np.float64), corners, ts)
    sg = np.sign(f[..., None] - iso)                                  # [R, G, S+1, K]
    event = sg == 0
    event[..., :-1, :] |= sg[..., :-1, :] * sg[..., 1:, :] < 0
    event &= live[:, :, None, None]
    flat = event.reshape(r, -1, iso.size)
    found = flat.any(axis=1)                                          # [R, K]
    first = np.argmax(flat, axis=1)
    seg, k = np.divmod(first, samples + 1)
    cand = np.full((r, iso.size), np.inf)
    rows, isos = np.nonzero(found)
    s_, k_ = seg[rows, isos], k[rows, isos]
    exact = sg[rows, s_, k_, isos] == 0
    cand[rows[exact], isos[exact]] = ts[rows[exact], s_[exact], k_[exact]]
    b = ~exact
    rb, ib, sb, kb = rows[b], isos[b], s_[b], k_[b]
    if rb.size:
        cand[rb, ib] = _bisect(q0[rb], e[rb], cell[rb, sb].astype(np.float64),
                               corners[rb, sb], ts[rb, sb, kb], ts[rb, sb, kb + 1], iso[ib])
    which = np.argmin(cand, axis=1)
    t = cand[np.arange(r), which]
    return t, np.where(np.isfinite(t), which, -1)


def first_hits(data, rays_o, rays_d, isovalues, *, spacing, origin, t_min=0.0, t_max=np.inf,
               samples=64):
    """First intersection of each ray with {F = iso} for any of the isovalues.

    data [nx, ny, nz] (any real dtype; NaN/inf mark missing voxels); rays_o, rays_d [N, 3]
    (an origin [3] is broadcast); isovalues: scalar or [K]; spacing, origin: 3-vectors.
    Returns (t [N] float64, inf for a miss; hit [N] bool; which [N] int64, the index of the
    isovalue hit, -1 for a miss). See the module docstring for the method and limitations.
    """
    data = np.asarray(data, np.float64)
    if data.ndim != 3:
        raise ValueError(f"data must be 3-D, got shape {data.shape}")
    iso = np.atleast_1d(np.asarray(isovalues, np.float64)).ravel()
    if iso.size == 0 or not np.all(np.isfinite(iso)):
        raise ValueError("need at least one finite isovalue")
    spacing = np.broadcast_to(np.asarray(spacing, np.float64), 3)
    origin = np.broadcast_to(np.asarray(origin, np.float64), 3)
    if not np.all(spacing > 0):
        raise ValueError(f"spacing must be positive, got {spacing}")
    d = np.asarray(rays_d, np.float64).reshape(-1, 3)
    o = np.broadcast_to(np.asarray(rays_o, np.float64), d.shape)
    n = d.shape[0]
    t = np.full(n, np.inf)
    which = np.full(n, -1, np.int64)
    if min(data.shape) < 2:       # no cells
        return t, np.zeros(n, bool), which
    q0, e = (o - origin) / spacing, d / spacing
    t0, t1, valid = clip_to_index_box(q0, e, data.shape, t_min, t_max)
    segments = sum(data.shape) - 5
    chunk = max(1, _POINT_BUDGET // (segments * (samples + 1) * max(iso.size, 3)))
    live = np.nonzero(valid)[0]
    for c in range(0, live.size, chunk):
        idx = live[c:c + chunk]
        t[idx], which[idx] = _first_hits_chunk(data, q0[idx], e[idx], t0[idx], t1[idx],
                                               valid[idx], iso, int(samples))
    return t, np.isfinite(t), which
