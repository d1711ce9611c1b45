"""Exact ray–isosurface intersection inside one trilinear cell (seed Sec. 3.3.4).

A cell holds 8 corner values ``corners[..., 8]``; corner index ``4a + 2b + c`` belongs to
the offset (a, b, c) in {0, 1}^3 along (x, y, z). On local coordinates u in [0, 1]^3 the
field is the trilinear interpolant

    F(u) = sum_abc corners[4a + 2b + c] * w_a(u_x) * w_b(u_y) * w_c(u_z),
    w_0(t) = 1 - t,  w_1(t) = t.

Along a ray p(s) = p0 + s * dl (local entry point p0, local direction dl = world direction
/ spacing, s in world t units) each weight is linear in s, so g(s) = F(p(s)) is a cubic
(`ray_cubic`). `first_root` finds the first s in [0, s1] with g(s) = iso, either
iteratively after splitting the segment at the extrema of g into monotone pieces
(Marmitt et al. 2004, the "Neubauer" finder the seed uses; the first bracketing piece is
refined by bracketed Newton steps rather than Neubauer's repeated linear interpolation,
which converges too slowly for a fixed step count) or in closed form (Cardano /
trigonometric as in the Schwarze solver of Parker et al., but taking only the root the
formulas give accurately and deflating for the other two: textbook Cardano in float32
misses roots inside the cell whenever the cubic term is small, see `_largest_cubic_root`).

Conventions shared by the root finders:
  * a root counts where g - iso changes sign or is exactly 0 (an exact 0 at s = 0 is a hit
    at 0, so a cell that equals the isovalue everywhere is hit at its entry);
  * tangential double roots (g touches iso without crossing) may be missed;
  * no root: ``hit = False`` and ``s = inf``; non-finite coefficients, isovalue or s1, and
    s1 < 0, never hit. Finite inputs never give NaN.
Everything is pure jax.numpy, float32, broadcasts over leading batch axes and runs under
jit and vmap (fixed iteration counts, no data-dependent Python control flow).
"""

from __future__ import annotations

import math
import typing

import jax
import jax.numpy as jnp

NEUBAUER_ITERATIONS = 10   # safeguarded Newton steps (converged by 9 on random cells)
CUBIC_DEGENERACY = 1e-6    # |c3| below this share of the coefficient scale: a quadratic
END_TOLERANCE = 1e-5       # closed-form roots this far outside [0, 1] (in s / s1) still count
METHODS = ("neubauer", "analytic")


class CellHit(typing.NamedTuple):
    s: jax.Array    # [...] first root in [0, s1], inf where none
    hit: jax.Array  # [...] bool


class CellHitMulti(typing.NamedTuple):
    s: jax.Array      # [...] nearest root over all isovalues, inf where none
    hit: jax.Array    # [...] bool
    which: jax.Array  # [...] int32 index of the isovalue hit, -1 where none


# ----------------------------------------------------------------------------- the field

def _lerp(v0, v1, t):
    """(1 - t) v0 + t v1: exact at t = 0 and t = 1, so corner values come back unchanged."""
    return (1.0 - t) * v0 + t * v1


def _as_cube(corners):
    """[..., 8] -> [..., 2, 2, 2] indexed [a, b, c] (x, y, z offsets)."""
    return jnp.reshape(corners, corners.shape[:-1] + (2, 2, 2))


def trilinear(corners, u):
    """F(u): corners [..., 8], u [..., 3] local coordinates -> [...]."""
    cube = _as_cube(jnp.asarray(corners))
    u = jnp.asarray(u)
    ux, uy, uz = (u[..., i, None, None] for i in range(3))
    face = _lerp(cube[..., 0, :, :], cube[..., 1, :, :], ux)   # [..., 2(b), 2(c)]
    edge = _lerp(face[..., 0, :], face[..., 1, :], uy[..., 0])  # [..., 2(c)]
    return _lerp(edge[..., 0], edge[..., 1], uz[..., 0, 0])


