"""The tape path inside `intersect` / `render` (jaxiso.implicit._tape_rays, `Plan.tape`).

References: the straight path (t-bisection with f's interval extension inlined: the same
pieces, so t must agree exactly), and float64 numpy sampling of the program
(tests/reference_program64.py) for hit masks.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_program64 import first_inside64, vm64

import jaxiso as ji
from jaxiso.implicit import surfaces
from jaxiso.implicit.generate import csg_program

TAPE = ji.Plan(tile=16, tape=True)
STRAIGHT = ji.Plan(tile=4)


def _compare(a, b, eps):
    """Hits of the two paths (unit ray directions): same masks; t on the same final piece
    for nearly every ray, never more than two pieces apart (the paths pad piece boxes
    differently, so a piece at the edge of containing the level can go either way);
    normals and surfaces equal where both end on the same piece."""
    ha, hb = np.asarray(a.hit), np.asarray(b.hit)
    np.testing.assert_array_equal(ha, hb)
    both = ha & hb
    ta, tb = np.asarray(a.t)[both], np.asarray(b.t)[both]
    same = np.abs(ta - tb) <= 1e-6 * (1 + np.abs(tb))
    assert same.mean() >= 0.98
    assert np.all(np.abs(ta - tb) <= 2 * float(eps))
    dot = np.sum(np.asarray(a.normal)[both] * np.asarray(b.normal)[both], axis=-1)
    assert np.all(dot[same] > 0.999)
    np.testing.assert_array_equal(np.asarray(a.surface), np.asarray(b.surface))


def test_generated_csg_same_hits_as_straight_and_float64():
    prog = csg_program(20, seed=1)
    lo, hi = (-1.6,) * 3, (1.6,) * 3
    S = ji.ImplicitSurface(prog, lo, hi, arithmetic="interval")
    cam = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=40, height=40)
    rays = cam.rays()
    tape = ji.intersect(S, rays, plan=TAPE)
    _compare(tape, ji.intersect(S, rays, plan=STRAIGHT), S.eps)
    ref_hit, ref_t = first_inside64(prog.ops, np.asarray(rays.origin).reshape(-1, 3),
                                    np.asarray(rays.direction).reshape(-1, 3), lo, hi,
                                    samples=1024)
    hit = np.asarray(tape.hit).reshape(-1)
    assert 0.2 < ref_hit.mean() < 0.8
    assert np.mean(hit == ref_hit) >= 0.995
    both = hit & ref_hit
    step = 2 * 1.6 * np.sqrt(3) / 1024
    assert np.max(np.abs(np.asarray(tape.t).reshape(-1)[both] - ref_t[both])) < 2 * step


@pytest.mark.parametrize("name,arithmetic", [("sphere", "interval"),
                                             ("barth_sextic", "affine")])
def test_catalogue_surfaces_same_hits_both_paths(name, arithmetic):
    """Interval (two isovalues) and affine forms on the tape (interval on a long program
    is the generated-CSG test's)."""
    S = surfaces.scene(name, arithmetic=arithmetic,
                       isovalues=(0.0, 0.25) if name == "sphere" else (0.0,))
    rays = surfaces.camera(name, 32).rays()
    _compare(ji.intersect(S, rays, plan=TAPE), ji.intersect(S, rays, plan=STRAIGHT), S.eps)


def test_t_min_t_max_and_verify_policy_on_the_tape_path():
    s = surfaces.get("sphere")
    S = ji.ImplicitSurface(s.f, s.lo, s.hi, arithmetic="interval")
    o = jnp.array([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.3, 0.0, 3.0]])
    d = jnp.array([[0.0, 0.0, -1.0]] * 4)
    rays = ji.Rays(o, d)
    t_min = jnp.array([0.0, 2.5, 0.0, 0.0])
    t_max = jnp.array([jnp.inf, jnp.inf, 1.5, jnp.inf])
    a = ji.intersect(S, rays, t_min=t_min, t_max=t_max, plan=TAPE)
    b = ji.intersect(S, rays, t_min=t_min, t_max=t_max, plan=STRAIGHT)
    _compare(a, b, S.eps)
    assert list(np.asarray(a.hit)) == [True, True, False, True]
    # a flat f whose intervals hold 0 everywhere: no verified hit, "none" accepts them
    flat = ji.ImplicitSurface(lambda x, y, z: (x - x) * 1e-9 + 1.0 + (y - y), (-1,) * 3,
                              (1,) * 3, arithmetic="interval")
    r = ji.Rays(jnp.array([[0.1, 0.2, 3.0]]), jnp.array([[0.0, 0.0, -1.0]]))
    assert not bool(ji.intersect(flat, r, plan=TAPE).hit[0])


