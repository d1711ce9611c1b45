"""Float64 numpy references for programs (independent of jaxiso's tape code).

`vm64(ops, x, y, z)` interprets a `VMProgram`'s ``ops`` tuple in float64 numpy, freeing
each value after its last use (`vm64_points`: the same on flat points in chunks, so that a
program with hundreds of live values stays small on a million points); `first_inside64`
casts rays by dense sampling: the first sample inside the solid f < 0 within the box.
"""

import numpy as np

_BIN = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide,
        "min": np.minimum, "max": np.maximum}
_UN = {"neg": np.negative, "abs": np.abs, "square": np.square, "sqrt": np.sqrt,
       "exp": np.exp, "ln": np.log, "sin": np.sin, "cos": np.cos}


def vm64(ops, x, y, z):
    last = {}
    for k, (op, args) in enumerate(ops):
        if op != "const" and not op.startswith("var"):
            for a in args:
                last[a] = k
    vals = {}
    coords = (x, y, z)
    for k, (op, args) in enumerate(ops):
        if op == "const":
            v = np.float64(args[0])
        elif op.startswith("var"):
            v = coords[args[0]]
        else:
            a = [vals[i] for i in args]
            with np.errstate(all="ignore"):
                v = _BIN[op](*a) if op in _BIN else _UN[op](*a)
            for i in set(args):
                if last[i] == k:
                    del vals[i]
        vals[k] = v
    return np.broadcast_to(vals[len(ops) - 1], np.broadcast(x, y, z).shape)


def vm64_points(ops, x, y, z, chunk=65536):
    """`vm64` on flat points [N] (numpy float64), `chunk` points at a time: [N]."""
    x, y, z = (np.asarray(v, np.float64).reshape(-1) for v in (x, y, z))
    return np.concatenate([vm64(ops, x[k:k + chunk], y[k:k + chunk], z[k:k + chunk])
                           for k in range(0, x.size, chunk)])


def first_inside64(ops, origin, direction, lo, hi, samples=1024, chunk=256):
    """(hit, t) per ray [N] ([N, 3] origins and unit directions): the centre of the first
    of `samples` equal pieces of the ray's segment in the box whose centre has f < 0."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(direction, np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        a, b = (lo - o) * inv, (hi - o) * inv
    t0 = np.maximum(np.nanmax(np.minimum(a, b), axis=1), 0.0)
    t1 = np.nanmin(np.maximum(a, b), axis=1)
    hit = np.zeros(len(o), bool)
    t = np.full(len(o), np.inf)
    for s in range(0, len(o), chunk):
        sl = slice(s, s + chunk)
        ts = t0[sl, None] + (t1 - t0)[sl, None] * (np.arange(samples) + 0.5) / samples
        p = o[sl, None] + ts[..., None] * d[sl, None]
        neg = (vm64(ops, p[..., 0], p[..., 1], p[..., 2]) < 0) & (t1 > t0)[sl, None]
        hit[sl] = neg.any(axis=1)
        t[sl] = np.where(hit[sl], ts[np.arange(len(ts)), np.argmax(neg, axis=1)], np.inf)
    return hit, t
