"""Evaluating a user's implicit on pieces of rays, in points, intervals or affine forms.

The user writes ``f(x, y, z)``, ``f(x, y, z, w)``, ``f(x, y, z, params)`` or
``f(x, y, z, w, params)`` in plain jax.numpy; `as_field` turns any of these into
``g(x, y, z, w, params)``. A piece of a ray, ``p + D s`` for s in [s0, s1], becomes
boxes in the chosen arithmetic: intervals per axis, or affine forms sharing one noise
symbol (the seed's float3 RAA with n = 1), which keeps x, y and z exactly correlated.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import on_points, slab, unit_or_facing, unwrapped
from ..arith import Affine, Interval, aa, extend, ia
from ._memo import BoundedCache


def as_field(f, has_params: bool):
    """``g(x, y, z, w, params)`` calling f with the arguments it declares.

    g is a point function like f (batches of points go through `on_points`, so f may be
    any scalar JAX function). It returns a float array of the coordinates' broadcast
    shape: a constant f (``1.0``, ``jnp.float32(0)``) is broadcast, an integer value
    becomes float32; a bool (an inequality, which has no surface) raises TypeError and a
    value with more entries than points (e.g. shape (1,) for one point) ValueError when
    g is called."""
    try:
        sig = inspect.signature(f)
        kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        # parameters with defaults (e.g. closures' i=i) are not coordinates
        n = sum(p.kind in kinds and p.default is inspect.Parameter.empty
                for p in sig.parameters.values())
        var = any(p.kind == inspect.Parameter.VAR_POSITIONAL for p in sig.parameters.values())
    except (TypeError, ValueError):
        n, var = 4, False
    if var:
        n = 5 if has_params else 4
    if n == 3:
        if has_params:
            raise TypeError("f takes (x, y, z) but params were given; declare "
                            "f(x, y, z, params) or f(x, y, z, w, params)")
        call = lambda x, y, z, w, params: f(x, y, z)  # noqa: E731
    elif n == 4:
        call = ((lambda x, y, z, w, params: f(x, y, z, unwrapped(params)))  # noqa: E731
                if has_params else (lambda x, y, z, w, params: f(x, y, z, w)))
    elif n == 5:
        if not has_params:
            raise TypeError("f takes (x, y, z, w, params) but no params were given")
        call = lambda x, y, z, w, params: f(x, y, z, w, unwrapped(params))  # noqa: E731
    else:
        raise TypeError(f"f must take (x, y, z[, w][, params]); it takes {n} positional "
                        "arguments")

    # one jit of f per (f, has_params): every point evaluation of a render (the lanes'
    # verification, normals, gradients, auto's values) binds f's jaxpr, traced once,
    # instead of running f's Python again under each transformation
    traced = _POINT_FUNCTIONS.get((f, has_params), lambda: jax.jit(call))

    def g(x, y, z, w, params):
        if any(isinstance(v, (Interval, Affine)) for v in (x, y, z, w)):
            return _real_value(call(x, y, z, w, params), x, y, z, w)
        return _real_value(traced(x, y, z, w, params), x, y, z, w)

    return g


_POINT_FUNCTIONS = BoundedCache("jitted point functions", 32)


def _real_value(value, *coords):
    """f's value as a float array broadcast with the coordinates (lifted values pass)."""
    if isinstance(value, (Interval, Affine)):
        return value
    value = jnp.asarray(value)
    if value.dtype == jnp.bool_ or not (jnp.issubdtype(value.dtype, jnp.floating)
                                        or jnp.issubdtype(value.dtype, jnp.integer)):
        raise TypeError(f"f must return a real number per point, got {value.dtype}; an "
                        "inequality such as x*x + y*y < 1 has no surface: return the "
                        "difference x*x + y*y - 1 instead")
    if not jnp.issubdtype(value.dtype, jnp.floating):
        value = value.astype(jnp.float32)
    shape = jnp.broadcast_shapes(*[jnp.shape(c) for c in coords])
    if jnp.broadcast_shapes(value.shape, shape) != shape:
        raise ValueError(f"f must return one number per point, got shape {value.shape} for "
                         f"points of shape {shape}; take the single output (e.g. out[0] or "
                         "jnp.squeeze(out))")
    return jnp.broadcast_to(value, shape)


