"""Activations spelled with jnp.where against their jax.nn rules, in affine arithmetic.

A random MLP (3 coordinates -> DEPTH x WIDTH -> 1) is extended with ``ji.extend(f,
"affine")`` (AF1, and with fresh symbols as the sign grid uses them) and evaluated on
random small boxes; the table gives the median width of the enclosure per spelling
(smaller is tighter) and its ratio to the jax.nn spelling. CPU, a few seconds.

    python benchmarks/bench_affine_where.py [--boxes 256] [--size 0.02]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji

DEPTH, WIDTH = 3, 32


def network(act, seed=0, depth=DEPTH, width=WIDTH):
    rng = np.random.default_rng(seed)
    sizes = [3] + [width] * depth + [1]
    layers = [(jnp.asarray(rng.normal(size=(a, b)) / np.sqrt(a), jnp.float32),
               jnp.asarray(rng.normal(size=b) * 0.3, jnp.float32))
              for a, b in zip(sizes[:-1], sizes[1:])]

    def f(x, y, z):
        h = jnp.stack([x, y, z])
        for w, b in layers[:-1]:
            h = act(h @ w + b)
        w, b = layers[-1]
        return (h @ w + b)[0]

    return f


def _huber_min(a, m):
    return m * (a - 0.5 * m)


SPELLINGS = {
    "elu": {
        "jax.nn.elu": jax.nn.elu,
        "where(h > 0, h, exp(min(h, 0)) - 1)":
            lambda h: jnp.where(h > 0, h, jnp.exp(jnp.minimum(h, 0)) - 1),
        "where(h > 0, h, expm1(h))": lambda h: jnp.where(h > 0, h, jnp.expm1(h)),
    },
    "relu": {
        "jax.nn.relu": jax.nn.relu,
        "where(h > 0, h, 0)": lambda h: jnp.where(h > 0, h, 0.0),
    },
    "leaky_relu": {
        "jax.nn.leaky_relu": lambda h: jax.nn.leaky_relu(h, 0.01),
        "where(h > 0, h, 0.01 h)": lambda h: jnp.where(h > 0, h, 0.01 * h),
    },
    "clamp": {
        "jnp.clip(h, -1, 1)": lambda h: jnp.clip(h, -1.0, 1.0),
        "where(h > 1, 1, where(h < -1, -1, h))":
            lambda h: jnp.where(h > 1, 1.0, jnp.where(h < -1, -1.0, h)),
    },
    "huber": {
        "m = min(|h|, 1); m (|h| - m / 2)":
            lambda h: _huber_min(jnp.abs(h), jnp.minimum(jnp.abs(h), 1.0)),
        "where(|h| < 1, h^2 / 2, |h| - 1/2)":
            lambda h: jnp.where(jnp.abs(h) < 1, 0.5 * h * h, jnp.abs(h) - 0.5),
    },
}


def widths(f, boxes, fresh):
    F = jax.jit(ji.extend(f, "affine", fresh_symbols=fresh))
    out = ji.aa.to_interval(F(*boxes))
    return np.asarray(out.hi, np.float64) - np.asarray(out.lo, np.float64)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=256)
    ap.add_argument("--size", type=float, default=0.02, help="box edge (domain [-1, 1]^3)")
    ap.add_argument("--fresh", type=int, default=64, help="fresh symbols of the 2nd column")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rng = np.random.default_rng(1)
    lo = rng.uniform(-1, 1 - args.size, size=(3, args.boxes)).astype(np.float32)
    boxes = [ji.Interval(jnp.asarray(lo[i]), jnp.asarray(lo[i] + np.float32(args.size)))
             for i in range(3)]
    rows = []
    print(f"{DEPTH} x {WIDTH} MLP, {args.boxes} boxes of edge {args.size}: median width")
    print(f"{'activation':<11} {'spelling':<42} {'AF1':>9} {'ratio':>6} "
          f"{'fresh ' + str(args.fresh):>9} {'ratio':>6}")
    for act, spellings in SPELLINGS.items():
        ref = None
        for name, fn in spellings.items():
            f = network(fn)
            w0 = float(np.median(widths(f, boxes, 0)))
            w1 = float(np.median(widths(f, boxes, args.fresh)))
            ref = ref or (w0, w1)
            rows.append(dict(activation=act, spelling=name, af1=w0, fresh=w1))
            print(f"{act:<11} {name:<42} {w0:9.4g} {w0 / ref[0]:6.2f} {w1:9.4g} "
                  f"{w1 / ref[1]:6.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(jax=jax.__version__, device=jax.devices()[0].device_kind,
                           boxes=args.boxes, size=args.size, fresh=args.fresh, rows=rows),
                      fh, indent=1)


if __name__ == "__main__":
    main()
