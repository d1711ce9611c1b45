"""VolumeIsosurface against the independent float64 reference (tests/reference_volume64.py),
the dense macrocell-grid baseline, and the failure cases of structured volumes."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_volume64 as ref

import jaxiso as ji
from jaxiso.volume import (
    MacrocellGrid,
    OctreeVolume,
    VolumeIsosurface,
    VolumeSequence,
    data,
    lod_for,
)

W = 20
SPACING = np.array([0.1, 0.12, 0.09])
ORIGIN = np.array([-0.3, 0.2, 0.1])


def _view(shape, eye_dir=(1.6, 1.1, 0.9), inside=False):
    """A camera looking at the volume's centre, and its float64 reference rays."""
    centre = ORIGIN + SPACING * (np.array(shape) - 1) / 2
    reach = np.max(SPACING * np.array(shape))
    eye = centre + (0.15 if inside else 1.0) * np.array(eye_dir) * reach
    cam = ji.Camera.look_at(eye, centre, (0, 0, 1), fov=50 if inside else 40, width=W,
                            height=W)
    o, d = ref.camera_rays(eye, centre, (0, 0, 1), 50 if inside else 40, W, W)
    return cam, o, d


_trace = jax.jit(lambda scene, rays: ji.intersect(scene, rays, plan=ji.Plan(tile=8)))
# the whole image as one queue on 64 persistent lanes, then 32 for the tail
_trace_lanes = jax.jit(lambda scene, rays: ji.intersect(scene, rays,
                                                        plan=ji.Plan(tile=8, lanes=64)))


def _compare(arr, iso, volume, *, inside=False, lanes=False, **scene_options):
    """Hit masks must agree exactly; depths within 1e-4 voxel widths."""
    cam, o, d = _view(arr.shape, inside=inside)
    with np.errstate(invalid="ignore"):
        t_ref, h_ref, w_ref = ref.first_hits(np.asarray(arr, np.float64), o, d, iso,
                                             spacing=SPACING, origin=ORIGIN)
    trace = _trace_lanes if lanes else _trace
    hits = trace(VolumeIsosurface(volume, iso, **scene_options), cam.rays().reshape((W * W,)))
    hit, t = np.asarray(hits.hit), np.asarray(hits.t)
    assert np.array_equal(hit, h_ref), f"{int((hit != h_ref).sum())} pixels differ"
    err = np.abs(t[hit] - t_ref[hit]) * np.linalg.norm(d[hit], axis=-1) / SPACING.min()
    assert err.max(initial=0.0) <= 1e-4, err.max()
    assert np.array_equal(np.asarray(hits.surface)[hit], w_ref[hit])
    assert np.all(np.isfinite(np.asarray(hits.normal)))
    return hits, h_ref


def _random(shape, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, shape).astype(np.float32)


def test_octree_matches_reference_marschner_lobb():
    arr = data.marschner_lobb(17)
    hits, h_ref = _compare(arr, [0.5], OctreeVolume.from_array(arr, spacing=SPACING,
                                                                origin=ORIGIN))
    assert h_ref.sum() > 40


@pytest.mark.parametrize("traversal, method, lanes", [("neighbor", "analytic", False),
                                                      ("restart", "neubauer", False),
                                                      ("neighbor", "neubauer", True)])
def test_octree_matches_reference_two_isovalues(traversal, method, lanes):
    arr = _random((9, 7, 6))
    vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
    _compare(arr, [0.1, -0.3], vol, traversal=traversal, method=method, lanes=lanes)


def test_grid_baseline_and_octree_agree_on_integer_data_at_voxel_isovalues():
    # isovalues exactly equal to voxel values (uint8 0..3), and constant regions
    arr = np.random.default_rng(1).integers(0, 4, (12, 10, 9)).astype(np.uint8)
    arr[:6, :5] = 2
    oct_hits, _ = _compare(arr, [2.0, 1.0], OctreeVolume.from_array(arr, spacing=SPACING,
                                                                     origin=ORIGIN))
    grid = MacrocellGrid.from_array(arr, spacing=SPACING, origin=ORIGIN, levels=(2,))
    grid_hits, _ = _compare(arr, [2.0, 1.0], grid)
    np.testing.assert_allclose(oct_hits.t, grid_hits.t, rtol=1e-6)


