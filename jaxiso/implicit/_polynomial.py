"""Polynomial f on ray pieces: the Chebyshev enclosure from point values.

Restricted to a ray, a polynomial f of total degree n in x, y, z is a polynomial of degree
at most n in the ray's parameter. On a piece s in [s0, s1] it is fixed by its values at
the n + 1 Chebyshev-Lobatto points of the piece, and its Chebyshev coefficients c_k are
a fixed linear map of those values (`chebyshev_map`, a discrete cosine transform of norm
<= 4/3). Since |T_k| <= 1, f lies in ``c_0 +- sum_{k >= 1} |c_k|`` on the piece. The
enclosure costs n + 1 point evaluations of f and one small matrix product, whatever the
number of f's terms or how f is written (expanded, factored, Horner), and it converges
quadratically with the piece's length where interval arithmetic converges linearly
(Knoll 2009, Sec. 6.2-6.3 compares IA and AA; expansions in orthogonal bases are the
classical tight enclosures of polynomials, e.g. Chebyshev models).

Point values are rounded (float32, the arithmetic's "fast" rounding): the enclosure is
padded by the map's norm times a few ulps of the largest value, and the interpolant
passes through every sampled value, so a sign change among the samples is always
enclosed.
"""

from __future__ import annotations

import functools

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np

from .._core import on_points, pytree_dataclass
from ..arith import Interval, equation_count
from ._field import BOX_OVERLAP

__all__ = ["polynomial_degree", "chebyshev_map", "chebyshev_enclosure", "MAX_DEGREE",
           "ChebyshevTable", "chebyshev_table", "TABLE_FROM"]

# The highest degree enclosed this way: a piece costs degree + 1 point evaluations of f,
# against one interval evaluation that costs about 5-10 of them; `auto` picks interval
# or affine arithmetic above it
MAX_DEGREE = 16

# Primitives that pass their operand's degree through (linear in it, structural).
_SAME = frozenset({"neg", "convert_element_type", "reduce_precision", "copy", "copy_p",
                   "broadcast_in_dim", "reshape", "squeeze", "expand_dims", "transpose",
                   "slice", "dynamic_slice", "reduce_sum", "real", "stop_gradient",
                   "optimization_barrier", "gather", "dynamic_update_slice"})
# ... and those whose result has the largest degree of their operands.
_MAX = frozenset({"add", "sub", "add_any", "concatenate", "stack", "pad"})
# Call-like primitives whose body is traced through, by the parameter holding it.
_BODIES = {"pjit": "jaxpr", "jit": "jaxpr", "closed_call": "call_jaxpr",
           "custom_jvp_call": "call_jaxpr", "custom_vjp_call": "call_jaxpr",
           "custom_vjp_call_jaxpr": "fun_jaxpr", "remat": "jaxpr", "checkpoint": "jaxpr"}


def polynomial_degree(g, w, params) -> tuple[int | None, int]:
    """(degree, length): the total degree of ``g(x, y, z, w, params)`` in x, y and z when
    g is a polynomial in them (w and params are constants: any function of them may be a
    coefficient), else None; and the equations of g's jaxpr (0 where g cannot be traced
    on scalars). Reads g's jaxpr; evaluates nothing."""
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    rest = jax.tree_util.tree_map(
        lambda v: jax.ShapeDtypeStruct(jnp.shape(v), jnp.result_type(v)), (w, params))
    try:
        closed = jax.make_jaxpr(g)(scalar, scalar, scalar, *rest)
    except Exception:  # noqa: BLE001 - not traceable on scalars: not ours to say
        return None, 0
    n_in = len(closed.jaxpr.invars)
    out = _degrees(closed, [1, 1, 1] + [0] * (n_in - 3))
    length = equation_count(closed.jaxpr)
    if out is None or len(out) != 1:
        return None, length
    return max(out[0], 0), length


# The degree of the zero polynomial (a literal 0, e.g. the start of Horner's rule in
# `jnp.polyval`): a product with it is zero, a sum takes the other operand's degree
_ZERO = -1


def _degrees(jaxpr, degrees_in):
    """The degrees of the outputs of jaxpr (or a closed jaxpr) given its inputs' (0:
    constant, `_ZERO`: zero), None when some output is not a polynomial of the inputs."""
    consts = getattr(jaxpr, "consts", [])
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    degree = {v: _constant_degree(c) for v, c in zip(jaxpr.constvars, consts)}
    degree.update(zip(jaxpr.invars, degrees_in))

    def of(v):
        if isinstance(v, jax.extend.core.Literal):
            return _constant_degree(v.val)
        return degree.get(v, 0)

    for eqn in jaxpr.eqns:
        ins = [of(v) for v in eqn.invars]
        if all(d <= 0 for d in ins):
            degree.update((v, 0) for v in eqn.outvars)
            continue
        outs = _rule(eqn, ins)
        if outs is None:
            return None
        degree.update(zip(eqn.outvars, outs))
    return [of(v) for v in jaxpr.outvars]