def ray_boxes(p, D, s0, s1, arithmetic: str):
    """Boxes enclosing the piece ``p + D s``, s in [s0, s1]: a list of 3 Intervals or
    3 single-symbol Affine forms (p, D: [..., 3]; s0, s1: [...]).

    Boxes are padded by `BOX_OVERLAP` ulps of their coordinates: neighbouring pieces then
    overlap, so a root on a shared endpoint is not lost to a rounding difference between
    the lower- and upper-bound paths (XLA contracts a*b+c into FMAs differently there)."""
    if arithmetic == "interval":
        a = p + D * s0[..., None]
        b = p + D * s1[..., None]
        lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
        pad = BOX_OVERLAP * jnp.maximum(jnp.abs(lo), jnp.abs(hi))
        lo, hi = lo - pad, hi + pad
        return [Interval(lo[..., i], hi[..., i]) for i in range(3)]
    sm = 0.5 * (s0 + s1)
    sr = 0.5 * (s1 - s0)
    c = p + D * sm[..., None]
    dev = D * sr[..., None]
    pad = BOX_OVERLAP * (jnp.abs(c) + jnp.abs(dev))
    return [Affine(c[..., i], dev[..., i:i + 1], pad[..., i]) for i in range(3)]


BOX_OVERLAP = 4.0 * 2.0**-24  # 4 ulps (relative)


def enclosure(F, boxes, w, params, arithmetic: str) -> Interval:
    """The inclusion F(boxes) as an Interval."""
    out = F(*boxes, w, params=params)
    return aa.to_interval(out) if isinstance(out, Affine) else out


def contains_any(r: Interval, isovalues):
    """possible [...] (an isovalue lies in r) and finite [...] (r is bounded)."""
    iso = jnp.asarray(isovalues)
    possible = jnp.any((r.lo[..., None] <= iso) & (iso <= r.hi[..., None]), axis=-1)
    return possible, jnp.isfinite(r.hi - r.lo)


def box_arithmetic(arithmetic: str) -> str:
    """The arithmetic of boxes for a scene's arithmetic: "polynomial" encloses ray pieces
    of t-/K-bisection only (`_polynomial`); Mitchell's method and the tape path map it
    here at their entry and enclose its boxes in interval arithmetic (sign grids have
    their own arithmetic)."""
    return "interval" if arithmetic == "polynomial" else arithmetic


def extended(g, arithmetic: str, rounding: str):
    """The inclusion extension of g (one noise symbol in affine mode)."""
    if arithmetic not in ("interval", "affine"):
        raise ValueError(f"arithmetic must be 'interval' or 'affine', got {arithmetic!r}")
    return extend(g, arithmetic, rounding, n_symbols=1 if arithmetic == "affine" else None)


def clip_to_box(rays_o, rays_d, lo, hi, t_min, t_max):
    """(t_enter, t_exit, inside) per ray ([P] each) of the box [lo, hi] within
    [t_min, t_max]."""
    near, far = slab(rays_o, rays_d, lo, hi)
    t0 = jnp.maximum(near, t_min)
    t1 = jnp.minimum(far, t_max)
    return t0, t1, (t0 <= t1) & jnp.isfinite(t1 - t0)


def ray_segments(rays, lo, hi, t_min, t_max):
    """The part of each ray inside the box, as ``p + D s`` for s in [0, 1].

    Returns (t0, t1, inside, p, D): entry/exit parameters (0 where the ray misses),
    inside [P] bool, p [P, 3] the entry point, D [P, 3] the segment vector. Gradients are
    stopped: hits get theirs from the implicit function theorem."""
    o = jax.lax.stop_gradient(rays.origin)
    d = jax.lax.stop_gradient(rays.direction)
    t0, t1, inside = clip_to_box(o, d, lo, hi, t_min, t_max)
    t0 = jnp.where(inside, t0, 0.0)
    t1 = jnp.where(inside, t1, 0.0)
    return t0, t1, inside, o + t0[:, None] * d, d * (t1 - t0)[:, None]


