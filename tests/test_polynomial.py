"""Arithmetic "polynomial": the degree read from f's jaxpr, the Chebyshev enclosure of a
ray piece against float64 sampling written here, and the scenes that use it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji
from jaxiso.implicit._polynomial import (
    MAX_DEGREE,
    TABLE_FROM,
    chebyshev_enclosure,
    chebyshev_map,
    polynomial_degree,
)


def random_monomials(rng, degree, terms):
    """[(k, a, b, c)]: terms monomials of total degree 1..degree, one of exactly degree."""
    out = []
    for i in range(terms):
        total = degree if i == 0 else int(rng.integers(1, degree + 1))
        a = int(rng.integers(0, total + 1))
        b = int(rng.integers(0, total - a + 1))
        out.append((float(rng.normal()), a, b, total - a - b))
    return out


def expanded(mono, const=-0.3):
    def f(x, y, z):
        s = const
        for k, a, b, c in mono:
            s = s + k * x**a * y**b * z**c
        return s
    return f


def float64_values(mono, pts, const=-0.3):
    x, y, z = (pts[..., i].astype(np.float64) for i in range(3))
    return const + sum(k * x**a * y**b * z**c for k, a, b, c in mono)


def point_field(f):
    return lambda x, y, z, w, params: f(x, y, z)


# ---- the degree ---------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(6))
def test_degree_of_generated_spellings(seed):
    """Expanded sums, their Horner-like nesting, products of factors, vector forms and
    float exponents: the degree is the true total degree."""
    rng = np.random.default_rng(seed)
    d1, d2 = int(rng.integers(1, 6)), int(rng.integers(1, 6))
    m1, m2 = random_monomials(rng, d1, 7), random_monomials(rng, d2, 5)
    f1, f2 = expanded(m1), expanded(m2)
    cases = {
        "sum": (f1, d1),
        "product": (lambda x, y, z: f1(x, y, z) * f2(x, y, z), d1 + d2),
        "power": (lambda x, y, z: f1(x, y, z) ** 3 - f2(x, y, z) / 7.0, 3 * d1),
        "float power": (lambda x, y, z: f2(x, y, z) ** 2.0 + x, max(2 * d2, 1)),
        "nested": (lambda x, y, z: x * (y * (z * f1(x, y, z) + 1.0) - 2.0), d1 + 3),
        "vector": (lambda x, y, z: jnp.dot(jnp.stack([x, y, z]), jnp.array([1.0, 2, 3])) ** 2
                   + jnp.sum(jnp.array([x, y]) ** 2), 2),
        "square": (lambda x, y, z: jnp.square(f2(x, y, z)) - jnp.power(z, 3), max(2 * d2, 3)),
    }
    for name, (f, degree) in cases.items():
        assert polynomial_degree(point_field(f), 0.0, ())[0] == degree, name


def test_degree_with_w_and_params_as_coefficients():
    def f(x, y, z, w, params):
        return jnp.sin(w) * x**3 + jnp.exp(params["a"]) * y * z + jnp.where(w > 0, 1.0, 2.0) * x
    assert polynomial_degree(f, 0.5, {"a": 1.0})[0] == 3
    # a coefficient array in params
    def g(x, y, z, w, params):
        return jnp.dot(params["c"], jnp.stack([x, y * y, z**3]))
    assert polynomial_degree(g, 0.0, {"c": jnp.ones(3)})[0] == 3
    # a nested jit is read through
    inner = jax.jit(lambda x, y: x * y)
    assert polynomial_degree(lambda x, y, z, w, p: inner(x, inner(y, z)), 0.0, ())[0] == 3


@pytest.mark.parametrize("f", [
    lambda x, y, z: jnp.sin(x) + y,
    lambda x, y, z: jnp.sqrt(x * x + y * y + z * z) - 1.0,
    lambda x, y, z: jnp.abs(x) + y,
    lambda x, y, z: jnp.maximum(x, y * z),
    lambda x, y, z: jnp.where(x > 0, x, y),
    lambda x, y, z: 1.0 / (x + 2.0),
    lambda x, y, z: x**2.5,
    lambda x, y, z: x**-1.0,
    lambda x, y, z: jnp.exp(x) * 0.0,
], ids=["sin", "sqrt", "abs", "max", "where", "div", "pow2.5", "pow-1", "exp*0"])
def test_non_polynomials_have_no_degree(f):
    assert polynomial_degree(point_field(f), 0.0, ())[0] is None


# ---- the enclosure ------------------------------------------------------------------

def test_chebyshev_map_reproduces_the_basis():
    """M maps the values of T_k at the nodes to the unit vector e_k (float64)."""
    for n in (1, 2, 5, 10, 16):
        nodes, M, norm = chebyshev_map(n)
        for k in range(n + 1):
            tk = np.polynomial.chebyshev.chebval(2 * nodes - 1, np.eye(n + 1)[k])
            np.testing.assert_allclose(M @ tk, np.eye(n + 1)[k], atol=1e-12)
        assert norm <= 4.0 / 3.0 + 1e-12


@pytest.mark.parametrize("degree", [1, 2, 3, 5, 8, 12, MAX_DEGREE])
def test_enclosure_holds_float64_samples_and_tightens(degree):
    """On random pieces at scales 1 to 1e-4 of the box, the enclosure holds f's float64
    values at 513 points of the piece, and on the small pieces it is within a few
    percent of their range (it converges quadratically)."""
    rng = np.random.default_rng(degree)
    mono = random_monomials(rng, degree, 12)
    g = point_field(expanded(mono))
    n = 64
    for scale in (1.0, 1e-2, 1e-4):
        p = rng.uniform(-0.9, 0.9, (n, 3)).astype(np.float32)
        D = (rng.normal(size=(n, 3)) * scale).astype(np.float32)
        s0 = np.zeros(n, np.float32)
        s1 = np.ones(n, np.float32)
        r = chebyshev_enclosure(g, degree, jnp.asarray(p), jnp.asarray(D), jnp.asarray(s0),
                                jnp.asarray(s1), 0.0, ())
        lo, hi = np.asarray(r.lo, np.float64), np.asarray(r.hi, np.float64)
        s = np.linspace(0.0, 1.0, 513)
        pts = p[:, None, :].astype(np.float64) + s[None, :, None] * D[:, None, :]
        v = float64_values(mono, pts)
        vmin, vmax = v.min(axis=1), v.max(axis=1)
        # the float32 points and values are within a few ulps of the float64 ones
        slack = 1e-5 * np.abs(v).max(axis=1)
        assert np.all(lo <= vmin + slack), (scale, np.max(lo - vmin))
        assert np.all(hi >= vmax - slack), (scale, np.max(vmax - hi))
        if scale == 1e-2:
            ratio = (hi - lo) / np.maximum(vmax - vmin, 1e-30)
            assert np.median(ratio) < 1.05, np.median(ratio)


# ---- scenes -------------------------------------------------------------------------

def check_against_float64(hits, rays, mono, const=-0.6):
    """Hit mask (>= 99.5%) and depth (within eps 2^-11 plus the reference's step) of
    hits on the box [-1, 1]^3 against sign changes of the float64 polynomial sampled
    every 5e-4 along each ray; returns where both hit."""
    o = np.asarray(rays.origin, np.float64).reshape(-1, 3)
    d = np.asarray(rays.direction, np.float64).reshape(-1, 3)
    ts = np.linspace(0.0, 8.0, 16001)
    pts = o[:, None, :] + ts[None, :, None] * d[:, None, :]
    inside = np.all(np.abs(pts) <= 1.0, axis=-1)
    v = float64_values(mono, pts, const=const)
    change = inside[:, :-1] & inside[:, 1:] & (np.sign(v[:, :-1]) != np.sign(v[:, 1:]))
    hit64 = change.any(axis=1)
    assert 0.2 < hit64.mean() < 0.9
    hit = np.asarray(hits.hit).reshape(-1)
    assert np.mean(hit == hit64) >= 0.995
    both = hit & hit64
    t64 = ts[np.argmax(change, axis=1)]
    t = np.asarray(hits.t).reshape(-1)
    assert np.max(np.abs(t[both] - t64[both])) < 2.0**-11 + 8.0 / 16000
    return both


def barth(x, y, z):
    phi = (1 + 5**0.5) / 2
    return (4 * (phi**2 * x**2 - y**2) * (phi**2 * y**2 - z**2) * (phi**2 * z**2 - x**2)
            - (1 + 2 * phi) * (x**2 + y**2 + z**2 - 1) ** 2)


def test_auto_picks_polynomial_from_degree_three():
    box = dict(lo=(-1.5,) * 3, hi=(1.5,) * 3)
    scene = ji.ImplicitSurface(barth, **box).prepared()
    assert scene.arithmetic == "polynomial"
    assert "degree 6" in scene.arithmetic_report
    sphere = ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z - 1, **box).prepared()
    assert sphere.arithmetic in ("interval", "affine")
    torus = ji.ImplicitSurface(lambda x, y, z: (jnp.sqrt(x * x + y * y) - 0.8) ** 2
                               + z * z - 0.1, **box).prepared()
    assert torus.arithmetic in ("interval", "affine")
    outward = ji.ImplicitSurface(barth, rounding="outward", **box).prepared()
    assert outward.arithmetic in ("interval", "affine")


def test_polynomial_refused_where_it_does_not_apply():
    box = dict(lo=(-1.5,) * 3, hi=(1.5,) * 3)
    rays = ji.Camera.look_at((4, 3, 2), (0, 0, 0), (0, 0, 1), 30, 4, 4).rays()
    cases = [(lambda x, y, z: jnp.sin(x) + y, {}, "needs f to be a polynomial"),
             (lambda x, y, z: x**20 + y - 0.5, {}, "degree 20"),
             (barth, {"rounding": "outward"}, "outward")]
    for f, extra, message in cases:
        scene = ji.ImplicitSurface(f, arithmetic="polynomial", **box, **extra)
        with pytest.raises(ValueError, match=message):
            ji.intersect(scene, rays)


def test_polynomial_scene_matches_a_float64_reference():
    """A generated degree-7 polynomial through the default call (auto -> polynomial),
    hit mask and depth against each ray's polynomial solved in float64 here."""
    rng = np.random.default_rng(7)
    mono = random_monomials(rng, 7, 25)
    mono = [(0.1 * k, a, b, c) for k, a, b, c in mono]
    f = expanded(mono + [(1.0, 2, 0, 0), (1.0, 0, 2, 0), (1.0, 0, 0, 2)], const=-0.6)
    scene = ji.ImplicitSurface(f, lo=(-1.0,) * 3, hi=(1.0,) * 3)
    cam = ji.Camera.look_at((3, 2.2, 1.6), (0, 0, 0), (0, 0, 1), 30, 24, 24)
    rays = cam.rays()
    hits = ji.intersect(scene, rays)
    assert scene.prepared().arithmetic == "polynomial"
    check_against_float64(hits, rays, mono + [(1.0, 2, 0, 0), (1.0, 0, 2, 0), (1.0, 0, 0, 2)])


# ---- long polynomials: the Chebyshev table ------------------------------------------

def long_polynomial(seed=3, degree=6, terms=70):
    """A generated polynomial of more than `TABLE_FROM` jaxpr equations (a sphere of
    radius sqrt(0.6) bent by small monomials), with its monomials for float64."""
    rng = np.random.default_rng(seed)
    mono = [(0.05 * k, a, b, c) for k, a, b, c in random_monomials(rng, degree, terms)]
    mono += [(1.0, 2, 0, 0), (1.0, 0, 2, 0), (1.0, 0, 0, 2)]
    return expanded(mono, const=-0.6), mono


def test_table_reproduces_f_and_is_used_from_its_length():
    f, mono = long_polynomial()
    scene = ji.ImplicitSurface(f, lo=(-1.0,) * 3, hi=(1.0,) * 3).prepared()
    assert scene.facts.length >= TABLE_FROM and scene.polynomial_table is not None
    assert not scene.is_heavy()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (500, 3)).astype(np.float32)
    table = scene.polynomial_table
    got = np.asarray(table(jnp.asarray(pts[:, 0]), jnp.asarray(pts[:, 1]),
                           jnp.asarray(pts[:, 2])), np.float64)
    want = float64_values(mono, pts, const=-0.6)
    assert np.max(np.abs(got - want)) < 1e-5 * np.max(np.abs(want))
    # short polynomials keep their own code
    short = ji.ImplicitSurface(barth, lo=(-1.5,) * 3, hi=(1.5,) * 3).prepared()
    assert short.polynomial_table is None
    # a new box or params drop the table; the next preparation builds it anew
    moved = scene.replace(lo=(-0.5,) * 3)
    assert moved.polynomial_table is None and not moved.ready
    np.testing.assert_allclose(np.asarray(moved.prepared().polynomial_table.lo), -0.5)


