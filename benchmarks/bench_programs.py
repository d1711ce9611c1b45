"""Large implicit programs (issue 14): tape path vs straight (inlined) path.

Sections (each case runs in its own subprocess under a wall-clock timeout and an address
space cap, so that peak memory is per case and a case that blows up is reported, not
fatal):

  crossover  generated CSG programs of ~100..10,000 instructions: compile time, run time
             and peak RSS of (a) the straight path, ``jax.jit(ji.extend(f, "interval"))``
             on 4,096 boxes, and (b) the tape path, `program.evaluate_intervals` (one
             compiled evaluator per padded length).
  slab       Prospero as a 3D slab of text (max(prospero, |z| - 0.25)) through the default
             call, rays down z, 256^2 and 1024^2, next to dense evaluation of prospero at
             the pixel centres: first call, median call, peak RSS, agreement, registers.
             (Earlier rounds also cast Prospero as an extruded 2D solid with a separate
             renderer, `program.cast`; issue 27 removed it: one engine, the default call.)
  memory     peak RSS of the default call on generated CSG scenes against program length
             (50-800 primitives at 128^2) and image size (64^2-256^2).
  scene3d    a generated CSG of 400 primitives at 256^2 in perspective through the
             user's default call, ``ji.render(
             ji.ImplicitSurface(prog, lo, hi), cam)`` (the scene plans the tape path):
             first call, median render, median intersect, agreement, per-level tapes.
Charts: <out>_compile.png (compile time against program length).

Usage: python benchmarks/bench_programs.py [--sections crossover,slab,memory,scene3d]
       [--quick] [--out benchmarks/results/programs_cpu.json]
Only public jaxiso names are used.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import resource
import statistics
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data"
PROSPERO = DATA / "prospero.vm"
sys.path.insert(0, str(HERE.parent / "tests"))  # the float64 references


def _rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _block(x):
    import jax
    return jax.block_until_ready(x)


# ------------------------------------------------------------------------ the cases


def case_straight(n_prims, seed=0):
    import jax
    import numpy as np

    import jaxiso as ji
    from jaxiso.implicit.generate import csg_program
    prog = csg_program(n_prims, seed)
    rng = np.random.default_rng(0)
    c = rng.uniform(-1, 1, (4096, 3)).astype(np.float32)
    box = [ji.Interval(c[:, k] - 0.02, c[:, k] + 0.02) for k in range(3)]
    F = jax.jit(ji.extend(prog, "interval"))
    t0 = time.perf_counter()
    compiled = F.lower(*box).compile()
    compile_s = time.perf_counter() - t0
    _block(compiled(*box))
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        _block(compiled(*box))
        runs.append(time.perf_counter() - t0)
    return dict(path="straight", instructions=len(prog), compile_s=compile_s,
                run_s=statistics.median(runs), peak_rss_mb=_rss_mb())


def case_tape(n_prims, seed=0):
    import numpy as np

    import jaxiso as ji
    from jaxiso.implicit import program
    from jaxiso.implicit.generate import csg_program
    prog = csg_program(n_prims, seed)
    t0 = time.perf_counter()
    tape = program.tape_of(prog)
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    c = rng.uniform(-1, 1, (4096, 3)).astype(np.float32)
    box = [ji.Interval(c[:, k] - 0.02, c[:, k] + 0.02) for k in range(3)]
    t0 = time.perf_counter()
    _block(program.evaluate_intervals(tape, *box))
    first_s = time.perf_counter() - t0
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        _block(program.evaluate_intervals(tape, *box))
        runs.append(time.perf_counter() - t0)
    run_s = statistics.median(runs)
    return dict(path="tape", instructions=len(prog), tape_length=tape.length,
                build_s=build_s, compile_s=max(first_s - run_s, 0.0), run_s=run_s,
                peak_rss_mb=_rss_mb())


def _prospero_camera(n):
    import jaxiso as ji
    return ji.Camera.orthographic_view((0, 0, 3), (0, 0, 0), (0, 1, 0), 1.0, n, n)


def case_dense(n):
    """JAX brute force: the program inlined and jitted, evaluated at every pixel centre."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from reference_program64 import vm64_points

    import jaxiso as ji
    prog = ji.implicit.load_vm(PROSPERO)
    cam = _prospero_camera(n)
    o = cam.rays().origin
    x, y = o[..., 0].reshape(-1), o[..., 1].reshape(-1)
    f = jax.jit(lambda x, y: prog(x, y, jnp.zeros_like(x)))
    t0 = time.perf_counter()
    compiled = f.lower(x, y).compile()
    compile_s = time.perf_counter() - t0
    _block(compiled(x, y))
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        v = _block(compiled(x, y))
        runs.append(time.perf_counter() - t0)
    peak = _rss_mb()  # before the reference, which is not the figure
    on = np.asarray(o, np.float64)
    ref = vm64_points(prog.ops, on[..., 0], on[..., 1], on[..., 2]) < 0
    return dict(size=n, compile_s=compile_s, run_s=statistics.median(runs),
                agreement=float(np.mean((np.asarray(v) < 0) == ref)), peak_rss_mb=peak)


