"""Isosurfaces of tetrahedral meshes (seed ch. 5): BIH vs SAH builds and renders, scaling
under replication, traversal work, rendering modalities, time-varying data, a peer pipeline
(VTK contour + open3d ray casting) and accuracy against a float64 reference.

    python benchmarks/bench_tetra.py [--size 512] [--quick] [--repeats 3]
        [--only table51,table53,table54,modalities,timevarying,peers,accuracy]
        [--out benchmarks/results]

Images run ``ji.render`` and ray casts ``ji.intersect`` (rays in tile order) with the plan
a user gets, ``ji.plan_for(scene, n_rays)`` (tiles, or from 2^16 rays on the CPU the
whole image on 4096 persistent lanes); every row records it (``plan``, e.g.
"Plan(tile=16, lanes=None)"). Compile time (AOT ``lower().compile()``) is reported apart
from run time: one warm-up call, then the median of `repeats` calls, each
``jax.block_until_ready``; an entry whose warm-up call takes longer than `slow_s` is timed
by that call alone (repeats_used 0). Mrays/s = pixels / run s. table51 also times each
image as a user asks for it, ``ji.render(scene, camera)`` with no plan and no manual
``jax.jit`` (first call = compile + run, then the median), beside the AOT figure.
Timed rows also carry cpu_s, the process's CPU seconds over the same calls: on a CPU
shared with other work it is steadier than wall time, so ratios are given in both.
Scenes are put on the device once (``jax.device_put``) before they are timed. BVH builds
run in numpy and are timed as the median of `build_repeats` builds. Meshes are
``data.cube_tets(n)`` (6 n^3 tets in the unit cube) unless said otherwise; every camera
frames the mesh's bounding sphere from the same direction.

Sections:
  table51      BIH vs SAH (seed Table 5.1): build ms, BVH nodes / depth / bytes and render
               Mrays/s for n = 26, 40, 55 (1e5 .. 1e6 tets), wave field; checks the target
               (1M-tet BIH build < 5 s).
  table53      replication (seed Table 5.3): k^3 copies of a sphere-field base mesh
               (``data.replicate``), k = 1, 2, 4, 8 (8 when memory allows), camera framing
               all copies; build, nodes, render; checks the target (render time grows at
               most 4x for 64x more tets).
  table54      traversal work per ray (seed Table 5.4) on the table51 meshes, from
               ``jaxiso.tetra.traverse`` run as ``intersect`` runs it (same plan): nodes
               visited and leaves intersected;
               leaves x leaf_size bounds the ray-tet (isopolygon) tests from above,
               leaves x the mean leaf size estimates them. Two views: the others' and
               its opposite (the traversal takes the near child first by the ray's
               octant, so the work should barely depend on the side the eye is on).
  modalities   render cost of 2 and 4 isosurfaces, shadows, transparency (2 and 4 layers),
               a clip box and smooth normals, relative to the plain render.
  timevarying  a new time step: ``with_time_step`` (jit refit of the value bounds) vs a
               rebuild per step; moved vertices (``data.deform``): ``with_points`` (jit
               refit) and numpy ``refit`` vs a rebuild; seconds, and the render after each
               with its traversal work (nodes / leaves per ray; a refit tree over moved
               vertices can be looser, so slower).
  peers        an isovalue change: jaxiso (``with_isovalues`` + the compiled render) vs VTK
               ``vtkContourFilter`` on the unstructured grid + open3d ``RaycastingScene``
               ray casting; seconds per stage, depth error vs the float64 reference
               (tests/reference_tet64.py) on a pixel subsample. Skipped with the reason when
               vtk or open3d is missing.
  accuracy     hit-mask agreement and relative depth error vs the float64 reference for bih
               and sah on sphere, wave and random fields. Both trace the very same rays (the
               reference camera's float64 rays rounded to float32).
Writes ``<out>/tetra_<backend>.json`` and, when matplotlib is installed, charts
``<out>/tetra_<backend>_{table51,table53,modalities,timevarying,peers}.png``.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import os
import pathlib
import statistics
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji
from jaxiso.tetra import (
    TetIsosurface,
    build_bvh,
    bvh_stats,
    data,
    memory_report,
    refit,
    tet_mesh,
    traverse,
)

ROOT = pathlib.Path(__file__).resolve().parent
TETRA_SOURCES = ROOT.parent / "jaxiso" / "tetra"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests"))
import _common as common  # noqa: E402
import reference_tet64 as ref  # noqa: E402
from _common import compile_cell, fmt, now, print_table, subsample  # noqa: E402

SECTIONS = ("table51", "table53", "table54", "modalities", "timevarying", "peers",
            "accuracy")
METHODS = ("bih", "sah")
PLAIN = ji.Shading()
# Fields and isovalues. The wave's isovalue is off 0 because sin(k pi x) is exactly 0 on
# many grid vertices, which would make the benchmark a test of ties.
FIELDS = {
    "sphere": (lambda p: data.sphere_field(p, radius=0.4), 0.0),
    "wave": (data.wave_field, 0.1),
    "random": (lambda p: data.random_field(p, seed=1), 0.0),
}
VIEW_DIRECTION = (1.0, 0.78, 0.62)  # from the target towards the eye
FOV = 35.0
# The traversal visits the child nearer along the split axis first, by the ray's octant
# (before it took the left child first: work then depended on the view); table54 runs both
# sides to show the work no longer does.
WORK_VIEWS = {
    "default": (VIEW_DIRECTION, "the other sections' view: rays run towards lower "
                                "coordinates"),
    "opposite": (tuple(-c for c in VIEW_DIRECTION), "eye on the other side: rays run "
                                                    "towards higher coordinates"),
}
BUILD_TARGET_S = 5.0
BUILD_TARGET_TETS = 900_000  # "1M tets": cube_tets(55) has 998,250
REPLICATION_TARGET = 4.0  # render time ratio allowed for 64x more tets
# Renderings of the modalities section: (label, isovalues, shading, scene options)
MODALITIES = (
    ("plain", (0.1,), PLAIN, {}),
    ("2 isosurfaces", (0.1, 0.6), PLAIN, {}),
    ("4 isosurfaces", (-0.4, 0.1, 0.6, 1.1), PLAIN, {}),
    ("shadows", (0.1,), ji.Shading(shadows=True), {}),
    ("2 layers", (0.1,), ji.Shading(layers=2, opacity=0.5), {}),
    ("4 layers", (0.1,), ji.Shading(layers=4, opacity=0.5), {}),
    ("clip box", (0.1,), PLAIN, dict(clip_box=((0.0, 0.0, 0.0), (0.6, 1.0, 1.0)))),
    ("smooth normals", (0.1,), PLAIN, dict(normals="smooth")),
)
PEER_OLD_ISO, PEER_NEW_ISO = 0.1, 0.5  # wave field


# ---------------------------------------------------------------------------- data


def view(lo, hi, direction=VIEW_DIRECTION):
    """eye / target / up / fov of a camera that frames the box [lo, hi]'s bounding sphere
    from `direction` (target to eye)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    direction = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    distance = 1.05 * radius / math.sin(math.radians(FOV) / 2)
    return dict(eye=tuple(centre + distance * direction), target=tuple(centre),
                up=(0.0, 0.0, 1.0), fov=FOV)


