"""The comparison baselines (Mitchell, point sampling, sphere tracing) against analytic
intersections, against t-bisection, and where point methods are expected to fail."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso
from jaxiso import surfaces

EPS = 2.0**-11
EYE, TARGET, UP = (3.0, 2.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)


def sphere(x, y, z):
    return x * x + y * y + z * z - 1.0


def rays(size=24, eye=EYE, fov=40.0):
    return jaxiso.Camera.look_at(eye, TARGET, UP, fov, size, size).rays()


@functools.partial(jax.jit, static_argnames=("options",))
def _trace(scene, rays, options):
    return jaxiso.intersect(scene.replace(**dict(options)), rays)


def trace(scene, rays, **options):
    return jax.device_get(_trace(scene, rays, tuple(sorted(options.items()))))


def analytic_sphere(o, d, r=1.0):
    """Nearest t >= 0 on |o + t d| = r (float64 quadratic), and the ray-centre distance."""
    o, d = np.asarray(o, np.float64).reshape(-1, 3), np.asarray(d, np.float64).reshape(-1, 3)
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", o, d) / a
    c = (np.einsum("ij,ij->i", o, o) - r * r) / a
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    t = np.where((disc >= 0) & (t >= 0), t, np.inf)
    dist = np.sqrt(np.maximum(np.einsum("ij,ij->i", o, o) - b * b * a, 0.0))
    return t, dist


SPHERE_CASES = [
    ("mitchell", {}),
    ("mitchell", {"arithmetic": "affine"}),
    ("sampling", {}),
    ("sphere", {"lipschitz": 2.0 * 1.5 * 3**0.5}),  # |grad f| = 2|x| <= 2 |corner|
]


@pytest.mark.parametrize("method,options", SPHERE_CASES,
                         ids=[m + "".join(f"-{v}" for v in o.values() if isinstance(v, str))
                              for m, o in SPHERE_CASES])
def test_unit_sphere_matches_analytic(method, options):
    """The unit sphere f = 0 with the level set r = 0.5 (f = -0.75) nested inside it:
    every ray that meets the sphere must stop at the outer one (surface 0)."""
    scene = jaxiso.ImplicitSurface(sphere, (-1.5,) * 3, (1.5,) * 3, isovalues=(0.0, -0.75))
    r = rays()
    # sphere tracing stops when |f| / L < eps, which bounds the distance to the surface
    # only by eps L / |grad f| (<= 2.6 eps here): trace it to eps / 4
    eps = EPS / 4 if method == "sphere" else EPS
    h = trace(scene, r, method=method, eps=eps, **options)
    o = np.asarray(r.origin).reshape(-1, 3)
    d = np.asarray(r.direction).reshape(-1, 3)
    ta, dist = analytic_sphere(o, d)
    hit, t = h.hit.reshape(-1), h.t.reshape(-1)
    hit_a = np.isfinite(ta)
    assert 0.2 * hit.size < hit_a.sum() < 0.8 * hit.size
    clear = np.abs(dist - 1.0) > 1e-2  # away from the silhouette
    np.testing.assert_array_equal(hit[clear], hit_a[clear])
    assert np.all(h.surface.reshape(-1)[hit] == 0)
    assert np.all(h.steps.reshape(-1)[hit] > 0)
    both = hit & hit_a
    # the hit point lies on the sphere to eps (world units; |d| = 1)
    x = o[both] + t[both, None] * d[both]
    assert np.max(np.abs(np.linalg.norm(x, axis=1) - 1.0)) <= EPS
    if method == "sphere":
        # never steps through; along grazing rays the depth error is |f| / (L cos)
        assert np.all(t[both] <= ta[both] + 1e-5)
    else:
        assert np.max(np.abs(t[both] - ta[both])) <= EPS


def barth_np(x, y, z, w=0.0):
    tau = (1.0 + 5.0**0.5) / 2.0
    t2 = tau * tau
    x2, y2, z2 = x * x, y * y, z * z
    s = x2 + y2 + z2 - 1.0
    return 4.0 * (t2 * x2 - y2) * (t2 * y2 - z2) * (t2 * z2 - x2) - (1.0 + 2.0 * tau) * s * s


def test_mitchell_agrees_with_t_bisection_on_barth_sextic():
    from reference_trace64 import first_roots

    s = surfaces.get("barth_sextic")
    # both in interval arithmetic (auto would give t-bisection the polynomial enclosure;
    # Mitchell's pieces are boxes)
    scene = jaxiso.ImplicitSurface(s.f, s.lo, s.hi, arithmetic="interval")
    r = rays(24, eye=(3.5, 2.5, 2.0), fov=45.0)
    hm = trace(scene, r, method="mitchell", eps=EPS)
    ht = trace(scene, r, method="t-bisection", eps=EPS)
    hit_m, hit_t = hm.hit.reshape(-1), ht.hit.reshape(-1)
    t_m = hm.t.reshape(-1)
    assert hit_t.sum() > 0.2 * hit_t.size
    either = hit_m | hit_t
    assert np.mean(hit_m[either] == hit_t[either]) >= 0.99
    # isolation pays off: fewer steps than bisecting every piece to eps
    both = hit_m & hit_t
    assert hm.steps.reshape(-1)[both].mean() < ht.steps.reshape(-1)[both].mean()
    # Depth: interval t-bisection stops on the first piece of length eps whose (widely
    # overestimated) enclosure holds 0, up to ~16 eps in front of the surface here, never
    # behind it; Mitchell's refined roots lie within eps of the float64 reference.
    t_t = ht.t.reshape(-1)
    assert np.mean(t_m[both] >= t_t[both] - 2 * EPS) >= 0.99
    o = np.asarray(r.origin, np.float64).reshape(-1, 3)
    d = np.asarray(r.direction, np.float64).reshape(-1, 3)
    t_ref, _ = first_roots(barth_np, s.lo, s.hi, o, d, eps=2.0**-30)
    both = hit_m & np.isfinite(t_ref)
    assert np.mean(np.abs(t_m[both] - t_ref[both]) <= EPS) >= 0.99


def test_sampling_misses_a_thin_shell_that_bisection_finds():
    """A shell 0.02 thick (|r - 1| < 0.01) slips between 8 samples per ray (about 0.5
    apart); t-bisection's inclusions see it."""
    def shell(x, y, z):
        r = jnp.sqrt(x * x + y * y + z * z)
        return (r - 1.0) ** 2 - 1e-4

    scene = jaxiso.ImplicitSurface(shell, (-1.5,) * 3, (1.5,) * 3)
    r = rays(16)
    n_bisect = int(trace(scene, r, method="t-bisection", eps=EPS).hit.sum())
    n_sampled = int(trace(scene, r, method="sampling", eps=EPS, samples=8).hit.sum())
    assert n_bisect > 0.2 * r.shape[0] * r.shape[1]
    assert n_sampled < 0.5 * n_bisect


def test_sphere_tracing_needs_lipschitz():
    scene = jaxiso.ImplicitSurface(sphere, (-1.5,) * 3, (1.5,) * 3)
    with pytest.raises(ValueError, match="lipschitz"):
        scene.replace(method="sphere")
    with pytest.raises(ValueError, match="positive"):
        scene.replace(method="sphere", lipschitz=-1.0)


def test_unknown_option_is_reported():
    scene = jaxiso.ImplicitSurface(sphere, (-1.5,) * 3, (1.5,) * 3)
    with pytest.raises(TypeError, match="sampels"):
        scene.replace(method="sampling", sampels=3)
