"""Command line: ``jaxiso gallery`` (default) renders the catalogue of test surfaces;
``jaxiso demo`` prints interval vs affine enclosures; ``jaxiso render`` renders one scene,
on one process or on N (local processes, srun, mpirun: docs/distributed.md).

Bad arguments (unknown surface names, a negative seed, a size out of range, an output path
that is not a writable directory) are reported as argparse reports its own: usage and a
one-line error on stderr, exit status 2, before any rendering. An OSError while working
(e.g. a full disk) is one line on stderr and status 1.

Every command keeps its compiled programs on disk (`jaxiso.enable_cache`), so a second run
skips most compiling; ``--no-cache`` compiles afresh and writes nothing there.
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


def _render_scene(spec: str, size: int, iso=None, spacing=None):
    """(scene, camera, volume) for a --scene spec: implicit:NAME (the catalogue),
    volume:NAME[:N] (jaxiso.volume.data, N^3 voxels), volume:FILE (`_volume_file`),
    tets:N (an N^3 cube of Kuhn tets with a sphere's distance field). For a volume the
    scene is None and volume is (voxels, spacing [3], origin [3], iso): the caller builds
    the whole octree or only its own bricks."""
    import numpy as np

    from . import Camera, TetIsosurface, surfaces, tet_mesh
    from .tetra import data as tet_data
    from .volume import data as vol_data

    kind, _, rest = spec.partition(":")
    if kind == "implicit":
        return surfaces.scene(rest), surfaces.camera(rest, size), None
    if kind == "volume":
        if _is_volume_file(rest):
            vox, spacing, origin = _volume_file(rest, spacing)
        else:
            name, _, n = rest.partition(":")
            vox = vol_data.examples()[name](int(n or 41))
            spacing, origin = vol_data.box_geometry(vox.shape, *vol_data.DOMAINS[name])
            iso = vol_data.ISOVALUES[name]
        spacing, origin = (np.broadcast_to(np.asarray(v, np.float64), (3,))
                           for v in (spacing, origin))
        lo, hi = origin, origin + (np.asarray(vox.shape) - 1) * spacing
        mid, ext = (lo + hi) / 2, float(np.max(hi - lo))
        eye = mid + ext * np.array([1.3, 0.9, 0.7])
        cam = Camera.look_at(eye, mid, (0, 0, 1), 40.0, size)
        return None, cam, (vox, spacing, origin, iso)
    if kind == "tets":
        points, tets = tet_data.cube_tets(int(rest or 8))
        scene = TetIsosurface(tet_mesh(points, tets, tet_data.sphere_field(points)), 0.0)
        cam = Camera.look_at((1.9, 1.5, 1.3), (0.5, 0.5, 0.5), (0, 0, 1), 40.0, size)
        return scene, cam, None
    raise ValueError(f"unknown scene kind {kind!r}")


VOLUME_FILES = (".npy", ".npz", ".nii", ".nii.gz", ".vti")


def _is_volume_file(rest: str) -> bool:
    return rest.lower().endswith(VOLUME_FILES)


def _volume_file(path: str, spacing):
    """(voxels, spacing, origin) of a volume file: a .npy is memory-mapped (a process
    that renders bricks reads only its own voxels); other formats are read whole by
    `jaxiso.io.load_volume`, with the spacing and origin their headers give. `spacing`
    (the --spacing option, or None) overrides the file's."""
    import numpy as np

    from .io import load_volume

    if path.lower().endswith(".npy"):
        vox, meta = np.load(path, mmap_mode="r"), {}
    else:
        vox, meta = load_volume(path)
    if vox.ndim != 3:
        raise ValueError(f"{path}: need a 3-D volume, got shape {vox.shape}")
    spacing = spacing if spacing is not None else meta.get("spacing", 1.0)
    return vox, spacing, meta.get("origin", 0.0)


def _volume_scene(volume, bricks):
    """The whole volume's scene, or (bricks: a grid or "x") this process's bricks."""
    import numpy as np

    from . import OctreeVolume, VolumeIsosurface, distributed
    from .volume import brick_volume

    vox, spacing, origin, iso = volume
    if bricks is None:
        return VolumeIsosurface(OctreeVolume.from_array(np.asarray(vox), spacing=spacing,
                                                        origin=origin, progress=False), iso)
    grid = None if bricks == "x" else tuple(int(g) for g in bricks.split(","))
    return brick_volume(vox, iso, distributed.process_mesh("bricks"), grid=grid,
                        spacing=spacing, origin=origin)


def _bricks_note(scene, bricks) -> str:
    if bricks is None:
        return ""
    return f" in bricks {'x'.join(str(g) for g in scene.grid)}"


def _render_one(args) -> int:
    import jax
    import numpy as np

    from . import distributed, intersect, render, save_png

    if args.coordinator or args.distributed:
        distributed.initialize(args.coordinator, args.num_processes, args.process_id,
                               heartbeat_timeout_seconds=args.heartbeat)
    rank, n_proc = jax.process_index(), jax.process_count()
    mesh = distributed.process_mesh() if len(jax.devices()) > 1 else None
    scene, cam, volume = _render_scene(args.scene, args.size, args.iso, args.spacing)
    devices = mesh
    if volume is not None:
        try:
            scene = _volume_scene(volume, args.bricks)
        except ValueError as err:  # e.g. a brick grid that does not match the devices
            print(f"jaxiso render: error: {err}", file=sys.stderr)
            return 2
    if args.bricks:
        devices = None  # the data is split, not the rays
    t0 = time.perf_counter()
    img = render(scene, cam, devices=devices)
    t_render = time.perf_counter() - t0
    where = "" if mesh is None else f" over {mesh.devices.size} devices"
    held = _local_nbytes(scene)
    print(f"jaxiso render: process {rank}/{n_proc}{where}, {args.scene} "
          f"{args.size}x{args.size}{_bricks_note(scene, args.bricks)}: "
          f"{t_render:.2f} s (incl. compile), scene arrays here {held / 2**20:.2f} MiB",
          flush=True)
    if rank == 0 and args.out:
        save_png(img, args.out)
    if args.npz and (rank == 0 or "{process}" in args.npz):
        found = {}
        if args.hits:
            hits = distributed.to_host(intersect(scene, cam.rays(), devices=devices))
            found = dict(t=hits.t, hit=hits.hit, surface=hits.surface, normal=hits.normal)
        np.savez(args.npz.format(process=rank), image=np.asarray(img), scene_nbytes=held,
                 **found)
    return 0


def _local_nbytes(scene) -> int:
    """Bytes of the scene's arrays that this process's devices hold (a brick-distributed
    volume: its own bricks only)."""
    import jax

    total = 0
    for leaf in jax.tree_util.tree_leaves(scene):
        if isinstance(leaf, jax.Array):
            total += sum(s.data.nbytes for s in leaf.addressable_shards)
    return int(total)


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
    unknown = [n for n in getattr(args, "names", None) or () if n not in known]
    if unknown:
        parser.error(f"unknown surfaces: {', '.join(unknown)}; known: {', '.join(known)}")
    if args.command == "demo" and args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.command == "render":
        _check_render(args, parser)
    if args.command == "gallery":
        if not MIN_SIZE <= args.size <= MAX_SIZE:
            parser.error(f"--size must be in [{MIN_SIZE}, {MAX_SIZE}], got {args.size}")
        _check_out(args.out, parser)


def _check_render(args, parser) -> None:
    """`jaxiso render`'s arguments, before JAX starts."""
    from . import surfaces
    from .volume import data as vol_data

    kind, _, rest = args.scene.partition(":")
    name, _, n = rest.partition(":")
    known = {"implicit": surfaces.names(), "volume": list(vol_data.examples())}
    if kind == "volume" and _is_volume_file(rest):
        _check_volume_file(rest, args, parser)
        name, n, known = None, "", {}
    elif args.iso is not None or args.spacing is not None:
        parser.error("--iso and --spacing go with --scene volume:FILE")
    if kind not in ("implicit", "volume", "tets"):
        parser.error(f"--scene {args.scene}: kind must be implicit, volume or tets")
    if kind in known and name not in known[kind]:
        parser.error(f"--scene {args.scene}: unknown {kind} {name!r}; known: "
                     f"{', '.join(known[kind])}")
    count = rest if kind == "tets" else n
    if count and (not count.isdigit() or int(count) < 2):
        parser.error(f"--scene {args.scene}: the size must be an int >= 2")
    if args.bricks is not None and kind != "volume":
        parser.error("--bricks splits volumes only")
    if args.bricks not in (None, "x") and not _is_grid(args.bricks):
        parser.error(f"--bricks {args.bricks}: give a grid GX,GY,GZ of ints >= 1 "
                     "(e.g. 2,2,1), or nothing for one brick per device along x")
    if not MIN_SIZE <= args.size <= MAX_SIZE:
        parser.error(f"--size must be in [{MIN_SIZE}, {MAX_SIZE}], got {args.size}")
    given = [args.num_processes is not None, args.process_id is not None]
    if args.coordinator and not all(given):
        parser.error("--coordinator needs --num-processes and --process-id")


def _check_volume_file(path, args, parser) -> None:
    if not os.path.isfile(path):
        parser.error(f"--scene volume:{path}: no such file")
    if args.iso is None:
        parser.error(f"--scene volume:{path}: give the isovalue with --iso")
    if args.spacing is not None and not args.spacing > 0:
        parser.error(f"--spacing must be > 0, got {args.spacing}")


def _is_grid(text: str) -> bool:
    parts = text.split(",")
    return len(parts) == 3 and all(p.isdigit() and int(p) >= 1 for p in parts)


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
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--no-cache", action="store_true",
                        help="compile afresh: do not keep compiled programs on disk "
                        "(default: kept in $JAXISO_CACHE_DIR or ~/.cache/jaxiso/xla)")
    demo = sub.add_parser("demo", parents=[common],
                          help="interval vs affine enclosures on the catalogue")
    demo.add_argument("--names", nargs="*", help="surfaces to show (default: all)")
    demo.add_argument("--seed", type=int, default=0)
    gallery = sub.add_parser("gallery", parents=[common],
                             help="render the catalogue of test surfaces")
    gallery.add_argument("--out", default="gallery", help="output folder (default: gallery)")
    gallery.add_argument("--size", type=int, default=160, help="image edge in pixels")
    gallery.add_argument("--names", nargs="*", help="surfaces to render (default: all)")
    gallery.add_argument("--shadows", action="store_true", help="cast shadow rays")
    gallery.add_argument("--arithmetic", choices=("interval", "affine"),
                         help="override each surface's default arithmetic")
    one = sub.add_parser("render", parents=[common], help="render one scene, on one or N processes")
    one.add_argument("--scene", default="implicit:sphere",
                     help="implicit:NAME | volume:NAME[:N] | volume:FILE (.npy memory-mapped;"
                     " .npz, .nii[.gz], .vti) | tets:N (default implicit:sphere)")
    one.add_argument("--iso", type=float, help="isovalue of a volume:FILE scene")
    one.add_argument("--spacing", type=float,
                     help="voxel spacing of a volume:FILE scene (default: the file's, or 1)")
    one.add_argument("--size", type=int, default=256, help="image edge in pixels")
    one.add_argument("--out", default="render.png", help="PNG written by process 0")
    one.add_argument("--npz", help="image and hits (.npz) by process 0; a path with "
                     "{process} is written by every process")
    one.add_argument("--hits", action="store_true",
                     help="also store the camera rays' hits (intersect) in --npz")
    one.add_argument("--bricks", nargs="?", const="x", metavar="GX,GY,GZ",
                     help="volume only: one brick of the voxels per device, cut along x, "
                     "or a grid such as 2,2,1 (its product = the number of devices)")
    one.add_argument("--distributed", action="store_true",
                     help="join a multi-process run detected from SLURM / Open MPI")
    one.add_argument("--coordinator", help="host:port of process 0 (local processes)")
    one.add_argument("--num-processes", type=int)
    one.add_argument("--process-id", type=int)
    one.add_argument("--heartbeat", type=int, default=100,
                     help="seconds of silence after which a process counts as dead")
    args = parser.parse_args(argv)
    if args.command is None:
        args = gallery.parse_args([], argparse.Namespace(command="gallery"))
    _check(args, {"gallery": gallery, "demo": demo, "render": one}[args.command])
    if not args.no_cache:
        from ._cache import enable_cache

        enable_cache()
    try:
        return {"gallery": _gallery, "demo": _demo, "render": _render_one}[args.command](args)
    except OSError as err:  # the disk filling up, a directory removed while rendering
        print(f"jaxiso {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
