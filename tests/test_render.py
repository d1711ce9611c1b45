"""The render layer: cameras, packets, the intersect protocol, shading modalities,
sharding, retracing, and stability cases (axis-parallel rays, camera inside, misses,
NaN fields, division asymptotes)."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji

SIZE = 24


def sphere(x, y, z, params):
    return x * x + y * y + z * z - params["r"] ** 2


def _scene(**kw):
    kw.setdefault("params", {"r": jnp.float32(1.0)})
    kw.setdefault("arithmetic", "interval")  # built under vmap below: "auto" can't measure
    return ji.ImplicitSurface(sphere, (-1.5,) * 3, (1.5,) * 3, **kw)


def _analytic(o, d, r=1.0):
    """First root of |o + t d|^2 = r^2 in float64 (inf for none / behind)."""
    o = np.asarray(o, np.float64).reshape(-1, 3)
    d = np.asarray(d, np.float64).reshape(-1, 3)
    a = np.sum(d * d, -1)
    b = 2 * np.sum(o * d, -1)
    c = np.sum(o * o, -1) - r * r
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0))
    t1 = (-b - sq) / (2 * a)
    t2 = (-b + sq) / (2 * a)
    t = np.where(t1 >= 0, t1, t2)
    return np.where((disc >= 0) & (t >= 0), t, np.inf)


CAM = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 40.0, SIZE, SIZE)


def test_camera_rays_geometry():
    rays = CAM.rays()
    assert rays.shape == (SIZE, SIZE)
    np.testing.assert_allclose(np.linalg.norm(rays.direction, axis=-1), 1.0, rtol=1e-6)
    # the image centre looks at the target; row 0 is the top (up component largest)
    c = rays.direction[SIZE // 2 - 1:SIZE // 2 + 1, SIZE // 2 - 1:SIZE // 2 + 1].mean((0, 1))
    fwd = -np.array([3.0, 2.0, 1.5]) / np.linalg.norm([3.0, 2.0, 1.5])
    np.testing.assert_allclose(c / np.linalg.norm(c), fwd, atol=1e-3)
    assert rays.direction[0, SIZE // 2, 2] > rays.direction[-1, SIZE // 2, 2]
    ortho = ji.Camera.orthographic_view((0, 0, 5), (0, 0, 0), (0, 1, 0), 1.2, 8, 6)
    r = ortho.rays()
    assert r.shape == (6, 8)
    np.testing.assert_array_equal(np.asarray(r.direction), np.broadcast_to([0, 0, -1], (6, 8, 3)))
    np.testing.assert_allclose(np.asarray(r.origin)[..., 1].max(), 1.2 * (1 - 1 / 6), rtol=1e-6)


@pytest.mark.parametrize("bad", [dict(fov=0.0), dict(fov=180.0), dict(up=(3.0, 2.0, 1.5)),
                                 dict(eye=(0.0, 0.0, 0.0)), dict(width=0)])
def test_camera_rejects_bad_input(bad):
    kw = dict(eye=(3.0, 2.0, 1.5), target=(0, 0, 0), up=(0, 0, 1), fov=40.0, width=8)
    kw.update(bad)
    with pytest.raises(ValueError):
        ji.Camera.look_at(**kw)


@pytest.mark.parametrize("h,w,tile", [(24, 24, 8), (10, 7, 4), (5, 9, 8)])
def test_tiles_roundtrip(h, w, tile):
    x = jnp.arange(h * w * 3, dtype=jnp.float32).reshape(h, w, 3)
    t = ji.to_tiles(x, tile)
    assert t.shape[0] % (tile * tile) == 0
    np.testing.assert_array_equal(ji.from_tiles(t, tile, h, w), x)
    # a tile holds neighbouring pixels
    if h >= tile and w >= tile:
        np.testing.assert_array_equal(t[:tile * tile].reshape(tile, tile, 3), x[:tile, :tile])


@pytest.mark.parametrize("method", ["t-bisection", "k-bisection"])
@pytest.mark.parametrize("arithmetic", ["interval", "affine"])
def test_sphere_matches_analytic(method, arithmetic):
    eps = 2.0**-12
    rays = CAM.rays()
    hits = ji.intersect(_scene().replace(method=method, arithmetic=arithmetic, eps=eps), rays)
    t_ref = _analytic(rays.origin, rays.direction).reshape(SIZE, SIZE)
    assert np.array_equal(np.asarray(hits.hit), np.isfinite(t_ref))
    both = np.isfinite(t_ref)
    # Eq. 6.20: the hit piece is at most eps long in world units (unit directions) and
    # holds a root when the enclosure is exact along the ray (affine: one shared symbol);
    # an interval box is wider than its piece, so IA may accept a piece up to ~eps before
    # the surface (measured: <= 1.98 eps)
    bound = eps if arithmetic == "affine" else 2 * eps
    assert np.max(np.abs(np.asarray(hits.t)[both] - t_ref[both])) <= bound
    p = np.asarray(rays.at(jnp.where(hits.hit, hits.t, 0.0)))[both]
    np.testing.assert_allclose(np.asarray(hits.normal)[both], p / np.linalg.norm(p, axis=-1,
                               keepdims=True), atol=2e-3)
    assert np.all(np.asarray(hits.surface)[both] == 0)
    assert np.all(np.asarray(hits.surface)[~both] == -1)
    assert np.all(np.asarray(hits.steps)[both] > 0)


def test_eager_jit_vmap_agree_and_persistent_lanes():
    rays = CAM.rays()
    eager = ji.intersect(_scene(), rays)
    jitted = jax.jit(lambda s, r: ji.intersect(s, r))(_scene(), rays)
    lanes = ji.intersect(_scene(), rays, plan=ji.Plan(tile=4, lanes=64))
    for h in (jitted, lanes):
        np.testing.assert_array_equal(np.asarray(h.hit), np.asarray(eager.hit))
        np.testing.assert_allclose(np.asarray(h.t), np.asarray(eager.t), rtol=1e-6)
    # vmap over a batch of radii equals separate calls
    radii = jnp.array([0.6, 0.9, 1.2], jnp.float32)
    batched = jax.vmap(lambda r: ji.intersect(_scene(params={"r": r}), rays).t)(radii)
    for i, r in enumerate(radii):
        single = ji.intersect(_scene(params={"r": r}), rays).t
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(single), rtol=1e-6)
        t_ref = _analytic(rays.origin, rays.direction, float(r)).reshape(SIZE, SIZE)
        assert np.array_equal(np.isfinite(single), np.isfinite(t_ref))


def test_changing_camera_params_isovalue_w_does_not_retrace():
    traces = []

    def f(x, y, z, w, params):
        traces.append(1)
        return x * x + y * y + z * z - params["r"] ** 2 - w

    scene = ji.ImplicitSurface(f, (-1.5,) * 3, (1.5,) * 3, params={"r": 1.0})
    ji.render(scene, CAM)
    n = len(traces)
    assert n > 0
    ji.render(scene.replace(params={"r": 0.8}, isovalues=(0.1,), w=0.05),
              ji.Camera.look_at((2.0, -3.0, 1.0), (0.1, 0, 0), (0, 0, 1), 30.0, SIZE, SIZE))
    assert len(traces) == n


def _two_isovalues_scene():
    return ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z, (-1.5,) * 3, (1.5,) * 3,
                              isovalues=(0.36, 1.0))


def test_multiple_isovalues_and_transparency():
    scene = _two_isovalues_scene()
    hits = ji.intersect(scene, CAM.rays())
    parts = np.asarray(hits.surface)
    # the outer level set (iso 1.0, index 1) is hit first wherever it is hit
    t_outer = _analytic(CAM.rays().origin, CAM.rays().direction, 1.0).reshape(SIZE, SIZE)
    assert np.array_equal(parts == 1, np.isfinite(t_outer))
    colors = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    opaque = ji.render(scene, CAM, shading=ji.Shading(colors=colors))
    see_through = ji.render(scene, CAM, shading=ji.Shading(colors=colors, layers=3,
                                                            opacity=0.5))
    assert np.all(np.isfinite(see_through)) and see_through.shape == (SIZE, SIZE, 3)
    c = SIZE // 2
    # opaque: the outer (blue) shell only; transparent: the inner red sphere shows through
    assert opaque[c, c, 0] < 0.05 and see_through[c, c, 0] > 0.1
    # front-to-back: a pixel that misses everything is background in both
    np.testing.assert_allclose(opaque[0, 0], 1.0)
    np.testing.assert_allclose(see_through[0, 0], 1.0)


def _ball_on_floor():
    from jaxiso.implicit import csg
    ball = csg.Solid(lambda x, y, z: x * x + y * y + (z - 0.2) ** 2 - 0.49)
    floor = csg.Solid(lambda x, y, z: z + 0.5)
    return csg.CSG(csg.union(ball, floor), (-2.0, -2.0, -0.8), (2.0, 2.0, 1.0))


def test_shadows_and_reflections_change_the_right_pixels():
    scene = _ball_on_floor()
    cam = ji.Camera.look_at((3.0, 0.0, 1.6), (0, 0, 0), (0, 0, 1), 45.0, 32, 32)
    light = ji.Light((0.0, 0.0, 1.0))  # from straight above: shadow under the ball
    plain = ji.render(scene, cam, light=light)
    shadowed = ji.render(scene, cam, light=light, shading=ji.Shading(shadows=True))
    hits = ji.intersect(scene, cam.rays())
    floor_px = np.asarray(hits.surface) == 1
    darker = (plain.sum(-1) - shadowed.sum(-1)) > 0.3
    assert darker.sum() > 10 and np.all(floor_px[darker])  # only the floor darkens
    p = np.asarray(cam.rays().at(jnp.where(hits.hit, hits.t, 0.0)))
    under = floor_px & (np.hypot(p[..., 0], p[..., 1]) < 0.6)
    assert np.mean(darker[under]) > 0.9
    mirror = ji.render(scene, cam, light=light,
                       shading=ji.Shading(reflections=2, reflectivity=0.5))
    changed = np.abs(mirror - plain).sum(-1) > 0.05
    assert changed.sum() > 10 and np.all(np.isfinite(mirror))
    assert not np.any(changed & ~np.asarray(hits.hit))  # background stays background


def test_render_sharded_over_devices_equals_single_device():
    code = textwrap.dedent("""
        import jax, numpy as np, jaxiso as ji
        assert len(jax.devices()) == 4
        scene = ji.ImplicitSurface(lambda x, y, z: x*x + y*y + z*z - 1.0, (-1.5,)*3, (1.5,)*3)
        cam = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 40.0, 20, 12)
        one = ji.render(scene, cam)
        four = ji.render(scene, cam, devices=jax.devices())
        mesh = jax.sharding.Mesh(np.array(jax.devices()), ("tiles",))
        four_mesh = ji.render(scene, cam, devices=mesh, plan=ji.Plan(tile=4))
        lanes = ji.render(scene, cam, devices=jax.devices(), plan=ji.Plan(tile=4, lanes=32))
        assert np.allclose(one, four, atol=1e-6) and np.allclose(one, four_mesh, atol=1e-6)
        assert np.allclose(one, lanes, atol=1e-5)
        assert (one.sum(-1) < 2.9).sum() > 20
        print("ok")
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok")


