"""Time to the first picture (issue 29): a FRESH Python process per scene kind imports
jax and jaxiso, builds the scene, renders it once (tracing and compiling included) and
then renders it `--frames` more times (the steady frame). Each kind runs as

  no cache  the process a user starts today (no `ji.enable_cache`; skipped by --quick),
  cold      `ji.enable_cache(dir)` with an empty folder (what the cache costs to fill),
  warm      a second process on the same folder (what the cache saves).

Scenes (--kinds):
  blob    the README's first example (a quartic blob, arithmetic "auto") at 256^2
  fox     "Spelunking the Deep"'s fox network (8 x 32 ReLU) at 128^2, from
          /work/shared/data/neural/fox.npz (--data; skipped, said so, when absent)
  volume  `jaxiso.volume.data.mixing(--voxels)` as an octree at 256^2
  tets    `jaxiso.tetra.data.cube_tets(--tets)` (6 n^3 tets) with a wave field at 256^2

Figures per process: import_s (Python start of this script to jax + jaxiso imported),
build_s (data made, scene built), first_render_s (first `ji.render`, block_until_ready),
first_picture_s (their sum: this script's start to the first image), frame_s (median of
the later renders) and wall_s (the whole process, as its parent saw it). Targets
(issue 29, cold cache): blob under 4 s, fox under 10 s; warm under half of cold.
Writes <out>/first_picture_<backend>.json and first_picture_<backend>.png.

    python benchmarks/bench_first_picture.py [--quick] [--kinds blob fox volume tets]
        [--frames 5] [--voxels 128] [--tets 18] [--out benchmarks/results]

On a machine shared with other jobs, every figure here moves with their load: compare
rows of one run, and look at the load average printed in the header.
"""

import time

T0 = time.perf_counter()  # a child's clock starts before jax is imported

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pathlib  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
KINDS = ("blob", "fox", "volume", "tets")
SIZES = {"blob": 256, "fox": 128, "volume": 256, "tets": 256}
TARGETS_S = {"blob": 4.0, "fox": 10.0}  # cold cache; warm: half of these
MODES = ("no cache", "cold", "warm")


# ------------------------------------------------------------------------------ scenes


def blob_scene(ji, size, args):
    """The README's first example."""
    def blob(x, y, z, w, params):
        return x**4 + y**4 + z**4 - params["r"] ** 4 + w * x * y * z

    scene = ji.ImplicitSurface(blob, lo=(-1.5,) * 3, hi=(1.5,) * 3, params={"r": 1.0},
                               isovalues=(0.0,), w=0.0, eps=2.0**-11)
    return scene, ji.Camera.look_at(eye=(4, 3, 2.5), target=(0, 0, 0), up=(0, 0, 1),
                                    fov=35, width=size, height=size)


def fox_scene(ji, size, args):
    """The fox network as bench_neural.py frames it (y up)."""
    from jaxiso.implicit import load_mlp

    net = load_mlp(pathlib.Path(args.data) / "fox.npz")
    scene = ji.ImplicitSurface(net, lo=(-1.0,) * 3, hi=(1.0,) * 3, params=net.params,
                               eps=2.0**-10)
    return scene, ji.Camera.look_at((3.0, 0.8, 1.2), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 35.0,
                                    size, size)


def volume_scene(ji, size, args):
    """The mixing layer at time 2 on --voxels^3, at the interface between the fluids."""
    from jaxiso.volume import data

    voxels = data.mixing(args.voxels, time=2.0)
    spacing, origin = data.box_geometry(voxels.shape, *data.DOMAINS["mixing"])
    vol = ji.OctreeVolume.from_array(voxels, spacing=spacing, origin=origin, progress=False)
    scene = ji.VolumeIsosurface(vol, data.ISOVALUES["mixing"])
    return scene, ji.Camera.look_at((1.9, -1.0, 1.45), (0.5, 0.5, 0.45), (0, 0, 1), 36.0,
                                    size, size)


