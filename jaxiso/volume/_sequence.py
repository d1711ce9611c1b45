"""Time-varying volumes: a sequence of octree volumes (seed Sec. 3.5.4, Table 3.1's
heptane 0-152 row) that switches time step without a rebuild or a retrace.

Each step is its own lossless octree (time steps compress differently). To switch steps
inside a jitted render with a traced index, the steps' flat arrays are padded to the
largest step and stacked; `at(step)` slices one out. The padding is reported apart from
the footprint of the steps themselves.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._core import pytree_dataclass, static_field
from ._octree import OctreeVolume

__all__ = ["VolumeSequence"]

_STACKED = ("child_start", "child_offset", "child_value", "child_min", "child_max", "caps")


@pytree_dataclass
class VolumeSequence:
    """S octree volumes of one grid, stacked for traced step selection.

    Attributes:
      stacked: dict of the flat arrays, each [S, max size, ...].
      spacing, origin: [3] float32, shared by the steps.
      shape, depth, multires, raw_itemsize: the steps' static layout.
      volume_nbytes: static tuple, bytes of each step's own octree.
    """

    stacked: dict
    spacing: jax.Array
    origin: jax.Array
    shape: tuple = static_field()
    depth: int = static_field()
    multires: bool = static_field()
    raw_itemsize: int = static_field()
    volume_nbytes: tuple = static_field()

    @staticmethod
    def from_arrays(frames, *, progress=None, **build_options) -> VolumeSequence:
        """Build one octree per frame ([S, nx, ny, nz] array or a list of 3-D arrays);
        `build_options` go to `OctreeVolume.from_array` (spacing, iso_range, ...)."""
        frames = list(frames)
        if not frames:
            raise ValueError("a volume sequence needs at least one frame")
        volumes = []
        for i, frame in enumerate(frames):
            volumes.append(OctreeVolume.from_array(frame, progress=progress, **build_options))
            if progress:
                print(f"[jaxiso] built time step {i + 1}/{len(frames)}", flush=True)
        return VolumeSequence.from_volumes(volumes)

    @staticmethod
    def from_volumes(volumes) -> VolumeSequence:
        volumes = list(volumes)
        first = volumes[0]
        for i, v in enumerate(volumes):
            same = (v.shape, v.depth, v.multires, v.dtype) == (first.shape, first.depth,
                                                                first.multires, first.dtype)
            if not same:
                raise ValueError(f"time step {i} has shape/depth/dtype {v.shape}, {v.depth}, "
                                 f"{v.dtype}; step 0 has {first.shape}, {first.depth}, "
                                 f"{first.dtype}: a sequence needs one grid")
        stacked = {}
        for name in _STACKED:
            arrays = [np.asarray(getattr(v, name)) for v in volumes]
            size = max(a.shape[0] for a in arrays)
            # padding records are never reached: no pointer of a real record leads there
            stacked[name] = jnp.asarray(np.stack([
                np.concatenate([a, np.zeros((size - a.shape[0],) + a.shape[1:], a.dtype)])
                for a in arrays]))
        return VolumeSequence(stacked, first.spacing, first.origin, first.shape, first.depth,
                              first.multires, first.raw_itemsize,
                              tuple(v.nbytes for v in volumes))

    @property
    def n_steps(self) -> int:
        return len(self.volume_nbytes)

    @property
    def nbytes(self) -> int:
        """Footprint of the steps' own octrees (the Table 3.1 figure)."""
        return int(sum(self.volume_nbytes))

    @property
    def padded_nbytes(self) -> int:
        """Bytes actually held, with every step padded to the largest."""
        return int(sum(a.nbytes for a in self.stacked.values()))

    @property
    def raw_nbytes(self) -> int:
        return self.at(0).raw_nbytes * self.n_steps

    @property
    def compression_ratio(self) -> float:
        return self.raw_nbytes / self.nbytes

    def at(self, step) -> OctreeVolume:
        """The volume of time step `step` (an int or a traced int32: no retrace)."""
        step = jnp.asarray(step, jnp.int32)
        arrays = {name: a[step] for name, a in self.stacked.items()}
        return OctreeVolume(**arrays, spacing=self.spacing, origin=self.origin,
                            shape=self.shape, depth=self.depth, multires=self.multires,
                            raw_itemsize=self.raw_itemsize)