def test_non_finite_voxels_are_missing_data_and_the_image_is_finite():
    arr = _random((8, 8, 8), seed=2)
    arr[3, 4, 2] = np.nan
    arr[5, 1:4, 6] = np.inf
    arr[2, 6, 5] = -np.inf
    vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
    _compare(arr, [0.0], vol)
    cam, _, _ = _view(arr.shape)
    img = ji.render(VolumeIsosurface(vol, 0.0), cam, shading=ji.Shading(shadows=True))
    assert np.all(np.isfinite(img))


def test_camera_inside_the_volume():
    arr = data.sphere_distance((10, 9, 8), radius=0.3)
    _compare(arr, [0.05], OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN),
             inside=True)


def test_constant_volumes_and_volumes_without_cells_have_no_hits():
    cam, _, _ = _view((6, 6, 6))
    rays = cam.rays().reshape((W * W,))
    for arr, iso in [(np.full((6, 6, 6), 3.0, np.float32), 3.0),
                     (np.full((6, 6, 6), 3.0, np.float32), 2.0),
                     (_random((1, 6, 6)), 0.0), (_random((6, 6, 1)), 0.0)]:
        vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
        hits = _trace(VolumeIsosurface(vol, iso), rays)
        assert not np.any(hits.hit)
        assert np.all(np.isinf(hits.t))


def test_rays_along_cell_faces_and_edges_hit_a_linear_field_exactly():
    # F = x + 2 y + 3 z is reproduced exactly by trilinear interpolation; orthographic
    # rays along -x run exactly on grid planes (y or z integer) and grid edges (both).
    n = 7
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float32)] * 3, indexing="ij")
    vol = OctreeVolume.from_array(i + 2 * j + 3 * k)
    yz = np.array([(y, z) for y in (0.0, 1.0, 2.5, 3.0, 6.0) for z in (0.0, 2.0, 4.5, 6.0)],
                  np.float32)
    o = np.stack([np.full(len(yz), 20.0, np.float32), yz[:, 0], yz[:, 1]], -1)
    d = np.tile(np.array([[-1.0, 0.0, 0.0]], np.float32), (len(yz), 1))
    iso = 9.5
    hits = ji.intersect(VolumeIsosurface(vol, iso), ji.Rays(jnp.asarray(o), jnp.asarray(d)))
    x = iso - 2 * yz[:, 0] - 3 * yz[:, 1]
    expect = (x >= 0) & (x <= n - 1)
    assert np.array_equal(np.asarray(hits.hit), expect)
    np.testing.assert_allclose(np.asarray(hits.t)[expect], 20.0 - x[expect], atol=2e-5)


def test_bad_input_is_a_clear_error():
    vol = OctreeVolume.from_array(_random((4, 4, 4)))
    with pytest.raises(TypeError, match="OctreeVolume"):
        VolumeIsosurface(np.zeros((4, 4, 4)), 0.0)
    with pytest.raises(ValueError, match="finite"):
        VolumeIsosurface(vol, [0.0, np.nan])
    with pytest.raises(ValueError, match="method"):
        VolumeIsosurface(vol, 0.0, method="newton")
    with pytest.raises(ValueError):
        OctreeVolume.from_array(np.zeros((0, 3, 3)))
    with pytest.raises(TypeError):
        OctreeVolume.from_array(np.zeros((3, 3, 3), np.complex64))