def _sampled_reference(prog, rays, result, lo, hi, size):
    """(hit, t, ref_hit, ref_t) on 1,500 seeded pixels: `result`'s and float64 dense
    sampling's (first_inside64)."""
    import numpy as np
    from reference_program64 import first_inside64
    pick = np.random.default_rng(0).choice(size * size, min(1500, size * size), replace=False)
    ref_hit, ref_t = first_inside64(prog.ops, np.asarray(rays.origin).reshape(-1, 3)[pick],
                                    np.asarray(rays.direction).reshape(-1, 3)[pick], lo, hi)
    return (np.asarray(result.hit).reshape(-1)[pick], np.asarray(result.t).reshape(-1)[pick],
            ref_hit, ref_t)


def case_scene3d(n_prims=400, size=256, seed=1, repeats=3, noprune=False):
    """The user's default call: ``ji.render(ji.ImplicitSurface(prog, lo, hi), cam)`` (the
    scene plans the tape path for a long program), and ``ji.intersect`` of the camera's
    rays for the hit mask and the per-level statistics."""
    import numpy as np

    import jaxiso as ji
    from jaxiso.implicit.generate import csg_program
    prog = csg_program(n_prims, seed)
    cam = ji.Camera.look_at((3.0, 2.2, 1.8), (0, 0, 0), fov=45.0, width=size, height=size)
    lo, hi = (-1.4,) * 3, (1.4,) * 3
    t0 = time.perf_counter()
    scene = ji.ImplicitSurface(prog, lo, hi)
    build_s = time.perf_counter() - t0
    plan = ji.plan_for(scene, size * size)
    t0 = time.perf_counter()
    _block(ji.render(scene, cam))
    render_first_s = time.perf_counter() - t0
    render_runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _block(ji.render(scene, cam))
        render_runs.append(time.perf_counter() - t0)
    rays = cam.rays()
    hits = ji.intersect(scene, rays)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        hits = _block(ji.intersect(scene, rays))
        runs.append(time.perf_counter() - t0)
    peak = _rss_mb()  # the calls' peak: the references below are not the figure
    stats = {}
    if plan.tape:  # the same rays in the same order as intersect runs them (Z-order tiles)
        from jaxiso.render import to_zorder
        zrays = ji.Rays(to_zorder(rays.origin, plan.tile), to_zorder(rays.direction, plan.tile))
        scene.intersect_tape(zrays, 0.0, np.inf, stats=stats)
        if noprune:  # what pruning buys: every region runs the full tape
            _block(scene.intersect_tape(zrays, 0.0, np.inf, prune=False).t)  # compile
            t0 = time.perf_counter()
            _block(scene.intersect_tape(zrays, 0.0, np.inf, prune=False).t)
            stats["noprune_intersect_s"] = time.perf_counter() - t0
    hit, t, ref_hit, ref_t = _sampled_reference(prog, rays, hits, lo, hi, size)
    both = hit & ref_hit
    return dict(primitives=n_prims, instructions=len(prog), size=size, plan=repr(plan),
                arithmetic_report=scene.arithmetic_report, build_s=build_s,
                first_call_s=render_first_s, run_s=statistics.median(render_runs),
                intersect_run_s=statistics.median(runs),
                hit_agreement=float(np.mean(hit == ref_hit)),
                hit_fraction=float(ref_hit.mean()),
                t_error_median=float(np.median(np.abs(t[both] - ref_t[both]))),
                levels=stats.get("levels"),
                noprune_intersect_s=stats.get("noprune_intersect_s"), peak_rss_mb=peak)


def _slab_program(prog):
    """Prospero as a 3D slab of text: inside where prospero < 0 and |z| < 0.25."""
    import jax.numpy as jnp
    return lambda x, y, z: jnp.maximum(prog(x, y, z), jnp.abs(z) - 0.25)


