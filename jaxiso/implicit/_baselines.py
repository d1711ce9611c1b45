"""Comparison baselines for the seed's interval ray casting (Sec. 6.6.4, Table 6.2).

Three ray-segment root finders with the same calling convention as the interval methods
(`_methods`) (a ray segment ``p + D s``, s in [0, 1], one per packet lane):

* ``"mitchell"``: Mitchell's (1990) interval root *isolation* followed by point root
  refinement, the method the seed compares t-/K-bisection against (Table 6.2). Pieces
  whose inclusion excludes every isovalue are rejected as in t-bisection; a piece whose
  directional-derivative inclusion excludes 0 is monotone, holds at most one root per
  isovalue, and is settled by the signs of f at its ends and regula falsi (Illinois) on
  points. It is robust like bisection (pieces that never become monotone, e.g. at the
  singular lines of the Steiner surface or the teardrop's cusp, are accepted at the eps
  depth exactly as t-bisection does) but pays for a gradient inclusion per piece.
* ``"sampling"``: uniform point sampling of f along the segment and bisection of the
  first sign change. Not an inclusion method: it misses every feature thinner than the
  sample spacing and every root of even multiplicity (tangent touches, the Steiner
  surface's singular lines, the double-sided zero sets of ``f = g^2``), which is what it
  is here to show.
* ``"sphere"``: sphere tracing (Hart 1996) with a user-given Lipschitz bound of f. Sound
  only if the bound holds on the whole segment, and a global bound is loose for
  polynomials (Barth sextic: |grad f| up to ~800 in its box), so steps are tiny; it crawls
  (and runs out of steps) along grazing rays and towards tangent touches or double roots,
  where |f| shrinks like the distance squared, and an underestimated bound steps through
  thin features.

The method registry (`_methods.METHODS`) calls them with the scene's options. Every
method is jit-able: a per-ray ``lax.while_loop`` with a static iteration bound, vmapped over the
packet, in float32.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..arith import Affine, aa, extend
from . import _bisect
from ._field import box_arithmetic, contains_any, enclosure, extended, on_points, ray_boxes

__all__ = ["mitchell", "sampling", "sphere"]

DEFAULT_SAMPLES = 64
DEFAULT_SPHERE_STEPS = 256
DEFAULT_REFINE_STEPS = 2 * _bisect.MAX_DEPTH

# ------------------------------------------------------------------------- helpers


def _point_value(g, scene, p, D, s):
    """g(p + D s) for one ray (p, D: [3]; s scalar): a call of the point function at one
    point, inside the per-ray `vmap` (batches of points go through `on_points`)."""
    x = p + D * s
    return g(x[0], x[1], x[2], scene.w, scene.params)


def _sign_change(a, b):
    """a and b (values minus an isovalue) bracket a root: opposite signs or a zero;
    NaN/inf never count."""
    ok = jnp.isfinite(a) & jnp.isfinite(b)
    return ok & (((a <= 0) & (b >= 0)) | ((a >= 0) & (b <= 0)))


def _first_crossed(va, vb, iso):
    """Of the isovalues whose level a monotone (or linearly interpolated) function
    crosses between values va and vb, the one met first (closest to va): (index, any)."""
    fa, fb = va - iso, vb - iso
    change = _sign_change(fa, fb)
    idx = jnp.argmin(jnp.where(change, jnp.abs(fa), jnp.inf)).astype(jnp.int32)
    return idx, jnp.any(change)


def _refine(val, a, b, fa, fb, length, eps, max_iters: int, falsi: bool):
    """Shrink the bracket [a, b] of one sign change of ``val`` (values fa, fb at the
    ends) until it is at most eps long in world units
    (length = |D|). falsi: Illinois regula falsi (bisection where the secant point is
    unusable), else plain bisection. Returns (s, iterations), s the bracket midpoint."""
    # a root exactly at an end: collapse the bracket onto it (the first end first)
    at_a = fa == 0
    at_b = (fb == 0) & ~at_a
    a, b = jnp.where(at_b, b, a), jnp.where(at_a, a, b)

    def cond(st):
        a, b, fa, fb, side, n = st
        mid = 0.5 * (a + b)
        return ((n < max_iters) & ((b - a) * length > eps) & (mid > a) & (mid < b))

    def body(st):
        a, b, fa, fb, side, n = st
        mid = 0.5 * (a + b)
        if falsi:
            xf = (a * fb - b * fa) / (fb - fa)
            x = jnp.where(jnp.isfinite(xf) & (xf > a) & (xf < b), xf, mid)
        else:
            x = mid
        fx = val(x)
        zero = fx == 0
        keep_b = (fx > 0) == (fa > 0)  # same sign as at a: the root is in [x, b]
        # Illinois: an end kept twice in a row has its value halved
        fb_new = jnp.where(keep_b & (side == 1), 0.5 * fb, fb)
        fa_new = jnp.where(~keep_b & (side == -1), 0.5 * fa, fa)
        a2 = jnp.where(zero, x, jnp.where(keep_b, x, a))
        b2 = jnp.where(zero, x, jnp.where(keep_b, b, x))
        fa2 = jnp.where(keep_b, fx, fa_new)
        fb2 = jnp.where(keep_b, fb_new, fx)
        side2 = jnp.where(keep_b, 1, -1).astype(jnp.int32)
        return a2, b2, fa2, fb2, side2, n + 1

    init = (a, b, fa, fb, jnp.int32(0), jnp.int32(0))
    a, b, _, _, _, n = lax.while_loop(cond, body, init)
    return 0.5 * (a + b), n


# ------------------------------------------------------------------------- Mitchell


def _directional_derivative(g):
    """h(x, y, z, w, dx, dy, dz, params) = grad g(x, y, z) . (dx, dy, dz), by forward
    mode (one jvp), as plain JAX for `extend`."""
    def h(x, y, z, w, dx, dy, dz, params):
        def at(x, y, z):
            return g(x, y, z, w, params)
        return jax.jvp(at, (x, y, z), (dx, dy, dz))[1]
    return h


def _derivative_extension(g, scene, arithmetic, rounding):
    """The inclusion of the directional derivative, or None (with a warning) when some
    primitive of the derivative has no rule: Mitchell then degrades to bisection to eps."""
    H = extend(_directional_derivative(g), arithmetic, rounding,
               n_symbols=1 if arithmetic == "affine" else None)
    zero = jnp.zeros((), jnp.float32)
    probe = ray_boxes(jnp.zeros(3, jnp.float32), jnp.ones(3, jnp.float32), zero,
                      zero + 1.0, arithmetic)
    try:
        jax.eval_shape(lambda w, params: H(*probe, w, zero, zero, zero, params=params),
                       scene.w, scene.params)
    except NotImplementedError as e:
        warnings.warn(f"method='mitchell': the derivative of f cannot be extended ({e}); "
                      "falling back to interval bisection to eps (no isolation)",
                      stacklevel=4)
        return None
    return H


def mitchell(g, scene, p, D, inside, eps, arithmetic="interval", rounding="fast",
             max_steps=None, *, refine_steps=None) -> _bisect.Result:
    """Mitchell's interval root isolation with point refinement (seed Sec. 6.6.4).

    Stackless bisection over s (`_bisect.advance`, as in `_bisect.t_bisect`). A
    piece whose inclusion F excludes every isovalue is rejected. A possible piece is
    *isolated* when the inclusion of the directional derivative ``grad f . D`` on it
    excludes 0 (and is bounded): f is monotone there, so if f - iso changes sign between
    the piece's ends the first root is in it (earlier pieces were rejected) and regula
    falsi (Illinois) on points refines it to eps in world units; without a sign change the
    piece holds no root and the march moves on. Pieces that reach the eps depth (Eq. 6.19)
    without being isolated are accepted like t-bisection (singular points, cusps and
    tangent touches are still found, at the precision of t-bisection).

    Options:
      refine_steps: bound on regula falsi iterations (default 60).
    steps counts inclusion evaluations (F, plus the derivative where it is computed) and
    refinement iterations. Its pieces are boxes: a "polynomial" scene's run in interval
    arithmetic (`_field.box_arithmetic`).
    """
    arithmetic = box_arithmetic(arithmetic)
    F = extended(g, arithmetic, rounding)
    H = _derivative_extension(g, scene, arithmetic, rounding)
    refine_steps = DEFAULT_REFINE_STEPS if refine_steps is None else int(refine_steps)
    if max_steps is None:
        max_steps = 64 * _bisect.MAX_DEPTH
    length = jnp.linalg.norm(D, axis=-1)
    d_max = _bisect.depth_for(length, eps)
    field = _Inclusions(g, scene, F, H, arithmetic)

    def one(p, D, d_max, length, active):
        k, d, kind, evals = _isolate(field, p, D, d_max, active, max_steps)
        return _refine_piece(field, p, D, k, d, kind, evals, length, eps, refine_steps)

    return jax.vmap(one)(p, D, d_max, length, inside)


# how a ray's march ended (`mitchell`): no hit, a piece at the eps depth, an isolated bracket
_NONE, _DEPTH, _BRACKET = 0, 1, 2


class _Inclusions(NamedTuple):
    """What `mitchell` evaluates: the point function g, its inclusion F and that of its
    directional derivative H (None: none), in `arithmetic`, at the scene's w and params."""
    g: Callable
    scene: object
    F: Callable
    H: Callable | None
    arithmetic: str


