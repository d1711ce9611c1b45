"""Finishing hits of implicit scenes: which level or part was hit, a differentiable t
(implicit function theorem, `attach_t`) and the normal, from the raw hit parameters."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._core import Hits, attach_t, on_points
from ._field import point_normal

__all__ = ["finish_hits", "nearest_drawn"]


def nearest_drawn(values, drawn):
    """Index [...] of the drawn part nearest its zero set, from the parts' values
    [..., K] and which parts are drawn [K] (bool)."""
    return jnp.argmin(jnp.where(drawn, jnp.abs(values), jnp.inf), axis=-1)


def finish_hits(g, scene, rays, t_raw, hit, steps, normals, which=None) -> Hits:
    """Hits [P] from raw hit parameters t_raw [P] of rays [P] on the point field g
    (evaluated on the packet through `on_points`): which isovalue of the scene (unless
    `which` [P] is given: then g vanishes on every part), t differentiable with respect
    to the scene and rays, and the normal (`normals`: None for jax.grad, else a
    central-difference width)."""
    o, d = rays.origin, rays.direction
    safe_t = jnp.where(hit, t_raw, 0.0)
    if which is None:
        p_raw = jax.lax.stop_gradient(o + safe_t[:, None] * d)
        val = on_points(g)(p_raw[:, 0], p_raw[:, 1], p_raw[:, 2], scene.w, scene.params)
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
