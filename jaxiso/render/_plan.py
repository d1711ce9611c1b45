"""One execution plan, and `intersect`: any batch of rays against any scene.

`plan_for` asks the scene for its fastest measured `Plan` (tile edge, persistent lanes)
on the current backend; `intersect` and `render` both use it, and both are jitted inside,
so the call a user writes first is the fast call. Packets are tiles of neighbouring
pixels: a batched ``while_loop`` runs until its slowest lane is done, so coherent rays
that finish together waste the least work (docs/performance.md, "The plan"; the packet
sizes measured are in benchmarks/NOTES.md, "Ray tracing kernels").
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._core import Hits, Plan, Rays, Scene, miss_like

__all__ = ["Plan", "plan_for", "prepare", "intersect", "to_tiles", "from_tiles",
           "morton_order", "to_zorder", "from_zorder", "check_scene"]


def plan_for(scene, n_rays: int, backend: str | None = None) -> Plan:
    """The plan `intersect` and `render` use for a batch of n_rays rays of `scene` on
    `backend` (default: jax's default backend); prepares the scene to know it."""
    return prepare(scene, n_rays, backend=backend)[1]


def prepare(scene, n_rays: int, plan: Plan | None = None, backend: str | None = None):
    """(scene, plan) ready to trace n_rays rays: the scene prepared (``scene.prepared()``
    where the scene kind has expensive preparation, e.g. `ImplicitSurface`; done once,
    the prepared scene returns itself) and `plan`, by default the scene's preferred plan
    on `backend`, checked. The one preparation step of `intersect` and `render`."""
    check_scene(scene)
    prepared = getattr(scene, "prepared", None)
    scene = scene if prepared is None else prepared()
    if plan is None:
        backend = jax.default_backend() if backend is None else backend
        plan = scene.preferred_plan(int(n_rays), backend)
        if not isinstance(plan, Plan):
            raise TypeError(f"{type(scene).__name__}.preferred_plan returned "
                            f"{type(plan).__name__}, not a Plan")
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a jaxiso.Plan, got {type(plan).__name__}")
    check_plan(plan, scene)
    return scene, plan


def check_scene(scene) -> None:
    """TypeError unless `scene` implements the protocol (`jaxiso.Scene`)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"expected a scene (ImplicitSurface, CSG, VolumeIsosurface, "
                        f"TetIsosurface or any jaxiso.Scene), got {type(scene).__name__}")


def intersect(scene, rays: Rays, *, t_min=0.0, t_max=jnp.inf, plan: Plan | None = None
              ) -> Hits:
    """First hits of `rays` (any batch shape S) with `scene`.

    Every option lives on the scene (method, arithmetic, eps, ...: `scene.replace`).
    `t_min`/`t_max` are scalars or arrays broadcastable to S. `plan` (default
    `plan_for(scene, n)`): rays run in consecutive packets of ``plan.tile**2`` (pass them
    in a coherent order, e.g. `to_tiles`), or all as one queue on ``plan.lanes``
    persistent lanes. Jitted inside (a new scene value never recompiles, a new shape or
    static field does), jit/vmap/grad-able; `t` is differentiable (implicit function
    theorem) with respect to the scene's traced fields and the rays.
    """
    check_scene(scene)
    if not isinstance(rays, Rays):
        raise TypeError(f"rays must be jaxiso.Rays, got {type(rays).__name__}")
    shape = rays.shape
    n = math.prod(shape)
    if n == 0:
        return miss_like(jnp.zeros(shape))
    scene, plan = prepare(scene, n, plan)
    t_min = jnp.broadcast_to(jnp.asarray(t_min, jnp.float32), shape)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), shape)
    if plan.tape:
        return intersect_traced(scene, rays, t_min, t_max, plan)
    return _intersect(scene, rays, t_min, t_max, plan)


def _tape_hits(scene, rays, t_min, t_max, tile, budget):
    """The tape path on rays of any shape; an image-shaped batch [H, W] runs in Z-order
    within tile x tile tiles, so that its ray groups are squares of pixels."""
    shape = rays.shape
    if len(shape) != 2:
        n = math.prod(shape)
        return scene.intersect_tape(rays.reshape((n,)), t_min.reshape(n),
                                    t_max.reshape(n), budget=budget).reshape(shape)
    hits = scene.intersect_tape(
        Rays(to_zorder(rays.origin, tile), to_zorder(rays.direction, tile)),
        to_zorder(t_min, tile), to_zorder(t_max, tile), budget=budget)
    return jax.tree_util.tree_map(lambda x: from_zorder(x, tile, *shape), hits)


@functools.partial(jax.jit, static_argnums=(1,))
def to_zorder(x, tile: int):
    """`to_tiles`, then Z-order within each tile (tile a power of 2): every run of 4^k
    consecutive entries is a square of pixels. Jitted: eagerly each of its steps
    compiled on its own (the tape path's first call reorders rays, hits and colours)."""
    x = to_tiles(x, tile)
    return x.reshape((-1, tile * tile) + x.shape[1:])[:, morton_order(tile)].reshape(x.shape)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def from_zorder(x, tile: int, height: int, width: int):
    """Inverse of `to_zorder`."""
    undo = np.argsort(morton_order(tile))
    x = x.reshape((-1, tile * tile) + x.shape[1:])[:, undo].reshape(x.shape)
    return from_tiles(x, tile, height, width)


def check_plan(plan: Plan, scene) -> None:
    """A tape plan needs a scene with a tape path (which runs eagerly, or under jit /
    vmap in a `jax.pure_callback`)."""
    if plan.tape and not hasattr(scene, "intersect_tape"):
        raise TypeError(f"Plan(tape=True) runs ImplicitSurface programs only, not "
                        f"{type(scene).__name__}")


@functools.partial(jax.jit, static_argnums=(4,))
def _intersect(scene, rays, t_min, t_max, plan):
    return intersect_traced(scene, rays, t_min, t_max, plan)


def intersect_traced(scene, rays: Rays, t_min, t_max, plan: Plan) -> Hits:
    """`intersect` without the checks and the jit (for callers already under jit; a
    tape plan is not jitted here: its driver is on the host, called directly on concrete
    values and through a callback on traced ones)."""
    shape = rays.shape
    n = math.prod(shape)
    if plan.tape:
        return _tape_hits(scene, rays, jnp.broadcast_to(t_min, shape),
                          jnp.broadcast_to(t_max, shape), plan.tile, plan.memory_budget)
    packet = n if plan.lanes else max(1, min(plan.packet, n))
    n_packets = -(-n // packet)
    pad = n_packets * packet - n
    t_min = jnp.broadcast_to(t_min, shape).reshape(n)
    t_max = jnp.broadcast_to(t_max, shape).reshape(n)
    flat = rays.reshape((n,))
    # padding rays are valid (copies of ray 0) with an empty [t_min, t_max]
    o = _pad(flat.origin, pad, edge=True).reshape(n_packets, packet, 3)
    d = _pad(flat.direction, pad, edge=True).reshape(n_packets, packet, 3)
    lo = _pad(t_min, pad, value=1.0).reshape(n_packets, packet)
    hi = _pad(t_max, pad, value=0.0).reshape(n_packets, packet)

    def one(args):
        o, d, lo, hi = args
        return scene.intersect_packet(Rays(o, d), lo, hi, lanes=plan.lanes)

    if n_packets == 1:
        hits = jax.tree_util.tree_map(lambda a: a[None], one((o[0], d[0], lo[0], hi[0])))
    else:
        hits = jax.lax.map(one, (o, d, lo, hi))
    hits = jax.tree_util.tree_map(lambda a: a.reshape((n_packets * packet,) + a.shape[2:]),
                                  hits)
    hits = jax.tree_util.tree_map(lambda a: a[:n], hits)
    return hits.reshape(shape)


def _pad(a, pad, *, edge=False, value=0.0):
    if pad == 0:
        return a
    if edge:
        filler = jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])
    else:
        filler = jnp.full((pad,) + a.shape[1:], value, a.dtype)
    return jnp.concatenate([a, filler])


def to_tiles(x, tile: int):
    """Reorder an image-shaped array [H, W, ...] into tile order [H*W', ...]: tiles of
    tile x tile pixels, row-major within a tile and across tiles. H and W are padded up
    to multiples of `tile` by repeating the last row/column; `from_tiles` undoes it."""
    h, w = x.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    x = jnp.pad(x, [(0, th * tile - h), (0, tw * tile - w)] + [(0, 0)] * (x.ndim - 2),
                mode="edge")
    x = x.reshape((th, tile, tw, tile) + x.shape[2:])
    x = jnp.moveaxis(x, 2, 1)
    return x.reshape((th * tw * tile * tile,) + x.shape[4:])


def morton_order(tile: int) -> np.ndarray:
    """Permutation of a row-major tile x tile block (tile a power of 2) into Z-order:
    every run of 4^k consecutive entries is a 2^k x 2^k square."""
    i, j = np.meshgrid(np.arange(tile), np.arange(tile), indexing="ij")
    key = np.zeros_like(i)
    for bit in range(int(tile).bit_length()):
        key |= ((j >> bit) & 1) << (2 * bit)
        key |= ((i >> bit) & 1) << (2 * bit + 1)
    return np.argsort(key.reshape(-1), kind="stable")


def from_tiles(x, tile: int, height: int, width: int):
    """Inverse of `to_tiles`: [n, ...] in tile order -> [H, W, ...]."""
    th, tw = -(-height // tile), -(-width // tile)
    x = x.reshape((th, tw, tile, tile) + x.shape[1:])
    x = jnp.moveaxis(x, 1, 2)
    x = x.reshape((th * tile, tw * tile) + x.shape[4:])
    return x[:height, :width]
