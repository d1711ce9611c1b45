"""Seeded random networks whose activations are written in several spellings (issue 28,
the generality suite): the same function written with `jax.nn`, by hand in jax.numpy
(``where``, ``maximum``, ``exp``, ``log``) and as an equinox module, so that tests and
benchmarks can check that every way of writing a network draws the same surface, as fast.

A network is signed-distance-like: ``f(p) = |p| - RADIUS + mlp(p)``, a sphere's distance
plus a multilayer perceptron (`depth` hidden layers of `width` neurons, weights drawn from
a numpy seed) whose last layer is scaled so that ``|mlp| <= AMPLITUDE`` on 4,096 samples
of the box [-1, 1]^3 (centred there): its zero set is a bumpy sphere inside the box.

Activations (`ACTIVATIONS`) and their spellings (`spellings_of`; every activation has
"jax.nn", "jnp" and "equinox"):

* relu: ``jax.nn.relu``; ``jnp.maximum(h, 0)``; "jnp.where": ``jnp.where(h > 0, h, 0)``
* elu: ``jax.nn.elu``; ``jnp.where(h > 0, h, jnp.exp(jnp.minimum(h, 0)) - 1)``
* leaky_relu (slope 0.01): ``jax.nn.leaky_relu``; ``jnp.maximum(h, 0.01 * h)``
* softplus: ``jax.nn.softplus``; ``jnp.log(1 + jnp.exp(h))``
* softplus_t8 (temperature 8): ``jax.nn.softplus(8 h) / 8``; ``jnp.logaddexp(8 h, 0) / 8``
* sin (SIREN, frequency OMEGA): ``jnp.sin(OMEGA * h)``; ``jnp.sin(h)`` with OMEGA folded
  into the layer's weights (exact: OMEGA is a power of two)
* tanh: ``jax.nn.tanh``; ``1 - 2 / (1 + jnp.exp(2 h))``
* gelu (tanh form, jax.nn's default): ``jax.nn.gelu``; its formula with ``jnp.tanh``
* silu: ``jax.nn.silu``; ``h / (1 + jnp.exp(-h))``
* layer_norm (then relu): ``jax.nn.standardize``; mean and variance in jax.numpy;
  ``eqx.nn.LayerNorm`` (no weight or bias)

"equinox" is a module called as ``f(x, y, z)`` that holds its weights (an
``eqx.nn.MLP`` with the jax.nn activation, a custom module for layer_norm);
"equinox.partition" is the same module split with ``eqx.partition`` into
``f(x, y, z, params)`` and its array leaves (the way docs/neural_and_programs.md shows);
"equinox.params" passes the whole module as params, ``f(x, y, z, module)`` (its
activation is a leaf too, not an array). Equinox is imported only when one of them is
asked for. The other spellings are ``f(x, y, z, params)`` with ``params`` a list of
``{"A": [in, out], "b": [out]}``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ACTIVATIONS", "SPELLINGS", "RandomNet", "Spelled", "random_net", "spell",
           "spellings_of", "RADIUS", "AMPLITUDE", "OMEGA", "TEMPERATURE", "SLOPE",
           "NORM_EPS"]

RADIUS = 0.55
AMPLITUDE = 0.2
OMEGA = 4.0  # SIREN's frequency
TEMPERATURE = 8.0
SLOPE = 0.01  # jax.nn.leaky_relu's default
NORM_EPS = 1e-5  # layer norm's epsilon (jax.nn.standardize's and eqx.nn.LayerNorm's)
GELU_C = math.sqrt(2.0 / math.pi)
WIDTHS = (16, 32, 64, 128)


def _layer_norm_relu(h):
    return jax.nn.relu(jax.nn.standardize(h, epsilon=NORM_EPS))


def _layer_norm_relu_jnp(h):
    c = h - jnp.mean(h)
    return jnp.maximum(c / jnp.sqrt(jnp.mean(c * c) + NORM_EPS), 0.0)


# activation -> spelling -> the activation of a layer's pre-activations h [width]
_SPELLED: dict[str, dict[str, Callable]] = {
    "relu": {"jax.nn": jax.nn.relu, "jnp": lambda h: jnp.maximum(h, 0.0),
             "jnp.where": lambda h: jnp.where(h > 0, h, 0.0)},
    "elu": {"jax.nn": jax.nn.elu,
            "jnp": lambda h: jnp.where(h > 0, h, jnp.exp(jnp.minimum(h, 0.0)) - 1.0)},
    "leaky_relu": {"jax.nn": jax.nn.leaky_relu, "jnp": lambda h: jnp.maximum(h, SLOPE * h)},
    "softplus": {"jax.nn": jax.nn.softplus, "jnp": lambda h: jnp.log(1.0 + jnp.exp(h))},
    "softplus_t8": {"jax.nn": lambda h: jax.nn.softplus(TEMPERATURE * h) / TEMPERATURE,
                    "jnp": lambda h: jnp.logaddexp(TEMPERATURE * h, 0.0) / TEMPERATURE},
    "sin": {"jax.nn": lambda h: jnp.sin(OMEGA * h), "jnp": jnp.sin},  # jnp: OMEGA folded
    "tanh": {"jax.nn": jax.nn.tanh, "jnp": lambda h: 1.0 - 2.0 / (1.0 + jnp.exp(2.0 * h))},
    "gelu": {"jax.nn": jax.nn.gelu,
             "jnp": lambda h: 0.5 * h * (1.0 + jnp.tanh(GELU_C * (h + 0.044715 * h**3)))},
    "silu": {"jax.nn": jax.nn.silu, "jnp": lambda h: h / (1.0 + jnp.exp(-h))},
    "layer_norm": {"jax.nn": _layer_norm_relu, "jnp": _layer_norm_relu_jnp},
}
ACTIVATIONS = tuple(_SPELLED)
EQUINOX = ("equinox", "equinox.partition", "equinox.params")
SPELLINGS = ("jax.nn", "jnp", "jnp.where") + EQUINOX


def spellings_of(activation: str) -> tuple[str, ...]:
    """The spellings an activation has, in `SPELLINGS` order."""
    _check(activation, ACTIVATIONS, "activation")
    own = set(_SPELLED[activation]) | set(EQUINOX)
    return tuple(s for s in SPELLINGS if s in own)


def _check(value, choices, what):
    if value not in choices:
        raise ValueError(f"unknown {what} {value!r}; choose from {', '.join(choices)}")


@dataclasses.dataclass(frozen=True, eq=False)
class RandomNet:
    """One random network, independent of how it is spelled.

    Attributes:
      activation: a name in `ACTIVATIONS`.
      seed: the numpy seed it was drawn from.
      layers: ``((A [in, out], b [out]), ...)`` float32 numpy arrays; the activation acts
        between layers (not after the last); for "sin" it is ``sin(OMEGA * h)``, for
        "layer_norm" relu of the standardized h.
    """

    activation: str
    seed: int
    layers: tuple

    @property
    def depth(self) -> int:
        return len(self.layers) - 1

    @property
    def width(self) -> int:
        return int(self.layers[0][0].shape[1])

    @property
    def name(self) -> str:
        return f"{self.activation} {self.depth}x{self.width} seed {self.seed}"


class Spelled(typing.NamedTuple):
    """A network in one spelling: ``ImplicitSurface(f, lo, hi, params=params)``.

    ``point(x, y, z, params)`` calls f with or without params (for code that always
    passes them)."""

    net: RandomNet
    spelling: str
    f: Callable
    params: object

    def point(self, x, y, z, params):
        return self.f(x, y, z) if _no_params(self.params) else self.f(x, y, z, params)


def _no_params(params):
    return isinstance(params, tuple) and not params


def _sphere(x, y, z):
    return jnp.sqrt(x * x + y * y + z * z) - RADIUS


def _mlp(act, params, p):
    h = p
    for i, layer in enumerate(params):
        if i:
            h = act(h)
        h = h @ layer["A"] + layer["b"]
    return h[0]


def _draw(rng, activation, dims):
    """Unscaled layers [(A, b)] float64 for the activation (gains keep h near unit size)."""
    layers = []
    for i, (n_in, n_out) in enumerate(zip(dims[:-1], dims[1:])):
        if activation == "sin":  # SIREN's uniform init, frequency OMEGA taken out
            c = 1.5 if i == 0 else math.sqrt(6.0 / n_in)
            A = rng.uniform(-c, c, (n_in, n_out)) / OMEGA
            b = rng.uniform(-0.5, 0.5, n_out) / OMEGA
        else:
            gain = 1.2 if activation in ("tanh", "layer_norm") else math.sqrt(2.0)
            A = rng.normal(size=(n_in, n_out)) * gain / math.sqrt(n_in)
            b = rng.normal(size=n_out) * 0.1
        layers.append((A, b))
    return layers


def random_net(seed: int, activation: str, depth: int | None = None,
               width: int | None = None) -> RandomNet:
    """A random network: `depth` hidden layers (default: drawn in 2..8) of `width`
    neurons (default: drawn from 16, 32, 64, 128), weights from ``default_rng(seed)``;
    the last layer is scaled and shifted so that the network's output spans at most
    +-AMPLITUDE around 0 on 4,096 uniform samples of [-1, 1]^3 (the same seed gives the
    same network)."""
    _check(activation, ACTIVATIONS, "activation")
    rng = np.random.default_rng(seed)
    depth = int(rng.integers(2, 9)) if depth is None else int(depth)
    width = int(rng.choice(WIDTHS)) if width is None else int(width)
    if depth < 1 or width < 1:
        raise ValueError(f"depth and width must be >= 1, got {depth}, {width}")
    layers = _draw(rng, activation, [3] + [width] * depth + [1])
    p = jnp.asarray(rng.uniform(-1.0, 1.0, (4096, 3)), jnp.float32)
    params = [{"A": jnp.asarray(A, jnp.float32), "b": jnp.asarray(b, jnp.float32)}
              for A, b in layers]
    v = np.asarray(jax.jit(jax.vmap(functools.partial(_mlp, _SPELLED[activation]["jax.nn"],
                                                      params)))(p), np.float64)
    centre = 0.5 * (v.max() + v.min())
    scale = AMPLITUDE / max(0.5 * (v.max() - v.min()), 1e-12)
    A, b = layers[-1]
    layers[-1] = (A * scale, (b - centre) * scale)
    return RandomNet(activation, int(seed), tuple(
        (np.asarray(A, np.float32), np.asarray(b, np.float32)) for A, b in layers))


def _params(net, fold=1.0):
    """The layers as a params list; `fold` multiplies every layer but the last."""
    last = len(net.layers) - 1
    return [{"A": jnp.asarray(A * (1.0 if i == last else fold)),
             "b": jnp.asarray(b * (1.0 if i == last else fold))}
            for i, (A, b) in enumerate(net.layers)]


def spell(net: RandomNet, spelling: str) -> Spelled:
    """The network in one of `spellings_of(net.activation)`."""
    _check(spelling, spellings_of(net.activation), f"spelling of {net.activation}")
    if spelling.startswith("equinox"):
        return _equinox(net, spelling)
    act = _SPELLED[net.activation][spelling]
    fold = OMEGA if (net.activation, spelling) == ("sin", "jnp") else 1.0

    def f(x, y, z, params):
        return _sphere(x, y, z) + _mlp(act, params, jnp.stack([x, y, z]))
    return Spelled(net, spelling, f, _params(net, fold))


@functools.cache
def _equinox_classes():
    """The equinox module classes (defined on first use: equinox is optional)."""
    import equinox as eqx

    class NormedMLP(eqx.Module):
        """Linear -> LayerNorm -> relu, ..., Linear to a scalar."""
        linears: tuple
        norms: tuple

        def __call__(self, p):
            h = p
            for linear, norm in zip(self.linears[:-1], self.norms):
                h = jax.nn.relu(norm(linear(h)))
            return self.linears[-1](h)

    class SphereNet(eqx.Module):
        """|p| - radius + mlp(p), called as f(x, y, z)."""
        mlp: eqx.Module
        radius: float

        def __call__(self, x, y, z):
            return (jnp.sqrt(x * x + y * y + z * z) - self.radius
                    + self.mlp(jnp.stack([x, y, z])))

    return eqx, NormedMLP, SphereNet


def _equinox_mlp(eqx, NormedMLP, net):
    """net's layers in an eqx.nn.MLP (or NormedMLP for layer_norm), weights copied."""
    key = jax.random.PRNGKey(net.seed)
    if net.activation == "layer_norm":
        keys = jax.random.split(key, net.depth + 1)
        dims = [3] + [net.width] * net.depth + ["scalar"]
        mlp = NormedMLP(tuple(eqx.nn.Linear(a, b, key=k)
                              for a, b, k in zip(dims[:-1], dims[1:], keys)),
                        tuple(eqx.nn.LayerNorm(net.width, NORM_EPS, use_weight=False,
                                               use_bias=False) for _ in range(net.depth)))
        linears = lambda m: m.linears
    else:
        mlp = eqx.nn.MLP(3, "scalar", net.width, net.depth,
                         activation=_SPELLED[net.activation]["jax.nn"], key=key)
        linears = lambda m: m.layers
    for i, (A, b) in enumerate(net.layers):
        mlp = eqx.tree_at(lambda m, i=i: (linears(m)[i].weight, linears(m)[i].bias), mlp,
                          (jnp.asarray(A.T), jnp.asarray(b)))
    return mlp


def _equinox(net, spelling):
    eqx, NormedMLP, SphereNet = _equinox_classes()
    module = SphereNet(_equinox_mlp(eqx, NormedMLP, net), RADIUS)
    if spelling == "equinox":
        return Spelled(net, spelling, module, ())
    if spelling == "equinox.params":
        return Spelled(net, spelling, lambda x, y, z, m: m(x, y, z), module)
    arrays, static = eqx.partition(module, eqx.is_array)

    def f(x, y, z, params):
        return eqx.combine(params, static)(x, y, z)
    return Spelled(net, spelling, f, arrays)
