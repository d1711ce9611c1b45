"""`extend(..., "affine", fresh_symbols=k)` over every registered primitive (issue 28):
no crash where a constant lifted with one noise symbol meets a form that took fresh ones
(``jnp.logaddexp(8 * h, 0) / 8`` raised "mixing affine forms with 1 and 67 noise
symbols"), and sound against float64 numpy at points sampled in the boxes.

Each case applies a primitive to vectors of forms (so that fresh symbols are handed out)
with constants on either side; a coverage test requires a case (or a stated reason) for
every primitive in the rule registry."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from boxes import assert_encloses
from jax import lax
from jax.extend import core as jcore

import jaxiso as ji
from jaxiso.arith._rules import NAMED_CALLS, RULES

W = 4  # vector width: nonlinear vector equations take fresh symbols
_rng = np.random.default_rng(28)
M1 = _rng.dirichlet(np.ones(3), size=W)  # rows >= 0 summing to 1: M @ p in [0, 1]
M2 = _rng.dirichlet(np.ones(3), size=W)
WEIGHTS = np.linspace(0.5, -0.7, W)
GATHER = np.array([2, 0, 3, 3])
DOMAINS = {"any": (-2.0, 2.0), "pos": (0.2, 2.0), "unit": (-0.9, 0.9), "ge1": (1.1, 3.0)}


def _vectors(xp, p, domain):
    """h, h2: two vectors of W values affine in the point p (entries in the domain)."""
    lo, hi = DOMAINS[domain]
    f32 = (lambda a: jnp.asarray(a, jnp.float32)) if xp is jnp else (lambda a: a)
    return (lo + (hi - lo) * (f32(M1) @ p), lo + (hi - lo) * (f32(M2) @ p))


def _c(domain):
    lo, hi = DOMAINS[domain]
    return np.linspace(lo + 0.1 * (hi - lo), hi - 0.2 * (hi - lo), W).astype(np.float32)


_erf64 = np.vectorize(math.erf)


def _grad_sin_t(xp, h):  # d/dt sin(t) t: jax.grad's transpose sums with add_any
    return xp.cos(h) * h + xp.sin(h)


# name: (domain, jax fn(h, h2, c), float64 numpy fn(h, h2, c)); both vectors -> any shape
CASES = {
    "add": ("any", lambda h, h2, c: (h + c, c + h, h + h2), None),
    "sub": ("any", lambda h, h2, c: (h - c, c - h, h - h2), None),
    "mul": ("any", lambda h, h2, c: (h * c, c * h, h * h2), None),
    "div": ("pos", lambda h, h2, c: (h / c, c / h, h / h2, h / 8), None),
    "neg": ("any", lambda h, h2, c: -h, None),
    "max": ("any", lambda h, h2, c: (jnp.maximum(h, c), jnp.maximum(c, h), jnp.maximum(h, 0.0),
                                     jnp.maximum(h, h2)),
            lambda h, h2, c: (np.maximum(h, c), np.maximum(c, h), np.maximum(h, 0.0),
                              np.maximum(h, h2))),
    "min": ("any", lambda h, h2, c: (jnp.minimum(h, c), jnp.minimum(c, h), jnp.minimum(h, h2)),
            lambda h, h2, c: (np.minimum(h, c), np.minimum(c, h), np.minimum(h, h2))),
    "clamp": ("any", lambda h, h2, c: lax.clamp(np.float32(-0.5), h, np.float32(0.7)),
              lambda h, h2, c: np.clip(h, -0.5, 0.7)),
    "abs": ("any", lambda h, h2, c: jnp.abs(h - c), lambda h, h2, c: np.abs(h - c)),
    "sign": ("any", lambda h, h2, c: jnp.sign(h - c) * h, lambda h, h2, c: np.sign(h - c) * h),
    "floor": ("any", lambda h, h2, c: jnp.floor(2 * h) + h,
              lambda h, h2, c: np.floor(2 * h) + h),
    "ceil": ("any", lambda h, h2, c: jnp.ceil(c - 2 * h), lambda h, h2, c: np.ceil(c - 2 * h)),
    "round": ("any", lambda h, h2, c: jnp.round(3 * h), lambda h, h2, c: np.round(3 * h)),
    "rem": ("pos", lambda h, h2, c: (jnp.fmod(h, c), jnp.fmod(c, h)),
            lambda h, h2, c: (np.fmod(h, c), np.fmod(c, h))),
    "square": ("any", lambda h, h2, c: jnp.square(h - c), lambda h, h2, c: np.square(h - c)),
    "integer_pow": ("any", lambda h, h2, c: (h ** 3, (c - h) ** 4, h ** -2 + 0 * c),
                    lambda h, h2, c: (h ** 3, (c - h) ** 4, h ** -2.0)),
    "pow": ("pos", lambda h, h2, c: (h ** 2.5, c ** h, h ** h2), None),
    "sqrt": ("pos", lambda h, h2, c: (jnp.sqrt(h), jnp.sqrt(h * c)),
             lambda h, h2, c: (np.sqrt(h), np.sqrt(h * c))),
    "rsqrt": ("pos", lambda h, h2, c: lax.rsqrt(h + c), lambda h, h2, c: 1 / np.sqrt(h + c)),
    "cbrt": ("any", lambda h, h2, c: jnp.cbrt(h - c), lambda h, h2, c: np.cbrt(h - c)),
    "exp": ("any", lambda h, h2, c: jnp.exp(h) * c, lambda h, h2, c: np.exp(h) * c),
    "exp2": ("any", lambda h, h2, c: jnp.exp2(c - h), lambda h, h2, c: np.exp2(c - h)),
    "expm1": ("any", lambda h, h2, c: jnp.expm1(h) + c, lambda h, h2, c: np.expm1(h) + c),
    "log": ("pos", lambda h, h2, c: jnp.log(h) - c, lambda h, h2, c: np.log(h) - c),
    "log1p": ("pos", lambda h, h2, c: jnp.log1p(h - 0.2), lambda h, h2, c: np.log1p(h - 0.2)),
    "sin": ("any", lambda h, h2, c: jnp.sin(c * h), lambda h, h2, c: np.sin(c * h)),
    "cos": ("any", lambda h, h2, c: jnp.cos(h + c), lambda h, h2, c: np.cos(h + c)),
    "tan": ("unit", lambda h, h2, c: jnp.tan(h), lambda h, h2, c: np.tan(h)),
    "tanh": ("any", lambda h, h2, c: jnp.tanh(2 * h), lambda h, h2, c: np.tanh(2 * h)),
    "atan": ("any", lambda h, h2, c: jnp.arctan(h), lambda h, h2, c: np.arctan(h)),
    "atan2": ("any", lambda h, h2, c: (jnp.arctan2(h, c), jnp.arctan2(c, h)),
              lambda h, h2, c: (np.arctan2(h, c), np.arctan2(c, h))),
    "sinh": ("any", lambda h, h2, c: jnp.sinh(h), lambda h, h2, c: np.sinh(h)),
    "cosh": ("any", lambda h, h2, c: jnp.cosh(h), lambda h, h2, c: np.cosh(h)),
    "asin": ("unit", lambda h, h2, c: jnp.arcsin(h), lambda h, h2, c: np.arcsin(h)),
    "acos": ("unit", lambda h, h2, c: jnp.arccos(h), lambda h, h2, c: np.arccos(h)),
    "atanh": ("unit", lambda h, h2, c: jnp.arctanh(h), lambda h, h2, c: np.arctanh(h)),
    "asinh": ("any", lambda h, h2, c: jnp.arcsinh(h), lambda h, h2, c: np.arcsinh(h)),
    "acosh": ("ge1", lambda h, h2, c: jnp.arccosh(h), lambda h, h2, c: np.arccosh(h)),
    "logistic": ("any", lambda h, h2, c: jax.nn.sigmoid(h),
                 lambda h, h2, c: 1 / (1 + np.exp(-h))),
    "erf": ("any", lambda h, h2, c: jax.scipy.special.erf(h), lambda h, h2, c: _erf64(h)),
    "select_n": ("any", lambda h, h2, c: (jnp.where(h > c, h, c * h2), jnp.where(c < h, 1.0, h),
                                          jnp.where(h >= h2, 0.0, 1.0) * h),
                 lambda h, h2, c: (np.where(h > c, h, c * h2), np.where(c < h, 1.0, h),
                                   np.where(h >= h2, 0.0, 1.0) * h)),
    "logic": ("any", lambda h, h2, c: jnp.where(((h > c) & ~(h2 <= 0.3)) | (h == h2) | (h != c),
                                                h - h2, c),
              lambda h, h2, c: np.where(((h > c) & ~(h2 <= 0.3)) | (h == h2) | (h != c),
                                        h - h2, c)),
    "convert": ("any", lambda h, h2, c: h.astype(jnp.float16).astype(jnp.float32) * c,
                lambda h, h2, c: h.astype(np.float16).astype(np.float64) * c),
    "reduce_precision": ("any", lambda h, h2, c: lax.reduce_precision(h, 5, 10) + c,
                         lambda h, h2, c: h.astype(np.float16).astype(np.float64) + c),
    "reductions": ("any", lambda h, h2, c: (jnp.sum(h * c), jnp.max(h), jnp.min(h2 - c),
                                            h @ np.outer(c, c).astype(np.float32)),
                   lambda h, h2, c: (np.sum(h * c), np.max(h), np.min(h2 - c), h @ np.outer(c, c))),
    "data": ("any", lambda h, h2, c: (jnp.concatenate([h, c]), h[::-1] * c, h[1:3],
                                      lax.dynamic_slice(h, (1,), (2,)), h[GATHER] - c,
                                      jnp.pad(h, (1, 2), constant_values=0.5),
                                      h.reshape(2, 2).T, h.reshape(1, W).squeeze(0),
                                      h[None, :] * c[:, None], lax.optimization_barrier(h),
                                      jnp.copy(h), jnp.real(h), jnp.expand_dims(h, 0),
                                      jnp.stack([h, c])),
             lambda h, h2, c: (np.concatenate([h, c]), h[::-1] * c, h[1:3], h[1:3],
                               h[GATHER] - c, np.pad(h, (1, 2), constant_values=0.5),
                               h.reshape(2, 2).T, h, h[None, :] * c[:, None], h, h, h,
                               h[None], np.stack([h, c]))),
    "add_any": ("any", lambda h, h2, c: jax.vmap(jax.grad(lambda t: jnp.sin(t) * t))(h) * c,
                lambda h, h2, c: _grad_sin_t(np, h) * c),
    # library functions with rules of their own (NAMED_CALLS)
    "elu": ("any", lambda h, h2, c: jax.nn.elu(h - c), lambda h, h2, c: np.where(
        h - c > 0, h - c, np.expm1(np.minimum(h - c, 0.0)))),
    "softplus": ("any", lambda h, h2, c: jax.nn.softplus(3 * h),
                 lambda h, h2, c: np.logaddexp(3 * h, 0.0)),
    "silu": ("any", lambda h, h2, c: jax.nn.silu(4 * h - c),
             lambda h, h2, c: (4 * h - c) / (1.0 + np.exp(c - 4 * h))),
    "hypot": ("any", lambda h, h2, c: jnp.hypot(h, c), lambda h, h2, c: np.hypot(h, c)),
    "floor_divide": ("any", lambda h, h2, c: (h // 0.25, h // c),
                     lambda h, h2, c: (np.floor_divide(h, 0.25), np.floor_divide(h, c))),
    "trunc": ("any", lambda h, h2, c: jnp.trunc(3 * h), lambda h, h2, c: np.trunc(3 * h)),
    # compositions with constants on either side
    "softplus_temperature": ("any", lambda h, h2, c: jnp.logaddexp(8 * h, 0) / 8,
                             lambda h, h2, c: np.logaddexp(8 * h, 0) / 8),
    "compositions": ("any", lambda h, h2, c: (c / (1 + jnp.exp(-h)), 2 - h * c,
                                              (c - h) ** 2 / 3, jnp.where(c > h, c, h - h2),
                                              jnp.exp(jnp.minimum(h, 0)) - 1, 1 / (3 + h)),
                     lambda h, h2, c: (c / (1 + np.exp(-h)), 2 - h * c, (c - h) ** 2 / 3,
                                       np.where(c > h, c, h - h2),
                                       np.exp(np.minimum(h, 0)) - 1, 1 / (3 + h))),
}

# registered primitives that a user's jnp code does not emit in this jax version
NOT_EMITTED = {"copy_p": "jnp.copy emits 'copy'", "stack": "jnp.stack concatenates",
               "real": "jnp.real of a float is the identity",
               "expand_dims": "jnp.expand_dims broadcasts (broadcast_in_dim)"}


def _flatten(out):
    return out if isinstance(out, tuple) else (out,)


def _program(case, xp):
    domain, fn, ref = CASES[case]
    fn = fn if xp is jnp else (ref if ref is not None else fn)
    c = _c(domain)
    c = c if xp is jnp else c.astype(np.float64)

    def f(x, y, z):
        p = xp.stack([x, y, z])
        h, h2 = _vectors(xp, p, domain)
        return sum(xp.sum(xp.asarray(o))
                   * (1.0 + 0.25 * k) for k, o in enumerate(_flatten(fn(h, h2, c))))

    return f


def _primitives(jaxpr, seen):
    for eqn in jaxpr.eqns:
        seen.add(eqn.primitive.name)
        if eqn.params.get("name") in NAMED_CALLS:
            seen.add(eqn.params["name"])
        for v in eqn.params.values():
            for sub in (v if isinstance(v, (tuple, list)) else (v,)):
                if isinstance(sub, jcore.ClosedJaxpr):
                    _primitives(sub.jaxpr, seen)
                elif isinstance(sub, jcore.Jaxpr):
                    _primitives(sub, seen)
    return seen


def test_every_registered_primitive_has_a_case():
    """A primitive added to the registry needs a case here (or a reason it is not
    emitted): the cases' jaxprs must reach every registered rule."""
    seen = set()
    for case in CASES:
        s = jax.ShapeDtypeStruct((), jnp.float32)
        _primitives(jax.make_jaxpr(_program(case, jnp))(s, s, s).jaxpr, seen)
    missing = (set(RULES) | set(NAMED_CALLS)) - seen - set(NOT_EMITTED)
    assert not missing, f"registered primitives without a fresh-symbol case: {missing}"


