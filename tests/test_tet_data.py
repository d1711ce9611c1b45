"""Tests of the tetrahedral test data (jaxiso.tetra.data) and the float64 reference
(reference_tet64), each against computations written independently here."""

import numpy as np
import pytest
from reference_tet64 import (
    camera_rays,
    first_hits,
    interpolate,
    marching_tets_case,
    marching_tets_cases,
)

from jaxiso.tetra import data


def signed_volumes(points, tets):
    """6 x signed volume by determinant (independent of the cross-product code under test)."""
    p = np.asarray(points, np.float64)[tets]
    return np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], 1))


def face_counts(tets):
    """Unique triangles (sorted vertex triples) [F, 3] and how many tets hold each."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]],
                            tets[:, [0, 1, 2]]])
    return np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)


def check_conforming(points, tets, lo, hi):
    """Assert every face is held by 1 or 2 tets and the 1-tet faces tile the box surface."""
    faces, counts = face_counts(tets)
    assert set(np.unique(counts)) <= {1, 2}
    boundary = faces[counts == 1]
    corners = np.asarray(points, np.float64)[boundary]                   # [B, 3, 3]
    on_plane = ((corners == lo) | (corners == hi)).all(axis=1).any(axis=1)
    assert on_plane.all(), "a face held by one tet lies inside the box: not conforming"
    return len(boundary)


@pytest.mark.parametrize("split", [5, 6])
@pytest.mark.parametrize("n", [1, 3, (2, 3, 4)])
def test_cube_tets_volume_orientation_conformity(split, n):
    lo, hi = np.array([-1.0, 0.5, 2.0]), np.array([1.0, 1.5, 2.5])
    points, tets = data.cube_tets(n, split=split, lo=lo, hi=hi)
    nx, ny, nz = np.broadcast_to(n, (3,))
    assert points.dtype == np.float32 and tets.dtype == np.int32
    assert points.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3)
    assert tets.shape == (split * nx * ny * nz, 4)
    np.testing.assert_array_equal(points.min(0), lo.astype(np.float32))
    np.testing.assert_array_equal(points.max(0), hi.astype(np.float32))
    vol = signed_volumes(points, tets) / 6.0
    cell = np.prod((hi - lo) / [nx, ny, nz])
    # every tet of both splits has volume cell / 6 or cell / 3: none inverted or degenerate
    assert vol.min() > cell / 6 * (1 - 1e-5)
    np.testing.assert_allclose(np.abs(vol).sum(), np.prod(hi - lo), rtol=1e-6)
    # each boundary square is cut into 2 triangles
    assert check_conforming(points, tets, lo, hi) == 4 * (nx * ny + ny * nz + nz * nx)
    assert len(np.unique(np.sort(tets, axis=1), axis=0)) == len(tets)


def test_conformity_check_catches_unmirrored_five_split():
    """The same 5-tet template in every cube (no parity mirroring) is not conforming."""
    n = 2
    _, one_cube = data.cube_tets(1, split=5)
    points, _ = data.cube_tets(n)
    # local vertex (a, b, c) of cube (i, j, k) is grid vertex (i + a, j + b, k + c)
    local = np.stack(np.unravel_index(one_cube, (2, 2, 2)), -1)          # [5, 4, 3]
    cubes = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 1, 1, 3)
    naive = np.ravel_multi_index(np.moveaxis(cubes + local, -1, 0), (n + 1,) * 3).reshape(-1, 4)
    with pytest.raises(AssertionError, match="not conforming"):
        check_conforming(points, naive, 0.0, 1.0)


def test_cube_tets_rejects_bad_arguments():
    with pytest.raises(ValueError):
        data.cube_tets(2, split=4)
    with pytest.raises(ValueError):
        data.cube_tets(0)
    with pytest.raises(ValueError):
        data.cube_tets(2, lo=(0, 0, 0), hi=(1, 0, 1))


def test_fields():
    points, _ = data.cube_tets(4)
    p = points.astype(np.float64)
    s = data.sphere_field(points, center=(0.5, 0.5, 0.5), radius=0.25)
    assert s.dtype == np.float32 and s.shape == (len(points),)
    np.testing.assert_allclose(s, np.sqrt(((p - 0.5) ** 2).sum(1)) - 0.25, atol=1e-6)
    w0 = data.wave_field(points, 0.0)
    assert w0.dtype == np.float32 and np.abs(w0).max() <= 1.5
    np.testing.assert_allclose(data.wave_field(points, 2 * np.pi), w0, atol=1e-5)
    assert np.abs(data.wave_field(points, 1.0) - w0).max() > 0.1         # t animates it
    r = data.random_field(points, seed=3)
    np.testing.assert_array_equal(r, data.random_field(points, seed=3))
    assert r.dtype == np.float32 and -1 <= r.min() and r.max() < 1 and r.std() > 0.3
    assert not np.array_equal(r, data.random_field(points, seed=4))


def test_time_series_and_deform():
    points, tets = data.cube_tets(3, split=5)
    series = data.time_series(points, 4)
    assert series.shape == (4, len(points)) and series.dtype == np.float32
    for s in range(4):
        np.testing.assert_array_equal(series[s], data.wave_field(points, s * np.pi / 2))
    for t in np.linspace(0.0, 6.0, 7):
        moved = data.deform(points, t)
        shift = np.linalg.norm(moved.astype(np.float64) - points, axis=1)
        assert moved.dtype == np.float32 and 0 < shift.max() <= 0.02 * np.sqrt(3) + 1e-6
        assert signed_volumes(moved, tets).min() > 0                    # nothing inverted
    np.testing.assert_allclose(data.deform(points, 2 * np.pi), data.deform(points, 0.0),
                               atol=1e-6)


def test_replicate():
    points, tets = data.cube_tets(2, lo=(0, 0, 0), hi=(1, 2, 1))
    values = data.random_field(points, 0)
    k = 3
    rp, rt, rv = data.replicate(points, tets, values, k, gap=0.5)
    v, t = len(points), len(tets)
    assert rp.shape == (k**3 * v, 3) and rt.shape == (k**3 * t, 4) and rv.shape == (k**3 * v,)
    assert rt.dtype == np.int32 and rt.min() == 0 and rt.max() == k**3 * v - 1
    for copy, (a, b, c) in enumerate(np.ndindex(k, k, k)):
        shift = np.array([a, b, c]) * 1.5 * np.array([1.0, 2.0, 1.0])
        np.testing.assert_allclose(rp[rt[copy * t:(copy + 1) * t]], points[tets] + shift,
                                   atol=1e-6)
        np.testing.assert_array_equal(rv[copy * v:(copy + 1) * v], values)
    _, _, series = data.replicate(points, tets, np.stack([values, 2 * values]), 2)
    assert series.shape == (2, 8 * v)
    np.testing.assert_array_equal(series[1], 2 * np.tile(values, 8))


def test_poisson_cube():
    pytest.importorskip("skfem")
    points, tets, u = data.poisson_cube(6)
    p = points.astype(np.float64)
    on_boundary = ((p == 0) | (p == 1)).any(axis=1)
    np.testing.assert_allclose(u[on_boundary], 0.0, atol=1e-12)
    assert u[~on_boundary].min() > 0
    centre = np.flatnonzero((np.abs(p - 0.5) < 1e-6).all(axis=1))
    # series solution of -laplace u = 1 on the unit cube: u(centre) = 0.056213...
    np.testing.assert_allclose(u[centre], 0.0562, rtol=0.08)


def test_poisson_on_ball():
    pytest.importorskip("skfem")
    points, tets, u = data.poisson_on_ball(3)
    assert signed_volumes(points, tets).min() > 0
    r2 = (points.astype(np.float64) ** 2).sum(1)
    exact = (1 - r2) / 6                                                  # -laplace = 1
    on_boundary = np.abs(r2 - 1) < 1e-6
    assert on_boundary.sum() > 20
    np.testing.assert_allclose(u[on_boundary], 0.0, atol=1e-12)
    assert u[~on_boundary].min() > 0
    np.testing.assert_allclose(u, exact, atol=0.01)                      # max 1/6


# ---------------------------------------------------------------- reference ray tracer


def box_interval(o, d, lo, hi):
    """Slab interval of rays in a box, written separately from the reference's clipping."""
    with np.errstate(divide="ignore"):
        a, b = (lo - o) / d, (hi - o) / d
    return np.minimum(a, b).max(1), np.maximum(a, b).min(1)


