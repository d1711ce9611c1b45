"""Ray–trilinear cell intersection (jaxiso.volume._cell) against float64 numpy references.

The reference field is the trilinear interpolant written as the sum of its 8 weighted
corners (not nested interpolation, no cubic). The reference first root samples g - iso
densely along the segment, takes the first sign change or zero and bisects it in float64;
the roots of a float64 cubic fitted through 4 exact samples (numpy.roots) cross-check it.
Cases too close to tangency for float32 to decide are excluded from the comparisons (see
`ambiguous`).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxiso.volume import _cell as cell

METHODS = ("neubauer", "analytic")
BITS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]  # index 4a + 2b + c


# ------------------------------------------------------------------- float64 references

def f64_field(corners, u):
    """Trilinear interpolant as the sum of weighted corners: corners [..., 8], u [..., 3]."""
    corners = np.asarray(corners, np.float64)
    u = np.asarray(u, np.float64)
    total = 0.0
    for index, bits in enumerate(BITS):
        weight = 1.0
        for axis, bit in enumerate(bits):
            weight = weight * (u[..., axis] if bit else 1.0 - u[..., axis])
        total = total + corners[..., index] * weight
    return total


def f64_along(corners, p0, dl, s):
    """g(s) = F(p0 + s dl) in float64; s [n] or [n, m]."""
    s = np.asarray(s, np.float64)
    extra = s.ndim - 1
    p0 = np.asarray(p0, np.float64).reshape(p0.shape[:1] + (1,) * extra + (3,))
    dl = np.asarray(dl, np.float64).reshape(dl.shape[:1] + (1,) * extra + (3,))
    corners = np.asarray(corners).reshape(corners.shape[:1] + (1,) * extra + (8,))
    return f64_field(corners, p0 + s[..., None] * dl)


def reference_first_root(corners, p0, dl, s1, iso, samples=4097, bisections=60):
    """First s in [0, s1] with g(s) - iso = 0 (sign change or exact zero) -> (s, hit)."""
    s1 = np.asarray(s1, np.float64)
    iso = np.asarray(iso, np.float64)
    rows = np.arange(len(s1))
    grid = s1[:, None] * np.linspace(0.0, 1.0, samples)
    h = f64_along(corners, p0, dl, grid) - iso[:, None]
    crossing = np.sign(h[:, :-1]) * np.sign(h[:, 1:]) <= 0
    hit = crossing.any(axis=1)
    first = np.argmax(crossing, axis=1)
    lo, hi = grid[rows, first], grid[rows, first + 1]
    h_lo = h[rows, first]
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        h_mid = f64_along(corners, p0, dl, mid) - iso
        left = np.sign(h_mid) * np.sign(h_lo) <= 0
        lo, hi = np.where(left, lo, mid), np.where(left, mid, hi)
        h_lo = np.where(left, h_lo, h_mid)
    root = np.where(h[rows, first] == 0, grid[rows, first], 0.5 * (lo + hi))
    return np.where(hit, root, np.inf), hit


def f64_sigma_cubic(corners, p0, dl, s1):
    """Cubic of g in sigma = s / s1 from 4 exact float64 samples -> [n, 4] ascending."""
    nodes = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    values = f64_along(corners, p0, dl, np.asarray(s1, np.float64)[:, None] * nodes)
    return np.linalg.solve(np.vander(nodes, 4, increasing=True), values.T).T


def real_roots(a):
    """Real roots of polynomials a [n, k] (ascending; leading zeros allowed) by numpy.roots
    -> [n, k - 1], NaN-padded. Roots with |imag| > 1e-9 count as complex."""
    out = np.full((len(a), a.shape[1] - 1), np.nan)
    for i, row in enumerate(a):
        roots = np.roots(row[::-1]) if np.any(row[1:]) else np.zeros(0)
        roots = roots[np.abs(roots.imag) <= 1e-9].real
        out[i, :roots.size] = roots
    return out


def ambiguous(corners, p0, dl, s1, iso):
    """Cases float32 cannot be expected to decide: g - iso within 1e-4 of the corner range
    at an end or at an extremum inside the segment, or two roots closer than 1e-3 s1."""
    a = f64_sigma_cubic(corners, p0, dl, s1)
    a[:, 0] -= iso
    tolerance = 1e-4 * (corners.max(axis=1) - corners.min(axis=1))
    critical = real_roots(np.stack([a[:, 1], 2 * a[:, 2], 3 * a[:, 3]], axis=1))
    critical = np.where((critical > 0) & (critical < 1), critical, np.nan)
    at = lambda x: np.abs(a[:, 0] + x * (a[:, 1] + x * (a[:, 2] + x * a[:, 3])))
    near_end = (at(0.0) < tolerance) | (at(1.0) < tolerance)
    near_tangent = np.any(np.nan_to_num(at(critical.T).T, nan=np.inf) < tolerance[:, None], 1)
    roots = real_roots(a)
    roots = np.sort(np.where((roots > -1e-3) & (roots < 1 + 1e-3), roots, np.nan), axis=1)
    close = np.nan_to_num(np.diff(roots, axis=1), nan=np.inf).min(axis=1) < 1e-3
    return near_end | near_tangent | close


def random_cells_and_rays(seed, n):
    """Random cells (corners in [-1, 1]), rays through the unit cube with random spacing,
    isovalues: half on the ray (a hit), half anywhere in the corner range."""
    rng = np.random.default_rng(seed)
    corners = rng.uniform(-1, 1, (n, 8)).astype(np.float32)
    spacing = rng.uniform(0.5, 2.0, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    dl = direction / spacing
    inside = rng.uniform(0, 1, (n, 3))
    # float64 slab test of the line through `inside` against the unit cube
    t_a, t_b = (0 - inside) / dl, (1 - inside) / dl
    t_in, t_out = np.minimum(t_a, t_b).max(axis=1), np.maximum(t_a, t_b).min(axis=1)
    p0 = np.clip(inside + t_in[:, None] * dl, 0, 1).astype(np.float32)
    dl = dl.astype(np.float32)
    s1 = (t_out - t_in).astype(np.float32)
    on_ray = f64_along(corners, p0, dl, rng.uniform(0, 1, n) * s1)
    anywhere = rng.uniform(corners.min(axis=1), corners.max(axis=1))
    iso = np.where(rng.uniform(size=n) < 0.5, on_ray, anywhere).astype(np.float32)
    return corners, p0, dl, s1, iso


@pytest.fixture(scope="module")
def random_case():
    corners, p0, dl, s1, iso = random_cells_and_rays(seed=7, n=2000)
    s_ref, hit_ref = reference_first_root(corners, p0, dl, s1, iso)
    return dict(corners=corners, p0=p0, dl=dl, s1=s1, iso=iso, s_ref=s_ref, hit_ref=hit_ref,
                clear=~ambiguous(corners, p0, dl, s1, iso))


# Eager jax compiles every primitive per shape (seconds per call on 2 cores), so the tests
# run the kernels jitted on inputs padded to one size: one compilation per method.
# test_jit_and_vmap_match_eager checks eager execution against these.
PAD = 4096
_first_root = jax.jit(cell.first_root, static_argnames=("method", "iterations"))
_first_root_multi = jax.jit(cell.first_root_multi, static_argnames=("method", "iterations"))
_ray_cubic = jax.jit(cell.ray_cubic)


def pad_rows(a, n, width=None):
    """Broadcast a to n rows ([n] or [n, width]) and zero-pad to PAD rows (float32)."""
    shape = (n,) if width is None else (n, width)
    a = np.broadcast_to(np.asarray(a, np.float32), shape)
    return np.concatenate([a, np.zeros((PAD - n,) + shape[1:], np.float32)])


def ray_cubic(corners, p0, dl):
    n = len(corners)
    coeffs = _ray_cubic(pad_rows(corners, n, 8), pad_rows(p0, n, 3), pad_rows(dl, n, 3))
    return np.asarray(coeffs)[:n]


def solve(coeffs, iso, s1, method, iterations=cell.NEUBAUER_ITERATIONS):
    """first_root on a batch [n] (or one cubic) -> numpy (s [n], hit [n])."""
    coeffs = np.reshape(coeffs, (-1, 4))
    n = len(coeffs)
    s, hit = _first_root(pad_rows(coeffs, n, 4), pad_rows(iso, n), pad_rows(s1, n),
                         method=method, iterations=iterations)
    return np.asarray(s)[:n], np.asarray(hit)[:n]


def solve_multi(coeffs, isovalues, s1, method):
    n = len(coeffs)
    s, hit, which = _first_root_multi(pad_rows(coeffs, n, 4), isovalues, pad_rows(s1, n),
                                      method=method)
    return np.asarray(s)[:n], np.asarray(hit)[:n], np.asarray(which)[:n]


# ---------------------------------------------------------------------------- the field

def test_trilinear_and_gradient_match_float64():
    rng = np.random.default_rng(0)
    corners = rng.uniform(-1, 1, (50, 8)).astype(np.float32)
    u = rng.uniform(0, 1, (50, 3)).astype(np.float32)
    np.testing.assert_allclose(cell.trilinear(corners, u), f64_field(corners, u), atol=2e-6)
    # corners come back exactly
    for index, bits in enumerate(BITS):
        at_corner = np.broadcast_to(np.array(bits, np.float32), (50, 3))
        np.testing.assert_array_equal(cell.trilinear(corners, at_corner), corners[:, index])
    h = 1e-6
    central = np.stack([(f64_field(corners, u + h * e) - f64_field(corners, u - h * e)) / (2 * h)
                        for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(cell.trilinear_gradient(corners, u), central, atol=1e-5)


def test_ray_cubic_reproduces_field_along_ray():
    corners, p0, dl, s1, _ = random_cells_and_rays(seed=1, n=500)
    coeffs = np.asarray(ray_cubic(corners, p0, dl), np.float64)
    s = s1[:, None] * np.linspace(-0.5, 1.5, 9)   # also off the segment: the whole cubic
    poly = sum(coeffs[:, k, None] * s**k for k in range(4))
    np.testing.assert_allclose(poly, f64_along(corners, p0, dl, s), atol=1e-5)
    # c0 is F(p0) and is exact at a corner
    at_corner = np.zeros((500, 3), np.float32)
    np.testing.assert_array_equal(np.asarray(ray_cubic(corners, at_corner, dl))[:, 0],
                                  corners[:, 0])


def test_reference_agrees_with_cubic_roots(random_case):
    """The sampled/bisected reference and numpy.roots of the float64 cubic agree."""
    c = random_case
    a = f64_sigma_cubic(c["corners"], c["p0"], c["dl"], c["s1"])
    a[:, 0] -= c["iso"]
    roots = real_roots(a)
    first = np.where((roots >= 0) & (roots <= 1), roots, np.inf).min(axis=1) * c["s1"]
    clear = c["clear"]
    np.testing.assert_array_equal(np.isfinite(first)[clear], c["hit_ref"][clear])
    both = clear & c["hit_ref"]
    np.testing.assert_allclose(first[both], c["s_ref"][both], atol=1e-9, rtol=0)


# ------------------------------------------------------------------ random cells vs ref

# The brief expected the closed form to need a looser bound in float32; with deflation
# (see _cell._cubic_real_roots) it meets the same one (100k cells: max 4e-5 for both;
# textbook Cardano: 89 wrong hit masks, max error 0.8 of the segment).
@pytest.mark.parametrize("method, bound", [("neubauer", 1e-4), ("analytic", 1e-4)])
def test_random_cells_match_reference(random_case, method, bound):
    c = random_case
    coeffs = ray_cubic(c["corners"], c["p0"], c["dl"])
    s, hit = solve(coeffs, c["iso"], c["s1"], method)
    clear = c["clear"]
    assert clear.mean() > 0.97 and c["hit_ref"].mean() > 0.4   # the sample is not trivial
    mismatched = np.flatnonzero(clear & (hit != c["hit_ref"]))
    assert mismatched.size == 0, f"{method}: hit masks differ at {mismatched[:10]}"
    both = clear & hit
    error = np.abs(s[both] - c["s_ref"][both]) / c["s1"][both]
    assert error.max() <= bound, f"{method}: max relative error {error.max():.2e}"
    assert np.all(np.isinf(s[~hit])) and np.all((s[hit] >= 0) & (s[hit] <= c["s1"][hit]))


def test_neubauer_error_falls_with_iterations(random_case):
    """The iteration count matters (the test can fail): 2 steps are not enough."""
    c = random_case
    coeffs = ray_cubic(c["corners"], c["p0"], c["dl"])
    both = c["clear"] & c["hit_ref"]
    errors = []
    for iterations in (2, cell.NEUBAUER_ITERATIONS):
        s, _ = solve(coeffs, c["iso"], c["s1"], "neubauer", iterations=iterations)
        errors.append(np.max(np.abs(s[both] - c["s_ref"][both]) / c["s1"][both]))
    assert errors[0] > 1e-3 > 1e-4 > errors[1]


# ------------------------------------------------------------------------- edge cases

@pytest.mark.parametrize("method", METHODS)
def test_isovalue_equal_to_entry_corner(method):
    rng = np.random.default_rng(3)
    corners = rng.uniform(-1, 1, (8, 8)).astype(np.float32)
    entries = np.array(BITS, np.float32)                       # one cell per corner
    dl = np.where(entries == 0, 0.7, -0.7).astype(np.float32)  # pointing into the cell
    iso = corners[np.arange(8), np.arange(8)]
    coeffs = ray_cubic(corners, entries, dl)
    s, hit = solve(coeffs, iso, np.full(8, 1.0, np.float32), method)
    assert hit.all() and np.all(s == 0)


@pytest.mark.parametrize("method", METHODS)
def test_constant_cell(method):
    corners = np.full((2, 8), 0.25, np.float32)
    p0 = np.array([[0.0, 0.3, 0.1]] * 2, np.float32)
    dl = np.array([[0.5, 0.2, 0.1]] * 2, np.float32)
    coeffs = ray_cubic(corners, p0, dl)
    s, hit = solve(coeffs, np.array([0.25, 0.5], np.float32), np.ones(2, np.float32), method)
    assert hit.tolist() == [True, False]
    assert s[0] == 0 and np.isinf(s[1])


@pytest.mark.parametrize("method", METHODS)
def test_axis_parallel_rays_and_edges(method):
    """Rays along each axis (interior, on a face, on an edge): g is linear in s, so the root
    is (iso - F(entry)) / (F(exit) - F(entry)) * s1, with F in float64."""
    rng = np.random.default_rng(4)
    n = 3 * 3
    corners = rng.uniform(-1, 1, (n, 8)).astype(np.float32)
    p0 = np.zeros((n, 3), np.float32)
    dl = np.zeros((n, 3), np.float32)
    for k in range(n):
        axis, where = divmod(k, 3)
        others = [a for a in range(3) if a != axis]
        # interior line, line on a face, line on an edge
        p0[k, others] = [(0.37, 0.61), (0.0, 0.61), (1.0, 0.0)][where]
        dl[k, axis] = 1.25                                    # spacing 0.8 along the axis
    s1 = np.full(n, 0.8, np.float32)
    f_in = f64_field(corners, p0)
    f_out = f64_field(corners, p0 + s1[:, None] * dl.astype(np.float64))
    iso = (f_in + 0.3 * (f_out - f_in)).astype(np.float32)
    expected = (iso - f_in) / (f_out - f_in) * 0.8
    coeffs = np.asarray(ray_cubic(corners, p0, dl))
    assert np.all(coeffs[:, 2:] == 0)                          # exactly linear
    s, hit = solve(coeffs, iso, s1, method)
    assert hit.all()
    np.testing.assert_allclose(s, expected, atol=1e-5)


@pytest.mark.parametrize("method", METHODS)
def test_grazing_rays_in_a_face(method):
    """Rays inside the face x = 0 (bilinear there: g quadratic) and along the face diagonal,
    against the float64 reference."""
    rng = np.random.default_rng(5)
    n = 200
    corners = rng.uniform(-1, 1, (n, 8)).astype(np.float32)
    p0 = np.zeros((n, 3), np.float32)
    p0[:, 1] = rng.uniform(0, 1, n)
    dl = np.zeros((n, 3), np.float32)
    dl[:, 2] = 1.0
    dl[:, 1] = np.where(p0[:, 1] < 0.5, 0.5, -0.5)
    s1 = np.ones(n, np.float32)                    # stays in the face: |y step| <= 0.5
    iso = f64_along(corners, p0, dl, rng.uniform(0, 1, n)).astype(np.float32)
    coeffs = np.asarray(ray_cubic(corners, p0, dl))
    assert np.all(coeffs[:, 3] == 0)
    s_ref, hit_ref = reference_first_root(corners, p0, dl, s1, iso)
    clear = ~ambiguous(corners, p0, dl, s1, iso)
    s, hit = solve(coeffs, iso, s1, method)
    assert np.array_equal(hit[clear], hit_ref[clear]) and clear.mean() > 0.9
    both = clear & hit
    np.testing.assert_allclose(s[both], s_ref[both], atol=1e-4)


@pytest.mark.parametrize("method", METHODS)
def test_zero_length_segment(method):
    corners = np.random.default_rng(6).uniform(-1, 1, (2, 8)).astype(np.float32)
    p0 = np.zeros((2, 3), np.float32)
    dl = np.full((2, 3), 0.5, np.float32)
    coeffs = ray_cubic(corners, p0, dl)
    iso = np.array([corners[0, 0], corners[1, 0] + 0.01], np.float32)
    s, hit = solve(coeffs, iso, np.zeros(2, np.float32), method)
    assert hit.tolist() == [True, False] and s[0] == 0 and np.isinf(s[1])


@pytest.mark.parametrize("method", METHODS)
def test_non_finite_inputs_never_hit(method):
    corners = np.random.default_rng(8).uniform(-1, 1, (6, 8)).astype(np.float32)
    corners[0, 3] = np.nan
    corners[1, 0] = np.inf
    corners[2, 7] = -np.inf
    p0 = np.full((6, 3), 0.0, np.float32)
    dl = np.full((6, 3), 0.5, np.float32)
    coeffs = ray_cubic(corners, p0, dl)
    iso = np.array([0.0, 0.0, 0.0, np.nan, 0.0, 0.0], np.float32)
    s1 = np.array([1.0, 1.0, 1.0, 1.0, np.inf, -1.0], np.float32)
    s, hit = solve(coeffs, iso, s1, method)
    assert not hit.any() and np.all(np.isinf(s)) and np.all(s > 0)


@pytest.mark.parametrize("method", METHODS)
def test_huge_finite_inputs_never_give_nan(method):
    """Overflow inside the kernel (c3 s1^3, discriminants) is a miss or a valid hit."""
    coeffs = np.array([[1e30, -3e30, 2e30, -1e30], [1e18, -3e18, 2e18, 1e17],
                       [1e-30, -3e-30, 2e-30, 1e-31], [-0.5, 1.0, 0.0, 1e-38]], np.float32)
    s1 = np.array([1e4, 1.0, 1.0, 1.0], np.float32)
    s, hit = solve(coeffs, 0.0, s1, method)
    assert not np.isnan(s).any()
    assert not hit[0] and np.all((s[hit] >= 0) & (s[hit] <= s1[hit]))
    assert hit[3] and abs(s[3] - 0.5) < 1e-6


def f32(*values):
    return np.array(values, np.float32)


def expand(roots, lead=1.0):
    """Ascending float64 coefficients of lead * prod (x - r)."""
    return np.polynomial.polynomial.polyfromroots(roots) * lead


# (ascending coefficients on s in [0, 1], iso, expected first root or None, tolerance)
POLYNOMIALS = {
    "two roots in the cell": (expand([0.2, 0.6, 2.0]), 0.0, 0.2, 1e-5),
    "three roots in the cell": (expand([0.15, 0.5, 0.85]), 0.0, 0.15, 1e-5),
    "roots behind the entry": (expand([-0.3, -0.1, 0.4]), 0.0, 0.4, 1e-5),
    "quadratic": (f32(0.21, -1.0, 1.0, 0.0), 0.0, 0.3, 1e-5),
    "linear": (f32(-0.25, 1.0, 0.0, 0.0), 0.0, 0.25, 1e-6),
    "linear with iso": (f32(0.5, -2.0, 0.0, 0.0), -0.5, 0.5, 1e-6),
    "nearly quadratic": (expand([0.3, 0.7, -1e5], lead=-1e-5), 0.0, 0.3, 1e-5),
    "small root, large complex pair": (
        np.polynomial.polynomial.polymul([-0.5, 1.0], [100.0, 0.0, 1.0]), 0.0, 0.5, 1e-5),
    "triple root (crossing)": (expand([0.5, 0.5, 0.5]), 0.0, 0.5, 1e-2),
    "no root": (expand([1.5, 2.0, -0.5]), 0.0, None, 0),
    "constant": (f32(0.3, 0.0, 0.0, 0.0), 0.2, None, 0),
    "pure cubic through 0 at the entry": (f32(0.0, 0.0, 0.0, 1.0), 0.0, 0.0, 0.0),
}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", list(POLYNOMIALS))
def test_special_polynomials(method, name):
    coeffs, iso, expected, tolerance = POLYNOMIALS[name]
    s, hit = solve(np.asarray(coeffs, np.float32), iso, 1.0, method)
    if expected is None:
        assert not hit[0] and np.isinf(s[0])
    else:
        assert hit[0] and abs(s[0] - expected) <= tolerance, (name, s[0])


@pytest.mark.parametrize("method", METHODS)
def test_tangential_double_root_is_finite(method):
    """g touches iso at 0.5 without crossing: may be missed (documented), but never NaN,
    and a reported hit is near the touching point."""
    s, hit = solve(np.asarray(expand([0.5, 0.5, 3.0]), np.float32), 0.0, 1.0, method)
    assert not np.isnan(s[0])
    assert (not hit[0] and np.isinf(s[0])) or abs(s[0] - 0.5) < 1e-2


@pytest.mark.parametrize("method", METHODS)
def test_root_is_in_world_units(method):
    """The same ray with a 4x finer spacing: dl 4x longer, s1 4x shorter, s 4x shorter."""
    corners, p0, dl, s1, iso = random_cells_and_rays(seed=9, n=300)
    s_a, hit_a = solve(ray_cubic(corners, p0, dl), iso, s1, method)
    s_b, hit_b = solve(ray_cubic(corners, p0, 4 * dl), iso, s1 / 4, method)
    clear = ~ambiguous(corners, p0, dl, s1, iso)
    assert np.array_equal(hit_a[clear], hit_b[clear])
    both = clear & hit_a
    np.testing.assert_allclose(s_b[both], s_a[both] / 4, atol=1e-4 * s1[both].max())


@pytest.mark.parametrize("method", METHODS)
def test_offset_data_shifted_by_the_isovalue(method):
    """Corners 1000 +- 1: float32 rounding of F ~ 6e-5 of the range moves roots; passing
    corners - iso (the documented remedy) restores the accuracy contract."""
    corners, p0, dl, s1, _ = random_cells_and_rays(seed=12, n=500)
    corners = (1000.0 + corners.astype(np.float64)).astype(np.float32)
    rng = np.random.default_rng(13)
    iso = f64_along(corners, p0, dl, rng.uniform(0, 1, 500) * s1).astype(np.float32)
    s_ref, hit_ref = reference_first_root(corners, p0, dl, s1, iso)
    clear = ~ambiguous(corners, p0, dl, s1, iso)
    s, hit = solve(ray_cubic(corners - iso[:, None], p0, dl), 0.0, s1, method)
    assert np.array_equal(hit[clear], hit_ref[clear]) and hit_ref[clear].all()
    np.testing.assert_allclose(s[clear], s_ref[clear], rtol=0, atol=1e-4 * s1.max())


# ---------------------------------------------------------------- multiple isovalues

@pytest.fixture(scope="module")
def multi_case():
    """400 random rays, K = 3 isovalues (as in the eager test): float64 reference per
    isovalue; decidable where every isovalue is and the two nearest roots are apart."""
    corners, p0, dl, s1, _ = random_cells_and_rays(seed=10, n=400)
    isovalues = np.array([-0.4, 0.05, 0.3], np.float32)
    s_ref = np.stack([reference_first_root(corners, p0, dl, s1, np.full(400, v))[0]
                      for v in isovalues], axis=1)
    clear = np.all([~ambiguous(corners, p0, dl, s1, np.full(400, v, np.float32))
                    for v in isovalues], axis=0)
    ordered = np.sort(s_ref, axis=1)
    finite = np.where(np.isfinite(ordered), ordered, 0.0)
    clear &= ~(np.isfinite(ordered[:, 1]) & (finite[:, 1] - finite[:, 0] < 1e-3 * s1))
    return ray_cubic(corners, p0, dl), isovalues, s1, s_ref, clear


@pytest.mark.parametrize("method", METHODS)
def test_multiple_isovalues(multi_case, method):
    coeffs, isovalues, s1, s_ref, clear = multi_case
    s, hit, which = solve_multi(coeffs, isovalues, s1, method)
    hit_ref = np.isfinite(s_ref).any(axis=1)
    assert np.array_equal(hit[clear], hit_ref[clear]) and hit_ref[clear].mean() > 0.3
    both = clear & hit
    np.testing.assert_allclose(s[both], s_ref.min(axis=1)[both], atol=1e-4 * s1.max())
    np.testing.assert_array_equal(which[both], np.argmin(s_ref, axis=1)[both])
    assert np.all(which[~hit] == -1) and np.all(np.isinf(s[~hit]))


def test_multiple_isovalues_by_hand():
    coeffs = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], np.float32)  # g(s) = s
    isovalues = np.array([0.7, 0.2, 5.0], np.float32)
    for method in METHODS:
        s, hit, which = solve_multi(coeffs, isovalues, np.array([1.0, 0.1]), method)
        assert hit.tolist() == [True, False] and which.tolist() == [1, -1]
        assert abs(s[0] - 0.2) < 1e-6 and np.isinf(s[1])


# ------------------------------------------------------------------- jit, vmap, misc

@pytest.mark.parametrize("method", METHODS)
def test_eager_jit_and_vmap_agree(random_case, method):
    """Eager, jit (the padded jitted kernels the other tests use) and vmap give the same
    results; a second call does not retrace."""
    c = random_case
    n = len(c["s1"])
    corners, p0, dl = pad_rows(c["corners"], n, 8), pad_rows(c["p0"], n, 3), pad_rows(c["dl"], n, 3)
    iso, s1 = pad_rows(c["iso"], n), pad_rows(c["s1"], n)
    traces = []

    def one_ray(corners, p0, dl, iso, s1):
        traces.append(1)
        coeffs = cell.ray_cubic(corners, p0, dl)
        return (coeffs, *cell.first_root(coeffs, iso, s1, method=method))

    eager = one_ray(corners, p0, dl, iso, s1)
    traces.clear()
    mapped_fn = jax.jit(jax.vmap(one_ray))
    mapped = mapped_fn(corners, p0, dl, iso, s1)
    mapped_fn(corners + 1, p0, dl, iso, s1)
    assert len(traces) == 1
    jitted_coeffs = _ray_cubic(corners, p0, dl)
    jitted = (jitted_coeffs, *_first_root(jitted_coeffs, iso, s1, method=method))
    # XLA fuses differently (FMA) under jit: coefficients agree to float32 rounding, roots
    # to the accuracy contract, hit masks exactly where float32 can decide (padding rows are
    # constant cells equal to the isovalue: hit at 0).
    decidable = np.concatenate([c["clear"], np.ones(PAD - n, bool)])
    for other in (jitted, mapped):
        np.testing.assert_allclose(other[0], eager[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(other[2])[decidable], eager[2][decidable])
        both = decidable & np.asarray(eager[2])
        np.testing.assert_allclose(np.asarray(other[1])[both], eager[1][both], rtol=0,
                                   atol=1e-4 * s1.max())
    # first_root_multi (jitted) is the nearest of eager single-isovalue roots
    isovalues = np.array([-0.2, 0.1, 0.4], np.float32)
    singles = np.stack([np.asarray(cell.first_root(eager[0], np.full_like(iso, v), s1,
                                                   method=method).s)   # same shapes: cached
                        for v in isovalues], axis=-1)
    s, hit, which = solve_multi(eager[0][:n], isovalues, s1[:n], method)
    np.testing.assert_allclose(s, singles[:n].min(axis=-1), rtol=0, atol=1e-4 * s1.max())
    np.testing.assert_array_equal(hit, np.isfinite(singles[:n]).any(axis=-1))
    unique = hit & (np.sort(singles[:n], axis=-1)[:, 1] > singles[:n].min(axis=-1) + 1e-3)
    np.testing.assert_array_equal(which[unique], singles[:n].argmin(axis=-1)[unique])


def test_unknown_method_is_an_error():
    with pytest.raises(ValueError, match="method"):
        cell.first_root(jnp.zeros(4), 0.0, 1.0, method="bisection")