def tets_scene(ji, size, args):
    """A wave field's zero set on cube_tets(--tets)."""
    from jaxiso.tetra import data

    points, tets = data.cube_tets(args.tets)
    mesh = ji.tet_mesh(points, tets, data.wave_field(points))
    return ji.TetIsosurface(mesh, 0.0), ji.Camera.look_at((1.9, 1.5, 1.3), (0.5, 0.5, 0.5),
                                                          (0, 0, 1), 40.0, size, size)


SCENES = {"blob": blob_scene, "fox": fox_scene, "volume": volume_scene, "tets": tets_scene}


# ------------------------------------------------------------------------------ child


def child(args):
    """One fresh process: the figures of one kind and mode, as a dict."""
    import jax

    import jaxiso as ji

    t_import = time.perf_counter()
    if args.cache:
        ji.enable_cache(args.cache)
    scene, camera = SCENES[args.child](ji, args.size, args)
    t_build = time.perf_counter()
    jax.block_until_ready(ji.render(scene, camera))
    t_first = time.perf_counter()
    frames = []
    for _ in range(args.frames):
        t = time.perf_counter()
        jax.block_until_ready(ji.render(scene, camera))
        frames.append(time.perf_counter() - t)
    return dict(import_s=t_import - T0, build_s=t_build - t_import,
                first_render_s=t_first - t_build, first_picture_s=t_first - T0,
                frame_s=statistics.median(frames) if frames else None,
                cache_files=len(os.listdir(args.cache)) if args.cache else None)


def run_child(kind, size, mode, cache, args):
    """Runs this script as a child for one kind and mode; its figures plus wall_s."""
    cmd = [sys.executable, __file__, "--child", kind, "--size", str(size),
           "--frames", str(args.frames), "--voxels", str(args.voxels), "--tets",
           str(args.tets), "--data", args.data]
    if mode != "no cache":
        cmd += ["--cache", cache]
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    wall = time.perf_counter() - t
    if out.returncode != 0:
        raise RuntimeError(f"{kind} ({mode}) failed:\n{out.stderr[-2000:]}")
    return dict(json.loads(out.stdout.strip().splitlines()[-1]), wall_s=wall)


# ------------------------------------------------------------------------------ parent


def measure(kind, size, args):
    """{mode: figures} for one kind, the cache in a fresh temporary folder."""
    modes = MODES[1:] if args.quick else MODES
    with tempfile.TemporaryDirectory(prefix="jaxiso-cache-") as cache:
        return {mode: run_child(kind, size, mode, cache, args) for mode in modes}


def verdict(kind, size, runs):
    """'target met' / 'missed' for the cold and warm first pictures, or '' without one
    (other kinds, other sizes)."""
    if kind not in TARGETS_S or size != SIZES[kind]:
        return ""
    cold, warm = runs["cold"]["first_picture_s"], runs["warm"]["first_picture_s"]
    ok = cold < TARGETS_S[kind] and warm < TARGETS_S[kind] / 2
    return f"target cold < {TARGETS_S[kind]:g} s, warm < {TARGETS_S[kind] / 2:g} s: " + \
        ("met" if ok else "missed")


def table(result):
    """Prints one row per kind and mode."""
    head = ("kind", "size", "mode", "import s", "build s", "1st render s", "1st picture s",
            "frame s", "process s")
    rows = []
    for kind, entry in result["kinds"].items():
        for mode, r in entry.get("runs", {}).items():
            rows.append((kind, str(entry["size"]), mode, *(f"{r[k]:.2f}" for k in (
                "import_s", "build_s", "first_render_s", "first_picture_s")),
                f"{r['frame_s']:.3f}" if r["frame_s"] is not None else "-",
                f"{r['wall_s']:.2f}"))
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    print("  ".join(h.rjust(w) for h, w in zip(head, widths)))
    print("-" * (sum(widths) + 2 * len(widths)))
    for r in rows:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))
    for kind, entry in result["kinds"].items():
        print(f"{kind}: {entry.get('verdict') or entry.get('skipped', '')}")