def case_slab(n, repeats=2):
    """Prospero as a 3D slab through the user's default call, ``ji.intersect(
    ji.ImplicitSurface(slab, lo, hi), cam.rays())``, rays straight down z: first call,
    median call after, peak RSS, the tape path's registers and batches, and agreement of
    the hit mask with float64 ``prospero < 0`` at the pixel centres (the same picture)."""
    import numpy as np
    from reference_program64 import vm64_points

    import jaxiso as ji
    from jaxiso.render import to_zorder
    prog = ji.implicit.load_vm(PROSPERO)
    cam = _prospero_camera(n)
    rays = cam.rays()
    t0 = time.perf_counter()
    scene = ji.ImplicitSurface(_slab_program(prog), (-1, -1, -1), (1, 1, 1))
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    hits = _block(ji.intersect(scene, rays))
    first_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        hits = _block(ji.intersect(scene, rays))
        runs.append(time.perf_counter() - t0)
    peak = _rss_mb()  # the calls' peak: the references below are not the figure
    o = np.asarray(rays.origin, np.float64)
    ref = (vm64_points(prog.ops, o[..., 0], o[..., 1], o[..., 2]) < 0).reshape(
        np.shape(hits.hit))
    stats = {}
    plan = ji.plan_for(scene, n * n)
    if plan.tape and n <= 256:  # the per-level figures (one more call)
        zr = ji.Rays(to_zorder(rays.origin, plan.tile), to_zorder(rays.direction, plan.tile))
        scene.intersect_tape(zr, 0.0, np.inf, stats=stats)
    return dict(size=n, instructions=len(prog), plan=repr(plan), build_s=build_s,
                first_call_s=first_s, run_s=statistics.median(runs),
                compile_s_est=max(first_s - statistics.median(runs), 0.0),
                agreement=float(np.mean(np.asarray(hits.hit) == ref)),
                inside_fraction=float(ref.mean()), registers=stats.get("registers"),
                batches=stats.get("batches"), levels=stats.get("levels"),
                peak_rss_mb=peak)


def case_memory(n_prims, size, seed=1):
    """Peak RSS of the default call on a generated CSG scene (perspective) against
    program length and image size: ``ji.intersect(ji.ImplicitSurface(prog), cam.rays())``,
    first call and one more."""
    import jaxiso as ji
    from jaxiso.implicit.generate import csg_program
    prog = csg_program(n_prims, seed)
    cam = ji.Camera.look_at((3.0, 2.2, 1.8), (0, 0, 0), fov=45.0, width=size, height=size)
    scene = ji.ImplicitSurface(prog, (-1.4,) * 3, (1.4,) * 3)
    t0 = time.perf_counter()
    _block(ji.intersect(scene, cam.rays()))
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    _block(ji.intersect(scene, cam.rays()))
    return dict(primitives=n_prims, instructions=len(prog), size=size,
                plan=repr(ji.plan_for(scene, size * size)), first_call_s=first_s,
                run_s=time.perf_counter() - t0, peak_rss_mb=_rss_mb())


CASES = dict(straight=case_straight, tape=case_tape,
             dense=case_dense, scene3d=case_scene3d, slab=case_slab,
             memory=case_memory)


# ------------------------------------------------------------------------ the driver


