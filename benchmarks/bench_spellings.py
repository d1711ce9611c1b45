"""The spelling suite (issue 28, item 5): random SDF-like networks, each activation in
several spellings, through the DEFAULT call, against a float64 reference and jitted dense
sampling on the same rays.

    python benchmarks/bench_spellings.py [--size 128] [--activations relu,elu,...]
        [--spellings jax.nn,jnp,...] [--shapes relu=4x64,...] [--ref-max 64]
        [--pilot 16] [--row-budget-s 240] [--repeats 3] [--slow-s 10]
        [--out benchmarks/results]

Networks: ``jaxiso.implicit.spellings.random_net(seed, activation, depth, width)`` (a
sphere's distance plus a random MLP, zero set inside [-1, 1]^3), one per activation, of
the shape SHAPES gives it (depth 2-8, width 16-128 over the suite; --shapes overrides),
in every spelling `spellings_of` lists that --spellings names (default
DEFAULT_SPELLINGS). All spellings of a network compute the same function to float32
rounding.

Each row (network, spelling) times what a user writes, with no option and no manual jit:
``S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params)`` (construct_s), then
``S.prepared()`` (prepare_s: the arithmetic `auto` chooses and the sign grid; the same
preparation `intersect` does on a first call, memoised by f), then ``ji.intersect(S,
rays)``. A probe first runs it on the same rays turned away from the box (every ray
misses): compile_s is that first call less the second, fixed_s the second (what a call
costs besides its rays, e.g. preparation that is not memoised); then the prepared
scene's call on those rays and on a pilot (the same with a --pilot^2 block of pixels at
the image's centre real, `pilot_block`) gives the cost per real ray; rays of one shape
compile once. When the call predicted at full size (fixed + per ray x pixels) times the
calls it would take exceeds --row-budget-s, the row keeps the prediction (``measured:
false``, run_s = est_run_s) and the pilot's hits (compared with a float64 reference of
the pilot's block); otherwise the full call runs: its first call (first_call_s =
compile_s + that call) and the median of --repeats more after a warm-up (run_s; a
warm-up slower than --slow-s is the figure alone; est_run_s stays, to judge the
prediction). Recorded with it: the arithmetic `auto` chose, its report, the sign grid's
report and the plan. ``dense``: the same spelling's point function sampled at 128 points
per ray segment in the box, the first sign change and 8 bisections, jitted
(`bench_neural.hand_sampling`), first call and median call. ``paired``: after a
network's rows, the jax.nn row, each other spelling and the dense sampling of the jax.nn
spelling run in turn for --repeats rounds (rows slower than --slow-s a call are left
out); the median of each time over the jax.nn row's (the machine's drift falls on both).

Hit masks against the float64 reference (tests/reference_spellings64.py: numpy, 1,000
samples per segment, the first sign change, bisection; cached in --cache) on a regular
ref_max^2 subsample of the pixels: agreement, false and missed hits, |t - t_ref| where
both hit. A spelling that raises records its error and the others go on.

Writes ``<out>/spellings_<backend>.json`` and the chart ``spellings_<backend>_ratios.png``
(per activation, each spelling's call time over the jax.nn spelling's, and hit-mask
disagreement).
"""

from __future__ import annotations

import argparse
import gc
import os
import pathlib
import sys

import jax
import numpy as np

import jaxiso as ji
from jaxiso.implicit import spellings as sp

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests"))
import _common as common  # noqa: E402
import bench_neural  # noqa: E402
import reference_spellings64 as ref64  # noqa: E402
from _common import fmt, now, print_table  # noqa: E402

SECTIONS = ("spellings",)
LO, HI = (-1.0,) * 3, (1.0,) * 3
EYE, FOV, UP = (2.0, 1.3, 1.0), 32.0, (0.0, 0.0, 1.0)
SEED = 0
# depth x width per activation: depths 2..8 and widths 16..128 over the suite
SHAPES = {"relu": (4, 64), "elu": (8, 32), "leaky_relu": (3, 128), "softplus": (2, 32),
          "softplus_t8": (3, 64), "sin": (3, 32), "tanh": (5, 16), "gelu": (2, 128),
          "silu": (6, 32), "layer_norm": (4, 32)}
