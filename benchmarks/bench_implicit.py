"""Ray tracing throughput, work and accuracy of the implicit-surface methods: analogs of
the seed's Tables 6.1 and 6.2, a packet-size table (seed Table 4.2) and an eps sweep.

    python benchmarks/bench_implicit.py [--size 512] [--quick] [--repeats 3]
        [--only table61,table62,packets,sweep,scalar] [--names sphere,...]
        [--out benchmarks/results]

Every entry runs ``ji.intersect(scene, rays, plan=plan)`` (the render path: rays in tile
order, hits with normals) on a catalogue camera, with the options (eps, method,
arithmetic, samples) as scene fields (``scene.replace``). The plan is the one a user gets
(``ji.plan_for(scene, n_rays)``: packets of tile x tile rays, or persistent lanes) unless
the entry says otherwise; every row records it (``plan``, e.g. "Plan(tile=4, lanes=None)").
Compile time (AOT ``lower().compile()``) is reported apart from run time: one warm-up
call, then the median of `repeats` calls, each ``jax.block_until_ready``. Mrays/s =
pixels / run s. The packets section also times the calls a user writes first,
``ji.intersect(scene, camera.rays())`` and ``ji.render(scene, camera)`` (no plan, no
manual ``jax.jit``: first call = compile + run, then the median), beside the tuned plans.
Work counters come from ``hits.steps`` (loop iterations per ray): mean / max, the hit
fraction, the rays that exhausted ``max_steps``, the lane utilisation of a packet (the
useful share of lane-iterations: sum of steps / sum over packets of packet x its
slowest ray's steps) and the cost per ray-step (run s / total steps).

Sections:
  table61  every catalogue surface, eps 2^-11, interval and affine t-bisection at
           size x size; "converged eps" (the largest eps in 2^-6..2^-14 whose hit mask
           agrees with the float64 reference tracer, tests/reference_trace64.py, eps
           2^-22, on >= 99.5% of pixels) at a smaller size. CSG entries have no reference
           (the reference tracer handles plain level sets only): no converged eps.
  table62  t-bisection vs K-bisection vs Mitchell at eps 2^-11 and 2^-22 on the Mitchell
           and Barth decic surfaces, interval arithmetic.
  packets  Barth sextic, interval t-bisection, eps 2^-11: one vmap over all rays, square
           tiles, and persistent lanes with refill (the whole image as one queue); and
           the default calls (ji.intersect, ji.render) side by side.
  sweep    eps 2^-6..2^-16 on barth_sextic and mitchell for t-/K-bisection x interval /
           affine and Mitchell; point sampling with 16/64/256 samples. Pixel error
           (fraction of hit masks differing from the reference) and depth error
           (median / 99th percentile of |t - t_ref| where both hit) against Mrays/s.
  scalar   Barth sextic, eps 2^-11, --size: the default call ``ji.intersect(scene,
           camera.rays())`` on the catalogue's scene (its arithmetic) and in interval
           arithmetic as the C loop (no plan, no manual jit: first call, then the median of
           `repeats` calls, never cut short by --slow-s) beside a plain scalar C loop in the
           same process (benchmarks/scalar_bisect.c: the seed's stackless t-bisection one
           ray at a time, float32 interval arithmetic rounded to nearest, hit at the
           piece's midpoint), compiled at run time with ``cc -O2 -march=native -fopenmp``
           (fallbacks without -march=native / with pthreads; no compiler: a skip with the
           reason) and run on os.cpu_count() threads and on 1; its enclosures are checked
           against ``ji.extend`` on random boxes. Hit-mask agreement C vs jaxiso and each
           vs the float64 reference, median |t_C - t_jaxiso| where both hit; verdict:
           jaxiso Mrays/s / C (all threads) Mrays/s. If packets ran first, the default
           call's executable is cached (first_call_s is then a run, not a compile).
The target (>= 1 Mray/s on the Barth sextic at eps 2^-11, best configuration measured)
is checked at the end. Writes ``<out>/implicit_<backend>.json`` and, when matplotlib is
installed, ``<out>/implicit_<backend>_{sweep,packets,table61}.png``.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
import types

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests"))
import _common as common  # noqa: E402
import reference64  # noqa: E402
import reference_trace64  # noqa: E402
from _common import compile_cell, fmt, print_table  # noqa: E402

SECTIONS = ("table61", "table62", "packets", "sweep", "scalar")
ARITHMETICS = ("interval", "affine")
EPS_DEFAULT = 2.0**-11
CONVERGED_EPS = tuple(2.0**-k for k in range(6, 15))  # 2^-6 .. 2^-14, coarse to fine
SWEEP_EPS = tuple(2.0**-k for k in range(6, 17))  # 2^-6 .. 2^-16
SAMPLES = (16, 64, 256)
AGREE = 0.995
REF_EPS = 2.0**-22
TARGET_MRAYS = 1.0
# bisection's default loop bound (ImplicitSurface.max_steps None: 256 x the depth bound 30,
# 8 x that for K-bisection, which counts per packet)
MAX_DEPTH = 30
MAX_STEPS = {"t-bisection": 256 * MAX_DEPTH, "k-bisection": 8 * 256 * MAX_DEPTH}

# Seed Table 6.1 (frames/s at 1024^2; CPU: 4-core Xeon SSE, IA; GPU: 8800 GTX) and the
# converged eps column, for side-by-side reading (1 fps = 1.048576 Mrays/s).
SEED_TABLE61 = {
    "sphere": (15, 75, 147, "RAA", -10), "steiner": (7.5, 34, 40, "RAA", -12),
    "mitchell": (5.2, 16, 58, "RAA", -10), "teardrop": (5.5, 102, 115, "RAA", -10),
    "bretzel4": (13, 78, 48, "IA", -10), "klein": (11, 30, 110, "RAA", -12),
    "tangle": (3.2, 15, 68, "RAA", -10), "decocube": (5.5, 28, 27, "IA", -11),
    "barth_sextic": (7.4, 31, 76, "RAA", -10), "barth_decic": (0.92, 4.9, 15.6, "RAA", -11),
    "superquadric": (18, 119, 8.3, "IA", -12), "icos.csg": (1.8, 13.3, None, "IA", -11),
    "sesc.csg": (1.6, 8.9, None, "IA", -13), "sin.blob": (0.71, 6.0, None, "IA", -12),
    "cloth": (2.2, 38, None, "IA", -9), "water": (2.2, 37, None, "IA", -9),
}
# Seed Table 6.2, CPU SSE (frames/s at 1024^2): (mitchell 2^-11, 2^-22, decic 2^-11, 2^-22)
SEED_TABLE62 = {"t-bisection": (5.0, 1.0, 0.90, 0.061), "k-bisection": (5.1, 1.2, 0.92, 0.18),
                "mitchell": (0.54, 0.22, 0.19, 0.036)}


def log2_label(eps):
    return f"2^{round(math.log2(eps))}"


# ---------------------------------------------------------------------------- runner


def surface_scene(name, eps=EPS_DEFAULT, method="t-bisection", arithmetic="interval",
                  **extra):
    """A catalogue scene with the benchmark's options as its fields."""
    return ji.surfaces.scene(name).replace(eps=eps, method=method, arithmetic=arithmetic,
                                           **extra)