def test_touching_pieces_rechecked_apart_on_the_tape_path():
    """A sphere whose f crosses its level beside one whose f only touches it (squared):
    the touching pieces fail the sign test and are rechecked apart from the others
    (`_tape_rays._recheck`); hits as the straight path's, which checks every piece."""
    def f(x, y, z):
        crossing = (x + 0.5) ** 2 + y * y + z * z - 0.09
        touching = ((x - 0.5) ** 2 + y * y + z * z - 0.09) ** 2
        return jnp.minimum(crossing, touching)

    S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, arithmetic="interval")
    u = np.linspace(-0.95, 0.95, 20, dtype=np.float32)
    x, y = np.meshgrid(u, u)
    o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0, np.float32)], -1)
    rays = ji.Rays(jnp.asarray(o), jnp.broadcast_to(jnp.array([0.0, 0.0, -1.0]), o.shape))
    a = ji.intersect(S, rays, plan=TAPE)
    _compare(a, ji.intersect(S, rays, plan=STRAIGHT), S.eps)
    inside = (x.ravel() - 0.5) ** 2 + y.ravel() ** 2 < 0.08  # clear of the rim
    assert np.all(np.asarray(a.hit)[inside])


def test_group_boxes_hold_every_ray_point_of_their_slabs():
    """`_tape_rays._group_boxes` (boxes blended from the hulls of a group's entry and exit
    points) holds each ray's points on the slab within the scene's box, p + s D at 65
    values of s, in float64, for perspective rays from several cameras (groups of 16 and
    64 rays, 4 slabs)."""
    from jaxiso.implicit import _tape_rays as tr
    from jaxiso.render import to_zorder
    lo, hi = jnp.full(3, -1.0), jnp.full(3, 1.0)
    for eye in [(3.0, 2.5, 2.0), (0.2, -2.8, 0.5), (0.1, 0.2, 0.3)]:  # the last inside
        cam = ji.Camera.look_at(eye, (0, 0, 0), fov=60.0, width=32, height=32)
        r = cam.rays()
        rays = ji.Rays(to_zorder(r.origin, 16), to_zorder(r.direction, 16))
        seg = tr._segments(rays, lo, hi, jnp.zeros(1024), jnp.full(1024, jnp.inf), 2.0**-11)
        _, _, inside, p, D, _ = (np.asarray(x, np.float64) for x in seg)
        pyramid = tr._group_hulls(seg, 64)
        assert sorted(pyramid) == [1, 4, 16, 64]
        for size in (1, 4, 16, 64):  # each size's hulls: the groups' own min / max
            ok = (inside > 0).reshape(-1, size, 1)
            for k, x in enumerate((p, p + D)):
                xs = np.asarray(x, np.float32).reshape(-1, size, 3)
                np.testing.assert_array_equal(np.asarray(pyramid[size][2 * k]),
                                              np.where(ok, xs, np.inf).min(axis=1))
                np.testing.assert_array_equal(np.asarray(pyramid[size][2 * k + 1]),
                                              np.where(ok, xs, -np.inf).max(axis=1))
        for size in (16, 64):
            hull = pyramid[size]
            g = jnp.repeat(jnp.arange(1024 // size, dtype=jnp.int32), 4)[None]
            s0 = jnp.tile(jnp.arange(4.0) / 4, 1024 // size)[None]
            blo, bhi, valid = (np.asarray(x) for x in tr._group_boxes(
                hull, g, s0, s0 + 0.25, lo, hi, jnp.ones(g.shape, bool)))
            s = np.linspace(0.0, 0.25, 65)
            for c in range(g.shape[1]):
                rays_c = np.arange(size) + int(g[0, c]) * size
                rays_c = rays_c[inside[rays_c] > 0]
                assert valid[0, c] == (rays_c.size > 0)
                if rays_c.size:
                    pts = p[rays_c, None] + (float(s0[0, c]) + s)[None, :, None] * D[rays_c, None]
                    pts = np.clip(pts, -1.0, 1.0)  # boxes are clipped to the scene's
                    assert np.all(pts >= blo[0, c]) and np.all(pts <= bhi[0, c])


def test_long_program_chooses_the_tape_plan_and_renders():
    prog = csg_program(60, seed=2)  # ~1,300 instructions: above the crossover
    lo, hi = (-1.6,) * 3, (1.6,) * 3
    S = ji.ImplicitSurface(prog, lo, hi).prepared()
    assert S.arithmetic == "interval" and "tape path" in S.arithmetic_report
    assert "median enclosure width" in S.arithmetic_report  # measured on the tape
    assert ji.plan_for(S, 1024).tape
    cam = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=24, height=24)
    hits = ji.intersect(S, cam.rays())
    ref_hit, _ = first_inside64(prog.ops, np.asarray(cam.rays().origin).reshape(-1, 3),
                                np.asarray(cam.rays().direction).reshape(-1, 3), lo, hi,
                                samples=1024)
    assert np.mean(np.asarray(hits.hit).reshape(-1) == ref_hit) >= 0.995
    img = np.asarray(ji.render(S, cam, shading=ji.Shading(shadows=True)))
    assert img.shape == (24, 24, 3) and np.all(np.isfinite(img))
    bg = np.asarray(ji.Shading().background)
    drawn = np.any(np.abs(img - bg) > 1e-6, axis=-1).reshape(-1)
    np.testing.assert_array_equal(drawn, np.asarray(hits.hit).reshape(-1))


# ~90 s on 2 cores; the tape path's render is checked in the suite by
# test_long_program_chooses_the_tape_plan_and_renders
@pytest.mark.heavy
def test_render_same_image_both_paths_with_shadows():
    prog = csg_program(12, seed=3)
    S = ji.ImplicitSurface(prog, (-1.6,) * 3, (1.6,) * 3, arithmetic="interval")
    cam = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=20, height=20)
    shading = ji.Shading(shadows=True)
    a = np.asarray(ji.render(S, cam, shading=shading, plan=TAPE))
    b = np.asarray(ji.render(S, cam, shading=shading, plan=STRAIGHT))
    assert np.mean(np.all(np.abs(a - b) <= 1e-4, axis=-1)) >= 0.99


def test_under_jit_and_vmap_the_tape_path_runs_in_a_callback():
    """Traced inputs (jit, vmap) run the host driver through jax.pure_callback: the same
    hits as the eager call, and no compile of the straight extension."""
    prog = csg_program(12, seed=3)
    S = ji.ImplicitSurface(prog, (-1.6,) * 3, (1.6,) * 3, arithmetic="interval")
    rays = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=16, height=16).rays()
    eager = ji.intersect(S, rays, plan=TAPE)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jitted = jax.jit(lambda r: ji.intersect(S, r, plan=TAPE))(rays)
    for a, b in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    counts = jax.vmap(lambda m: ji.intersect(S, rays, t_max=m, plan=TAPE).hit.sum())(
        jnp.array([jnp.inf, 3.2]))
    assert int(counts[0]) == int(eager.hit.sum()) > 0
    assert int(counts[1]) == int(ji.intersect(S, rays, t_max=3.2, plan=TAPE).hit.sum())
    assert int(counts[1]) < int(counts[0])