BASE = "jax.nn"
# equinox.partition (the module's arrays as params) ran as fast as jax.nn in a 16^2
# trial (tests/test_spellings.py covers it): left out of the default run to save time
DEFAULT_SPELLINGS = ("jax.nn", "jnp", "jnp.where", "equinox", "equinox.params")
SLOW_S = 10.0  # this benchmark's default --slow-s


def camera(size):
    return ji.Camera.look_at(EYE, (0.0, 0.0, 0.0), UP, FOV, size, size)


def dense_call(spelled, rays, cfg):
    """(call, extract) of jitted dense sampling with the spelling's point function."""
    trace = bench_neural.hand_sampling(spelled.point, cfg["dense_samples"],
                                       cfg["dense_bisections"])
    h, w = rays.origin.shape[:2]
    o, d = rays.origin.reshape(-1, 3), rays.direction.reshape(-1, 3)
    return (lambda: trace(spelled.params, o, d)), (
        lambda out: tuple(np.asarray(a).reshape(h, w) for a in out))


def pilot_rays(rays, rows):
    """(idle, pilot): the rays turned away from the box (every ray misses: no work), and
    the same with the pixels rows x rows real. Same shapes as `rays`, so the default call
    compiles once for all three."""
    o, d = np.asarray(rays.origin), np.asarray(rays.direction)
    real = np.zeros(o.shape[:2], bool)
    real[np.ix_(rows, rows)] = True
    pd = np.where(real[..., None], d, -d)
    return ji.Rays(rays.origin, -rays.direction), ji.Rays(rays.origin, jax.numpy.asarray(pd))


def timed(call):
    t0 = now()
    out = jax.block_until_ready(call())
    return out, now() - t0


def budget_probe(call, prepared_call, idle, pilot, n, n_pilot):
    """Compiles the default call on idle rays, times it on idle rays again (the call's
    fixed cost: dispatch, and preparation where it is not memoised), then the prepared
    scene's call on idle rays and on the pilot (the cost per real ray, apart from any
    preparation, whose time varies more than a pilot's rays take). Returns (compile s,
    fixed s, pilot s, predicted call s at n rays, the pilot's hits)."""
    _, first = timed(lambda: call(idle))
    _, fixed = timed(lambda: call(idle))
    jax.block_until_ready(prepared_call(idle))  # compiles where the scene's statics differ
    _, idle_s = timed(lambda: prepared_call(idle))
    hits, pilot_s = timed(lambda: prepared_call(pilot))
    per_ray = max(pilot_s - idle_s, 0.0) / n_pilot
    return max(first - fixed, 0.0), fixed, pilot_s, fixed + per_ray * n, hits


def default_row(spelled, rays, pilot_rows, cfg):
    """Times the default call of one spelling: (row dict, (hit, t, steps) [H, W] (on the
    pilot's pixels only when not measured), the call for pairing)."""
    t0 = now()
    S = ji.ImplicitSurface(spelled.f, LO, HI, params=spelled.params)
    construct = now() - t0
    t0 = now()
    P = S.prepared()
    prepare = now() - t0
    n = int(np.prod(rays.origin.shape[:2]))
    call = lambda r: ji.intersect(S, r)
    compile_s, fixed, pilot_s, est, hits = budget_probe(
        call, lambda r: ji.intersect(P, r), *pilot_rays(rays, pilot_rows), n,
        len(pilot_rows) ** 2)
    row = dict(call="ji.intersect(ji.ImplicitSurface(f, lo, hi, params=params), rays)",
               construct_s=construct, prepare_s=prepare, compile_s=compile_s,
               fixed_s=fixed, pilot_s=pilot_s, pilot_pixels=len(pilot_rows) ** 2,
               est_run_s=est, arithmetic=P.arithmetic,
               arithmetic_report=P.arithmetic_report, culling_report=P.culling_report,
               plan=repr(ji.plan_for(P, n)))
    calls = 2 + (cfg["repeats"] if est <= cfg["slow_s"] else 0)
    if cfg["row_budget_s"] and est * calls > cfg["row_budget_s"]:
        row.update(measured=False, run_s=est, first_call_s=compile_s + est)
    else:
        hits, first = timed(lambda: call(rays))
        hits, timing = common.time_calls(lambda: call(rays), cfg["repeats"], cfg["slow_s"])
        row.update(measured=True, first_call_s=compile_s + first, **timing)
    row["rays_per_s"] = n / row["run_s"]
    shape = rays.origin.shape[:2]
    out = (np.asarray(hits.hit).reshape(shape), np.asarray(hits.t, np.float64).reshape(shape),
           np.asarray(hits.steps).reshape(shape))
    return row, out, (lambda: call(rays))