def _isolate(field, p, D, d_max, active, max_steps):
    """The stackless march of one ray (p, D: [3]) to its first isolated bracket or
    eps-depth piece: (k, d, kind, evals), kind `_NONE` where it found neither."""
    def cond(st):
        k, d, done, kind, steps, evals = st
        return ~done & (steps < max_steps)

    def body(st):
        return _march_step(field, p, D, d_max, st)

    init = (jnp.int32(0), jnp.int32(0), ~active, jnp.int32(_NONE), jnp.int32(0),
            jnp.int32(0))
    k, d, done, kind, steps, evals = lax.while_loop(cond, body, init)
    return k, d, jnp.where(done & active, kind, _NONE), evals


def _march_step(field, p, D, d_max, st):
    """One piece (k, d) of the march: rejected, descended into, or stopped at (an
    isolated bracket, or a possible piece at the eps depth)."""
    g, scene, F, H, arithmetic = field
    k, d, done, kind, steps, evals = st
    iso = scene.isovalues
    s0, s1 = _bisect.piece(k, d)
    boxes = ray_boxes(p, D, s0, s1, arithmetic)
    r = enclosure(F, boxes, scene.w, scene.params, arithmetic)
    possible, finite = contains_any(r, iso)
    cand = possible & finite
    monotone = _monotone(H, boxes, scene, D)
    va = _point_value(g, scene, p, D, s0)
    vb = _point_value(g, scene, p, D, s1)
    _, crossing = _first_crossed(va, vb, iso)
    isolated = cand & monotone & jnp.isfinite(va) & jnp.isfinite(vb)
    bracket = isolated & crossing
    depth_hit = cand & ~isolated & (d >= d_max)
    stop = bracket | depth_hit
    descend = possible & ~isolated & ~depth_hit & (d < d_max)
    k, d, finished = _bisect.advance(k, d, stop, descend)
    kind = jnp.where(bracket, _BRACKET, jnp.where(depth_hit, _DEPTH, _NONE))
    n_eval = 1 + (possible & (H is not None)).astype(jnp.int32)
    return k, d, done | finished, kind.astype(jnp.int32), steps + 1, evals + n_eval


