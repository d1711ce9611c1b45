"""Self-tests of the float64 reference tracer against analytic intersections."""

import numpy as np
import pytest
from reference_trace64 import camera_rays, first_roots

BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))


def sphere(x, y, z, w=0.0):
    return x * x + y * y + z * z - 1.0


def analytic_sphere(o, d, r=1.0):
    """Nearest t >= 0 of |o + t d| = r (centre 0), inf for a miss; also the ray-centre
    distance. Written independently of the tracer (quadratic formula)."""
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", o, d) / a
    c = (np.einsum("ij,ij->i", o, o) - r * r) / a
    disc = b * b - c
    sq = np.sqrt(np.maximum(disc, 0.0))
    near = -b - sq
    far = -b + sq
    t = np.where(near >= 0, near, far)
    t = np.where((disc >= 0) & (t >= 0), t, np.inf)
    dist = np.sqrt(np.maximum(np.einsum("ij,ij->i", o, o) - b * b * a, 0.0))
    return t, dist


def test_camera_convention():
    o, d = camera_rays((0, -5, 0), (0, 0, 0), (0, 0, 1), 90.0, 4, 2)
    assert o.shape == d.shape == (8, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(o, np.tile([0.0, -5.0, 0.0], (8, 1)))
    # forward = +y, right = forward x up = +x, true_up = +z; tan(45deg) = 1, aspect 2
    expect = np.array([[(2 * (j + 0.5) / 4 - 1) * 2, 1.0, 1 - 2 * (i + 0.5) / 2]
                       for i in range(2) for j in range(4)])
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    np.testing.assert_allclose(d, expect, rtol=0, atol=1e-15)
    assert d[0, 2] > 0 and d[0, 0] < 0  # row 0 is the top, column 0 the left


def test_sphere_image_matches_analytic():
    o, d = camera_rays((3, 2, 1), (0, 0, 0), (0, 0, 1), 40.0, 64, 64)
    t, which = first_roots(sphere, *BOX, o, d, eps=2.0**-42)
    ta, dist = analytic_sphere(o, d)
    hit_a = np.isfinite(ta)
    assert 0.1 * hit_a.size < hit_a.sum() < 0.9 * hit_a.size  # non-trivial image
    ok = np.abs(dist - 1.0) > 1e-6
    np.testing.assert_array_equal(np.isfinite(t)[ok], hit_a[ok])
    np.testing.assert_array_equal(which, np.where(np.isfinite(t), 0, -1))
    both = hit_a & np.isfinite(t)
    np.testing.assert_allclose(t[both], ta[both], rtol=1e-9, atol=0)


def test_default_eps_accuracy():
    o, d = camera_rays((3, 2, 1), (0, 0, 0), (0, 0, 1), 30.0, 16, 16)
    d = d * 2.5  # non-unit directions: t scales by 1/2.5
    t, _ = first_roots(sphere, *BOX, o, d)
    ta, _ = analytic_sphere(o, d)
    hit = np.isfinite(ta)
    assert hit.any()
    np.testing.assert_array_equal(np.isfinite(t), hit)
    # bisection stops at world width eps * L; L <= box diagonal
    L = np.sqrt(3) * 3.0
    assert np.max(np.abs(t[hit] - ta[hit]) * 2.5) <= 2.0**-22 * L / 2 * 1.01


def plane(x, y, z, w=0.0):
    return z - 0.3


def test_plane_axis_parallel_rays():
    lo, hi = (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)
    o = np.array([[0.2, -0.4, -2.0],   # up +z, enters at z=-1
                  [0.5, 0.5, 2.0],     # down -z
                  [0.0, 0.0, -2.0],    # up, non-unit direction
                  [0.0, 1.0, -2.0],    # on the box face y = hi: closed box, hits
                  [0.0, 1.5, -2.0],    # parallel to the y slab, outside it: misses
                  [-2.0, 0.0, 0.5],    # along x above the plane: no crossing
                  [-2.0, 0.0, 0.3]])   # along x in the plane: exact zero at the entry sample
    dz = [0.0, 0.0, 1.0]
    d = np.array([dz, [0.0, 0.0, -1.0], [0.0, 0.0, 2.0], dz, dz, [1.0, 0.0, 0.0],
                  [1.0, 0.0, 0.0]])
    expect = np.array([2.3, 1.7, 1.15, 2.3, np.inf, np.inf, 1.0])
    t, which = first_roots(plane, lo, hi, o, d, eps=2.0**-44)
    np.testing.assert_allclose(t, expect, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(which, [0, 0, 0, 0, -1, -1, 0])
    assert t[6] == 1.0  # exact zero at a sample returns that sample


def test_rays_missing_the_box():
    o = np.array([[5.0, 5.0, 5.0], [0.0, 0.0, 5.0], [3.0, 3.0, 0.0], [-3.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.1, 1.0, 0.0],
                  [0.0, 0.0, 0.0]])  # last: zero direction
    t, which = first_roots(sphere, *BOX, o, d)
    assert np.all(np.isinf(t)) and np.all(which == -1)
    # control: the same machinery does hit when aimed at the sphere
    t, _ = first_roots(sphere, *BOX, o[:1], -o[:1], eps=2.0**-44)
    np.testing.assert_allclose(t, 1 - 1 / np.sqrt(75.0), rtol=1e-11)


def test_t_min_t_max():
    o, d = np.array([[-3.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    t, _ = first_roots(sphere, *BOX, o, d, t_max=1.9)
    assert np.isinf(t[0])
    t, _ = first_roots(sphere, *BOX, o, d, t_min=2.5, eps=2.0**-44)  # past the first root
    assert t[0] == pytest.approx(4.0, abs=1e-11)


@pytest.mark.parametrize("ox, dx, expect", [(0.0, 1.0, 1.0), (0.5, -1.0, 1.5),
                                            (1.25, -1.0, 0.25), (-0.3, 2.0, 0.65)])
def test_origin_inside_box(ox, dx, expect):
    o = np.array([[ox, 0.0, 0.0]])
    d = np.array([[dx, 0.0, 0.0]])
    t, which = first_roots(sphere, (-2, -2, -2), (2, 2, 2), o, d, eps=2.0**-44)
    assert t[0] == pytest.approx(expect, abs=1e-11) and which[0] == 0


def test_multiple_isovalues_nearest():
    r_in = np.sqrt(0.5)
    o = np.array([[3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 0.9, 0.0], [0.0, 0.0, 0.3]])
    d = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    expect = np.array([2.0, r_in, 3.0 - np.sqrt(1 - 0.81), 0.3 + r_in])
    t, which = first_roots(sphere, *BOX, o, d, isovalues=(0.0, -0.5), eps=2.0**-44)
    np.testing.assert_allclose(t, expect, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(which, [0, 1, 0, 1])
    t2, which2 = first_roots(sphere, *BOX, o, d, isovalues=(-0.5, 0.0), eps=2.0**-44)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(which2, 1 - which)


def test_isovalues_in_same_interval():
    # f = 0 and f = 1e-6 cross within one sample interval; the outer shell (iso 1e-6) is nearer
    o, d = np.array([[3.0, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]])
    t, which = first_roots(sphere, *BOX, o, d, isovalues=(0.0, 1e-6), eps=2.0**-44)
    assert which[0] == 1
    assert t[0] == pytest.approx(3.0 - np.sqrt(1 + 1e-6), abs=1e-11)


def half_nan_sphere(x, y, z, w=0.0):
    return np.where(x < 0, np.nan, sphere(x, y, z))


def test_nan_half_domain():
    o = np.array([[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0], [-0.5, -3.0, 0.0], [0.5, -3.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    # ray 0: the root at x = -1 is in the NaN half, the NaN -> finite step is not a crossing;
    # ray 2 stays in the NaN half; ray 3 meets y = -sqrt(0.75) at t = 3 - sqrt(0.75)
    expect = np.array([4.0, 2.0, np.inf, 3.0 - np.sqrt(0.75)])
    t, which = first_roots(half_nan_sphere, *BOX, o, d, eps=2.0**-44)
    np.testing.assert_allclose(t, expect, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(which, [0, 0, -1, 0])
    t, _ = first_roots(lambda x, y, z, w: np.where(x < 0, np.nan, 1.0), *BOX, o, d)
    assert np.all(np.isinf(t))


def test_chunking_is_invisible():
    o, d = camera_rays((3, 2, 1), (0, 0, 0), (0, 0, 1), 30.0, 16, 16)
    t1, w1 = first_roots(sphere, *BOX, o, d, isovalues=(0.0, -0.5))
    t2, w2 = first_roots(sphere, *BOX, o, d, isovalues=(0.0, -0.5), chunk=37)
    np.testing.assert_array_equal(t1, t2)
    np.testing.assert_array_equal(w1, w2)