def test_long_polynomial_matches_float64_and_differentiates():
    """The default call on a long polynomial (bisection on its table) against float64
    sampling; dt/dr of its radius parameter against central differences."""
    f, mono = long_polynomial(seed=5)

    def g(x, y, z, params):
        return f(x, y, z) + 0.6 - params["r"] ** 2

    cam = ji.Camera.look_at((3, 2.2, 1.6), (0, 0, 0), (0, 0, 1), 30, 20, 20)
    rays = cam.rays()

    def depth(r):
        scene = ji.ImplicitSurface(g, lo=(-1.0,) * 3, hi=(1.0,) * 3, params={"r": r})
        return ji.intersect(scene, rays)

    hits = depth(jnp.float32(0.6**0.5))
    both = check_against_float64(hits, rays, mono)

    r0, h = 0.6**0.5, 1e-2
    dt = np.asarray(jax.jacfwd(lambda r: depth(r).t)(jnp.float32(r0))).reshape(-1)
    fd = (np.asarray(depth(jnp.float32(r0 + h)).t, np.float64)
          - np.asarray(depth(jnp.float32(r0 - h)).t, np.float64)).reshape(-1) / (2 * h)
    # away from grazing rays (|dt/dr| large: t is far from linear over +-h there); the
    # differences carry eps / h ~ 0.05 of bisection's quantisation
    ok = both & np.isfinite(fd) & (np.abs(dt) < 5)
    assert ok.sum() > 20
    np.testing.assert_allclose(dt[ok], fd[ok], rtol=0.05, atol=0.1)