def camera(v, size):
    return ji.Camera.look_at(v["eye"], v["target"], v["up"], v["fov"], size, size)


def render_mode(plan):
    """A plan in words: "lanes 4096" or "tile E"."""
    return f"lanes {plan.lanes}" if plan.lanes else f"tile {plan.tile}"


def work_rays(direction, size, tile):
    """Tile-ordered camera rays (o, d) [size^2, 3] framing the unit cube from `direction`."""
    r = camera(view((0, 0, 0), (1, 1, 1), direction), size).rays()
    return ji.to_tiles(r.origin, tile), ji.to_tiles(r.direction, tile)


def reference_rays(v, size):
    """The reference camera's rays [size^2, 3] rounded to float32 (raster order): jaxiso
    traces them as they are, the reference in float64 from the same float32 values."""
    o, d = ref.camera_rays(v["eye"], v["target"], v["up"], v["fov"], size, size)
    return o.astype(np.float32), d.astype(np.float32)


def tile_order(x, size, tile):
    """[size^2, ...] raster-ordered rows -> tile order (whole tile x tile packets)."""
    return ji.to_tiles(jnp.asarray(x).reshape((size, size) + x.shape[1:]), tile)


def raster_order(x, size, tile):
    """Inverse of `tile_order`: tile-ordered [N, ...] -> [size^2, ...] raster order (numpy)."""
    return np.asarray(ji.from_tiles(x, tile, size, size)).reshape((size * size,)
                                                                  + x.shape[1:])


def cube_mesh(n, field):
    """(TetMesh of cube_tets(n) with FIELDS[field], isovalue)."""
    points, tets = data.cube_tets(n)
    fn, iso = FIELDS[field]
    return tet_mesh(points, tets, fn(points)), iso


def source_state():
    """The git commit, and a digest of jaxiso/tetra/*.py: the code these figures are of
    (the working tree may differ from the commit)."""
    digest = hashlib.sha256()
    for path in sorted(TETRA_SOURCES.glob("*.py")):
        digest.update(path.name.encode() + path.read_bytes())
    try:
        def git(*words):
            return subprocess.run(["git", *words], cwd=ROOT.parent, capture_output=True,
                                  text=True, timeout=10).stdout

        commit = git("rev-parse", "HEAD").strip() or None
        dirty = git("status", "--porcelain", "--", "jaxiso").splitlines()
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, []
    return dict(git_commit=commit, jaxiso_modified=[x[3:] for x in dirty if x.strip()],
                tetra_sources_sha256=digest.hexdigest())


def load_average():
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def clip_range(o, d, lo, hi):
    """[t_lo, t_hi] of rays o + t d (t >= 0) inside the box [lo, hi] (bounds may be inf),
    as `intersect` gives the scene with t_min = 0, t_max = inf."""
    inv = 1.0 / d
    ta, tb = (lo - o) * inv, (hi - o) * inv
    # 0 * inf (a ray in a slab's plane) is nan: that axis sets no limit
    near = jnp.where(jnp.isnan(ta), -jnp.inf, jnp.minimum(ta, tb))
    far = jnp.where(jnp.isnan(tb), jnp.inf, jnp.maximum(ta, tb))
    return jnp.maximum(jnp.max(near, axis=-1), 0.0), jnp.min(far, axis=-1)


