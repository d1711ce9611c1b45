"""Scaffolding shared by bench_implicit.py, bench_volume.py and bench_tetra.py: timing calls,
AOT compile caching, timing the call a user writes (no plan, no manual jit), the common
command-line options, a run (header line, metadata, sections, the JSON file), table
printing, the charts' matplotlib set-up and the peers' helpers (memory check, pixel
subsample, VTK isosurface, open3d ray casting).

Only public jaxiso names are used here and in the benchmarks (docs/layout.md: the command
line, notebooks, benchmarks and examples use the public names).

The benchmarks put this folder on ``sys.path`` and import it as ``_common``.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import platform
import statistics
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji

TIMING = ("compile: AOT lower+compile; run: median of `repeats` calls after one warm-up call "
          "(entries whose warm-up exceeds slow_s: the warm-up call), block_until_ready; "
          "Mrays/s = pixels / run s; user calls (ji.render / ji.intersect with no plan and "
          "no manual jax.jit): first_call_s = compile + first run, then run_s as above; "
          "plan: the jaxiso.Plan each entry ran")


def now():
    return time.perf_counter()


# ---------------------------------------------------------------------------- timing


def time_calls(call, repeats, slow_s, timed=True):
    """Runs a no-argument call once (warm-up), then `repeats` more times unless `timed` is
    false or the warm-up took longer than `slow_s`; each call waits for the device.

    Returns (the last output, timing): run_s (median wall seconds of the repeats, else the
    warm-up's), cpu_s (the same for this process's CPU time over all its threads: less
    sensitive than wall time to other processes on a shared machine), warmup_s and
    repeats_used."""
    t0, c0 = now(), time.process_time()
    out = jax.block_until_ready(call())
    warm, warm_cpu = now() - t0, time.process_time() - c0
    times, cpu = [], []
    for _ in range(repeats if timed and warm <= slow_s else 0):
        t0, c0 = now(), time.process_time()
        out = jax.block_until_ready(call())
        times.append(now() - t0)
        cpu.append(time.process_time() - c0)
    return out, dict(run_s=statistics.median(times) if times else warm,
                     cpu_s=statistics.median(cpu) if cpu else warm_cpu,
                     warmup_s=warm, repeats_used=len(times))


def signature(*args):
    """Hashable pytree structure + leaf shapes/dtypes/weak types: the key of an AOT
    executable."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    return treedef, tuple((jnp.shape(x), jnp.result_type(x).str, getattr(x, "weak_type", False))
                          for x in leaves)


class TimedBench:
    """Times calls and caches AOT-compiled executables by their arguments' signature."""

    def __init__(self, repeats: int, slow_s: float):
        self.repeats = repeats
        self.slow_s = slow_s
        self._compiled = {}

    def compiled(self, kind, fn, *args):
        """(executable, compile s, cached) of jit(fn) for these argument shapes; `kind`
        names fn (with whatever it closes over) in the cache key."""
        key = (kind, signature(*args))
        if key in self._compiled:
            exe, s = self._compiled[key]
            return exe, s, True
        t0 = now()
        exe = jax.jit(fn).lower(*args).compile()
        self._compiled[key] = (exe, now() - t0)
        return exe, self._compiled[key][1], False

    def timed(self, call, timed=True):
        """`time_calls` with this bench's repeats and slow_s: (output, timing dict)."""
        return time_calls(call, self.repeats, self.slow_s, timed)

    def user_call(self, call, plan, label):
        """`user_call` with this bench's repeats and slow_s: (output, row dict)."""
        return user_call(call, plan, label, self.repeats, self.slow_s)


def user_call(call, plan, label, repeats, slow_s):
    """Times the call a user writes first (``ji.render(scene, cam)``,
    ``ji.intersect(scene, rays)``: no plan, no manual ``jax.jit``; both are jitted inside):
    its first call compiles (unless an earlier call of the same shapes did) and runs
    (first_call_s); then `time_calls` (one more warm-up call, the median of `repeats`
    calls, or that warm-up alone when it took longer than `slow_s`). `plan` is the plan
    that call runs (``ji.plan_for(scene, n)``).

    Returns (the last output, row dict: call, plan, first_call_s, run_s, cpu_s,
    warmup_s, repeats_used)."""
    t0 = now()
    jax.block_until_ready(call())
    first = now() - t0
    out, timing = time_calls(call, repeats, slow_s)
    return out, dict(call=label, plan=repr(plan), plan_tile=plan.tile, plan_lanes=plan.lanes,
                     first_call_s=first, **timing)