def plane_x_hits(o, d, iso, lo=0.0, hi=1.0):
    """Analytic first hit of F = x = iso inside the box [lo, hi]^3 (inf for none)."""
    ta, tb = box_interval(o, d, lo, hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (iso - o[:, 0]) / d[:, 0]
    ok = (t >= np.maximum(ta, 0)) & (t <= tb)
    return np.where(ok, t, np.inf)


def rays_into_unit_cube(rng, count):
    origins = rng.uniform(-1.5, 2.5, (count, 3))
    origins[np.arange(count), rng.integers(0, 3, count)] = -1.0             # start outside
    targets = rng.uniform(0.0, 1.0, (count, 3))
    return origins, targets - origins


@pytest.mark.parametrize("split", [5, 6])
def test_reference_linear_field_random_rays(split):
    points, tets = data.cube_tets(4, split=split)
    values = points[:, 0]
    o, d = rays_into_unit_cube(np.random.default_rng(1), 200)
    t, hit, which, tet = first_hits(points, tets, values, o, d, 0.37)
    expected = plane_x_hits(o, d, 0.37)
    np.testing.assert_array_equal(hit, np.isfinite(expected))
    assert 60 < hit.sum() < 200
    np.testing.assert_allclose(t[hit], expected[hit], rtol=1e-9, atol=1e-12)
    assert (which[hit] == 0).all() and (which[~hit] == -1).all() and (tet[~hit] == -1).all()
    x = o[hit] + t[hit, None] * d[hit]
    f, lam = interpolate(points, tets, values, tet[hit], x)
    np.testing.assert_allclose(f, 0.37, atol=1e-12)
    assert lam.min() > -1e-8                                              # hit in its tet


@pytest.mark.parametrize("split", [5, 6])
def test_reference_no_holes_through_vertices_edges_faces(split):
    """Rays aimed exactly at grid vertices / edges / faces of the mesh, and rays running
    along grid lines and inside grid planes, all find the plane x = iso."""
    n = 4
    points, tets = data.cube_tets(n, split=split)
    values = points[:, 0]
    g = np.arange(n + 1) / n
    yy, zz = np.meshgrid(g, g, indexing="ij")
    grid_yz = np.stack([yy.ravel(), zz.ravel()], 1)                       # grid vertices
    mid_yz = (grid_yz[:, None] + [[0.5 / n, 0], [0, 0.5 / n], [0.5 / n, 0.5 / n]]).reshape(-1, 2)
    mid_yz = mid_yz[(mid_yz <= 1).all(1)]                                 # edge / face points
    for iso in (0.5, 0.375):      # on a grid plane (faces), and between planes (edges cut)
        for yz in (grid_yz, mid_yz):
            targets = np.column_stack([np.full(len(yz), iso), yz])
            # oblique rays through the targets, with t = 1 exactly at the target
            o = targets + np.array([-1.25, 0.5, -0.75])
            t, hit, _, _ = first_hits(points, tets, values, o, targets - o, iso)
            assert hit.all()
            np.testing.assert_allclose(t, 1.0, rtol=1e-9)
            # axis-parallel rays running along grid lines / inside grid planes
            o = targets - np.array([2.0, 0.0, 0.0])
            t, hit, _, _ = first_hits(points, tets, values, o, np.tile([1.0, 0, 0], (len(o), 1)),
                                      iso)
            assert hit.all()
            np.testing.assert_allclose(t, 2.0, rtol=1e-9)
    # a ray lying in the grid plane z = 0.5, diagonal in x-y, crossing vertices and edges
    o = np.array([[-0.5, -0.25, 0.5]])
    t, hit, _, _ = first_hits(points, tets, values, o, np.array([[1.0, 1.0, 0.0]]), 0.5)
    assert hit.all() and np.isclose(t[0], 1.0, rtol=1e-12)


def test_reference_no_holes_on_deformed_mesh_edges():
    """A globally linear field on a deformed (non-axis-aligned) mesh: rays aimed at the points
    where the plane F = iso cuts mesh edges all hit there. (With no barycentric slack, tol=0,
    rounding loses one of these 88 rays.)"""
    points, tets = data.cube_tets(4, split=5)
    points = data.deform(points, 0.7).astype(np.float64)
    field = points @ np.array([0.8, -0.45, 0.3])
    iso = 0.21
    pairs = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    edges = np.unique(np.sort(pairs, axis=1), axis=0)
    fa, fb = field[edges[:, 0]], field[edges[:, 1]]
    edges = edges[(fa - iso) * (fb - iso) < 0]
    s = (iso - field[edges[:, 0]]) / (field[edges[:, 1]] - field[edges[:, 0]])
    targets = points[edges[:, 0]] + s[:, None] * (points[edges[:, 1]] - points[edges[:, 0]])
    o = targets + np.random.default_rng(0).normal(size=targets.shape) * 2
    t, hit, _, _ = first_hits(points, tets, field, o, targets - o, iso)
    assert len(targets) > 50 and hit.all()
    np.testing.assert_allclose(t, 1.0, atol=1e-7)


def test_reference_multiple_isovalues_misses_and_ranges():
    points, tets = data.cube_tets(3, split=6)
    values = points[:, 0]
    isos = [0.8, 0.3]
    count = 20
    yz = np.random.default_rng(2).uniform(0.2, 0.8, (count, 2))
    o = np.column_stack([np.full(count, -1.0), yz])
    plus = np.tile([1.0, 0.1, -0.05], (count, 1))
    t, hit, which, _ = first_hits(points, tets, values, o, plus, isos)
    assert hit.all() and (which == 1).all()
    np.testing.assert_allclose(t, 1.3, rtol=1e-12)
    o2 = o + [3.0, 0, 0]
    t, hit, which, _ = first_hits(points, tets, values, o2, -plus, isos)
    assert hit.all() and (which == 0).all()
    np.testing.assert_allclose(t, 1.2, rtol=1e-12)
    _, _, which, _ = first_hits(points, tets, values, o, plus, [0.3, 0.3])
    assert (which == 0).all()                                 # ties go to the lower index
    # pointing away, missing the cube, or a zero direction: misses
    away = np.concatenate([-plus, np.tile([0.0, 0, 1], (count, 1)), np.zeros((count, 3))])
    t, hit, which, tet = first_hits(points, tets, values, np.tile(o, (3, 1)), away, isos)
    assert not hit.any() and np.isinf(t).all() and (which == -1).all() and (tet == -1).all()
    # t range: t_max before the first plane, t_min past it
    _, hit, _, _ = first_hits(points, tets, values, o, plus, isos, t_max=1.29)
    assert not hit.any()
    t, hit, which, _ = first_hits(points, tets, values, o, plus, isos, t_min=1.31)
    assert hit.all() and (which == 0).all() and np.allclose(t, 1.8, rtol=1e-12)
    # closed range: a root exactly at t_max, or exactly at t_min, counts
    o_exact = np.column_stack([np.full(count, -1.0), yz])
    along_x = np.tile([1.0, 0, 0], (count, 1))
    for bounds in (dict(t_max=1.25), dict(t_min=1.25)):
        t, hit, _, _ = first_hits(points, tets, values, o_exact, along_x, 0.25, **bounds)
        assert hit.all() and (t == 1.25).all(), bounds
    # an isovalue outside the data range is never hit
    assert not first_hits(points, tets, values, o, plus, 1.5)[1].any()


def test_reference_clip_box():
    points, tets = data.cube_tets(4, split=5)
    values = points[:, 0]
    o, d = rays_into_unit_cube(np.random.default_rng(5), 300)
    box = (np.array([0.2, 0.3, -1.0]), np.array([0.9, 0.6, 2.0]))
    t, hit, _, _ = first_hits(points, tets, values, o, d, 0.5, clip_box=box)
    expected = plane_x_hits(o, d, 0.5)
    x = o + np.where(np.isfinite(expected), expected, 0)[:, None] * d
    in_box = np.isfinite(expected) & (x[:, 1] >= 0.3) & (x[:, 1] <= 0.6)
    np.testing.assert_array_equal(hit, in_box)
    assert 10 < hit.sum() < np.isfinite(expected).sum()
    # value_tol (5e-8) may move a root at a range end by ~1e-9 relative
    np.testing.assert_allclose(t[hit], expected[hit], rtol=1e-8)


def test_reference_constant_field_at_the_isovalue_has_no_surface():
    """A tet with one value throughout has no surface, even at the isovalue."""
    points, tets = data.cube_tets(2, split=6)
    o, d = rays_into_unit_cube(np.random.default_rng(6), 50)
    _, hit, _, _ = first_hits(points, tets, np.full(len(points), 0.5), o, d, 0.5)
    assert not hit.any()


def sphere_hits(o, d, centre, radius):
    """Nearest t >= 0 of |o + t d - centre| = radius for unit d (quadratic formula)."""
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius**2)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return np.where((disc >= 0) & (t >= 0), t, np.inf)