def test_crossings_on_cell_faces_leave_no_cracks():
    # Rays aimed at points of cell faces where the trilinear field equals the isovalue
    # (found in float64 on the face, where F is bilinear): each must hit there or before.
    # Two float32 evaluations of F at a shared face can put such a root outside both
    # cells' [0, s1]; a 512^3 mixing-layer image lost 1 pixel in 4096 that way.
    rng = np.random.default_rng(21)
    arr = rng.uniform(-1, 1, (9, 9, 9)).astype(np.float32)
    vol = OctreeVolume.from_array(arr)
    targets, dirs = [], []
    while len(targets) < 512:
        axis = rng.integers(3)
        cell = rng.integers(0, 8, 3)
        cell[axis] = rng.integers(1, 8)  # an interior face: the plane x_axis = cell[axis]
        u, v = [a for a in range(3) if a != axis]
        a = rng.uniform()
        face = arr.astype(np.float64)
        idx = [slice(None)] * 3
        idx[axis] = cell[axis]
        face = face[tuple(idx)]  # [9, 9] over axes (u, v)
        f00, f10 = face[cell[u], cell[v]], face[cell[u] + 1, cell[v]]
        f01, f11 = face[cell[u], cell[v] + 1], face[cell[u] + 1, cell[v] + 1]
        g0, g1 = f00 + a * (f10 - f00), f01 + a * (f11 - f01)  # F along v at u = a
        if g0 * g1 >= 0:
            continue
        b = g0 / (g0 - g1)
        point = cell.astype(np.float64)
        point[u], point[v] = cell[u] + a, cell[v] + b
        d = rng.normal(size=3)
        d[axis] = np.sign(d[axis] or 1.0) * max(abs(d[axis]), 0.3)  # crosses the face
        targets.append(point)
        dirs.append(d / np.linalg.norm(d))
    targets, dirs = np.array(targets), np.array(dirs)
    o = (targets - 3.0 * dirs).astype(np.float32)
    d = dirs.astype(np.float32)
    # float32 rays pass ~1e-6 voxels off their target: a ray nearly tangent there may
    # then miss it; the reference traces the same float32 rays
    t_ref, h_ref, _ = ref.first_hits(arr.astype(np.float64), o.astype(np.float64),
                                     d.astype(np.float64), [0.0], spacing=np.ones(3),
                                     origin=np.zeros(3))
    assert np.sum(np.abs(t_ref - 3.0) < 1e-5) > 100  # first crossing at the target
    hits = _trace(VolumeIsosurface(vol, 0.0), ji.Rays(jnp.asarray(o), jnp.asarray(d)))
    t = np.asarray(hits.t)
    late = h_ref & ~(t <= t_ref + 1e-4)
    assert not late.any(), f"{int(late.sum())} rays passed a crossing the reference finds"


def test_clip_box_removes_hits_outside():
    arr = data.sphere_distance((10, 10, 10), radius=0.3)
    vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
    cam, o, d = _view(arr.shape)
    # keep x <= the sphere's centre: rays enter through the cut inside the sphere and
    # hit its far half from within
    top = ORIGIN + SPACING * np.array([4.5, 9.0, 9.0])
    rays = cam.rays().reshape((W * W,))
    clipped = ji.intersect(VolumeIsosurface(vol, 0.0, clip_box=(ORIGIN, top)), rays)
    full = ji.intersect(VolumeIsosurface(vol, 0.0), rays)
    p = np.asarray(rays.at(clipped.t))[np.asarray(clipped.hit)]
    assert np.asarray(clipped.hit).sum() > 10
    assert np.all(p <= top + 1e-4) and np.all(p >= ORIGIN - 1e-4)
    # hits inside the box are kept where nothing in front was cut away
    q = np.asarray(rays.at(full.t))
    kept = np.asarray(full.hit) & np.all(q <= top - 1e-3, axis=-1)
    np.testing.assert_allclose(np.asarray(clipped.t)[kept], np.asarray(full.t)[kept], rtol=1e-6)


def test_central_difference_normals_are_smooth_and_close_to_trilinear():
    arr = data.sphere_distance((12, 12, 12), radius=0.3)
    vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
    cam, _, _ = _view(arr.shape)
    rays = cam.rays().reshape((W * W,))
    fwd = ji.intersect(VolumeIsosurface(vol, 0.0), rays)
    ctr = ji.intersect(VolumeIsosurface(vol, 0.0, normals="central"), rays)
    hit = np.asarray(fwd.hit)
    cos = np.sum(np.asarray(fwd.normal) * np.asarray(ctr.normal), -1)[hit]
    assert cos.min() > 0.9
    # the field is a sphere distance in unit-cube coordinates w, stretched by the
    # anisotropic spacing: its exact world gradient is (w - 1/2) / |w - 1/2| / extent
    extent = SPACING * (np.array(arr.shape) - 1)
    w = (np.asarray(rays.at(fwd.t))[hit] - ORIGIN) / extent
    exact = (w - 0.5) / extent
    exact /= np.linalg.norm(exact, axis=-1, keepdims=True)
    agree = {name: np.median(np.sum(np.asarray(h.normal)[hit] * exact, -1))
             for name, h in (("trilinear", fwd), ("central", ctr))}
    assert agree["central"] > 0.995 and agree["trilinear"] > 0.98, agree


