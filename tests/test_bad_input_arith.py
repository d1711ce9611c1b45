"""Bad or degenerate user functions in `extend` and in implicit scenes: a constant f
works (a point enclosure of the batch shape; a scene has hits only where the constant is
an isovalue), an integer result works in scenes, a bool result is refused by scenes.
Expected values come from plain numpy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji
from jaxiso import aa
from jaxiso.arith import Affine, Interval
from jaxiso.implicit._field import as_field

ARITH = ["interval", "affine"]
LO, HI = -np.ones(3), np.ones(3)


def _as_iv(x):
    return aa.to_interval(x) if isinstance(x, Affine) else x


def _boxes(shape):
    rng = np.random.default_rng(3)
    lo = rng.uniform(-2.0, 1.0, size=shape).astype(np.float32)
    hi = (lo + rng.uniform(0.0, 1.0, size=shape)).astype(np.float32)
    return Interval(jnp.asarray(lo), jnp.asarray(hi))


@pytest.mark.parametrize("rounding", ["fast", "outward"])
@pytest.mark.parametrize("arithmetic", ARITH)
def test_extend_python_float_constant_is_a_point_of_the_batch_shape(arithmetic, rounding):
    box = _boxes((2, 3))
    out = ji.extend(lambda x, y, z: 1.0, arithmetic, rounding)(box, box, 0.0)
    iv = _as_iv(out)
    assert iv.lo.shape == (2, 3) and iv.hi.shape == (2, 3)
    lo, hi = np.asarray(iv.lo, np.float64), np.asarray(iv.hi, np.float64)
    assert np.all(lo <= 1.0) and np.all(hi >= 1.0)
    if rounding == "fast":
        np.testing.assert_array_equal(lo, np.full((2, 3), 1.0))
        np.testing.assert_array_equal(hi, np.full((2, 3), 1.0))
    else:  # at most a few ulps of 1 wider
        assert np.all(hi - lo <= 8 * np.finfo(np.float32).eps)
    assert bool(jnp.all(iv.defined))


@pytest.mark.parametrize("arithmetic", ARITH)
def test_extend_float32_zero_constant_eager_jit_vmap(arithmetic):
    box = _boxes((5,))
    F = ji.extend(lambda x, y, z: jnp.float32(0), arithmetic)
    expect = np.zeros(5, np.float32)
    for out in (F(box, box, box), jax.jit(lambda b: F(b, b, b))(box),
                jax.vmap(lambda b: F(b, b, b))(box)):
        iv = _as_iv(out)
        np.testing.assert_array_equal(np.asarray(iv.lo), expect)
        np.testing.assert_array_equal(np.asarray(iv.hi), expect)


def test_extend_constant_bool_is_certainly_true():
    out = ji.extend(lambda x, y, z: jnp.bool_(True))(_boxes((4,)), 0.0, 0.0)
    np.testing.assert_array_equal(np.asarray(out.lo), np.ones(4, bool))
    np.testing.assert_array_equal(np.asarray(out.hi), np.ones(4, bool))


def test_extend_integer_result_is_a_clear_error():
    with pytest.raises(ValueError, match="must return a float .or bool., got int32"):
        ji.extend(lambda x, y, z: 1)(_boxes((2,)), 0.0, 0.0)


@pytest.mark.parametrize("f", [lambda x, y, z: 1.0, lambda x, y, z: 1,
                               lambda x, y, z: jnp.float32(1.0)])
def test_field_of_a_constant_is_broadcast_to_the_points(f):
    g = as_field(f, has_params=False)
    x = jnp.linspace(-1.0, 1.0, 7)
    val = g(x, 0.0, jnp.zeros((1, 7)), 0.0, ())
    assert val.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(val), np.ones((1, 7), np.float32))


def test_field_returning_bool_is_a_type_error():
    g = as_field(lambda x, y, z: x * x + y * y < 1.0, has_params=False)
    with pytest.raises(TypeError, match="must return a real number per point, got bool"):
        g(jnp.zeros(3), 0.0, 0.0, 0.0, ())


def _rays():
    cam = ji.Camera.look_at((3.0, 0.5, 0.3), (0.0, 0.0, 0.0), fov=60, width=6, height=6)
    return cam.rays()


def _box_entry(rays):
    """(enters [R], t_entry [R]) of the rays and the box [LO, HI], by the slab test."""
    o = np.asarray(rays.origin, np.float64).reshape(-1, 3)
    d = np.asarray(rays.direction, np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (LO - o) / d, (HI - o) / d
    t_near = np.minimum(ta, tb).max(axis=-1)
    t_far = np.maximum(ta, tb).min(axis=-1)
    return (t_near <= t_far) & (t_far >= 0.0), np.maximum(t_near, 0.0), d


@pytest.mark.parametrize("arithmetic", ARITH)
def test_scene_of_a_constant_off_the_isovalues_has_no_hits(arithmetic):
    scene = ji.ImplicitSurface(lambda x, y, z: 1.0, lo=LO, hi=HI, isovalues=(0.0, 0.5),
                               arithmetic=arithmetic)
    hits = ji.intersect(scene, _rays())
    assert not bool(jnp.any(hits.hit))
    assert bool(jnp.all(jnp.isinf(hits.t))) and bool(jnp.all(hits.surface == -1))


@pytest.mark.parametrize("method", ["t-bisection", "k-bisection"])
@pytest.mark.parametrize("arithmetic", ARITH)
def test_scene_of_a_constant_isovalue_is_hit_where_rays_enter_the_box(arithmetic, method):
    """f = 2 with isovalues (0.5, 2): the whole box is the level set; the integer result
    is a real number too. Rays hit it at their box entry (within eps), surface 1, with
    the normal facing the ray (the gradient vanishes)."""
    scene = ji.ImplicitSurface(lambda x, y, z: 2, lo=LO, hi=HI, isovalues=(0.5, 2.0),
                               arithmetic=arithmetic)
    rays = _rays()
    hits = ji.intersect(scene.replace(method=method), rays)
    enters, t_entry, d = _box_entry(rays)
    hit = np.asarray(hits.hit).ravel()
    np.testing.assert_array_equal(hit, enters)
    assert enters.sum() > 0
    t = np.asarray(hits.t, np.float64).ravel()
    assert np.all(np.abs(t[hit] - t_entry[hit]) <= float(scene.eps))
    assert np.all(np.asarray(hits.surface).ravel()[hit] == 1)
    normal = np.asarray(hits.normal, np.float64).reshape(-1, 3)
    np.testing.assert_allclose(normal[hit], -d[hit], atol=1e-6)


@pytest.mark.parametrize("arithmetic", ARITH)
def test_scene_of_an_inequality_is_a_type_error(arithmetic):
    scene = ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z < 1.0, lo=LO, hi=HI,
                               arithmetic=arithmetic)
    with pytest.raises(TypeError, match="must return a real number per point, got bool"):
        ji.intersect(scene, _rays())
