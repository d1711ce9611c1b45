"""Command line: ``jaxiso demo`` (default) shows the inclusion arithmetic at work.

The renderer (``jaxiso gallery``) arrives with the ray tracing layer; until then the
main job demonstrates `extend` on the seed's test surfaces.
"""

from __future__ import annotations

import argparse
import sys
import time


def _demo(args) -> int:
    import jax
    import numpy as np

    from . import extend, ia, interval, surfaces
    from .arith import aa

    print(f"jaxiso demo: interval vs reduced affine enclosures (jax {jax.__version__}, "
          f"{jax.default_backend()})")
    rng = np.random.default_rng(args.seed)
    names = args.names or surfaces.names()
    header = f"{'surface':<14}{'box':>34}  {'interval':>26}  {'affine':>26}"
    print(header)
    print("-" * len(header))
    for name in names:
        s = surfaces.get(name)
        lo, hi = np.array(s.lo), np.array(s.hi)
        centre = lo + rng.uniform(0.2, 0.8, 3) * (hi - lo)
        half = 0.02 * (hi - lo)
        boxes = [interval(c - h, c + h) for c, h in zip(centre, half)]
        f = lambda x, y, z, s=s: s.f(x, y, z, s.w)  # noqa: E731
        t0 = time.perf_counter()
        iv = extend(f, "interval")(*boxes)
        af = aa.to_interval(extend(f, "affine")(*boxes))
        jax.block_until_ready((iv.lo, af.lo))
        box = "x".join(f"[{c - h:.2f},{c + h:.2f}]" for c, h in zip(centre, half))
        print(f"{name:<14}{box:>34}  [{float(iv.lo):>11.4g},{float(iv.hi):>11.4g}]  "
              f"[{float(af.lo):>11.4g},{float(af.hi):>11.4g}]"
              f"  ({time.perf_counter() - t0:.2f}s)")
    x = interval(-1.0, 2.0)
    print("\nthree-valued logic: [-1, 2] < 0 ->", _truth(ia.lt(x, 0.0)),
          "; [-1, 2] < 3 ->", _truth(ia.lt(x, 3.0)))
    print("division by an interval holding 0: 1 / [-1, 2] ->",
          f"[{float(ia.div(1.0, x).lo)}, {float(ia.div(1.0, x).hi)}]")
    sq = ia.sqrt(x)
    print("sqrt([-1, 2]) drops the negative part:",
          f"[{float(sq.lo):.4f}, {float(sq.hi):.4f}], defined={bool(sq.defined)}")
    return 0


def _truth(c) -> str:
    from . import ia

    if bool(ia.certainly(c)):
        return "certainly true"
    if bool(ia.is_false(c)):
        return "certainly false"
    return "unknown"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxiso", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    demo = sub.add_parser("demo", help="interval vs affine enclosures on the catalogue")
    demo.add_argument("--names", nargs="*", help="surfaces to show (default: all)")
    demo.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.command in (None, "demo"):
        if args.command is None:
            args = demo.parse_args([])
        return _demo(args)
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