VERIFY = ("sign+distance", "sign", "none")


def touches(value_grad, m, value, grad, level, length):
    """The touching test of verify "sign+distance" ([...] bool) at points m [..., 3] where
    g = value [...] with gradient grad [..., 3], for the isovalue `level` [...]:
    m lies within `length` of the level set at first order (``|g - level| <= length
    |grad|``), and the level set is singular there. Singular: at the first Newton foot
    point ``m - (g - level) grad / |grad|^2`` the gradient is at most 3/4 of m's, and none
    of the next `_REGULAR_STEPS` Newton steps lands on a regular surface (|g - level| cut
    by 8 or more, the gradient kept above 3/4). Newton converges linearly to a double
    zero (Steiner's whiskers, g ~ a r^2: each step halves r and the gradient, quarters g)
    and quadratically to a simple one, so a ray grazing a regular surface is no hit and
    silhouettes are not widened by a piece. The later steps are needed for ReLU networks,
    whose gradient can halve at a step by crossing a region boundary (hammer: 0.46-0.56,
    then g cut 20-1000 fold with the gradient kept); float32 noise near Steiner's pinch
    points does not look like that (g cut 0.7-1.3 fold). value_grad: points [..., 3] ->
    (g, grad g)."""
    gap = value - level
    slope2 = jnp.sum(grad * grad, axis=-1)
    near = gap * gap <= slope2 * length * length

    def newton(q, gap_q, grad_q, slope2_q):
        q = q - (gap_q / _nonzero(slope2_q))[..., None] * grad_q
        g_q, grad_q = value_grad(q)
        return q, g_q - level, grad_q, jnp.sum(grad_q * grad_q, axis=-1)

    # the steps as a loop, not unrolled: each step evaluates g and its gradient, and g
    # may be a long program (one copy of its code in the compiled render, not four)
    def step(i, carry):
        q, gap_q, grad_q, slope2_q, shrinks, regular = carry
        q, gap_n, grad_q, slope2_n = newton(q, gap_q, grad_q, slope2_q)
        first = i == 0
        shrinks = jnp.where(first, slope2_n <= _SINGULAR**2 * slope2_q, shrinks)
        regular |= ~first & (8.0 * jnp.abs(gap_n) <= jnp.abs(gap_q)) & (
            slope2_n > _SINGULAR**2 * slope2_q)
        return q, gap_n, grad_q, slope2_n, shrinks, regular

    no = jnp.zeros_like(near)
    *_, shrinks, regular = jax.lax.fori_loop(0, 1 + _REGULAR_STEPS, step,
                                             (m, gap, grad, slope2, no, no))
    return (gap == 0) | (near & shrinks & ~regular)


_SINGULAR = 0.75  # the gradient's largest ratio at a Newton step towards a touch
# Newton steps after the first that may land on a regular zero: ReLU networks can cross
# two region boundaries first (hammer 128^2, pixel 8020 of bench_neural's view: g 3.0,
# 1.8, 1.1, then 5e-11 with the gradient kept; two steps took it for a touch)
_REGULAR_STEPS = 3


def _nonzero(x):
    return jnp.where(x > 0, x, 1.0)


def changes_sign(f):
    """[..., m - 1] bool: the values f - iso [..., m, n_iso] at m points along a piece
    change sign between neighbours, a root between them by the intermediate value
    theorem (NaN compares False: no root)."""
    return jnp.any(f[..., :-1, :] * f[..., 1:, :] <= 0, axis=-1)


