"""Scenes split over the devices of a mesh: one part of the data per device, the nearest
hit of every ray by a collective minimum of `t` (docs/distributed.md, "Split the data").

A split scene holds P parts of one scene kind (bricks of a volume, spatial groups of a
tet mesh), each a complete scene of its own (its own octree or BVH). Their arrays are
stacked along a leading part axis [P, ...] that is sharded over a one-axis mesh, part k
on device k, so no device holds more than its part, and each process builds only the
parts of its own devices (`stack_parts`). Parts of different sizes are padded to the
largest (zeros by default: octree records and tets that nothing points at).

`SplitScene.intersect_packet` traces every ray through every part (each device its own)
and `nearest_hits` keeps, per ray, the hit of smallest `t` over the mesh: a `pmin` of t
and of the winning part's index, then one `psum` carrying the winner's hit, normal,
surface and steps. This module is scene-kind neutral: `jaxiso.volume.brick_volume` and
`jaxiso.tetra.split_tets` build on it; it never imports `render` (the caller's mesh).
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._core import LANES, Hits, Plan, SceneFields, pytree_dataclass, static_field

__all__ = ["SplitScene", "nearest_hits", "stack_parts", "local_parts", "SPLIT_LANES_FROM"]

# split scenes trace on persistent lanes from this many rays on the CPU (one scene:
# 2^16): each of their packets waits for a collective (`SplitScene.preferred_plan`)
SPLIT_LANES_FROM = 2**14


def local_parts(mesh: Mesh) -> list[int]:
    """Indices k of the parts this process builds: those of its own devices of `mesh`."""
    if len(mesh.axis_names) != 1:
        raise ValueError(f"a split scene goes over a mesh with one axis, got "
                         f"{mesh.axis_names}")
    me = jax.process_index()
    return [k for k, d in enumerate(mesh.devices.flat) if d.process_index == me]


def nearest_hits(hits: Hits, axis_name: str) -> Hits:
    """Per ray, the hit of smallest `t` over the devices of mesh axis `axis_name` (call
    inside `shard_map`); ties go to the lowest device index. Every device returns the
    same Hits [P]: the winner's t, hit, normal, surface and steps."""
    t = jax.lax.pmin(hits.t, axis_name)
    me = jax.lax.axis_index(axis_name)
    owner = jax.lax.pmin(jnp.where(hits.t == t, me, jnp.iinfo(jnp.int32).max), axis_name)
    mine = owner == me

    def winner(x):
        keep = mine.reshape(mine.shape + (1,) * (x.ndim - mine.ndim))
        return jnp.where(keep, x, jnp.zeros((), x.dtype))

    hit, normal, surface, steps = jax.lax.psum(
        (winner(hits.hit.astype(jnp.int32)), winner(hits.normal), winner(hits.surface),
         winner(hits.steps)), axis_name)
    return Hits(t=t, hit=hit > 0, normal=normal, surface=surface, steps=steps)


def _largest_shapes(leaves_per_part, mesh: Mesh) -> list[tuple]:
    """Per leaf, the largest shape over all parts of all processes (an all-gather of the
    few shape numbers through JAX's runtime when the mesh spans processes)."""
    local = np.array([[s for leaf in leaves for s in leaf.shape]
                      for leaves in leaves_per_part], np.int64).max(axis=0)
    if any(d.process_index != jax.process_index() for d in mesh.devices.flat):
        from jax.experimental import multihost_utils

        local = np.asarray(multihost_utils.process_allgather(local)).reshape(
            -1, local.size).max(axis=0)
    shapes, i = [], 0
    for leaf in leaves_per_part[0]:
        shapes.append(tuple(int(s) for s in local[i:i + leaf.ndim]))
        i += leaf.ndim
    return shapes


def zero_pad(path, leaf: np.ndarray, shape) -> np.ndarray:
    """`leaf` zero-padded at the end of every axis to `shape` (the default filler)."""
    return np.pad(leaf, [(0, s - n) for n, s in zip(leaf.shape, shape)])


def stack_parts(scenes, mesh: Mesh, pad=zero_pad):
    """The parts `scenes` (this process's, in the order of `local_parts(mesh)`; all of
    one treedef: same static fields) as one scene whose every array has a leading part
    axis sharded over `mesh`, part k on device k. Each leaf is padded to the largest
    shape over all parts by ``pad(key_path, leaf, shape)``."""
    mine = local_parts(mesh)
    if len(scenes) != len(mine):
        raise ValueError(f"{len(scenes)} parts for {len(mine)} local devices")
    devices = list(mesh.devices.flat)
    flat = [jax.tree_util.tree_flatten_with_path(s) for s in scenes]
    treedef = flat[0][1]
    if any(f[1] != treedef for f in flat):
        raise ValueError("the parts differ in their static fields: " + ", ".join(
            sorted({str(f[1]) for f in flat}))[:500])
    paths = [p for p, _ in flat[0][0]]
    leaves = [[np.asarray(x) for _, x in f[0]] for f in flat]
    shapes = _largest_shapes(leaves, mesh)
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    stacked = []
    for j, shape in enumerate(shapes):
        parts = [jax.device_put(pad(paths[j], leaves[i][j], shape)[None], devices[k])
                 for i, k in enumerate(mine)]
        stacked.append(jax.make_array_from_single_device_arrays(
            (len(devices),) + shape, sharding, parts))
    return jax.tree_util.tree_unflatten(treedef, stacked)


