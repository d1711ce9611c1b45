"""Independent float64 numpy reference for neural implicits (issue 13): the network of a
Spelunking-layout .npz file evaluated in float64, and first hits of rays with its zero set
inside a box. Deliberately does not import jaxiso.

Network format (/work/shared/data/neural/README.md): keys ``NNNN.kind.param`` applied in
order of NNNN: ``dense.A`` [in, out] and ``dense.b`` [out] (h = h @ A + b), ``relu`` /
``elu`` activations, ``squeeze_last`` (the single output). Input (x, y, z).

First hits (`first_hits`): `reference_trace64.first_roots` (uniform samples of the
box-clipped segment, the first sign change, float64 bisection) with this evaluator; its
limitations apply (two crossings inside one sample interval are invisible).
"""

from __future__ import annotations

import hashlib
import os

import numpy as np
import reference_trace64

ACTIVATIONS64 = {
    "relu": lambda h: np.maximum(h, 0.0),
    # expm1 of the clipped value: no overflow warning for large positive h
    "elu": lambda h: np.where(h > 0.0, h, np.expm1(np.minimum(h, 0.0))),
    # log(1 + e^h) without overflow (the layout examples/fit_neural_sdf.py writes)
    "softplus": lambda h: np.logaddexp(0.0, h),
}
# points per matmul pass: [_CHUNK, width] float64 activations stay at a few MiB
_CHUNK = 2**14
SAMPLES = 4000
TOL = 1e-9  # world-space bracket width the bisection stops at


def load_npz64(path):
    """The layers of a network file: list of ("dense", A [in, out], b [out]) and
    (activation name,) in application order, all float64."""
    with np.load(os.fspath(path), allow_pickle=False) as data:
        items = {k: np.asarray(data[k]) for k in data.files}
    layers = []
    for key in sorted(items):
        _, kind, part = key.split(".")
        if kind == "dense" and part == "A":
            layers.append(("dense", items[key].astype(np.float64),
                           items[key[:-1] + "b"].astype(np.float64)))
        elif kind in ACTIVATIONS64 or kind == "squeeze_last":
            layers.append((kind,))
        elif kind != "dense":
            raise ValueError(f"{path}: unknown layer kind {kind!r} in {key!r}")
    return layers


def evaluate(layers, p):
    """The network at points p [..., 3] -> [...] float64, in chunks of points."""
    p = np.asarray(p, np.float64)
    shape = p.shape[:-1]
    flat = p.reshape(-1, 3)
    out = np.empty(flat.shape[0])
    for c in range(0, flat.shape[0], _CHUNK):
        h = flat[c:c + _CHUNK]
        for layer in layers:
            if layer[0] == "dense":
                h = h @ layer[1] + layer[2]
            elif layer[0] == "squeeze_last":
                h = h[:, 0]
            else:
                h = ACTIVATIONS64[layer[0]](h)
        out[c:c + _CHUNK] = h.reshape(-1)
    return out.reshape(shape)


def field(layers):
    """``f(x, y, z, w)`` for reference_trace64 (w unused)."""
    def f(x, y, z, w=0.0):
        x, y, z = np.broadcast_arrays(x, y, z)
        return evaluate(layers, np.stack([x, y, z], axis=-1))
    return f


def first_hits(layers, origins, directions, lo=(-1.0,) * 3, hi=(1.0,) * 3, *,
               samples=SAMPLES, tol=TOL, chunk=1024):
    """First zero crossing of each ray o + t d inside the box [lo, hi] (origins,
    directions [N, 3]; directions unit, so t is world length): t [N] float64, inf where
    none. `samples` uniform samples per clipped segment, then bisection until the bracket
    is at most `tol` long (relative bound: tol over the longest diagonal of the box)."""
    diag = float(np.linalg.norm(np.subtract(hi, lo)))
    t, _ = reference_trace64.first_roots(field(layers), lo, hi, origins, directions,
                                         eps=tol / diag, samples=samples, chunk=chunk)
    return t


def cache_key(path, origins, directions, lo, hi, samples, tol):
    """A hex digest of everything the reference depends on: the network file's bytes,
    the rays (so camera and resolution), the box and the sampling."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        h.update(fh.read())
    for a in (origins, directions, lo, hi):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    h.update(f"{samples} {tol!r} v1".encode())
    return h.hexdigest()[:16]


def cached_first_hits(path, origins, directions, cache_dir, label, lo=(-1.0,) * 3,
                      hi=(1.0,) * 3, *, samples=SAMPLES, tol=TOL):
    """`first_hits` of the network in `path`, read from / written to
    ``<cache_dir>/<label>_<key>.npz`` (`cache_key`). Returns (t [N], seconds it took,
    0 when read from the cache)."""
    key = cache_key(path, origins, directions, lo, hi, samples, tol)
    file = os.path.join(os.fspath(cache_dir), f"{label}_{key}.npz")
    return cached_array(file, lambda: first_hits(load_npz64(path), origins, directions, lo,
                                                 hi, samples=samples, tol=tol))


def cached_array(file, compute):
    """compute() -> array, read from / written to the .npz `file`. Returns (array,
    seconds compute took, 0 when read from the file)."""
    import time

    if os.path.exists(file):
        with np.load(file) as data:
            return np.asarray(data["t"]), 0.0
    t0 = time.perf_counter()
    t = compute()
    seconds = time.perf_counter() - t0
    os.makedirs(os.path.dirname(file) or ".", exist_ok=True)
    tmp = file + ".tmp.npz"  # write then rename: a killed run leaves no half file
    np.savez(tmp, t=t, seconds=seconds)
    os.replace(tmp, file)
    return t, seconds