class Bench:
    """Compiles and times ``intersect`` configurations (AOT); caches executables and the
    float64 references."""

    def __init__(self, repeats: int, slow_s: float):
        self.repeats = repeats
        self.slow_s = slow_s
        self._compiled = {}
        self._refs = {}
        self._rays = {}

    def rays(self, name, size, tile):
        """Camera rays of a catalogue entry in tile order (tile x tile packets)."""
        key = (name, size, tile)
        if key not in self._rays:
            r = ji.surfaces.camera(name, size).rays()
            self._rays[key] = ji.Rays(ji.to_tiles(r.origin, tile),
                                      ji.to_tiles(r.direction, tile))
        return self._rays[key]

    def compiled(self, scene, name, size, plan, method, arithmetic, extra):
        """(executable, compile s) of intersect(scene, tile-ordered rays, plan=plan), and
        whether it was cached (eps is a traced field: one executable serves every eps)."""
        key = (name, size, plan, method, arithmetic, tuple(sorted(extra.items())))
        if key in self._compiled:
            return self._compiled[key], True

        def fn(scene, rays):
            return ji.intersect(scene, rays, plan=plan)

        t0 = time.perf_counter()
        exe = jax.jit(fn).lower(scene, self.rays(name, size, plan.tile)).compile()
        entry = (exe, time.perf_counter() - t0)
        self._compiled[key] = entry
        return entry, False

    def run(self, name, size, eps, *, method="t-bisection", arithmetic="interval",
            plan=None, timed=True, exec_size=None, **extra):
        """One configuration: returns (row dict, image-ordered hit mask, image-ordered t).

        plan: None, the user's plan (``ji.plan_for(scene, rays)``), or a `ji.Plan`.
        An entry whose warm-up call takes longer than `slow_s` is timed by that call
        alone (repeats_used 0). exec_size: run on the executable compiled for
        exec_size^2 rays (>= size^2): the size^2 camera rays followed by rays that miss
        the domain, so no new compile (for masks; the timing includes empty packets)."""
        scene = surface_scene(name, eps, method, arithmetic, **extra)
        ex = size if exec_size is None else exec_size
        plan = ji.plan_for(scene, ex * ex) if plan is None else plan
        tile = plan.tile
        (exe, compile_s), cached = self.compiled(scene, name, ex, plan, method, arithmetic,
                                                 extra)
        rays = self.rays(name, size, tile)
        m = rays.origin.shape[0]
        if ex != size:
            rays = pad_rays(rays, self.rays(name, ex, tile).origin.shape[0], scene)
        hits, timing = common.time_calls(lambda: exe(scene, rays), self.repeats,
                                         self.slow_s, timed)
        run_s = timing["run_s"] if timed else None
        hits = jax.tree_util.tree_map(lambda a: a[:m], hits)
        n = size * size
        packet = rays.origin.shape[0] if plan.lanes else plan.packet
        row = dict(surface=name, method=method, arithmetic=arithmetic, eps=float(eps),
                   size=size, **common.plan_fields(plan), packet=packet, **extra,
                   compile_s=compile_s, compile_cached=cached, run_s=run_s,
                   warmup_s=timing["warmup_s"], repeats_used=timing["repeats_used"],
                   mrays_per_s=(n / run_s / 1e6) if run_s else None,
                   **work(hits, method, packet if plan.lanes is None else None, run_s))
        h = np.asarray(ji.from_tiles(hits.hit, tile, size, size)).reshape(-1)
        t = np.asarray(ji.from_tiles(hits.t, tile, size, size), np.float64).reshape(-1)
        return row, h, t

    def defaults(self, name, size):
        """The calls a user writes first, timed as written (no plan, no manual jit):
        ``ji.intersect(scene, camera.rays())`` (raster order, work counters as in `run`)
        and ``ji.render(scene, camera)``; interval t-bisection at eps 2^-11."""
        scene = surface_scene(name)
        cam = ji.surfaces.camera(name, size)
        rays = cam.rays()
        n = size * size
        plan = ji.plan_for(scene, n)
        rows = []
        hits, row = common.user_call(lambda: ji.intersect(scene, rays), plan,
                                     "ji.intersect(scene, camera.rays())", self.repeats,
                                     self.slow_s)
        flat = jax.tree_util.tree_map(lambda a: a.reshape((n,) + a.shape[2:]), hits)
        packet = n if plan.lanes else plan.packet
        row.update(surface=name, method="t-bisection", arithmetic="interval",
                   eps=EPS_DEFAULT, size=size, packet=packet, label="default: intersect",
                   mrays_per_s=n / row["run_s"] / 1e6,
                   **work(flat, "t-bisection", None if plan.lanes else packet, row["run_s"]))
        rows.append(row)
        _, row = common.user_call(lambda: ji.render(scene, cam), plan,
                                  "ji.render(scene, camera)", self.repeats, self.slow_s)
        row.update(surface=name, method="t-bisection", arithmetic="interval",
                   eps=EPS_DEFAULT, size=size, label="default: render (with shading)",
                   mrays_per_s=n / row["run_s"] / 1e6)
        rows.append(row)
        return rows

    def reference(self, name, size):
        """float64 reference (t [size^2], raster order) and the seconds it took."""
        key = (name, size)
        if key not in self._refs:
            e = ji.surfaces.get(name)
            o, d = reference_trace64.camera_rays(e.eye, e.target, e.up, e.fov, size, size)
            t0 = time.perf_counter()
            t = reference_t(name, o, d)
            self._refs[key] = (t, time.perf_counter() - t0)
        return self._refs[key]