def root_check(g, w, params, isovalues, policy: str):
    """``verify(p, D, s0, s1) -> bool [...]``: is a root of ``g = iso`` established on
    the piece ``p + D s``, s in [s0, s1] (p, D: [..., 3]; s0, s1: [...])? None for
    policy "none" (the enclosure alone decides, the seed's rule).

    "sign": g - iso changes sign between the piece's ends (point evaluation; a root by
    the intermediate value theorem; the first and last piece of a segment look half a
    piece beyond it, so a root on the box's face is kept), or, where they do not, between
    two of CLOSER_PARTS + 1 points spread over the piece (over the two parts about the
    point nearest a level, with `parts`): a feature thinner than the piece whose enclosure
    holds a level (birdcage_occ's bars: 6e-4 against pieces of 1e-3) is kept, and its
    root is proven like any other. "sign+distance" also accepts
    a piece whose midpoint m touches the level set (`touches`): within the piece's length
    L of it at first order, ``|g(m) - iso| <= L |grad g(m)|``, where it is singular.
    Surfaces that touch a level without crossing it (Steiner's whiskers, where g ~ a r^2
    and |g| / |grad g| = r / 2) are found, while neither a loose enclosure far from the
    surface nor a ray grazing a regular surface is taken for a hit.

    ``verify(p, D, s0, s1, parts=n)`` (n a power of two) cuts the piece into n equal
    parts and returns (ok, part): the first part whose ends' signs differ (the part
    holding the closer points' sign change where none does), or -1 where the whole
    piece passes the touching test only (`_bisect.first_verified`)."""
    if policy == "none":
        return None
    iso = jnp.asarray(isovalues)
    field = _PieceField(on_points(g), on_points(jax.value_and_grad(g, argnums=(0, 1, 2))),
                        w, params, iso)
    return functools.partial(_verify, field, policy)


class _PieceField(NamedTuple):
    """g - iso at points of ray pieces, for `root_check`'s tests: value and value_grad
    are g and (g, grad g) through `on_points`, at w and params."""
    value: Callable
    value_grad: Callable
    w: object
    params: object
    iso: jax.Array

    def sign_changes(self, p, D, s):
        """g - iso [..., m, n_iso] at the points p + D s (s [..., m]), and where it
        changes sign between neighbours [..., m - 1] (`changes_sign`)."""
        q = p[..., None, :] + D[..., None, :] * s[..., None]
        f = self.value(q[..., 0], q[..., 1], q[..., 2], self.w, self.params)[..., None] \
            - self.iso
        return f, changes_sign(f)

    def at_points(self, q):
        """(g, grad g [..., 3]) at points q [..., 3]."""
        value, grad = self.value_grad(q[..., 0], q[..., 1], q[..., 2], self.w, self.params)
        return value, jnp.stack(grad, axis=-1)