def test_reference_sphere_field_camera():
    n, radius = 8, 0.3
    points, tets = data.cube_tets(n, split=6)
    values = data.sphere_field(points, (0.5, 0.5, 0.5), radius)
    o, d = camera_rays((2.0, 1.4, 1.1), (0.5, 0.5, 0.5), fov=30.0, width=16)
    t, hit, _, tet = first_hits(points, tets, values, o, d, 0.0)
    exact = sphere_hits(o, d, 0.5, radius)
    # P1 interpolation of the distance inscribes the sphere to within ~h^2 / r
    h = 1.0 / n
    inner, outer = sphere_hits(o, d, 0.5, radius - h), sphere_hits(o, d, 0.5, radius + h)
    assert hit[np.isfinite(inner)].all() and not hit[~np.isfinite(outer)].any()
    both = hit & np.isfinite(exact)
    assert both.sum() > 50
    assert np.abs(t[both] - exact[both]).max() < h
    x = o[hit] + t[hit, None] * d[hit]
    f, lam = interpolate(points, tets, values, tet[hit], x)
    np.testing.assert_allclose(f, 0.0, atol=1e-12)
    assert lam.min() > -1e-8


def test_reference_is_nearest_for_random_field():
    """No isosurface crossing before the reported hit, by point sampling the field along
    each ray (point location by brute-force barycentrics)."""
    points, tets = data.cube_tets(2, split=5)
    values = data.random_field(points, seed=7).astype(np.float64)
    o, d = rays_into_unit_cube(np.random.default_rng(8), 40)
    iso = 0.1
    t, hit, _, _ = first_hits(points, tets, values, o, d, iso)
    assert hit.sum() > 10
    ta, tb = box_interval(o, d, 0.0, 1.0)
    for r in np.flatnonzero(hit):
        ts = np.linspace(max(ta[r], 0), t[r], 60)[:-1]
        xs = o[r] + ts[:, None] * d[r]
        f = np.full(len(ts), np.nan)
        for k in range(len(tets)):
            fk, lam = interpolate(points, np.repeat(tets[k:k + 1], len(ts), 0), values,
                                  np.arange(len(ts)), xs)
            f = np.where(np.isnan(f) & (lam.min(1) >= -1e-12), fk, f)
        assert not np.isnan(f).any()
        side = np.sign(f - iso)
        assert (side == side[0]).all() or np.abs(f - iso).min() < 1e-9
        x = o[r] + t[r] * d[r]
        assert abs(interpolate(points, tets, values, [hit_tet(points, tets, x)], x[None])[0][0]
                   - iso) < 1e-9