def traverse_counts(scene, o, d, plan):
    """hit, nodes visited, leaves intersected [N] of rays o, d [N, 3] from the BVH
    traversal itself, run as `intersect` runs it with `plan`: packets of plan.tile**2
    consecutive rays (N a multiple of it), or the whole batch on plan.lanes persistent
    lanes."""
    n = o.shape[0]
    t_lo, t_hi = clip_range(o, d, scene.clip_lo, scene.clip_hi)
    points = jnp.asarray(scene.mesh.points)
    tets = jnp.asarray(scene.mesh.tets)
    values = jnp.asarray(scene.mesh.values)[scene.time_step]

    def one(args):
        po, pd, a, b = args
        _, hit, _, _, nodes, leaves = traverse(scene.bvh, points, tets, values,
                                               scene.isovalues, po, pd, a, b,
                                               max_steps=scene.max_steps, lanes=plan.lanes)
        return hit, nodes, leaves

    if plan.lanes:
        return one((o, d, t_lo, t_hi))
    packet = plan.packet
    packets = [x.reshape((n // packet, packet) + x.shape[1:]) for x in (o, d, t_lo, t_hi)]
    return tuple(x.reshape(n) for x in jax.lax.map(one, packets))


# ---------------------------------------------------------------------------- runner


def tree_stats(bvh):
    """bvh_stats with its tet count named bvh_tets (tets kept: non-degenerate ones)."""
    stats = bvh_stats(bvh)
    stats["bvh_tets"] = stats.pop("tets")
    return stats


def on_device(tree):
    """The pytree's arrays as device arrays, so timed calls transfer nothing."""
    return jax.block_until_ready(jax.device_put(tree))


class Bench(common.TimedBench):
    """Caches meshes, BVHs and compiled executables; times calls and builds."""

    def __init__(self, repeats: int, slow_s: float, build_repeats: int):
        super().__init__(repeats, slow_s)
        self.build_repeats = build_repeats
        self._meshes = {}
        self._bvhs = {}
        self._rays = {}

    # -- data
    def mesh(self, n, field):
        """(TetMesh, isovalue, seconds to make it) of cube_tets(n) with a field, cached."""
        key = (n, field)
        if key not in self._meshes:
            t0 = now()
            mesh, iso = cube_mesh(n, field)
            self._meshes[key] = (mesh, iso, now() - t0)
        return self._meshes[key]

    def build(self, mesh, method, *, key=None, leaf_size=8, step=0):
        """(BVH, median build s, all build s); cached under `key` when given. Builds
        after one longer than 10 s are skipped (the median is then of fewer)."""
        if key is not None and (key, method) in self._bvhs:
            return self._bvhs[(key, method)]
        times = []
        for _ in range(self.build_repeats):
            t0 = now()
            bvh = build_bvh(mesh, method=method, leaf_size=leaf_size, step=step)
            times.append(now() - t0)
            if times[-1] > 10.0:
                break
        out = (bvh, statistics.median(times), times)
        if key is not None:
            self._bvhs[(key, method)] = out
        return out

    # -- compile and time
    def render_exe(self, scene, cam, shading):
        """compiled(...) of jit(render) with a constant `shading` (a module constant: the
        executables are cached by its id) and the user's plan, and that plan."""
        plan = ji.plan_for(scene, cam.width * cam.height)
        exe, compile_s, cached = self.compiled(
            ("render", plan, id(shading)),
            lambda s, c: ji.render(s, c, shading=shading, plan=plan), scene, cam)
        return exe, compile_s, cached, plan

    def render(self, scene, cam, shading=PLAIN):
        """jit(render) of a device scene: row dict (no image kept)."""
        exe, compile_s, cached, plan = self.render_exe(scene, cam, shading)
        _, timing = self.timed(lambda: exe(scene, cam))
        n = cam.width * cam.height
        return dict(pixels=n, plan=repr(plan), mode=render_mode(plan), compile_s=compile_s,
                    compile_cached=cached,
                    **timing, mrays_per_s=n / timing["run_s"] / 1e6)

    def user_render(self, scene, cam):
        """``ji.render(scene, camera)`` as a user calls it (no plan, no manual jit):
        {call, plan, first_call_s (compile + run), run_s, cpu_s, repeats_used,
        mrays_per_s}."""
        n = cam.width * cam.height
        _, row = self.user_call(lambda: ji.render(scene, cam), ji.plan_for(scene, n),
                                "ji.render(scene, camera)")
        row["mrays_per_s"] = n / row["run_s"] / 1e6
        return row

    def work_rays(self, scene, direction, size):
        """(plan, o, d): the user's plan for size^2 rays of `scene` and tile-ordered
        camera rays for it (`work_rays`), cached by tile."""
        plan = ji.plan_for(scene, size * size)
        key = ("work_rays", direction, size, plan.tile)
        if key not in self._rays:
            self._rays[key] = work_rays(direction, size, plan.tile)
        return (plan, *self._rays[key])

    def counts(self, scene, direction, size):
        """`traverse_counts` of size^2 camera rays from `direction` with the user's plan:
        (info dict: plan, compile and timing, hit, nodes, leaves [size^2] in raster
        order)."""
        plan, o, d = self.work_rays(scene, direction, size)
        exe, compile_s, cached = self.compiled(
            ("traverse", plan), lambda s, a, c: traverse_counts(s, a, c, plan), scene, o, d)
        out, timing = self.timed(lambda: exe(scene, o, d))
        hit, nodes, leaves = (raster_order(x, size, plan.tile) for x in out)
        return (dict(**common.plan_fields(plan), compile_s=compile_s, compile_cached=cached,
                     **timing), hit, nodes.astype(np.int64), leaves.astype(np.int64))

    def intersect(self, scene, o, d, size):
        """jit(intersect) of rays o, d [size^2, 3] (raster order, run in tile order) with
        the user's plan: (row, hit [size^2], t [size^2] float64)."""
        plan = ji.plan_for(scene, size * size)
        tile = plan.tile
        rays = ji.Rays(tile_order(o, size, tile), tile_order(d, size, tile))
        exe, compile_s, cached = self.compiled(
            ("intersect", plan), lambda s, r: ji.intersect(s, r, plan=plan), scene, rays)
        hits, timing = self.timed(lambda: exe(scene, rays))
        row = dict(pixels=size * size, plan=repr(plan), compile_s=compile_s,
                   compile_cached=cached, **timing,
                   mrays_per_s=size * size / timing["run_s"] / 1e6)
        return (row, raster_order(hits.hit, size, tile),
                raster_order(hits.t, size, tile).astype(np.float64))


# ---------------------------------------------------------------------------- depth error


def depth_stats(hit, t, t_ref):
    """Hit-mask agreement and relative depth error |t - t_ref| / t_ref where both hit, with
    the pixels (indices into the rays) to look at: mismatches and errors above 1e-4."""
    hit_ref = np.isfinite(t_ref)
    both = hit & hit_ref
    err = np.zeros(t.shape)
    err[both] = np.abs(t[both] - t_ref[both]) / t_ref[both]
    return dict(mask_agreement=float(np.mean(hit == hit_ref)),
                mask_mismatches=int(np.sum(hit != hit_ref)), both_hit=int(both.sum()),
                ref_hit_fraction=float(hit_ref.mean()),
                depth_rel_max=float(err[both].max()) if both.any() else None,
                depth_rel_median=float(np.median(err[both])) if both.any() else None,
                mismatch_pixels=np.flatnonzero(hit != hit_ref)[:20].tolist(),
                large_error_pixels=np.flatnonzero(err > 1e-4)[:20].tolist())


# ---------------------------------------------------------------------------- sections


def table51(b, cfg):
    size, field = cfg["size"], cfg["t51_field"]
    cam = camera(view((0, 0, 0), (1, 1, 1)), size)
    print(f"== Table 5.1 analog: BIH vs SAH, cube_tets(n) x 6 tets, {field} field, "
          f"{size}x{size} render (the JSON rows say how it ran); build = median of "
          f"{b.build_repeats} numpy builds, leaf size 8")
    rows = []
    for n in cfg["t51_n"]:
        mesh, iso, mesh_s = b.mesh(n, field)
        for method in METHODS:
            bvh, build_s, builds = b.build(mesh, method, key=(n, field))
            scene = on_device(TetIsosurface(mesh, iso, bvh=bvh))
            mem = memory_report(bvh, mesh)
            row = dict(n=n, tets=mesh.n_tets, field=field, isovalue=iso, method=method,
                       mesh_s=mesh_s, build_ms=1e3 * build_s,
                       build_ms_all=[1e3 * t for t in builds], **tree_stats(bvh),
                       bvh_bytes=mem["bvh_bytes"], mesh_bytes=mem["mesh_bytes"],
                       overhead_pct=mem["overhead_pct"], size=size,
                       **b.render(scene, cam))
            # the same image as a user asks for it (no plan, no manual jit)
            row["user_call"] = b.user_render(scene, cam)
            row["user_run_s"] = row["user_call"]["run_s"]
            rows.append(row)
            print(f"  n={n} {method} done", flush=True)
    print_table(["n", "tets", "method", "build ms", "nodes", "depth", "leaf", "BVH MB",
                 "+% mesh", "plan", "compile s", "render s", "cpu s", "Mrays/s",
                 "user 1st s", "user s"],
                [[str(r["n"]), str(r["tets"]), r["method"], fmt(r["build_ms"], ".0f"),
                  str(r["nodes"]), str(r["depth"]), fmt(r["mean_leaf_size"], ".2f"),
                  fmt(r["bvh_bytes"] / 2**20, ".1f"), fmt(r["overhead_pct"], ".0f"),
                  r["plan"], compile_cell(r), fmt(r["run_s"]), fmt(r["cpu_s"], ".2f"),
                  fmt(r["mrays_per_s"], ".4f"), fmt(r["user_call"]["first_call_s"], ".1f"),
                  fmt(r["user_run_s"])]
                 for r in rows])
    print("  user: ji.render(scene, camera) as a user calls it (no plan, no manual jit): its "
          "first call (compile + run) and the median after")
    largest = max((r for r in rows if r["method"] == "bih"), key=lambda r: r["tets"])
    checked = largest["tets"] >= BUILD_TARGET_TETS
    met = largest["build_ms"] < 1e3 * BUILD_TARGET_S if checked else None
    print(f"  target: 1M-tet BIH build < {BUILD_TARGET_S:g} s: {largest['tets']} tets in "
          f"{largest['build_ms'] / 1e3:.2f} s -> "
          + ({True: "MET", False: "NOT met", None: "not checked (mesh < 1M tets)"}[met]))
    for method in METHODS:
        rr = [r for r in rows if r["method"] == method]
        if len(rr) > 1:
            per = [r["build_ms"] / r["tets"] * 1e3 for r in rr]
            print(f"  {method}: build {', '.join(fmt(x, '.2f') for x in per)} us per tet")
    print()
    return dict(size=size, field=field, rows=rows,
                build_target=dict(seconds=BUILD_TARGET_S, tets=largest["tets"],
                                  build_s=largest["build_ms"] / 1e3, checked=checked,
                                  met=met))


def table53(b, cfg):
    size, n_base, field = cfg["size"], cfg["t53_base"], "sphere"
    points, tets = data.cube_tets(n_base)
    fn, iso = FIELDS[field]
    values = fn(points)
    print(f"== Table 5.3 analog: k^3 copies of cube_tets({n_base}) ({tets.shape[0]} tets, "
          f"{field} field, iso {iso}), BIH, {size}x{size} render framing all copies")
    rows, skipped = [], []
    for k in cfg["t53_k"]:
        n_tets = k**3 * tets.shape[0]
        # about 1 KB per tet at peak (float64 validation, numpy build, device copies)
        need_gb = 1e3 * n_tets / 2**30
        if common.available_gb() < need_gb:
            skipped.append(f"k={k}: {n_tets} tets need about {need_gb:.1f} GiB, "
                           f"{common.available_gb():.1f} GiB available")
            continue
        t0 = now()
        p, t, v = data.replicate(points, tets, values, k)
        mesh = tet_mesh(p, t, v)
        mesh_s = now() - t0
        bvh, build_s, builds = b.build(mesh, "bih")
        scene = on_device(TetIsosurface(mesh, iso, bvh=bvh))
        cam = camera(view(p.min(axis=0), p.max(axis=0)), size)
        mem = memory_report(bvh, mesh)
        rows.append(dict(k=k, copies=k**3, tets=mesh.n_tets, mesh_s=mesh_s,
                         build_s=build_s, build_s_all=builds, **tree_stats(bvh),
                         bvh_bytes=mem["bvh_bytes"], total_bytes=mem["total_bytes"],
                         size=size, **b.render(scene, cam)))
        print(f"  k={k} done", flush=True)
        del scene, mesh, bvh, p, t, v
    base = rows[0] if rows and rows[0]["k"] == 1 else None
    for r in rows:
        r["render_ratio"] = r["run_s"] / base["run_s"] if base else None
        r["render_ratio_cpu"] = r["cpu_s"] / base["cpu_s"] if base else None
        r["tets_ratio"] = r["tets"] / base["tets"] if base else None
    print_table(["k", "tets", "build s", "nodes", "depth", "MB", "compile s", "render s",
                 "cpu s", "Mrays/s", "x render", "x cpu", "x tets"],
                [[str(r["k"]), str(r["tets"]), fmt(r["build_s"], ".2f"), str(r["nodes"]),
                  str(r["depth"]), fmt(r["total_bytes"] / 2**20, ".0f"), compile_cell(r),
                  fmt(r["run_s"]), fmt(r["cpu_s"], ".2f"), fmt(r["mrays_per_s"], ".4f"),
                  fmt(r["render_ratio"], ".2f"), fmt(r["render_ratio_cpu"], ".2f"),
                  fmt(r["tets_ratio"], ".0f")] for r in rows])
    k4 = next((r for r in rows if r["k"] == 4), None)
    ratio = k4["render_ratio"] if k4 and base else None
    ratio_cpu = k4["render_ratio_cpu"] if k4 and base else None
    met = ratio <= REPLICATION_TARGET if ratio is not None else None
    print(f"  target: render time grows <= {REPLICATION_TARGET:g}x for 64x more tets "
          f"(k=4 vs k=1): " + (f"{ratio:.2f}x wall ({ratio_cpu:.2f}x CPU time) -> "
                               f"{'MET' if met else 'NOT met'}"
                               if ratio is not None else "not checked (no k=4 row)"))
    for s in skipped:
        print(f"  skipped: {s}")
    print()
    return dict(size=size, base_n=n_base, base_tets=int(tets.shape[0]), field=field,
                isovalue=iso, rows=rows, skipped=skipped,
                target=dict(max_ratio=REPLICATION_TARGET, ratio=ratio, ratio_cpu=ratio_cpu,
                            met=met))


def table54(b, cfg):
    size, field = cfg["work_size"], cfg["t51_field"]
    print(f"== Table 5.4 analog: traversal work per ray, {field} field, {size}x{size} rays "
          f"run as intersect runs them (the user's plan, ji.plan_for); tet tests <= leaves "
          f"x leaf size. Views: "
          + "; ".join(f"{k}: eye at {v[0]}" for k, v in WORK_VIEWS.items()))
    rows = []
    for n in cfg["t51_n"]:
        mesh, iso, _ = b.mesh(n, field)
        for method in METHODS:
            bvh, _, _ = b.build(mesh, method, key=(n, field))
            scene = on_device(TetIsosurface(mesh, iso, bvh=bvh))
            stats = bvh_stats(bvh)
            for name, (direction, _) in WORK_VIEWS.items():
                info, hit, nodes, leaves = b.counts(scene, direction, size)
                rows.append(dict(
                    n=n, tets=mesh.n_tets, method=method, view=name, size=size, **info,
                    hit_fraction=float(hit.mean()),
                    nodes_mean=float(nodes.mean()), nodes_max=int(nodes.max()),
                    nodes_mean_hit=float(nodes[hit].mean()) if hit.any() else None,
                    nodes_mean_miss=float(nodes[~hit].mean()) if (~hit).any() else None,
                    leaves_mean=float(leaves.mean()), leaves_max=int(leaves.max()),
                    leaf_size=bvh.leaf_size, mean_leaf_size=stats["mean_leaf_size"],
                    tet_tests_bound_mean=float(leaves.mean() * bvh.leaf_size),
                    tet_tests_est_mean=float(leaves.mean() * stats["mean_leaf_size"]),
                    isovalues=1))
            print(f"  n={n} {method} done", flush=True)
    print_table(["n", "tets", "method", "view", "plan", "hit", "nodes", "max", "nodes|hit",
                 "nodes|miss", "leaves", "max", "tet tests <=", "~tet tests", "compile s",
                 "run s"],
                [[str(r["n"]), str(r["tets"]), r["method"], r["view"], r["plan"],
                  fmt(r["hit_fraction"], ".2f"), fmt(r["nodes_mean"], ".1f"),
                  str(r["nodes_max"]), fmt(r["nodes_mean_hit"], ".1f"),
                  fmt(r["nodes_mean_miss"], ".1f"), fmt(r["leaves_mean"], ".2f"),
                  str(r["leaves_max"]), fmt(r["tet_tests_bound_mean"], ".1f"),
                  fmt(r["tet_tests_est_mean"], ".1f"), compile_cell(r), fmt(r["run_s"])]
                 for r in rows])
    for name, (_, meaning) in WORK_VIEWS.items():
        print(f"  {name}: {meaning}")
    print()
    return dict(size=size, field=field, plan=sorted({r["plan"] for r in rows}),
                views={k: dict(eye_direction=v[0], meaning=v[1]) for k, v in WORK_VIEWS.items()},
                rows=rows)


def modalities(b, cfg):
    size, n, field = cfg["size"], cfg["mod_n"], "wave"
    mesh, _, _ = b.mesh(n, field)
    bvh, _, _ = b.build(mesh, "bih", key=(n, field))
    cam = camera(view((0, 0, 0), (1, 1, 1)), size)
    wanted = cfg["modalities"]
    print(f"== Modalities: cube_tets({n}) ({mesh.n_tets} tets), {field} field, BIH, "
          f"{size}x{size}; cost relative to the plain render")
    rows = []
    for label, isos, shading, options in MODALITIES:
        if label not in wanted:
            continue
        scene = on_device(TetIsosurface(mesh, isos, bvh=bvh, **options))
        rows.append(dict(label=label, isovalues=list(isos), layers=shading.layers,
                         shadows=shading.shadows, options={k: str(v) for k, v in
                                                           options.items()},
                         size=size, **b.render(scene, cam, shading)))
    plain = next((r for r in rows if r["label"] == "plain"), None)
    for r in rows:
        r["relative"] = r["run_s"] / plain["run_s"] if plain else None
        r["relative_cpu"] = r["cpu_s"] / plain["cpu_s"] if plain else None
    print_table(["rendering", "compile s", "render s", "cpu s", "Mrays/s", "x plain",
                 "x plain (cpu)"],
                [[r["label"], compile_cell(r), fmt(r["run_s"]), fmt(r["cpu_s"], ".2f"),
                  fmt(r["mrays_per_s"], ".4f"), fmt(r["relative"], ".2f"),
                  fmt(r["relative_cpu"], ".2f")] for r in rows])
    return dict(size=size, n=n, tets=mesh.n_tets, field=field, rows=rows)


def timevarying(b, cfg):
    size, n, steps = cfg["size"], cfg["tv_n"], cfg["tv_steps"]
    points, tets = data.cube_tets(n)
    iso = FIELDS["wave"][1]
    mesh = tet_mesh(points, tets, data.time_series(points, steps))
    cam = camera(view((0, 0, 0), (1, 1, 1)), size)
    print(f"== Time-varying data: cube_tets({n}) ({mesh.n_tets} tets), wave field, "
          f"{steps} time steps, {size}x{size} render after each change; traversal work "
          f"(nodes, leaves per ray) on {cfg['work_size']}^2 rays of the same view")
    switch = lambda s, k: s.with_time_step(k)
    move = lambda s, q: s.with_points(q)
    rows = []

    work_size = cfg["work_size"]

    def add(method, change, how, seconds, scene, **extra):
        r = b.render(scene, cam)
        work = dict(nodes_mean=None, leaves_mean=None, hit_fraction=None)
        if cfg["tv_work"]:  # traversal work: load-independent, unlike the render's seconds
            _, hit, nodes, leaves = b.counts(scene, VIEW_DIRECTION, work_size)
            work = dict(nodes_mean=float(nodes.mean()), leaves_mean=float(leaves.mean()),
                        hit_fraction=float(hit.mean()))
        rows.append(dict(method=method, change=change, how=how, seconds=seconds, **work,
                         render_s=r["run_s"], render_cpu_s=r["cpu_s"], plan=r["plan"],
                         render_compile_s=r["compile_s"],
                         render_compile_cached=r["compile_cached"], **extra))

    for method in cfg["tv_methods"]:
        bvh, build_s, _ = b.build(mesh, method)
        base = on_device(TetIsosurface(mesh, iso, bvh=bvh))
        add(method, "-", "initial build (numpy)", build_s, base)
        # a new time step: refit of the value bounds (jit) vs a rebuild (numpy)
        step = jnp.int32(1)
        exe, compile_s, cached = b.compiled(("with_time_step", method), switch, base, step)
        refit_scene, timing = b.timed(lambda: exe(base, step))
        add(method, "time step", "with_time_step (jit refit)", timing["run_s"], refit_scene,
            compile_s=compile_s, repeats_used=timing["repeats_used"])
        times, rebuilt = [], []
        for k in range(1, steps):
            t0 = now()
            rebuilt.append(on_device(TetIsosurface(
                mesh, iso, bvh=build_bvh(mesh, method=method, step=k), time_step=k)))
            times.append(now() - t0)
        add(method, "time step", "rebuild (numpy build + scene)", statistics.median(times),
            rebuilt[0])
        del rebuilt, refit_scene
        # moved vertices: refit of the boxes (jit / numpy) vs a rebuild
        for amp in cfg["tv_amplitudes"]:
            moved = data.deform(points, 1.0, amplitude=amp)
            change = f"points (amplitude {amp:g})"
            q = jnp.asarray(moved)
            exe, compile_s, cached = b.compiled(("with_points", method), move, base, q)
            refit_scene, timing = b.timed(lambda: exe(base, q))
            add(method, change, "with_points (jit refit)", timing["run_s"], refit_scene,
                compile_s=compile_s, repeats_used=timing["repeats_used"])
            t0 = now()
            moved_mesh = mesh.with_points(moved)
            mesh_s = now() - t0
            t0 = now()
            refit(bvh, moved_mesh)
            rows.append(dict(method=method, change=change, how="refit (numpy)",
                             seconds=now() - t0, render_s=None, render_cpu_s=None,
                             nodes_mean=None, leaves_mean=None, hit_fraction=None,
                             mesh_s=mesh_s))
            new_bvh, rebuild_s, _ = b.build(moved_mesh, method)
            add(method, change, "rebuild (numpy build)", rebuild_s,
                on_device(TetIsosurface(moved_mesh, iso, bvh=new_bvh)), mesh_s=mesh_s,
                nodes=bvh_stats(new_bvh)["nodes"])
            del refit_scene
        print(f"  {method} done", flush=True)
    for r in rows:
        first = next(x for x in rows if x["method"] == r["method"])
        r["render_relative"] = r["render_s"] / first["render_s"] if r["render_s"] else None
        r["render_relative_cpu"] = (r["render_cpu_s"] / first["render_cpu_s"]
                                    if r["render_s"] else None)
    print_table(["method", "change", "how", "seconds", "compile s", "render s", "cpu s",
                 "render compile s", "x initial", "x initial (cpu)", "nodes", "leaves"],
                [[r["method"], r["change"], r["how"], fmt(r["seconds"], ".4f"),
                  fmt(r.get("compile_s"), ".1f"), fmt(r["render_s"]),
                  fmt(r["render_cpu_s"], ".2f"),
                  (fmt(r["render_compile_s"], ".1f") + ("*" if r["render_compile_cached"]
                                                        else "")) if r["render_s"] else "-",
                  fmt(r["render_relative"], ".2f"), fmt(r["render_relative_cpu"], ".2f"),
                  fmt(r["nodes_mean"], ".1f"), fmt(r["leaves_mean"], ".2f")]
                 for r in rows])
    for r in rows:
        if r["how"] == "with_points (jit refit)" and r["nodes_mean"] is not None:
            new = next(x for x in rows if x["method"] == r["method"]
                       and x["change"] == r["change"] and x["how"].startswith("rebuild"))
            r["nodes_vs_rebuild"] = r["nodes_mean"] / new["nodes_mean"]
            print(f"  {r['method']}, {r['change']}: the refit tree visits "
                  f"{r['nodes_vs_rebuild']:.2f}x the nodes of a rebuilt one")
    print("  A refit keeps the tree: time steps change only value bounds (the spatial "
          "splits never depended on them), moved vertices loosen boxes.\n")
    return dict(size=size, n=n, tets=mesh.n_tets, steps=steps, isovalue=iso, rows=rows)


# ---------------------------------------------------------------------------- peers


def peer_versions():
    """Versions of the peer libraries, and why a missing one is missing."""
    out = {}
    for name in ("vtk", "open3d"):
        try:
            mod = __import__(name)
            out[name] = (mod.vtkVersion.GetVTKVersion() if name == "vtk"
                         else mod.__version__)
            if name == "vtk":  # how many threads VTK's filters may use
                from vtkmodules.vtkCommonCore import vtkSMPTools

                out["vtk_smp_backend"] = vtkSMPTools.GetBackend()
        except Exception as e:  # ImportError, or a missing shared library
            out[name] = None
            out[name + "_error"] = f"{type(e).__name__}: {e}"
    return out


def vtk_grid(points, tets, values):
    """A vtkUnstructuredGrid of linear tets with point scalars `values`."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_TETRA, vtkCellArray, vtkUnstructuredGrid

    pts = vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(points, np.float32), deep=True))
    conn = numpy_to_vtkIdTypeArray(np.ascontiguousarray(tets, np.int64).ravel(), deep=True)
    offsets = numpy_to_vtkIdTypeArray(np.arange(0, 4 * len(tets) + 1, 4, dtype=np.int64),
                                      deep=True)
    cells = vtkCellArray()
    cells.SetData(offsets, conn)
    grid = vtkUnstructuredGrid()
    grid.SetPoints(pts)
    grid.SetCells(VTK_TETRA, cells)
    grid.GetPointData().SetScalars(numpy_to_vtk(np.ascontiguousarray(values, np.float32),
                                                deep=True))
    return grid


def vtk_contour(grid, iso):
    """Triangles of the isosurface: (vertices [M, 3], faces [F, 3])."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersCore import vtkContourFilter, vtkTriangleFilter

    poly = common.vtk_isosurface(vtkContourFilter(), grid, iso, "Normals", "Scalars")
    polys = poly.GetPolys()
    if np.any(np.diff(vtk_to_numpy(polys.GetOffsetsArray())) != 3):
        tri = vtkTriangleFilter()  # contours of tets are triangles; this is a safeguard
        tri.SetInputData(poly)
        tri.Update()
        poly = tri.GetOutput()
        polys = poly.GetPolys()
    verts = vtk_to_numpy(poly.GetPoints().GetData()) if poly.GetNumberOfPoints() else \
        np.zeros((0, 3), np.float32)
    faces = vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3)
    return verts, faces


def lambert(t, normals):
    """A two-sided Lambert image [N, 3] of mesh hits (the peer's shading stage)."""
    light = np.array([0.45, 0.35, 0.82], np.float32)
    light /= np.linalg.norm(light)
    shade = 0.18 + 0.75 * np.abs(normals @ light)
    col = shade[:, None] * np.array([0.85, 0.55, 0.25], np.float32)
    return np.where(np.isfinite(t)[:, None], col, 1.0)


def peers(b, cfg):
    size, n, ref_size = cfg["size"], cfg["peer_n"], cfg["ref_size"]
    versions = peer_versions()
    mesh, _, mesh_s = b.mesh(n, "wave")
    print(f"== Peers: an image after an isovalue change {PEER_OLD_ISO} -> {PEER_NEW_ISO}, "
          f"cube_tets({n}) ({mesh.n_tets} tets), wave field, {size}x{size}; depth error vs "
          f"the float64 reference on a {min(ref_size, size)}^2 pixel subsample")
    print("  versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()
                                     if not k.endswith("_error")))
    v = view((0, 0, 0), (1, 1, 1))
    cam = camera(v, size)
    o32, d32 = reference_rays(v, size)
    idx = subsample(size, ref_size)
    pix = (idx[:, None] * size + idx[None, :]).reshape(-1)
    m = idx.size
    t0 = now()
    t_ref, _, _, _ = ref.first_hits(mesh.points, mesh.tets, mesh.values[0],
                                    o32[pix].astype(np.float64), d32[pix].astype(np.float64),
                                    PEER_NEW_ISO)
    ref_s = now() - t0
    rows, skipped = [], []
    # jaxiso: build and compile once, then an isovalue change costs one render
    bvh, build_s, _ = b.build(mesh, "bih", key=(n, "wave"))
    scene = on_device(TetIsosurface(mesh, PEER_OLD_ISO, bvh=bvh))
    exe, compile_s, cached, plan = b.render_exe(scene, cam, PLAIN)
    jax.block_until_ready(exe(scene, cam))  # at the old isovalue
    _, timing = b.timed(lambda: exe(scene.with_isovalues(PEER_NEW_ISO), cam))
    image_s = timing["run_s"]
    row, hit, t = b.intersect(scene.with_isovalues(PEER_NEW_ISO), o32[pix], d32[pix], m)
    rows.append(dict(pipeline="jaxiso", image_s=image_s, cpu_s=timing["cpu_s"],
                     warmup_s=timing["warmup_s"], repeats_used=timing["repeats_used"],
                     once=dict(mesh_s=mesh_s, build_s=build_s, compile_s=compile_s),
                     compile_cached=cached, subsample_compile_s=row["compile_s"],
                     plan=repr(plan), subsample_plan=row["plan"],
                     stages=dict(render_s=image_s), triangles=None,
                     **depth_stats(hit, t, t_ref)))
    if versions.get("vtk") is None or versions.get("open3d") is None:
        skipped.append("VTK contour + open3d: " + (versions.get("vtk_error")
                                                   or versions.get("open3d_error", "")))
    else:
        t0 = now()
        grid = vtk_grid(mesh.points, mesh.tets, mesh.values[0])
        wrap_s = now() - t0
        vtk_contour(grid, PEER_OLD_ISO)  # the old isovalue's image came first
        t0 = now()
        verts, faces = vtk_contour(grid, PEER_NEW_ISO)
        contour_s = now() - t0
        t_all, normals, cast_s, again_s = common.mesh_raycast(verts, faces, o32, d32)
        t0 = now()
        lambert(t_all, normals)
        shade_s = now() - t0
        t_sub = t_all[pix]
        rows.append(dict(pipeline="VTK contour + open3d", image_s=contour_s + cast_s + shade_s,
                         once=dict(wrap_s=wrap_s),
                         stages=dict(contour_s=contour_s, cast_s=cast_s, shade_s=shade_s),
                         cast_again_s=again_s, triangles=int(faces.shape[0]),
                         **depth_stats(np.isfinite(t_sub), t_sub, t_ref)))
    print_table(["pipeline", "image s", "stages (s)", "once (s)", "triangles", "mask agree",
                 "rel depth med", "rel depth max"],
                [[r["pipeline"], fmt(r["image_s"]),
                  " + ".join(f"{k[:-2]} {x:.3f}" for k, x in r["stages"].items()),
                  ", ".join(f"{k[:-2]} {x:.2f}" for k, x in r["once"].items()),
                  str(r["triangles"] or "-"), fmt(r["mask_agreement"], ".4f"),
                  fmt(r["depth_rel_median"], ".1e"), fmt(r["depth_rel_max"], ".1e")]
                 for r in rows])
    for s in skipped:
        print(f"  skipped: {s}")
    print(f"  reference: {ref_s:.1f} s for {pix.size} rays. jaxiso intersects the same linear "
          "tets the contour triangulates, so both should match the reference to float32 "
          "rounding.\n  Threads: XLA CPU and open3d (Embree) use every core; VTK's SMP "
          f"backend is {versions.get('vtk_smp_backend')} (Sequential: one thread).\n")
    return dict(size=size, n=n, tets=mesh.n_tets, ref_pixels=int(pix.size), ref_s=ref_s,
                old_isovalue=PEER_OLD_ISO, new_isovalue=PEER_NEW_ISO, rows=rows,
                skipped=skipped, versions=versions)


def accuracy(b, cfg):
    size, n = cfg["acc_size"], cfg["acc_n"]
    v = view((0, 0, 0), (1, 1, 1))
    o32, d32 = reference_rays(v, size)
    o64, d64 = o32.astype(np.float64), d32.astype(np.float64)
    print(f"== Accuracy: cube_tets({n}) ({6 * n**3} tets), {size}x{size} rays, jaxiso "
          f"(float32) vs the float64 reference on the same rays; depth error relative to t")
    rows = []
    for field in cfg["acc_fields"]:
        mesh, iso, _ = b.mesh(n, field)
        t0 = now()
        t_ref, _, _, _ = ref.first_hits(mesh.points, mesh.tets, mesh.values[0], o64, d64, iso)
        ref_s = now() - t0
        for method in METHODS:
            bvh, _, _ = b.build(mesh, method, key=(n, field))
            scene = on_device(TetIsosurface(mesh, iso, bvh=bvh))
            row, hit, t = b.intersect(scene, o32, d32, size)
            rows.append(dict(field=field, isovalue=iso, method=method, n=n, tets=mesh.n_tets,
                             size=size, ref_s=ref_s, **row, **depth_stats(hit, t, t_ref)))
    print_table(["field", "method", "ref hit", "mask agree", "mismatch", "rel depth med",
                 "rel depth max", "compile s", "run s"],
                [[r["field"], r["method"], fmt(r["ref_hit_fraction"], ".2f"),
                  fmt(r["mask_agreement"], ".4f"), str(r["mask_mismatches"]),
                  fmt(r["depth_rel_median"], ".1e"), fmt(r["depth_rel_max"], ".1e"),
                  compile_cell(r), fmt(r["run_s"])] for r in rows])
    return dict(size=size, n=n, rows=rows)


# ---------------------------------------------------------------------------- charts


def charts(plt, save, result):
    """Draws the charts of `result`; save(fig, name) writes each (`common.save_charts`)."""
    if result.get("table51", {}).get("rows"):
        rows = result["table51"]["rows"]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for method, marker in zip(METHODS, "os"):
            rr = [r for r in rows if r["method"] == method]
            axes[0].plot([r["tets"] for r in rr], [r["build_ms"] for r in rr], marker=marker,
                         label=method)
            axes[1].plot([r["tets"] for r in rr], [r["mrays_per_s"] for r in rr],
                         marker=marker, label=method)
        axes[0].axhline(1e3 * BUILD_TARGET_S, color="k", lw=0.8, ls="--",
                        label="target (1M tets, BIH)")
        axes[0].set_ylabel("build ms (numpy)")
        axes[1].set_ylabel(f"render Mrays/s at {result['table51']['size']}^2")
        for ax in axes:
            ax.set_xscale("log")
            ax.set_xlabel("tets")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend()
        fig.suptitle("Table 5.1 analog: BIH vs SAH")
        save(fig, "table51")
    if result.get("table53", {}).get("rows"):
        rows = result["table53"]["rows"]
        fig, ax = plt.subplots(figsize=(6.5, 4))
        x = [r["tets"] for r in rows]
        ax.plot(x, [r["run_s"] for r in rows], marker="o", label="render s")
        ax.plot(x, [r["build_s"] for r in rows], marker="x", ls="--", label="BIH build s")
        if rows[0]["k"] == 1:
            ax.plot([x[0], 64 * x[0]], [rows[0]["run_s"], REPLICATION_TARGET * rows[0]["run_s"]],
                    color="k", lw=0.8, ls=":", label=f"target: {REPLICATION_TARGET:g}x per 64x")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("tets (k^3 copies)")
        ax.set_ylabel("seconds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        ax.set_title(f"Table 5.3 analog: replication, {result['table53']['size']}^2")
        save(fig, "table53")
    if result.get("modalities", {}).get("rows"):
        rows = result["modalities"]["rows"]
        fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.5))
        ax.barh([r["label"] for r in rows], [r["relative"] or 0.0 for r in rows])
        ax.axvline(1.0, color="k", lw=0.8)
        ax.set_xlabel("render time relative to plain")
        ax.invert_yaxis()
        ax.set_title(f"modalities, {result['modalities']['tets']} tets, "
                     f"{result['modalities']['size']}^2")
        save(fig, "modalities")
    if result.get("timevarying", {}).get("rows"):
        rows = result["timevarying"]["rows"]
        fig, axes = plt.subplots(1, 2, figsize=(12, 0.32 * len(rows) + 1.8))
        labels = [f"{r['method']}: {r['change']}: {r['how']}" for r in rows]
        axes[0].barh(labels, [r["seconds"] for r in rows])
        axes[0].set_xscale("log")
        axes[0].set_xlabel("seconds for the change")
        axes[1].barh(labels, [r["render_s"] or 0.0 for r in rows])
        axes[1].set_xlabel("render s after it")
        axes[1].set_yticks([])
        for ax in axes:
            ax.invert_yaxis()
            ax.tick_params(axis="y", labelsize=7)
        fig.suptitle(f"time-varying data, {result['timevarying']['tets']} tets, "
                     f"{result['timevarying']['size']}^2")
        save(fig, "timevarying")
    if result.get("peers", {}).get("rows"):
        rows = result["peers"]["rows"]
        # the pipelines differ by orders of magnitude: one bar per stage on a log axis
        labels, secs, colors = [], [], []
        for i, r in enumerate(rows):
            for stage, sec in {"image_s": r["image_s"], **r["stages"]}.items():
                labels.append(f"{r['pipeline']}: " + ("image (total)" if stage == "image_s"
                                                      else stage[:-2]))
                secs.append(max(sec, 1e-6))
                colors.append(f"C{i}")
        fig, ax = plt.subplots(figsize=(7, 0.3 * len(labels) + 1.5))
        ax.barh(labels, secs, color=colors)
        ax.set_xscale("log")
        ax.set_xlabel("seconds to an image after an isovalue change")
        ax.invert_yaxis()
        ax.set_title(f"peers, {result['peers']['tets']} tets, {result['peers']['size']}^2")
        save(fig, "peers")


