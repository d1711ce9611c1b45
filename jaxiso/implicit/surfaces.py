"""The seed's test surfaces (Knoll 2009, Tables B.1 and B.2, and the 4D morph of
Sec. 6.6.7.2) as plain jax.numpy functions.

Each `Surface` holds ``f(x, y, z, w)`` (w is the 4D/morphing parameter; ignored by most),
the domain box it is shown in, a default ray precision and camera. Where the printed formula
is ambiguous the choice is recorded in `notes`. The two CSG entries of Table B.2 also carry
their component functions (`parts`) and the seed's CSG condition (`csg`). Use `get(name)`
and `names()` (Table B.1, then B.2, then "morph").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax.numpy as jnp

__all__ = ["Surface", "get", "names", "scene", "camera", "TAU"]

TAU = (1.0 + math.sqrt(5.0)) / 2.0  # golden ratio


@dataclasses.dataclass(frozen=True)
class Surface:
    """A catalogue entry.

    Attributes:
      name: catalogue key.
      f: ``f(x, y, z, w) -> scalar``, plain jnp code (w defaults to `w`).
      lo, hi: corners of the domain box (world space).
      w: default value of the 4th coordinate.
      notes: how an ambiguous printed formula was read.
      eps: default ray precision; the "converged eps" column of the seed's Table 6.1
        (the highest eps giving a correctly converged image), 2^-11 where none is given.
      eye, target, up, fov: default pinhole camera (fov: vertical, degrees) framing the
        surface (checked for a square image in tests/test_surfaces.py).
      params: named constants ``((name, value), ...)``; informational only.
      isovalues: the level sets to draw.
      w_range: ``(w0, w1)`` the interval w is animated over (4D / time-dependent
        surfaces), else None.
      parts: CSG entries only: ``((name, g), ...)`` component functions g(x, y, z, w);
        `f` is then the component whose zero set is the main drawn surface.
      csg: CSG entries only: the seed's CSG condition (Table B.2) over `parts` names,
        "0 in g" meaning the zero set of g.
    """

    name: str
    f: Callable
    lo: tuple
    hi: tuple
    w: float = 0.0
    notes: str = ""
    eps: float = 2.0**-11
    eye: tuple = (4.0, 3.0, 2.5)
    target: tuple = (0.0, 0.0, 0.0)
    up: tuple = (0.0, 0.0, 1.0)
    fov: float = 40.0
    params: tuple = ()
    isovalues: tuple = (0.0,)
    w_range: tuple | None = None
    parts: tuple = ()
    csg: str = ""


def _sphere(x, y, z, w):
    return x * x + y * y + z * z - 1.0


def _steiner(x, y, z, w):
    return x * x * y * y + y * y * z * z + x * x * z * z + x * y * z


def _mitchell(x, y, z, w):
    r2 = y * y + z * z
    return (4.0 * (x**4 + r2 * r2) + 17.0 * x * x * r2
            - 20.0 * (x * x + y * y + z * z) + 17.0)


def _teardrop(x, y, z, w):
    return 0.5 * (x**5 + x**4) - y * y - z * z


def _bretzel4(x, y, z, w):
    x2 = x * x
    g = x2 * (1.21 - x2) ** 2 * (3.8 - x2) ** 3 - 10.0 * y * y
    return 0.1 * g * g + 60.0 * z * z - 2.0


def _klein(x, y, z, w):
    r2 = x * x + y * y + z * z
    a = r2 - 2.0 * y - 1.0
    return (r2 + 2.0 * y - 1.0) * (a * a - 8.0 * z * z) + 16.0 * x * z * a


def _tangle(x, y, z, w):
    return x**4 - 5.0 * x * x + y**4 - 5.0 * y * y + z**4 - 5.0 * z * z + 11.8


def _decocube(x, y, z, w):
    x2, y2, z2 = x * x, y * y, z * z
    c = 0.8 * 0.8
    return (((x2 + y2 - c) ** 2 + (z2 - 1.0) ** 2)
            * ((y2 + z2 - c) ** 2 + (x2 - 1.0) ** 2)
            * ((z2 + x2 - c) ** 2 + (y2 - 1.0) ** 2) - 0.02)


def _barth_sextic(x, y, z, w):
    t2 = TAU * TAU
    x2, y2, z2 = x * x, y * y, z * z
    s = x2 + y2 + z2 - 1.0
    return (4.0 * (t2 * x2 - y2) * (t2 * y2 - z2) * (t2 * z2 - x2)
            - (1.0 + 2.0 * TAU) * s * s)


def _barth_decic(x, y, z, w):
    t4 = TAU**4
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    r2 = x2 + y2 + z2
    a = r2 - w2
    b = r2 - (2.0 - TAU) * w2
    return (8.0 * (x2 - t4 * y2) * (y2 - t4 * z2) * (z2 - t4 * x2)
            * (x2 * x2 + y2 * y2 + z2 * z2 - 2.0 * x2 * y2 - 2.0 * x2 * z2 - 2.0 * y2 * z2)
            + (3.0 + 5.0 * TAU) * a * a * b * b * w2)


def _superquadric(x, y, z, w):
    return x**500 + 0.5 * jnp.abs(y) ** 35 + 0.5 * z**4 - 1.0


# ---- Table B.2 -------------------------------------------------------------------------

ICOS_R_INNER, ICOS_R_OUTER = 3.5, 4.5  # the shell that trims the icosahedral lattice


def _icos(x, y, z, w):
    t = TAU
    return 2.0 - (jnp.cos(x + t * y) + jnp.cos(x - t * y) + jnp.cos(y + t * z)
                  + jnp.cos(y - t * z) + jnp.cos(z - t * x) + jnp.cos(z + t * x))


def _icos_sphere_inner(x, y, z, w):
    return ICOS_R_INNER * ICOS_R_INNER - (x * x + y * y + z * z)


def _icos_sphere_outer(x, y, z, w):
    return ICOS_R_OUTER * ICOS_R_OUTER - (x * x + y * y + z * z)


def _sesc_se(x, y, z, w):
    y4, z4 = y**4, z**4
    return x**6 + 0.5 * (y4 + z4) ** 4 - 20.0


def _sesc_sc(x, y, z, w):
    return (x * y + jnp.cos(z) + 1.741 * jnp.sin(2.0 * x) * jnp.sin(z) * jnp.cos(y)
            + jnp.sin(2.0 * y) * jnp.sin(x) * jnp.cos(z)
            + jnp.sin(2.0 * z) * jnp.sin(y) * jnp.cos(x)
            - jnp.cos(2.0 * x) * jnp.cos(2.0 * y)
            + jnp.cos(2.0 * y) * jnp.cos(2.0 * z)
            + jnp.cos(2.0 * z) * jnp.cos(2.0 * x) + 0.05)


SIN_BLOB_R = (0.104, 0.402, -0.347)  # r0, r1, r2


def _sin_blob(x, y, z, w):
    r0, r1, r2 = SIN_BLOB_R
    return (1.0 + r1 * (y + w) + jnp.cos(r2 * z)
            + 4.0 * (jnp.sin((4.0 * r0 * r2) * x) * jnp.sin(r0 * z) * jnp.cos(r1 * y)
                     + jnp.sin((2.0 * r0 * r1) * y) * jnp.sin(r2 * x) * jnp.cos(r2 * z)
                     + jnp.sin((2.0 * r2) * z) * jnp.sin(r1 * y) * jnp.cos(r2 * x))
            - (jnp.cos((2.0 * r2) * x) * jnp.cos((2.0 * r0) * y)
               + jnp.cos((2.0 * r0 * r1) * y) * jnp.cos((2.0 * r2) * z)
               + jnp.cos((2.0 * r2) * z) * jnp.cos((2.0 * r2) * x)))


def _cloth(x, y, z, w):
    return (y - 0.5 * jnp.sin(x + 3.0 * w)
            - 0.1 * (1.0 + 0.1 * jnp.sin(x * z)) * jnp.cos(z + 3.0 * w))


WATER_R = (2.736, 15.0)  # r0 (phase of the third wave), r1 (distance of the sources)


def _water(x, y, z, w):
    r0, r1 = WATER_R
    a = jnp.sqrt((x + r1) ** 2 + z * z)  # three point sources in the y = 0 plane:
    b = jnp.sqrt((x - r1) ** 2 + z * z)  # (-r1, 0), (r1, 0) and (0, r1) in (x, z)
    c = jnp.sqrt((z - r1) ** 2 + x * x)
    return (jnp.sin(a - w) / (10.0 + a) + jnp.sin(b - w) / (10.0 + b)
            + jnp.sin(2.0 * c - w - r0) / (10.0 + c) - 0.5 * y)


# ---- 4D morph (Sec. 6.6.7.2, Fig. 6.12) --------------------------------------------------

MORPH_K, MORPH_R = 12.0, 1.2  # sigmoid steepness, sphere radius


def _morph(x, y, z, w):
    s = 1.0 / (1.0 + jnp.exp(-MORPH_K * (w - 0.5)))
    return (1.0 - s) * _decocube(x, y, z, w) + s * (x * x + y * y + z * z - MORPH_R * MORPH_R)


_ICOS_CSG = "(0 in ic) and (sphere_inner < 0) and (sphere_outer > 0)"
_SESC_CSG = "((sc > 0) and (0 in se)) or ((se < 0) and (0 in sc))"

# eps: Table 6.1, "converged eps" column (the morph uses the decocube row, Fig. 6.12).
_CATALOGUE = {s.name: s for s in (
    Surface("sphere", _sphere, (-1.5,) * 3, (1.5,) * 3, notes="r = 1", eps=2.0**-10,
            eye=(2.3, 1.72, 1.43)),
    Surface("steiner", _steiner, (-1.0,) * 3, (1.0,) * 3,
            notes="Steiner's Roman surface; singular lines along the axes", eps=2.0**-12,
            eye=(1.3, 0.98, 0.81)),
    Surface("mitchell", _mitchell, (-2.0,) * 3, (2.0,) * 3,
            notes="printed with an unbalanced parenthesis; read as Mitchell's surface "
                  "4(x^4 + (y^2+z^2)^2) + 17 x^2 (y^2+z^2) - 20 (x^2+y^2+z^2) + 17",
            eps=2.0**-10, eye=(4.48, 3.36, 2.8)),
    Surface("teardrop", _teardrop, (-1.25, -0.5, -0.5), (0.25, 0.5, 0.5),
            notes="cusp at the origin; for x > 0 the zero set opens into an unbounded "
                  "sheet, of which the box keeps a small piece",
            eps=2.0**-10, eye=(0.39, 1.54, 0.96), target=(-0.38, 0.0, 0.0)),
    Surface("bretzel4", _bretzel4, (-2.25, -1.5, -0.5), (2.25, 1.5, 0.5),
            notes="read as 0.1 (x^2 (1.21-x^2)^2 (3.8-x^2)^3 - 10 y^2)^2 + 60 z^2 - 2 "
                  "(four holes: two lobes of the x-polynomial above sqrt(20) per side); "
                  "the ends reach |x| = 2.08, so the box is |x| <= 2.25",
            eps=2.0**-10, eye=(2.42, 3.63, 4.85)),
    Surface("klein", _klein, (-3.0, -2.75, -3.75), (3.0, 3.25, 3.75),
            notes="figure-8 Klein bottle immersion as printed; the zero set spans "
                  "|x| <= 2.87, -2.41 <= y <= 3.03, |z| <= 3.65",
            eps=2.0**-12, eye=(8.76, 6.87, 5.47), target=(0.0, 0.3, 0.0)),
    Surface("tangle", _tangle, (-3.0,) * 3, (3.0,) * 3,
            notes="printed 'x^4 - r x^2'; read as the tangle cube x^4 - 5x^2 + ...",
            eps=2.0**-10, eye=(7.73, 5.79, 4.83)),
    Surface("decocube", _decocube, (-1.5,) * 3, (1.5,) * 3, eps=2.0**-11,
            eye=(3.1, 2.33, 1.94)),
    Surface("barth_sextic", _barth_sextic, (-1.5,) * 3, (1.5,) * 3,
            notes="the zero set is unbounded (cones to infinity); the box trims it",
            eps=2.0**-10, eye=(5.49, 4.12, 3.43)),
    Surface("barth_decic", _barth_decic, (-2.0,) * 3, (2.0,) * 3, w=1.0,
            notes="w is the homogenising coordinate; w = 1 gives the Barth decic; "
                  "unbounded, the box trims it",
            eps=2.0**-11, eye=(6.44, 4.83, 4.03)),
    Surface("superquadric", _superquadric, (-1.5,) * 3, (1.5,) * 3,
            notes="printed 'y ^35'; read as |y|^35 (an odd power of y is not a "
                  "superquadric); x^500 overflows float32 beyond |x| ~ 1.19",
            eps=2.0**-12, eye=(4.03, 3.02, 2.52)),
    # ---- Table B.2
    Surface("icos.csg", _icos, (-4.75,) * 3, (4.75,) * 3,
            notes="f = ic, the icosahedral cosine lattice (sum over the six 5-fold axes "
                  "(0, +-1, tau) and cyclic), clipped by the CSG condition to the shell "
                  f"{ICOS_R_INNER} < |p| < {ICOS_R_OUTER}. The printed 'sphere_inner < 0 and "
                  "sphere_outer > 0' is empty for spheres written |p|^2 - r^2; the parts "
                  "are written r^2 - |p|^2 (positive inside) so the printed condition holds "
                  "verbatim and selects the shell. The shell cuts the lattice cage (radii "
                  "~3-4.9 around a separate core blob of radius ~1.2) on both sides.",
            eps=2.0**-11, eye=(10.11, 7.58, 6.32),
            parts=(("ic", _icos), ("sphere_inner", _icos_sphere_inner),
                   ("sphere_outer", _icos_sphere_outer)),
            csg=_ICOS_CSG),
    Surface("sesc.csg", _sesc_se, (-1.8, -1.4, -1.4), (1.8, 1.4, 1.4),
            notes="f = se. se as printed, x^6 + 1/2 (y^4 + z^4)^4 - 20, is a sensible "
                  "closed convex superellipsoid (a rounded box: |x| <= 20^(1/6) = 1.648, "
                  "|y|, |z| <= 40^(1/16) = 1.259). sc as printed (1.741 multiplies only the "
                  "first product; the signs of the cos(2.)cos(2.) terms as printed). The "
                  "CSG object lies inside se <= 0, so inside the box. sc varies on a scale "
                  "~pi, comparable to se, so the condition cuts one large opening.",
            eps=2.0**-13, eye=(4.53, 3.4, 2.83),
            parts=(("se", _sesc_se), ("sc", _sesc_sc)), csg=_SESC_CSG),
    Surface("sin.blob", _sin_blob, (-16.0,) * 3, (16.0,) * 3,
            notes="as printed with r0 = 0.104, r1 = 0.402, r2 = -0.347, dropping one "
                  "unmatched closing parenthesis at the end; w enters only as r1 (y + w), "
                  "a shift of the linear y term (i.e. of the isovalue by r1 w). Quasi-"
                  "periodic, necessarily cut by the box; w in [-10, 10] keeps 15-75% of "
                  "the box inside. eps 2^-10 instead of the seed's 2^-12: at |p| ~ 16 float32 "
                  "resolution limits the depth error on grazing rays to ~1.7 eps at 2^-12.",
            eps=2.0**-10, eye=(49.47, 37.1, 30.92), w_range=(-10.0, 10.0)),
    Surface("cloth", _cloth, (-2.0 * math.pi, -0.75, -2.0 * math.pi),
            (2.0 * math.pi, 0.75, 2.0 * math.pi),
            notes="as printed; a height field y(x, z) with |y| <= 0.61, y is up; the box "
                  "shows two periods in x and z; w in [0, 2 pi] as printed",
            eps=2.0**-9, eye=(17.93, 15.69, 13.45), up=(0.0, 1.0, 0.0),
            w_range=(0.0, 2.0 * math.pi)),
    Surface("water", _water, (-16.0, -0.5, -16.0), (16.0, 0.5, 16.0),
            notes="printed garbled; read as three damped radial waves from the sources "
                  "(x, z) = (-r1, 0), (r1, 0), (0, r1): sin(a - w)/(10 + a) + "
                  "sin(b - w)/(10 + b) + sin(2c - w - r0)/(10 + c) - y/2 with "
                  "a = |(x + r1, z)|, b = |(x - r1, z)|, c = |(x, z - r1)|, r0 = 2.736, "
                  "r1 = 15. The second term (printed 'sin(b)') gets the '- w' and the "
                  "divisor of the others; the third keeps its printed factor 2 and phase "
                  "r0; the printed 'r2 = 830746' appears in no term and is unused. A height "
                  "field with |y| < 0.36, y is up; w in [0, 2 pi] is one period.",
            eps=2.0**-9, eye=(45.53, 39.85, 34.14), up=(0.0, 1.0, 0.0),
            w_range=(0.0, 2.0 * math.pi)),
    # ---- Sec. 6.6.7.2
    Surface("morph", _morph, (-1.5,) * 3, (1.5,) * 3, w=0.5,
            notes="decocube -> sphere morph (Sec. 6.6.7.2, Fig. 6.12): "
                  f"(1 - s) decocube + s (|p|^2 - {MORPH_R}^2), s = 1 / (1 + exp(-{MORPH_K} "
                  "(w - 1/2))); w = 0 / 1 give the decocube / sphere up to a 0.25% blend. "
                  "The sphere (r = 1.2) sits inside the decocube's corners (|p| <= 1.37) "
                  "and outside its tubes' inner side, so the tubes thicken and close into "
                  "the ball with no empty intermediate. Default w = 1/2 (s = 1/2 exactly).",
            eps=2.0**-11, eye=(3.1, 2.33, 1.94), w_range=(0.0, 1.0)),
)}


def names() -> list[str]:
    return list(_CATALOGUE)


def get(name: str) -> Surface:
    try:
        return _CATALOGUE[name]
    except KeyError:
        raise KeyError(f"unknown surface {name!r}; known: {', '.join(_CATALOGUE)}") from None


# Default inclusion arithmetic per surface: the cheapest that meets Eq. 6.20 (depth error
# <= eps against a float64 reference) at the entry's eps, measured in
# tests/test_accuracy.py. Interval arithmetic is first order here: its box is wider than
# the ray piece it encloses, so the accepted piece can lie several eps before the surface
# (max 2.6 eps on the sphere, 890 eps on a Barth sextic grazing ray); the single-symbol
# affine form is exact along the ray (<= 0.57 eps on every surface). Interval is kept
# where it meets the bound (water: 0.68 eps) and is cheaper.
_ARITHMETIC = {name: "affine" for name in _CATALOGUE}
_ARITHMETIC["water"] = "interval"
# polynomials of degree 3 and up take the default, "auto", which encloses them by their
# Chebyshev coefficients along each ray (exact along the ray as the affine form is,
# max |t - t64| measured by the same test)
for _name in ("steiner", "mitchell", "teardrop", "klein", "tangle", "decocube",
              "barth_sextic", "barth_decic", "morph"):
    _ARITHMETIC[_name] = "auto"


def _csg_expr(entry: Surface):
    """The CSG condition of a Table B.2 entry as an expression of solids (g < 0)."""
    from . import csg

    parts = dict(entry.parts)
    if entry.name == "icos.csg":
        # (0 in ic) and sphere_inner < 0 and sphere_outer > 0; the spheres only trim
        return csg.intersection(csg.Solid(parts["ic"], name="ic"),
                                csg.Solid(parts["sphere_inner"], draw=False),
                                csg.complement(csg.Solid(parts["sphere_outer"], draw=False)))
    if entry.name == "sesc.csg":
        # ((sc > 0) and (0 in se)) or ((se < 0) and (0 in sc)): the boundary of
        # {se < 0} and {sc > 0}
        return csg.intersection(csg.Solid(parts["se"], name="se"),
                                csg.complement(csg.Solid(parts["sc"], name="sc")))
    raise ValueError(f"{entry.name} has no CSG expression")


def scene(name: str, **overrides):
    """The ready-to-render scene of a catalogue entry: an `ImplicitSurface`, or a `CSG`
    for the Table B.2 CSG objects. `overrides` replace scene fields (w, eps,
    isovalues, arithmetic, method, params...)."""
    from . import csg
    from ._scene import ImplicitSurface

    entry = get(name)
    fields = dict(lo=entry.lo, hi=entry.hi, w=entry.w, eps=entry.eps,
                  arithmetic=_ARITHMETIC[name])
    if entry.parts:
        fields.update(overrides)
        return csg.CSG(_csg_expr(entry), **fields)
    fields["isovalues"] = entry.isovalues
    fields.update(overrides)
    return ImplicitSurface(entry.f, **fields)


def camera(name: str, width: int = 256, height: int | None = None):
    """The default `Camera` of a catalogue entry at the given image size."""
    from .._camera import Camera

    entry = get(name)
    return Camera.look_at(entry.eye, entry.target, entry.up, entry.fov, width, height)