def dense_row(spelled, rays, cfg):
    call, extract = dense_call(spelled, rays, cfg)
    t0 = now()
    jax.block_until_ready(call())
    first = now() - t0
    out, timing = common.time_calls(call, cfg["repeats"], cfg["slow_s"])
    return dict(first_call_s=first, **timing), extract(out), call


def reference(net, rays, idx, cfg, tag=""):
    """(t_ref [R, R] of the pixels idx x idx, seconds (0: cached))."""
    size = rays.origin.shape[0]
    o, d = bench_neural.flat64(bench_neural.sub_rays(rays, idx, idx))
    t, secs = ref64.cached_first_hits(
        net.activation, net.layers, ref64.constants(sp), o, d, cfg["cache"],
        f"spell_{net.activation}_{net.depth}x{net.width}_s{net.seed}_{size}{tag}", LO, HI,
        samples=cfg["ref_samples"])
    return t.reshape(len(idx), len(idx)), secs


def pilot_block(size, pilot):
    """The rows (and columns) of the pilot: a contiguous block at the image's centre,
    where the surface is (full packets of rays, as at full size; a strided subsample puts
    one real ray in a packet of idle ones and predicted 3-25x too much)."""
    start = max(0, size // 2 - pilot // 2)
    return np.arange(start, min(size, start + pilot))


def spelling_rows(net, rays, idx, t_ref, cfg, spellings):
    """One row per spelling of net (errors recorded), and the calls to pair."""
    rows, calls = [], {}
    block = pilot_block(rays.origin.shape[0], cfg["pilot"])
    t_block = None
    for spelling in spellings(net.activation):
        row = dict(activation=net.activation, network=net.name, depth=net.depth,
                   width=net.width, seed=net.seed, spelling=spelling)
        try:
            spelled = sp.spell(net, spelling)
            d, (hit, t, steps), call = default_row(spelled, rays, block, cfg)
            if not d["measured"] and t_block is None:
                t_block, _ = reference(net, rays, block, cfg, "_pilot")
            px, ref = (idx, t_ref) if d["measured"] else (block, t_block)
            row.update(d, **bench_neural.work(hit[px][:, px], steps[px][:, px]),
                       **bench_neural.agreement(hit[px][:, px], t[px][:, px], ref))
            if d["measured"] and row["run_s"] <= cfg["slow_s"]:
                calls[spelling] = call
            dn, (dhit, dt, _), dcall = dense_row(spelled, rays, cfg)
            dn.update(bench_neural.agreement(dhit[idx][:, idx], dt[idx][:, idx], t_ref))
            row["dense"] = dn
            if spelling == BASE:
                calls["dense"] = dcall
        except Exception as e:  # a spelling that fails leaves the others
            row["error"] = f"{type(e).__name__}: {str(e)[:400]}"
            print(f"  {spelling} FAILED: {row['error']}", flush=True)
        row["load_avg"] = list(os.getloadavg())  # 1, 5, 15 min, at the row's end
        rows.append(row)
    return rows, calls


def add_ratios(rows, calls, cfg):
    """Each row's run_s over the jax.nn row's, and over its own dense sampling's; the
    paired medians where both ran fast enough to pair."""
    base = next((r for r in rows if r["spelling"] == BASE and "error" not in r), None)
    paired = (bench_neural.paired_speedups(calls, BASE, cfg["repeats"])
              if BASE in calls and len(calls) > 1 and cfg["repeats"] else {})
    for r in rows:
        if "error" in r:
            continue
        if base is not None:
            r["ratio_to_jax_nn"] = r["run_s"] / base["run_s"]
            r["first_picture_ratio_to_jax_nn"] = (
                (r["prepare_s"] + r["first_call_s"]) / (base["prepare_s"] + base["first_call_s"]))
        r["ratio_to_dense"] = r["run_s"] / r["dense"]["run_s"]
        if r["spelling"] in paired:
            r["paired_ratio_to_jax_nn"] = paired[r["spelling"]]
        if "dense" in paired and (r["spelling"] in paired or r["spelling"] == BASE):
            r["paired_ratio_to_dense"] = paired.get(r["spelling"], 1.0) / paired["dense"]
    return paired


def print_rows(rows):
    printed = []
    for r in rows:
        if "error" in r:
            printed.append([r["spelling"], "CRASH"] + ["-"] * 9)
            continue
        printed.append([r["spelling"], r["arithmetic"], fmt(r["prepare_s"], ".1f"),
                        fmt(r["compile_s"], ".1f"),
                        fmt(r["run_s"], ".3f") + ("" if r["measured"] else "~"),
                        fmt(r.get("ratio_to_jax_nn"), ".2f"),
                        fmt(r.get("paired_ratio_to_jax_nn"), ".2f"),
                        fmt(r["dense"]["run_s"], ".3f"),
                        fmt(r.get("paired_ratio_to_dense", r["ratio_to_dense"]), ".2f"),
                        fmt(r["mask_agreement"], ".4f"), fmt(r["dense"]["mask_agreement"], ".4f")])
    print_table(["spelling", "arith", "prepare s", "compile s", "call s", "/jax.nn",
                 "paired", "dense s", "/dense", "agree", "dense agree"], printed)
    if any("error" not in r and not r["measured"] for r in rows):
        print("  ~: over the row budget: the call predicted from the pilot (agreement on "
              "the pilot's pixels)\n")


def spellings_section(cfg, spellings, save):
    """spellings(activation) -> the spellings to run; save(partial section) after each
    network (a crash keeps what was measured). JAX's and jaxiso's caches are emptied
    between networks: every compiled program holds memory maps, and one process that
    compiles them all passes the kernel's vm.max_map_count ("LLVM ERROR: Unable to
    allocate section memory", seen at the fifth network)."""
    rays = camera(cfg["size"]).rays()
    rows, refs = [], []
    for activation in cfg["activations"]:
        depth, width = cfg["shapes"][activation]
        net = sp.random_net(SEED, activation, depth, width)
        idx = common.subsample(cfg["size"], min(cfg["size"], cfg["ref_max"]))
        t_ref, secs = reference(net, rays, idx, cfg)
        refs.append(dict(network=net.name, seconds=secs, cached=secs == 0.0,
                         ref_size=len(idx), hit_fraction=float(np.mean(np.isfinite(t_ref)))))
        print(f"== {net.name} at {cfg['size']}^2: float64 reference on {len(idx)}^2 pixels "
              + ("(cached)" if secs == 0.0 else f"({secs:.0f} s)")
              + f", hit fraction {refs[-1]['hit_fraction']:.3f}", flush=True)
        mine, calls = spelling_rows(net, rays, idx, t_ref, cfg, spellings)
        paired = add_ratios(mine, calls, cfg)
        print_rows(mine)
        if paired:
            print("  paired (median of rounds, time / jax.nn's): "
                  + ", ".join(f"{k} {v:.2f}x" for k, v in paired.items()) + "\n", flush=True)
        rows.extend(mine)
        save(section(cfg, refs, rows))
        del calls
        jax.clear_caches()
        ji.clear_caches()
        gc.collect()
    return section(cfg, refs, rows)


def section(cfg, refs, rows):
    return dict(size=cfg["size"], eye=EYE, fov=FOV, lo=LO, hi=HI, seed=SEED,
                constants=ref64.constants(sp),
                reference=dict(module="tests/reference_spellings64.py",
                               samples=cfg["ref_samples"], tol=ref64.TOL,
                               ref_max=cfg["ref_max"], runs=refs),
                rows=rows, summary=summary(rows))


def summary(rows):
    """What the issue's 'done when' asks of each spelling, in lists of row names."""
    def name(r):
        return f"{r['activation']}/{r['spelling']}"
    ok = [r for r in rows if "error" not in r]
    return dict(crashed=[name(r) for r in rows if "error" in r],
                disagree=[name(r) for r in ok if r["mask_agreement"] < 0.995],
                slower_than_1_5x=[name(r) for r in ok if r["spelling"] != BASE and
                                  r.get("paired_ratio_to_jax_nn",
                                        r.get("ratio_to_jax_nn", 0.0)) > 1.5],
                slower_than_dense=[name(r) for r in ok if r.get(
                    "paired_ratio_to_dense", r["ratio_to_dense"]) > 1.0])


def charts(plt, save, result):
    """Per activation and spelling: call time over the same spelling's dense sampling,
    over the jax.nn spelling's, and hit-mask disagreement (hatched: predicted rows)."""
    if "spellings" not in result:
        return
    rows = result["spellings"]["rows"]
    acts = list(dict.fromkeys(r["activation"] for r in rows))
    spellings = [s for s in sp.SPELLINGS if any(r["spelling"] == s for r in rows)]
    colours = {s: plt.cm.tab10(i) for i, s in enumerate(spellings)}
    fig, axes = plt.subplots(3, 1, figsize=(max(8, 1.1 * len(acts) + 2), 11), sharex=True)
    width = 0.8 / max(1, len(spellings))
    for i, a in enumerate(acts):
        for j, s in enumerate(spellings):
            r = next((r for r in rows if r["activation"] == a and r["spelling"] == s), None)
            if r is None:
                continue
            x = i + (j - (len(spellings) - 1) / 2) * width
            if "error" in r:
                for ax, y in zip(axes, (1.0, 1.0, 1e-4)):
                    ax.text(x, y, "X", color=colours[s], ha="center", fontsize=11)
                continue
            style = dict(color=colours[s], hatch=None if r["measured"] else "//",
                         edgecolor="k" if not r["measured"] else colours[s])
            axes[0].bar(x, r.get("paired_ratio_to_dense", r["ratio_to_dense"]), width, **style)
            axes[1].bar(x, r.get("paired_ratio_to_jax_nn", r.get("ratio_to_jax_nn", np.nan)),
                        width, **style)
            dis = 1.0 - r["mask_agreement"]
            if dis > 0:
                axes[2].bar(x, dis, width, **style)
            else:
                axes[2].plot(x, 2e-5, "o", color=colours[s], ms=4)
    axes[0].axhline(1.0, color="k", ls="--", lw=1, label="dense sampling, 128 per ray")
    axes[0].set_ylabel("call time / dense sampling's\n(same spelling, same rays)")
    axes[1].axhline(1.5, color="r", ls="--", lw=1, label="1.5x the jax.nn spelling")
    axes[1].set_ylabel("call time / jax.nn spelling's")
    axes[2].axhline(0.005, color="r", ls="--", lw=1, label="0.5% (the issue's bar)")
    axes[2].set_ylim(1e-5, 1.0)
    axes[2].set_ylabel("hit-mask disagreement with\nfloat64 (dot: none on its pixels)")
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(True, axis="y", which="major", alpha=0.3)
    axes[2].set_xticks(range(len(acts)))
    axes[2].set_xticklabels([next(r["network"] for r in rows if r["activation"] == a)
                             .replace(" seed 0", "") for a in acts], rotation=30, ha="right")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[s], label=s) for s in spellings]
    handles.append(plt.Rectangle((0, 0), 1, 1, facecolor="w", edgecolor="k", hatch="//",
                                 label="predicted (over the row budget)"))
    axes[0].legend(handles=handles + axes[0].get_legend_handles_labels()[0], fontsize=8)
    axes[1].legend(fontsize=8)
    axes[2].legend(fontsize=8)
    axes[0].set_title(f"Spellings through the default call, {result['spellings']['size']}^2 "
                      "(X: crashed)")
    save(fig, "ratios")