# CSG references need reference_trace64.first_change (membership changes along a ray)
FIRST_CHANGE = getattr(reference_trace64, "first_change", None)
CSG_PARTS = getattr(reference64, "CSG_PARTS", {})


def has_reference(name):
    if name in CSG_PARTS:
        return FIRST_CHANGE is not None and name in ("icos.csg", "sesc.csg")
    return name in reference64.SURFACES


def reference_t(name, o, d):
    """First hit t (inf: none) of float64 rays with a catalogue entry
    (tests/reference_trace64.catalogue_first_hits)."""
    e = ji.surfaces.get(name)
    return reference_trace64.catalogue_first_hits(
        name, reference64.SURFACES.get(name), CSG_PARTS.get(name), e.lo, e.hi, o, d,
        isovalues=e.isovalues, w=e.w, eps=REF_EPS)


def pad_rays(rays, n, scene):
    """rays [m] followed by n - m rays that miss the domain box (they start beyond its
    upper corner and point away from it)."""
    m = rays.origin.shape[0]
    far = scene.hi + 10.0 * (scene.hi - scene.lo)
    o = jnp.broadcast_to(far, (n - m, 3)).astype(jnp.float32)
    d = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0], jnp.float32), (n - m, 3))
    return ji.Rays(jnp.concatenate([rays.origin, o]), jnp.concatenate([rays.direction, d]))


