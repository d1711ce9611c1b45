"""Sign grid culling of implicit scenes: when a scene gets a sign grid (`_grid.SignGrid`)
and how its rays use it (the part of each segment near possible cells, and the empty
stretches the walks leap)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..arith import network_shape
from ._grid import build_sign_grid, free_from, samples_per_segment, segment_span, values_key
from ._memo import BoundedCache
from ._methods import METHODS

__all__ = ["sign_grid_for", "near_possible_cells", "GRID_EQUATIONS", "GRID_INPUTS"]

# A sign grid compiles f's affine extension with fresh symbols: cheap for networks (fox:
# 30 operations), minutes for long scalar programs, which gain nothing from the symbols
# (they only take the errors of vector operations) and run on the tape path.
GRID_EQUATIONS = 256
# the fields a scene's sign grid depends on (`replace` of any of them drops it)
GRID_INPUTS = frozenset({"f", "lo", "hi", "w", "params", "rounding", "method", "culling"})
# grids by (f, rounding, digest of the values): the same inputs give the same grid
_GRIDS = BoundedCache("sign grids", 8)


def sign_grid_for(scene, heavy: bool):
    """(SignGrid or None, report) for the scene by its `culling` option; `heavy`: f is a
    network (`_policy.is_heavy`)."""
    why = _no_grid(scene, heavy)
    if why is not None:
        return None, why
    inputs = (scene.params, scene.w, scene.lo, scene.hi, scene.isovalues)
    key = (scene.f, scene.rounding, values_key(inputs))
    return _GRIDS.get(key, lambda: build_sign_grid(
        scene.field, scene.lo, scene.hi, scene.w, scene.params, scene.isovalues,
        scene.rounding, key=(scene.f, scene.has_params)))


def _no_grid(scene, heavy: bool) -> str | None:
    """Why the scene gets no sign grid ("" for culling="none"), or None."""
    if scene.culling == "none":
        return ""
    if not METHODS[scene.method].bisects:
        return f"no sign grid: method {scene.method!r} does not bisect"
    inputs = (scene.params, scene.w, scene.lo, scene.hi, scene.isovalues)
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(inputs)):
        return "no sign grid: params, w or the box are traced values"
    if scene.culling == "auto" and not heavy:
        return "no sign grid: f is light (auto builds one for networks)"
    if scene.culling == "auto" and not _network_like(scene):
        return ("no sign grid: f is no network (auto builds one for functions of "
                f"at most {GRID_EQUATIONS} operations, some on vectors)")
    return None


def _network_like(scene) -> bool:
    g = scene.field
    try:
        eqns, vectors = network_shape(lambda x, y, z, w: g(x, y, z, w, scene.params), 4)
    except Exception:  # noqa: BLE001 - a function that cannot be traced on scalars
        return False
    return eqns <= GRID_EQUATIONS and vectors > 0


def near_possible_cells(scene, t0, t1, inside, p, D):
    """The ray segments cut to the part near the sign grid's possible cells (all of it
    while delta > 0: a narrow enclosure is accepted there without holding an isovalue),
    and the stretches of them that the grid shows empty: (ahead, aux) for the walk
    (`_bisect.t_bisect_lanes`; none while delta > 0)."""
    span = segment_span(scene.sign_grid, scene.lo, scene.hi, scene.isovalues, p, D, inside)
    off = scene.delta > 0
    s0 = jnp.where(off, 0.0, span.s0)
    s1 = jnp.where(off, 1.0, span.s1)
    inside = jnp.where(off, inside, span.inside)
    length = t1 - t0
    # the walk's s in [0, 1] is the span's; the marks count gaps of the whole segment
    gaps = samples_per_segment(scene.sign_grid) - 1
    u0, du = s0 * gaps, (s1 - s0) * gaps
    marks = jnp.where(off, ~jnp.uint32(0), span.marks)
    return (t0 + s0 * length, t0 + s1 * length, inside, p + s0[:, None] * D,
            D * (s1 - s0)[:, None], (_grid_empty_until, (marks, u0, du)))


# The walk's position in the grid's sample coordinates is rounded (and so are the span's
# ends and the cut segment): the stretch it leaps is shortened by this many samples
_EMPTY_MARGIN = 1e-3


def _grid_empty_until(aux, s):
    """``ahead`` of the walk from a sign grid: the end of the empty stretch from s on
    (s itself or less where s's gap may hold a crossing; inf past the last one)."""
    marks, u0, du = aux
    u = u0 + s * du
    free = free_from(marks, u - _EMPTY_MARGIN) - _EMPTY_MARGIN
    return jnp.where(du > 0, (free - u0) / jnp.where(du > 0, du, 1.0), s)