def test_tape_plan_bad_input():
    with pytest.raises(ValueError, match="tape must be a bool"):
        ji.Plan(tape=1)
    with pytest.raises(ValueError, match="lanes must be None"):
        ji.Plan(tape=True, lanes=64)
    vol = ji.VolumeIsosurface(ji.OctreeVolume.from_array(
        np.zeros((4, 4, 4), np.float32) + np.arange(4.0, dtype=np.float32)), 1.5)
    with pytest.raises(TypeError, match="ImplicitSurface programs only"):
        ji.intersect(vol, ji.Rays(jnp.zeros((1, 3)), jnp.ones((1, 3))), plan=TAPE)


def _long_sum(x, y, z, r):
    v = x * x + y * y + z * z - r
    for k in range(300):
        v = jnp.minimum(v, (x - 0.001 * k) ** 2 + y * y + z * z - r)
    return v


def test_short_and_param_functions_keep_the_straight_plan():
    s = surfaces.get("sphere")
    assert not ji.plan_for(ji.ImplicitSurface(s.f, s.lo, s.hi), 1024).tape
    box = dict(lo=(-1,) * 3, hi=(1,) * 3, arithmetic="interval")
    assert ji.plan_for(ji.ImplicitSurface(lambda x, y, z: _long_sum(x, y, z, 0.5), **box),
                       1024).tape
    scalar_params = ji.ImplicitSurface(_long_sum, params=jnp.float32(0.5), **box)
    assert ji.plan_for(scalar_params, 1024).tape  # scalar params: tape coordinates
    array_params = ji.ImplicitSurface(lambda x, y, z, p: _long_sum(x, y, z, p[0]),
                                      params=jnp.array([0.5, 0.1]), **box)
    assert not ji.plan_for(array_params, 1024).tape
    outward = ji.ImplicitSurface(lambda x, y, z: _long_sum(x, y, z, 0.5), rounding="outward",
                                 **box)
    assert not ji.plan_for(outward, 1024).tape  # tapes round like "fast"


