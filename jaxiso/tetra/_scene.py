"""`TetIsosurface`: isosurfaces of a piecewise-linear field on a tetrahedral mesh (ch. 5).

Implements the scene protocol (`intersect_packet`) by traversing the implicit BVH and
intersecting marching-tets isopolygons. Within a tet the field is linear, so the hit is
t = (iso - F(o)) / (grad F . d) in closed form; it is recomputed from the hit tet with
jax.numpy after the loop, which makes `t` (and the normal) differentiable with respect to
the isovalues, the vertex values, the vertex positions and the rays (the implicit
function theorem for a linear field) without differentiating the loop.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._core import (
    Hits,
    Plan,
    SceneFields,
    check_choice,
    check_count,
    concrete,
    cpu_lanes,
    isovalues_array,
    pytree_dataclass,
    slab,
    static_field,
    unit_or_facing,
)
from ._bvh import BVH, build_bvh, refit_jax
from ._isopoly import tet_gradient
from ._mesh import TetMesh
from ._traverse import traverse

__all__ = ["TetIsosurface"]

NORMALS = ("flat", "smooth")


@pytree_dataclass
class TetIsosurface(SceneFields):
    """The level sets ``F = iso`` of the linear interpolant of vertex values on tets.

    Attributes:
      mesh: `TetMesh` (points, tets, values per time step).
      bvh: the implicit BVH, bounds valid for `time_step` and the mesh's points.
      isovalues: [K] float32; `Hits.surface` says which one was hit.
      time_step: int32 [] (traced: switching steps does not retrace).
      clip_lo, clip_hi: [3] world-space clip box (default: none, +-inf).
      vertex_gradients: [V, 3] area-weighted field gradients for smooth normals, or None.
      normals: "flat" (the tet's gradient) or "smooth" (vertex gradients interpolated).
      max_steps: iteration bound per ray (None: the traversal's default).

    All but normals and max_steps (static) are traced: `replace`, `with_isovalues`,
    `with_time_step` and `with_points` never recompile for the same shapes.
    """

    mesh: TetMesh
    bvh: BVH
    isovalues: jax.Array
    time_step: jax.Array
    clip_lo: jax.Array
    clip_hi: jax.Array
    vertex_gradients: jax.Array | None
    normals: str = static_field("flat")
    max_steps: int | None = static_field(None)

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """16x16 packets below 2^16 rays (fastest with postponed leaf tests; replicated
        spheres at 128^2: 4x4 0.21 / 1.61 s, 8x8 0.10 / 0.89 s, 16x16 0.11 / 0.32 s), and
        on the CPU 4096 persistent lanes from 2^16 rays (256^2: 0.27 vs 0.32 s for 10k
        tets, 0.27-0.34 vs 1.10 s for 664k; benchmarks/NOTES.md)."""
        lanes = cpu_lanes(n_rays, backend)
        return Plan(tile=16, lanes=lanes)

    def __init__(self, mesh, isovalues, *, bvh="bih", leaf_size=8, clip_box=None,
                 time_step=0, normals="flat", max_steps=None):
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a TetMesh (tet_mesh(points, tets, values), "
                            f"from_meshio, from_pyvista), got {type(mesh).__name__}")
        if normals not in NORMALS:
            raise ValueError(f"normals must be one of {NORMALS}, got {normals!r}")
        step = int(time_step)
        if not 0 <= step < mesh.n_steps:
            raise ValueError(f"time_step {step} out of range: the mesh has {mesh.n_steps}")
        if isinstance(bvh, str):
            bvh = build_bvh(mesh, method=bvh, leaf_size=leaf_size, step=step)
        elif not isinstance(bvh, BVH):
            raise TypeError(f"bvh must be 'bih', 'sah' or a BVH, got {type(bvh).__name__}")
        bvh = jax.tree_util.tree_map(jnp.asarray, bvh)  # traversal indexes with tracers
        # no clip box: no clipping at all (a surface on the mesh's own boundary faces must
        # not be lost to the rounding of a box test against that same face)
        lo, hi = np.full(3, -np.inf, np.float32), np.full(3, np.inf, np.float32)
        if clip_box is not None:
            lo, hi = (np.broadcast_to(np.asarray(c, np.float32), (3,)) for c in clip_box)
            if np.any(lo > hi):
                raise ValueError(f"clip box needs lo <= hi, got {lo} and {hi}")
        values = {"mesh": mesh, "bvh": bvh, "isovalues": isovalues,
                  "time_step": jnp.int32(step), "clip_lo": jnp.asarray(lo, jnp.float32),
                  "clip_hi": jnp.asarray(hi, jnp.float32), "vertex_gradients": None,
                  "normals": normals, "max_steps": max_steps}
        for name, value in values.items():
            object.__setattr__(self, name, value)
        if normals == "smooth":
            object.__setattr__(self, "vertex_gradients", _vertex_gradients(
                mesh.points, mesh.tets, jnp.asarray(mesh.values)[step]))
        self._validate()

    def _validate(self):
        """Normalise and check the fields (construction and every `replace`)."""
        check_choice("normals", self.normals, NORMALS)
        if self.normals == "smooth" and self.vertex_gradients is None:
            raise ValueError("smooth normals need vertex gradients: build the scene with "
                             "TetIsosurface(mesh, ..., normals='smooth')")
        object.__setattr__(self, "isovalues", isovalues_array(self.isovalues))
        lo, hi = (jnp.asarray(getattr(self, n), jnp.float32) for n in ("clip_lo", "clip_hi"))
        lo_, hi_ = concrete(lo), concrete(hi)
        if lo_ is not None and hi_ is not None and (np.any(np.isnan(lo_)) or np.any(
                np.isnan(hi_)) or np.any(lo_ > hi_)):
            raise ValueError(f"clip box needs lo <= hi without NaN, got {lo_} and {hi_}")
        object.__setattr__(self, "clip_lo", lo)
        object.__setattr__(self, "clip_hi", hi)
        check_count("max_steps", self.max_steps)

    # -- the renderer reads these
    @property
    def lo(self):
        """[3] min corner of the drawn part (mesh bounds within the clip box)."""
        return jnp.maximum(self.bvh.lo[0, :3], self.clip_lo)

    @property
    def hi(self):
        return jnp.minimum(self.bvh.hi[0, :3], self.clip_hi)

    @property
    def offset_scale(self):
        """Secondary rays leave a surface by 1e-5 of the scene's diagonal."""
        return 1e-5 * jnp.linalg.norm(self.hi - self.lo)

    def coarser(self, factor) -> TetIsosurface:
        """Hits are exact: shadow rays use the same scene."""
        return self

    # -- changes without a rebuild (all jit-able)

    def with_time_step(self, step) -> TetIsosurface:
        """Another time step: the BVH's value bounds are refit (Schema II), the tree kept."""
        step = jnp.asarray(step, jnp.int32)
        values = jnp.asarray(self.mesh.values)[step]
        bvh = refit_jax(self.bvh, jnp.asarray(self.mesh.points), values,
                        jnp.asarray(self.mesh.tets))
        return self.replace(bvh=bvh, time_step=step,
                        vertex_gradients=self._gradients(self.mesh.points, values))

    def with_points(self, points) -> TetIsosurface:
        """Moved vertices (same tets): the BVH's boxes are refit, the tree kept (Schema II).
        Large motions loosen the tree; rebuild with `TetIsosurface(mesh, ...)` (Schema I)."""
        points = jnp.asarray(points, jnp.float32)
        values = jnp.asarray(self.mesh.values)[self.time_step]
        bvh = refit_jax(self.bvh, points, values, jnp.asarray(self.mesh.tets))
        mesh = dataclasses.replace(self.mesh, points=points)
        return self.replace(mesh=mesh, bvh=bvh,
                        vertex_gradients=self._gradients(points, values))

    def _gradients(self, points, values):
        if self.vertex_gradients is None:
            return None
        return _vertex_gradients(points, self.mesh.tets, values)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of one packet of rays [P] (the scene protocol, `jaxiso.Scene`).
        lanes: run the packet on this many persistent lanes with refill (same hits)."""
        normals = self.normals
        o, d = rays.origin, rays.direction
        points = jnp.asarray(self.mesh.points)
        tets = jnp.asarray(self.mesh.tets)
        values = jnp.asarray(self.mesh.values)[self.time_step]
        t0, t1 = slab(o, d, self.clip_lo, self.clip_hi)
        t_lo = jnp.maximum(t_min, t0)
        t_hi = jnp.minimum(t_max, t1)
        stop = jax.lax.stop_gradient
        t_raw, hit, which, tet, nodes, leaves = traverse(
            stop(self.bvh), stop(points), tets, stop(values), stop(self.isovalues),
            stop(o), stop(d), stop(t_lo), stop(t_hi), max_steps=self.max_steps, lanes=lanes)
        # closed-form t on the hit tet: differentiable, and equal to the loop's value
        ids = tets[jnp.maximum(tet, 0)]
        p, f = points[ids], values[ids]
        grad = tet_gradient(p, f)
        iso = self.isovalues[jnp.maximum(which, 0)]
        slope = jnp.sum(grad * d, axis=-1)
        f_o = f[:, 0] + jnp.sum(grad * (o - p[:, 0]), axis=-1)
        safe = jnp.where(hit & (slope != 0), slope, 1.0)
        t = jnp.where(hit, (iso - f_o) / safe, jnp.inf)
        if normals == "smooth":
            x = o + jnp.where(hit, t, 0.0)[:, None] * d
            n = _interpolate(p, self.vertex_gradients[ids], x)
        else:
            n = grad
        normal = unit_or_facing(n, d)
        return Hits(t=t, hit=hit, normal=jnp.where(hit[:, None], normal, 0.0),
                    surface=jnp.where(hit, which, -1), steps=nodes)

    def memory_report(self) -> dict:
        """Bytes of the mesh and the BVH (seed Table 5.5 analog)."""
        from ._bvh import memory_report

        return memory_report(self.bvh, self.mesh)


def _interpolate(p, vertex_values, x):
    """Linear interpolation in tets p [P, 4, 3] of per-vertex vectors [P, 4, C] at x [P, 3]."""
    eye = jnp.eye(4, dtype=jnp.float32)
    lam = []
    for i in range(4):
        g = tet_gradient(p, jnp.broadcast_to(eye[i], p.shape[:-1]))
        lam.append(eye[i][0] + jnp.sum(g * (x - p[:, 0]), axis=-1))
    lam = jnp.stack(lam, axis=-1)
    return jnp.sum(lam[..., None] * vertex_values, axis=-2)


def _vertex_gradients(points, tets, values):
    """[V, 3] volume-weighted mean of the gradients of the tets around each vertex."""
    points = jnp.asarray(points, jnp.float32)
    tets = jnp.asarray(tets)
    p = points[tets]
    grad = tet_gradient(p, jnp.asarray(values)[tets])
    e = p[:, 1:] - p[:, :1]
    vol = jnp.abs(jnp.sum(e[:, 0] * jnp.cross(e[:, 1], e[:, 2]), axis=-1))
    weighted = jnp.repeat((grad * vol[:, None])[:, None, :], 4, axis=1).reshape(-1, 3)
    sums = jax.ops.segment_sum(weighted, tets.reshape(-1), points.shape[0])
    total = jax.ops.segment_sum(jnp.repeat(vol, 4), tets.reshape(-1), points.shape[0])
    return sums / jnp.maximum(total, 1e-30)[:, None]
