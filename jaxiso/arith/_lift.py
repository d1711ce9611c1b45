"""Values in `extend`: lifting the user's coordinates and params into an arithmetic.

A *lifted* value is an `Interval` or an `Affine`; anything else (arrays, Python scalars,
jaxpr literals) is a constant. Coordinates are checked, lifted, broadcast to the batch
shape S and flattened for the `vmap` over boxes; a constant result is turned back into an
enclosure.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _affine as aa
from . import _interval as ia
from ._affine import Affine
from ._interval import Interval


def is_lifted(x) -> bool:
    return isinstance(x, (Interval, Affine))


def as_range(x) -> Interval:
    """The Interval enclosing x: an Affine's (padded) range, a constant as a point."""
    return aa.padded_range(x) if isinstance(x, Affine) else ia.as_interval(x)


def shape_of(x) -> tuple:
    """The batch shape of a lifted value or the shape of a constant."""
    return tuple(x.shape) if hasattr(x, "shape") else np.shape(x)


def point_dtype(x):
    """The float dtype f is traced with for coordinate x (float32 for non-floats)."""
    if isinstance(x, Interval):
        dt = jnp.result_type(x.lo, x.hi)
    elif isinstance(x, Affine):
        dt = jnp.result_type(x.center)
    else:
        dt = jnp.result_type(x)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.dtype(jnp.float32)


def param_aval(x) -> jax.ShapeDtypeStruct:
    """The abstract value f is traced with for one params leaf."""
    if is_lifted(x):
        return jax.ShapeDtypeStruct(shape_of(x), point_dtype(x))
    return jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x))


def check_coordinate(x, i: int) -> None:
    """ValueError for a concrete coordinate with NaN (or lo > hi, or a negative error)."""
    if isinstance(x, Interval):
        ia.check_endpoints(x.lo, x.hi, what=f"extend: coordinate {i}")
    elif isinstance(x, Affine):
        if not isinstance(x.center, jax.core.Tracer) and not isinstance(x.err, jax.core.Tracer):
            if np.isnan(np.asarray(x.center)).any() or (np.asarray(x.err) < 0).any():
                raise ValueError(f"extend: coordinate {i} is an Affine form with NaN "
                                 "centre or negative error term")
    else:
        arr = np.asarray(x) if not isinstance(x, jax.core.Tracer) else None
        if arr is not None and arr.dtype.kind == "f" and np.isnan(arr).any():
            raise ValueError(f"extend: coordinate {i} contains NaN")


def _subnormal_sign(v):
    """+1 / -1 where v is a nonzero subnormal, else 0, read from the bits: XLA on CPU
    treats subnormal operands as 0 (DAZ), so arithmetic tests cannot see them."""
    if v.dtype != jnp.float32:
        return jnp.zeros(v.shape, jnp.int32)
    bits = lax.bitcast_convert_type(v, jnp.int32)
    subnormal = ((bits & 0x7F800000) == 0) & ((bits & 0x7FFFFFFF) != 0)
    return jnp.where(subnormal, jnp.where(bits < 0, -1, 1), 0)


def _flush_subnormals_outward(x: Interval) -> Interval:
    """Round subnormal endpoints outward to 0 / +-tiny (CPU XLA flushes them to 0)."""
    lo, hi = jnp.asarray(x.lo), jnp.asarray(x.hi)
    if not jnp.issubdtype(lo.dtype, jnp.floating):
        return x
    tiny = float(jnp.finfo(lo.dtype).tiny)
    s_lo, s_hi = _subnormal_sign(lo), _subnormal_sign(hi)
    lo = jnp.where(s_lo > 0, 0.0, jnp.where(s_lo < 0, -tiny, lo))
    hi = jnp.where(s_hi > 0, tiny, jnp.where(s_hi < 0, 0.0, hi))
    return Interval(lo, hi, x.defined)


def lift_coordinates(coords, arithmetic: str, outward: bool, n_symbols: int | None):
    """Coordinates (Interval, Affine or arrays) as Intervals or as Affine forms with one
    noise symbol per Interval coordinate (or `n_symbols`; given Affine forms keep theirs).
    Outward: subnormal endpoints are flushed outward and affine forms padded by an ulp
    (their midpoints and radii were rounded)."""
    if outward:
        coords = [_flush_subnormals_outward(c) if isinstance(c, Interval) else c
                  for c in coords]
    if arithmetic == "interval":
        return [as_range(c) for c in coords]
    given = [c.n for c in coords if isinstance(c, Affine)]
    if given:
        out = [aa.as_affine(c, max(given)) for c in coords]
    else:
        k = sum(isinstance(c, Interval) for c in coords)
        n = max(1, k) if n_symbols is None else int(n_symbols)
        if n < k:
            raise ValueError(f"n_symbols={n} is fewer than the {k} interval coordinates")
        out, s = [], 0
        for c in coords:
            if isinstance(c, Interval):
                out.append(aa.from_interval(c, s, n))
                s += 1
            else:
                out.append(aa.as_affine(c, n))
    return [aa.widen(c, 1.0) for c in out] if outward else out


def lift_param(p, arithmetic: str, n: int):
    """A params leaf in the arithmetic: Intervals become affine forms on the error term
    (n symbols) in affine mode, affine forms their range in interval mode."""
    if arithmetic == "affine" and isinstance(p, Interval):
        return aa.from_interval(p, None, n)
    if arithmetic == "interval" and isinstance(p, Affine):
        return aa.padded_range(p)
    return p


def _map_components(x, fn):
    """fn(array, trailing_axes) on every component of a lifted value (dev has one axis
    more: the noise symbols)."""
    if isinstance(x, Interval):
        return Interval(fn(x.lo, ()), fn(x.hi, ()), fn(x.defined, ()))
    return Affine(fn(x.center, ()), fn(x.dev, (x.n,)), fn(x.err, ()), fn(x.defined, ()))


def broadcast(x, shape):
    """A lifted value broadcast to batch shape `shape`."""
    return _map_components(x, lambda a, tail: jnp.broadcast_to(a, tuple(shape) + tail))


def reshape(x, shape):
    """A lifted value reshaped to batch shape `shape`."""
    return _map_components(x, lambda a, tail: a.reshape(tuple(shape) + tail))


def as_result(out, point_coords, arithmetic: str):
    """f's value at one point as a scalar enclosure: a constant output (f ignored the
    boxes) becomes a point (an exact affine form in affine mode, unless bool)."""
    if isinstance(out, Interval):
        return broadcast(out, ())
    if isinstance(out, Affine):
        return out
    if arithmetic == "affine" and not jnp.issubdtype(jnp.result_type(out), jnp.bool_):
        return aa.as_affine(jnp.asarray(out, jnp.float32), point_coords[0].n)
    return ia.point(out)
