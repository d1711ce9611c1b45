"""The one scene protocol, and ray packets.

Every scene type is a pytree with a method

    scene.intersect_packet(rays, t_min, t_max, **options) -> Hits

that intersects one packet of rays (a flat batch [P]). Packets are tiles of neighbouring
pixels: a batched ``while_loop`` runs until its slowest lane is done, so coherent rays
that finish together waste the least work (DESIGN.md: 8x8 tiles ran 13x faster than one
vmap over a whole 512x512 image). `intersect` cuts any batch of rays into packets and
runs them with ``lax.map``; `render` orders camera rays tile by tile first. `slab` is the
ray-box clip the scenes share.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from ._camera import Rays

__all__ = ["Hits", "intersect", "to_tiles", "from_tiles", "default_tile", "slab"]

# Square tile edge used by render when none is given, per backend and arithmetic, from
# the packet table of benchmarks/bench_implicit.py on the 2-core CPU: interval t-bisection
# was fastest in 4x4 tiles (Barth sextic 0.74 Mrays/s vs 0.57 in 8x8; one vmap over the
# whole image 0.025), affine in 8x8 on most surfaces. Persistent lanes (`lanes=4096`)
# matched 4x4 tiles at 512^2 but compile 2-4x longer, so they are opt-in. Other backends
# are unmeasured here (no GPU was lent) and use 8x8.
_TILES = {("cpu", "interval"): 4, ("cpu", "affine"): 8}


def default_tile(arithmetic: str = "interval", backend: str | None = None) -> int:
    backend = jax.default_backend() if backend is None else backend
    return _TILES.get((backend, arithmetic), 8)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays (all arrays share the batch shape S).

    Attributes:
      t: [S] ray parameter of the hit, inf where none.
      hit: [S] bool.
      normal: [S, 3] unit normal (the field's gradient direction; (0, 0, 0) on a miss).
      surface: [S] int32, which isovalue or CSG part was hit (-1 on a miss).
      steps: [S] int32, loop iterations spent (a work counter for benchmarks).
    """

    t: jax.Array
    hit: jax.Array
    normal: jax.Array
    surface: jax.Array
    steps: jax.Array

    def reshape(self, shape) -> Hits:
        shape = tuple(shape)
        return Hits(self.t.reshape(shape), self.hit.reshape(shape),
                    self.normal.reshape(shape + (3,)), self.surface.reshape(shape),
                    self.steps.reshape(shape))


def miss_like(t) -> Hits:
    """Hits with no hit, shaped like t."""
    shape = jnp.shape(t)
    return Hits(jnp.full(shape, jnp.inf, jnp.float32), jnp.zeros(shape, bool),
                jnp.zeros(shape + (3,), jnp.float32), jnp.full(shape, -1, jnp.int32),
                jnp.zeros(shape, jnp.int32))


def intersect(scene, rays: Rays, *, t_min=0.0, t_max=jnp.inf, packet: int = 64,
              **options) -> Hits:
    """First hits of `rays` (any batch shape S) with `scene`.

    Rays are cut into consecutive packets of `packet` rays (the last one padded) that run
    one after another; pass rays in a coherent order (e.g. `to_tiles`) for speed.
    `t_min`/`t_max` are scalars or arrays broadcastable to S. Pure and jit-able;
    `t` is differentiable (implicit function theorem) for implicit and CSG scenes.

    Options for implicit scenes (defaults from the scene):
      method: "t-bisection" | "k-bisection" | "mitchell" | "sampling" | "sphere".
      arithmetic: "interval" | "affine".
      eps: world-space length of the final piece (Eq. 6.19).
      delta: range tolerance: also accept a piece whose enclosure is narrower.
      rounding: "fast" (seed) | "outward" (enclosures hold against exact arithmetic).
      normals: None (jax.grad) or a central-difference stencil width.
      max_steps: iteration bound per ray (per packet for K-bisection); rays that run
        out report no hit and steps == max_steps.
      lanes: run t-bisection on this many persistent lanes with refill (use a large
        `packet`, e.g. all rays).
      samples (sampling), lipschitz (sphere, required), refine_steps (mitchell).
    """
    shape = rays.shape
    n = math.prod(shape)
    if n == 0:
        return miss_like(jnp.zeros(shape))
    packet = max(1, min(int(packet), n))
    n_packets = -(-n // packet)
    pad = n_packets * packet - n
    t_min = jnp.broadcast_to(jnp.asarray(t_min, jnp.float32), shape).reshape(n)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), shape).reshape(n)
    flat = rays.reshape((n,))
    # padding rays are valid (copies of ray 0) with an empty [t_min, t_max]
    o = _pad(flat.origin, pad, edge=True).reshape(n_packets, packet, 3)
    d = _pad(flat.direction, pad, edge=True).reshape(n_packets, packet, 3)
    lo = _pad(t_min, pad, value=1.0).reshape(n_packets, packet)
    hi = _pad(t_max, pad, value=0.0).reshape(n_packets, packet)

    def one(args):
        o, d, lo, hi = args
        return scene.intersect_packet(Rays(o, d), lo, hi, **options)

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


def from_tiles(x, tile: int, height: int, width: int):
    """Inverse of `to_tiles`: [n, ...] in tile order -> [H, W, ...]."""
    th, tw = -(-height // tile), -(-width // tile)
    x = x.reshape((th, tw, tile, tile) + x.shape[1:])
    x = jnp.moveaxis(x, 1, 2)
    x = x.reshape((th * tile, tw * tile) + x.shape[4:])
    return x[:height, :width]


def slab(q0, dq, lo, hi):
    """Entry and exit t [P] of rays q0 + t dq through the boxes [lo, hi] (inclusive);
    axis-parallel rays are inside an axis's slab for all t or for none."""
    safe = jnp.where(dq == 0, 1.0, dq)
    ta = (lo - q0) / safe
    tb = (hi - q0) / safe
    inside = (q0 >= lo) & (q0 <= hi)
    near = jnp.where(dq == 0, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(ta, tb))
    far = jnp.where(dq == 0, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(ta, tb))
    return jnp.max(near, axis=-1), jnp.min(far, axis=-1)