def work(hits, method, packet, run_s):
    """Work counters of hits [N] (steps in the order the rays ran): mean / max / total
    steps, hit fraction, rays that exhausted max_steps, the lane utilisation of packets of
    `packet` consecutive rays (t-bisection only; None for persistent lanes: packet None)
    and ns per ray-step."""
    steps = np.asarray(hits.steps, np.int64)
    util = None
    if method == "t-bisection" and packet is not None:
        m = steps.size
        n_pk = -(-m // packet)
        pad = np.zeros(n_pk * packet - m, np.int64)
        per = np.concatenate([steps, pad]).reshape(n_pk, packet)
        lane_iters = float(np.sum(per.max(axis=1)) * packet)
        util = float(steps.sum() / lane_iters) if lane_iters else None
    max_steps = MAX_STEPS.get(method)
    return dict(steps_mean=float(steps.mean()), steps_max=int(steps.max()),
                steps_total=int(steps.sum()), hit_fraction=float(np.mean(hits.hit)),
                exhausted=int(np.sum(steps >= max_steps)) if max_steps else None,
                lane_utilisation=util,
                ns_per_step=(run_s / max(int(steps.sum()), 1) * 1e9) if run_s else None)


def accuracy(hit, t, t_ref):
    ref_hit = np.isfinite(t_ref)
    both = hit & ref_hit
    err = np.abs(t[both] - t_ref[both])
    return dict(pixel_error=float(np.mean(hit != ref_hit)),
                depth_err_median=float(np.median(err)) if err.size else None,
                depth_err_p99=float(np.percentile(err, 99)) if err.size else None)


# ---------------------------------------------------------------------------- printing


def work_cells(r):
    """Table cells of a row; a user call's first call (compile + run) stands in the
    compile column, marked '+'; a render has no work counters ('-')."""
    first = compile_cell(r) if "compile_s" in r else fmt(r["first_call_s"], ".1f") + "+"
    return [first, fmt(r["run_s"]), fmt(r["mrays_per_s"]), fmt(r.get("steps_mean"), ".1f"),
            fmt(r.get("steps_max"), "d"), fmt(r.get("hit_fraction")),
            fmt(r.get("exhausted"), "d"), fmt(r.get("lane_utilisation"), ".2f"),
            fmt(r.get("ns_per_step"), ".0f")]


WORK_HDR = ["compile s", "run s", "Mrays/s", "steps", "max", "hit", "exh", "util", "ns/step"]


# ---------------------------------------------------------------------------- sections


def table61(b, cfg):
    names = cfg["table61_names"]
    size, csize = cfg["size"], cfg["conv_size"]
    user_plans = {a: ji.plan_for(surface_scene(names[0], arithmetic=a), size * size)
                  for a in ARITHMETICS}
    plans = {a: repr(plan) for a, plan in user_plans.items()}
    print(f"== Table 6.1 analog: t-bisection, eps 2^-11, {size}x{size}, plans {plans} "
          f"(ji.plan_for, as render); converged eps (2^-6..2^-14, hit mask vs float64 "
          f"reference eps 2^-22 on >= {AGREE:.1%} of pixels) at {csize}x{csize}")
    rows, summary, printed = [], [], []
    for name in names:
        per = {}
        for arith in ARITHMETICS:
            row, _, _ = b.run(name, size, EPS_DEFAULT, arithmetic=arith)
            rows.append(row)
            per[arith] = row
        faster = max(ARITHMETICS, key=lambda a: per[a]["mrays_per_s"])
        s = dict(surface=name, faster=faster,
                 mrays_interval=per["interval"]["mrays_per_s"],
                 mrays_affine=per["affine"]["mrays_per_s"], conv_size=csize,
                 seed_fps=dict(zip(("cpu_ia", "gpu_ia", "gpu_raa"),
                                   SEED_TABLE61.get(name, (None,) * 3)[:3])),
                 seed_converged=(SEED_TABLE61[name][3] + " 2^" + str(SEED_TABLE61[name][4])
                                 if name in SEED_TABLE61 else None))
        if has_reference(name):
            t_ref, ref_s = b.reference(name, csize)
            s["reference_s"] = ref_s
            s["reference_hit_fraction"] = float(np.mean(np.isfinite(t_ref)))
            # the conv-size rays run on the size x size executable (padded with rays
            # that miss), so no second compile
            ex = size if csize <= size else None
            for arith in ARITHMETICS:
                agree = {}
                s[f"converged_eps_{arith}"] = None
                for eps in CONVERGED_EPS:  # coarse to fine: the first agreeing is largest
                    _, h, _ = b.run(name, csize, eps, arithmetic=arith, timed=False,
                                    exec_size=ex)
                    agree[log2_label(eps)] = float(np.mean(h == np.isfinite(t_ref)))
                    if agree[log2_label(eps)] >= AGREE:
                        s[f"converged_eps_{arith}"] = eps
                        break
                s[f"agreement_{arith}"] = agree
        else:
            s["converged_note"] = ("no float64 reference (tests/reference_trace64.py has "
                                   "no first_change for CSG): converged eps skipped")
            for arith in ARITHMETICS:
                s[f"converged_eps_{arith}"] = None
        summary.append(s)
        for arith in ARITHMETICS:
            r = per[arith]
            conv = (log2_label(s[f"converged_eps_{arith}"])
                    if s.get(f"converged_eps_{arith}") else
                    ("n/a" if "converged_note" in s else "none"))
            printed.append([name, arith + (" <" if arith == faster else ""), r["plan"],
                            *work_cells(r), conv, fmt(s["seed_fps"][{"interval": "gpu_ia",
                                                     "affine": "gpu_raa"}[arith]], "")])
        print_table(["surface", "arith", "plan", *WORK_HDR, "conv eps", "seed GPU fps"],
                    printed[-2:])
    print("  '<' marks the faster arithmetic at 2^-11; '*' a compile reused; conv eps: "
          "2^-6 means 2^-6 or coarser, 'n/a' no reference (CSG), 'none' no eps down to "
          "2^-14 agrees; util: useful share of lane-iterations; exh: rays that exhausted "
          "max_steps")
    skipped = [s["surface"] for s in summary if "converged_note" in s]
    if skipped:
        print(f"  converged eps skipped (no float64 reference for CSG): {skipped}")
    faster = {s["surface"]: s["faster"] for s in summary}
    print(f"  faster arithmetic per surface: {faster}\n")
    return dict(size=size, conv_size=csize, eps=EPS_DEFAULT,
                plan=plans, tile={a: plan.tile for a, plan in user_plans.items()},
                conv_eps_grid=list(CONVERGED_EPS), agree_threshold=AGREE,
                reference="tests/reference_trace64.first_roots (CSG: first_change when "
                          "available), eps 2^-22, 4096 samples",
                rows=rows, summary=summary)


def table62(b, cfg):
    size = cfg["table62_size"]
    names = cfg["table62_names"]
    eps_list = cfg["table62_eps"]
    print(f"== Table 6.2 analog: interval arithmetic, {size}x{size}, the plan ji.plan_for "
          f"gives each method")
    rows, printed = [], []
    for name in names:
        for eps in eps_list:
            for method in ("t-bisection", "k-bisection", "mitchell"):
                row, _, _ = b.run(name, size, eps, method=method)
                rows.append(row)
                printed.append([name, log2_label(eps), method, row["plan"], *work_cells(row)])
    print_table(["surface", "eps", "method", "plan", *WORK_HDR], printed)
    return dict(size=size, plan={r["method"]: r["plan"] for r in rows},
                arithmetic="interval", rows=rows,
                seed_cpu_fps=SEED_TABLE62)


def packets(b, cfg):
    size = cfg["size"]
    n = size * size
    name = "barth_sextic"
    user_plan = ji.plan_for(surface_scene(name), n)
    print(f"== Packets: {name}, interval t-bisection, eps 2^-11, {size}x{size}; the user's "
          f"plan (ji.plan_for) is {user_plan!r}")
    # one packet of all rays: a tile as large as the image (tile order = raster order)
    configs = [("vmap all rays", ji.Plan(tile=size))]
    configs += [(f"tiles {t}x{t}", ji.Plan(tile=t)) for t in cfg["tiles"]]
    # persistent lanes run the whole batch as one queue, in the user plan's tile order
    configs += [(f"lanes {lanes}", ji.Plan(tile=user_plan.tile, lanes=lanes))
                for lanes in cfg["lanes"]]
    rows, printed = [], []
    for label, plan in configs:
        row, _, _ = b.run(name, size, EPS_DEFAULT, plan=plan)
        row["label"] = label
        rows.append(row)
        printed.append([label, row["plan"], *work_cells(row)])
    defaults = b.defaults(name, size)
    for d in defaults:
        printed.append([d["label"], d["plan"], *work_cells(d)])
    print_table(["configuration", "plan", *WORK_HDR], printed)
    best = max(rows, key=lambda r: r["mrays_per_s"])
    print(f"  fastest: {best['label']} ({best['mrays_per_s']:.3f} Mrays/s); the user's "
          + "; ".join(f"{d['call']}: {d['mrays_per_s']:.3f} Mrays/s (first call "
                      f"{d['first_call_s']:.1f} s)" for d in defaults)
          + "\n  (default rows: no plan, no manual jit; '+': their first call, compile + "
          "run)\n")
    return dict(surface=name, size=size, eps=EPS_DEFAULT, arithmetic="interval", rows=rows,
                fastest=best["label"], user_plan=repr(user_plan), defaults=defaults)


def sweep(b, cfg):
    size = cfg["sweep_size"]
    print(f"== Speed vs accuracy: {size}x{size}, reference float64 eps 2^-22; sampling "
          f"refines to eps 2^-11")
    configs = [("t-bisection", "interval"), ("t-bisection", "affine"),
               ("k-bisection", "interval"), ("k-bisection", "affine"),
               ("mitchell", "interval")]
    rows = []
    for name in cfg["sweep_names"]:
        t_ref, ref_s = b.reference(name, size)
        print(f"  {name}: reference {ref_s:.1f} s, hit fraction "
              f"{np.mean(np.isfinite(t_ref)):.3f}")
        printed = []
        for method, arith in configs:
            for eps in cfg["sweep_eps"]:
                row, h, t = b.run(name, size, eps, method=method, arithmetic=arith)
                row.update(accuracy(h, t, t_ref), axis="eps", label=f"{method}/{arith}")
                rows.append(row)
                printed.append([row["label"], log2_label(eps), fmt(row["mrays_per_s"]),
                                fmt(row["steps_mean"], ".1f"), fmt(row["pixel_error"], ".4f"),
                                fmt(row["depth_err_median"], ".2e"),
                                fmt(row["depth_err_p99"], ".2e")])
        for samples in cfg["samples"]:
            row, h, t = b.run(name, size, EPS_DEFAULT, method="sampling", samples=samples)
            row.update(accuracy(h, t, t_ref), axis="samples", label="sampling")
            rows.append(row)
            printed.append(["sampling", f"{samples} smp", fmt(row["mrays_per_s"]),
                            fmt(row["steps_mean"], ".1f"), fmt(row["pixel_error"], ".4f"),
                            fmt(row["depth_err_median"], ".2e"),
                            fmt(row["depth_err_p99"], ".2e")])
        print(f"  -- {name}")
        print_table(["method/arith", "eps", "Mrays/s", "steps", "pixel err", "depth med",
                     "depth p99"], printed)
    return dict(size=size, eps=list(cfg["sweep_eps"]), samples=list(cfg["samples"]),
                sampling_eps=EPS_DEFAULT, rows=rows)


# the scalar C loop (benchmarks/scalar_bisect.c) and the flags tried to build it, best first
SCALAR_C = ROOT / "scalar_bisect.c"
SCALAR_FLAGS = (("-march=native", "-fopenmp"), ("-fopenmp",), ("-march=native", "-pthread"),
                ("-pthread",))
SCALAR_CHECK_BOXES = 4096


def build_scalar(tmp):
    """Compiles scalar_bisect.c into the folder tmp and loads it: (ctypes library, the
    command used, compile s, None) or (None, None, None, the reason it could not).
    ``cc -O2 <flags> -shared -fPIC -std=c99`` with the flags of SCALAR_FLAGS in turn
    ($CC, else cc, gcc or clang); -std=c99 keeps GCC from contracting a*b+c into FMAs."""
    cc = next((c for c in (os.environ.get("CC"), "cc", "gcc", "clang")
               if c and shutil.which(c)), None)
    if cc is None:
        return None, None, None, "no C compiler ($CC, cc, gcc or clang) on PATH"
    errors = []
    for i, flags in enumerate(SCALAR_FLAGS):
        out = pathlib.Path(tmp) / f"scalar_bisect_{i}.so"
        cmd = [cc, "-O2", *flags, "-shared", "-fPIC", "-std=c99", str(SCALAR_C), "-o",
               str(out), "-lm"]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired) as e:
            errors.append(f"{' '.join(cmd)}: {type(e).__name__}: {e}")
            continue
        compile_s = time.perf_counter() - t0
        if proc.returncode != 0:
            errors.append(f"{' '.join(flags)}: {proc.stderr.strip()[-300:]}")
            continue
        try:
            lib = ctypes.CDLL(str(out))
        except OSError as e:
            errors.append(f"{' '.join(flags)}: load failed: {e}")
            continue
        f32, i32 = ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_int)
        head = [ctypes.c_int, f32, f32, ctypes.c_float, f32, f32, ctypes.c_int, f32, i32,
                ctypes.c_int]
        lib.trace.argtypes = head
        lib.trace.restype = ctypes.c_int
        lib.trace_steps.argtypes = head + [i32]
        lib.trace_steps.restype = ctypes.c_int
        lib.enclose.argtypes = [ctypes.c_int, f32, f32, f32, f32]
        lib.enclose.restype = None
        lib.parallel_backend.restype = ctypes.c_int
        return lib, " ".join(cmd), compile_s, None
    return None, None, None, "every compile failed: " + " | ".join(errors)


