"""Command line: ``jaxiso gallery`` (default) renders the catalogue of test surfaces;
``jaxiso demo`` prints interval vs affine enclosures.

Bad arguments (unknown surface names, a negative seed, a size out of range, an output path
that is not a writable directory) are reported as argparse reports its own: usage and a
one-line error on stderr, exit status 2, before any rendering. An OSError while working
(e.g. a full disk) is one line on stderr and status 1.
"""

from __future__ import annotations

import argparse
import os
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


def _gallery(args) -> int:
    import jax
    import numpy as np

    from . import render, save_png, surfaces
    from .render import Shading

    names = args.names or surfaces.names()
    print(f"jaxiso gallery: {len(names)} surfaces at {args.size}x{args.size} -> {args.out} "
          f"(jax {jax.__version__}, {jax.default_backend()})", flush=True)
    shading = Shading(shadows=args.shadows)
    images, t_all = [], time.perf_counter()
    for i, name in enumerate(names, 1):
        entry = surfaces.get(name)
        scene = surfaces.scene(name)
        cam = surfaces.camera(name, args.size)
        if args.arithmetic is not None:
            scene = scene.replace(arithmetic=args.arithmetic)
        t0 = time.perf_counter()
        img = render(scene, cam, shading=shading)
        dt = time.perf_counter() - t0
        path = save_png(img, os.path.join(args.out, f"{name}.png"))
        covered = float(np.mean(np.any(np.abs(img - np.asarray(shading.background)) > 1e-3,
                                       axis=-1)))
        images.append(img)
        print(f"[{i:2d}/{len(names)}] {name:<14} eps 2^{np.log2(entry.eps):.0f}  "
              f"{dt:6.2f} s (incl. compile)  coverage {covered:5.1%}  {path}", flush=True)
    sheet = _contact_sheet(images, cols=min(6, len(images)))
    path = save_png(sheet, os.path.join(args.out, "gallery.png"))
    print(f"done in {time.perf_counter() - t_all:.1f} s; contact sheet {path}")
    return 0


def _contact_sheet(images, cols: int):
    import numpy as np

    rows = -(-len(images) // cols)
    h, w = images[0].shape[:2]
    sheet = np.ones((rows * h, cols * w, 3), np.float32)
    for k, img in enumerate(images):
        r, c = divmod(k, cols)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = img
    return sheet


def _truth(c) -> str:
    from . import ia

    if bool(ia.certainly(c)):
        return "certainly true"
    if bool(ia.is_false(c)):
        return "certainly false"
    return "unknown"


# gallery image edge in pixels: below 8 the contact sheet is unreadable, above 8192 one
# image is 67M rays (minutes on a GPU, hours on a CPU) and its buffers some GiB
MIN_SIZE, MAX_SIZE = 8, 8192


def _check(args, parser) -> None:
    """Exit through `parser.error` (status 2) on the first bad argument of `args`."""
    from . import surfaces

    known = surfaces.names()
    unknown = [n for n in args.names or () if n not in known]
    if unknown:
        parser.error(f"unknown surfaces: {', '.join(unknown)}; known: {', '.join(known)}")
    if args.command == "demo" and args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.command == "gallery":
        if not MIN_SIZE <= args.size <= MAX_SIZE:
            parser.error(f"--size must be in [{MIN_SIZE}, {MAX_SIZE}], got {args.size}")
        _check_out(args.out, parser)


def _check_out(out: str, parser) -> None:
    """`out` is (made) a writable directory; checked up front so that a bad path fails
    before minutes of rendering, not at the first image written."""
    if os.path.exists(out) and not os.path.isdir(out):
        parser.error(f"--out {out}: not a directory")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as err:
        parser.error(f"--out {out}: cannot create the directory ({err.strerror or err})")
    if not os.access(out, os.W_OK | os.X_OK):
        parser.error(f"--out {out}: the directory is not writable")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxiso", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    demo = sub.add_parser("demo", help="interval vs affine enclosures on the catalogue")
    demo.add_argument("--names", nargs="*", help="surfaces to show (default: all)")
    demo.add_argument("--seed", type=int, default=0)
    gallery = sub.add_parser("gallery", help="render the catalogue of test surfaces")
    gallery.add_argument("--out", default="gallery", help="output folder (default: gallery)")
    gallery.add_argument("--size", type=int, default=160, help="image edge in pixels")
    gallery.add_argument("--names", nargs="*", help="surfaces to render (default: all)")
    gallery.add_argument("--shadows", action="store_true", help="cast shadow rays")
    gallery.add_argument("--arithmetic", choices=("interval", "affine"),
                         help="override each surface's default arithmetic")
    args = parser.parse_args(argv)
    if args.command is None:
        args = gallery.parse_args([], argparse.Namespace(command="gallery"))
    _check(args, {"gallery": gallery, "demo": demo}[args.command])
    try:
        return {"gallery": _gallery, "demo": _demo}[args.command](args)
    except OSError as err:  # the disk filling up, a directory removed while rendering
        print(f"jaxiso {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