# ---------------------------------------------------------------------------- main


def config(args):
    if args.quick:
        size, n = 16, 3
        return dict(quick=True, size=size, t51_n=[n], t51_field="wave", t53_base=n,
                    t53_k=[1, 2], work_size=size, mod_n=n,
                    modalities=["plain", "clip box"], tv_n=n, tv_steps=2,
                    tv_methods=["bih"], tv_amplitudes=[0.05], tv_work=False, peer_n=n,
                    ref_size=size, acc_n=n, acc_size=size, acc_fields=list(FIELDS),
                    build_repeats=args.build_repeats)
    return dict(quick=False, size=args.size,
                t51_n=[int(x) for x in args.table51_n.split(",")], t51_field="wave",
                t53_base=args.table53_base, t53_k=[int(x) for x in args.table53_k.split(",")],
                work_size=args.work_size, mod_n=args.mesh_n,
                modalities=[m[0] for m in MODALITIES], tv_n=args.mesh_n, tv_steps=4,
                tv_methods=list(METHODS), tv_amplitudes=[0.02, 0.1], tv_work=True,
                peer_n=args.mesh_n, ref_size=args.ref_size, acc_n=args.acc_n,
                acc_size=args.acc_size, acc_fields=list(FIELDS),
                build_repeats=args.build_repeats)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512,
                   help="image size (table51, table53, modalities, timevarying, peers)")
    p.add_argument("--table51-n", default="26,40,55",
                   help="comma-separated cube_tets sizes n (6 n^3 tets) of table51/table54")
    p.add_argument("--table53-base", type=int, default=12,
                   help="cube_tets n of the replicated base mesh (6 n^3 tets)")
    p.add_argument("--table53-k", default="1,2,4,8",
                   help="copies per axis (k^3 copies; skipped when memory is short)")
    p.add_argument("--work-size", type=int, default=128, help="table54 image size")
    p.add_argument("--mesh-n", type=int, default=26,
                   help="cube_tets n of the modalities, timevarying and peers meshes")
    p.add_argument("--ref-size", type=int, default=64,
                   help="pixel subsample edge for the peers' depth error")
    p.add_argument("--acc-size", type=int, default=64, help="accuracy image size")
    p.add_argument("--acc-n", type=int, default=16, help="cube_tets n of the accuracy meshes")
    args, only = common.parse_args(p, argv, SECTIONS, ROOT / "results",
                                   repeat_flags=("--repeats", "--build-repeats"))
    cfg = config(args)
    load = load_average()
    run = common.Run("tetra", args, only, cfg, header_note=f"load average {load}, ",
                     stamp=lambda result: result.update(load_average_end=load_average()),
                     load_average_start=load, source=source_state(),
                     timing=common.TIMING + "; builds: median of build_repeats numpy builds")
    b = Bench(args.repeats, args.slow_s, cfg["build_repeats"])

    def load_note(section):
        section["load_average"] = load_average()
        return f", load average {section['load_average']}"

    funcs = dict(table51=table51, table53=table53, table54=table54, modalities=modalities,
                 timevarying=timevarying, peers=peers, accuracy=accuracy)
    run.sections(SECTIONS, lambda sec: funcs[sec](b, cfg), load_note)
    return run.finish(charts)


if __name__ == "__main__":
    main()
