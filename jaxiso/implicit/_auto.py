"""`arithmetic="auto"`: pick the cheapest arithmetic that is tight enough for a scene.

At construction the scene's f is extended in interval and in affine arithmetic and both
are evaluated on sample pieces of rays (32 pieces, 1/64 of the domain's diagonal long,
at seeded random places and directions in the box: the scale where bisection spends most
of its steps). Each enclosure's width is compared with f's true range on the piece (9
point samples, a lower bound of it). Affine costs about twice an interval evaluation per
piece, so it is chosen when its median width ratio is more than 2x smaller (networks:
interval enclosures do not shrink with the piece; polynomials: they are within 2x).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._core import concrete, on_points
from ._field import enclosure, extended, ray_boxes

N_PIECES = 32
PIECE = 2.0**-6   # of the domain's diagonal
SAMPLES = 9
COST_RATIO = 2.0  # affine / interval evaluation cost per piece


_CHOICES: dict = {}  # (f, rounding, box) -> (arithmetic, report): measure once


def choose_arithmetic(f, g, lo, hi, w, params, rounding: str) -> tuple[str, str]:
    """(arithmetic, report) for the field g (of the user's f) on the box [lo, hi].
    Measured once per f, rounding and box (the choice is a property of the function:
    later scenes with other params or w reuse it, under jit too). Traced inputs (a scene
    built under jit) cannot be measured: unless this f was measured before they get
    "affine", which converges on every f jaxiso extends, and the report says so."""
    key = None
    if concrete(lo) is not None and concrete(hi) is not None:
        key = (f, rounding, tuple(np.asarray(lo).tolist()), tuple(np.asarray(hi).tolist()))
        try:
            if key in _CHOICES:  # also under a trace: what this f got when measured
                return _CHOICES[key]
        except TypeError:  # an unhashable f: measure every time
            key = None
    leaves = [lo, hi, w] + jax.tree_util.tree_leaves(params)
    if any(concrete(x) is None for x in leaves):
        return "affine", "auto: affine (built under a trace: nothing measured)"
    choice = _measure(g, lo, hi, w, params, rounding)
    if key is not None:
        _CHOICES[key] = choice
    return choice


def _measure(g, lo, hi, w, params, rounding: str) -> tuple[str, str]:
    rng = np.random.default_rng(0)
    lo_, hi_ = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    diag = float(np.linalg.norm(hi_ - lo_))
    centre = lo_ + rng.uniform(0.1, 0.9, (N_PIECES, 3)) * (hi_ - lo_)
    direction = rng.normal(size=(N_PIECES, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    D = jnp.asarray(direction * PIECE * diag, jnp.float32)
    p = jnp.asarray(centre, jnp.float32) - 0.5 * D
    s0, s1 = jnp.zeros(N_PIECES), jnp.ones(N_PIECES)
    s = jnp.linspace(0.0, 1.0, SAMPLES)
    pts = p[:, None, :] + s[None, :, None] * D[:, None, :]
    vals = np.asarray(on_points(g)(pts[..., 0], pts[..., 1], pts[..., 2], w, params))
    true = vals.max(axis=1) - vals.min(axis=1)
    ratios = {}
    for arithmetic in ("interval", "affine"):
        F = extended(g, arithmetic, rounding)

        @jax.jit  # one compile: eager, the interpreter dispatches thousands of small ops
        def widths(p, D, w, params, F=F, arithmetic=arithmetic):
            r = enclosure(F, ray_boxes(p, D, s0, s1, arithmetic), w, params, arithmetic)
            return r.hi - r.lo

        width = np.asarray(widths(p, D, w, params), np.float64)
        ok = np.isfinite(vals).all(axis=1) & (true > 0)
        ratio = np.where(np.isfinite(width), width, np.inf)[ok] / true[ok]
        ratios[arithmetic] = float(np.median(ratio)) if ratio.size else np.inf
    ia_, af = ratios["interval"], ratios["affine"]
    pick = "affine" if ia_ > COST_RATIO * af else "interval"
    return pick, (f"auto: {pick} (median enclosure width / true range on {N_PIECES} ray "
                  f"pieces of 1/{round(1 / PIECE)} of the diagonal: interval {ia_:.3g}, "
                  f"affine {af:.3g})")
