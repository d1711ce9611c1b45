"""`VolumeIsosurface`: isosurfaces of the trilinear interpolant of a voxel volume.

Implements the scene protocol (`intersect_packet`) over an `OctreeVolume` (seed ch. 3-4)
or the dense `MacrocellGrid` baseline. The hit is the exact first root of the trilinear
patch along the ray (`_cell`); `t` is differentiable with respect to the isovalues, the
rays and the float voxel values through the implicit function theorem (`attach_t`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._core import (
    Hits,
    Plan,
    SceneFields,
    attach_t,
    check_choice,
    check_count,
    check_finite,
    concrete,
    cpu_lanes,
    isovalues_array,
    pytree_dataclass,
    slab,
    static_field,
    unit_or_facing,
)
from . import _cell, _octree
from ._hierarchy import GridCells, MacrocellGrid, OctreeCells
from ._traverse import traverse, voxel_ray

__all__ = ["VolumeIsosurface"]

METHODS = _cell.METHODS
TRAVERSALS = ("restart", "neighbor")
NORMALS = ("trilinear", "central")


@pytree_dataclass
class VolumeIsosurface(SceneFields):
    """The level sets ``F = iso`` of the trilinear interpolant F of a volume's voxels.

    Attributes:
      volume: an `OctreeVolume` or a `MacrocellGrid`.
      isovalues: [K] float32; `Hits.surface` says which one was hit.
      clip_lo, clip_hi: [3] world-space clip box (default: the volume's cells).
      method: cell root finder, "neubauer" (Marmitt et al.'s iterative solver) or
        "analytic" (closed-form cubic roots), Sec. 3.3.4.
      traversal: octree "restart" (from the root after every move) or "neighbor"
        (resume at the common ancestor, Sec. 3.3.2.2).
      normals: "trilinear" (gradient of the hit cell's patch, the seed's forward
        differences) or "central" (central differences of the voxels, interpolated:
        continuous across cells, Sec. 4.5.1).
      lod: None (full resolution) or a `LevelOfDetail` (`lod_for(camera, quality)`):
        stop at coarse cells where a pixel covers several voxels (octree only, ch. 4).
        Shadow rays from `render` run at `shadow_eps_scale` times its dP/dV ratio.
      max_steps: iteration bound per ray (None: enough for any ray through the volume).
      frame_origin, frame_offset: None (rays in this volume's own voxel frame), or a
        [3] float32 origin and the [3] int32 index this volume's voxel (0, 0, 0) has
        there: a brick of a larger volume (`brick_volume`) traces rays in the whole
        volume's frame, so the float32 arithmetic on either side of a seam is the same
        as the whole volume's and the bricks' depths equal its own.

    volume, isovalues, clip box and lod are traced (`replace` / `with_isovalues` /
    `with_lod` never recompile for the same shapes); method, traversal, normals and
    max_steps are static.

    Non-finite voxels mark missing data: cells touching one are never hit.
    """

    volume: object
    isovalues: jax.Array
    clip_lo: jax.Array
    clip_hi: jax.Array
    method: str = static_field("neubauer")
    traversal: str = static_field("restart")
    normals: str = static_field("trilinear")
    lod: object = None
    max_steps: int | None = static_field(None)
    frame_origin: object = None
    frame_offset: object = None

    def __init__(self, volume, isovalues, *, clip_box=None, method="neubauer",
                 traversal="restart", normals="trilinear", lod=None, max_steps=None,
                 frame=None):
        if not isinstance(volume, (_octree.OctreeVolume, MacrocellGrid)):
            raise TypeError("volume must be an OctreeVolume or a MacrocellGrid, got "
                            f"{type(volume).__name__}; build one with "
                            "OctreeVolume.from_array(data)")
        lo, hi = _cells_box(volume)
        if clip_box is not None:
            c_lo, c_hi = (jnp.broadcast_to(jnp.asarray(c, jnp.float32), (3,))
                          for c in clip_box)
            check_finite("clip_box", jnp.stack([c_lo, c_hi]))
            _check_box(c_lo, c_hi)
            lo, hi = jnp.maximum(lo, c_lo), jnp.minimum(hi, c_hi)
        frame_origin, frame_offset = (None, None) if frame is None else frame
        for name, value in (("volume", volume), ("isovalues", isovalues), ("clip_lo", lo),
                            ("clip_hi", hi), ("method", method), ("traversal", traversal),
                            ("normals", normals), ("lod", lod), ("max_steps", max_steps),
                            ("frame_origin", frame_origin), ("frame_offset", frame_offset)):
            object.__setattr__(self, name, value)
        self._validate()

    def _validate(self):
        """Normalise and check the fields (construction and every `replace`)."""
        check_choice("method", self.method, METHODS)
        check_choice("traversal", self.traversal, TRAVERSALS)
        check_choice("normals", self.normals, NORMALS)
        volume, lod = self.volume, self.lod
        if lod is not None and not isinstance(volume, _octree.OctreeVolume):
            raise ValueError("level of detail needs an OctreeVolume")
        if lod is not None and not volume.multires:
            raise ValueError("level of detail needs a volume built with multires=True")
        object.__setattr__(self, "isovalues", isovalues_array(self.isovalues))
        for name in ("clip_lo", "clip_hi"):
            object.__setattr__(self, name, jnp.asarray(getattr(self, name), jnp.float32))
            check_finite(name, getattr(self, name))
        check_count("max_steps", self.max_steps)
        self._validate_frame()

    def _validate_frame(self):
        """Both frame fields or neither; the volume's origin where the frame puts it."""
        if (self.frame_origin is None) != (self.frame_offset is None):
            raise ValueError("frame_origin and frame_offset go together (both or neither)")
        if self.frame_origin is None:
            return
        object.__setattr__(self, "frame_origin", jnp.asarray(self.frame_origin, jnp.float32))
        object.__setattr__(self, "frame_offset", jnp.asarray(self.frame_offset, jnp.int32))
        origin, offset = concrete(self.frame_origin), concrete(self.frame_offset)
        own, spacing = concrete(self.volume.origin), concrete(self.volume.spacing)
        if any(x is None for x in (origin, offset, own, spacing)):
            return
        placed = origin.astype(np.float64) + offset * spacing.astype(np.float64)
        if not np.allclose(placed, own, rtol=1e-5, atol=1e-4 * float(np.min(spacing))):
            raise ValueError(f"the frame puts this volume's first voxel at {placed}, but "
                             f"its origin is {own} (a brick's volume replaced? build "
                             "bricks with brick_volume)")

    @property
    def lo(self):
        return self.clip_lo

    @property
    def hi(self):
        return self.clip_hi

    @property
    def offset_scale(self):
        """Secondary rays leave a surface by a thousandth of a voxel."""
        return 1e-3 * jnp.min(self.volume.spacing)

    def coarser(self, factor) -> VolumeIsosurface:
        """Shadow rays: the level of detail `factor` times coarser (no effect without)."""
        if self.lod is None:
            return self
        return self.replace(lod=self.lod.coarser(jnp.maximum(factor, 1.0)))

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """8x8 packets (fastest in the packet table of bench_volume.py, 256^3 mixing layer
        at 256^2: 2x2 0.005, 4x4 0.008, 8x8 0.014, 16x16 0.012 Mrays/s); on the CPU,
        4096 persistent lanes from 2^16 rays (benchmarks/NOTES.md)."""
        lanes = cpu_lanes(n_rays, backend)
        return Plan(tile=8, lanes=lanes)

    def with_lod(self, lod) -> VolumeIsosurface:
        """The same scene with another level-of-detail model (None: full resolution)."""
        return self.replace(lod=lod)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of one packet of rays [P] (the scene protocol, `jaxiso.Scene`).
        lanes: run the packet on this many persistent lanes with refill (same hits)."""
        method, traversal, normals = self.method, self.traversal, self.normals
        vol = self.volume
        lod = self.lod
        o, d = rays.origin, rays.direction
        origin, offset = self._frame()
        q0, dq = voxel_ray(origin, vol.spacing, o, d)
        box_lo = _voxel_coordinates(self.clip_lo, origin, vol.spacing)
        box_hi = _voxel_coordinates(self.clip_hi, origin, vol.spacing)
        t_in, t_out = slab(q0, dq, box_lo, box_hi)
        t_start = jnp.maximum(t_min, t_in)
        t_end = jnp.minimum(t_max, t_out)
        if isinstance(vol, MacrocellGrid):
            cells = GridCells(vol, self.isovalues)
        else:
            cells = OctreeCells(vol, self.isovalues, traversal == "neighbor", lod)
        t_raw, hit, which, cell, size, steps = traverse(
            cells, self.isovalues, q0, dq, t_start, t_end, method=method,
            max_steps=self.max_steps, lanes=lanes, offset=offset)
        safe_t = jnp.where(hit, t_raw, 0.0)
        if lod is None:
            level = self.isovalues[jnp.maximum(which, 0)]
            safe_t = attach_t(_field, safe_t, o, d, jnp.float32(0.0), vol, level, hit)
        q_hit = q0 + safe_t[:, None] * dq
        corners = cells.cell(cells.init(q0.shape[0]), cell, _log2(size))
        u = jnp.clip((q_hit - (cell + offset)) / size[:, None], 0.0, 1.0)
        if normals == "central" and lod is None:
            grad = _central_gradient(vol, cell, u)
        else:
            grad = _cell.trilinear_gradient(corners, u) / size[:, None]
        normal = unit_or_facing(grad / vol.spacing, d)
        return Hits(t=jnp.where(hit, safe_t, jnp.inf), hit=hit,
                    normal=jnp.where(hit[:, None], normal, 0.0),
                    surface=jnp.where(hit, which, -1), steps=steps)

    def _frame(self):
        """(origin [3] float32, offset [3] int32) of the voxel frame rays are traced in."""
        if self.frame_origin is None:
            return self.volume.origin, jnp.zeros(3, jnp.int32)
        return self.frame_origin, self.frame_offset


def _voxel_coordinates(corner, origin, spacing):
    """A clip-box corner [3] in voxel units, snapped onto the voxel plane it is within
    float32 rounding of: a volume's own faces and a brick's seams are such planes, and
    the traversal crosses planes at exact integers (a face a few ulp off would start a
    brick's rays a few ulp away from where the whole volume's traversal enters the same
    cell, and move their roots at grazing incidence)."""
    q = (corner - origin) / spacing
    nearest = jnp.round(q)
    rounding = 1e-6 * (jnp.abs(corner) + jnp.abs(origin)) / spacing   # ~8 ulp
    return jnp.where(jnp.abs(q - nearest) <= rounding, nearest, q)


def _log2(size):
    return 31 - jax.lax.clz(size.astype(jnp.int32))


def _field(x, y, z, w, vol):
    """The trilinear interpolant at a world point (scalars), differentiable with respect
    to float voxel values; the cell comes from the (non-differentiable) floor."""
    q = (jnp.stack([x, y, z]) - vol.origin) / vol.spacing
    n_cells = jnp.array(vol.shape, jnp.int32) - 2
    v = jnp.clip(jnp.floor(jax.lax.stop_gradient(q)).astype(jnp.int32), 0,
                 jnp.maximum(n_cells, 0))
    corners = _corners_of(vol, v[None])[0]
    return _cell.trilinear(corners, q - v)


def _corners_of(vol, v):
    if isinstance(vol, MacrocellGrid):
        return GridCells(vol, jnp.zeros(1)).cell({}, v, None)
    return _octree.cell_corners(vol, v)


_STENCIL = np.array([[a, b, c] for a in range(-1, 3) for b in range(-1, 3)
                     for c in range(-1, 3)], np.int32)


def _central_gradient(vol, cell, u):
    """Central differences of the voxels at the 8 corners of each cell [P, 3],
    interpolated trilinearly at u [P, 3] (one-sided at the volume's faces)."""
    last = jnp.array(vol.shape, jnp.int32) - 1
    pos = cell[:, None, :] + _STENCIL[None]                              # [P, 64, 3]
    clamped = jnp.clip(pos, 0, last)
    if isinstance(vol, MacrocellGrid):
        vals = vol.data[clamped[..., 0], clamped[..., 1], clamped[..., 2]]
    else:
        vals = _octree.lookup(vol, clamped)
    vals = vals.reshape(-1, 4, 4, 4)
    grads = []
    for axis in range(3):
        lo_idx = [slice(None)] * 4
        hi_idx = [slice(None)] * 4
        lo_idx[axis + 1] = slice(0, 2)
        hi_idx[axis + 1] = slice(2, 4)
        p_lo = jnp.clip(cell[:, axis, None] + jnp.arange(2) - 1, 0, last[axis])
        p_hi = jnp.clip(cell[:, axis, None] + jnp.arange(2) + 1, 0, last[axis])
        width = (p_hi - p_lo).astype(jnp.float32)                            # [P, 2]
        diff = vals[tuple(hi_idx)] - vals[tuple(lo_idx)]                     # [P, ., ., .]
        shape = [-1, 1, 1, 1]
        shape[axis + 1] = 2
        diff = diff / jnp.maximum(width, 1.0).reshape(shape)
        # keep the 2x2x2 corner block of the other axes
        idx = [slice(None)] + [slice(1, 3)] * 3
        idx[axis + 1] = slice(None)
        grads.append(diff[tuple(idx)].reshape(-1, 8))
    corner_grads = jnp.stack(grads, axis=-1)                                 # [P, 8, 3]
    return jnp.stack([_cell.trilinear(corner_grads[..., i], u) for i in range(3)], axis=-1)


def _cells_box(volume):
    n = jnp.array(volume.shape, jnp.float32)
    lo = volume.origin
    hi = volume.origin + jnp.maximum(n - 1.0, 0.0) * volume.spacing
    return lo.astype(jnp.float32), hi.astype(jnp.float32)


def _check_box(lo, hi):
    lo_, hi_ = concrete(lo), concrete(hi)
    if lo_ is None or hi_ is None:
        return
    if np.any(lo_ > hi_):
        raise ValueError(f"clip box needs lo <= hi, got {lo_} and {hi_}")
