"""Hits are differentiable: d t / d (params, isovalues, w, ray origin, ray direction).

`attach_t` gives t its derivative by the implicit function theorem. Each case checks it
(jax.grad and jax.jvp) against central differences of the *exact* t, an analytic ray-
sphere intersection in float64 numpy written independently of the tracer, and against
central differences of the traced t itself at a fine eps (2^-20) with a step much larger
than eps, so the tracer's own error stays far below the difference. At such a fine eps
the pieces of ray are a few float32 ulps long, so these traces round outward (with the
default round-to-nearest an enclosure may miss a root by an ulp and drop the hit).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji

FINE = 2.0**-20          # ray precision for the comparisons
H_TRACED = 1e-2          # step of differences of the traced t (>> FINE)
H_EXACT = 1e-6           # step of differences of the float64 analytic t
LO, HI = (-2.0, -2.0, -2.0), (2.0, 2.0, 2.0)

# rays from z = -3 upwards (unit and non-unit directions), all meeting the unit sphere
# well away from grazing; t is in units of |d|
ORIGINS = np.array([[0.0, 0.0, -3.0], [0.3, -0.2, -3.0], [-0.5, 0.4, -3.0],
                    [0.6, 0.5, -3.0], [-2.5, 0.3, -2.4]])
DIRS = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.05, 0.1, 1.0],
                 [0.0, -0.1, 0.7], [0.8, 0.0, 0.9]])


def exact_sphere_t(o, d, radius):
    """First t > 0 of |o + t d| = radius (float64; inf on a miss)."""
    o = np.asarray(o, np.float64).reshape(-1, 3)
    d = np.asarray(d, np.float64).reshape(-1, 3)
    a = np.sum(d * d, -1)
    b = np.sum(o * d, -1)
    c = np.sum(o * o, -1) - radius * radius
    disc = b * b - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    near, far = (-b - sq) / a, (-b + sq) / a
    t = np.where(near > 0, near, far)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def central(fn, x, h):
    return (np.asarray(fn(x + h), np.float64) - np.asarray(fn(x - h), np.float64)) / (2 * h)


def rays(o=ORIGINS, d=DIRS):
    return ji.Rays(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32))


def sphere_r(x, y, z, params):
    return x * x + y * y + z * z - params["r"] ** 2


def sphere_w(x, y, z, w):
    return x * x + y * y + z * z - (1.0 + w) ** 2


def radius2(x, y, z):
    return x * x + y * y + z * z


def traced_t(scene, r=None, eps=FINE, **options):
    h = ji.intersect(scene.replace(eps=eps, rounding="outward", **options),
                     rays() if r is None else r)
    return jnp.where(h.hit, h.t, 0.0)


UNIT = ji.ImplicitSurface(radius2, LO, HI, isovalues=(1.0,))


# --- d t / d params -------------------------------------------------------------------

@jax.jit
def t_of_r(r):
    return traced_t(ji.ImplicitSurface(sphere_r, LO, HI, params={"r": r}))


def test_dt_dparams_matches_exact_and_traced_differences():
    r0 = 1.0
    t = t_of_r(jnp.float32(r0))
    np.testing.assert_allclose(t, exact_sphere_t(ORIGINS, DIRS, r0), rtol=0, atol=2 * FINE)
    # forward mode: every ray's derivative at once
    _, dt = jax.jvp(t_of_r, (jnp.float32(r0),), (jnp.float32(1.0),))
    exact = central(lambda r: exact_sphere_t(ORIGINS, DIRS, r), r0, H_EXACT)
    np.testing.assert_allclose(dt, exact, rtol=2e-4, atol=1e-5)
    traced = central(lambda r: t_of_r(jnp.float32(r)), r0, H_TRACED)
    np.testing.assert_allclose(dt, traced, rtol=2e-3, atol=2e-4)
    # reverse mode agrees with forward mode
    g = jax.grad(lambda r: jnp.sum(t_of_r(r) * jnp.arange(1.0, 6.0)))(jnp.float32(r0))
    np.testing.assert_allclose(g, np.sum(np.asarray(dt) * np.arange(1.0, 6.0)), rtol=1e-5)


@pytest.mark.parametrize("method,arithmetic", [("k-bisection", "interval"),
                                               ("t-bisection", "affine")])
def test_dt_dparams_other_methods(method, arithmetic):
    def f(r):
        scene = ji.ImplicitSurface(sphere_r, LO, HI, params={"r": r})
        return traced_t(scene, method=method, arithmetic=arithmetic)

    _, dt = jax.jvp(jax.jit(f), (jnp.float32(0.8),), (jnp.float32(1.0),))
    exact = central(lambda r: exact_sphere_t(ORIGINS, DIRS, r), 0.8, H_EXACT)
    np.testing.assert_allclose(dt, exact, rtol=2e-4, atol=1e-5)


@pytest.mark.parametrize("method", ["t-bisection", "k-bisection"])
def test_root_on_a_piece_boundary_is_found(method):
    """The axis ray meets the unit sphere at s = 1/4 of its segment in the box, a piece
    boundary at every depth. The pieces must tile the segment exactly (piece widths
    2^-d computed exactly, not by an approximate exp2) or the hit, and its derivative,
    falls into a gap between pieces; default rounding, every eps."""
    ray = rays(ORIGINS[:1], DIRS[:1])

    @jax.jit
    def trace(eps):
        h = ji.intersect(UNIT.replace(eps=eps, method=method), ray)
        return h.t[0], h.hit[0]

    for eps in (2.0**-11, 2.0**-16, 2.0**-20):
        t, hit = trace(jnp.float32(eps))
        assert bool(hit), f"eps={eps}: the hit at t=2 was lost"
        assert abs(float(t) - 2.0) <= eps


# --- d t / d isovalue and d t / d w -----------------------------------------------------

def test_dt_disovalue():
    @jax.jit
    def t_of_iso(iso):
        return traced_t(ji.ImplicitSurface(radius2, LO, HI, isovalues=jnp.stack([iso])))

    iso0 = 0.81  # radius 0.9
    _, dt = jax.jvp(t_of_iso, (jnp.float32(iso0),), (jnp.float32(1.0),))
    exact = central(lambda s: exact_sphere_t(ORIGINS, DIRS, np.sqrt(s)), iso0, H_EXACT)
    np.testing.assert_allclose(dt, exact, rtol=2e-4, atol=1e-5)
    traced = central(lambda s: t_of_iso(jnp.float32(s)), iso0, H_TRACED)
    np.testing.assert_allclose(dt, traced, rtol=2e-3, atol=2e-4)
    g = jax.grad(lambda s: jnp.sum(t_of_iso(s)))(jnp.float32(iso0))
    np.testing.assert_allclose(g, np.sum(exact), rtol=2e-4)


def test_dt_dw():
    @jax.jit
    def t_of_w(w):
        return traced_t(ji.ImplicitSurface(sphere_w, LO, HI, w=w))

    w0 = 0.1  # radius 1.1
    _, dt = jax.jvp(t_of_w, (jnp.float32(w0),), (jnp.float32(1.0),))
    exact = central(lambda w: exact_sphere_t(ORIGINS, DIRS, 1.0 + w), w0, H_EXACT)
    np.testing.assert_allclose(dt, exact, rtol=2e-4, atol=1e-5)
    traced = central(lambda w: t_of_w(jnp.float32(w)), w0, H_TRACED)
    np.testing.assert_allclose(dt, traced, rtol=2e-3, atol=2e-4)
    g = jax.grad(lambda w: jnp.sum(t_of_w(w)))(jnp.float32(w0))
    np.testing.assert_allclose(g, np.sum(exact), rtol=2e-4)


# --- d t / d origin and d t / d direction -----------------------------------------------

@jax.jit
def t_of_ray(o, d):
    return traced_t(UNIT, ji.Rays(o, d))


def _exact_jacobian(which):
    """[P, 3] d t_p / d (origin or direction)_p,k of the analytic t (rays independent)."""
    jac = np.zeros((len(ORIGINS), 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = H_EXACT
        o, d = ORIGINS, DIRS
        if which == "origin":
            plus, minus = exact_sphere_t(o + e, d, 1.0), exact_sphere_t(o - e, d, 1.0)
        else:
            plus, minus = exact_sphere_t(o, d + e, 1.0), exact_sphere_t(o, d - e, 1.0)
        jac[:, k] = (plus - minus) / (2 * H_EXACT)
    return jac


def _traced_jacobian(which):
    jac = np.zeros((len(ORIGINS), 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = H_TRACED
        o, d = ORIGINS, DIRS
        if which == "origin":
            plus, minus = t_of_ray(*_f32(o + e, d)), t_of_ray(*_f32(o - e, d))
        else:
            plus, minus = t_of_ray(*_f32(o, d + e)), t_of_ray(*_f32(o, d - e))
        jac[:, k] = (np.asarray(plus, np.float64) - np.asarray(minus, np.float64)) / (
            2 * H_TRACED)
    return jac


def _f32(*arrays):
    return tuple(jnp.asarray(a, jnp.float32) for a in arrays)


@pytest.mark.parametrize("which", ["origin", "direction"])
def test_dt_dray(which):
    o, d = _f32(ORIGINS, DIRS)
    argnum = 0 if which == "origin" else 1
    # each ray's t depends only on its own ray: the gradient of the sum is the per-ray
    # Jacobian row
    grad = jax.grad(lambda o, d: jnp.sum(t_of_ray(o, d)), argnums=argnum)(o, d)
    np.testing.assert_allclose(grad, _exact_jacobian(which), rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(grad, _traced_jacobian(which), rtol=3e-3, atol=5e-4)
    # forward mode along a random tangent
    v = jax.random.normal(jax.random.key(0), o.shape)
    tangents = (v, jnp.zeros_like(d)) if which == "origin" else (jnp.zeros_like(o), v)
    _, dt = jax.jvp(t_of_ray, (o, d), tangents)
    np.testing.assert_allclose(dt, np.sum(np.asarray(grad) * np.asarray(v), -1),
                               rtol=1e-4, atol=1e-5)


# --- several isovalues ------------------------------------------------------------------

def test_two_isovalues_jacobian():
    """Nested spheres r = 0.5 and r = 1 (isovalues 0.25, 1): each ray's t moves only
    with the isovalue it hit. Rays from between the shells meet the inner one."""
    o = np.array([[0.0, 0.0, -3.0], [0.2, 0.3, -3.0], [0.0, 0.0, 0.75],
                  [0.1, -0.1, -0.8], [0.9, 0.0, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0],
                  [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    isos = np.array([0.25, 1.0])

    def t_of_isos(isos):
        # built under jit: name the arithmetic ("auto" could not measure there)
        scene = ji.ImplicitSurface(radius2, LO, HI, isovalues=isos, arithmetic="interval")
        h = ji.intersect(scene.replace(eps=FINE, rounding="outward"), ji.Rays(*_f32(o, d)))
        return jnp.where(h.hit, h.t, 0.0), h.surface

    def exact(isos):
        t = np.stack([exact_sphere_t(o, d, np.sqrt(s)) for s in isos], -1)
        return np.min(t, -1), np.argmin(t, -1)

    t, surface = jax.jit(t_of_isos)(jnp.asarray(isos, jnp.float32))
    t_exact, which = exact(isos)
    np.testing.assert_array_equal(surface, which)
    assert set(which.tolist()) == {0, 1}
    np.testing.assert_allclose(t, t_exact, atol=2 * FINE)
    jac = jax.jit(jax.jacrev(lambda s: t_of_isos(s)[0]))(jnp.asarray(isos, jnp.float32))
    jac_f = jax.jit(jax.jacfwd(lambda s: t_of_isos(s)[0]))(jnp.asarray(isos, jnp.float32))
    expect = np.zeros((len(o), 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = H_EXACT
        expect[:, k] = (exact(isos + e)[0] - exact(isos - e)[0]) / (2 * H_EXACT)
    assert np.all(expect[np.arange(len(o)), 1 - which] == 0.0)
    np.testing.assert_allclose(jac, expect, rtol=2e-4, atol=1e-5)
    np.testing.assert_allclose(jac_f, jac, rtol=1e-5, atol=1e-6)


# --- misses, jit, many rays, render -----------------------------------------------------

def test_miss_gives_zero_gradient_not_nan():
    o = np.array([[3.0, 3.0, -3.0], [0.0, 0.0, -3.0], [1.5, 0.0, -3.0], [0.0, 5.0, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    o, d = _f32(o, d)  # ray 0 misses the box; rays 2 and 3 cross it but miss the sphere

    def loss(p, o, d):
        h = ji.intersect(ji.ImplicitSurface(sphere_r, LO, HI, params={"r": p}, eps=FINE,
                                            rounding="outward"), ji.Rays(o, d))
        return jnp.where(h.hit, h.t, 0.0), h.hit

    _, hit = jax.jit(loss)(jnp.float32(1.0), o, d)
    np.testing.assert_array_equal(hit, [False, True, False, False])
    grads = jax.jit(jax.jacrev(lambda *a: loss(*a)[0], argnums=(0, 1, 2)))(
        jnp.float32(1.0), o, d)
    for g in grads:
        assert np.all(np.isfinite(g))
    dp, do, dd = (np.asarray(g) for g in grads)
    np.testing.assert_array_equal(dp[[0, 2, 3]], 0.0)
    np.testing.assert_allclose(dp[1], -1.0, rtol=1e-5)      # t = 3 - r on the axis
    np.testing.assert_array_equal(do[[0, 2, 3]], 0.0)
    np.testing.assert_array_equal(dd[[0, 2, 3]], 0.0)
    # nothing hit at all: the gradient is exactly 0
    miss = np.array([0, 2, 3])
    g = jax.jit(jax.grad(lambda p: jnp.sum(loss(p, o[miss], d[miss])[0])))(jnp.float32(1.0))
    assert float(g) == 0.0


def test_grad_under_jit_does_not_retrace():
    traces = []

    def loss(params):
        traces.append(1)
        scene = ji.ImplicitSurface(sphere_r, LO, HI, params=params)
        return jnp.sum(traced_t(scene))

    g_jit = jax.jit(jax.grad(loss))
    for r in (1.0, 0.9):
        g = g_jit({"r": jnp.float32(r)})
        exact = np.sum(central(lambda r: exact_sphere_t(ORIGINS, DIRS, r), r, H_EXACT))
        np.testing.assert_allclose(g["r"], exact, rtol=2e-4)
    assert len(traces) == 1


def test_gradient_finite_over_an_image():
    """Camera rays over a superquadric-like blob, grazing rays at its silhouette
    included: the gradient of the summed depth of hit pixels is finite and nonzero."""
    def blob(x, y, z, params):
        return (x * x + y * y + z * z) ** params["p"] + params["k"] * x * y * z - 1.0

    cam = ji.Camera.look_at((3.0, 2.0, 1.5), width=24)

    @jax.jit
    def loss(params):
        h = ji.intersect(ji.ImplicitSurface(blob, LO, HI, params=params), cam.rays())
        return jnp.sum(jnp.where(h.hit, h.t, 0.0)), h.hit

    params = {"p": jnp.float32(1.5), "k": jnp.float32(0.3)}
    (_, hit), g = jax.value_and_grad(loss, has_aux=True)(params)
    assert 0.1 * hit.size < int(np.sum(hit)) < 0.9 * hit.size
    for v in g.values():
        assert np.isfinite(float(v)) and float(v) != 0.0


def test_render_differentiable_in_params():
    """d(image)/d(radius) of a lit sphere: finite, nonzero, and equal to differences of
    the rendered colours over the pixels that stay on the sphere."""
    cam = ji.Camera.look_at((0.0, -4.0, 1.0), fov=35.0, width=16)
    light = ji.Light((0.6, -0.5, 0.8))

    def image(r):
        scene = ji.ImplicitSurface(sphere_r, LO, HI, params={"r": r}, eps=FINE,
                                   rounding="outward")
        img = ji.render(scene, cam, light=light)
        assert isinstance(img, jax.Array)  # a jax array under transformation
        return img

    image_jit = jax.jit(image)
    colors = {r: np.asarray(image_jit(jnp.float32(r)), np.float64)
              for r in (0.9, 1.0 - 2e-3, 1.0 + 2e-3)}
    on_sphere = {r: ~np.all(c == 1.0, axis=-1) for r, c in colors.items()}
    assert 0.1 * on_sphere[0.9].size < np.sum(on_sphere[0.9]) < 0.9 * on_sphere[0.9].size
    keep = on_sphere[0.9][..., None]  # on the sphere for every r in [0.9, 1.002]

    g = jax.jit(jax.grad(lambda r: jnp.sum(jnp.where(keep, image(r), 0.0))))(
        jnp.float32(1.0))
    assert np.isfinite(float(g)) and float(g) != 0.0
    fd = np.sum(np.where(keep, colors[1.0 + 2e-3] - colors[1.0 - 2e-3], 0.0)) / 4e-3
    np.testing.assert_allclose(g, fd, rtol=5e-3)