def _ptr(a, kind=ctypes.c_float):
    return a.ctypes.data_as(ctypes.POINTER(kind))


def scalar_trace(lib, o, d, eps, lo, hi, max_steps, threads, steps=False):
    """Runs the C loop on rays o, d [n, 3] float32: (hit [n] bool, t [n] float64 (inf: no
    hit), steps [n] int or None)."""
    n = o.shape[0]
    t = np.empty(n, np.float32)
    hit = np.empty(n, np.int32)
    args = [n, _ptr(o), _ptr(d), eps, _ptr(lo), _ptr(hi), max_steps, _ptr(t),
            _ptr(hit, ctypes.c_int), threads]
    if steps:
        st = np.empty(n, np.int32)
        rc = lib.trace_steps(*args, _ptr(st, ctypes.c_int))
    else:
        st = None
        rc = lib.trace(*args)
    if rc < 0:
        raise ValueError(f"scalar_bisect.c trace rejected its arguments ({rc})")
    return hit.astype(bool), t.astype(np.float64), st


def scalar_enclosures_match(lib, name, n_boxes=SCALAR_CHECK_BOXES):
    """The C interval extension against ``ji.extend(f, "interval", "fast")`` on random
    boxes in and around the domain (widths from 0 to 1): the share of boxes whose two
    enclosures are bitwise equal, and the largest endpoint difference relative to the
    enclosure's width."""
    e = ji.surfaces.get(name)
    rng = np.random.default_rng(0)
    lo = rng.uniform(np.array(e.lo) - 0.1, np.array(e.hi) + 0.1, (n_boxes, 3))
    hi = lo + rng.uniform(0.0, 1.0, (n_boxes, 3)) ** 4
    lo, hi = (np.ascontiguousarray(a, np.float32) for a in (lo, hi))
    c_lo, c_hi = np.empty(n_boxes, np.float32), np.empty(n_boxes, np.float32)
    lib.enclose(n_boxes, _ptr(lo), _ptr(hi), _ptr(c_lo), _ptr(c_hi))
    F = ji.extend(e.f, "interval", "fast")
    r = F(*(ji.interval(jnp.asarray(lo[:, i]), jnp.asarray(hi[:, i])) for i in range(3)),
          e.w)
    j_lo, j_hi = np.asarray(r.lo), np.asarray(r.hi)
    diff = np.maximum(np.abs(j_lo - c_lo), np.abs(j_hi - c_hi)).astype(np.float64)
    width = np.maximum(np.abs(j_hi - j_lo).astype(np.float64), 1e-30)
    return dict(boxes=n_boxes, bitwise_equal=float(np.mean((j_lo == c_lo) & (j_hi == c_hi))),
                max_rel_diff=float(np.max(diff / width)))


def scalar_seed_rule_check(scene, rays, n, c_hit, c_t, c_steps):
    """One untimed call of jaxiso with the seed's hit rule (``verify="none"``: the
    enclosure alone, as the C loop) on the same rays: how closely the C loop reproduces
    it (hit masks, t, steps per ray). The default call differs from the C loop by its
    hit verification only."""
    t0 = time.perf_counter()
    hits = jax.block_until_ready(ji.intersect(scene.replace(verify="none"), rays))
    call_s = time.perf_counter() - t0
    hit = np.asarray(hits.hit, bool).reshape(n)
    t = np.asarray(hits.t, np.float64).reshape(n)
    both = hit & c_hit
    dt = np.abs(t[both] - c_t[both])
    return dict(call='ji.intersect(scene.replace(verify="none"), camera.rays())',
                first_call_s=call_s, hit_agree=float(np.mean(hit == c_hit)),
                t_equal=float(np.mean(dt == 0)) if dt.size else None,
                depth_max=float(np.max(dt)) if dt.size else None,
                steps_equal=float(np.mean(np.asarray(hits.steps).reshape(n) == c_steps)))