def _bilinear(square, s, t):
    """Bilinear interpolation of square [..., 2, 2] at (s, t) [...]."""
    edge = _lerp(square[..., 0, :], square[..., 1, :], s[..., None])
    return _lerp(edge[..., 0], edge[..., 1], t)


def trilinear_gradient(corners, u):
    """dF/du w.r.t. local coordinates: corners [..., 8], u [..., 3] -> [..., 3].

    World gradients are this divided by the spacing. Each component is the bilinear
    interpolant (over the other two axes) of the corner differences along its axis.
    """
    cube = _as_cube(jnp.asarray(corners))
    u = jnp.asarray(u)
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    dx = cube[..., 1, :, :] - cube[..., 0, :, :]   # [..., b, c]
    dy = cube[..., :, 1, :] - cube[..., :, 0, :]   # [..., a, c]
    dz = cube[..., :, :, 1] - cube[..., :, :, 0]   # [..., a, b]
    return jnp.stack([_bilinear(dx, uy, uz), _bilinear(dy, ux, uz), _bilinear(dz, ux, uy)],
                     axis=-1)


def _lerp_polynomials(p, q, start, slope):
    """Coefficients of (1 - t(s)) P(s) + t(s) Q(s) with t(s) = start + slope * s.

    p, q [..., n] ascending coefficients (degree n - 1) -> [..., n + 1]:
    R_k = lerp(P_k, Q_k, start) + slope * (Q_{k-1} - P_{k-1}).
    """
    zero = jnp.zeros_like(p[..., :1])
    low = jnp.concatenate([_lerp(p, q, start[..., None]), zero], axis=-1)
    high = jnp.concatenate([zero, slope[..., None] * (q - p)], axis=-1)
    return low + high


def ray_cubic(corners, p0, dl):
    """Exact cubic of the field along a ray: g(s) = F(p0 + s dl) = sum_k coeffs[k] s^k.

    Args:
      corners: [..., 8] corner values.
      p0: [..., 3] local entry point.
      dl: [..., 3] local direction (world direction / spacing).
    Returns:
      coeffs [..., 4], ascending (c0, c1, c2, c3).

    Derivation: the weight of offset 1 along axis i is u_i(s) = p0_i + s dl_i, that of
    offset 0 is 1 - u_i(s), both linear in s. Interpolating along x, then y, then z with
    these linear weights (`_lerp_polynomials`) raises the degree by one each time:
      x: e_bc(s) = lerp(v_0bc, v_1bc, p0_x) + s dl_x (v_1bc - v_0bc)            (degree 1)
      y: f_c(s)  = (1 - u_y(s)) e_0c(s) + u_y(s) e_1c(s)                         (degree 2)
      z: g(s)    = (1 - u_z(s)) f_0(s)  + u_z(s) f_1(s)                          (degree 3)
    which expands to c3 = dl_x dl_y dl_z (sum of the 8 corners with sign (-1)^(3-a-b-c)),
    c0 = F(p0) (exact at a corner), and so on. Nested interpolation keeps the coefficients
    as well conditioned as the corner differences allow; no monomial basis of F is formed.

    Precision: the coefficients carry float32 rounding of the corner *magnitudes*. For data
    with a large offset (corners 1000 +- 1) that alone moves roots by up to ~5e-2 of the
    segment (median 7e-5), whichever root finder follows. Passing ``corners - iso`` here and
    isovalue 0 to `first_root` removes it (the subtraction is exact for nearby values;
    measured max error 1e-5 on the same cells).
    """
    cube = _as_cube(jnp.asarray(corners))[..., None]        # [..., 2, 2, 2, 1] degree 0
    p0, dl = jnp.asarray(p0), jnp.asarray(dl)
    px, py, pz = (p0[..., i, None, None] for i in range(3))
    qx, qy, qz = (dl[..., i, None, None] for i in range(3))
    face = _lerp_polynomials(cube[..., 0, :, :, :], cube[..., 1, :, :, :], px, qx)
    edge = _lerp_polynomials(face[..., 0, :, :], face[..., 1, :, :],
                             py[..., 0], qy[..., 0])
    return _lerp_polynomials(edge[..., 0, :], edge[..., 1, :], pz[..., 0, 0], qz[..., 0, 0])


