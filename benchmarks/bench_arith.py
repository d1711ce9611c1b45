"""Box evaluations per second and enclosure tightness of interval vs reduced affine
arithmetic on the seed's Table B.1 surfaces.

    python benchmarks/bench_arith.py [--log2-batch 16] [--repeats 5] [--names ...]

For each surface: a batch of 2^16 random boxes inside its domain (edge lengths 2^-2 ..
2^-10 of the domain, log-uniform), evaluated by ``jit(extend(f, arithmetic, rounding))``.
Compile time (first call) is reported apart from run time (median of `repeats` calls,
each ``block_until_ready``). Tightness: on the first 1024 boxes, the enclosure width
divided by the width of the range sampled densely (9^3 grid points per box, float64 numpy
evaluation of the surface), so 1.0 is exact and larger is looser. Writes
``benchmarks/results/arith_<device>.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji
from jaxiso.arith import Interval

ROOT = pathlib.Path(__file__).resolve().parent
MODES = [("interval", "fast"), ("affine", "fast"), ("interval", "outward"),
         ("affine", "outward")]


def make_boxes(surface, n, rng, min_log2=2.0, max_log2=10.0):
    lo, hi = np.array(surface.lo), np.array(surface.hi)
    edge = (hi - lo) * 2.0 ** -rng.uniform(min_log2, max_log2, size=(n, 1))
    start = lo + rng.uniform(size=(n, 3)) * (hi - lo - edge)
    return start.astype(np.float32), (start + edge).astype(np.float32)


def sampled_range(surface, blo, bhi, per_axis=9):
    """Dense float64 sampling of f on each box: a lower bound of the true range."""
    sys.path.insert(0, str(ROOT.parent / "tests"))
    import reference64

    f64 = reference64.SURFACES[surface.name]
    t = np.linspace(0.0, 1.0, per_axis)
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    lo64, hi64 = blo.astype(np.float64), bhi.astype(np.float64)
    pts = lo64[:, None, :] + g[None] * (hi64 - lo64)[:, None, :]
    with np.errstate(all="ignore"):
        v = f64(pts[..., 0], pts[..., 1], pts[..., 2], surface.w)
    return np.nanmin(v, axis=1), np.nanmax(v, axis=1)


def time_mode(surface, arithmetic, rounding, blo, bhi, repeats):
    f = lambda x, y, z: surface.f(x, y, z, surface.w)
    F = ji.extend(f, arithmetic, rounding)

    def run(a, b):
        out = F(*[Interval(a[:, i], b[:, i]) for i in range(3)])
        return ji.aa.to_interval(out) if arithmetic == "affine" else out

    fn = jax.jit(run)
    a, b = jnp.asarray(blo), jnp.asarray(bhi)
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(a, b))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(a, b))
        times.append(time.perf_counter() - t0)
    return out, compile_s, statistics.median(times)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--log2-batch", type=int, default=16)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--tight-boxes", type=int, default=1024)
    p.add_argument("--names", nargs="*", default=None)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)

    n = 2**args.log2_batch
    device = jax.devices()[0]
    names = args.names or ji.surfaces.names()
    rng = np.random.default_rng(0)
    rows = []
    print(f"jax {jax.__version__} on {device.device_kind} ({platform.processor() or 'cpu'}),"
          f" batch {n} boxes, median of {args.repeats}; plan: none (flat batches of box "
          f"evaluations, no rays)")
    hdr = (f"{'surface':<14}{'mode':<18}{'compile s':>10}{'run ms':>9}{'Mbox/s':>8}"
           f"{'width/true mean':>16}{'median':>8}{'hits 0':>8}")
    print(hdr)
    print("-" * len(hdr))
    for name in names:
        s = ji.surfaces.get(name)
        blo, bhi = make_boxes(s, n, rng)
        k = min(args.tight_boxes, n)
        true_lo, true_hi = sampled_range(s, blo[:k], bhi[:k])
        true_w = true_hi - true_lo
        for arithmetic, rounding in MODES:
            out, c_s, r_s = time_mode(s, arithmetic, rounding, blo, bhi, args.repeats)
            lo, hi = np.asarray(out.lo[:k], np.float64), np.asarray(out.hi[:k], np.float64)
            ok = (true_w > 0) & np.isfinite(true_w)
            ratio = (hi - lo)[ok] / true_w[ok]
            finite = np.isfinite(ratio)
            contains0 = float(np.mean((np.asarray(out.lo) <= 0) & (np.asarray(out.hi) >= 0)))
            row = dict(surface=name, arithmetic=arithmetic, rounding=rounding,
                       boxes=n, compile_s=c_s, run_s=r_s, boxes_per_s=n / r_s,
                       width_ratio_mean=float(np.mean(ratio[finite])) if finite.any() else None,
                       width_ratio_median=float(np.median(ratio[finite])) if finite.any() else None,
                       unbounded_fraction=float(1 - finite.mean()) if ratio.size else None,
                       contains_zero_fraction=contains0,
                       sampled_outside=int(np.sum((lo > true_lo + 1e-5 * np.abs(true_lo))
                                                  | (hi < true_hi - 1e-5 * np.abs(true_hi)))))
            rows.append(row)
            mean = row["width_ratio_mean"]
            med = row["width_ratio_median"]
            print(f"{name:<14}{arithmetic + '/' + rounding:<18}{c_s:>10.2f}{r_s * 1e3:>9.2f}"
                  f"{n / r_s / 1e6:>8.2f}{mean if mean is not None else float('nan'):>16.3f}"
                  f"{med if med is not None else float('nan'):>8.3f}{contains0:>8.3f}")
    result = dict(benchmark="arith", jax_version=jax.__version__, backend=jax.default_backend(),
                  device_kind=device.device_kind, platform=platform.platform(),
                  python=platform.python_version(), batch=n, repeats=args.repeats,
                  tightness_boxes=args.tight_boxes, plan=None, rows=rows,
                  box_edges="2^-uniform(2,10) of the domain edge")
    out_path = pathlib.Path(args.out) if args.out else (
        ROOT / "results" / f"arith_{jax.default_backend()}.json")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=1))
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