@pytree_dataclass
class SplitScene(SceneFields):
    """A scene split into parts, one per device of `mesh` (a scene for `intersect` and
    `render`; build one with `jaxiso.volume.brick_volume` or `jaxiso.tetra.split_tets`).

    Attributes:
      parts: a scene (VolumeIsosurface, TetIsosurface) whose every array has a leading
        part axis [P, ...], sharded over the mesh axis (part k on device k).
      box_lo, box_hi: [3] the whole scene's drawn box (replicated).
      offset: [] the whole scene's offset for secondary rays.
      mesh: the one-axis mesh the parts live on (static).

    Every device traces all rays through its own part; `nearest_hits` composites them,
    so `Hits.steps` is the winning part's count. Render with `devices=None` (the rays are
    not split: the data is).
    """

    parts: object
    box_lo: jax.Array
    box_hi: jax.Array
    offset: jax.Array
    mesh: Mesh = static_field()

    def _validate(self):
        pass

    @property
    def n_parts(self) -> int:
        return int(self.mesh.devices.size)

    @property
    def lo(self):
        return self.box_lo

    @property
    def hi(self):
        return self.box_hi

    @property
    def offset_scale(self):
        return self.offset

    def coarser(self, factor):
        """No level of detail on split scenes: shadow rays trace the same scene."""
        return self

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """32x32 packets (one collective per 1024 rays) up to 2^14 rays, and on the CPU
        4096 persistent lanes from there (one collective per trace).

        A packet's collective costs far more than its tracing. 2 local processes (gloo,
        one thread each, a loaded 2-core box): 32^2 pixels of a 33^3 volume in 2 bricks,
        frame 344 ms in 8x8 packets, 56 ms in 32x32, 30 ms on 1024 lanes (first call
        13 / 17 / 46 s; one process, whole volume: 12 ms); 128^2 of 96^3: 16x16 packets
        1720 ms, 32x32 868 ms, 4096 lanes 260 ms (first call 17 / 21 / 78 s; one process,
        whole volume: 244 ms). Other backends: packets (unmeasured)."""
        lanes = LANES if backend == "cpu" and n_rays >= SPLIT_LANES_FROM else None
        return Plan(tile=32, lanes=lanes)

    def part_nbytes(self) -> int:
        """Bytes of one part's arrays (what each device holds of the scene; parts are
        padded to the largest)."""
        return int(sum(leaf.nbytes // leaf.shape[0]
                       for leaf in jax.tree_util.tree_leaves(self.parts)))

    def with_isovalues(self, isovalues):
        """The same parts at other isovalues (same count: no recompile)."""
        iso = np.atleast_1d(np.asarray(isovalues, np.float32))
        if iso.shape != tuple(self.parts.isovalues.shape[1:]):
            raise ValueError(f"with_isovalues keeps the count "
                             f"{self.parts.isovalues.shape[1]}, got shape {iso.shape}")
        sharding = NamedSharding(self.mesh, PartitionSpec(self.mesh.axis_names[0]))
        stacked = np.broadcast_to(iso, (self.n_parts,) + iso.shape)
        glob = jax.make_array_from_callback(stacked.shape, sharding, lambda i: stacked[i])
        parts = copy.copy(self.parts)
        object.__setattr__(parts, "isovalues", glob)
        return self.replace(parts=parts)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of rays [P] (the scene protocol): every device traces all P rays
        through its own part, then `nearest_hits` keeps the nearest per ray."""
        axis_name = self.mesh.axis_names[0]
        part_spec = PartitionSpec(axis_name)

        def one_part(parts, rays, t_min, t_max):
            part = jax.tree_util.tree_map(lambda a: a[0], parts)
            hits = part.intersect_packet(rays, t_min, t_max, lanes=lanes)
            return nearest_hits(hits, axis_name)

        specs = (jax.tree_util.tree_map(lambda _: part_spec, self.parts),
                 PartitionSpec(), PartitionSpec(), PartitionSpec())
        return jax.shard_map(one_part, mesh=self.mesh, in_specs=specs,
                             out_specs=PartitionSpec(), check_vma=False)(
            self.parts, rays, t_min, t_max)
