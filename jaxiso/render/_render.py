"""`render`: shading, shadows, transparency, multiple isovalues and reflections, written
once against the scene protocol (`intersect`), for every scene type.

Camera rays are put in tile order (packets of tile x tile neighbouring pixels) once;
every secondary ray (shadow, next transparent layer, reflection) keeps its pixel's slot,
so secondary packets stay as coherent as their pixels. With several devices the
tile-ordered rays are split across them with `jax.shard_map`.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._camera import Camera
from .._core import Plan, Rays, concrete, facing, pytree_dataclass
from ._distributed import as_mesh, mesh_of, shard_rays, to_global, to_host
from ._image import Image
from ._plan import (
    check_scene,
    from_tiles,
    from_zorder,
    intersect_traced,
    prepare,
    to_tiles,
    to_zorder,
)

__all__ = ["Light", "Shading", "render", "DEFAULT_COLORS"]

# one colour per isovalue / CSG part (cycled)
DEFAULT_COLORS = ((0.85, 0.55, 0.25), (0.30, 0.55, 0.85), (0.45, 0.75, 0.40),
                  (0.80, 0.35, 0.45), (0.65, 0.50, 0.80), (0.85, 0.80, 0.35))


@pytree_dataclass
class Light:
    """A directional light (`vector` points towards the light) or a point light at
    `vector` (`point=True`)."""

    vector: jax.Array = (0.45, 0.35, 0.82)
    color: jax.Array = (1.0, 1.0, 1.0)
    point: bool = dataclasses.field(default=False, metadata=dict(static=True))

    def __post_init__(self):
        object.__setattr__(self, "vector", jnp.asarray(self.vector, jnp.float32))
        object.__setattr__(self, "color", jnp.asarray(self.color, jnp.float32))
        if self.vector.shape != (3,) or self.color.shape != (3,):
            raise ValueError(f"Light vector and color must be 3-vectors, got shapes "
                             f"{self.vector.shape} and {self.color.shape}")
        v, c = concrete(self.vector), concrete(self.color)
        if v is not None and not np.all(np.isfinite(v)):
            raise ValueError(f"Light vector must be finite, got {v}")
        if v is not None and not self.point and not np.any(v != 0):
            raise ValueError("a directional Light needs a nonzero direction vector (it "
                             "points towards the light), got (0, 0, 0)")
        if c is not None and not (np.all(np.isfinite(c)) and np.all(c >= 0)):
            raise ValueError(f"Light color must be finite and >= 0, got {c}")


@pytree_dataclass
class Shading:
    """Phong material and effects (arrays are traced; counts are static).

    Attributes:
      colors: [C, 3] colour per isovalue / CSG part (cycled).
      background: [3].
      ambient, diffuse, specular, shininess: Phong terms.
      opacity: alpha of each transparent layer (1 = opaque).
      layers: surfaces composited front to back (1 = opaque first hit).
      reflectivity: mirror weight per bounce.
      reflections: number of mirror bounces.
      shadows: cast shadow rays.
      shadow_eps_scale: shadow rays run at eps times this (coarser, Sec. 6.4.6).
    """

    colors: jax.Array = DEFAULT_COLORS
    background: jax.Array = (1.0, 1.0, 1.0)
    ambient: jax.Array = 0.18
    diffuse: jax.Array = 0.75
    specular: jax.Array = 0.25
    shininess: jax.Array = 32.0
    opacity: jax.Array = 1.0
    reflectivity: jax.Array = 0.35
    layers: int = dataclasses.field(default=1, metadata=dict(static=True))
    reflections: int = dataclasses.field(default=0, metadata=dict(static=True))
    shadows: bool = dataclasses.field(default=False, metadata=dict(static=True))
    shadow_eps_scale: float = dataclasses.field(default=4.0, metadata=dict(static=True))

    def __post_init__(self):
        for name in ("colors", "background", "ambient", "diffuse", "specular",
                     "shininess", "opacity", "reflectivity"):
            object.__setattr__(self, name, jnp.asarray(getattr(self, name), jnp.float32))
        c = self.colors
        if c.ndim != 2 or c.shape[-1] != 3 or c.shape[0] == 0:
            raise ValueError(f"colors must be [C, 3] with C >= 1, got shape {c.shape}")
        for name in ("colors", "background", "ambient", "diffuse", "specular",
                     "shininess", "opacity", "reflectivity"):
            v = concrete(getattr(self, name))
            if v is not None and not np.all(np.isfinite(v)):
                raise ValueError(f"Shading {name} must be finite, got {v}")
        op = concrete(self.opacity)
        if op is not None and not np.all((op >= 0) & (op <= 1)):
            raise ValueError(f"Shading opacity must be in [0, 1], got {op}")
        if not (isinstance(self.shadow_eps_scale, (int, float)) and
                np.isfinite(self.shadow_eps_scale) and self.shadow_eps_scale >= 1):
            raise ValueError(f"shadow_eps_scale must be a finite number >= 1, got "
                             f"{self.shadow_eps_scale!r}")
        if self.layers < 1 or self.reflections < 0:
            raise ValueError("layers must be >= 1 and reflections >= 0")
        if self.layers > 1 and self.reflections > 0:
            raise ValueError("reflections are traced for opaque shading only (layers=1); "
                             "transparency with reflections is not supported")


def render(scene, camera: Camera, *, shading: Shading | None = None,
           light: Light | None = None, devices=None, plan: Plan | None = None):
    """Ray trace `scene` through `camera` and shade the first hits.

    Args:
      scene: any scene implementing the protocol (`jaxiso.Scene`: ImplicitSurface, CSG,
        VolumeIsosurface, TetIsosurface); its options (method, eps, ...) are its fields.
      camera: a `Camera`.
      shading: a `Shading` (default: opaque Phong, no shadows).
      light: a `Light` (default: directional, over the viewer's right shoulder).
      devices: None (default device), a list of devices or a `jax.sharding.Mesh`
        with one axis: camera tiles are split across them. The mesh may span processes
        (after `jax.distributed.initialize`): every process then gets the whole image.
      plan: a `Plan` (default: `plan_for(scene, rays per device)`, the fastest measured
        tile edge or persistent lanes for the scene and backend).

    Returns:
      Float [H, W, 3] colours in [0, 1]: an `Image` (numpy; shows inline in Jupyter)
      when called eagerly, a jax array under jit/grad.
    """
    check_scene(scene)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a jaxiso.Camera, got {type(camera).__name__}")
    shading = Shading() if shading is None else shading
    light = Light() if light is None else light
    mesh = None if devices is None else as_mesh(devices)
    home = mesh_of(scene, devices)  # where inputs live: a mesh over processes, or None
    n_dev = 1 if mesh is None else mesh.devices.size
    scene, plan = prepare(scene, -(-camera.width * camera.height // n_dev), plan)
    if plan.tape:
        if mesh is not None:
            warnings.warn("a tape plan (long program) renders on the default device only",
                          stacklevel=2)
        img = _render_tape(scene, camera, shading, light, plan)
    else:
        img = _render(*to_global((scene, camera, shading, light), home), plan, mesh)
    if isinstance(img, jax.core.Tracer):
        return img
    return Image(to_host(img))


@functools.partial(jax.jit, static_argnums=(4, 5))
def _render(scene, camera, shading, light, plan, mesh):
    tile = plan.tile
    rays = camera.rays()
    h, w = camera.height, camera.width
    o = to_tiles(rays.origin, tile)
    d = to_tiles(rays.direction, tile)

    def shade_all(shared, o, d):
        return shade_rays(shared[0], Rays(o, d), shared[1], shared[2], plan)

    shared = (scene, shading, light)
    if mesh is None:
        colors = shade_all(shared, o, d)
    else:
        colors = shard_rays(shade_all, mesh, shared, (o, d), plan.packet)
    return from_tiles(colors, tile, h, w)


def _render_tape(scene, camera, shading, light, plan):
    """`_render` for a tape plan, eagerly (the tape path's driver is on the host): rays
    in Z-order within plan.tile tiles, so that every ray group the traversal forms is a
    square of pixels."""
    tile = plan.tile
    rays = camera.rays()
    o, d = to_zorder(rays.origin, tile), to_zorder(rays.direction, tile)
    colors = shade_rays(scene, Rays(o, d), shading, light, plan)
    return from_zorder(colors, tile, camera.height, camera.width)


def _trace(scene, plan, rays, t_min=0.0, t_max=jnp.inf):
    t_min = jnp.broadcast_to(jnp.asarray(t_min, jnp.float32), rays.shape)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), rays.shape)
    return intersect_traced(scene, rays, t_min, t_max, plan)


def shade_rays(scene, rays: Rays, shading: Shading, light: Light, plan: Plan) -> jax.Array:
    """Colours [N, 3] of rays [N] (in packet order)."""
    diagonal = jnp.linalg.norm(scene.hi - scene.lo)
    # a finite offset even for unbounded scenes (a tet mesh without clip box is not)
    scale = jnp.where(jnp.isfinite(diagonal), diagonal, 1.0)
    offset = jnp.maximum(4.0 * scene.offset_scale, 1e-4 * scale)
    trace = functools.partial(_trace, scene, plan)
    bg = shading.background

    def surface_color(rays, hits):
        p = rays.at(jnp.where(hits.hit, hits.t, 0.0))
        n = facing(hits.normal, rays.direction)
        if light.point:
            to_light = light.vector - p
            dist = jnp.linalg.norm(to_light, axis=-1)
            ldir = to_light / jnp.maximum(dist, 1e-20)[:, None]
        else:
            ldir = jnp.broadcast_to(light.vector / jnp.linalg.norm(light.vector), p.shape)
            dist = jnp.full(p.shape[:1], jnp.inf)
        ndotl = jnp.sum(n * ldir, axis=-1)
        lit = jnp.ones_like(ndotl)
        if shading.shadows:
            cast = hits.hit & (ndotl > 0)
            # start outside the shadow ray's own (coarser) first piece: an interval box
            # of that piece must not reach back to the surface (shadow acne)
            srays = Rays(p + n * (offset * shading.shadow_eps_scale), ldir)
            shits = _trace(scene.coarser(shading.shadow_eps_scale), plan, srays,
                           0.0, jnp.where(cast, dist, -1.0))
            lit = jnp.where(shits.hit, 0.0, 1.0)
        n_col = shading.colors.shape[0]
        base = shading.colors[jnp.mod(jnp.maximum(hits.surface, 0), n_col)]
        v = -rays.direction / jnp.linalg.norm(rays.direction, axis=-1, keepdims=True)
        r = 2.0 * ndotl[:, None] * n - ldir
        spec = jnp.maximum(jnp.sum(r * v, axis=-1), 0.0) ** shading.shininess
        diffuse = shading.diffuse * jnp.maximum(ndotl, 0.0) * lit
        col = (base * (shading.ambient + diffuse)[:, None]
               + (shading.specular * spec * lit * (ndotl > 0))[:, None] * light.color)
        return jnp.clip(col, 0.0, 1.0)

    hits = trace(rays)
    if shading.layers == 1:
        color = _with_reflections(trace, rays, hits, surface_color, shading, offset)
        return jnp.where(hits.hit[:, None], color, bg)
    # front-to-back transparency: the next layer re-traces from just behind this hit
    alpha = shading.opacity
    color = jnp.zeros(rays.origin.shape)
    through = jnp.ones(rays.origin.shape[:1])
    for layer in range(shading.layers):
        if layer > 0:
            hits = trace(rays, t_min=jnp.where(hits.hit, hits.t + offset, jnp.inf))
        c = surface_color(rays, hits)
        a = jnp.where(hits.hit, alpha, 0.0)
        color = color + (through * a)[:, None] * c
        through = through * (1.0 - a)
    return color + through[:, None] * bg


def _with_reflections(trace, rays, hits, surface_color, shading, offset):
    """Local colour mixed with up to `reflections` mirror bounces."""
    color = surface_color(rays, hits)
    if shading.reflections == 0:
        return color
    k = shading.reflectivity
    weight = jnp.where(hits.hit, 1.0 - k, 1.0)
    total = weight[:, None] * color
    carry = jnp.where(hits.hit, k, 0.0)
    cur_rays, cur_hits = rays, hits
    for bounce in range(shading.reflections):
        n = facing(cur_hits.normal, cur_rays.direction)
        d = cur_rays.direction
        refl = d - 2.0 * jnp.sum(d * n, axis=-1, keepdims=True) * n
        p = cur_rays.at(jnp.where(cur_hits.hit, cur_hits.t, 0.0)) + n * offset
        nxt = Rays(p, refl)
        nxt_hits = trace(nxt, t_max=jnp.where(cur_hits.hit, jnp.inf, -1.0))
        c = jnp.where(nxt_hits.hit[:, None], surface_color(nxt, nxt_hits),
                      shading.background)
        last = bounce == shading.reflections - 1
        w_here = jnp.where(nxt_hits.hit & (not last), 1.0 - k, 1.0)
        total = total + (carry * w_here)[:, None] * c
        carry = carry * jnp.where(nxt_hits.hit, k, 0.0)
        cur_rays, cur_hits = nxt, nxt_hits
    return total