def test_axis_parallel_rays_and_camera_inside():
    ortho = ji.Camera.orthographic_view((0.0, 0.0, 3.0), (0, 0, 0), (0, 1, 0), 1.2, 16, 16)
    rays = ortho.rays()
    hits = ji.intersect(_scene().replace(eps=2.0**-14), rays)
    t_ref = _analytic(rays.origin, rays.direction).reshape(16, 16)
    assert np.array_equal(np.asarray(hits.hit), np.isfinite(t_ref))
    m = np.isfinite(t_ref)
    assert np.max(np.abs(np.asarray(hits.t)[m] - t_ref[m])) <= 2.0**-14
    # camera inside the domain and inside the sphere: every ray hits the sphere from inside
    inside = ji.Camera.look_at((0.2, 0.1, 0.0), (1.0, 0.3, 0.2), (0, 0, 1), 60.0, 12, 12)
    rays = inside.rays()
    hits = ji.intersect(_scene(), rays)
    t_ref = _analytic(rays.origin, rays.direction).reshape(12, 12)
    assert np.all(np.asarray(hits.hit))
    assert np.max(np.abs(np.asarray(hits.t) - t_ref)) <= 2.0**-11


def test_rays_missing_the_domain_and_empty_ranges():
    away = ji.Camera.look_at((3.0, 2.0, 1.5), (10.0, 7.0, 5.0), (0, 0, 1), 20.0, 8, 8)
    hits = ji.intersect(_scene(), away.rays())
    assert not np.any(np.asarray(hits.hit)) and np.all(np.isinf(np.asarray(hits.t)))
    assert np.all(np.asarray(hits.normal) == 0) and np.all(np.asarray(hits.surface) == -1)
    # t_max before the sphere: no hit; t_min past the front: the back side
    rays = CAM.rays()
    t_ref = _analytic(rays.origin, rays.direction).reshape(SIZE, SIZE)
    short = ji.intersect(_scene(), rays, t_max=2.0)
    assert not np.any(np.asarray(short.hit))
    assert np.isfinite(t_ref).sum() > 50


