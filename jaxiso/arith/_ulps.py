"""Rounding-error models for `extend(..., rounding="outward")`.

A `Rule` states the rounding error of its primitive's result in ulps: a number, or a
model ``ulps(invals, params)`` when the error depends on the operands. Sums and dots also
give a `scale`: their error grows with the magnitude of the terms, not of the (possibly
cancelled) result. invals are as the rule gets them (`Interval`, `Affine` or constant
arrays, batch shape S); models return a float or an array of the result's shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _interval as ia
from ._lift import as_range, is_lifted, shape_of

# IEEE basic operations are correctly rounded: half an ulp, padded to 2.
CORRECTLY_ROUNDED = 2.0
# XLA's transcendentals: a few ulps (measured worst cases are in tests/benchmarks).
TRANSCENDENTAL = 8.0


def exp_like(invals, params):
    """XLA's float32 exp family reduces the argument in float32: its relative error grows
    like |x| ulps (the condition number of exp), measured ~8e-6 relative at x = 59."""
    m = ia.mag(as_range(invals[0]))
    return TRANSCENDENTAL + 2.0 * jnp.where(jnp.isfinite(m), m, 0.0)


def power(invals, params):
    """XLA computes x**y as exp(y log x): its error grows with |y log x| ulps."""
    x, y = as_range(invals[0]), as_range(invals[1])
    with jax.numpy_dtype_promotion("standard"):
        logs = jnp.maximum(jnp.abs(jnp.log(jnp.abs(x.lo))), jnp.abs(jnp.log(jnp.abs(x.hi))))
    logs = jnp.where(jnp.isfinite(logs), logs, 0.0)
    growth = jnp.where(jnp.isfinite(ia.mag(y)), ia.mag(y), 0.0) * logs
    return TRANSCENDENTAL + 2.0 * growth


def integer_power(invals, params) -> float:
    """Repeated squaring rounds ~log2|y| times, but each squaring doubles the relative
    error carried in, so the total is about |y| ulps (superquadric: x**500)."""
    return 2.0 * abs(int(params["y"])) + 2.0


def reduce_sum(invals, params) -> float:
    """One rounding per term added, plus the last."""
    shape = shape_of(invals[0])
    return 1.0 + float(np.prod([shape[a] for a in params["axes"]], dtype=float))


def dot_general(invals, params) -> float:
    """One rounding per product and per term added."""
    (contract, _), _ = params["dimension_numbers"]
    shape = shape_of(invals[0])
    return 2.0 + float(np.prod([shape[a] for a in contract], dtype=float))


def sum_scale(invals, params):
    """The sum of the terms' magnitudes."""
    return jnp.sum(ia.mag(as_range(invals[0])), tuple(params["axes"]))


def dot_scale(invals, params):
    """|box| . |const|: the dot of the terms' magnitudes (one operand is constant)."""
    left = is_lifted(invals[0])
    box, const = (invals[0], invals[1]) if left else (invals[1], invals[0])
    m = ia.mag(as_range(box))
    big = jnp.finfo(m.dtype).max
    m, c = jnp.minimum(m, big), jnp.abs(const).astype(m.dtype)
    return lax.dot_general(m, c, **params) if left else lax.dot_general(c, m, **params)