def test_ift_derivatives_through_the_tape_path_match_float64():
    """Eager jax.grad runs the tape path on the primal values; t's derivative comes from
    the implicit function theorem: on the sphere x^2 + y^2 + z^2 = r the first hit of
    o + t d has dt/dr = -1 / (2 sqrt((o.d)^2 - |d|^2 (|o|^2 - r))) (float64, here)."""
    def f(x, y, z, p):
        return x * x + y * y + z * z - p["r"]

    params = dict(r=jnp.float32(0.5))
    S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params, arithmetic="interval")
    cam = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=12, height=12)
    rays = cam.rays()

    def loss(p, plan):
        h = ji.intersect(S.replace(params=p), rays, plan=plan)
        return jnp.sum(jnp.where(h.hit, h.t, 0.0)), h

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # eager grad: the tape path runs, no fallback
        (value, hits), grad = jax.value_and_grad(loss, has_aux=True)(params, TAPE)
    (value_s, hits_s), grad_s = jax.value_and_grad(loss, has_aux=True)(params, STRAIGHT)
    # jitted grad: the driver runs in a callback, derivatives through the custom JVP
    grad_j = jax.jit(jax.grad(lambda p: loss(p, TAPE)[0]))(params)
    np.testing.assert_allclose(float(grad_j["r"]), float(grad["r"]), rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(hits.hit), np.asarray(hits_s.hit))
    o = np.asarray(rays.origin, np.float64).reshape(-1, 3)
    d = np.asarray(rays.direction, np.float64).reshape(-1, 3)
    od = np.sum(o * d, axis=1)
    disc = od**2 - np.sum(d * d, axis=1) * (np.sum(o * o, axis=1) - 0.5)
    hit = np.asarray(hits.hit).reshape(-1)
    assert hit.sum() > 20 and np.all(disc[hit] > 0)
    expected = -np.sum(1.0 / (2.0 * np.sqrt(disc[hit])))
    np.testing.assert_allclose(float(grad["r"]), expected, rtol=2e-3)
    np.testing.assert_allclose(float(grad["r"]), float(grad_s["r"]), rtol=1e-3)
    # normals are differentiable too (straight point gradient at the hits)
    gn = jax.grad(lambda p: jnp.sum(ji.intersect(S.replace(params=p), rays,
                                                 plan=TAPE).normal[..., 0]))(params)
    assert np.isfinite(float(gn["r"]))


def _affine_pieces():
    """A 12-primitive CSG program, its tape, and 4 x 8 ray pieces as AF1 forms (one
    symbol): (prog, tape, centres, directions, coords, one region per row of pieces)."""
    from jaxiso.arith import _tape
    from jaxiso.arith._affine_type import Affine
    prog = csg_program(12, seed=3)
    tape = _tape.from_function(prog, 3)
    rng = np.random.default_rng(0)
    c = rng.uniform(-1, 1, (4, 8, 3)).astype(np.float32)
    D = (rng.normal(size=(4, 8, 3)) * 0.05).astype(np.float32)
    coords = [Affine(jnp.asarray(c[..., i]), jnp.asarray(D[..., i:i + 1]), jnp.zeros((4, 8)))
              for i in range(3)]
    tapes = _tape.take_regions(tape, jnp.zeros(4, jnp.int32))
    return prog, tape, c, D, coords, tapes