def chart(result, path):
    """Grouped bars (log scale) per kind: first picture per mode next to the steady
    frame, the targets as ticks."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install -e '.[bench]'): no chart")
        return None
    kinds = [k for k, e in result["kinds"].items() if "runs" in e]
    modes = [m for m in MODES if any(m in result["kinds"][k]["runs"] for k in kinds)]
    bars = [*modes, "steady frame"]
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    width = 0.8 / len(bars)
    for j, bar in enumerate(bars):
        runs = [result["kinds"][k]["runs"] for k in kinds]
        values = [r["warm" if "warm" in r else modes[-1]]["frame_s"] if bar == "steady frame"
                  else r.get(bar, {}).get("first_picture_s") for r in runs]
        xs = [i + (j - (len(bars) - 1) / 2) * width for i in range(len(kinds))]
        ax.bar(xs, [v or 0 for v in values], width, label=bar)
    for i, k in enumerate(kinds):
        if k in TARGETS_S:
            ax.hlines([TARGETS_S[k], TARGETS_S[k] / 2], i - 0.45, i + 0.45, colors="k",
                      linestyles=["--", ":"])
    ax.set_yscale("log")
    ax.set_xticks(range(len(kinds)),
                  [f"{k} {result['kinds'][k]['size']}^2" for k in kinds])
    ax.set_ylabel("seconds (log)")
    ax.set_title("time to first picture in a fresh process vs the steady frame\n"
                 "(dashed: cold target, dotted: warm target)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="64^2 images, small data, 1 frame, no 'no cache' process")
    p.add_argument("--kinds", nargs="*", default=list(KINDS), choices=KINDS)
    p.add_argument("--frames", type=int, default=5, help="steady renders after the first")
    p.add_argument("--voxels", type=int, default=128, help="volume edge in voxels")
    p.add_argument("--tets", type=int, default=18, help="cube_tets(n): 6 n^3 tets")
    p.add_argument("--data", default="/work/shared/data/neural", help="folder of fox.npz")
    p.add_argument("--out", default=str(HERE / "results"))
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per process")
    p.add_argument("--child", choices=KINDS, help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, help=argparse.SUPPRESS)
    p.add_argument("--cache", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick and not args.child:
        args.frames, args.voxels, args.tets = 1, 32, 6
    return args


def main(argv=None):
    args = parse(argv)
    if args.child:
        print(json.dumps(child(args)))
        return
    import jax

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"jax {jax.__version__}, {jax.default_backend()}, {os.cpu_count()} CPUs, "
          f"load average {load:.1f}{', QUICK' if args.quick else ''}\n", flush=True)
    result = dict(benchmark="first_picture", jax_version=jax.__version__,
                  backend=jax.default_backend(), cpu_count=os.cpu_count(),
                  platform=platform.platform(), quick=args.quick, frames=args.frames,
                  voxels=args.voxels, tets=6 * args.tets**3, load_average_start=load,
                  targets_cold_s=TARGETS_S, kinds={})
    for kind in args.kinds:
        size = 64 if args.quick else SIZES[kind]
        if kind == "fox" and not (pathlib.Path(args.data) / "fox.npz").exists():
            result["kinds"][kind] = dict(size=size, skipped=f"no {args.data}/fox.npz")
            continue
        runs = measure(kind, size, args)
        result["kinds"][kind] = dict(size=size, runs=runs, verdict=verdict(kind, size, runs))
        print(f"{kind} {size}^2: " + ", ".join(
            f"{m} {r['first_picture_s']:.1f} s" for m, r in runs.items()), flush=True)
    result["load_average_end"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    print()
    table(result)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"first_picture_{jax.default_backend()}.json"
    result["chart"] = chart(result, path.with_suffix(".png"))
    path.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {path}" + (f" and {result['chart']}" if result["chart"] else ""))


if __name__ == "__main__":
    main()