# ----------------------------------------------------------------------- root finding

def horner(a, x):
    """a[..., 0] + a[..., 1] x + a[..., 2] x^2 + a[..., 3] x^3 (x broadcast against a)."""
    return a[..., 0] + x * (a[..., 1] + x * (a[..., 2] + x * a[..., 3]))


def _safe_divide(num, den):
    """num / den where den != 0, else NaN-free +inf (callers treat it as 'no root')."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.inf)


def _quadratic_roots(a, b_half, c):
    """Both roots of a x^2 + 2 b_half x + c = 0, computed without cancellation.

    Returns ([...], [...]); a root that does not exist (negative discriminant, vanishing
    leading terms) is +inf. With a = 0 the second root is the linear root -c / (2 b_half).
    """
    disc = b_half * b_half - a * c
    root_disc = jnp.sqrt(jnp.maximum(disc, 0.0))
    q = -(b_half + jnp.where(b_half < 0, -root_disc, root_disc))
    real = disc >= 0
    return (jnp.where(real, _safe_divide(q, a), jnp.inf),
            jnp.where(real, _safe_divide(c, q), jnp.inf))


def normalise(coeffs, s1):
    """Coefficients in sigma = s / s1 on [0, 1]: a_k = c_k s1^k (s1 = 0 keeps only c0)."""
    powers = jnp.stack([jnp.ones_like(s1), s1, s1 * s1, s1 * s1 * s1], axis=-1)
    return coeffs * powers


def _monotone_breaks(a):
    """Break points 0 <= x1 <= x2 <= 1 of [0, 1] at the extrema of the cubic a [..., 4].

    The extrema are the roots of a1 + 2 a2 x + 3 a3 x^2; those not strictly inside (0, 1)
    (or absent) become 1, leaving empty pieces at the end. Returns (x1, x2), each [...].
    """
    r1, r2 = _quadratic_roots(3.0 * a[..., 3], a[..., 2], a[..., 1])
    inside = lambda r: jnp.where((r > 0) & (r < 1), r, 1.0)
    r1, r2 = inside(r1), inside(r2)
    return jnp.minimum(r1, r2), jnp.maximum(r1, r2)


def _brackets(fa, fb):
    """A piece holds a root by the counting rule: an end is exactly 0 or the signs differ."""
    return jnp.sign(fa) * jnp.sign(fb) <= 0


def _derivative(a, x):
    """d/dx of the cubic a [..., 4] at x."""
    return a[..., 1] + x * (2.0 * a[..., 2] + x * (3.0 * a[..., 3]))


def _safeguarded_newton(coeffs, lo, hi, flo, fhi, iterations):
    """Newton's method kept inside a bracket of a monotone piece.

    Starts at the false-position point of the bracket. Each step evaluates h and h' at x,
    shrinks the bracket to the side holding the sign change, and takes the Newton step
    if it lands inside the (new) bracket, else bisects. On a monotone piece this converges
    quadratically once close; bisection takes over where h' is small (near the extrema
    that bound the piece). Measured on random cells (tests/test_cell.py) the error stops
    improving after 9 steps. Regula falsi variants were tried first and stall on the long
    curved pieces that start at a cell's entry (Illinois with a bisection safeguard: max
    error 1.5e-3 of the segment after 12 steps).

    coeffs [..., 4] is the shifted cubic; lo, hi, flo, fhi [...] the bracket and its end
    values (opposite signs, or both 0 for a bracket collapsed onto an exact root).
    Returns [...] the point after the last step (the step uses the last evaluation).
    """
    span = hi - lo
    x = lo - flo * _safe_divide(span, fhi - flo)
    x = jnp.clip(jnp.where(jnp.isfinite(x), x, 0.5 * (lo + hi)), lo, hi)

    def newton(x, fx, dfx, lo, hi):
        xn = x - _safe_divide(fx, dfx)
        usable = jnp.isfinite(xn) & (xn >= lo) & (xn <= hi)
        return xn, usable

    for _ in range(iterations):   # static count: unrolled, fuses into one loop nest
        fx = horner(coeffs, x)
        dfx = _derivative(coeffs, x)
        on_lo_side = jnp.sign(fx) == jnp.sign(flo)
        lo = jnp.where(on_lo_side, x, lo)
        flo = jnp.where(on_lo_side, fx, flo)
        hi = jnp.where(on_lo_side, hi, x)
        xn, usable = newton(x, fx, dfx, lo, hi)
        x_next = jnp.where(usable, xn, 0.5 * (lo + hi))
        x_next = jnp.where(fx == 0, x, x_next)   # exact root: stay
        x = x_next
    return x


def _neubauer_sigma(a, d0, iterations):
    """First root in [0, 1] of the cubic a (constant term replaced by d0) -> (sigma, hit)."""
    x1, x2 = _monotone_breaks(a)                          # iso-independent
    coeffs = jnp.concatenate([d0[..., None], jnp.broadcast_to(a[..., 1:], d0.shape + (3,))],
                             axis=-1)
    # pieces [0, x1], [x1, x2], [x2, 1]; g(0) - iso is d0 exactly
    f1, f2, f3 = horner(coeffs, x1), horner(coeffs, x2), horner(coeffs, 1.0)
    first, second, third = _brackets(d0, f1), _brackets(f1, f2), _brackets(f2, f3)
    hit = first | second | third
    # the first bracketing piece, by selects (no gathers: they do not fuse on CPU)
    pick = lambda v0, v1, v2: jnp.where(first, v0, jnp.where(second, v1, v2))
    lo, hi = pick(0.0, x1, x2), pick(x1, x2, 1.0)
    flo, fhi = pick(d0, f1, f2), pick(f1, f2, f3)
    # An exact zero at an end is the root itself: collapse the bracket onto it.
    lo = jnp.where((flo != 0) & (fhi == 0), hi, lo)
    hi = jnp.where(flo == 0, lo, hi)
    zero_end = (flo == 0) | (fhi == 0)
    flo = jnp.where(zero_end, 0.0, flo)
    fhi = jnp.where(zero_end, 0.0, fhi)
    sigma = _safeguarded_newton(coeffs, lo, hi, flo, fhi, iterations)
    return sigma, hit


def _largest_cubic_root(a, d0):
    """One real root of a3 x^3 + a2 x^2 + a1 x + d0 (a3 != 0 assumed; else garbage, masked
    by the caller): Cardano when the depressed cubic has one real root, the trigonometric
    form (largest root in magnitude) when it has three.

    Only this root is taken from the formulas: it is the one they give to full relative
    precision. The others lose everything to cancellation in float32 when |a3| is small
    (the depressed cubic is then dominated by (b/3)^3 with b = a2 / a3 huge): with |a3| at
    1e-4 of the other coefficients, textbook Cardano misses roots inside the cell.
    """
    a3 = jnp.where(a[..., 3] != 0, a[..., 3], 1.0)
    b, c, d = a[..., 2] / a3, a[..., 1] / a3, d0 / a3
    shift = b / 3.0
    p = c - b * shift                                     # depressed: y^3 + p y + q = 0
    q = d + shift * (2.0 * shift * shift - c)            # with x = y - b / 3
    disc = (0.5 * q) ** 2 + (p / 3.0) ** 3
    # One real root: the larger-magnitude cube root first (no cancellation), the other
    # from u v = -p / 3.
    sign_q = jnp.where(q < 0, -1.0, 1.0)
    u = -sign_q * jnp.cbrt(0.5 * jnp.abs(q) + jnp.sqrt(jnp.maximum(disc, 0.0)))
    one = u - jnp.where(u != 0, p / (3.0 * jnp.where(u != 0, u, 1.0)), 0.0)
    # Three real roots: y = m cos(theta - 2 pi k / 3), cos(3 theta) = 3 q / (p m); keep the
    # one largest in magnitude after the shift back to x.
    m = 2.0 * jnp.sqrt(jnp.maximum(-p / 3.0, 0.0))
    pm = p * m
    arg = jnp.clip(jnp.where(pm != 0, 3.0 * q / jnp.where(pm != 0, pm, 1.0), 0.0), -1.0, 1.0)
    theta = jnp.arccos(arg) / 3.0
    x0, x1, x2 = (m * jnp.cos(theta - k * (2.0 * math.pi / 3.0)) - shift for k in range(3))
    larger = lambda u, v: jnp.where(jnp.abs(u) >= jnp.abs(v), u, v)
    return jnp.where(disc > 0, one - shift, larger(larger(x0, x1), x2))


def _cubic_real_roots(a, d0):
    """Real roots of a3 x^3 + a2 x^2 + a1 x + d0 (a3 != 0) -> 3 x [...], +inf if complex.

    One real root r from `_largest_cubic_root`, the other two from the quotient
    (a3 x^3 + ...) / (x - r) = b2 x^2 + b1 x + b0 by the stable quadratic formula.
    Deflation is stable from the end where r dominates: from the constant term
    (b0 = -d0 / r, b1 = (b0 - a1) / r, b2 = (b1 - a2) / r) when |r| is at least the modulus
    of the other roots, i.e. |a3 r^3| >= |d0| (always so with three real roots), else from
    the top (b2 = a3, b1 = a2 + r b2, b0 = a1 + r b1), e.g. a small real root beside a
    large complex pair.
    """
    r = _largest_cubic_root(a, d0)
    a1, a2, a3 = a[..., 1], a[..., 2], a[..., 3]
    from_constant = (jnp.abs(a3 * r * r * r) >= jnp.abs(d0)) & (r != 0)
    r_safe = jnp.where(from_constant, r, 1.0)
    c0 = -d0 / r_safe
    c1 = (c0 - a1) / r_safe
    c2 = (c1 - a2) / r_safe
    t1 = a2 + r * a3
    t0 = a1 + r * t1
    b2 = jnp.where(from_constant, c2, a3)
    b1 = jnp.where(from_constant, c1, t1)
    b0 = jnp.where(from_constant, c0, t0)
    q1, q2 = _quadratic_roots(b2, 0.5 * b1, b0)
    return r, q1, q2


def _analytic_sigma(a, d0):
    """First root in [0, 1] of the cubic a (constant term d0) in closed form."""
    a = jnp.broadcast_to(a, d0.shape + (4,))
    scale = jnp.maximum(jnp.max(jnp.abs(a[..., 1:]), axis=-1), jnp.abs(d0))
    # Below the threshold the cubic term is dropped (a value error <= 1e-6 scale); it also
    # keeps b = a2 / a3 <= 1e6, so q^2 ~ b^6 stays finite in float32.
    is_cubic = jnp.abs(a[..., 3]) > CUBIC_DEGENERACY * scale
    c1, c2, c3 = _cubic_real_roots(a, d0)
    # The stable quadratic formula needs no thresholds: a2 = 0 leaves the linear root in
    # r2 (r1 = inf), a1 = a2 = 0 leaves none.
    r1, r2 = _quadratic_roots(a[..., 2], 0.5 * a[..., 1], d0)
    roots = (jnp.where(is_cubic, c1, r1), jnp.where(is_cubic, c2, r2),
             jnp.where(is_cubic, c3, jnp.inf))
    in_cell = lambda r: jnp.where((r >= -END_TOLERANCE) & (r <= 1.0 + END_TOLERANCE), r,
                                  jnp.inf)
    first = jnp.minimum(jnp.minimum(in_cell(roots[0]), in_cell(roots[1])), in_cell(roots[2]))
    first = jnp.where(d0 == 0, 0.0, first)               # exact zero at the entry
    hit = jnp.isfinite(first)
    return jnp.clip(jnp.where(hit, first, 0.0), 0.0, 1.0), hit


def first_root(coeffs, iso, s1, *, method: str = "neubauer",
               iterations: int = NEUBAUER_ITERATIONS) -> CellHit:
    """First s in [0, s1] with g(s) = iso for the cubic g of `ray_cubic`.

    Args:
      coeffs: [..., 4] ascending cubic coefficients in s.
      iso: [...] isovalue (broadcast against the batch).
      s1: [...] segment length (s in [0, s1]).
      method: "neubauer" (split at the extrema of g into monotone pieces, take the first
        piece that brackets iso, refine it with `iterations` bracketed Newton steps) or
        "analytic" (the real roots in closed form: one from Cardano / the trigonometric
        form, the others from the deflated quadratic; the smallest in [0, s1] with a
        relative tolerance END_TOLERANCE at the ends; `iterations` is ignored).
    Returns:
      CellHit(s, hit): s inf where no root. See the module docstring for the counting rule.

    Both methods work on the normalised cubic in sigma = s / s1 in [0, 1], so the fixed
    iteration count and the tolerances do not depend on the cell's size in s.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    coeffs = jnp.asarray(coeffs, jnp.float32)
    iso = jnp.asarray(iso, jnp.float32)
    s1 = jnp.asarray(s1, jnp.float32)
    shape = jnp.broadcast_shapes(coeffs.shape[:-1], iso.shape, s1.shape)
    s1 = jnp.broadcast_to(s1, shape)
    finite_inputs = (jnp.all(jnp.isfinite(coeffs), axis=-1) & jnp.isfinite(iso)
                     & jnp.isfinite(s1) & (s1 >= 0))
    a = normalise(jnp.where(jnp.isfinite(coeffs), coeffs, 0.0),
                   jnp.where(jnp.isfinite(s1), s1, 0.0))
    # The isovalue shift is the only cancellation left: g(0) - iso, done once and exactly
    # as the caller's comparison would do it.
    d0 = jnp.broadcast_to(a[..., 0] - jnp.where(jnp.isfinite(iso), iso, 0.0), shape)
    # Finite inputs can still overflow here (c3 s1^3): such rays do not hit either.
    valid = finite_inputs & jnp.all(jnp.isfinite(a), axis=-1) & jnp.isfinite(d0)
    a = jnp.where(valid[..., None], a, 0.0)
    d0 = jnp.where(valid, d0, 0.0)
    if method == "neubauer":
        sigma, hit = _neubauer_sigma(a, d0, iterations)
    else:
        sigma, hit = _analytic_sigma(a, d0)
    hit = hit & valid & jnp.isfinite(sigma)   # intermediate overflow: a miss, never NaN
    return CellHit(jnp.where(hit, sigma * s1, jnp.inf), hit)