def _rule(eqn, ins):
    """The output degrees of one equation whose operands (degrees `ins`) are not all
    constant, or None."""
    name = eqn.primitive.name
    n_out = len(eqn.outvars)
    if name in _SAME and len(ins) >= 1 and all(d == 0 for d in ins[1:]):
        return [ins[0]] * n_out
    if name in _MAX:
        return [max(ins)] * n_out
    if name in ("mul", "dot_general"):
        return [_ZERO if _ZERO in ins else sum(ins)] * n_out
    if name == "div" and ins[1] == 0:
        return [ins[0]]
    if name == "integer_pow" and eqn.params["y"] >= 0:
        return [ins[0] * eqn.params["y"]]
    if name == "square":
        return [2 * ins[0]]
    if name == "reduce_prod":  # a product of as many factors as the axes hold
        shape = eqn.invars[0].aval.shape
        return [ins[0] * int(np.prod([shape[a] for a in eqn.params["axes"]]))]
    if name == "pow" and ins[1] == 0:  # x ** 2.0: a literal whole exponent
        y = eqn.invars[1]
        y = getattr(y, "val", None) if isinstance(y, jax.extend.core.Literal) else None
        if y is not None and np.ndim(y) == 0 and float(y).is_integer() and y >= 0:
            return [ins[0] * int(y)]
    if name == "select_n" and ins[0] == 0:  # a choice fixed by constants only
        return [max(ins[1:])]
    if name == "scan":
        return _scan_degrees(eqn, ins)
    body = eqn.params.get(_BODIES.get(name, ""))
    if body is not None:
        return _degrees(body, ins)
    return None


def _constant_degree(value) -> int:
    """`_ZERO` for a scalar zero (a literal, or a constant a jit hoisted), else 0."""
    try:
        return _ZERO if np.ndim(value) == 0 and float(value) == 0.0 else 0
    except (TypeError, ValueError):  # a tracer or something not numeric
        return 0


def _scan_degrees(eqn, ins):
    """A scan's output degrees (`jnp.polyval` is one: Horner's rule over the
    coefficients): its body run on degrees once per iteration, the stacked outputs
    taking the largest degree of any iteration; None past degree 1,000 (not ours)."""
    body = eqn.params["jaxpr"]
    n_consts, n_carry = eqn.params["num_consts"], eqn.params["num_carry"]
    consts, carry, xs = ins[:n_consts], ins[n_consts:n_consts + n_carry], ins[n_consts + n_carry:]
    ys = None
    for _ in range(eqn.params["length"]):
        out = _degrees(body, consts + carry + xs)
        if out is None or max(out, default=0) > 1000:
            return None
        carry = out[:n_carry]
        ys = out[n_carry:] if ys is None else [max(a, b) for a, b in zip(ys, out[n_carry:])]
    return carry + (ys if ys is not None else [0] * (len(eqn.outvars) - n_carry))


