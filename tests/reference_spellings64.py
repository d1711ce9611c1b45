"""Independent float64 numpy reference for the generated networks of the spelling suite
(jaxiso/implicit/spellings.py, issue 28): ``f(p) = |p| - radius + mlp(p)`` evaluated in
float64 from the network's float32 weights, and the first hits of rays with its zero set
inside a box. Deliberately does not import jaxiso: the caller passes the weights, the
activation's name and the generator's constants (`constants`).

First hits (`first_hits`): `reference_trace64.first_roots` (uniform samples of the
box-clipped segment, the first sign change, float64 bisection) with this evaluator; its
limitations apply (two crossings inside one sample interval are invisible).
"""

from __future__ import annotations

import hashlib
import math
import os

import numpy as np
import reference_neural64
import reference_trace64

SAMPLES = 1000
TOL = 1e-7  # world-space bracket width the bisection stops at
_CHUNK = 2**13  # points per pass: [_CHUNK, 128] float64 activations stay at 8 MiB
CONSTANTS = ("RADIUS", "OMEGA", "TEMPERATURE", "SLOPE", "NORM_EPS")


def constants(module):
    """{name: float} of the generator module's constants this reference needs."""
    return {k: float(getattr(module, k)) for k in CONSTANTS}


def _softplus(h):
    return np.logaddexp(0.0, h)


def _layer_norm_relu(h, eps):
    c = h - h.mean(axis=-1, keepdims=True)
    return np.maximum(c / np.sqrt((c * c).mean(axis=-1, keepdims=True) + eps), 0.0)


def activation64(name, k):
    """The activation `name` on float64 arrays [points, width] (k: the constants)."""
    c = math.sqrt(2.0 / math.pi)
    table = {
        "relu": lambda h: np.maximum(h, 0.0),
        "elu": lambda h: np.where(h > 0.0, h, np.expm1(np.minimum(h, 0.0))),
        "leaky_relu": lambda h: np.where(h >= 0.0, h, k["SLOPE"] * h),
        "softplus": _softplus,
        "softplus_t8": lambda h: _softplus(k["TEMPERATURE"] * h) / k["TEMPERATURE"],
        "sin": lambda h: np.sin(k["OMEGA"] * h),
        "tanh": np.tanh,
        "gelu": lambda h: 0.5 * h * (1.0 + np.tanh(c * (h + 0.044715 * h**3))),
        "silu": lambda h: h * 0.5 * (1.0 + np.tanh(0.5 * h)),  # h * sigmoid(h)
        "layer_norm": lambda h: _layer_norm_relu(h, k["NORM_EPS"]),
    }
    return table[name]


def evaluate(activation, layers, k, p):
    """f at points p [..., 3] -> [...] float64. layers: ((A [in, out], b [out]), ...)."""
    act = activation64(activation, k)
    p = np.asarray(p, np.float64)
    flat = p.reshape(-1, 3)
    out = np.empty(flat.shape[0])
    weights = [(np.asarray(A, np.float64), np.asarray(b, np.float64)) for A, b in layers]
    for c0 in range(0, flat.shape[0], _CHUNK):
        q = flat[c0:c0 + _CHUNK]
        h = q
        for i, (A, b) in enumerate(weights):
            if i:
                h = act(h)
            h = h @ A + b
        out[c0:c0 + _CHUNK] = np.sqrt((q * q).sum(axis=1)) - k["RADIUS"] + h[:, 0]
    return out.reshape(p.shape[:-1])


def first_hits(activation, layers, k, origins, directions, lo=(-1.0,) * 3, hi=(1.0,) * 3,
               *, samples=SAMPLES, tol=TOL):
    """First zero crossing of each ray o + t d inside the box (origins, directions
    [N, 3], directions unit): t [N] float64, inf where none."""
    def f(x, y, z, w=0.0):
        x, y, z = np.broadcast_arrays(x, y, z)
        with np.errstate(over="ignore"):
            return evaluate(activation, layers, k, np.stack([x, y, z], axis=-1))

    diag = float(np.linalg.norm(np.subtract(hi, lo)))
    t, _ = reference_trace64.first_roots(f, lo, hi, origins, directions, eps=tol / diag,
                                         samples=samples, chunk=1024)
    return t


def cached_first_hits(activation, layers, k, origins, directions, cache_dir, label,
                      lo=(-1.0,) * 3, hi=(1.0,) * 3, *, samples=SAMPLES, tol=TOL):
    """`first_hits`, read from / written to ``<cache_dir>/<label>_<key>.npz`` (key: a
    digest of the weights, activation, constants, rays, box and sampling). Returns
    (t [N], seconds it took, 0 when read from the cache)."""
    h = hashlib.sha256(f"{activation} {sorted(k.items())} {samples} {tol!r} v1".encode())
    for a in [w for layer in layers for w in layer] + [origins, directions, lo, hi]:
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    file = os.path.join(os.fspath(cache_dir), f"{label}_{h.hexdigest()[:16]}.npz")
    return reference_neural64.cached_array(file, lambda: first_hits(
        activation, layers, k, origins, directions, lo, hi, samples=samples, tol=tol))