def _boxes(rng, n=6):
    size = 2.0 ** -rng.uniform(0, 8, size=(n, 1))
    size[0] = 0.0  # a point box
    lo = rng.uniform(0, 1, size=(n, 3)) * (1 - size)
    return lo.astype(np.float32), np.maximum((lo + size).astype(np.float32), lo.astype(np.float32))


# Each case compiles its own affine program (2-4 s on 2 cores): the cases where a
# constant meets a form (and the where-join) run by default, the rest are marked heavy.
DEFAULT = ("div", "mul", "max", "select_n", "softplus_temperature", "elu")


@pytest.mark.parametrize("case", [c if c in DEFAULT else pytest.param(c, marks=pytest.mark.heavy)
                                  for c in sorted(CASES)])
def test_fresh_symbols_no_crash_and_sound(case):
    """Fresh symbols (a different count per case) with constants on either side: the
    enclosure (outward rounding) holds the float64 value at points in each box."""
    k = 1 + (sum(map(ord, case)) % 3) * 8  # 1, 9 or 17
    rng = np.random.default_rng(sum(map(ord, case)))
    blo, bhi = _boxes(rng)
    F = jax.jit(ji.extend(_program(case, jnp), "affine", "outward", fresh_symbols=k))
    out = ji.aa.to_interval(F(*[ji.Interval(jnp.asarray(blo[:, i]), jnp.asarray(bhi[:, i]))
                                for i in range(3)]))
    t = rng.uniform(size=(len(blo), 16, 3))
    t[:, 0], t[:, 1] = 0.0, 1.0
    pts = blo[:, None].astype(np.float64) + t * (bhi - blo)[:, None].astype(np.float64)
    ref = _program(case, np)
    vals = np.array([[ref(*pt) for pt in row] for row in pts])
    assert_encloses(out.lo, out.hi, vals, f"{case} fresh_symbols={k}")