@functools.cache
def chebyshev_map(n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(nodes [n + 1], M [n + 1, n + 1], norm): a polynomial of degree <= n on [0, 1]
    whose values at the Chebyshev-Lobatto nodes are v is ``sum_k (M v)_k T_k(2u - 1)``;
    norm is M's infinity norm (1 to 4/3 for n <= 30: the map is a discrete cosine
    transform).
    Computed in float64."""
    angles = np.pi * np.arange(n + 1) / n
    nodes = 0.5 * (1.0 - np.cos(angles))
    basis = np.cos(np.outer(np.pi - angles, np.arange(n + 1)))  # T_k(2 u_j - 1) [j, k]
    M = np.linalg.inv(basis)
    return nodes, M, float(np.abs(M).sum(axis=1).max())


# The value rounding covered by the pad, in ulps of the largest sampled value (f's own
# rounding and the matrix product's, which adds n + 1 products)
_VALUE_ULPS = 16.0


def chebyshev_enclosure(g, degree: int, p, D, s0, s1, w, params) -> Interval:
    """An Interval [...] holding g on the pieces ``p + D s``, s in [s0, s1] (p, D:
    [..., 3]; s0, s1: [...]) for g a polynomial of total degree `degree` in x, y, z:
    ``c_0 +- sum_{k >= 1} |c_k|`` of its Chebyshev coefficients on the piece."""
    n = max(int(degree), 1)
    nodes, M, norm = chebyshev_map(n)
    # the nodes on the leading axis: the map is one [n + 1, n + 1] x [n + 1, ...] product
    # and the sums run across whole rows of pieces (2x faster on the CPU than [..., n + 1])
    node = jnp.asarray(nodes, jnp.float32).reshape((n + 1,) + (1,) * s0.ndim)
    s = s0 + (s1 - s0) * node                                           # [n + 1, ...]
    q = p + D * s[..., None]                                            # [n + 1, ..., 3]
    v = on_points(g)(q[..., 0], q[..., 1], q[..., 2], w, params)        # [n + 1, ...]
    c = jnp.tensordot(jnp.asarray(M, jnp.float32), v, axes=1)           # [n + 1, ...]
    pad = (norm * (_VALUE_ULPS + n + 1) * 2.0**-24) * jnp.max(jnp.abs(v), axis=0)
    # the sample points are rounded by up to BOX_OVERLAP of their coordinates (as
    # `_field.ray_boxes` pads its boxes): a shift du along the piece (in its [-1, 1]
    # units) moves the series by at most du sum k^2 |c_k| (Markov's inequality)
    speed = jnp.linalg.norm(D, axis=-1)
    reach = jnp.linalg.norm(p, axis=-1) + speed * jnp.maximum(jnp.abs(s0), jnp.abs(s1))
    length = speed * jnp.abs(s1 - s0)
    du = 2.0 * BOX_OVERLAP * reach / jnp.maximum(length, jnp.finfo(jnp.float32).tiny)
    a = jnp.abs(c[1:])
    k2 = jnp.asarray(np.arange(1, n + 1) ** 2, jnp.float32).reshape((n,) + (1,) * s0.ndim)
    spread = jnp.sum(a, axis=0) + pad + jnp.minimum(du, 2.0) * jnp.sum(k2 * a, axis=0)
    return Interval(c[0] - spread, c[0] + spread)


# A polynomial f of at least this many jaxpr equations is traced through its Chebyshev
# table (`chebyshev_table`) instead of its own code: every copy of f in a render (the
# enclosure's values, the verification's points, Newton steps, normals) is then a few
# small matrix products whatever f's length. Measured (benchmarks/NOTES.md, session 29):
# with f's own code a generated polynomial's first picture at 64^2 grew ~15 ms per
# equation (8 x 150, 1,056 equations: 20.3 s).
TABLE_FROM = 256


@pytree_dataclass
class ChebyshevTable:
    """A polynomial of degree n on the box [lo, hi] as its Chebyshev coefficients:
    ``f(x) = sum_{i + j + k <= n} coeffs[i, j, k] T_i(u_x) T_j(u_y) T_k(u_z)``, u the
    coordinates mapped from [lo, hi] onto [-1, 1].

    Attributes:
      coeffs: [n + 1, n + 1, n + 1] float32 (zero where i + j + k > n).
      lo, hi: [3] float32 the box.
    """

    coeffs: jax.Array
    lo: jax.Array
    hi: jax.Array

    def __call__(self, x, y, z, w=None, params=None):
        """f at points x, y, z (scalars, or arrays of one shape) as a point field
        ``g(x, y, z, w, params)`` (w and params are ignored: they are in the table)."""
        n = self.coeffs.shape[0] - 1
        tx, ty, tz = (_chebyshev_values(2.0 * (c - self.lo[i]) / (self.hi[i] - self.lo[i])
                                        - 1.0, n) for i, c in enumerate((x, y, z)))
        inner = jnp.einsum("...k,ijk->...ij", tz, self.coeffs)
        return jnp.einsum("...i,...ij,...j->...", tx, inner, ty)


def _chebyshev_values(u, n: int):
    """[..., n + 1]: T_0(u) .. T_n(u) by their recurrence."""
    t = [jnp.ones_like(u), u]
    for _ in range(n - 1):
        t.append(2.0 * u * t[-1] - t[-2])
    return jnp.stack(t[:n + 1], axis=-1)


def chebyshev_table(g, degree: int, lo, hi, w, params) -> ChebyshevTable:
    """The `ChebyshevTable` of the point field g, a polynomial of total degree `degree`
    in x, y, z, on the box [lo, hi]: g at the (degree + 1)^3 Chebyshev-Lobatto points of
    the box (one batched evaluation of g), transformed along each axis. Coefficients of
    total degree over `degree` are zero in exact arithmetic and set to zero (only
    rounding is left there). Differentiable in w and params."""
    n = max(int(degree), 1)
    nodes, M, _ = chebyshev_map(n)
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    axes = lo + (hi - lo) * jnp.asarray(nodes, jnp.float32)[:, None]   # [n + 1, 3]
    X, Y, Z = jnp.meshgrid(axes[:, 0], axes[:, 1], axes[:, 2], indexing="ij")
    values = on_points(g)(X, Y, Z, w, params)                          # [n + 1]^3
    A = jnp.asarray(M, jnp.float32)
    coeffs = jnp.einsum("ai,bj,ck,ijk->abc", A, A, A, values)
    i = np.arange(n + 1)
    keep = (i[:, None, None] + i[None, :, None] + i[None, None, :]) <= n
    return ChebyshevTable(jnp.where(jnp.asarray(keep), coeffs, 0.0), lo, hi)