def scalar(b, cfg):
    size = cfg["size"]
    n = size * size
    name = "barth_sextic"
    scene = surface_scene(name)
    cam = ji.surfaces.camera(name, size)
    rays = cam.rays()
    plan = ji.plan_for(scene, n)
    threads = os.cpu_count() or 1
    max_steps = MAX_STEPS["t-bisection"]
    print(f"== Scalar C loop: {name}, t-bisection, eps 2^-11, {size}x{size}; jaxiso's "
          f"default call on the catalogue scene and in interval arithmetic (plan "
          f"{plan!r}) beside benchmarks/scalar_bisect.c (interval) on {threads} and 1 "
          f"thread(s), same process, same rays")
    result = dict(surface=name, size=size, eps=EPS_DEFAULT, arithmetic="interval",
                  rounding="fast", max_steps=max_steps, threads=threads,
                  c_source=str(SCALAR_C.relative_to(ROOT.parent)),
                  c_hit_point="midpoint of the accepted piece (as jaxiso; the seed's "
                              "Algorithm 7 returns its left end)",
                  c_depth_rule="d_max = ceil(log2(|p_exit - p_enter| / eps)) (Eq. 6.19), "
                               "clamped to [0, 30]; hit = enclosure holds 0 at d_max (the "
                               "seed's rule, no sign check)",
                  jaxiso_verify=scene.verify)
    # (a) jaxiso, the call a user writes (always the median of `repeats`: no slow_s cut):
    # the catalogue's scene as it comes (its arithmetic), then in interval arithmetic as
    # the C loop (the rows the C loop's agreement is measured against)
    default = ji.surfaces.scene(name).replace(eps=EPS_DEFAULT)
    rows = []
    ref = None
    if has_reference(name):
        t_ref, ref_s = b.reference(name, size)
        ref = np.isfinite(t_ref)
        result["reference_s"] = ref_s
    for label, sc in (("jaxiso default: intersect", default),
                      ("jaxiso interval: intersect", scene)):
        p = ji.plan_for(sc, n)
        hits, row = common.user_call(lambda sc=sc: ji.intersect(sc, rays), p,
                                     "ji.intersect(scene, camera.rays())", b.repeats,
                                     math.inf)
        flat = jax.tree_util.tree_map(lambda a: a.reshape((n,) + a.shape[2:]), hits)
        row.update(label=label, impl="jaxiso", threads=None, arithmetic=sc.arithmetic,
                   mrays_per_s=n / row["run_s"] / 1e6,
                   **work(flat, "t-bisection", None if p.lanes else p.packet, row["run_s"]))
        j_hit = np.asarray(flat.hit, bool)
        j_t = np.asarray(flat.t, np.float64)
        if ref is not None:
            row.update(hit_agree_reference=float(np.mean(j_hit == ref)),
                       **accuracy(j_hit, j_t, t_ref))
        rows.append(row)
    # (b) the C loop, built at run time
    tmp = tempfile.TemporaryDirectory(prefix="jaxiso_scalar_")
    try:
        lib, cmd, compile_s, why = build_scalar(tmp.name)
        result.update(c_compile_cmd=cmd, c_compile_s=compile_s)
        if lib is None:
            result["c_skipped"] = why
            print(f"  C loop skipped: {why}")
        else:
            result["c_parallel"] = {1: "openmp", 2: "pthreads"}[lib.parallel_backend()]
            result["c_enclosures_vs_jaxiso"] = scalar_enclosures_match(lib, name)
            o = np.ascontiguousarray(np.asarray(rays.origin, np.float32).reshape(n, 3))
            d = np.ascontiguousarray(np.asarray(rays.direction, np.float32).reshape(n, 3))
            lo = np.ascontiguousarray(np.asarray(scene.lo, np.float32))
            hi = np.ascontiguousarray(np.asarray(scene.hi, np.float32))
            eps = float(scene.eps)
            outs = {}
            for nt in dict.fromkeys((threads, 1)):
                out, timing = common.time_calls(
                    lambda nt=nt: scalar_trace(lib, o, d, eps, lo, hi, max_steps, nt),
                    b.repeats, math.inf)
                c_hit, c_t, _ = out
                outs[nt] = (c_hit, c_t)
                _, _, steps = scalar_trace(lib, o, d, eps, lo, hi, max_steps, nt, steps=True)
                if nt == threads:
                    steps_all = steps
                c_row = dict(label=f"scalar C, {nt} thread{'s' if nt > 1 else ''}",
                             impl="c", threads=nt, call="trace()", plan=None,
                             compile_cmd=cmd, compile_s=compile_s, compile_cached=False,
                             parallel=result["c_parallel"], **timing,
                             mrays_per_s=n / timing["run_s"] / 1e6,
                             **work(types.SimpleNamespace(steps=steps, hit=c_hit),
                                    "t-bisection", None, timing["run_s"]))
                both = c_hit & j_hit
                dt = np.abs(c_t[both] - j_t[both])
                c_row.update(hit_agree_jaxiso=float(np.mean(c_hit == j_hit)),
                             depth_vs_jaxiso_median=float(np.median(dt)) if dt.size else None,
                             depth_vs_jaxiso_p99=(float(np.percentile(dt, 99)) if dt.size
                                                  else None),
                             depth_vs_jaxiso_max=float(np.max(dt)) if dt.size else None)
                if ref is not None:
                    c_row.update(hit_agree_reference=float(np.mean(c_hit == ref)),
                                 **accuracy(c_hit, c_t, t_ref))
                rows.append(c_row)
            result["c_vs_jaxiso_seed_rule"] = scalar_seed_rule_check(
                scene, rays, n, *outs[threads], steps_all)
            hs = [h for h, _ in outs.values()]
            ts = [t for _, t in outs.values()]
            result["c_threads_identical"] = bool(all(np.array_equal(hs[0], h) for h in hs)
                                                 and all(np.array_equal(ts[0], t)
                                                         for t in ts))
    finally:
        tmp.cleanup()
    printed = [[r["label"], *work_cells(r), fmt(r.get("hit_agree_jaxiso"), ".4f"),
                fmt(r.get("hit_agree_reference"), ".4f"),
                fmt(r.get("depth_vs_jaxiso_median"), ".2e")] for r in rows]
    print_table(["implementation", *WORK_HDR, "=jaxiso", "=ref", "|dt| med"], printed)
    if result["c_compile_cmd"] and "c_skipped" not in result:
        enc = result["c_enclosures_vs_jaxiso"]
        print(f"  C: {result['c_compile_cmd']} ({result['c_parallel']}, compile "
              f"{result['c_compile_s']:.2f} s); enclosures bitwise equal to ji.extend's on "
              f"{enc['bitwise_equal']:.4f} of {enc['boxes']} random boxes; same result on "
              f"every thread count: {result['c_threads_identical']}")
        sr = result["c_vs_jaxiso_seed_rule"]
        print(f"  C vs jaxiso with the seed's hit rule (verify='none', one untimed call): "
              f"hit masks equal on {sr['hit_agree']:.4f} of pixels, t equal on "
              f"{fmt(sr['t_equal'], '.4f')} of common hits (max |dt| "
              f"{fmt(sr['depth_max'], '.1e')}), steps per ray equal on "
              f"{sr['steps_equal']:.4f}")
    c_all = next((r for r in rows if r["impl"] == "c" and r["threads"] == threads), None)
    row, interval_row = rows[0], rows[1]
    if c_all is not None:
        ratio = row["mrays_per_s"] / c_all["mrays_per_s"]
        result.update(ratio=ratio, met=ratio >= 1.0,
                      interval_ratio=interval_row["mrays_per_s"] / c_all["mrays_per_s"])
        verdict = (f"  verdict: jaxiso default ({row['arithmetic']}) {row['mrays_per_s']:.3f} "
                   f"Mrays/s / scalar C ({threads} threads) {c_all['mrays_per_s']:.3f} "
                   f"Mrays/s = {ratio:.2f}x ({'at least' if ratio >= 1.0 else 'below'} the "
                   f"C loop's speed); in interval arithmetic as the C loop "
                   f"{result['interval_ratio']:.2f}x")
    else:
        result.update(ratio=None, met=None)
        verdict = (f"  verdict: no C loop ({result.get('c_skipped')}); jaxiso default "
                   f"{row['mrays_per_s']:.3f} Mrays/s")
    result["verdict"] = verdict.strip()
    print(verdict)
    print("  (=jaxiso: share of pixels whose hit equals jaxiso's; =ref: equals the float64 "
          "reference's; |dt| med: median |t_C - t_jaxiso| where both hit; jaxiso verifies "
          f"hits ({scene.verify!r}), the C loop takes the seed's enclosure rule)\n")
    result["rows"] = rows
    return result