def _monotone(H, boxes, scene, D):
    """g is monotone on the piece: the derivative's inclusion H along D on `boxes` is
    bounded and excludes 0 (False without H)."""
    if H is None:
        return jnp.bool_(False)
    hr = H(*boxes, scene.w, D[0], D[1], D[2], params=scene.params)
    hr = aa.to_interval(hr) if isinstance(hr, Affine) else hr
    return jnp.isfinite(hr.hi - hr.lo) & hr.defined & ((hr.lo > 0) | (hr.hi < 0))


def _refine_piece(field, p, D, k, d, kind, evals, length, eps, refine_steps):
    """The ray's `_bisect.Result` from where its march ended: an isolated bracket refined
    on points (regula falsi), an eps-depth piece's midpoint, or no hit."""
    g, scene = field.g, field.scene
    iso = scene.isovalues
    s0, s1 = _bisect.piece(k, d)
    va = _point_value(g, scene, p, D, s0)
    vb = _point_value(g, scene, p, D, s1)
    which, _ = _first_crossed(va, vb, iso)
    level = iso[which]

    def val(s):
        return _point_value(g, scene, p, D, s) - level

    is_bracket = kind == _BRACKET
    s_ref, n_ref = _refine(val, s0, jnp.where(is_bracket, s1, s0), va - level,
                           vb - level, length, eps, refine_steps, falsi=True)
    hit = kind != _NONE
    s = jnp.where(is_bracket, s_ref, 0.5 * (s0 + s1))
    s = jnp.where(hit, s, jnp.inf)
    return _bisect.Result(s, hit, evals + n_ref)


# ------------------------------------------------------------------------- sampling