def _verify(field, policy, p, D, s0, s1, parts=None):
    """`root_check`'s verify: bool [...]; with `parts` (a power of two), the piece cut
    into that many equal parts: (ok, part) [...], part the first with a sign change, -1
    where only the whole piece touches (the parts are not tested for touching)."""
    n = 1 if parts is None else parts
    s = _part_ends(s0, s1, n)
    f, change = field.sign_changes(p, D, s)
    ok = jnp.any(change, axis=-1)
    part = jnp.argmax(change, axis=-1)
    # no sign change at the parts' ends: look closer around the point nearest a level
    # (a feature thinner than a part, e.g. birdcage_occ's bars, falls between them)
    lowest = jnp.argmin(jnp.min(jnp.abs(f), axis=-1), axis=-1)
    first = jnp.clip(lowest - 1, 0, max(n - 2, 0))
    last = jnp.minimum(first + 2, n)
    at = functools.partial(jnp.take_along_axis, s, axis=-1)
    dipped, sub, touched = _only_where(~ok, functools.partial(_closer, field, policy),
                                       p, D, s0, s1, at(first[..., None])[..., 0],
                                       at(last[..., None])[..., 0])
    part = jnp.where(ok, part, first + (sub * (last - first)) // CLOSER_PARTS)
    ok = ok | dipped
    if parts is None:
        return ok | touched
    return ok | touched, jnp.where(ok, part, -1)


def _part_ends(s0, s1, n):
    """The ends [..., n + 1] of n equal parts of [s0, s1]. A piece at an end of the
    segment looks half a part past it: a root on the box's face (a step of floor exactly
    there, with the entry point rounded inside) shows whichever side rounding puts it."""
    half = 0.5 * (s1 - s0) / n
    frac = jnp.arange(n + 1, dtype=jnp.float32) / n
    s = s0[..., None] + (s1 - s0)[..., None] * frac  # exact for dyadic pieces
    s = s.at[..., 0].set(jnp.where(s0 <= 0, s0 - half, s0))
    return s.at[..., n].set(jnp.where(s1 >= 1, s1 + half, s1))


def _closer(field, policy, p, D, s0, s1, a, b):
    """A piece without a sign change at its parts' ends, looked at closer: `_dip` on
    [a, b], and the touching test (policy "sign+distance") on the piece."""
    dipped, sub = _dip(field, p, D, a, b)
    touched = (_touching(field, p, D, s0, s1) if policy == "sign+distance"
               else jnp.zeros_like(dipped))
    return dipped, sub, touched


def _dip(field, p, D, a, b):
    """(ok, sub): the first of CLOSER_PARTS equal parts of [a, b] whose ends' signs
    differ."""
    frac = jnp.arange(CLOSER_PARTS + 1, dtype=jnp.float32) / CLOSER_PARTS
    _, change = field.sign_changes(p, D, a[..., None] + (b - a)[..., None] * frac)
    return jnp.any(change, axis=-1), jnp.argmax(change, axis=-1)


def _touching(field, p, D, s0, s1):
    """`touches` at the piece's midpoint, for the isovalue nearest g there."""
    m = p + D * (0.5 * (s0 + s1))[..., None]
    fm, grad = field.at_points(m)
    level = field.iso[jnp.argmin(jnp.abs(fm[..., None] - field.iso), axis=-1)]
    length = jnp.linalg.norm(D, axis=-1) * (s1 - s0)
    return touches(field.at_points, m, fm, grad, level, length)


# A piece with no sign change at its parts' ends is sampled this much finer over the two
# parts around its point nearest a level (`root_check`)
CLOSER_PARTS = 8


def _only_where(need, test, *args):
    """test(*args) (an array or a tuple of arrays [...]; args [..., *]) where `need` [...]
    holds, zeros elsewhere. The closer look of verification (9 point evaluations and the
    touching test's gradients) is costly per piece: on a batch [W] (the lanes'
    verification chunks) the pieces that need it are gathered W / 8 at a time
    (birdcage_occ 128^2: a few per chunk of 512 fail the sign test; the whole chunk's
    gradients cost 30% of the default call); elsewhere (per ray under vmap) only when
    some piece needs it."""
    shapes = jax.eval_shape(test, *args)
    none = jax.tree_util.tree_map(lambda r: jnp.zeros(r.shape, r.dtype), shapes)
    if need.ndim != 1 or need.shape[0] < 16:
        return jax.lax.cond(jnp.any(need), test, lambda *_: none, *args)
    n = need.shape[0]
    width = n // 8

    def some(carry):
        out, todo = carry
        at = jnp.nonzero(todo, size=width, fill_value=n)[0]  # n: none
        i = jnp.minimum(at, n - 1)
        res = test(*(a[i] for a in args))
        out = jax.tree_util.tree_map(lambda o, r: o.at[at].set(r, mode="drop"), out, res)
        return out, todo.at[at].set(False, mode="drop")

    return jax.lax.while_loop(lambda c: jnp.any(c[1]), some, (none, need))[0]


def point_normal(g, p, w, params, direction, stencil=None):
    """Unit normal from the gradient of the point function g at points p [..., 3]
    (jax.grad by default, central differences of width `stencil` otherwise, Sec. 6.4.7),
    both through `on_points`. Where the gradient vanishes or is not finite the normal
    faces the ray: -direction / |direction|."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if stencil is None:
        grad = jnp.stack(on_points(jax.grad(g, argnums=(0, 1, 2)))(x, y, z, w, params),
                         axis=-1)
    else:
        h = jnp.float32(stencil)
        G = on_points(g)
        grad = jnp.stack([(G(x + h * e[0], y + h * e[1], z + h * e[2], w, params)
                           - G(x - h * e[0], y - h * e[1], z - h * e[2], w, params)) / (2 * h)
                          for e in np.eye(3, dtype=np.float32)], axis=-1)
    return unit_or_facing(grad, direction)


__all__ = ["as_field", "on_points", "root_check", "VERIFY", "ray_boxes", "enclosure",
           "box_arithmetic", "BOX_OVERLAP",
           "contains_any", "extended", "clip_to_box", "ray_segments", "touches",
           "point_normal", "ia"]
