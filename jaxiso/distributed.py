"""More than one machine, on JAX's own runtime (docs/distributed.md).

    import jaxiso as ji
    from jaxiso import distributed

    distributed.initialize()          # SLURM / Open MPI detect themselves; or pass
                                      # coordinator_address, num_processes, process_id
    mesh = distributed.process_mesh() # every device of every process
    img = ji.render(scene, cam, devices=mesh)   # the same whole image in every process

`initialize` is `jax.distributed.initialize` plus the CPU collectives (gloo) that CPU
processes need to talk to each other; `ji.render` / `ji.intersect` take the mesh as their
`devices`. A volume too large for one device is split into bricks, one per device, with
`brick_volume` (see `jaxiso.volume.BrickedVolume`). Nothing here opens a socket of its
own: JAX's coordination service and collectives do the communication.
"""

from __future__ import annotations

import jax

from .render import process_mesh, spans_processes, to_global, to_host

__all__ = ["initialize", "process_mesh", "spans_processes", "to_global", "to_host",
           "CPU_COLLECTIVES"]

# what CPU processes use to exchange arrays (jax's config name for this jaxlib: gloo is
# built in; "mpi" needs an MPI library)
CPU_COLLECTIVES = "gloo"


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, heartbeat_timeout_seconds: int = 100,
               initialization_timeout: int = 300, cpu_collectives: str = CPU_COLLECTIVES,
               **kwargs) -> None:
    """Join this process to a multi-process JAX run (call before any other JAX work).

    Args:
      coordinator_address: "host:port" of process 0 (None: detected on SLURM, Open MPI,
        cloud TPU / GPU clusters; see `jax.distributed.initialize`).
      num_processes, process_id: this run's size and this process's rank (None: detected).
      heartbeat_timeout_seconds: a process silent this long is dead, and the others stop
        with an error instead of waiting for it.
      initialization_timeout: seconds to wait for every process to join.
      cpu_collectives: the CPU collectives implementation ("gloo" or "mpi"), set before
        the runtime starts (a no-op for GPU/TPU arrays).
      kwargs: passed on to `jax.distributed.initialize`.
    """
    jax.config.update("jax_cpu_collectives_implementation", cpu_collectives)
    jax.distributed.initialize(coordinator_address=coordinator_address,
                               num_processes=num_processes, process_id=process_id,
                               heartbeat_timeout_seconds=heartbeat_timeout_seconds,
                               initialization_timeout=initialization_timeout, **kwargs)