def first_root_multi(coeffs, isovalues, s1, *, method: str = "neubauer",
                     iterations: int = NEUBAUER_ITERATIONS) -> CellHitMulti:
    """Nearest root over K isovalues.

    Args:
      coeffs: [..., 4]; isovalues: [K] or [..., K]; s1: [...].
    Returns:
      CellHitMulti(s, hit, which): which is the index of the isovalue hit (the lowest
      index on ties), -1 where none.

    The isovalues are scanned one at a time over the whole batch: a batch laid out as
    [..., K] ran 8x slower on CPU (XLA handles the short minor axis poorly).
    """
    coeffs = jnp.asarray(coeffs, jnp.float32)
    s1 = jnp.asarray(s1, jnp.float32)
    isovalues = jnp.asarray(isovalues, jnp.float32)
    shape = jnp.broadcast_shapes(coeffs.shape[:-1], isovalues.shape[:-1], s1.shape)
    per_iso = jnp.moveaxis(jnp.broadcast_to(isovalues, shape + isovalues.shape[-1:]), -1, 0)

    def nearer(best, iso_and_index):
        best_s, which = best
        iso, index = iso_and_index
        s, _ = first_root(coeffs, iso, s1, method=method, iterations=iterations)
        closer = s < best_s                   # strict: the lower index wins ties
        return (jnp.where(closer, s, best_s), jnp.where(closer, index, which)), None

    start = (jnp.full(shape, jnp.inf, jnp.float32), jnp.full(shape, -1, jnp.int32))
    indices = jnp.arange(per_iso.shape[0], dtype=jnp.int32)
    (s, which), _ = jax.lax.scan(nearer, start, (per_iso, indices))
    return CellHitMulti(s, which >= 0, which)
