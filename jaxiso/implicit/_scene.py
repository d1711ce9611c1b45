"""`ImplicitSurface`: the zero set (or several level sets) of a plain-JAX function.

Implements the scene protocol (`intersect_packet`) with the seed's interval methods
(t-bisection, K-bisection) and the comparison baselines (Mitchell, point sampling,
sphere tracing). Hits are differentiable with respect to params, isovalues, w and the
rays through the implicit function theorem (`attach_t`), never through the loops.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..render._scene import Hits
from . import _bisect
from ._field import (
    as_field,
    contains_any,
    enclosure,
    extended,
    point_normal,
    ray_boxes,
    ray_segments,
)

__all__ = ["ImplicitSurface", "attach_t"]

DEFAULT_EPS = 2.0**-11


@dataclasses.dataclass(frozen=True)
class ImplicitSurface:
    """The level sets ``f = iso`` of a user function inside the box [lo, hi].

    Attributes:
      f: ``f(x, y, z[, w][, params])`` in plain jax.numpy on scalars (static: a new
        function object means a new trace).
      lo, hi: [3] corners of the domain box.
      params: pytree of arrays passed to f (traced: changing values never retraces).
      isovalues: [I] level values drawn (each hit reports which one in `Hits.surface`).
      w: the 4th coordinate (time / morphing).
      eps: default ray precision in world units (Eq. 6.19).
      arithmetic: default inclusion arithmetic, "interval" or "affine".
      method: default intersection method (see `jaxiso.intersect`).
    """

    f: Callable
    lo: jax.Array
    hi: jax.Array
    params: object = ()
    isovalues: jax.Array = (0.0,)
    w: jax.Array = 0.0
    eps: jax.Array = DEFAULT_EPS
    arithmetic: str = "interval"
    method: str = "t-bisection"

    def __post_init__(self):
        if not callable(self.f):
            raise TypeError(f"f must be callable, got {type(self.f).__name__}")
        lo = jnp.asarray(self.lo, jnp.float32)
        hi = jnp.asarray(self.hi, jnp.float32)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"lo and hi must be 3-vectors, got {lo.shape} and {hi.shape}")
        _check_concrete(lo, hi, self.eps)
        iso = jnp.atleast_1d(jnp.asarray(self.isovalues, jnp.float32))
        if iso.ndim != 1 or iso.shape[0] == 0:
            raise ValueError("isovalues must be a non-empty 1-D sequence")
        if self.arithmetic not in ("interval", "affine"):
            raise ValueError(f"arithmetic must be 'interval' or 'affine', got "
                             f"{self.arithmetic!r}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "isovalues", iso)
        object.__setattr__(self, "w", jnp.asarray(self.w, jnp.float32))
        object.__setattr__(self, "eps", jnp.asarray(self.eps, jnp.float32))
        # fail early on a bad signature
        as_field(self.f, self.has_params)

    @property
    def has_params(self) -> bool:
        return len(jax.tree_util.tree_leaves(self.params)) > 0

    def prefers_lanes(self, method) -> bool:
        """render: persistent lanes pay off for t-bisection of large images (measured in
        jaxiso/render/_render.py)."""
        return method == "t-bisection"

    @property
    def field(self):
        """``g(x, y, z, w, params)``."""
        return as_field(self.f, self.has_params)

    def replace(self, **changes) -> ImplicitSurface:
        return dataclasses.replace(self, **changes)

    def __call__(self, x, y, z):
        """The field f - (nothing subtracted) at points."""
        return self.field(x, y, z, self.w, self.params)

    def intersect_packet(self, rays, t_min, t_max, *, method=None, arithmetic=None,
                         eps=None, delta=None, rounding="fast", normals=None,
                         max_steps: int | None = None, lanes: int | None = None,
                         **method_options) -> Hits:
        method = self.method if method is None else method
        arithmetic = self.arithmetic if arithmetic is None else arithmetic
        eps = self.eps if eps is None else jnp.asarray(eps, jnp.float32)
        scene = jax.lax.stop_gradient(self)
        t0, t1, inside, p, D = ray_segments(rays, scene.lo, scene.hi, t_min, t_max)
        g = scene.field
        if method in ("t-bisection", "k-bisection"):
            F = extended(g, arithmetic, rounding)
            res = _interval_method(method, F, scene, p, D, inside, eps, delta,
                                   arithmetic, max_steps, lanes)
        else:
            from . import _baselines
            res = _baselines.run(method, g, scene, p, D, inside, eps, arithmetic,
                                 rounding, max_steps, **method_options)
        t_raw = jnp.where(res.hit, t0 + res.s * (t1 - t0), jnp.inf)
        return finish_hits(g, self, rays, t_raw, res.hit, res.steps, normals)


def _interval_method(method, F, scene, p, D, inside, eps, delta, arithmetic, max_steps,
                     lanes=None):
    tol = jnp.float32(-1.0) if delta is None else jnp.float32(delta)

    def test(p, D, s0, s1):
        boxes = ray_boxes(p, D, s0, s1, arithmetic)
        r = enclosure(F, boxes, scene.w, scene.params, arithmetic)
        possible, finite = contains_any(r, scene.isovalues)
        return _bisect.BoxTest(possible, finite, (r.hi - r.lo) < tol)

    return run_bisection(method, test, p, D, inside, eps, max_steps, lanes)


def run_bisection(method, test, p, D, inside, eps, max_steps=None, lanes=None):
    """Drive t- or K-bisection over a packet with a box test ``test(p, D, s0, s1)``."""
    length = jnp.linalg.norm(D, axis=-1)
    d_max = _bisect.depth_for(length, eps)
    if max_steps is None:
        # enough for eps 2^-22 with IA on the Barth decic (1920 was not); a K-bisection
        # packet visits the union of its rays' candidate pieces
        max_steps = 256 * _bisect.MAX_DEPTH * (8 if method == "k-bisection" else 1)
    if method == "t-bisection" and lanes is not None:
        return _bisect.t_bisect_lanes(test, p, D, d_max, inside, lanes, max_steps)
    if method == "t-bisection":
        def one(p, D, d_max, active):
            return _bisect.t_bisect(functools.partial(test, p, D), d_max, active, max_steps)
        return jax.vmap(one)(p, D, d_max, inside)
    if method == "k-bisection":
        return _k_bisection(test, p, D, d_max, inside, length, max_steps)
    raise ValueError(f"unknown bisection method {method!r}")


def _k_bisection(test, p, D, d_max, inside, length, max_steps):
    """K-bisection for the rays that march coherently along the packet's dominant axis;
    the rest (opposite or too oblique K direction) fall back to t-bisection."""
    mean = jnp.sum(jnp.where(inside[:, None], D, 0.0), axis=0)
    axis = jnp.argmax(jnp.abs(mean))
    dk = jnp.take(D, axis, axis=1)
    sign = jnp.sign(jnp.take(mean, axis))
    coherent = inside & (jnp.sign(dk) == sign) & (jnp.abs(dk) >= 0.25 * length)
    k_enter = jnp.take(p, axis, axis=1)
    res_k = _bisect.k_bisect(lambda s0, s1: test(p, D, s0, s1), k_enter, k_enter + dk,
                             d_max, coherent, max_steps)

    def one(p, D, d_max, active):
        return _bisect.t_bisect(functools.partial(test, p, D), d_max, active, max_steps)
    res_t = jax.vmap(one)(p, D, d_max, inside & ~coherent)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(coherent, a, b), res_k, res_t)


def finish_hits(g, scene, rays, t_raw, hit, steps, normals, which=None) -> Hits:
    """Which isovalue (unless `which` is given: then g vanishes on every part), a
    differentiable t and the normal of each hit."""
    o, d = rays.origin, rays.direction
    safe_t = jnp.where(hit, t_raw, 0.0)
    if which is None:
        p_raw = jax.lax.stop_gradient(o + safe_t[:, None] * d)
        val = g(p_raw[:, 0], p_raw[:, 1], p_raw[:, 2], scene.w, scene.params)
        iso = scene.isovalues
        which = jnp.argmin(jnp.abs(val[:, None] - iso[None, :]), axis=-1).astype(jnp.int32)
        level = iso[which]
    else:
        level = jnp.zeros(t_raw.shape, jnp.float32)
    t = attach_t(g, safe_t, o, d, scene.w, scene.params, level, hit)
    pts = o + t[:, None] * d
    normal = point_normal(g, pts, scene.w, scene.params, d, stencil=normals)
    return Hits(t=jnp.where(hit, t, jnp.inf), hit=hit,
                normal=jnp.where(hit[:, None], normal, 0.0),
                surface=jnp.where(hit, which, -1), steps=steps.astype(jnp.int32))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def attach_t(g, t, o, d, w, params, iso, hit):
    """The hit parameter t [P] of rays o + t d on g(., w, params) = iso, returned as is;
    its derivative comes from the implicit function theorem:
    dt = -(dg - diso) / (grad g . d), with dg the change of g at the fixed hit point."""
    return t


@attach_t.defjvp
def _attach_t_jvp(g, primals, tangents):
    t, o, d, w, params, iso, hit = primals
    _, do, dd, dw, dparams, diso, _ = tangents

    def at(q, w, params):
        return g(q[0], q[1], q[2], w, params)

    q = o + t[:, None] * d
    dq = do + t[:, None] * dd
    batched = jax.vmap(at, in_axes=(0, None, None))
    _, dg = jax.jvp(batched, (q, w, params), (dq, dw, dparams))
    grad = jax.vmap(jax.grad(at), in_axes=(0, None, None))(q, w, params)
    denom = jnp.sum(grad * d, axis=-1)
    ok = hit & (jnp.abs(denom) > 1e-20) & jnp.isfinite(denom)
    dt = jnp.where(ok, -(dg - diso) / jnp.where(ok, denom, 1.0), 0.0)
    return t, dt


def _check_concrete(lo, hi, eps):
    try:
        lo_, hi_, e = (np.asarray(v) for v in (lo, hi, eps))
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return
    if not (np.all(np.isfinite(lo_)) and np.all(np.isfinite(hi_))):
        raise ValueError("the domain box must be finite")
    if np.any(np.asarray(lo_) >= np.asarray(hi_)):
        raise ValueError(f"the domain box needs lo < hi on every axis, got {lo_} and {hi_}")
    if not np.all(np.asarray(e) > 0):
        raise ValueError(f"eps must be positive, got {e}")


def _flatten(s: ImplicitSurface):
    return ((s.lo, s.hi, s.params, s.isovalues, s.w, s.eps),
            (s.f, s.arithmetic, s.method))


def _unflatten(aux, children):
    s = object.__new__(ImplicitSurface)
    for name, v in zip(("lo", "hi", "params", "isovalues", "w", "eps"), children):
        object.__setattr__(s, name, v)
    for name, v in zip(("f", "arithmetic", "method"), aux):
        object.__setattr__(s, name, v)
    return s


jax.tree_util.register_pytree_node(ImplicitSurface, _flatten, _unflatten)