def test_hits_are_differentiable_in_isovalue_and_voxel_values():
    arr = data.sphere_distance((8, 8, 8), radius=0.3).astype(np.float32)
    vol = OctreeVolume.from_array(arr, spacing=SPACING, origin=ORIGIN)
    cam, o, d = _view(arr.shape)
    rays = cam.rays().reshape((W * W,))

    def depth(iso, vol):
        return ji.intersect(VolumeIsosurface(vol, iso), rays).t

    t0 = depth(0.02, vol)
    hit = np.asarray(jnp.isfinite(t0))
    dt_diso = jax.jvp(lambda s: depth(s, vol), (0.02,), (1.0,))[1]
    h = 1e-3
    t_ref = [ref.first_hits(arr.astype(np.float64), o, d, [0.02 + s], spacing=SPACING,
                            origin=ORIGIN)[0] for s in (-h, h)]
    fd = (t_ref[1] - t_ref[0]) / (2 * h)
    ok = hit & np.isfinite(fd)
    np.testing.assert_allclose(np.asarray(dt_diso)[ok], fd[ok], rtol=2e-2, atol=1e-3)
    # voxel values: raise every voxel by c -> same as lowering the isovalue by c
    bump = jax.tree_util.tree_map(lambda a: a, vol)
    tangent = jax.tree_util.tree_map(
        lambda a: jnp.ones_like(a) if a.dtype == jnp.float32 and a.ndim == 2 else
        np.zeros(a.shape, jax.dtypes.float0) if not jnp.issubdtype(a.dtype, jnp.floating)
        else jnp.zeros_like(a), bump)
    dt_dvox = jax.jvp(lambda v: depth(0.02, v), (vol,), (tangent,))[1]
    np.testing.assert_allclose(np.asarray(dt_dvox)[hit], -np.asarray(dt_diso)[hit],
                               rtol=1e-3, atol=1e-5)


def test_level_of_detail_matches_full_resolution_when_fine_and_is_close_when_coarse():
    arr = data.sphere_distance(33, radius=0.3)
    vol = OctreeVolume.from_array(arr, spacing=1 / 32)
    cam = ji.Camera.look_at((2.2, 1.6, 1.3), (0.5, 0.5, 0.5), fov=30, width=24, height=24)
    rays = cam.rays().reshape((24 * 24,))
    full = _trace(VolumeIsosurface(vol, 0.0), rays)
    fine = _trace(VolumeIsosurface(vol, 0.0, lod=lod_for(cam, 1e-3)), rays)
    np.testing.assert_array_equal(full.hit, fine.hit)
    np.testing.assert_allclose(fine.t, full.t, rtol=1e-6)
    # dP/dV = 2: coarse cells up to a few voxels wide; coarse voxels sit at their
    # node's min corner (the seed's layout), which shifts the surface by up to half a
    # coarse cell
    for smooth in (True, False):
        coarse = _trace(VolumeIsosurface(vol, 0.0, lod=lod_for(cam, 2.0, smooth=smooth)),
                        rays)
        both = np.asarray(full.hit & coarse.hit)
        assert both.sum() >= 0.9 * np.asarray(full.hit).sum()
        dist = np.abs(np.asarray(coarse.t - full.t))[both] * np.linalg.norm(
            np.asarray(rays.direction)[both], axis=-1) * 32
        assert np.median(dist) < 2.0 and dist.max() < 8.0, (smooth, dist)


def test_level_of_detail_does_not_cull_nodes_whose_coarse_cells_hold_the_surface():
    # the fine [min, max] of a node does not bound coarse corners from its neighbours:
    # culling by it punched holes through a mixing layer at dP/dV = 2
    vol = OctreeVolume.from_array(data.mixing(32, seed=0, time=2.0), spacing=1 / 31)
    cam = ji.Camera.look_at((3.2, 2.4, 2.6), (0.5, 0.5, 0.5), fov=30, width=48, height=48)
    rays = cam.rays().reshape((48 * 48,))
    full = np.asarray(_trace(VolumeIsosurface(vol, 128.0), rays).hit).reshape(48, 48)
    inner = full.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= np.roll(np.roll(full, dy, 0), dx, 1)
    lod = _trace(VolumeIsosurface(vol, 128.0, lod=lod_for(cam, 2.0)), rays)
    assert inner.sum() > 100
    assert not np.any(inner & ~np.asarray(lod.hit).reshape(48, 48))


