"""Past one machine: rays sharded over a mesh that spans processes, on JAX's own runtime.

After `jax.distributed.initialize(...)` every process sees all devices (`jax.devices()`)
and its own (`jax.local_devices()`). A `Mesh` over all of them is a *global* mesh: a
jitted call over it runs as one SPMD program in every process, and the collectives (an
all-gather of the image here) go through JAX's runtime (gloo or MPI on CPUs, NCCL on
GPUs). No socket or process pool of ours.

The rules a multi-process call must follow, kept here in small functions:

- every input is a global array: values that every process holds the same copy of (a
  scene, a camera) become *replicated* arrays over the mesh (`to_global`); arrays that
  already live on the mesh (a brick-distributed volume) stay as they are;
- the output is replicated over the mesh (every process gets the whole image) and read
  back from a local shard (`to_host`).

On one process these are no-ops, so the same call runs on a laptop and on a cluster.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._core import Hits, Plan, Rays
from ._plan import intersect as _intersect_local
from ._plan import intersect_traced, prepare

__all__ = ["process_mesh", "spans_processes", "to_global", "to_host", "mesh_of",
           "intersect", "replicated"]


def process_mesh(axis: str = "rays") -> Mesh:
    """A one-axis `Mesh` over every device of every process (`jax.devices()`), in the
    runtime's order (process 0's devices first). Call after `jax.distributed.initialize`
    to span processes; before it (or in one process) it is the local devices."""
    return Mesh(np.array(jax.devices()), (axis,))


def spans_processes(mesh: Mesh | None) -> bool:
    """Whether `mesh` holds devices of another process (its calls run in every process)."""
    if mesh is None:
        return False
    me = jax.process_index()
    return any(d.process_index != me for d in mesh.devices.flat)


def replicated(mesh: Mesh) -> NamedSharding:
    """The sharding of a value every device of `mesh` holds whole."""
    return NamedSharding(mesh, PartitionSpec())


def _on_mesh(x, mesh: Mesh) -> bool:
    """A jax array already placed on exactly the devices of `mesh`."""
    return isinstance(x, jax.Array) and set(x.sharding.device_set) == set(mesh.devices.flat)


def to_global(tree, mesh: Mesh | None):
    """`tree` with every array leaf placed on `mesh`: leaves already on its devices stay
    (a sharded brick volume), the others (the same value in every process: a scene, a
    camera) become replicated global arrays. Identity when `mesh` is None."""
    if mesh is None:
        return tree
    sharding = replicated(mesh)

    def place(x):
        if (not isinstance(x, (jax.Array, np.ndarray)) or isinstance(x, jax.core.Tracer)
                or _on_mesh(x, mesh)):
            return x  # python scalars, the caller's jit's values, arrays already placed
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])

    return jax.tree_util.tree_map(place, tree)


def to_host(x):
    """A (replicated) result as numpy in this process: from the local shard when the array
    spans processes (every process then gets the same value), else `jax.device_get`."""
    def one(a):
        if isinstance(a, jax.Array) and not a.is_fully_addressable:
            if not a.is_fully_replicated:
                raise ValueError("to_host reads replicated results only; this array is "
                                 f"sharded as {a.sharding}")
            return np.asarray(a.addressable_data(0))
        return jax.device_get(a)

    return jax.tree_util.tree_map(one, x)


def mesh_of(tree, devices=None) -> Mesh | None:
    """The mesh a call runs on: `devices` (a one-axis Mesh, a NamedSharding or a list of
    devices) when given, else the mesh of a leaf of `tree` that spans processes (a
    brick-distributed scene carries its own), else None (the default device). Under an
    outer jit the leaves are tracers: None (the caller's jit places the inputs)."""
    if devices is not None:
        return as_mesh(devices)
    for leaf in jax.tree_util.tree_leaves(tree):
        if (isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer)
                and not leaf.is_fully_addressable
                and isinstance(leaf.sharding, NamedSharding)):
            return leaf.sharding.mesh
    return None


def as_mesh(devices) -> Mesh:
    """A one-axis mesh from a Mesh, a NamedSharding or a sequence of devices."""
    if isinstance(devices, Mesh):
        if len(devices.axis_names) != 1:
            raise ValueError(f"rays shard over a mesh with one axis, got axes "
                             f"{devices.axis_names}")
        return devices
    if isinstance(devices, NamedSharding):
        return as_mesh(devices.mesh)
    devs = list(devices)
    if not devs:
        raise ValueError("devices is empty")
    return Mesh(np.array(devs), ("rays",))


