"""TetIsosurface against the independent float64 reference (tests/reference_tet64.py):
hit masks, depths, the 16 marching-tets cases, watertightness, refit, clip box, multiple
isovalues, derivatives and the renderer's modalities."""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_tet64 as ref

import jaxiso as ji
from jaxiso.tetra import TetIsosurface, data, tet_mesh
from jaxiso.tetra._isopoly import TET_EDGES, face_segments, isopolygon_hits

W = 20
EYE = np.array([2.2, 1.7, 1.4])
POINTS, TETS = data.cube_tets(5)
_trace = jax.jit(lambda scene, rays: ji.intersect(scene, rays, plan=ji.Plan(tile=8)))
# the whole image on 64 persistent lanes, then 32 for the tail
_trace_lanes = jax.jit(lambda scene, rays: ji.intersect(scene, rays,
                                                        plan=ji.Plan(tile=8, lanes=64)))
_polygon_t = jax.jit(lambda o, d, p, f, ids, iso: isopolygon_hits(o, d, p, f, ids, iso)[0])


def _camera():
    cam = ji.Camera.look_at(EYE, (0.5, 0.5, 0.5), (0, 0, 1), fov=40, width=W, height=W)
    o, d = ref.camera_rays(EYE, (0.5, 0.5, 0.5), (0, 0, 1), 40, W, W)
    return cam.rays().reshape((W * W,)), o, d


def _compare(values, iso, *, clip_box=None, lanes=False, **scene_options):
    rays, o, d = _camera()
    t_ref, h_ref, w_ref, _ = ref.first_hits(POINTS.astype(np.float64), TETS,
                                            np.asarray(values, np.float64), o, d, iso,
                                            clip_box=clip_box)
    scene = TetIsosurface(tet_mesh(POINTS, TETS, values), iso, clip_box=clip_box,
                          **scene_options)
    hits = (_trace_lanes if lanes else _trace)(scene, rays)
    hit, t = np.asarray(hits.hit), np.asarray(hits.t)
    assert np.array_equal(hit, h_ref), f"{int((hit != h_ref).sum())} pixels differ"
    np.testing.assert_allclose(t[hit], t_ref[hit], rtol=1e-5)
    assert np.array_equal(np.asarray(hits.surface)[hit], w_ref[hit])
    assert np.all(np.isfinite(np.asarray(hits.normal)))
    return hits, h_ref


@pytest.mark.parametrize("field, iso, bvh, lanes", [
    ("sphere", [0.0], "bih", False), ("wave", [0.0, 0.5], "sah", False),
    ("random", [0.1, -0.3, 0.5], "bih", False), ("wave", [0.0, 0.5], "bih", True)])
def test_hits_match_reference(field, iso, bvh, lanes):
    values = {"sphere": data.sphere_field(POINTS), "wave": data.wave_field(POINTS),
              "random": data.random_field(POINTS, 1)}[field]
    _, h_ref = _compare(values, iso, bvh=bvh, lanes=lanes)
    assert h_ref.sum() > 40