def plan_fields(plan):
    """The plan a row ran, for its JSON: plan (the repr, e.g. "Plan(tile=4, lanes=4096)"),
    tile and lanes."""
    return dict(plan=repr(plan), tile=plan.tile, lanes=plan.lanes)


# ---------------------------------------------------------------------------- command line


def parse_args(parser, argv, sections, default_out, repeat_flags=("--repeats",)):
    """Adds the options every benchmark has to `parser` (after its own): the repeat counts
    `repeat_flags` (default 3 each), --slow-s, --quick, --only and --out; parses argv.

    Returns (args, the sections --only names, in its order); a usage error for an unknown
    section or a repeat count below 1."""
    for flag in repeat_flags:
        parser.add_argument(flag, type=int, default=3)
    parser.add_argument("--slow-s", type=float, default=2.0,
                        help="an entry whose warm-up call takes longer is timed by it alone")
    parser.add_argument("--quick", action="store_true", help="tiny smoke run (< 60 s)")
    parser.add_argument("--only", default=",".join(sections),
                        help="comma-separated subset of " + ",".join(sections))
    parser.add_argument("--out", default=str(default_out))
    args = parser.parse_args(argv)
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = sorted(set(only) - set(sections))
    if bad:
        parser.error(f"unknown section(s) {bad}; choose from {sections}")
    if any(getattr(args, flag[2:].replace("-", "_")) < 1 for flag in repeat_flags):
        parser.error(" and ".join(repeat_flags) + " must be >= 1")
    return args, only


# ---------------------------------------------------------------------------- the run


def output_path(out, benchmark):
    """<out>/<benchmark>_<backend>.json, the run's result file; makes the folder."""
    out_dir = pathlib.Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir / f"{benchmark}_{jax.default_backend()}.json"


def print_header(args, note=""):
    """The run's first line: versions, device, CPUs, then `note`, then how calls are timed."""
    device = jax.devices()[0]
    print(f"jax {jax.__version__}, {jax.default_backend()} ({device.device_kind}), "
          f"{os.cpu_count()} CPUs, {note}median of {args.repeats} after a warm-up (entries "
          f"slower than {args.slow_s} s: the warm-up call alone)"
          f"{', QUICK' if args.quick else ''}\n")


def run_metadata(benchmark, args, sections, cfg, *, numpy_version=True, timing=TIMING,
                 **extra):
    """The head of a result dict: versions, device and platform, the options and `cfg`, an
    empty errors dict, then `extra` and `timing` (how the figures were measured)."""
    device = jax.devices()[0]
    result = dict(benchmark=benchmark, jax_version=jax.__version__,
                  jaxiso_version=ji.__version__)
    if numpy_version:
        result["numpy_version"] = np.__version__
    result.update(backend=jax.default_backend(), device_kind=device.device_kind,
                  device_count=jax.device_count(), cpu_count=os.cpu_count(),
                  platform=platform.platform(), processor=platform.processor(),
                  python=platform.python_version(), quick=args.quick, repeats=args.repeats,
                  slow_s=args.slow_s, sections=sections, config=cfg, errors={}, **extra,
                  timing=timing)
    return result


def json_default(x):
    """JSON for numpy scalars and arrays; anything else as its str."""
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating | np.ndarray):
        return x.tolist()
    return str(x)