def parse_shapes(text, parser):
    shapes = dict(SHAPES)
    for item in (s.strip() for s in text.split(",") if s.strip()):
        name, _, shape = item.partition("=")
        try:
            depth, width = (int(v) for v in shape.lower().split("x"))
        except ValueError:
            parser.error(f"--shapes wants NAME=DEPTHxWIDTH, got {item!r}")
        shapes[name] = (depth, width)
    return shapes


def config(args, parser):
    acts = [a.strip() for a in args.activations.split(",") if a.strip()]
    bad = sorted(set(acts) - set(sp.ACTIVATIONS))
    if bad:
        parser.error(f"unknown activation(s) {bad}; choose from {sp.ACTIVATIONS}")
    wanted = [s.strip() for s in args.spellings.split(",") if s.strip()]
    if sorted(set(wanted) - set(sp.SPELLINGS)):
        parser.error(f"unknown spelling(s) in {wanted}; choose from {sp.SPELLINGS}")
    shapes = parse_shapes(args.shapes, parser)
    cfg = dict(size=args.size, activations=acts, wanted_spellings=wanted,
               shapes={a: list(shapes[a]) for a in acts}, ref_samples=args.ref_samples,
               ref_max=args.ref_max, pilot=args.pilot, row_budget_s=args.row_budget_s,
               repeats=args.repeats, slow_s=args.slow_s,
               cache=str(args.cache), dense_samples=bench_neural.HAND_SAMPLES,
               dense_bisections=bench_neural.HAND_BISECTIONS)
    return cfg, lambda a: [s for s in sp.spellings_of(a) if s in wanted]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=128, help="image size (pixels^2)")
    p.add_argument("--activations", default=",".join(sp.ACTIVATIONS))
    p.add_argument("--spellings", default=",".join(DEFAULT_SPELLINGS),
                   help=f"a subset of {','.join(sp.SPELLINGS)}")
    p.add_argument("--shapes", default="", help="NAME=DEPTHxWIDTH,... (default SHAPES)")
    p.add_argument("--ref-samples", type=int, default=ref64.SAMPLES)
    p.add_argument("--ref-max", type=int, default=64,
                   help="the reference covers at most ref_max^2 pixels (a subsample)")
    p.add_argument("--pilot", type=int, default=16, help="pilot size (pixels^2)")
    p.add_argument("--row-budget-s", type=float, default=240.0,
                   help="rows predicted longer run as the pilot only (0: no limit)")
    p.add_argument("--cache", default=str(ROOT / "results" / "cache"),
                   help="where float64 references are cached")
    args, only = common.parse_args(p, argv, SECTIONS, ROOT / "results")
    given = sys.argv[1:] if argv is None else argv
    if not any(a.startswith("--slow-s") for a in given):
        args.slow_s = SLOW_S
    cfg, spellings = config(args, p)
    run = common.Run("spellings", args, only, cfg)

    def save(partial):
        run.result["spellings"] = partial
        run.save()
    run.sections(SECTIONS, lambda sec: spellings_section(cfg, spellings, save))
    return run.finish(charts)


if __name__ == "__main__":
    main()