def test_postponed_leaf_tests_give_the_same_hits_and_work_whenever_they_fire():
    # rays wait at leaves until a fraction of the packet waits: 0 tests every leaf as soon
    # as a ray reaches it, 1 only when all busy rays wait; the hits, and the nodes and
    # leaves each ray visits, must not depend on when the tests run
    from jaxiso.tetra import traverse

    values = data.random_field(POINTS, 2)
    scene = TetIsosurface(tet_mesh(POINTS, TETS, values), [0.1, -0.3], bvh="bih")
    rays, *_ = _camera()
    o, d = rays.origin, rays.direction
    t0, t1 = jnp.zeros(W * W), jnp.full(W * W, jnp.inf)
    values = jnp.asarray(values)

    def run(fill, lanes=None):
        one = jax.jit(lambda o, d, a, b: traverse(scene.bvh, jnp.asarray(POINTS),
                                                  jnp.asarray(TETS), values,
                                                  scene.isovalues, o, d, a, b,
                                                  leaf_fill=fill, lanes=lanes))
        if lanes:  # the whole image on persistent lanes (idle lanes must not hold it up)
            return [np.asarray(r) for r in one(o, d, t0, t1)]
        out = [one(*(x.reshape((-1, 16) + x.shape[1:])[i] for x in (o, d, t0, t1)))
               for i in range(W * W // 16)]
        return [np.concatenate([np.asarray(r[j]) for r in out]) for j in range(6)]

    first = run(0.0)
    assert first[1].sum() > 40 and first[5].max() >= 2  # hits, rays through several leaves
    for fill, lanes in ((0.5, None), (1.0, None), (1.0, 64)):
        for a, b in zip(first, run(fill, lanes)):
            assert np.array_equal(a, b)


@pytest.mark.parametrize("field, isovalues", [("sphere", (-0.15, 0.0, 0.15)),
                                              ("random", (0.1, 0.12))])
def test_several_isovalues_give_the_nearest_of_the_single_isovalue_hits(field, isovalues):
    # a leaf pass tests one isovalue per tet where no tet of the pass holds two (nested
    # spheres on tets smaller than their spacing, cut open by a clip box so that all are
    # seen), else every isovalue (the close random-field pair);
    # either way the hit is the nearest of what each isovalue alone gives
    points, tets = data.cube_tets(12)
    values = data.sphere_field(points) if field == "sphere" else data.random_field(points, 1)
    clip = ((0.0, 0.0, 0.0), (0.55, 1.0, 1.0))
    rays, *_ = _camera()
    mesh = tet_mesh(points, tets, values)
    bvh = TetIsosurface(mesh, isovalues).bvh
    alone = [_trace(TetIsosurface(mesh, iso, bvh=bvh, clip_box=clip), rays)
             for iso in isovalues]
    t_alone = np.stack([np.asarray(h.t) for h in alone])
    both = _trace(TetIsosurface(mesh, isovalues, bvh=bvh, clip_box=clip), rays)
    t, hit = np.asarray(both.t), np.asarray(both.hit)
    assert np.array_equal(hit, np.isfinite(t_alone).any(axis=0)) and hit.sum() > 40
    assert len(set(t_alone.argmin(axis=0)[hit])) > 1  # more than one isovalue is seen
    np.testing.assert_allclose(t[hit], t_alone.min(axis=0)[hit], rtol=1e-6)
    assert np.array_equal(np.asarray(both.surface)[hit], t_alone.argmin(axis=0)[hit])


def test_intersect_under_vmap_over_isovalues_and_eagerly_matches_jit():
    # the traversal's while_loop and lax.cond batch under vmap (the cond becomes a select)
    values = data.wave_field(POINTS)
    scene = TetIsosurface(tet_mesh(POINTS, TETS, values), [0.0, 0.5])
    rays, *_ = _camera()
    levels = jnp.asarray([[0.0, 0.5], [-0.3, 0.2]], jnp.float32)
    batched = jax.vmap(lambda iso: ji.intersect(scene.with_isovalues(iso), rays,
                                                plan=ji.Plan(tile=8)))(levels)
    for i, iso in enumerate(levels):
        one = _trace(scene.with_isovalues(iso), rays)
        assert np.array_equal(np.asarray(batched.hit[i]), np.asarray(one.hit))
        assert np.asarray(one.hit).sum() > 40
        np.testing.assert_array_equal(np.asarray(batched.t[i]), np.asarray(one.t))
    # the isopolygon kernel eagerly equals its jitted self (hit rays x the first 64 tets)
    hit = np.asarray(batched.hit[0])
    o, d = rays.origin[hit], rays.direction[hit]
    cells = jnp.asarray(TETS)[:64][None].repeat(o.shape[0], 0)            # [P, 64, 4]
    args = (o, d, jnp.asarray(POINTS)[cells], jnp.asarray(values)[cells], cells, 0.0)
    with jax.disable_jit():
        eager = isopolygon_hits(*args)[0]
    jitted = _polygon_t(*args)
    eager, jitted = np.asarray(eager), np.asarray(jitted)
    assert np.array_equal(np.isfinite(eager), np.isfinite(jitted)) and np.isfinite(jitted).any()
    # XLA may contract multiply-adds differently from op-by-op execution
    np.testing.assert_allclose(eager[np.isfinite(eager)], jitted[np.isfinite(jitted)],
                               rtol=1e-6)


def test_isovalues_equal_to_vertex_values_and_clip_box():
    values = np.random.default_rng(3).integers(0, 4, len(POINTS)).astype(np.float32)
    _compare(values, [1.0, 2.0])
    # clip faces off the isosurface planes (integer values on a 0.2 grid put them on
    # x.1, x.3, ...): a face on one makes the answer a float32 coin toss
    _compare(values, [2.0], clip_box=((0.11, 0.05, 0.15), (0.85, 0.69, 0.95)))


def test_all_16_marching_tets_cases_against_the_reference_polygon():
    rng = np.random.default_rng(0)
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    ids = np.arange(4, dtype=np.int32)
    for case in range(16):
        f = np.where([(case >> v) & 1 for v in range(4)],
                     rng.uniform(0.2, 1.0, 4), rng.uniform(-1.0, -0.2, 4)).astype(np.float32)
        n_ref, edges_ref = ref.marching_tets_case(f.astype(np.float64), 0.0)
        # the polygon's edges, one per cut face, chain head to tail over the cut edges
        segments = [(int(a), int(b)) for cut, a, b in face_segments(f > 0) if cut]
        assert len(segments) == n_ref
        starts, ends = sorted(a for a, _ in segments), sorted(b for _, b in segments)
        assert starts == ends and len(set(starts)) == n_ref
        assert {TET_EDGES[e] for e in starts} == {tuple(sorted(e)) for e in edges_ref}
        if n_ref:  # following the segments walks the reference's cycle (either way round)
            nxt = dict(segments)
            cycle = [segments[0][0]]
            while len(cycle) < n_ref:
                cycle.append(nxt[cycle[-1]])
            ring = [tuple(sorted(e)) for e in edges_ref]
            walk = [TET_EDGES[e] for e in cycle]
            turns = [ring[r:] + ring[:r] for r in range(n_ref)]
            assert walk in turns or walk[::-1] in turns
        if n_ref == 0:
            continue
        # polygon corners from the reference's edges; rays from outside at interior
        # points (hit there) and at points pushed outside the polygon (miss)
        w = -f[edges_ref[:, 0]] / (f[edges_ref[:, 1]] - f[edges_ref[:, 0]])
        corners = p[edges_ref[:, 0]] + w[:, None] * (p[edges_ref[:, 1]] - p[edges_ref[:, 0]])
        centre = corners.mean(axis=0)
        weights = rng.dirichlet(np.ones(n_ref), 16).astype(np.float32)
        inside = weights @ corners
        outside = centre + 1.3 * (corners - centre)
        targets = np.concatenate([inside, outside]).astype(np.float32)
        o = np.tile(np.float32([[2.0, 1.7, 1.9]]), (len(targets), 1))
        d = targets - o
        t, c = isopolygon_hits(jnp.asarray(o), jnp.asarray(d),
                               jnp.broadcast_to(jnp.asarray(p), (len(o), 1, 4, 3)),
                               jnp.broadcast_to(jnp.asarray(f), (len(o), 1, 4)),
                               jnp.broadcast_to(jnp.asarray(ids), (len(o), 1, 4)), 0.0)
        t = np.asarray(t)[:, 0]
        assert np.all(np.asarray(c) == case)
        np.testing.assert_allclose(t[:16], 1.0, atol=1e-5)
        assert np.all(np.isinf(t[16:]))


def test_closed_isosurface_is_watertight_at_polygon_vertices_and_edges():
    # rays aimed exactly at the corners and edge midpoints of every isopolygon of a
    # closed surface must hit it at or before their target
    values = data.sphere_field(POINTS, radius=0.3)
    f = values[TETS].astype(np.float64)
    targets = []
    for tet, fv in zip(TETS, f):
        n, edges = ref.marching_tets_case(fv, 0.0)
        if n == 0:
            continue
        pa, pb = POINTS[tet[edges[:, 0]]], POINTS[tet[edges[:, 1]]]
        w = (-fv[edges[:, 0]] / (fv[edges[:, 1]] - fv[edges[:, 0]]))[:, None]
        corners = pa + w * (pb - pa)
        targets += list(corners) + list(0.5 * (corners + np.roll(corners, -1, axis=0)))
    targets = np.unique(np.array(targets, np.float32), axis=0)
    o = np.tile(EYE.astype(np.float32), (len(targets), 1))
    d = targets - o
    # at the silhouette a ray only grazes the (polyhedral) surface and may legitimately
    # miss it: compare with the exact float64 answer, which must be hit wherever it hits
    _, expect, _, _ = ref.first_hits(POINTS.astype(np.float64), TETS,
                                     values.astype(np.float64), o.astype(np.float64),
                                     d.astype(np.float64), [0.0])
    scene = TetIsosurface(tet_mesh(POINTS, TETS, values), 0.0)
    hits = ji.intersect(scene, ji.Rays(jnp.asarray(o), jnp.asarray(d)), plan=ji.Plan(tile=16))
    hit = np.asarray(hits.hit)
    assert expect.sum() > 200
    assert np.all(hit[expect]), f"{int((~hit[expect]).sum())} holes"
    assert np.all(np.asarray(hits.t)[expect] <= 1.0 + 1e-5)


def test_rays_passing_just_outside_an_isopolygon_miss_it_and_just_inside_hit_it():
    # the rounding allowance of the edge tests must stay far below 1e-5 (world units here):
    # rays aimed at isopolygon edge midpoints moved 1e-5 across the edge, as seen from the
    # ray, miss that tet's polygon outside and hit it inside (polygons from the reference)
    values = data.sphere_field(POINTS, radius=0.3).astype(np.float64)
    eye = EYE.astype(np.float32)
    rows, targets, outside, t_plane = [], [], [], []
    for k, (tet, fv) in enumerate(zip(TETS, values[TETS])):
        n, edges = ref.marching_tets_case(fv, 0.0)
        if n == 0:
            continue
        pa, pb = POINTS[tet[edges[:, 0]]].astype(np.float64), POINTS[tet[edges[:, 1]]]
        w = (-fv[edges[:, 0]] / (fv[edges[:, 1]] - fv[edges[:, 0]]))[:, None]
        corners = pa + w * (pb - pa)
        nxt = np.roll(corners, -1, axis=0)
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        for a, b in zip(corners, nxt):
            across = np.cross(b - a, 0.5 * (a + b) - eye)
            for shift in (1e-5, -1e-5):
                target = (0.5 * (a + b) + shift * across / np.linalg.norm(across)).astype(
                    np.float32)
                d = (target - eye).astype(np.float64)   # the float32 ray, exactly
                # signed distances of that ray from the polygon's edge lines: all of one
                # sign inside; outside, the moved edge's has the other sign
                cross = np.cross(nxt - corners, d)
                dist = np.einsum("mk,mk->m", corners - eye, cross) / np.linalg.norm(cross,
                                                                                    axis=1)
                if np.any(np.abs(dist) < 2e-6):
                    continue  # near another edge too (a thin polygon seen from the ray)
                rows.append(k)
                targets.append(target)
                outside.append(abs(np.sign(dist).sum()) < n)
                t_plane.append(normal @ (corners[0] - eye) / (normal @ d))
    targets, outside = np.array(targets), np.array(outside)
    o = np.broadcast_to(eye, targets.shape)
    ids = jnp.asarray(TETS[rows])[:, None]
    t = np.asarray(_polygon_t(jnp.asarray(o), jnp.asarray(targets - o),
                              jnp.asarray(POINTS)[ids], jnp.asarray(values, jnp.float32)[ids],
                              ids, 0.0))[:, 0]
    assert outside.sum() > 300 and (~outside).sum() > 300
    assert np.all(np.isinf(t[outside]))
    np.testing.assert_allclose(t[~outside], np.array(t_plane)[~outside], rtol=1e-5)


def test_a_ray_in_the_plane_of_an_isopolygon_gets_no_spurious_depth():
    # field z on skewed tets: their gradient is (0, 0, 1) only up to rounding, so a ray in
    # the plane z = 0.3 has a slope that is rounding noise and t = (iso - f) / slope
    # would be arbitrary; it must be a miss (the tets around take it where it leaves)
    rng = np.random.default_rng(4)
    p = (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
         + rng.uniform(-0.3, 0.3, (50, 4, 3))).astype(np.float32)
    o = np.concatenate([rng.uniform(-3, 3, (50, 2)), np.full((50, 1), 0.3)], axis=1)
    target = np.concatenate([p.mean(axis=1)[:, :2], np.full((50, 1), 0.3)], axis=1)
    o, d = o.astype(np.float32), (target - o).astype(np.float32)
    t = _polygon_t(jnp.asarray(o), jnp.asarray(d), jnp.asarray(p)[:, None],
                   jnp.asarray(p[..., 2])[:, None], jnp.broadcast_to(jnp.arange(4), (50, 1, 4)),
                   0.3)
    assert np.all(np.isinf(np.asarray(t)))


def test_an_isopolygon_collapsed_to_a_segment_gets_no_hits_along_its_line():
    # values (2, 2, 0, 0) at iso 2: the level set is the tet edge v0 v1 alone (the >= case's
    # quad collapses onto it); rays through that edge's line, within rounding, on and
    # beyond the edge must not be taken as hits of a polygon there (its two sides are the
    # same number with opposite signs: a rounding allowance would accept the whole line)
    rng = np.random.default_rng(5)
    p = (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
         + rng.uniform(-0.2, 0.2, (4, 3))).astype(np.float32)
    s = np.repeat(np.float32([0.5, 0.25, 3.0, -2.0]), 10)
    on_line = (p[0] + s[:, None] * (p[1] - p[0])).astype(np.float32)
    o = (on_line + rng.normal(size=(len(s), 3))).astype(np.float32)
    n = len(s)
    t = _polygon_t(jnp.asarray(o), jnp.asarray(on_line - o),
                   jnp.broadcast_to(jnp.asarray(p), (n, 1, 4, 3)),
                   jnp.broadcast_to(jnp.float32([2, 2, 0, 0]), (n, 1, 4)),
                   jnp.broadcast_to(jnp.arange(4), (n, 1, 4)), 2.0)
    assert np.all(np.isinf(np.asarray(t)))


def test_refit_for_a_new_time_step_or_moved_vertices_equals_a_rebuild():
    steps = data.time_series(POINTS, 3)
    mesh = tet_mesh(POINTS, TETS, steps)
    rays, _, _ = _camera()
    scene = TetIsosurface(mesh, [0.0, 0.4])
    for step in (1, 2):
        refit = _trace(scene.with_time_step(step), rays)
        rebuilt = _trace(TetIsosurface(mesh, [0.0, 0.4], time_step=step), rays)
        np.testing.assert_array_equal(refit.hit, rebuilt.hit)
        np.testing.assert_array_equal(refit.t, rebuilt.t)
    moved = data.deform(POINTS, 1.0)
    refit = _trace(scene.with_points(moved), rays)
    rebuilt = _trace(TetIsosurface(tet_mesh(moved, TETS, steps), [0.0, 0.4]), rays)
    np.testing.assert_array_equal(refit.hit, rebuilt.hit)
    np.testing.assert_allclose(refit.t, rebuilt.t, rtol=1e-6)


def test_time_step_and_isovalue_changes_do_not_retrace():
    mesh = tet_mesh(POINTS, TETS, data.time_series(POINTS, 3))
    rays, _, _ = _camera()
    traces = []

    @jax.jit
    def frame(scene, step, iso):
        traces.append(1)
        return ji.intersect(scene.with_time_step(step).with_isovalues(iso), rays).t

    scene = TetIsosurface(mesh, [0.0])
    outs = [frame(scene, s, jnp.array([i])) for s in (0, 2) for i in (0.0, 0.3)]
    assert len(traces) == 1
    assert not np.array_equal(outs[0], outs[3])


def test_depth_is_differentiable_in_isovalue_and_vertex_values():
    values = data.sphere_field(POINTS)
    rays, o, d = _camera()
    mesh = tet_mesh(POINTS, TETS, values)

    def depth(iso, vals):
        scene = _with_values(TetIsosurface(mesh, [0.0]), vals).with_isovalues(iso)
        return ji.intersect(scene, rays).t

    iso = jnp.array([0.02])
    t, dt = jax.jvp(lambda s: depth(s, jnp.asarray(values)[None]), (iso,), (jnp.ones(1),))
    def fd(h):
        t = [ref.first_hits(POINTS.astype(np.float64), TETS, values.astype(np.float64), o, d,
                            [0.02 + s])[0] for s in (-h, h)]
        with np.errstate(invalid="ignore"):
            return (t[1] - t[0]) / (2 * h)

    # central differences of the float64 reference; rays whose hit changes tet or surface
    # within the step (silhouettes) disagree between two steps and are left out
    fd1, fd2 = fd(1e-3), fd(5e-4)
    ok = (np.isfinite(np.asarray(t)) & np.isfinite(fd1)
          & (np.abs(fd1 - fd2) <= 1e-3 * np.abs(fd1) + 1e-6))
    assert ok.sum() > 40
    np.testing.assert_allclose(np.asarray(dt)[ok], fd1[ok], rtol=1e-3, atol=1e-5)
    # raising every vertex value by c moves the surface like lowering the isovalue by c
    _, dv = jax.jvp(lambda v: depth(iso, v), (jnp.asarray(values)[None],),
                    (jnp.ones((1, len(values))),))
    np.testing.assert_allclose(np.asarray(dv)[ok], -np.asarray(dt)[ok], rtol=1e-4, atol=1e-6)


def _with_values(scene, values):
    """The scene with traced vertex values (same BVH: bounds are not differentiated)."""
    return scene.replace(mesh=dataclasses.replace(scene.mesh, values=values))


def test_degenerate_and_inverted_tets_are_reported_and_handled():
    values = data.sphere_field(POINTS)
    flat = np.array([[0, 1, 2, 3]], np.int32)  # the first grid points are collinear
    inverted = TETS[:5][:, [1, 0, 2, 3]]
    tets = np.concatenate([TETS, flat, inverted])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = tet_mesh(POINTS, tets, values)
    assert any("degenerate" in str(w.message) or "invert" in str(w.message) for w in caught)
    rays, _, _ = _camera()
    base = _trace(TetIsosurface(tet_mesh(POINTS, TETS, values), 0.0), rays)
    hits = ji.intersect(TetIsosurface(mesh, 0.0), rays)
    np.testing.assert_array_equal(hits.hit, base.hit)
    np.testing.assert_allclose(hits.t, base.t, rtol=1e-6)


def test_bad_input_is_a_clear_error():
    mesh = tet_mesh(POINTS, TETS, data.sphere_field(POINTS))
    with pytest.raises(TypeError, match="TetMesh"):
        TetIsosurface((POINTS, TETS), 0.0)
    with pytest.raises(ValueError, match="time_step"):
        TetIsosurface(mesh, 0.0, time_step=3)
    with pytest.raises(ValueError, match="isovalues"):
        TetIsosurface(mesh, [np.nan])
    with pytest.raises((IndexError, ValueError)):
        tet_mesh(POINTS, TETS + len(POINTS), data.sphere_field(POINTS))


def test_render_four_isosurfaces_with_clip_box_transparency_and_shadows():
    values = data.wave_field(POINTS)
    scene = TetIsosurface(tet_mesh(POINTS, TETS, values), [-0.6, -0.2, 0.2, 0.6],
                          clip_box=((0, 0, 0), (1, 1, 0.7)), normals="smooth")
    cam = ji.Camera.look_at(EYE, (0.5, 0.5, 0.5), (0, 0, 1), fov=40, width=16, height=16)
    colors = np.array([[0.9, 0.2, 0.2], [0.9, 0.7, 0.2], [0.2, 0.7, 0.9], [0.3, 0.3, 0.9]])
    img = ji.render(scene, cam, shading=ji.Shading(colors=colors, layers=3, opacity=0.5))
    lit = ji.render(scene, cam, shading=ji.Shading(colors=colors, shadows=True))
    assert np.all(np.isfinite(img)) and np.all(np.isfinite(lit))
    hits = ji.intersect(scene, cam.rays())
    assert len(set(np.asarray(hits.surface)[np.asarray(hits.hit)].tolist())) >= 3