def test_affine_tape_evaluation_equals_the_affine_extension():
    """`_tape.evaluate` on AF1 forms computes what `extend(f, "affine")` computes (the
    registers keep the forms' bounds: without them 4 of 32 pieces chose differently)."""
    from jaxiso.arith import _tape

    prog, tape, c, D, coords, tapes = _affine_pieces()
    value, _ = jax.jit(lambda t, x: _tape.evaluate(t, x, True))(tapes, coords)
    ref = ji.extend(prog, "affine", n_symbols=1)(*coords)
    np.testing.assert_allclose(np.asarray(value.center), np.asarray(ref.center), atol=1e-6)
    np.testing.assert_allclose(np.asarray(value.dev), np.asarray(ref.dev), atol=1e-6)
    np.testing.assert_allclose(np.asarray(value.err), np.asarray(ref.err), atol=1e-6)


@pytest.mark.parametrize("depth", [40, 160])
def test_affine_tape_keeps_min_max_chains_bounded(depth):
    """A chain of `depth` unions and cuts of spheres (min/max of sqrt distances, as
    Prospero's and generated CSG's programs are): the tape's affine enclosures stay within
    2x the interval ones on every piece. Registers without the forms' bounds grew the
    error by a factor at each min whose operands overlap: 1e38 on Prospero."""
    from jaxiso.arith import _affine as aa
    from jaxiso.arith import _tape

    rng = np.random.default_rng(depth)
    centres = rng.uniform(-0.6, 0.6, (depth, 3))
    radii = rng.uniform(0.1, 0.3, depth)

    def f(x, y, z):
        out = None
        for i, (c, r) in enumerate(zip(centres, radii)):
            d = jnp.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
            out = d if out is None else (jnp.maximum(out, -d) if i % 5 == 4 else
                                         jnp.minimum(out, d))
        return out

    tape = _tape.from_function(f, 3)
    tapes = _tape.take_regions(tape, jnp.zeros(4, jnp.int32))
    c = rng.uniform(-0.8, 0.8, (4, 16, 3)).astype(np.float32)
    D = (rng.normal(size=(4, 16, 3)) * 0.1).astype(np.float32)
    affine = [aa.Affine(jnp.asarray(c[..., i]), jnp.asarray(D[..., i:i + 1]),
                        jnp.zeros((4, 16))) for i in range(3)]
    lo, hi = c - np.abs(D), c + np.abs(D)
    boxes = [ji.Interval(jnp.asarray(lo[..., i]), jnp.asarray(hi[..., i])) for i in range(3)]
    run = jax.jit(_tape.evaluate)
    wa = aa.to_interval(run(tapes, affine))
    wi = run(tapes, boxes)
    width_a = np.asarray(wa.hi - wa.lo)
    width_i = np.asarray(wi.hi - wi.lo)
    assert np.all(np.isfinite(width_a))
    assert np.all(width_a <= 2.0 * width_i + 1e-6), np.max(width_a / width_i)


def test_affine_tape_evaluation_encloses_float64_and_prunes():
    """`_tape.evaluate` on AF1 forms encloses f on the piece (float64 samples), and the
    min/max choices it records prune the tape to a program equal to f on the piece."""
    from jaxiso.arith import _affine as aa
    from jaxiso.arith import _tape

    prog, tape, c, D, coords, tapes = _affine_pieces()
    value, chosen = jax.jit(lambda t, x: _tape.evaluate(t, x, True))(tapes, coords)
    s = np.linspace(-1.0, 1.0, 21)
    pts = c[..., None, :].astype(np.float64) + s[:, None] * D[..., None, :]
    f64 = vm64(prog.ops, pts[..., 0], pts[..., 1], pts[..., 2])
    box = aa.to_interval(value)
    assert np.all(f64 >= np.asarray(box.lo)[..., None] - 1e-6)
    assert np.all(f64 <= np.asarray(box.hi)[..., None] + 1e-6)
    # one region per piece: prune each with its own choices, evaluate at the samples
    per_piece = _tape.take_regions(tape, jnp.zeros(32, jnp.int32))
    pruned = _tape.prune(per_piece, chosen.reshape(chosen.shape[0], 32))
    assert int(jnp.max(pruned.n)) < int(tape.n)  # some choices were proved
    xs = [jnp.asarray(pts[..., i].reshape(32, -1), jnp.float32) for i in range(3)]
    np.testing.assert_allclose(np.asarray(_tape.evaluate(pruned, xs)),
                               f64.reshape(32, -1), atol=1e-5)