def test_spellings_of_one_polynomial_render_alike():
    """One quartic written five ways (expanded, factored, Horner in x, with jnp.power
    and a quadratic form, with its coefficients in params): every spelling reads as
    degree 4, gets "polynomial" through the default call, and finds the same hits."""
    def expanded_(x, y, z):
        return (x**4 + 2 * x**2 * y**2 + 2 * x**2 * z**2 + y**4 + 2 * y**2 * z**2 + z**4
                - 1.5 * x**2 - 1.5 * y**2 - 1.5 * z**2 + 0.5 + 0.3 * x * y * z)

    def factored(x, y, z):
        r2 = x * x + y * y + z * z
        return (r2 - 0.5) * (r2 - 1.0) + 0.3 * x * y * z

    def horner(x, y, z):
        r = y * y + z * z
        return (((x * x + (2 * r - 1.5)) * x * x) + (r * r - 1.5 * r + 0.5)
                + 0.3 * x * y * z)

    def powers(x, y, z):
        v = jnp.stack([x, y, z])
        r2 = v @ jnp.eye(3) @ v
        return jnp.power(r2, 2) - 1.5 * r2 + 0.5 + 0.3 * jnp.prod(v)

    def with_params(x, y, z, params):
        r2 = jnp.dot(jnp.stack([x, y, z]) ** 2, params["w"])
        return jnp.polyval(params["c"], r2) + params["k"] * x * y * z

    params = {"w": jnp.ones(3), "c": jnp.array([1.0, -1.5, 0.5]), "k": jnp.float32(0.3)}
    cam = ji.Camera.look_at((2.6, 1.9, 1.4), (0, 0, 0), (0, 0, 1), 35, 20, 20)
    rays = cam.rays()
    box = dict(lo=(-1.2,) * 3, hi=(1.2,) * 3)
    results = {}
    for f, extra in ((expanded_, {}), (factored, {}), (horner, {}), (powers, {}),
                     (with_params, {"params": params})):
        scene = ji.ImplicitSurface(f, **box, **extra).prepared()
        assert scene.facts.degree == 4, f.__name__
        assert scene.arithmetic == "polynomial", f.__name__
        results[f.__name__] = ji.intersect(scene, rays)
    first = results["expanded_"]
    assert 0.2 < float(np.mean(first.hit)) < 0.9
    for name, h in results.items():
        assert np.mean(np.asarray(h.hit) == np.asarray(first.hit)) >= 0.995, name
        both = np.asarray(h.hit) & np.asarray(first.hit)
        assert np.max(np.abs(np.asarray(h.t)[both] - np.asarray(first.t)[both])) <= 2 * 2.0**-11


def test_degree_through_loops_and_zero_terms():
    """jnp.polyval (a scan: Horner's rule from a zero), a fori_loop of products, and
    products with a literal zero."""
    def rest(f):
        return polynomial_degree(lambda x, y, z, w, p: f(x, y, z, p), 0.0, jnp.ones(5))[0]
    assert rest(lambda x, y, z, p: jnp.polyval(p, x)) == 4
    assert rest(lambda x, y, z, p: jnp.polyval(jnp.array([1.0, 2, 3, 4]), x * y)) == 6
    assert rest(lambda x, y, z, p: jax.lax.fori_loop(0, 3, lambda i, c: c * x + y, 1.0)) == 3
    assert rest(lambda x, y, z, p: 0.0 * x**7 + y) == 1
    assert rest(lambda x, y, z, p: jax.lax.fori_loop(0, 3, lambda i, c: jnp.sin(c) * x,
                                                       1.0)) is None