def test_nan_on_part_of_the_domain_is_not_a_hit():
    # sqrt of a negative number is undefined for x < 0: only the x >= 0 half is drawn
    def half(x, y, z):
        return jnp.sqrt(x) + y * y + z * z - 1.0

    scene = ji.ImplicitSurface(half, (-1.5,) * 3, (1.5,) * 3)
    cam = ji.Camera.look_at((0.0, 0.0, 4.0), (0, 0, 0), (0, 1, 0), 40.0, SIZE, SIZE)
    img = ji.render(scene, cam)
    hits = ji.intersect(scene, cam.rays())
    assert np.all(np.isfinite(img))
    p = np.asarray(cam.rays().at(jnp.where(hits.hit, hits.t, 0.0)))[np.asarray(hits.hit)]
    assert len(p) > 20 and np.all(p[:, 0] >= -2.0**-10)
    assert np.all(np.isfinite(np.asarray(hits.normal)))


def test_division_asymptotes_are_not_drawn():
    # 1 / (x - 0.2) never vanishes; its enclosure is unbounded on pieces that cross the
    # pole x = 0.2, which must not register hits (Sec. 6.4.4)
    scene = ji.ImplicitSurface(lambda x, y, z: 1.0 / (x - 0.2), (-1.0,) * 3, (1.0,) * 3)
    cam = ji.Camera.look_at((0.2, -3.0, 0.3), (0.2, 0, 0), (0, 0, 1), 40.0, SIZE, SIZE)
    for arithmetic in ("interval", "affine"):
        hits = ji.intersect(scene.replace(arithmetic=arithmetic), cam.rays())
        assert not np.any(np.asarray(hits.hit)), arithmetic
    # y = 1/x has a real surface next to the pole: it is drawn, the pole plane is not
    hyper = ji.ImplicitSurface(lambda x, y, z: y - 1.0 / x, (-2.0,) * 3, (2.0,) * 3)
    cam = ji.Camera.look_at((0.0, 0.0, 5.0), (0, 0, 0), (0, 1, 0), 40.0, SIZE, SIZE)
    hits = ji.intersect(hyper, cam.rays())
    p = np.asarray(cam.rays().at(jnp.where(hits.hit, hits.t, 0.0)))[np.asarray(hits.hit)]
    assert len(p) > 10
    np.testing.assert_allclose(p[:, 1] * p[:, 0], 1.0, atol=0.05)