def _budget_case():
    prog = csg_program(40, seed=7)
    S = ji.ImplicitSurface(prog, (-1.3,) * 3, (1.3,) * 3, arithmetic="interval")
    cam = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=32, height=32)
    rays = cam.rays().reshape((-1,))
    return S, rays, jnp.zeros(rays.shape), jnp.full(rays.shape, jnp.inf)


# ~170 s on 2 cores: every batch size is a compile of its own
@pytest.mark.heavy
def test_a_small_memory_budget_runs_in_batches_with_the_same_hits():
    """The tape path's regions run in batches sized from the budget: a budget a few
    hundred times smaller splits the work into many batches and finds the same hits."""
    S, rays, t_min, t_max = _budget_case()
    big, small = {}, {}
    a = S.intersect_tape(rays, t_min, t_max, stats=big)
    b = S.intersect_tape(rays, t_min, t_max, stats=small, budget=400_000)
    assert small["batches"] > 2 * big["batches"]
    np.testing.assert_array_equal(np.asarray(a.hit), np.asarray(b.hit))
    np.testing.assert_array_equal(np.asarray(a.t), np.asarray(b.t))


def test_a_budget_too_small_raises_naming_both_figures():
    """A budget too small for one region's tape raises MemoryError naming both figures,
    before any level runs; Plan refuses a budget under 1 MB."""
    S, rays, t_min, t_max = _budget_case()
    with pytest.raises(MemoryError, match="memory budget"):
        S.intersect_tape(rays, t_min, t_max, budget=20_000)
    with pytest.raises(ValueError, match="memory_budget"):
        ji.Plan(tape=True, memory_budget=1000)


def test_two_stage_pruning_gives_the_same_hits(monkeypatch):
    """Children of long tapes pruned first by their ray group's shared choices, then by
    their own, give bitwise the hits of pruning each child against its parent's tape
    (forced on for a 1,024-long tape; by default from 2,048) and the same tapes."""
    from jaxiso.implicit import _tape_rays

    S, rays, t_min, t_max = _budget_case()
    runs = {}
    for name, start in (("once", 10**9), ("twice", 0)):
        monkeypatch.setattr(_tape_rays, "SHARED_PRUNE_FROM", start)
        stats = {}
        runs[name] = (S.intersect_tape(rays, t_min, t_max, stats=stats), stats)
    (a, sa), (b, sb) = runs["once"], runs["twice"]
    assert int(np.asarray(a.hit).sum()) > 50
    np.testing.assert_array_equal(np.asarray(a.hit), np.asarray(b.hit))
    np.testing.assert_array_equal(np.asarray(a.t), np.asarray(b.t))
    np.testing.assert_array_equal(np.asarray(a.normal), np.asarray(b.normal))
    assert sa["levels"][0]["tape_max"] == sb["levels"][0]["tape_max"]


def test_stats_of_a_level_that_keeps_no_region():
    """A field that is positive over the whole box keeps no region at its first level;
    the stats still report that level (it raised 'need at least one array to
    concatenate')."""
    S = ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z + 1.0, (-1.0,) * 3,
                           (1.0,) * 3, arithmetic="interval")
    rays = ji.Camera.look_at((3.0, 2.5, 2.0), (0, 0, 0), width=8, height=8).rays()
    rays = rays.reshape((-1,))
    stats = {}
    hits = S.intersect_tape(rays, jnp.zeros(rays.shape), jnp.full(rays.shape, jnp.inf),
                            stats=stats)
    assert not np.asarray(hits.hit).any()
    assert stats["levels"][0]["kept"] == 0
    assert stats["levels"][0]["regions"] > 0 and stats["levels"][0]["tape_max"] == 0