def target(b, cfg, result):
    """>= 1 Mray/s on the Barth sextic at eps 2^-11 with the best configuration measured;
    affine arithmetic is also run in the fastest (interval) packet configuration."""
    size = cfg["size"]
    cands, notes = [], []
    for sec in ("table61", "packets"):
        for r in result.get(sec, {}).get("rows", []):
            if (r["surface"] == "barth_sextic" and r["eps"] == EPS_DEFAULT
                    and r["size"] == size and r["run_s"]):
                cands.append(r)
    if not cands:
        return None
    defaults = result.get("packets", {}).get("defaults")
    if "packets" in result and "table61" in result:
        t61 = {r["arithmetic"]: r for r in result["table61"]["rows"]
               if r["surface"] == "barth_sextic"}
        best_pk = max(result["packets"]["rows"], key=lambda r: r["mrays_per_s"])
        if not cfg["quick"] and t61:
            plan = ji.Plan(tile=best_pk["tile"], lanes=best_pk["lanes"])
            row, _, _ = b.run("barth_sextic", size, EPS_DEFAULT, arithmetic="affine",
                              plan=plan)
            row["label"] = "affine, " + best_pk.get("label", "")
            cands.append(row)
            notes.append(f"  affine in the fastest packet configuration ({best_pk['label']}): "
                         f"{row['mrays_per_s']:.3f} Mrays/s (interval "
                         f"{best_pk['mrays_per_s']:.3f})")
    best = max(cands, key=lambda r: r["mrays_per_s"])
    met = best["mrays_per_s"] >= TARGET_MRAYS
    steps = best["steps_total"]
    limits = dict(steps_per_ray=best["steps_mean"], steps_max=best["steps_max"],
                  lane_utilisation=best["lane_utilisation"],
                  idle_lane_fraction=(1 - best["lane_utilisation"]
                                      if best["lane_utilisation"] is not None else None),
                  ns_per_step=best["ns_per_step"],
                  hit_fraction=best["hit_fraction"],
                  steps_needed_per_s_for_target=TARGET_MRAYS * 1e6 * best["steps_mean"],
                  steps_per_s_measured=steps / best["run_s"],
                  batch_ns_per_box=arith_ns_per_box(best["arithmetic"]))
    desc = f"{best['method']}/{best['arithmetic']}, {best['plan']}"
    print(f"== Target: >= {TARGET_MRAYS} Mray/s on barth_sextic at eps 2^-11, {size}x{size}: "
          f"best {best['mrays_per_s']:.3f} Mrays/s ({desc}) -> "
          f"{'MET' if met else 'NOT met'}")
    for line in notes:
        print(line)
    for d in defaults or ():
        print(f"  the user's call {d['call']} ({d['plan']}): {d['mrays_per_s']:.3f} Mrays/s")
    if not met:
        print(f"  limits: {best['steps_mean']:.1f} steps/ray (max {best['steps_max']}), "
              + (f"{limits['idle_lane_fraction']:.2f} of lane-iterations idle, "
                 if limits["idle_lane_fraction"] is not None else
                 "idle lanes not measured (persistent lanes), ")
              + f"{best['ns_per_step']:.0f} ns per ray-step; the target needs "
              f"{limits['steps_needed_per_s_for_target'] / 1e6:.1f} M ray-steps/s, measured "
              f"{limits['steps_per_s_measured'] / 1e6:.1f} M")
        if limits["batch_ns_per_box"]:
            print(f"  for scale: one flat batch of 2^16 {best['arithmetic']} box "
                  f"evaluations of barth_sextic costs {limits['batch_ns_per_box']:.0f} ns "
                  f"per box (benchmarks/results/arith_*.json): the rest of a ray-step is "
                  f"loop and packet overhead")
    print()
    return dict(goal_mrays_per_s=TARGET_MRAYS, size=size, met=met, best=best,
                candidates=[dict(label=r.get("label"), method=r["method"],
                                 arithmetic=r["arithmetic"], plan=r["plan"], tile=r["tile"],
                                 packet=r["packet"], lanes=r["lanes"],
                                 mrays_per_s=r["mrays_per_s"]) for r in cands],
                best_config=desc, best_plan=best["plan"], defaults=defaults, limits=limits)


