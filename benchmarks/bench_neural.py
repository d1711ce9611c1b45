"""Neural implicit MLPs (issue 13): speed and agreement with a float64 reference of jaxiso
and its baselines on the public networks of "Spelunking the Deep", and the tightness of
each arithmetic on ray pieces of the networks.

    python benchmarks/bench_neural.py [--quick] [--sizes 256,512] [--networks fox,...]
        [--extra NAME=PATH.npz] [--spelunking PATH] [--tightness] [--row-budget-s 240]
        [--only rays,tightness] [--out benchmarks/results]

Networks: /work/shared/data/neural/{fox,bunny,hammer,birdcage_occ}.npz (--data; domain
[-1, 1]^3, inside where f < 0), loaded with ``ji.implicit.load_mlp``; fox and bunny are
signed distance functions (--sdf), hammer and birdcage_occ are not. --extra adds networks
of the same layout. Each network has its own camera (VIEWS), at size^2 pixels: 128^2
(--quick), 256^2 and 512^2 (full), or --sizes.

Section ``rays``, one row per network, size and caster, all on the same rays:
  jaxiso default   ``ji.intersect(S, rays)`` with ``S = ji.ImplicitSurface(m, lo, hi,
                   params=m.params, eps=2^-10)``: whatever the defaults are at run time
                   (the row records the scene's options, e.g. ``arithmetic``)
                   (the scene's construction, which builds the sign grid, is timed
                   apart: ``construct_s``)
  jaxiso interval / affine   the same with that arithmetic
  jaxiso verify=sign   hits by sign change only
  jaxiso culling=none  the default without the sign grid (every ray walks its segment)
  sphere L=net     method "sphere" with ``lipschitz=m.lipschitz`` (product of spectral
                   norms: a true bound, so guaranteed but tiny steps; default max_steps)
  sphere L=1       SDF networks only: the fast unguaranteed baseline
  hand sampling    what a user writes without jaxiso: 128 point evaluations per ray,
                   jitted, the first sign change, then 8 bisection steps
  spelunking       (--spelunking PATH, a checkout of nmwsharp/neural-implicit-queries)
                   its ``queries.cast_rays`` with its default options and mode
                   affine_fixed, rays started at their box entry (see `Spelunking`)
Metrics: rays/s (median of --repeats calls after the first call and a warm-up,
block_until_ready), the first call (compile + run) apart, evaluations per ray (mean of
the caster's step counter; its unit is in ``steps_unit``), and against the float64
reference (tests/reference_neural64.py: 4,000 samples per ray segment in the box, the
first sign change, bisection to ~1e-9; cached in --cache, not committed): the share of
pixels whose hit/miss agrees, false hits and missed hits, and |t - t_ref| (median, 99th
percentile) where both hit. paired_speedup (on the default row): after a network's rows,
the default call and each peer run in turn for --repeats rounds; the median of the peer's
time over the default's (the machine's drift falls on both alike). Above --ref-max the
reference (and the comparison) covers a regular ref_max^2 subsample of the pixels.

A row whose full run would take longer than --row-budget-s (a pilot run on a regular
--pilot^2 subsample of the pixels, extrapolated to first call + warm-up + repeats) is
not run at full size: it records ``measured: false``, the pilot's rays/s and its
agreement on the pilot's pixels (a shared 2-core CPU cannot afford 10-minute calls;
--row-budget-s 0 measures every row).

Section ``tightness`` (always in full mode, with --tightness in quick mode): enclosure
width / true range of each network on ray pieces of length 2^-4 .. 2^-14 of the domain
edge, for interval, affine and affine+grid through ``ji.extend``: affine gets one
noise symbol (the piece's parameter), interval the piece's axis box (as the ray tracer
builds them), affine+grid the sign grid's arithmetic: the affine form with fresh
symbols for the nonlinearities' errors (the grid's ``fresh_symbols`` cap and
``fresh_per_op``: 8 per relu, 24 per elu). Pieces are
centred at points near the surface (the smallest |f| of uniform samples) along random
directions; the true range is the float64 range of 257 points along the piece. Median
per length.

Writes ``<out>/neural_<backend>.json`` and charts ``neural_<backend>_scatter.png``
(rays/s against hit-mask disagreement, per network) and ``..._tightness.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import importlib
import io
import pathlib
import sys
import time
import types
import typing

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxiso as ji

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests"))
import _common as common  # noqa: E402
import reference_neural64 as ref64  # noqa: E402
import reference_trace64  # noqa: E402
from _common import fmt, now, print_table  # noqa: E402

SECTIONS = ("rays", "tightness")
DATA = pathlib.Path("/work/shared/data/neural")
NETWORKS = ("fox", "bunny", "hammer", "birdcage_occ")
SDF_NETWORKS = ("fox", "bunny")
LO, HI = (-1.0,) * 3, (1.0,) * 3
EPS = 2.0**-10
# eye, fov (degrees); target the origin, y up (the networks' convention)
VIEWS = {"fox": ((3.0, 0.8, 1.2), 35.0), "bunny": ((1.8, 1.2, 2.6), 40.0),
         "hammer": ((1.0, 2.8, 1.6), 36.0), "birdcage_occ": ((2.4, 1.2, 2.0), 40.0)}
DEFAULT_VIEW = ((1.8, 1.2, 2.6), 40.0)
UP = (0.0, 1.0, 0.0)
HAND_SAMPLES = 128
HAND_BISECTIONS = 8
TIGHT_LENGTHS = tuple(2.0**-k for k in range(4, 15))  # of the domain edge
TIGHT_SAMPLES = 257
TIGHT_ARITHMETICS = ("interval", "affine", "affine+grid")  # the last: the sign grid's
SLOW_S = 60.0  # this benchmark's default --slow-s


class Network(typing.NamedTuple):
    name: str
    path: pathlib.Path
    mlp: object  # ji.implicit.MLP
    sdf: bool
    view: tuple


def camera(net, size):
    eye, fov = net.view
    return ji.Camera.look_at(eye, (0.0, 0.0, 0.0), UP, fov, size, size)


def user_scene(net):
    """The scene a user writes first for a network: defaults except eps."""
    m = net.mlp
    return ji.ImplicitSurface(m, lo=LO, hi=HI, params=m.params, eps=EPS)


def scene_options(S):
    """The scene's options for a row's JSON: every field but the function, the weights
    and the box (so options added later show up too); traced scalars as floats."""
    out = {}
    for f in dataclasses.fields(S):
        if f.name in ("f", "params", "lo", "hi"):
            continue
        v = getattr(S, f.name)
        if isinstance(v, ji.implicit.SignGrid):
            out[f.name] = {"resolution": list(v.resolution)}
        elif f.name == "facts" and v is not None:
            out[f.name] = {"heavy": v.heavy, "long_program": v.tape is not None}
        elif v is None or isinstance(v, str | bool | int | float):
            out[f.name] = v
        elif np.size(v) == 1:
            out[f.name] = float(np.asarray(v).reshape(()))
        else:
            out[f.name] = np.asarray(v).tolist()
    return out


def sub_rays(rays, rows, cols):
    """The rays of the pixels rows x cols of an image of rays [H, W]."""
    o = np.asarray(rays.origin)[rows][:, cols]
    d = np.asarray(rays.direction)[rows][:, cols]
    return ji.Rays(jnp.asarray(o), jnp.asarray(d))


def flat64(rays):
    """(origins, directions) [N, 3] float64 of rays of any batch shape."""
    return (np.asarray(rays.origin, np.float64).reshape(-1, 3),
            np.asarray(rays.direction, np.float64).reshape(-1, 3))


# ---------------------------------------------------------------------------- casters
# Each caster is make(rays [h, w]) -> (call, extract): call() runs it (no arguments, the
# value a jitted call returns), extract(value) -> (hit, t, steps) numpy [h, w].


def jaxiso_caster(S):
    def make(rays):
        h, w = rays.origin.shape[:2]

        def extract(hits):
            return (np.asarray(hits.hit).reshape(h, w),
                    np.asarray(hits.t, np.float64).reshape(h, w),
                    np.asarray(hits.steps).reshape(h, w))
        return (lambda: ji.intersect(S, rays)), extract
    return make


def hand_sampling(m, samples=HAND_SAMPLES, bisections=HAND_BISECTIONS, batch=256):
    """Dense sampling as a user writes it without jaxiso: jitted, `samples` points per
    ray segment in the box [-1, 1]^3, the first sign change, `bisections` halvings.
    Returns trace(params, origins [N, 3], directions [N, 3]) -> (hit, t, evaluations)."""
    def f(p, params):
        return m(p[0], p[1], p[2], params)

    def one_ray(params, o, d):
        # the segment inside the box (slab method; 1/0 = inf is fine here)
        ta, tb = (-1.0 - o) / d, (1.0 - o) / d
        t0 = jnp.maximum(jnp.max(jnp.minimum(ta, tb)), 0.0)
        t1 = jnp.min(jnp.maximum(ta, tb))
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, samples)
        neg = jax.vmap(lambda t: f(o + t * d, params))(ts) < 0.0
        change = neg[1:] != neg[:-1]
        k = jnp.argmax(change)
        hit = (t0 < t1) & jnp.any(change)

        def halve(_, ab):
            a, b = ab
            mid = 0.5 * (a + b)
            left = (f(o + mid * d, params) < 0.0) != neg[k]  # the change is in [a, mid]
            return jnp.where(left, a, mid), jnp.where(left, mid, b)

        a, b = lax.fori_loop(0, bisections, halve, (ts[k], ts[k + 1]))
        return hit, jnp.where(hit, 0.5 * (a + b), jnp.inf)

    @functools.partial(jax.jit, static_argnums=(0, 1))
    def traced(tree, static, arrays, origins, directions):
        params = _rejoin(tree, static, arrays)
        # batches of rays bound the [batch, samples, width] activations
        hit, t = lax.map(lambda od: one_ray(params, *od), (origins, directions),
                         batch_size=batch)
        # every ray evaluates all its points (a miss of the box too)
        return hit, t, jnp.full(hit.shape, samples + bisections, jnp.int32)

    def trace(params, origins, directions):
        # params' leaves that are no arrays (an equinox module's activation function)
        # are static, as equinox.filter_jit would make them
        leaves, tree = jax.tree_util.tree_flatten(params)
        static = tuple(None if _is_array(x) else x for x in leaves)
        arrays = [x for x in leaves if _is_array(x)]
        return traced(tree, static, arrays, origins, directions)
    return trace


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic, float, int))


def _rejoin(tree, static, arrays):
    arrays = iter(arrays)
    return jax.tree_util.tree_unflatten(
        tree, [next(arrays) if x is None else x for x in static])


def hand_caster(net, trace):
    def make(rays):
        h, w = rays.origin.shape[:2]
        o, d = rays.origin.reshape(-1, 3), rays.direction.reshape(-1, 3)

        def extract(out):
            return tuple(np.asarray(a).reshape(h, w) for a in out)
        return (lambda: trace(net.mlp.params, o, d)), extract
    return make


class Spelunking:
    """The ray caster of nmwsharp/neural-implicit-queries ("Spelunking the Deep", Sharp &
    Jacobson 2022) run from a local checkout (never vendored): its modules are imported
    from ``PATH/src`` with stub modules standing in for the GUI and plotting imports it
    makes at module level, then removed from ``sys.modules`` again (their names, e.g.
    ``utils``, ``render``, are generic). Its ``jnp.clip(a_min=, a_max=)`` calls, whose
    keywords newer JAX removed, go through a ``jnp`` proxy given to its modules only."""

    STUBS = ("polyscope", "polyscope.imgui", "imageio", "matplotlib", "matplotlib.pyplot")
    MODULES = ("utils", "render", "geometry", "queries", "bucketing", "implicit_function",
               "affine", "affine_layers", "mlp", "sdf", "slope_interval",
               "slope_interval_layers", "implicit_mlp_utils")

    def __init__(self, path):
        src = pathlib.Path(path) / "src"
        if not (src / "queries.py").exists():
            raise FileNotFoundError(f"{src / 'queries.py'} not found")
        saved = {n: sys.modules.get(n) for n in self.STUBS + self.MODULES}
        for n in self.STUBS:
            sys.modules[n] = types.ModuleType(n)
        sys.path.insert(0, str(src))
        try:
            self.queries = importlib.import_module("queries")
            self.utils = importlib.import_module("implicit_mlp_utils")
            mods = [sys.modules[n] for n in self.MODULES if n in sys.modules]
        finally:
            sys.path.remove(str(src))
            for n, m in saved.items():
                if m is None:
                    sys.modules.pop(n, None)
                else:
                    sys.modules[n] = m
        proxy = _ClipProxy("jax.numpy (a_min/a_max clip)")
        for m in mods:
            if getattr(m, "jnp", None) is jnp:
                m.jnp = proxy
        self.path = str(path)

    def load(self, npz, mode):
        """(implicit function, params) of a network file in one of its modes."""
        with contextlib.redirect_stdout(io.StringIO()):  # it prints the parameter count
            return self.utils.generate_implicit_from_file(str(npz), mode=mode)

    def caster(self, net, mode):
        func, params = self.load(net.path, mode)
        cast = self.queries.cast_rays

        def make(rays):
            # rays start at their entry into the domain box (the network is only trained
            # there, and the reference and jaxiso look inside it only); the rays that miss
            # the box are not cast; a hit beyond the ray's box exit is a miss
            h, w = rays.origin.shape[:2]
            o, d = flat64(rays)
            t0, t1, valid = reference_trace64.clip_to_box(LO, HI, o, d, 0.0)
            sel = np.nonzero(valid)[0]
            roots = jnp.asarray(o[sel] + t0[sel, None] * d[sel], jnp.float32)
            dirs = jnp.asarray(d[sel], jnp.float32)
            opts = self.queries.get_default_cast_opts()
            seg = t1[sel] - t0[sel]
            opts["max_dist"] = float(seg.max()) if sel.size else 1.0

            def call():
                if not sel.size:
                    return ()
                t, hit_id, count, _ = cast((func,), (params,), roots, dirs, opts)
                return t, hit_id, count

            def extract(out):
                hit, t, steps = (np.zeros(h * w, bool), np.full(h * w, np.inf),
                                 np.zeros(h * w, np.int64))
                if out:
                    ts, hid, count = (np.asarray(a) for a in out)
                    ok = (hid > 0) & (ts <= seg)
                    hit[sel] = ok
                    t[sel] = np.where(ok, t0[sel] + ts, np.inf)
                    steps[sel] = count
                return hit.reshape(h, w), t.reshape(h, w), steps.reshape(h, w)
            make.opts = opts
            return call, extract
        return make


class _ClipProxy(types.ModuleType):
    """jax.numpy, except that clip also takes the old a_min / a_max keywords."""

    def __getattr__(self, name):
        return getattr(jnp, name)

    @staticmethod
    def clip(a, a_min=None, a_max=None, **kw):
        return jnp.clip(a, kw.pop("min", a_min), kw.pop("max", a_max), **kw)


# ---------------------------------------------------------------------------- rows


def agreement(hit, t, t_ref):
    """Hit masks and depths against the reference (arrays of one shape; t_ref inf: no
    hit)."""
    ref_hit = np.isfinite(t_ref)
    both = hit & ref_hit
    err = np.abs(t[both] - t_ref[both])
    return dict(mask_agreement=float(np.mean(hit == ref_hit)),
                false_hits=float(np.mean(hit & ~ref_hit)),
                missed_hits=float(np.mean(~hit & ref_hit)),
                both_hit=int(both.sum()), compared=int(hit.size),
                depth_err_median=float(np.median(err)) if err.size else None,
                depth_err_p99=float(np.percentile(err, 99)) if err.size else None)


def work(hit, steps):
    steps = np.asarray(steps, np.int64)
    stuck = (steps == steps.max()) & ~hit if steps.max() > 0 else np.zeros_like(hit)
    return dict(steps_mean=float(steps.mean()), steps_max=int(steps.max()),
                hit_fraction=float(np.mean(hit)),
                # rays that ran as long as the longest one and found nothing: for a
                # caster with a step bound, those that ran out of steps
                at_max_no_hit=float(np.mean(stuck)))


def measure(make, rays, pilot, budget, repeats, slow_s):
    """Times one caster on rays [H, W]: returns (timing dict, (hit, t, steps) of the run,
    the compiled call at full size, or None where the pilot stood in).

    With a budget and `pilot` (rays of a pixel subsample), the pilot runs first (first
    call, then one timed call); when first call + warm-up + repeats at full size, scaled
    from it by the pixel count, would exceed the budget, the pilot's figures are
    returned instead (measured False)."""
    n = int(np.prod(rays.origin.shape[:2]))
    if budget and pilot is not None:
        call, extract = make(pilot)
        t0 = now()
        jax.block_until_ready(call())
        first = now() - t0
        t0 = now()
        out = jax.block_until_ready(call())
        run = now() - t0
        n_p = int(np.prod(pilot.origin.shape[:2]))
        est = run * n / n_p
        if est * (2 + repeats) > budget:
            return (dict(measured=False, pixels_run=n_p, first_call_s=first, run_s=run,
                         est_run_s=est, repeats_used=1, rays_per_s=n_p / run),
                    extract(out), None)
    call, extract = make(rays)
    t0 = now()
    jax.block_until_ready(call())
    first = now() - t0
    out, timing = common.time_calls(call, repeats, slow_s)
    return (dict(measured=True, pixels_run=n, first_call_s=first, **timing,
                 rays_per_s=n / timing["run_s"]), extract(out), call)


def paired_speedups(calls, base, repeats):
    """{label: median over `repeats` rounds of (label's time / base's time)}: each round
    calls base and every other caster once, in turn, so that the machine's drift (+-25%
    over minutes on the 2-core CPU) falls on both sides of each ratio alike."""
    ratios = {label: [] for label in calls if label != base}
    for _ in range(repeats):
        t0 = now()
        jax.block_until_ready(calls[base]())
        t_base = now() - t0
        for label in ratios:
            t0 = now()
            jax.block_until_ready(calls[label]())
            ratios[label].append((now() - t0) / t_base)
    return {label: float(np.median(r)) for label, r in ratios.items()}


DEFAULT = "jaxiso default"


def casters(net, cfg, spelunking):
    """(label, kind, description dict, make) for every caster run on a network."""
    start = time.perf_counter()
    S = user_scene(net).prepared()  # construction checks; preparation measures, builds
    construct_s = time.perf_counter() - start
    lip = net.mlp.lipschitz
    jx = [(DEFAULT, S, "ji.intersect(S, rays)"),

          ("jaxiso interval", S.replace(arithmetic="interval"),
           "ji.intersect(S.replace(arithmetic='interval'), rays)"),
          ("jaxiso affine", S.replace(arithmetic="affine"),
           "ji.intersect(S.replace(arithmetic='affine'), rays)"),
          # hits by sign change only: no first-order "touching" pieces (grazing rays at
          # silhouettes, which the sign-change reference counts as misses)
          ("jaxiso verify=sign", S.replace(verify="sign"),
           "ji.intersect(S.replace(verify='sign'), rays)"),
          # the walk over the whole segment, without the sign grid
          ("jaxiso culling=none", S.replace(culling="none"),
           "ji.intersect(S.replace(culling='none'), rays)"),
          ("sphere L=net", S.replace(method="sphere", lipschitz=lip),
           "ji.intersect(S.replace(method='sphere', lipschitz=m.lipschitz), rays)")]
    if net.sdf:
        jx.append(("sphere L=1", S.replace(method="sphere", lipschitz=1.0),
                   "ji.intersect(S.replace(method='sphere', lipschitz=1.0), rays)"))
    out = []
    for label, scene, call in jx:
        unit = ("point evaluations" if scene.method in ("sphere", "sampling")
                else "loop iterations (enclosures)")
        desc = dict(call=call, scene=scene_options(scene), steps_unit=unit)
        if scene is S:  # the scene's construction: the arithmetic's measurement, the grid
            desc["construct_s"] = construct_s
        out.append((label, "jaxiso", desc, jaxiso_caster(scene), scene))
    trace = hand_sampling(net.mlp, cfg["hand_samples"], cfg["hand_bisections"])
    out.append((f"hand sampling {cfg['hand_samples']}", "hand",
                dict(call=f"jax.jit: {cfg['hand_samples']} samples, first sign change, "
                          f"{cfg['hand_bisections']} bisections",
                     steps_unit="point evaluations"), hand_caster(net, trace), None))
    for mode in cfg["spelunking_modes"] if spelunking else ():
        if mode == "sdf" and not net.sdf:
            continue
        out.append((f"spelunking {mode}", "spelunking",
                    dict(call=f"queries.cast_rays, mode {mode}, get_default_cast_opts() "
                              "with max_dist = the longest segment in the box",
                         steps_unit="steps (a box classification + 2 point evaluations)"),
                    spelunking.caster(net, mode), None))
    return out


def reference(net, size, cfg):
    """The float64 reference of a network's camera at size^2: (pixel indices, t
    [R, R], seconds (0: from the cache)), R = min(size, ref_max): a regular subsample."""
    r = min(size, cfg["ref_max"])
    idx = common.subsample(size, r)
    o, d = flat64(sub_rays(camera(net, size).rays(), idx, idx))
    t, secs = ref64.cached_first_hits(net.path, o, d, cfg["cache"], f"{net.name}_{size}",
                                      LO, HI, samples=cfg["ref_samples"], tol=ref64.TOL)
    return idx, t.reshape(r, r), secs


def rays_section(networks, cfg, spelunking):
    rows, refs = [], []
    for net in networks:
        for size in cfg["sizes"]:
            idx, t_ref, ref_s = reference(net, size, cfg)
            refs.append(dict(network=net.name, size=size, ref_size=len(idx),
                             seconds=ref_s, cached=ref_s == 0.0,
                             hit_fraction=float(np.mean(np.isfinite(t_ref)))))
            print(f"== {net.name} {size}x{size}: float64 reference on {len(idx)}^2 pixels "
                  + ("(cached)" if ref_s == 0.0 else f"({ref_s:.0f} s)")
                  + f", hit fraction {refs[-1]['hit_fraction']:.3f}")
            rays = camera(net, size).rays()
            # the pilot: a regular subsample of the reference's pixels
            p = common.subsample(len(idx), min(len(idx), cfg["pilot"]))
            pilot = sub_rays(rays, idx[p], idx[p]) if cfg["pilot"] < size else None
            printed, calls = [], {}
            for label, kind, desc, make, scene in casters(net, cfg, spelunking):
                row = dict(network=net.name, size=size, label=label, kind=kind, **desc)
                if scene is not None:
                    row["plan"] = repr(ji.plan_for(scene, size * size))
                try:
                    timing, (hit, t, steps), ran = measure(
                        make, rays, pilot, cfg["row_budget_s"], cfg["repeats"],
                        cfg["slow_s"])
                except Exception as e:  # a caster that fails leaves the others
                    row["error"] = f"{type(e).__name__}: {str(e)[:300]}"
                    print(f"  {label} FAILED: {row['error']}")
                    rows.append(row)
                    continue
                if hasattr(make, "opts"):  # the options of the run that counted
                    row["opts"] = dict(make.opts)
                row.update(timing, **work(hit, steps), mrays_per_s=timing["rays_per_s"] / 1e6)
                if ran is not None:  # compare on the reference's pixels
                    if kind != "jaxiso" or label == DEFAULT:
                        calls[label] = ran
                    row.update(agreement(hit[idx][:, idx], t[idx][:, idx], t_ref))
                else:
                    row.update(agreement(hit, t, t_ref[p][:, p]))
                rows.append(row)
                printed.append([label, row.get("scene", {}).get("arithmetic", "-"),
                                row.get("plan", "-"),
                                fmt(row["rays_per_s"], ".3g") + ("" if row["measured"]
                                                                 else "~"),
                                fmt(row["first_call_s"], ".1f"), fmt(row["steps_mean"], ".1f"),
                                fmt(row["mask_agreement"], ".4f"),
                                fmt(row["false_hits"], ".4f"), fmt(row["missed_hits"], ".4f"),
                                fmt(row["depth_err_median"], ".1e"),
                                fmt(row["depth_err_p99"], ".1e")])
            print_table(["caster", "arith", "plan", "rays/s", "first s", "evals/ray",
                         "agree", "false", "missed", "depth med", "depth p99"], printed)
            if DEFAULT in calls and len(calls) > 1 and cfg["repeats"]:
                paired = paired_speedups(calls, DEFAULT, cfg["repeats"])
                next(r for r in rows[::-1] if r["label"] == DEFAULT)["paired_speedup"] = paired
                print("  the default call in turn with each peer (median of "
                      f"{cfg['repeats']} rounds, peer's time / default's): "
                      + ", ".join(f"{k} {v:.2f}x" for k, v in paired.items()))
    if any(not r.get("measured", True) for r in rows):
        print(f"  ~: over the row budget ({cfg['row_budget_s']:.0f} s): pilot of "
              f"{cfg['pilot']}^2 pixels, its rays/s and agreement\n")
    return dict(sizes=cfg["sizes"], eps=EPS, views={n.name: n.view for n in networks},
                reference=dict(module="tests/reference_neural64.py",
                               samples=cfg["ref_samples"], tol=ref64.TOL,
                               ref_max=cfg["ref_max"], runs=refs),
                rows=rows)


# ---------------------------------------------------------------------------- tightness


def piece_coords(arithmetic, c, half):
    """The ray pieces c + s half, s in [-1, 1] (c, half [N, 3] float32), as the
    coordinates `ji.extend` takes: one-symbol affine forms, or the axis boxes (interval
    and any other arithmetic). Returns (coordinates, extend keywords, description)."""
    if arithmetic == "affine":
        zero = jnp.zeros_like(c[:, 0])
        return ([ji.Affine(c[:, i], half[:, i:i + 1], zero) for i in range(3)],
                dict(n_symbols=1), "one noise symbol (the piece parameter)")
    a, b = c - half, c + half
    lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
    return ([ji.Interval(lo[:, i], hi[:, i]) for i in range(3)], {}, "axis box of the piece")


def enclosure_widths(m, arithmetic, coords, kw):
    """Widths [N] float64 of the enclosures of network m on the pieces `coords`."""
    F = ji.extend(m, arithmetic, **kw)
    out = jax.jit(lambda co, prm: F(*co, params=prm))(coords, m.params)
    out = ji.aa.to_interval(out) if isinstance(out, ji.Affine) else out
    return np.asarray(out.hi, np.float64) - np.asarray(out.lo, np.float64)


def near_surface(layers, n, rng, candidates=2**14):
    """n points of the domain where |f| is smallest among uniform samples."""
    p = rng.uniform(LO, HI, size=(candidates, 3))
    v = np.abs(ref64.evaluate(layers, p))
    return p[np.argsort(v)[:n]]


def tightness_section(networks, cfg):
    lengths = cfg["tight_lengths"]
    edge = HI[0] - LO[0]
    rows, errors = [], {}
    s = np.linspace(-1.0, 1.0, TIGHT_SAMPLES)
    for net in networks:
        rng = np.random.default_rng(0)
        layers = ref64.load_npz64(net.path)
        c = near_surface(layers, cfg["tight_points"], rng)
        u = rng.normal(size=c.shape)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        # every (length, point) piece in one batch: [L * N, 3]
        cc = np.tile(c, (len(lengths), 1))
        half = np.concatenate([u * (0.5 * edge * ln) for ln in lengths])
        cc32, half32 = cc.astype(np.float32), half.astype(np.float32)
        # the true range of the float32 pieces the enclosures see
        pts = cc32[:, None].astype(np.float64) + s[None, :, None] * half32[:, None]
        v = ref64.evaluate(layers, pts)
        true = v.max(axis=1) - v.min(axis=1)
        printed = []
        for arith in TIGHT_ARITHMETICS:
            base, _, grid = arith.partition("+")
            coords, kw, form = piece_coords(base, jnp.asarray(cc32), jnp.asarray(half32))
            if grid:  # the sign grid's arithmetic, here on ray pieces
                cells = ji.implicit.SignGrid
                kw = dict(kw, fresh_symbols=cells.FRESH_SYMBOLS,
                          fresh_per_op=cells.FRESH_PER_OP)
                form += (f", fresh symbols for the nonlinearities' errors (at most "
                         f"{cells.FRESH_SYMBOLS}, {cells.FRESH_PER_OP} per kink)")
            t0 = now()
            try:
                width = enclosure_widths(net.mlp, base, coords, kw)
            except Exception as e:  # an arithmetic that cannot run leaves the others
                errors[f"{net.name}/{arith}"] = f"{type(e).__name__}: {str(e)[:300]}"
                print(f"  {net.name} {arith} FAILED: {errors[f'{net.name}/{arith}']}")
                continue
            secs = now() - t0
            ratio = (width / np.maximum(true, 1e-300)).reshape(len(lengths), -1)
            for k, ln in enumerate(lengths):
                r = ratio[k]
                with np.errstate(invalid="ignore"):  # inf - inf between percentiles
                    stats = dict(median_ratio=float(np.median(r)),
                                 mean_ratio=float(np.mean(r)),
                                 p90_ratio=float(np.percentile(r, 90)))
                rows.append(dict(network=net.name, arithmetic=arith, input=form,
                                 length=ln * edge, length_of_domain=ln, **stats,
                                 # an unbounded enclosure (overflow inside the network)
                                 infinite=int(np.sum(~np.isfinite(r))),
                                 # below 1: narrower than the sampled range (unsound,
                                 # beyond float32 rounding)
                                 narrower=int(np.sum(r < 1.0 - 1e-4)), pieces=int(r.size)))
            printed.append([arith, f"{secs:.1f}"] + [fmt(float(np.median(r)), ".3g")
                                                     for r in ratio])
        print(f"== tightness {net.name}: median enclosure width / true range, "
              f"{cfg['tight_points']} pieces per length (inf: more than half of them "
              "unbounded)")
        print_table(["arithmetic", "s"] + [f"2^{round(np.log2(ln))}" for ln in lengths],
                    printed)
    return dict(lengths_of_domain=list(lengths), domain_edge=edge,
                points=cfg["tight_points"], true_range_samples=TIGHT_SAMPLES,
                arithmetics=list(TIGHT_ARITHMETICS),
                centres="smallest |f| of 2^14 uniform samples (float64), random directions",
                rows=rows, errors=errors)


# ---------------------------------------------------------------------------- charts


def charts(plt, save, result):
    if "rays" in result:
        rows = [r for r in result["rays"]["rows"] if "error" not in r]
        nets = list(dict.fromkeys(r["network"] for r in rows))
        labels = list(dict.fromkeys(r["label"] for r in rows))
        colours = {lb: plt.cm.tab10(i % 10) for i, lb in enumerate(labels)}
        marks = dict(zip(result["rays"]["sizes"], "os^Dv"))
        fig, axes = plt.subplots(1, len(nets), figsize=(5.5 * len(nets), 4.8), squeeze=False)
        for ax, name in zip(axes[0], nets):
            for r in (r for r in rows if r["network"] == name):
                # full agreement cannot sit on a log axis: drawn at half a pixel
                y = max(1.0 - r["mask_agreement"], 0.5 / r["compared"])
                ax.scatter(r["rays_per_s"], y, marker=marks.get(r["size"], "o"), s=36,
                           color=colours[r["label"]] if r["measured"] else "none",
                           edgecolors=colours[r["label"]])
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("rays/s")
            ax.set_ylabel("hit-mask disagreement with float64 ref. (0: at 1/2 px)")
            ax.set_title(f"{name} (" + ", ".join(f"{m} {s}^2" for s, m in marks.items()
                                                 if s in result["rays"]["sizes"])
                         + "; hollow: pilot)", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
        handles = [plt.Line2D([], [], ls="", marker="o", color=colours[lb], label=lb)
                   for lb in labels]
        axes[0][-1].legend(handles=handles, fontsize=7, loc="best")
        save(fig, "scatter")
    if "tightness" in result:
        tg = result["tightness"]
        nets = list(dict.fromkeys(r["network"] for r in tg["rows"]))
        fig, axes = plt.subplots(1, len(nets), figsize=(4.5 * len(nets), 4), squeeze=False)
        for ax, name in zip(axes[0], nets):
            mine = [r for r in tg["rows"] if r["network"] == name]
            finite = [r["median_ratio"] for r in mine if np.isfinite(r["median_ratio"])]
            top = 10.0 * max(finite, default=1.0)  # unbounded medians are drawn here
            for arith in tg["arithmetics"]:
                rr = [r for r in mine if r["arithmetic"] == arith]
                x = [r["length_of_domain"] for r in rr]
                y = [r["median_ratio"] for r in rr]
                line, = ax.plot(x, [v if np.isfinite(v) else np.nan for v in y],
                                marker="o", ms=3, label=arith)
                inf = [xi for xi, v in zip(x, y) if not np.isfinite(v)]
                if inf:
                    ax.plot(inf, [top] * len(inf), ls="", marker="^", ms=5,
                            color=line.get_color(), label=f"{arith}: unbounded (drawn at top)")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel("ray-piece length / domain edge")
            ax.set_ylabel("median enclosure width / true range")
            ax.set_title(name)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
        save(fig, "tightness")


# ---------------------------------------------------------------------------- main


def load_networks(args, parser):
    names = [n.strip() for n in args.networks.split(",") if n.strip()]
    sdf = {n.strip() for n in args.sdf.split(",") if n.strip()}
    paths = {n: pathlib.Path(args.data) / f"{n}.npz" for n in names}
    for spec in args.extra:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            parser.error(f"--extra wants NAME=PATH.npz, got {spec!r}")
        paths[name] = pathlib.Path(path)
    missing = [str(p) for p in paths.values() if not p.exists()]
    if missing:
        parser.error(f"network file(s) not found: {missing}")
    return [Network(n, p, ji.implicit.load_mlp(p), n in sdf, VIEWS.get(n, DEFAULT_VIEW))
            for n, p in paths.items()]


def config(args):
    sizes = ([int(s) for s in args.sizes.split(",")] if args.sizes
             else [128] if args.quick else [256, 512])
    return dict(quick=args.quick, sizes=sizes, ref_samples=args.ref_samples,
                ref_max=args.ref_max, pilot=args.pilot, row_budget_s=args.row_budget_s,
                repeats=args.repeats, slow_s=args.slow_s, cache=str(args.cache),
                hand_samples=HAND_SAMPLES, hand_bisections=HAND_BISECTIONS,
                spelunking=args.spelunking,
                spelunking_modes=[m for m in args.spelunking_modes.split(",") if m],
                tight_points=args.tight_points or (64 if args.quick else 256),
                tight_lengths=list(TIGHT_LENGTHS[:args.tight_lengths]))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(DATA), help="folder of the network .npz files")
    p.add_argument("--networks", default=",".join(NETWORKS))
    p.add_argument("--extra", action="append", default=[], metavar="NAME=PATH.npz",
                   help="another network of the same layout (repeatable)")
    p.add_argument("--sdf", default=",".join(SDF_NETWORKS),
                   help="networks that are signed distance functions (sphere L=1 rows)")
    p.add_argument("--sizes", default=None, help="image sizes (quick: 128; full: 256,512)")
    p.add_argument("--ref-samples", type=int, default=ref64.SAMPLES)
    p.add_argument("--ref-max", type=int, default=256,
                   help="the reference covers at most ref_max^2 pixels (a subsample)")
    p.add_argument("--cache", default=str(ROOT / "results" / "cache"),
                   help="where float64 references are cached")
    p.add_argument("--pilot", type=int, default=16, help="pilot image size (pixels^2)")
    p.add_argument("--row-budget-s", type=float, default=240.0,
                   help="rows predicted longer run as the pilot only (0: no limit)")
    p.add_argument("--spelunking", default=None, metavar="PATH",
                   help="a checkout of nmwsharp/neural-implicit-queries")
    p.add_argument("--spelunking-modes", default="affine_fixed")
    p.add_argument("--tightness", action="store_true", help="tightness in quick mode")
    p.add_argument("--tight-points", type=int, default=0,
                   help="pieces per length (default: 64 quick, 256 full)")
    p.add_argument("--tight-lengths", type=int, default=len(TIGHT_LENGTHS),
                   help="the first k piece lengths of 2^-4 .. 2^-14")
    args, only = common.parse_args(p, argv, SECTIONS, ROOT / "results")
    given = sys.argv[1:] if argv is None else argv
    if not any(a.startswith("--slow-s") for a in given):
        # the row budget bounds the calls: time every measured row by its repeats
        args.slow_s = SLOW_S
    if args.quick and not args.tightness and args.only == ",".join(SECTIONS):
        only.remove("tightness")  # quick runs skip it unless asked for
    networks = load_networks(args, p)
    cfg = config(args)
    spelunking = None
    if args.spelunking:
        try:
            spelunking = Spelunking(args.spelunking)
        except Exception as e:  # absent or broken checkout: the other rows still run
            cfg["spelunking_skipped"] = f"{type(e).__name__}: {e}"
    else:
        cfg["spelunking_skipped"] = "no --spelunking PATH"
    run = common.Run("neural", args, only, cfg, networks=[
        dict(name=n.name, path=str(n.path), activation=n.mlp.activation, sdf=n.sdf,
             lipschitz=n.mlp.lipschitz, layers=[list(np.shape(w["A"])) for w in n.mlp.params])
        for n in networks])
    if "spelunking_skipped" in cfg:
        print(f"Spelunking rows skipped: {cfg['spelunking_skipped']}\n")
    funcs = dict(rays=lambda: rays_section(networks, cfg, spelunking),
                 tightness=lambda: tightness_section(networks, cfg))
    run.sections(SECTIONS, lambda sec: funcs[sec]())
    return run.finish(charts)


if __name__ == "__main__":
    main()
