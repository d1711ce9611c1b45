"""Level of detail for octree volumes (seed ch. 4): where a pixel covers several voxels,
intersect one coarse cell of averaged voxels instead of many fine ones.

The seed picks the stop depth from the pixel-to-voxel width ratio dP/dV at K-slices of a
coherent packet traversal. Rays here are traversed one by one (in packets of lanes), so
the same ratio is evaluated at the node itself: a node of 2^b cells per axis is
intersected as one coarse cell when 2^b voxel widths fit in `quality` pixel footprints at
its centre's distance from the eye. The level is a function of position alone, so every
ray (and every shadow ray) sees the same cells: no seams between packets.

Smooth transitions (Sec. 4.4.3): the seed substitutes coarse values at fine vertices on a
transition slice. Here each corner's value is blended towards the next coarser level as
the level function approaches the switch, reaching the coarse value (within a margin that
bounds the level's change across a node) before any neighbouring node switches; the two
sides of a transition then share their face values and the surface stays continuous.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._core import pytree_dataclass
from . import _octree

__all__ = ["LevelOfDetail", "lod_for"]

_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int32)


@pytree_dataclass
class LevelOfDetail:
    """Pixel footprint model and quality knob.

    Attributes:
      eye: [3] world position the footprint grows from.
      base, slope: footprint (world width of a pixel) = base + slope * distance to eye;
        (0, 2 tan(fov/2) / H) for a pinhole camera, (view height / H, 0) orthographic.
      quality: dP/dV: a node is coarse when its cells are at most `quality` pixel
        footprints wide (larger = coarser and faster; the seed's 1, 2, 4).
      smooth: blend corners across transitions (static).
      band: width, in levels, of the blend before a switch (static).
    """

    eye: jax.Array
    base: jax.Array
    slope: jax.Array
    quality: jax.Array
    smooth: bool = dataclasses.field(default=True, metadata=dict(static=True))
    band: float = dataclasses.field(default=0.5, metadata=dict(static=True))

    def coarser(self, factor) -> LevelOfDetail:
        """The same model at `factor` times the dP/dV ratio (shadow rays, Sec. 4.5.2)."""
        return dataclasses.replace(self, quality=self.quality * factor)

    def level(self, vol, q):
        """Continuous level [..] at voxel-space points q [.., 3]: log2 of how many voxel
        widths fit in `quality` pixel footprints there."""
        world = vol.origin + q * vol.spacing
        dist = jnp.linalg.norm(world - self.eye, axis=-1)
        footprint = self.quality * (self.base + self.slope * dist)
        return jnp.log2(jnp.maximum(footprint / jnp.min(vol.spacing), 1e-30))

    def margin(self, vol):
        """Bound on how much `level` changes between a node's centre and its corners
        (half-diagonal / (distance * ln 2), with distance >= the switch distance)."""
        return jnp.sqrt(3.0) * self.quality * self.slope / (2.0 * jnp.log(2.0)) + 1e-3

    def stops(self, vol, centre, b):
        """[P] bool: the node of 2^b cells centred at voxel-space `centre` [P, 3] is
        intersected as one coarse cell."""
        return self.level(vol, centre) >= b

    def corners(self, vol, lo, bits):
        """Corner values [P, 8] of the cube [lo, lo + 2^bits] at level `bits`, blended
        towards level bits + 1 near the switch when `smooth`."""
        fine = _level_corners(vol, lo, bits)
        if not self.smooth:
            return fine
        size = jnp.left_shift(1, bits)
        pos = lo[:, None, :] + _CORNERS[None] * size[:, None, None]        # [P, 8, 3]
        up = bits + 1
        lam = self.level(vol, pos.astype(jnp.float32))
        start = up[:, None] - self.margin(vol) - self.band
        beta = jnp.clip((lam - start) / self.band, 0.0, 1.0)

        def coarse(_):
            lo_up = jnp.left_shift(jnp.right_shift(lo, up[:, None]), up[:, None])
            coarse_corners = _level_corners(vol, lo_up, up)                   # [P, 8]
            u = (pos - lo_up[:, None, :]).astype(jnp.float32) / (2.0 * size)[:, None, None]
            return _trilinear_many(coarse_corners, u)                        # [P, 8]

        # most cells of a packet lie away from every transition band: skip the second
        # lookup of 8 voxels then
        return fine + beta * (jax.lax.cond(jnp.any(beta > 0), coarse, lambda _: fine, None)
                              - fine)


def _level_corners(vol, lo, bits):
    """Values [P, 8] of the level-`bits` voxels at lo + corner * 2^bits (corners past the
    last coarse voxel holding data are clamped to it)."""
    size = jnp.left_shift(1, bits)
    last = jnp.array(vol.shape, jnp.int32) - 1
    last = jnp.left_shift(jnp.right_shift(last[None, :], bits[:, None]), bits[:, None])
    pos = lo[:, None, :] + _CORNERS[None] * size[:, None, None]
    pos = jnp.minimum(pos, last[:, None, :])
    level = vol.depth - jnp.broadcast_to(bits[:, None], pos.shape[:2])
    return _octree.lookup_coarse(vol, pos, level)


def _trilinear_many(corners, u):
    """Trilinear interpolation of corners [P, 8] at local points u [P, M, 3] -> [P, M]."""
    w = jnp.stack([(1 - u[..., 0]) if a == 0 else u[..., 0] for a in (0, 1)], -1)
    wy = jnp.stack([(1 - u[..., 1]) if b == 0 else u[..., 1] for b in (0, 1)], -1)
    wz = jnp.stack([(1 - u[..., 2]) if c == 0 else u[..., 2] for c in (0, 1)], -1)
    weights = (w[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :])
    return jnp.einsum("pmabc,pabc->pm", weights, corners.reshape(-1, 2, 2, 2))


def lod_for(camera, quality=1.0, *, smooth=True, band=0.5) -> LevelOfDetail:
    """The level-of-detail model of a `Camera` at dP/dV = `quality`."""
    per_pixel = 2.0 * camera.scale / camera.height
    if camera.orthographic:
        base, slope = per_pixel, jnp.float32(0.0)
    else:
        base, slope = jnp.float32(0.0), per_pixel
    return LevelOfDetail(jnp.asarray(camera.eye, jnp.float32), jnp.asarray(base, jnp.float32),
                         jnp.asarray(slope, jnp.float32), jnp.asarray(quality, jnp.float32),
                         smooth, band)