def arith_ns_per_box(arithmetic, surface="barth_sextic"):
    """ns per box of a flat batch evaluation from bench_arith.py's results, if present."""
    path = ROOT / "results" / f"arith_{jax.default_backend()}.json"
    try:
        rows = json.loads(path.read_text())["rows"]
    except (OSError, ValueError, KeyError):
        return None
    for r in rows:
        if (r.get("surface") == surface and r.get("arithmetic") == arithmetic
                and r.get("rounding") == "fast"):
            return 1e9 / r["boxes_per_s"]
    return None


# ---------------------------------------------------------------------------- charts


def charts(plt, save, result):
    """Draws the charts of `result`; save(fig, name) writes each (`common.save_charts`)."""
    if "sweep" in result:
        names = sorted({r["surface"] for r in result["sweep"]["rows"]})
        fig, axes = plt.subplots(1, len(names), figsize=(6.5 * len(names), 5), squeeze=False)
        for ax, name in zip(axes[0], names):
            rows = [r for r in result["sweep"]["rows"] if r["surface"] == name]
            for label in dict.fromkeys(r["label"] for r in rows):
                rr = [r for r in rows if r["label"] == label]
                x = [r["mrays_per_s"] for r in rr]
                # zero pixel error cannot sit on a log axis: floor at 1 pixel's share
                floor = 0.5 / (rr[0]["size"] ** 2)
                y = [max(r["pixel_error"], floor) for r in rr]
                ax.plot(x, y, marker="o", ms=3, label=label)
                first = rr[0]
                tag = (f"{first['samples']}" if label == "sampling"
                       else log2_label(first["eps"]))
                ax.annotate(tag, (x[0], y[0]), fontsize=7)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("Mrays/s")
            ax.set_ylabel("pixel error (hit mask vs float64 ref.; 0 drawn at 1/2 px)")
            eps = result["sweep"]["eps"]
            ax.set_title(f"{name}, {result['sweep']['size']}^2, eps {log2_label(max(eps))}"
                         f"..{log2_label(min(eps))}; sampling: samples")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        save(fig, "sweep")
    if "packets" in result:
        pk = result["packets"]
        fig, ax = plt.subplots(figsize=(8, 4))
        ax.barh([r["label"] for r in pk["rows"]], [r["mrays_per_s"] for r in pk["rows"]])
        ax.set_xlabel("Mrays/s")
        ax.set_title(f"barth_sextic IA t-bisection 2^-11, {pk['size']}^2")
        ax.invert_yaxis()
        save(fig, "packets")
    if "table61" in result:
        summ = result["table61"]["summary"]
        fig, ax = plt.subplots(figsize=(10, 4))
        x = np.arange(len(summ))
        ax.bar(x - 0.2, [s["mrays_interval"] for s in summ], 0.4, label="interval")
        ax.bar(x + 0.2, [s["mrays_affine"] for s in summ], 0.4, label="affine")
        ax.set_xticks(x, [s["surface"] for s in summ], rotation=45, ha="right")
        ax.set_ylabel("Mrays/s")
        ax.set_yscale("log")
        ax.set_title(f"t-bisection, eps 2^-11, {result['table61']['size']}^2")
        ax.legend()
        save(fig, "table61")


# ---------------------------------------------------------------------------- main


def config(args):
    if args.quick:
        size = 24
        return dict(quick=True, size=size, conv_size=size,
                    table61_names=["barth_sextic", "mitchell"],
                    table62_size=size, table62_names=["mitchell"], table62_eps=[EPS_DEFAULT],
                    tiles=[8], lanes=[256], sweep_size=size, sweep_names=["mitchell"],
                    sweep_eps=[2.0**-6, 2.0**-11], samples=[16])
    return dict(quick=False, size=args.size, conv_size=args.conv_size,
                table61_names=(args.names.split(",") if args.names else ji.surfaces.names()),
                table62_size=args.table62_size, table62_names=["mitchell", "barth_decic"],
                table62_eps=[EPS_DEFAULT, 2.0**-22], tiles=[2, 4, 8, 16, 32],
                lanes=[256, 1024, 4096], sweep_size=args.sweep_size,
                sweep_names=["barth_sextic", "mitchell"], sweep_eps=list(SWEEP_EPS),
                samples=list(SAMPLES))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512, help="Table 6.1 and packet image size")
    p.add_argument("--conv-size", type=int, default=96, help="converged-eps image size")
    p.add_argument("--table62-size", type=int, default=128)
    p.add_argument("--sweep-size", type=int, default=128)
    p.add_argument("--names", default=None,
                   help="comma-separated Table 6.1 surfaces (default: the whole catalogue)")
    args, only = common.parse_args(p, argv, SECTIONS, ROOT / "results")
    if args.names:
        unknown = sorted(set(args.names.split(",")) - set(ji.surfaces.names()))
        if unknown:
            p.error(f"unknown surface(s) {unknown}")
    cfg = config(args)
    run = common.Run("implicit", args, only, cfg, default=float, numpy_version=False)
    b = Bench(args.repeats, args.slow_s)
    funcs = dict(table61=table61, table62=table62, packets=packets, sweep=sweep,
                 scalar=scalar)
    run.sections(SECTIONS, lambda sec: funcs[sec](b, cfg))
    result = run.result
    try:
        result["target"] = target(b, cfg, result)
    except Exception as e:
        traceback.print_exc()
        result["errors"]["target"] = f"{type(e).__name__}: {e}"
        result["target"] = None
    return run.finish(charts)


if __name__ == "__main__":
    main()
