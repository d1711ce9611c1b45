"""Neural implicits: multilayer perceptrons as plain-JAX scalar functions.

`load_mlp` reads the `.npz` layout of the sample networks of "Spelunking the Deep"
(Sharp & Jacobson 2022; keys ``NNNN.kind.param`` applied in order of ``NNNN``):
``dense.A`` [in, out] and ``dense.b`` [out] for ``h = h @ A + b``, ``relu`` / ``elu``
activations, and ``squeeze_last`` for the single output. The input is ``(x, y, z)``.

The result is an `MLP`: ``f(x, y, z, params)`` written point by point (``h @ A + b``,
``jax.nn.relu``), with the weights as ``params`` (a list of ``{"A", "b"}``) so they can
be trained and differentiated through `ImplicitSurface(..., params=...)`.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["MLP", "load_mlp", "ACTIVATIONS"]

ACTIVATIONS = {"relu": jax.nn.relu, "elu": jax.nn.elu, "softplus": jax.nn.softplus,
               "tanh": jnp.tanh, "sigmoid": jax.nn.sigmoid, "silu": jax.nn.silu,
               "gelu": jax.nn.gelu, "sin": jnp.sin}


@dataclasses.dataclass(frozen=True, eq=False)  # identity hash: a scene's static f
class MLP:
    """``f(x, y, z, params)``: dense layers with `activation` between them (none after
    the last), one scalar output.

    Attributes:
      activation: a name in `ACTIVATIONS`.
      params: the weights read from the file, ``[{"A": [in, out], "b": [out]}, ...]``.
    """

    activation: str
    params: list

    def __call__(self, x, y, z, params):
        act = ACTIVATIONS[self.activation]
        h = jnp.stack([x, y, z])
        for i, layer in enumerate(params):
            if i:
                h = act(h)
            h = h @ layer["A"] + layer["b"]
        return h[0]

    @property
    def lipschitz(self) -> float:
        """An upper bound on the Lipschitz constant of `params`' network (product of the
        layers' spectral norms; relu, elu, tanh, sin are 1-Lipschitz, sigmoid 1/4)."""
        slope = {"sigmoid": 0.25, "silu": 1.1, "gelu": 1.13}.get(self.activation, 1.0)
        norms = [float(np.linalg.norm(np.asarray(p["A"], np.float64), 2)) for p in self.params]
        return float(np.prod(norms) * slope ** (len(norms) - 1))


def load_mlp(path: str | os.PathLike) -> MLP:
    """Read a Spelunking-layout `.npz` network (format: module docstring).

    Raises ValueError naming the key for an unknown layer kind, a mix of activations,
    shapes that do not chain (3 inputs, one output) or NaN / infinite weights."""
    with np.load(os.fspath(path), allow_pickle=False) as data:
        items = {k: np.asarray(data[k]) for k in data.files}
    layers, acts = [], set()
    for key in sorted(items):
        parts = key.split(".")
        if len(parts) != 3:
            raise ValueError(f"{path}: key {key!r} is not NNNN.kind.param")
        _, kind, part = parts
        if kind == "dense":
            if part == "A":
                layers.append((key, items[key], items.get(key[:-1] + "b")))
            elif part != "b":
                raise ValueError(f"{path}: unknown dense parameter {key!r}")
        elif kind in ACTIVATIONS:
            acts.add(kind)
        elif kind != "squeeze_last":
            raise ValueError(f"{path}: unknown layer kind {kind!r} in key {key!r} "
                             f"(known: dense, squeeze_last, {', '.join(ACTIVATIONS)})")
    if len(acts) > 1:
        raise ValueError(f"{path}: mixed activations {sorted(acts)} are not supported")
    params, width = [], 3
    for key, A, b in layers:
        if b is None:
            raise ValueError(f"{path}: {key!r} has no matching bias {key[:-1] + 'b'!r}")
        if A.ndim != 2 or A.shape[0] != width or b.shape != (A.shape[1],):
            raise ValueError(f"{path}: {key!r} has shape {A.shape} and its bias {b.shape}; "
                             f"expected [{width}, out] and [out]")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise ValueError(f"{path}: {key!r} or its bias holds NaN or infinite weights")
        params.append({"A": jnp.asarray(A, jnp.float32), "b": jnp.asarray(b, jnp.float32)})
        width = A.shape[1]
    if not params or width != 1:
        raise ValueError(f"{path}: the network must end in one output, got {width}")
    return MLP(acts.pop() if acts else "relu", params)