def run_case(name, args, timeout, mem_mb):
    """One case in a subprocess (ulimit -v mem_mb, timeout); its JSON line or a failure."""
    cmd = ["bash", "-c", f'ulimit -v {mem_mb * 1024}; exec "$0" "$@"', sys.executable,
           __file__, "--case", name, "--case-args", json.dumps(args)]
    env = dict(os.environ)
    env.setdefault("PYTHONPATH", str(HERE.parent))
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return dict(case=name, args=args, failed=f"timeout after {timeout} s")
    wall = time.perf_counter() - t0
    for line in reversed(out.stdout.splitlines()):
        if line.startswith("{"):
            return dict(case=name, args=args, wall_s=wall, **json.loads(line))
    tail = (out.stderr or out.stdout).strip().splitlines()[-3:]
    return dict(case=name, args=args, failed=f"exit {out.returncode}: {' | '.join(tail)}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case")
    ap.add_argument("--case-args", default="[]")
    ap.add_argument("--sections", default="crossover,slab,memory,scene3d")
    ap.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    ap.add_argument("--timeout", type=int, default=600)
    ap.add_argument("--mem-mb", type=int, default=8000)
    ap.add_argument("--out", default=str(HERE / "results" / "programs_cpu.json"))
    a = ap.parse_args()
    if a.case:
        print(json.dumps(CASES[a.case](*json.loads(a.case_args))))
        return
    import jax
    sections = a.sections.split(",")
    results = dict(device=jax.devices()[0].device_kind, jax=jax.__version__,
                   machine=platform.machine(), cpus=os.cpu_count(), sections={},
                   timing="first_call_s = compile + first run; run_s = median of repeats "
                          "(host clock, block_until_ready); peak_rss_mb = the case "
                          "subprocess's max RSS after its timed calls, before the "
                          "float64 references")

    def record(section, r):
        results["sections"].setdefault(section, []).append(r)
        keys = ("instructions", "size", "prune", "compile_s", "compile_s_est",
                "first_call_s", "run_s", "agreement", "hit_agreement", "peak_rss_mb",
                "failed")
        print(section, r["case"], {k: (round(r[k], 4) if isinstance(r[k], float) else r[k])
                                   for k in keys if k in r}, flush=True)
        pathlib.Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(a.out).write_text(json.dumps(results, indent=1))

    if "crossover" in sections:
        prims = [5, 15, 50, 150, 480] if not a.quick else [5, 15]
        for n in prims:
            record("crossover", run_case("tape", [n], a.timeout, a.mem_mb))
            record("crossover", run_case("straight", [n], a.timeout, a.mem_mb))
    if "slab" in sections and PROSPERO.exists():
        for n in ([256, 1024] if not a.quick else [64]):
            record("slab", run_case("slab", [n, 2 if n <= 256 else 1], a.timeout, a.mem_mb))
            record("slab", run_case("dense", [n], a.timeout, a.mem_mb))
    if "memory" in sections:
        for args in ([[50, 128], [200, 128], [800, 128], [200, 64], [200, 256]]
                     if not a.quick else [[60, 32], [120, 32]]):  # tape-path sizes
            record("memory", run_case("memory", args, a.timeout, a.mem_mb))
    if "scene3d" in sections:
        args = [400, 256] if not a.quick else [60, 32]
        record("scene3d", run_case("scene3d", args, a.timeout, a.mem_mb))
        args = [150, 128] if not a.quick else [60, 32]  # pruning off: a smaller model
        record("scene3d", run_case("scene3d", args + [1, 1, True], a.timeout, a.mem_mb))
    chart(results, pathlib.Path(a.out).with_suffix(""))


def _pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # the bench extra is not installed
        return None
    return plt


def chart_memory(results, stem):
    """Peak RSS of the default call against program length and image size (the memory
    and slab sections) as <stem>_memory.png."""
    rows = [r for r in results["sections"].get("memory", []) if "peak_rss_mb" in r]
    plt = _pyplot()
    if not rows or plt is None:
        return
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    by_len = sorted((r["instructions"], r["peak_rss_mb"] / 1024) for r in rows
                    if r["size"] == 128)
    by_size = sorted((r["size"] ** 2, r["peak_rss_mb"] / 1024) for r in rows
                     if r["primitives"] == 200)
    if by_len:
        axes[0].plot(*zip(*by_len), marker="o", label="generated CSG, 128^2")
    axes[0].set_xscale("log")
    axes[0].set_xlabel("program length (instructions)")
    if by_size:
        axes[1].plot(*zip(*by_size), marker="o", label="CSG of 200 primitives")
    slab = sorted((r["size"] ** 2, r["peak_rss_mb"] / 1024) for r in
                  results["sections"].get("slab", []) if r.get("case") == "slab"
                  and "peak_rss_mb" in r)
    if slab:
        axes[1].plot(*zip(*slab), marker="s", label="Prospero slab (7,866)")
    axes[1].set_xscale("log")
    axes[1].set_xlabel("rays")
    for ax in axes:
        ax.set_ylabel("peak RSS (GB)")
        ax.set_ylim(0, None)
        if ax.lines:
            ax.legend(fontsize=7)
    fig.suptitle("Default call, tape path, memory budget 1 GiB (2-core CPU)", fontsize=9)
    fig.tight_layout()
    fig.savefig(f"{stem}_memory.png", dpi=110)
    plt.close(fig)


def chart(results, stem):
    """Compile time against program length (the crossover section) as a PNG, when
    matplotlib (the bench extra) is installed; and `chart_memory`."""
    chart_memory(results, stem)
    rows = results["sections"].get("crossover", [])
    plt = _pyplot()
    if not rows or plt is None:
        return
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for case, label in (("straight", "straight (XLA inlines the interval extension)"),
                        ("tape", "tape (one evaluator per padded length)")):
        pts = sorted((r["instructions"], r["compile_s"]) for r in rows
                     if r["case"] == case and "compile_s" in r)
        if pts:
            ax.plot(*zip(*pts), marker="o", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("program length (tape instructions)")
    ax.set_ylabel("compile time (s)")
    ax.set_title("Compile time against program length (2-core CPU)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(f"{stem}_compile.png", dpi=120)
    plt.close(fig)

if __name__ == "__main__":
    main()