class Run:
    """One run of a benchmark: prints the header line, holds the result dict and rewrites
    it to <out>/<benchmark>_<backend>.json after every section (a crash keeps what was
    measured).

    header_note goes into the header line (`print_header`); default is the JSON
    encoder's fallback; stamp(result), if given, adds to the result before each write;
    `metadata` goes to `run_metadata`."""

    def __init__(self, benchmark, args, sections, cfg, *, header_note="",
                 default=json_default, stamp=None, **metadata):
        self.t_start = now()
        self.path = output_path(args.out, benchmark)
        print_header(args, header_note)
        self.result = run_metadata(benchmark, args, sections, cfg, **metadata)
        self._default = default
        self._stamp = stamp

    def save(self):
        self.result["total_s"] = now() - self.t_start
        if self._stamp is not None:
            self._stamp(self.result)
        self.path.write_text(json.dumps(self.result, indent=1, default=self._default))

    def sections(self, sections, run, finish=None):
        """result[sec] = run(sec) for the sections chosen (result["sections"]), in the
        order of `sections`, each with its section_s, saving after each. A failing section
        is reported (traceback, and result["errors"][sec]) and the others go on.
        finish(section result), if given, may add to a finished section; the text it
        returns is printed after its seconds."""
        for sec in sections:
            if sec not in self.result["sections"]:
                continue
            t0 = now()
            try:
                self.result[sec] = run(sec)
            except Exception as e:  # keep the other sections' figures
                traceback.print_exc()
                self.result["errors"][sec] = f"{type(e).__name__}: {e}"
                print(f"  {sec} FAILED: {type(e).__name__}: {str(e)[:200]}\n")
                continue
            self.result[sec]["section_s"] = now() - t0
            note = finish(self.result[sec]) if finish else ""
            print(f"  ({sec}: {self.result[sec]['section_s']:.0f} s{note})\n", flush=True)
            self.save()

    def finish(self, draw_charts, more=()):
        """Draws the charts (`save_charts`), saves the result a last time and prints what
        was written (`more`: other files); returns the result."""
        self.result["charts"] = save_charts(draw_charts, self.result, self.path.parent,
                                            self.path.stem)
        self.save()
        print(f"wrote {self.path} ({self.result['total_s']:.0f} s)")
        for c in [*self.result["charts"], *more]:
            print(f"wrote {c}")
        if self.result["errors"]:
            print(f"ERRORS in {sorted(self.result['errors'])}")
        return self.result


# ---------------------------------------------------------------------------- printing


def fmt(v, spec=".3f"):
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    return format(v, spec)


def print_table(headers, rows):
    """Right-aligned columns of strings under a header and a rule, then a blank line."""
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
    line = "  ".join(h.rjust(w) for h, w in zip(headers, widths))
    print(line)
    print("-" * len(line))
    for r in rows:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))
    print()


def compile_cell(r):
    """A row's compile seconds; '*' where the executable was reused."""
    return fmt(r["compile_s"], ".1f") + ("*" if r["compile_cached"] else "")


# ---------------------------------------------------------------------------- charts


def save_charts(draw, result, out_dir, prefix):
    """Runs draw(plt, save, result) with pyplot on the Agg backend, where save(fig, name)
    lays a figure out, writes it to <out_dir>/<prefix>_<name>.png and closes it. Returns
    the paths written, as str ([] when matplotlib is not installed, said so)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install -e '.[bench]'): no charts")
        return []
    paths = []

    def save(fig, name):
        fig.tight_layout()
        p = out_dir / f"{prefix}_{name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)

    draw(plt, save, result)
    return [str(p) for p in paths]


# ---------------------------------------------------------------------------- peers


def available_gb():
    """MemAvailable in GiB (inf where /proc/meminfo is missing)."""
    try:
        for line in pathlib.Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return math.inf


def subsample(size, ref_size):
    """Row/column indices of a ref_size^2 regular pixel subsample of a size^2 image."""
    if ref_size >= size:
        return np.arange(size)
    stride = size / ref_size
    return (np.arange(ref_size) * stride + stride / 2).astype(np.int64)


def vtk_isosurface(vtk_filter, data, iso, *outputs_off):
    """The polydata of a VTK isosurface filter (vtkContourFilter, vtkFlyingEdges3D, ...)
    run on `data` at `iso`, with Compute<name> switched off for each of `outputs_off`
    ("Normals", "Scalars", ...: what the ray casting does not need)."""
    vtk_filter.SetInputData(data)
    vtk_filter.SetValue(0, float(iso))
    for name in outputs_off:
        getattr(vtk_filter, f"Compute{name}Off")()
    vtk_filter.Update()
    return vtk_filter.GetOutput()


def mesh_raycast(verts, faces, o, d):
    """open3d ray casting of a triangle mesh: (t [N] float64 (inf: miss), normals [N, 3],
    build + first cast s, second cast s). The BVH is built lazily by the first cast."""
    import open3d as o3d

    t0 = now()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(verts, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    rays = o3d.core.Tensor(np.ascontiguousarray(np.concatenate([o, d], axis=1), np.float32))
    ans = scene.cast_rays(rays)
    t_hit = ans["t_hit"].numpy()
    first_s = now() - t0
    t0 = now()
    ans = scene.cast_rays(rays)
    again_s = now() - t0
    return t_hit.astype(np.float64), ans["primitive_normals"].numpy(), first_s, again_s