def hit_tet(points, tets, x):
    """First tet containing point x (brute force)."""
    for k in range(len(tets)):
        _, lam = interpolate(points, tets, np.zeros(len(points)), [k], x[None])
        if lam.min() >= -1e-9:
            return k
    raise AssertionError("point outside the mesh")


def test_camera_rays_match_jaxiso_camera():
    from jaxiso.render import Camera

    eye, target, up = (2.0, -1.0, 1.5), (0.2, 0.3, -0.1), (0.0, 0.0, 1.0)
    cam = Camera.look_at(eye, target, up, fov=50.0, width=7, height=5)
    rays = cam.rays()
    o, d = camera_rays(eye, target, up, fov=50.0, width=7, height=5)
    np.testing.assert_allclose(np.asarray(rays.origin).reshape(-1, 3), o, atol=1e-6)
    np.testing.assert_allclose(np.asarray(rays.direction).reshape(-1, 3), d, atol=2e-6)


def test_marching_tets_table():
    cases = marching_tets_cases()
    counts = [n for n, _ in cases]
    assert counts[0] == counts[15] == 0
    assert sorted(counts[1:15]) == [3] * 8 + [4] * 6
    for c, (n, edges) in enumerate(cases):
        above = [(c >> i) & 1 for i in range(4)]
        assert n == sum(above) * (4 - sum(above))                         # edges cut
        for below_vertex, above_vertex in edges:
            assert not above[below_vertex] and above[above_vertex]