def sampling(g, scene, p, D, inside, eps, *, samples=DEFAULT_SAMPLES,
             refine_steps=None) -> _bisect.Result:
    """Uniform point sampling with bisection refinement (not an inclusion method).

    f is evaluated at `samples` evenly spaced points of the segment (both ends included:
    spacing 1 / (samples - 1) of the segment); the first pair of consecutive samples
    between which f - iso changes sign (any isovalue; NaN/inf samples never count) is
    bisected on points until it is at most eps long in world units. Misses whatever does
    not change sign between samples: features thinner than the spacing, tangent touches
    and even-multiplicity roots (e.g. the Steiner surface's singular lines).

    Options:
      samples: number of samples (>= 2, default 64).
      refine_steps: bound on bisection iterations (default 60).
    steps counts the samples a front-to-back marcher takes up to the bracket (all of them
    on a miss; all are evaluated at once, in one batch) plus bisection iterations.
    """
    n = int(samples)
    if n < 2:
        raise ValueError(f"method='sampling' needs samples >= 2, got {samples}")
    refine_steps = DEFAULT_REFINE_STEPS if refine_steps is None else int(refine_steps)
    iso = scene.isovalues
    length = jnp.linalg.norm(D, axis=-1)
    s = jnp.linspace(0.0, 1.0, n, dtype=jnp.float32)
    pts = p[:, None, :] + D[:, None, :] * s[None, :, None]  # [P, n, 3]
    v = on_points(g)(pts[..., 0], pts[..., 1], pts[..., 2], scene.w, scene.params)
    v = v.astype(jnp.float32)  # [P, n]
    diff = v[..., None] - iso  # [P, n, I]
    change = jnp.any(_sign_change(diff[:, :-1], diff[:, 1:]), axis=-1)  # [P, n - 1]
    first = jnp.argmax(change, axis=-1).astype(jnp.int32)
    found = inside & jnp.any(change, axis=-1)

    def one(p, D, v, i, length, found):
        va, vb = v[i], v[i + 1]
        which, _ = _first_crossed(va, vb, iso)
        level = iso[which]

        def val(s):
            return _point_value(g, scene, p, D, s) - level

        a, b = s[i], s[i + 1]
        s_hit, n_ref = _refine(val, a, jnp.where(found, b, a), va - level, vb - level,
                               length, eps, refine_steps, falsi=False)
        steps = jnp.where(found, i + 2 + n_ref, n)
        return _bisect.Result(jnp.where(found, s_hit, jnp.inf), found,
                              steps.astype(jnp.int32))

    return jax.vmap(one)(p, D, v, first, length, found)


# --------------------------------------------------------------------- sphere tracing


def sphere(g, scene, p, D, inside, eps, max_steps=None, *, lipschitz=None
           ) -> _bisect.Result:
    """Sphere tracing (Hart 1996) with a Lipschitz bound of f (not an inclusion method).

    Steps s += |f - iso| / (lipschitz |D|) towards the closest isovalue; a hit is
    reported when |f - iso| / lipschitz < eps (world units), a miss past the segment's
    end (s > 1), on a non-finite f, or after max_steps (default 256). Sound only if
    `lipschitz` bounds |grad f| on the segment; it crawls along grazing rays and towards
    tangent touches, and a loose bound makes every step short.

    Options:
      lipschitz: required; an upper bound of |grad f| over the domain box (scalar).
    """
    if lipschitz is None:
        raise ValueError(
            "method='sphere' needs a Lipschitz bound of f: pass lipschitz=L, an upper "
            "bound of |grad f| over the domain box (e.g. intersect(scene, rays, "
            "method='sphere', lipschitz=6.0))")
    if jnp.ndim(lipschitz) != 0:
        raise ValueError(f"lipschitz must be a scalar, got shape {jnp.shape(lipschitz)}")
    try:
        value = float(np.asarray(lipschitz))
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        value = None  # traced: checked by the caller
    if value is not None and not (np.isfinite(value) and value > 0):
        raise ValueError(f"lipschitz must be positive and finite, got {lipschitz}")
    lip = jnp.asarray(lipschitz, jnp.float32)
    if max_steps is None:
        max_steps = DEFAULT_SPHERE_STEPS
    iso = scene.isovalues
    length = jnp.linalg.norm(D, axis=-1)

    def one(p, D, length, active):
        def cond(st):
            s, done, hit, steps = st
            return ~done & (steps < max_steps)

        def body(st):
            s, done, hit, steps = st
            v = _point_value(g, scene, p, D, s)
            dist = jnp.min(jnp.abs(v - iso)) / lip  # world-space distance bound
            finite = jnp.isfinite(dist)
            close = finite & (dist < eps)
            s_next = s + dist / length
            finished = close | ~finite | ~(s_next <= 1.0)
            s = jnp.where(finished, s, s_next)
            return s, done | finished, hit | close, steps + 1

        init = (jnp.float32(0.0), ~active, jnp.bool_(False), jnp.int32(0))
        s, done, hit, steps = lax.while_loop(cond, body, init)
        hit = hit & active
        return _bisect.Result(jnp.where(hit, s, jnp.inf), hit, steps)

    return jax.vmap(one)(p, D, length, inside)