def test_shading_rejects_unsupported_combinations():
    with pytest.raises(ValueError):
        ji.Shading(layers=2, reflections=1)
    with pytest.raises(ValueError):
        ji.Shading(layers=0)
    with pytest.raises(ValueError):
        ji.Shading(colors=(1.0, 0.0, 0.0))


def test_bad_scene_input():
    with pytest.raises(ValueError):
        ji.ImplicitSurface(sphere, (1.0, 0, 0), (0.0, 1, 1), params={"r": 1.0})
    with pytest.raises(ValueError):
        ji.ImplicitSurface(sphere, (0, 0), (1, 1), params={"r": 1.0})
    with pytest.raises(TypeError):
        ji.ImplicitSurface(lambda x, y: x, (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError):
        ji.ImplicitSurface(sphere, (-1,) * 3, (1,) * 3, params={"r": 1.0}, eps=0.0)
    with pytest.raises(ValueError):
        ji.ImplicitSurface(sphere, (-1,) * 3, (1,) * 3, params={"r": 1.0}, arithmetic="x")


def test_image_png_roundtrip(tmp_path):
    img = ji.render(_scene(), CAM)
    assert isinstance(img, ji.Image) and img.dtype == np.float32
    assert img._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    path = img.save(tmp_path / "a" / "sphere.png")
    from PIL import Image as PILImage
    back = np.asarray(PILImage.open(path))
    assert back.shape == (SIZE, SIZE, 3)
    np.testing.assert_allclose(back / 255.0, np.clip(img, 0, 1), atol=1 / 255)


def test_central_difference_normals_and_zero_gradients():
    rays = CAM.rays()
    grad = ji.intersect(_scene(), rays)
    central = ji.intersect(_scene().replace(normals=1e-2), rays)
    m = np.asarray(grad.hit)
    np.testing.assert_allclose(np.asarray(central.normal)[m], np.asarray(grad.normal)[m],
                               atol=1e-3)
    # a double root: f = (|p|^2 - 1)^2 touches 0 with a zero gradient; interval bisection
    # still finds it (sign-change methods cannot) and the normal faces the ray, not NaN
    double = ji.ImplicitSurface(lambda x, y, z: (x * x + y * y + z * z - 1.0) ** 2,
                                (-1.5,) * 3, (1.5,) * 3)
    hits = ji.intersect(double, rays)
    hm = np.asarray(hits.hit)
    assert hm.sum() >= 0.9 * m.sum()
    d = np.asarray(rays.direction)[hm]
    n = np.asarray(hits.normal)[hm]
    assert np.all(np.isfinite(n))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-5)
    img = ji.render(double, CAM)
    assert np.all(np.isfinite(img))
    # near the double root the gradient is tiny but radial (either sign); where it
    # vanishes exactly the normal is -direction
    p = np.asarray(rays.at(jnp.where(hits.hit, hits.t, 0.0)))[hm]
    radial = np.abs(np.sum(n * p / np.linalg.norm(p, axis=-1, keepdims=True), -1)) > 0.99
    facing = np.all(np.abs(n + d) < 1e-5, axis=-1)
    assert np.all(radial | facing)
