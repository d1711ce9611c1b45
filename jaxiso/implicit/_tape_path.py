"""`ImplicitSurface` on the tape path (`Plan.tape`): the host driver
(`_tape_rays.intersect_rays`) called directly on concrete values, through a
`jax.pure_callback` under jit / vmap, and differentiable through a custom JVP that
finishes the hits on the straight point function only when derivatives are taken."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._core import DEFAULT_MEMORY_BUDGET, Hits, on_host
from ._hits import finish_hits
from ._tape_rays import intersect_rays

__all__ = ["intersect_tape"]


def intersect_tape(scene, tape, rays, t_min, t_max, stats=None, prune=True,
                   budget=DEFAULT_MEMORY_BUDGET) -> Hits:
    """First hits [N] of rays [N] of `scene` on its program's `tape` (see
    `ImplicitSurface.intersect_tape`)."""
    primal = jax.lax.stop_gradient((scene, rays, t_min, t_max))
    leaves = jax.tree_util.tree_leaves((scene, rays, t_min, t_max))
    run = functools.partial(intersect_rays, stats=stats, prune=prune, budget=budget)
    if all(on_host(x) for x in leaves):
        hits = run(primal[0], tape, *primal[1:])
    else:
        hits = _callback(run, tape, primal)
    if not any(isinstance(x, jax.core.Tracer) for x in leaves):
        return hits
    t, normal = _differentiable_hits(scene.normals, (scene, rays), hits)
    return dataclasses.replace(hits, t=t, normal=normal)


def _callback(run, tape, primal) -> Hits:
    """`run` on values that exist only at run time (under jit / vmap): the host driver
    runs in a `jax.pure_callback` on the concrete values (vmap: once per batch
    element)."""
    flat, tree = jax.tree_util.tree_flatten(primal)
    n = primal[1].shape[0]
    out = Hits(t=jax.ShapeDtypeStruct((n,), jnp.float32),
               hit=jax.ShapeDtypeStruct((n,), jnp.bool_),
               normal=jax.ShapeDtypeStruct((n, 3), jnp.float32),
               surface=jax.ShapeDtypeStruct((n,), jnp.int32),
               steps=jax.ShapeDtypeStruct((n,), jnp.int32))

    def host(*values):
        scene, rays, t_min, t_max = jax.tree_util.tree_unflatten(
            tree, [jnp.asarray(v) for v in values])
        return jax.tree_util.tree_map(np.asarray, run(scene, tape, rays, t_min, t_max))

    return jax.pure_callback(host, out, *flat, vmap_method="sequential")


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _differentiable_hits(normals, scene_rays, hits: Hits):
    """(t, normal) of `hits` found on the tape path, with the derivatives of
    `finish_hits` (the implicit function theorem on the straight point function) with
    respect to the scene and rays: a custom JVP, so that a jitted call that is not
    differentiated never compiles the point function of a long program."""
    return hits.t, hits.normal


@_differentiable_hits.defjvp
def _differentiable_hits_jvp(normals, primals, tangents):
    scene_rays, hits = primals

    def finished(scene_rays):
        scene, rays = scene_rays
        h = finish_hits(scene.field, scene, rays, hits.t, hits.hit, hits.steps, normals)
        return h.t, h.normal

    _, (dt, dnormal) = jax.jvp(finished, (scene_rays,), (tangents[0],))
    return (hits.t, hits.normal), (dt, dnormal)