def shard_rays(fn, mesh: Mesh, shared, arrays, packet: int):
    """`fn(shared, *arrays)` with arrays [N, ...] split over the mesh axis in whole packets
    of `packet` rays (padded by repeating ray 0, cut off after), under the caller's jit.

    shared: a pytree every device gets whole (the scene, shading, ...; passed in, not
    closed over: a closed-over global array keeps its mesh-wide sharding inside the
    per-device function). fn maps arrays [n, ...] to a pytree of [n, ...]. Returns that
    pytree for all N rays, replicated over the mesh (every device, hence every process,
    holds all of it)."""
    n_dev = mesh.devices.size
    n = arrays[0].shape[0]
    pad = (-n) % (n_dev * packet)
    padded = [jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])])
              for a in arrays]
    spec = PartitionSpec(mesh.axis_names[0])
    out = jax.shard_map(fn, mesh=mesh, in_specs=(PartitionSpec(),) + (spec,) * len(arrays),
                        out_specs=spec, check_vma=False)(shared, *padded)
    out = jax.tree_util.tree_map(lambda a: a[:n], out)
    return jax.lax.with_sharding_constraint(out, replicated(mesh))


def intersect(scene, rays: Rays, *, t_min=0.0, t_max=jnp.inf, plan: Plan | None = None,
              devices=None) -> Hits:
    """First hits of `rays` (any batch shape S) with `scene`; `jaxiso.intersect`.

    Every option lives on the scene (`scene.replace`). `t_min`/`t_max` are scalars or
    arrays broadcastable to S. `plan` (default `plan_for(scene, rays per device)`): rays
    run in consecutive packets of ``plan.tile**2`` (pass them in a coherent order, e.g.
    `to_tiles`), or all as one queue on ``plan.lanes`` persistent lanes. Jitted inside,
    jit/vmap/grad-able; `t` is differentiable (implicit function theorem) with respect to
    the scene's traced fields and the rays.

    devices: None (the default device; or, for a brick-distributed scene, its mesh), a
    list of devices or a one-axis `jax.sharding.Mesh`, which may span processes (after
    `jax.distributed.initialize`): rays are split over it in whole packets, and the
    returned Hits are replicated over the mesh, so every process holds all of them
    (`jaxiso.distributed.to_host` reads them as numpy in each process).
    """
    mesh = mesh_of(scene, devices)
    if mesh is None or not isinstance(rays, Rays) or math.prod(rays.shape) == 0:
        # the local call (and its checks: not rays, an empty batch)
        return _intersect_local(scene, rays, t_min=t_min, t_max=t_max, plan=plan)
    shape = rays.shape
    # the preparation `intersect` and `render` do: the scene checked and prepared, the
    # plan (default: for the rays of one device) checked
    scene, plan = prepare(scene, -(-math.prod(shape) // mesh.devices.size), plan)
    if plan.tape:
        raise TypeError(f"plan must be a jaxiso.Plan without tape (a long program's tape "
                        f"runs on one process's host) on a mesh, got {plan!r}")
    t_min = jnp.broadcast_to(jnp.asarray(t_min, jnp.float32), shape)
    t_max = jnp.broadcast_to(jnp.asarray(t_max, jnp.float32), shape)
    args = to_global((scene, rays, t_min, t_max), mesh)
    split = None if devices is None else as_mesh(devices)
    return _intersect_on(*args, plan, mesh, split)


@functools.partial(jax.jit, static_argnums=(4, 5, 6))
def _intersect_on(scene, rays, t_min, t_max, plan, mesh, split):
    """Hits of rays [S] on `mesh`; rays split over `split` (None: every device traces
    all of them: a brick-distributed scene splits its data instead)."""
    shape = rays.shape
    n = math.prod(shape)
    flat = rays.reshape((n,))
    lo, hi = t_min.reshape(n), t_max.reshape(n)
    if split is None:
        hits = intersect_traced(scene, flat, lo, hi, plan)
        hits = jax.lax.with_sharding_constraint(hits, replicated(mesh))
    else:
        def fn(scene, o, d, lo, hi):
            return intersect_traced(scene, Rays(o, d), lo, hi, plan)

        hits = shard_rays(fn, split, scene, (flat.origin, flat.direction, lo, hi),
                          plan.packet)
    return hits.reshape(shape)