def test_marching_tets_case_polygons_convex_and_wound():
    """On random positively oriented tets the polygon (from edge interpolation) is planar at
    the isovalue, convex, and its winding normal follows the field gradient."""
    rng = np.random.default_rng(4)
    seen = set()
    for _ in range(300):
        p = rng.normal(size=(4, 3))
        if signed_volumes(p, np.array([[0, 1, 2, 3]]))[0] < 0:
            p = p[[0, 1, 3, 2]]
        v = rng.normal(size=4)
        iso = rng.normal() * 0.5
        n, edges = marching_tets_case(v, iso)
        assert n == np.sum(v > iso) * np.sum(v <= iso)
        if n == 0:
            continue
        seen.add(n)
        a, b = edges[:, 0], edges[:, 1]
        s = (iso - v[a]) / (v[b] - v[a])
        poly = p[a] + s[:, None] * (p[b] - p[a])
        grad = np.linalg.solve(p[1:] - p[0], v[1:] - v[0])               # linear field gradient
        np.testing.assert_allclose(poly @ grad, iso - v[0] + p[0] @ grad, atol=1e-9)
        turns = np.cross(np.roll(poly, -1, 0) - poly, np.roll(poly, -2, 0) - np.roll(poly, -1, 0))
        assert (turns @ grad > -1e-12).all()                              # convex, wound along
    assert seen == {3, 4}


def test_marching_tets_ties():
    v = np.array([0.0, 1.0, 1.0, 2.0])
    n, edges = marching_tets_case(v, 1.0)                                 # 1s count as below
    assert n == 3 and set(edges[:, 1]) == {3}
    n, edges = marching_tets_case(v, 1.0, ties_above=True)
    assert n == 3 and set(edges[:, 0]) == {0}