def test_shadow_rays_trace_a_coarser_level_of_detail():
    # render passes shadow rays eps * shadow_eps_scale; with level of detail that scales
    # dP/dV (seed Sec. 4.5.2): the same hits as the scene at that coarser quality
    vol = OctreeVolume.from_array(data.mixing(32, seed=0, time=2.0), spacing=1 / 31)
    cam = ji.Camera.look_at((3.2, 2.4, 2.6), (0.5, 0.5, 0.5), fov=30, width=24, height=24)
    rays = cam.rays().reshape((24 * 24,))
    lod = lod_for(cam, 0.5)
    scene = VolumeIsosurface(vol, 128.0, lod=lod)
    shadow = jax.jit(lambda s, r: ji.intersect(s.coarser(8.0), r, plan=ji.Plan(tile=8)))(
        scene, rays)
    coarse = _trace(scene.with_lod(lod.coarser(8.0)), rays)
    fine = _trace(scene, rays)
    np.testing.assert_array_equal(np.asarray(shadow.hit), np.asarray(coarse.hit))
    np.testing.assert_array_equal(np.asarray(shadow.t), np.asarray(coarse.t))
    assert np.any(np.asarray(shadow.t) != np.asarray(fine.t))  # eps did coarsen it


def test_sequence_switches_time_step_without_retrace():
    frames = [data.mixing(12, seed=0, time=t) for t in (0.0, 2.0, 4.0)]
    seq = VolumeSequence.from_arrays(frames, spacing=1 / 11)
    assert seq.n_steps == 3 and seq.nbytes <= seq.padded_nbytes
    assert math.isclose(seq.compression_ratio, seq.raw_nbytes / seq.nbytes)
    cam = ji.Camera.look_at((2.0, 1.5, 1.6), (0.5, 0.5, 0.5), fov=35, width=16, height=16)
    rays = cam.rays().reshape((256,))
    traces = []

    @jax.jit
    def at_step(seq, step, iso):
        traces.append(1)
        return ji.intersect(VolumeIsosurface(seq.at(step), iso), rays).t

    for step, frame in enumerate(frames):
        for iso in (100.0, 160.0):
            t = at_step(seq, step, iso)
            single = ji.intersect(VolumeIsosurface(OctreeVolume.from_array(
                frame, spacing=1 / 11), iso), rays).t
            np.testing.assert_array_equal(np.asarray(t), np.asarray(single))
    assert len(traces) == 1


def test_render_multiple_isovalues_transparency_and_no_retrace_on_isovalue_change():
    arr = data.marschner_lobb(17)
    vol = OctreeVolume.from_array(arr, spacing=2 / 16, origin=-1)
    cam = ji.Camera.look_at((2.5, 1.8, 1.5), (0, 0, 0), fov=40, width=16, height=16)
    shading = ji.Shading(layers=2, opacity=0.5)
    a = ji.render(VolumeIsosurface(vol, [0.3, 0.6]), cam, shading=shading)
    b = ji.render(VolumeIsosurface(vol, [0.35, 0.6]), cam, shading=shading)
    assert np.all(np.isfinite(a)) and not np.array_equal(a, b)
    assert a.shape == (16, 16, 3)


def test_a_voxel_frame_must_place_the_volume_at_its_origin():
    """A brick traces rays in the whole volume's frame (origin, offset of its first voxel);
    a frame that puts the voxels elsewhere than the volume's own origin, or half a frame,
    is refused (a brick whose volume was replaced would draw in the wrong place)."""
    vol = OctreeVolume.from_array(np.random.default_rng(0).random((5, 5, 5)), spacing=0.5,
                                  origin=(1.0, 2.0, 3.0), progress=False)
    scene = VolumeIsosurface(vol, 0.5, frame=((0.0, 2.0, 3.0), (2, 0, 0)))  # 0 + 2 * 0.5
    assert scene.frame_offset.tolist() == [2, 0, 0]
    with pytest.raises(ValueError, match="frame puts"):
        VolumeIsosurface(vol, 0.5, frame=((0.0, 0.0, 0.0), (0, 0, 0)))
    with pytest.raises(ValueError, match="go together"):
        scene.replace(frame_origin=None)
