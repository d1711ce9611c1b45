"""Isosurfaces of structured volumes (seed ch. 3-4): octree compression, octree vs dense
macrocell grid, packet sizes, level of detail, peers (marching cubes, flying edges) and
accuracy against a float64 reference.

    python benchmarks/bench_volume.py [--size 512] [--volume 256] [--quick] [--repeats 3]
        [--only table31,table32,packets,lod,peers,accuracy] [--out benchmarks/results]

Ray casts run ``ji.intersect(scene, rays, plan=plan)`` on the camera's rays in tile order
with the plan a user gets (``ji.plan_for(scene, n_rays)``: tile x tile packets, or on the
CPU from 2^16 rays the whole image as one queue on persistent lanes with refill, as render
does), except the packets section, which sweeps plans; the peers' jaxiso images run
``ji.render``. Every row records its plan (``plan``, e.g. "Plan(tile=8, lanes=None)").
Compile time (AOT ``lower().compile()``) is reported apart from run time: one warm-up
call, then the median of `repeats` calls, each ``jax.block_until_ready``; an entry whose
warm-up call takes longer than `slow_s` is timed by that call alone (repeats_used 0).
Mrays/s = pixels / run s. Where plans are tuned (packets) and in the peers section, the
calls a user writes first (``ji.intersect(scene, camera.rays())``, ``ji.render(scene,
camera)``: no plan, no manual ``jax.jit``; first call = compile + run) are timed beside.
Work counters come from ``hits.steps`` (cells visited per ray). Depth errors are in voxel
widths (the smallest spacing), against the exact trilinear surface computed by
tests/reference_volume64.py (float64, sampling + bisection).

Sections:
  table31   compression (seed Table 3.1): octree bytes vs the raw array for the mixing
            layer (float32 and uint8, several time steps, their VolumeSequence), the CT
            phantom, Marschner-Lobb, a sphere distance field and nibabel's example4d
            (one volume), each full range and clamped to an iso-range, plus lossy rows;
            build seconds; the reconstruction error (to_array vs the clamped input).
  table32   octree (restart / neighbour traversal) vs the dense macrocell grid (seed
            Table 3.2) on the mixing layer at isovalue 127.5, far and close cameras.
  packets   tile sizes 2..32 (seed Table 4.2) and persistent lanes, octree restart, far
            camera; the default calls (ji.intersect, ji.render) side by side.
  lod       dP/dV quality 1, 2, 4, smooth and not, vs full resolution (seed Fig. 4.12 /
            4.15): Mrays/s, hit-mask differences and pinholes, colour differences of
            the hits shaded white on black, depth differences; the difference images
            go to <out>/volume_lod_diff.png.
  peers     time to an image after an isovalue change, volumes 64^3 .. 512^3: jaxiso
            (with_isovalues + compiled render; build and compile reported once), scikit-
            image marching cubes + open3d ray casting, VTK flying edges + open3d ray
            casting (each skipped, with the reason, when its library is missing); stage
            seconds, growth per 8x voxels, depth error on a pixel subsample.
  accuracy  neubauer vs analytic cell roots on the mixing layer and Marschner-Lobb:
            depth error (max / median / p99), hit-mask agreement, speed.
Writes ``<out>/volume_<backend>.json`` and, when matplotlib is installed, charts
``<out>/volume_<backend>_{table31,table32,packets,lod,peers}.png``.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys

import numpy as np

import jaxiso as ji
from jaxiso.volume import MacrocellGrid, OctreeVolume, VolumeIsosurface, VolumeSequence, lod_for
from jaxiso.volume import data as vdata

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests"))
import _common as common  # noqa: E402
import reference_volume64 as ref  # noqa: E402
from _common import compile_cell, fmt, now, print_table, subsample  # noqa: E402

SECTIONS = ("table31", "table32", "packets", "lod", "peers", "accuracy")
LANES = 4096  # persistent lanes swept by the packets section (plan_for's CPU choice)
MIXING_TIME = 1.0
MIXING_ISO = vdata.ISOVALUES["mixing"]  # 127.5, the middle of the mixing layer
PEER_NEW_ISO = 96.0  # the isovalue the peers section changes to
LOD_QUALITIES = (1.0, 2.0, 4.0)
# the seed's iso-range clamp for the RM data (Table 3.1), on our 0..255 mixing layer
MIXING_CLAMP = (64, 127)

# Camera views in unit-cube coordinates, mapped onto each data set's domain box.
VIEWS = {
    "far": dict(eye=(2.05, 1.55, 1.5), target=(0.5, 0.5, 0.45), fov=32.0),
    "close": dict(eye=(0.28, 0.2, 0.8), target=(0.62, 0.6, 0.45), fov=60.0),
}

# Seed tables for side-by-side reading (2007-2008 hardware: shape, not targets).
# Table 3.1: (data, iso-range, time step, original bytes, octree bytes, %)
SEED_TABLE31 = [
    ("heptane", "full", "70", "27.5M", "3.96M", 14),
    ("heptane", "full", "152", "27.5M", "9.5M", 33),
    ("heptane", "full", "0-152", "4.11G", "678M", 16),
    ("RM", "full", "50", "8.0G", "687M", 8.5),
    ("RM", "full", "150", "8.0G", "1.89G", 25),
    ("RM", "full", "270", "8.0G", "2.48G", 30),
    ("RM", "64-127", "270", "8.0G", "1.81G", 22),
    ("CThead", "full", "", "14.8M", "12.4M", 84),
    ("femur", "full", "", "162M", "163M", 101),
    ("femur", "100-163", "", "162M", "9.0M", 5.5),
]
# Table 3.2 (fps, RM t=270, 16-core Opteron): data source -> (macrocell grid, octree)
SEED_TABLE32 = {"3D array": (18.9, 15.7), "octree volume": (8.0, 17.5)}
# Table 4.2 (512^2, one Core Duo core; (intersections/ray, fps)) per packet edge (1 = single)
SEED_TABLE42 = {
    "HEP64": {1: (0.70, 1.9), 2: (0.26, 4.3), 4: (0.11, 9.7), 8: (0.058, 14.4),
              16: (0.041, 14.5)},
    "HEP302": {1: (0.64, 2.3), 2: (0.5, 2.84), 4: (0.45, 4.54), 8: (0.47, 4.6),
               16: (0.50, 2.81)},
    "RM": {1: (3.58, 0.57), 2: (5.65, 0.38), 4: (7.94, 0.33), 8: (12.4, 0.22),
           16: (20.5, 0.08)},
}
# Fig. 4.12 (RM t=270, 512^2, Core Duo fps): single-ray, then dP/dV 1, 2, 4; Fig. 4.15
# (fps forward / central differences): without and with multiresolution at dP/dV 1
SEED_LOD = {"fig412_fps": {"single": 0.92, 1: 1.0, 2: 1.9, 4: 3.6},
            "fig415_fps": {"full": (1.8, 1.3), "dPdV1": (4.2, 3.1)}}

SHADING = ji.Shading()  # the peers' jaxiso images: default Phong, no shadows


# ---------------------------------------------------------------------------- data


def geometry(name, shape):
    """(spacing, origin) of a `jaxiso.volume.data` example sampled on `shape`."""
    return vdata.box_geometry(shape, *vdata.DOMAINS[name])


def view(name, kind):
    """eye / target / up / fov of VIEWS[kind] on data set `name`'s domain."""
    lo, hi = vdata.DOMAINS[name]
    v = VIEWS[kind]
    return dict(eye=tuple(lo + (hi - lo) * c for c in v["eye"]),
                target=tuple(lo + (hi - lo) * c for c in v["target"]), up=(0.0, 0.0, 1.0),
                fov=v["fov"])


def camera(v, size):
    return ji.Camera.look_at(v["eye"], v["target"], v["up"], v["fov"], size, size)


def tiled(cam, tile):
    """Camera rays in tile order (tile x tile packets)."""
    r = cam.rays()
    return ji.Rays(ji.to_tiles(r.origin, tile), ji.to_tiles(r.direction, tile))


def nibabel_example():
    """(volume [nx, ny, nz] int16, spacing) of nibabel's example4d.nii.gz (time step 0),
    or (None, reason)."""
    try:
        import nibabel
    except ImportError:
        return None, "nibabel not installed (pip install -e '.[data]')"
    path = pathlib.Path(nibabel.__file__).parent / "tests" / "data" / "example4d.nii.gz"
    if not path.exists():
        return None, f"{path} not shipped with this nibabel"
    from jaxiso.io import load_volume

    arr, meta = load_volume(path)
    return (arr[..., 0] if arr.ndim == 4 else arr), meta["spacing"]


# ---------------------------------------------------------------------------- runner


class Bench(common.TimedBench):
    """Caches data, volumes and compiled executables; times calls."""

    def __init__(self, repeats: int, slow_s: float):
        super().__init__(repeats, slow_s)
        self._arrays = {}
        self._octrees = {}

    # -- data
    def mixing(self, n, *, time=MIXING_TIME, quantize=False):
        """(array, seconds to generate) of the mixing layer, cached."""
        key = ("mixing", n, time, quantize)
        if key not in self._arrays:
            t0 = now()
            a = vdata.mixing(n, time=time, quantize=quantize)
            self._arrays[key] = (a, now() - t0)
        return self._arrays[key]

    def mixing_octree(self, n, *, time=MIXING_TIME):
        """(float32 mixing octree with multires, build seconds), cached."""
        key = (n, time)
        if key not in self._octrees:
            a, _ = self.mixing(n, time=time)
            sp, org = geometry("mixing", a.shape)
            t0 = now()
            vol = OctreeVolume.from_array(a, spacing=sp, origin=org, progress=False)
            self._octrees[key] = (vol, now() - t0)
        return self._octrees[key]

    # -- compile and time
    def render_exe(self, scene, cam, shading):
        """(executable, compile s, cached, plan) of jit(render) with the user's plan
        (``ji.plan_for``) and a constant `shading` (a Shading checks its fields on
        construction, so it cannot be a traced argument)."""
        plan = ji.plan_for(scene, cam.width * cam.height)
        exe, compile_s, cached = self.compiled(
            ("render", plan, id(shading)),
            lambda s, c: ji.render(s, c, shading=shading, plan=plan), scene, cam)
        return exe, compile_s, cached, plan

    def trace(self, scene, cam, plan=None, timed=True):
        """jit(intersect) of a camera's rays in tile order with `plan` (default: the user's,
        ``ji.plan_for(scene, pixels)``): (row, hit [H, W], t [H, W], normal [H, W, 3])."""
        h, w = cam.height, cam.width
        n = h * w
        plan = ji.plan_for(scene, n) if plan is None else plan
        rays = tiled(cam, plan.tile)
        exe, compile_s, cached = self.compiled(
            ("intersect", plan), lambda s, r: ji.intersect(s, r, plan=plan), scene, rays)
        hits, timing = self.timed(lambda: exe(scene, rays), timed)
        run_s = timing["run_s"]

        def image(a):
            return np.asarray(ji.from_tiles(a, plan.tile, h, w))

        steps = np.asarray(hits.steps, np.int64)
        hit = image(hits.hit)
        # one queue on persistent lanes: the batch is the packet
        packet = rays.origin.shape[0] if plan.lanes else plan.packet
        counters = work(steps, packet, run_s)
        if plan.lanes:  # lanes refill: a packet's slowest ray does not hold the others
            counters["lane_utilisation"] = None
        row = dict(**common.plan_fields(plan), packet=packet, pixels=n,
                   compile_s=compile_s, compile_cached=cached, run_s=run_s,
                   warmup_s=timing["warmup_s"], repeats_used=timing["repeats_used"],
                   mrays_per_s=n / run_s / 1e6, hit_fraction=float(hit.mean()), **counters)
        return row, hit, image(hits.t).astype(np.float64), image(hits.normal)

    def defaults(self, scene, cam):
        """The calls a user writes first, timed as written (no plan, no manual jit):
        ``ji.intersect(scene, camera.rays())`` (raster order; work counters as `trace`)
        and ``ji.render(scene, camera)``. Rows as `trace`'s, with first_call_s (compile +
        first run) instead of compile_s."""
        n = cam.width * cam.height
        plan = ji.plan_for(scene, n)
        rays = cam.rays()
        hits, row = self.user_call(lambda: ji.intersect(scene, rays), plan,
                                   "ji.intersect(scene, camera.rays())")
        steps = np.asarray(hits.steps, np.int64).reshape(-1)
        packet = n if plan.lanes else plan.packet
        counters = work(steps, packet, row["run_s"])
        if plan.lanes:
            counters["lane_utilisation"] = None
        row.update(label="default: intersect", packet=packet, pixels=n,
                   mrays_per_s=n / row["run_s"] / 1e6,
                   hit_fraction=float(np.mean(np.asarray(hits.hit))), **counters)
        rows = [row]
        _, row = self.user_call(lambda: ji.render(scene, cam), plan,
                                "ji.render(scene, camera)")
        row.update(label="default: render (with shading)", pixels=n,
                   mrays_per_s=n / row["run_s"] / 1e6)
        rows.append(row)
        return rows


def work(steps, packet, run_s):
    """Work counters of tile-ordered steps [N]: mean / max cells visited per ray, lane
    utilisation of packets (useful share of lane-iterations: sum of steps / sum over
    packets of packet x its slowest ray's steps) and ns per ray-step."""
    n_pk = -(-steps.size // packet)
    per = np.concatenate([steps, np.zeros(n_pk * packet - steps.size, np.int64)])
    lane_iters = float(per.reshape(n_pk, packet).max(axis=1).sum() * packet)
    total = int(steps.sum())
    return dict(steps_mean=float(steps.mean()), steps_max=int(steps.max()),
                steps_total=total,
                lane_utilisation=(total / lane_iters) if lane_iters else None,
                ns_per_step=run_s / max(total, 1) * 1e9)


def depth_stats(hit, t, hit_ref, t_ref, voxel):
    """Hit-mask difference and |t - t_ref| / voxel where both hit (unit-speed rays)."""
    both = hit & hit_ref
    err = np.abs(t[both] - t_ref[both]) / voxel
    return dict(mask_diff=float(np.mean(hit != hit_ref)),
                mask_agreement=float(np.mean(hit == hit_ref)), both_hit=int(both.sum()),
                depth_err_max=float(err.max()) if err.size else None,
                depth_err_median=float(np.median(err)) if err.size else None,
                depth_err_p99=float(np.percentile(err, 99)) if err.size else None)


# ---------------------------------------------------------------------------- printing


def mb(nbytes):
    return f"{nbytes / 2**20:.2f}M"


# ---------------------------------------------------------------------------- table31


def compression_row(label, arr, *, iso_range=None, variance=0.0, spacing=1.0, origin=0.0,
                    **info):
    """Build an octree; bytes, build seconds and the reconstruction error against the
    (clamped) input, computed here with numpy."""
    t0 = now()
    vol = OctreeVolume.from_array(arr, spacing=spacing, origin=origin, iso_range=iso_range,
                                  variance=variance, progress=False)
    build_s = now() - t0
    expected = np.asarray(arr)
    if iso_range is not None:  # the bounds in the data's dtype, as a clamped array holds them
        expected = np.clip(expected, *(np.asarray(v).astype(expected.dtype) for v in iso_range))
    err = np.abs(vol.to_array().astype(np.float64) - expected.astype(np.float64))
    row = dict(data=label, dtype=str(np.asarray(arr).dtype), shape=list(np.shape(arr)),
               iso_range=list(iso_range) if iso_range is not None else None,
               variance=variance, raw_nbytes=vol.raw_nbytes, octree_nbytes=vol.nbytes,
               percent=100.0 * vol.nbytes / vol.raw_nbytes, ratio=vol.compression_ratio,
               n_nodes=vol.n_nodes, n_caps=vol.n_caps, build_s=build_s,
               max_abs_error=float(err.max()), rms_error=float(np.sqrt(np.mean(err**2))),
               **info)
    return row, vol


def table31(b, cfg):
    n = cfg["t31_size"]
    print(f"== Table 3.1 analog: octree bytes vs raw (all arrays of the octree: records, "
          f"caps, min/max tree, multires values), {n}^3 unless stated; error = max "
          f"|to_array - clamped input|")
    rows, notes = [], []
    # mixing layer, float32 and uint8 (the seed's 8-bit data), several time steps
    a, gen_s = b.mixing(n)
    sp, org = geometry("mixing", a.shape)
    geo = dict(spacing=sp, origin=org)
    rows.append(compression_row("mixing", a, time=MIXING_TIME, gen_s=gen_s, **geo)[0])
    rows.append(compression_row("mixing", a, iso_range=MIXING_CLAMP, time=MIXING_TIME,
                                **geo)[0])
    for var in cfg["variances"]:
        rows.append(compression_row("mixing lossy", a, variance=var, time=MIXING_TIME,
                                    **geo)[0])
    step_vols, step_build = [], 0.0
    for t in cfg["time_steps"]:
        q, gen_s = b.mixing(n, time=t, quantize=True)
        row, vol = compression_row("mixing u8", q, time=t, gen_s=gen_s, **geo)
        rows.append(row)
        step_vols.append(vol)
        step_build += row["build_s"]
    q_last, _ = b.mixing(n, time=cfg["time_steps"][-1], quantize=True)
    rows.append(compression_row("mixing u8", q_last, iso_range=MIXING_CLAMP,
                                time=cfg["time_steps"][-1], **geo)[0])
    rows.append(compression_row("mixing u8 lossy", q_last, variance=cfg["variances"][0],
                                time=cfg["time_steps"][-1], **geo)[0])
    t0 = now()
    seq = VolumeSequence.from_volumes(step_vols)
    stack_s = now() - t0
    steps_label = f"{cfg['time_steps'][0]:g}-{cfg['time_steps'][-1]:g}"
    rows.append(dict(data="mixing u8 sequence", dtype="uint8", shape=[len(step_vols), n, n, n],
                     iso_range=None, variance=0.0, time=steps_label,
                     raw_nbytes=seq.raw_nbytes, octree_nbytes=seq.nbytes,
                     percent=100.0 * seq.nbytes / seq.raw_nbytes,
                     ratio=seq.compression_ratio, padded_nbytes=seq.padded_nbytes,
                     n_nodes=None, n_caps=None, build_s=step_build + stack_s,
                     stack_s=stack_s, max_abs_error=max(
                         r["max_abs_error"] for r in rows if r["data"] == "mixing u8"
                         and r["iso_range"] is None and r["variance"] == 0.0),
                     rms_error=None))
    notes.append(f"sequence of {len(step_vols)} steps ({steps_label}): footprint "
                 f"{mb(seq.nbytes)} of the steps' own octrees, {mb(seq.padded_nbytes)} held "
                 f"when stacked for traced step selection (each padded to the largest)")
    ct = vdata.ct_phantom(n)
    sp, org = geometry("ct_phantom", ct.shape)
    rows.append(compression_row("ct_phantom", ct, spacing=sp, origin=org)[0])
    rows.append(compression_row("ct_phantom", ct, iso_range=(100, 200), spacing=sp,
                                origin=org)[0])
    for m in dict.fromkeys((41, n)):
        ml = vdata.marschner_lobb(m)
        sp, org = geometry("marschner_lobb", ml.shape)
        rows.append(compression_row("marschner_lobb", ml, spacing=sp, origin=org)[0])
    rows.append(compression_row("marschner_lobb", ml, iso_range=(0.45, 0.55), spacing=sp,
                                origin=org)[0])
    sd = vdata.sphere_distance(n)
    sp, org = geometry("sphere_distance", sd.shape)
    rows.append(compression_row("sphere_distance", sd, spacing=sp, origin=org)[0])
    rows.append(compression_row("sphere_distance", sd, iso_range=(-0.05, 0.05), spacing=sp,
                                origin=org)[0])
    nib, spacing = nibabel_example()
    if nib is None:
        notes.append(f"example4d skipped: {spacing}")
    else:
        rows.append(compression_row("nibabel example4d", nib, spacing=spacing)[0])
        rows.append(compression_row("nibabel example4d", nib, iso_range=(500, 800),
                                    spacing=spacing)[0])
    printed = []
    for r in rows:
        rng = "full" if r["iso_range"] is None else "{:g}-{:g}".format(*r["iso_range"])
        if r["variance"]:
            rng += f", var {r['variance']:g}"
        printed.append([r["data"], rng, fmt(r.get("time"), "g"), r["dtype"],
                        "x".join(map(str, r["shape"])), mb(r["raw_nbytes"]),
                        mb(r["octree_nbytes"]), fmt(r["percent"], ".1f"),
                        fmt(r["build_s"], ".2f"), fmt(r["max_abs_error"], ".3g")])
    print_table(["data", "iso-range", "time", "dtype", "shape", "original", "octree", "%",
                 "build s", "error"], printed)
    for line in notes:
        print("  " + line)
    print("  seed Table 3.1 (%): " + ", ".join(f"{d} {r}{' t=' + t if t else ''} {p:g}"
                                               for d, r, t, _, _, p in SEED_TABLE31))
    big = [r for r in rows if r["shape"] == [n, n, n] and r["data"] == "mixing"
           and r["iso_range"] is None]
    if big:
        print(f"  {n}^3 build (float32 mixing, lossless): {big[0]['build_s']:.2f} s")
    print()
    return dict(size=n, rows=rows, notes=notes, seed_table31=SEED_TABLE31)


# ---------------------------------------------------------------------------- table32


def table32(b, cfg):
    n, size = cfg["volume"], cfg["size"]
    vol, build_s = b.mixing_octree(n)
    a, _ = b.mixing(n)
    sp, org = geometry("mixing", a.shape)
    t0 = now()
    grid = MacrocellGrid.from_array(a, spacing=sp, origin=org, levels=(5, 3))
    grid_build_s = now() - t0
    print(f"== Table 3.2 analog: mixing {n}^3 float32, isovalue {MIXING_ISO}, {size}x{size}, "
          f"the user's plans (ji.plan_for); octree {mb(vol.nbytes)}, macrocell grid "
          f"(levels 2^5, 2^3, over the dense array) {mb(grid.nbytes)}")
    configs = [c for c in (("octree", "restart", vol), ("octree", "neighbor", vol),
                           ("grid", "-", grid)) if c[0] in cfg["structures"]
               or c[1] in cfg["structures"]]
    rows, printed = [], []
    for cam_kind in cfg["cameras"]:
        cam = camera(view("mixing", cam_kind), size)
        base_hit = None
        for structure, traversal, source in configs:
            opts = {} if structure == "grid" else dict(traversal=traversal)
            scene = VolumeIsosurface(source, MIXING_ISO, **opts)
            row, hit, _, _ = b.trace(scene, cam)
            base_hit = hit if base_hit is None else base_hit
            row.update(structure=structure, traversal=traversal, camera=cam_kind,
                       size=size, volume=n, structure_nbytes=source.nbytes,
                       build_s=build_s if structure == "octree" else grid_build_s,
                       mask_diff_vs_restart=float(np.mean(hit != base_hit)))
            rows.append(row)
            printed.append([cam_kind, structure, traversal, mb(source.nbytes), row["plan"],
                            compile_cell(row), fmt(row["run_s"]), fmt(row["mrays_per_s"]),
                            fmt(row["steps_mean"], ".1f"), str(row["steps_max"]),
                            fmt(row["hit_fraction"]), fmt(row["lane_utilisation"], ".2f"),
                            fmt(row["ns_per_step"], ".0f"),
                            fmt(row["mask_diff_vs_restart"], ".4f")])
    print_table(["camera", "structure", "traversal", "bytes", "plan", "compile s", "run s",
                 "Mrays/s", "steps", "max", "hit", "util", "ns/step", "mask diff"], printed)
    print("  (* compiled executable reused; mask diff: share of pixels whose hit differs "
          "from octree restart)")
    print(f"  seed Table 3.2 (fps, RM t=270, 16 cores): grid / octree over the 3D array "
          f"{SEED_TABLE32['3D array']}, over octree data {SEED_TABLE32['octree volume']}\n")
    return dict(volume=n, size=size, isovalue=MIXING_ISO,
                plan=sorted({r["plan"] for r in rows}), octree_build_s=build_s,
                grid_build_s=grid_build_s, grid_levels=[5, 3],
                rows=rows, seed_table32=SEED_TABLE32)


# ---------------------------------------------------------------------------- packets


def packets(b, cfg):
    n, size = cfg["volume"], cfg["size"]
    vol, _ = b.mixing_octree(n)
    cam = camera(view("mixing", "far"), size)
    scene = VolumeIsosurface(vol, MIXING_ISO)
    user_plan = ji.plan_for(scene, size * size)
    print(f"== Packets (Table 4.2 analog): mixing {n}^3, octree restart, far camera, "
          f"{size}x{size}; the user's plan (ji.plan_for) is {user_plan!r}")
    plans = [(f"{t}x{t}", ji.Plan(tile=t)) for t in cfg["tiles"]]
    # persistent lanes: the whole image as one queue, in the user plan's tile order
    plans += [(f"{lanes} lanes", ji.Plan(tile=user_plan.tile, lanes=lanes))
              for lanes in cfg["lanes"]]
    rows, printed = [], []
    for label, plan in plans:
        row, _, _, _ = b.trace(scene, cam, plan)
        row.update(label=label, volume=n, size=size)
        rows.append(row)
        printed.append([row["label"], row["plan"], compile_cell(row), fmt(row["run_s"]),
                        fmt(row["mrays_per_s"]), fmt(row["steps_mean"], ".1f"),
                        str(row["steps_max"]), fmt(row["lane_utilisation"], ".2f"),
                        fmt(row["ns_per_step"], ".0f")])
    defaults = b.defaults(scene, cam)
    for d in defaults:
        d.update(volume=n, size=size)
        printed.append([d["label"], d["plan"], fmt(d["first_call_s"], ".1f") + "+",
                        fmt(d["run_s"]), fmt(d["mrays_per_s"]), fmt(d.get("steps_mean"), ".1f"),
                        fmt(d.get("steps_max"), "d"), fmt(d.get("lane_utilisation"), ".2f"),
                        fmt(d.get("ns_per_step"), ".0f")])
    print_table(["packet", "plan", "compile s", "run s", "Mrays/s", "steps", "max", "util",
                 "ns/step"], printed)
    best = max(rows, key=lambda r: r["mrays_per_s"])
    print(f"  fastest: {best['label']} ({best['mrays_per_s']:.4f} Mrays/s); the user's "
          + "; ".join(f"{d['call']}: {d['mrays_per_s']:.4f} Mrays/s" for d in defaults)
          + " ('+': a user call's first call, compile + run)")
    print(f"  seed Table 4.2 (fps by packet edge): RM {_seed42('RM')}, HEP302 "
          f"{_seed42('HEP302')}\n")
    return dict(volume=n, size=size, rows=rows, fastest=best["label"],
                user_plan=repr(user_plan), defaults=defaults,
                seed_table42={k: {str(e): v for e, v in d.items()}
                              for k, d in SEED_TABLE42.items()})


def _seed42(name):
    return ", ".join(f"{e}:{v[1]}" for e, v in SEED_TABLE42[name].items())


# ---------------------------------------------------------------------------- lod


def lod(b, cfg, out_dir):
    n, size = cfg["volume"], cfg["size"]
    vol, _ = b.mixing_octree(n)
    cam = camera(view("mixing", "far"), size)
    direction = np.asarray(cam.rays().direction)
    voxel = float(np.min(np.asarray(vol.spacing)))
    print(f"== Level of detail (Fig. 4.12/4.15 analog): mixing {n}^3, far camera, "
          f"{size}x{size}; intersect with the user's plans, timed as in table32; images: "
          f"the hits shaded white on black (Lambert); differences vs full resolution "
          f"(depth in voxels, where both hit)")
    full = VolumeIsosurface(vol, MIXING_ISO)
    full_row, full_hit, full_t, normal = b.trace(full, cam)
    full_img = lambert_image(full_hit, normal, direction)
    full_row.update(label="full", quality=None, smooth=None, mask_diff=0.0, colour_diff=0.0,
                    depth_diff_median=0.0, depth_diff_p99=0.0, speedup=1.0,
                    pinholes=pinholes(full_hit, full_hit))
    rows, images = [full_row], {"full": full_img}
    for smooth in cfg["lod_smooth"]:
        for q in cfg["lod_qualities"]:
            scene = full.with_lod(lod_for(cam, q, smooth=smooth))
            row, hit, t, normal = b.trace(scene, cam)
            img = lambert_image(hit, normal, direction)
            both = hit & full_hit
            dd = np.abs(t[both] - full_t[both]) / voxel
            label = f"dP/dV {q:g}" + (" smooth" if smooth else "")
            row.update(label=label, quality=q, smooth=smooth,
                       mask_diff=float(np.mean(hit != full_hit)),
                       pinholes=pinholes(hit, full_hit),
                       colour_diff=float(np.mean(np.abs(img - full_img))),
                       depth_diff_median=float(np.median(dd)) if dd.size else None,
                       depth_diff_p99=float(np.percentile(dd, 99)) if dd.size else None,
                       speedup=full_row["run_s"] / row["run_s"])
            rows.append(row)
            images[label] = img
    printed = [[r["label"], compile_cell(r), fmt(r["run_s"]), fmt(r["mrays_per_s"]),
                fmt(r["speedup"], ".2f"), fmt(r["steps_mean"], ".1f"),
                fmt(100 * r["mask_diff"], ".2f"), str(r["pinholes"]),
                fmt(r["colour_diff"], ".4f"), fmt(r["depth_diff_median"], ".3f"),
                fmt(r["depth_diff_p99"], ".3f")] for r in rows]
    print_table(["resolution", "compile s", "run s", "Mrays/s", "speedup", "steps", "mask %",
                 "pinholes", "colour", "depth med", "depth p99"], printed)
    print("  pinholes: missed pixels whose 4 neighbours hit, where full resolution hits "
          "(cracks, or surface parts thinner than a coarse cell)")
    print(f"  seed Fig. 4.12 (RM, 512^2, Core Duo fps): {SEED_LOD['fig412_fps']}\n")
    path = lod_difference_png(rows, images, out_dir / "volume_lod_diff.png")
    return dict(volume=n, size=size, isovalue=MIXING_ISO, rows=rows,
                difference_png=str(path), seed=SEED_LOD)


def pinholes(hit, full_hit):
    """Pixels [H, W] that miss while their 4 neighbours hit and the full-resolution image
    hits there: holes in an otherwise covered surface."""
    inner = np.zeros_like(hit)
    inner[1:-1, 1:-1] = (hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
                         & ~hit[1:-1, 1:-1])
    return int(np.sum(inner & full_hit))


LIGHT = np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])  # render's default


def lambert_image(hit, normal, direction):
    """[H, W, 3] white-on-black Lambert image of hits (normals turned to face the ray),
    the seed's Fig. 4.15 style."""
    facing = np.where(np.sum(normal * direction, axis=-1, keepdims=True) > 0, -normal, normal)
    grey = 0.18 + 0.75 * np.maximum(facing @ LIGHT, 0.0)
    return np.repeat(np.where(hit, grey, 0.0)[..., None], 3, axis=-1).astype(np.float32)


def lod_difference_png(rows, images, path):
    """Fig. 4.15-style mosaic: the images on top, 1 - |full - image| per channel below."""
    labels = [r["label"] for r in rows]
    full = images["full"]
    diffs = {k: 1.0 - np.abs(full - images[k]) for k in labels}
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # a plain mosaic: images above, differences below
        ji.save_png(np.concatenate([np.concatenate([images[k] for k in labels], axis=1),
                                    np.concatenate([diffs[k] for k in labels], axis=1)]), path)
        return path
    fig, axes = plt.subplots(2, len(labels), figsize=(2.6 * len(labels), 5.6), squeeze=False)
    by_label = {r["label"]: r for r in rows}
    for j, k in enumerate(labels):
        r = by_label[k]
        axes[0, j].imshow(np.clip(images[k], 0, 1))
        axes[0, j].set_title(f"{k}\n{r['mrays_per_s']:.3f} Mrays/s", fontsize=8)
        axes[1, j].imshow(np.clip(diffs[k], 0, 1))
        axes[1, j].set_title(f"mask {100 * r['mask_diff']:.2f}%, colour "
                             f"{r['colour_diff']:.4f}", fontsize=8)
        for ax in axes[:, j]:
            ax.set_axis_off()
    fig.suptitle("level of detail vs full resolution: images (top), 1 - |full - image| "
                 "(bottom)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------- peers


def peer_versions():
    """Versions of the peer libraries, and why a missing one is missing."""
    out = {}
    for name in ("skimage", "open3d", "vtk"):
        try:
            mod = __import__(name)
            out[name] = getattr(mod, "__version__", None) or _vtk_version(mod)
        except Exception as e:  # ImportError, or a missing shared library (open3d: libusb)
            out[name] = None
            out[name + "_error"] = f"{type(e).__name__}: {e}"
    return out


def _vtk_version(mod):
    return mod.vtkVersion.GetVTKVersion() if hasattr(mod, "vtkVersion") else "?"


def lambert(t, normals):
    """A two-sided Lambert image [N, 3] of mesh hits (the peers' shading stage)."""
    shade = 0.18 + 0.75 * np.abs(normals @ LIGHT.astype(np.float32))
    col = shade[:, None] * np.array([0.85, 0.55, 0.25], np.float32)
    return np.where(np.isfinite(t)[:, None], col, 1.0)


def peer_marching_cubes(a, iso, sp, org, o, d):
    """scikit-image marching cubes + open3d ray casting + shading of rays o, d [N, 3]:
    (stage seconds, t [N])."""
    from skimage.measure import marching_cubes

    t0 = now()
    verts, faces, _, _ = marching_cubes(a, iso, spacing=tuple(sp))
    extract_s = now() - t0
    verts = verts + np.asarray(org)
    t, normals, cast_s, again_s = common.mesh_raycast(verts, faces, o, d)
    t0 = now()
    lambert(t, normals)
    shade_s = now() - t0
    return dict(extract_s=extract_s, cast_s=cast_s, shade_s=shade_s,
                image_s=extract_s + cast_s + shade_s, cast_again_s=again_s,
                triangles=int(faces.shape[0])), t


def peer_flying_edges(a, iso, sp, org, o, d):
    """VTK flying edges + open3d ray casting + shading: (stage seconds, t [N])."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    t0 = now()
    # VTK runs its first axis fastest: hand it the C-order array with the axes reversed
    # (no copy) and swap the mesh's coordinates back
    img = vtkImageData()
    img.SetDimensions(*a.shape[::-1])
    img.SetSpacing(*sp[::-1])
    img.SetOrigin(*org[::-1])
    img.GetPointData().SetScalars(numpy_to_vtk(np.ascontiguousarray(a).reshape(-1),
                                               deep=False))
    wrap_s = now() - t0
    t0 = now()
    poly = common.vtk_isosurface(vtkFlyingEdges3D(), img, iso, "Normals", "Gradients",
                                 "Scalars")
    verts = vtk_to_numpy(poly.GetPoints().GetData())[:, ::-1]
    faces = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    extract_s = now() - t0
    t, normals, cast_s, again_s = common.mesh_raycast(verts, faces, o, d)
    t0 = now()
    lambert(t, normals)
    shade_s = now() - t0
    return dict(wrap_s=wrap_s, extract_s=extract_s, cast_s=cast_s, shade_s=shade_s,
                image_s=wrap_s + extract_s + cast_s + shade_s, cast_again_s=again_s,
                triangles=int(faces.shape[0])), t


def timed_stages(b, run):
    """A mesh pipeline timed like the jitted calls: one warm-up run, then the median of
    each stage over `repeats` runs unless the warm-up took longer than `slow_s`."""
    stages, t = run()
    if stages["image_s"] > b.slow_s:
        return dict(stages, repeats_used=0), t
    runs = [run()[0] for _ in range(b.repeats)]
    return dict({k: statistics.median(r[k] for r in runs) for k in stages},
                triangles=stages["triangles"], repeats_used=len(runs)), t


def peers(b, cfg):
    size, ref_size = cfg["size"], cfg["ref_size"]
    versions = peer_versions()
    print(f"== Peers: time to an image after an isovalue change {MIXING_ISO} -> "
          f"{PEER_NEW_ISO}, mixing layer, far camera, {size}x{size}; depth error vs the "
          f"float64 trilinear reference on a {min(ref_size, size)}^2 pixel subsample")
    print("  versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()
                                     if not k.endswith("_error")))
    have = dict(mc=versions.get("skimage") is not None and versions.get("open3d") is not None,
                fe=versions.get("vtk") is not None and versions.get("open3d") is not None)
    skipped = []
    if not have["mc"]:
        skipped.append("marching cubes + open3d: " + (versions.get("open3d_error")
                                                       or versions.get("skimage_error", "")))
    if not have["fe"]:
        skipped.append("flying edges + open3d: " + (versions.get("vtk_error")
                                                     or versions.get("open3d_error", "")))
    v = view("mixing", "far")
    cam = camera(v, size)
    o_all, d_all = ref.camera_rays(v["eye"], v["target"], v["up"], v["fov"], size, size)
    idx = subsample(size, ref_size)
    pix = (idx[:, None] * size + idx[None, :]).reshape(-1)
    r = cam.rays()
    m = idx.size
    rows = []
    for n in cfg["peer_sizes"]:
        # the array, the build's temporaries, the reference's float64 copy, the meshes
        need_gb = 40 * n**3 / 2**30
        if common.available_gb() < need_gb:
            skipped.append(f"{n}^3: needs about {need_gb:.0f} GiB, "
                           f"{common.available_gb():.0f} GiB available")
            continue
        a, gen_s = b.mixing(n)
        sp, org = geometry("mixing", a.shape)
        voxel = float(min(sp))
        t0 = now()
        t_ref, hit_ref, _ = ref.first_hits(a, o_all[pix], d_all[pix], PEER_NEW_ISO,
                                           spacing=sp, origin=org)
        ref_s = now() - t0
        # (a) jaxiso: build once, compile once, then isovalue changes cost one render
        vol, build_s = b.mixing_octree(n)
        scene = VolumeIsosurface(vol, MIXING_ISO)
        new_scene = scene.with_isovalues(PEER_NEW_ISO)
        exe, compile_s, cached, plan = b.render_exe(scene, cam, SHADING)
        _, timing = b.timed(lambda: exe(new_scene, cam))
        # the same image as a user asks for it: ji.render, no plan, no manual jit (its
        # first call compiles; the same shapes then render any isovalue without one)
        _, user = b.user_call(lambda: ji.render(new_scene, cam, shading=SHADING), plan,
                              "ji.render(scene.with_isovalues(new), camera)")
        sub_plan = ji.plan_for(scene, m * m)
        sub_rays = ji.Rays(ji.to_tiles(r.origin[idx][:, idx], sub_plan.tile),
                           ji.to_tiles(r.direction[idx][:, idx], sub_plan.tile))
        sub_exe, sub_compile_s, _ = b.compiled(
            ("intersect", sub_plan),
            lambda s, rr: ji.intersect(s, rr, plan=sub_plan), scene, sub_rays)
        hits = sub_exe(new_scene, sub_rays)
        t_j = np.asarray(ji.from_tiles(hits.t, sub_plan.tile, m, m),
                         np.float64).reshape(-1)
        row = dict(pipeline="jaxiso", n=n, voxels=n**3, gen_s=gen_s, build_s=build_s,
                   plan=repr(plan), subsample_plan=repr(sub_plan),
                   compile_s=compile_s, compile_cached=cached, image_s=timing["run_s"],
                   warmup_s=timing["warmup_s"], repeats_used=timing["repeats_used"],
                   user_call=user, user_image_s=user["run_s"],
                   octree_nbytes=vol.nbytes, ref_s=ref_s, ref_pixels=int(pix.size),
                   subsample_compile_s=sub_compile_s,
                   **depth_stats(np.isfinite(t_j), t_j, hit_ref, t_ref, voxel))
        rows.append(row)
        o32, d32 = o_all.astype(np.float32), d_all.astype(np.float32)
        for key, name, fn in (("mc", "marching cubes + open3d", peer_marching_cubes),
                              ("fe", "flying edges + open3d", peer_flying_edges)):
            if not have[key]:
                continue
            stages, t_all = timed_stages(b, lambda: fn(a, PEER_NEW_ISO, sp, org, o32, d32))
            t_sub = t_all[pix]
            rows.append(dict(pipeline=name, n=n, voxels=n**3, **stages,
                             **depth_stats(np.isfinite(t_sub), t_sub, hit_ref, t_ref, voxel)))
        print(f"  {n}^3 done (reference {ref_s:.1f} s)", flush=True)
    printed = []
    for r in rows:
        stages = (f"build {r['build_s']:.2f} + compile {r['compile_s']:.1f} once; "
                  f"{r['plan']}; user call ji.render {r['user_image_s']:.3f} (first "
                  f"{r['user_call']['first_call_s']:.1f})"
                  if r["pipeline"] == "jaxiso" else
                  " + ".join(f"{k[:-2]} {r[k]:.3f}" for k in
                             ("wrap_s", "extract_s", "cast_s", "shade_s") if k in r))
        printed.append([r["pipeline"], f"{r['n']}^3", fmt(r["image_s"]), stages,
                        str(r.get("triangles", "-")), fmt(r["mask_agreement"], ".4f"),
                        fmt(r["depth_err_median"], ".2e"), fmt(r["depth_err_p99"], ".2e"),
                        fmt(r["depth_err_max"], ".2e")])
    print_table(["pipeline", "volume", "image s", "stages (s)", "triangles", "mask agree",
                 "depth med", "depth p99", "depth max"], printed)
    growth = growth_per_8x(rows)
    for name, g in growth.items():
        if not g:
            continue
        print(f"  growth per 8x voxels, {name}: " + "; ".join(
            f"{stage} " + ", ".join(fmt(x, ".1f") for x in ratios)
            for stage, ratios in g.items()))
    for s in skipped:
        print(f"  skipped: {s}")
    print("  jaxiso intersects the trilinear interpolant exactly (error: float32 roots); "
          "marching cubes approximates it by triangles through edge-interpolated points, "
          "so its depth error is not 0 and its hit mask differs where the surface is "
          "thinner than a cell.\n  Threads: XLA CPU and open3d (Embree) use every core; "
          "skimage marching cubes is single-threaded; VTK flying edges uses vtkSMPTools.\n")
    return dict(size=size, ref_pixels=int(pix.size), old_isovalue=MIXING_ISO,
                new_isovalue=PEER_NEW_ISO, sizes=cfg["peer_sizes"], rows=rows,
                growth_per_8x=growth, skipped=skipped, versions=versions)


def growth_per_8x(rows):
    """Per pipeline and stage: time ratio between consecutive volume sizes (2x per axis)."""
    stages = ("image_s", "build_s", "extract_s", "cast_s", "compile_s")
    out = {}
    for name in dict.fromkeys(r["pipeline"] for r in rows):
        rr = sorted((r for r in rows if r["pipeline"] == name), key=lambda r: r["n"])
        g = {}
        for s in stages:
            pairs = [(p[s], q[s]) for p, q in zip(rr, rr[1:])
                     if s in p and q["n"] == 2 * p["n"] and p[s]]
            if pairs:
                g[s] = [q / p for p, q in pairs]
        out[name] = g
    return out


# ---------------------------------------------------------------------------- accuracy


def accuracy(b, cfg):
    size = cfg["acc_size"]
    print(f"== Accuracy: neubauer vs analytic cell roots, far camera, {size}x{size}, "
          f"errors in voxel widths vs the float64 reference (tests/reference_volume64.py)")
    cases = [(name, n) for name, n in (("mixing", cfg["acc_mixing"]),
                                       ("marschner_lobb", cfg["acc_ml"])) if n]
    rows, printed = [], []
    for name, n in cases:
        if name == "mixing":
            vol, _ = b.mixing_octree(n)
            arr, _ = b.mixing(n)
        else:
            arr = vdata.examples()[name](n)
            sp, org = geometry(name, arr.shape)
            vol = OctreeVolume.from_array(arr, spacing=sp, origin=org, progress=False)
        sp, org = geometry(name, arr.shape)
        iso = vdata.ISOVALUES[name]
        v = view(name, "far")
        o, d = ref.camera_rays(v["eye"], v["target"], v["up"], v["fov"], size, size)
        t0 = now()
        t_ref, hit_ref, _ = ref.first_hits(arr, o, d, iso, spacing=sp, origin=org)
        ref_s = now() - t0
        cam = camera(v, size)
        for method in ("neubauer", "analytic"):
            row, hit, t, _ = b.trace(VolumeIsosurface(vol, iso, method=method), cam)
            row.update(data=name, n=n, method=method, isovalue=iso, size=size, ref_s=ref_s,
                       **depth_stats(hit.reshape(-1), t.reshape(-1), hit_ref, t_ref,
                                     float(min(sp))))
            rows.append(row)
            printed.append([name, f"{n}^3", method, compile_cell(row),
                            fmt(row["mrays_per_s"]), fmt(row["steps_mean"], ".1f"),
                            fmt(row["mask_agreement"], ".4f"), fmt(row["depth_err_max"], ".2e"),
                            fmt(row["depth_err_median"], ".2e"),
                            fmt(row["depth_err_p99"], ".2e"), fmt(ref_s, ".1f")])
    print_table(["data", "volume", "method", "compile s", "Mrays/s", "steps", "mask agree",
                 "depth max", "depth med", "depth p99", "ref s"], printed)
    print("  (the reference samples 64 points per cell and bisects sign changes: it misses "
          "grazing double roots, so a mask disagreement can be the reference's)\n")
    return dict(size=size, rows=rows)


# ---------------------------------------------------------------------------- charts


def charts(plt, save, result):
    """Draws the charts of `result`; save(fig, name) writes each (`common.save_charts`)."""
    if "table31" in result:
        rows = result["table31"]["rows"]
        fig, ax = plt.subplots(figsize=(9, 0.28 * len(rows) + 1.5))
        n = result["table31"]["size"]
        labels = [f"{r['data']} " + ("full" if r["iso_range"] is None else
                                     "{:g}-{:g}".format(*r["iso_range"]))
                  + (f" var {r['variance']:g}" if r["variance"] else "")
                  + (f" t={r['time']}" if r.get("time") is not None else "")
                  + ("" if r["shape"][-3:] == [n, n, n] else
                     " " + "x".join(map(str, r["shape"]))) for r in rows]
        ax.barh(labels, [r["percent"] for r in rows])
        ax.axvline(100, color="k", lw=0.8)
        ax.set_xlabel("octree bytes, % of the raw array")
        ax.invert_yaxis()
        ax.tick_params(axis="y", labelsize=7)
        ax.set_title(f"Table 3.1 analog, {result['table31']['size']}^3")
        save(fig, "table31")
    if "table32" in result:
        rows = result["table32"]["rows"]
        fig, ax = plt.subplots(figsize=(7, 4))
        cams = list(dict.fromkeys(r["camera"] for r in rows))
        kinds = list(dict.fromkeys((r["structure"], r["traversal"]) for r in rows))
        x = np.arange(len(cams))
        for i, k in enumerate(kinds):
            vals = [next(r["mrays_per_s"] for r in rows if r["camera"] == c
                         and (r["structure"], r["traversal"]) == k) for c in cams]
            ax.bar(x + (i - 1) * 0.27, vals, 0.27, label=" ".join(p for p in k if p != "-"))
        ax.set_xticks(x, cams)
        ax.set_ylabel("Mrays/s")
        ax.set_title(f"octree vs macrocell grid, mixing {result['table32']['volume']}^3, "
                     f"{result['table32']['size']}^2")
        ax.legend()
        save(fig, "table32")
    if "packets" in result:
        rows = result["packets"]["rows"]
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.bar([r["label"] for r in rows], [r["mrays_per_s"] for r in rows])
        ax.set_ylabel("Mrays/s")
        ax.set_xlabel("packet (tile) or persistent lanes")
        ax.set_title(f"octree restart, mixing {result['packets']['volume']}^3, "
                     f"{result['packets']['size']}^2")
        save(fig, "packets")
    if "lod" in result:
        rows = result["lod"]["rows"]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, key, label in ((axes[0], "mask_diff", "hit mask difference (%)"),
                               (axes[1], "depth_diff_p99", "depth difference p99 (voxels)")):
            for smooth, marker in ((True, "o"), (False, "s"), (None, "*")):
                rr = [r for r in rows if r["smooth"] is smooth]
                if not rr:
                    continue
                scale = 100.0 if key == "mask_diff" else 1.0
                ax.plot([r["mrays_per_s"] for r in rr], [scale * (r[key] or 0.0) for r in rr],
                        marker=marker, ls="-" if smooth is not None else "",
                        label={True: "smooth", False: "not smooth", None: "full"}[smooth])
                for r in rr:
                    ax.annotate(r["label"].replace(" smooth", ""),
                                (r["mrays_per_s"], scale * (r[key] or 0.0)), fontsize=7)
            ax.set_xlabel("Mrays/s (jit(intersect))")
            ax.set_ylabel(label)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
        fig.suptitle(f"level of detail: speed vs error, mixing {result['lod']['volume']}^3, "
                     f"{result['lod']['size']}^2")
        save(fig, "lod")
    if "peers" in result and result["peers"]["rows"]:
        rows = result["peers"]["rows"]
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for name in dict.fromkeys(r["pipeline"] for r in rows):
            rr = [r for r in rows if r["pipeline"] == name]
            ax.plot([r["voxels"] for r in rr], [r["image_s"] for r in rr], marker="o",
                    label=f"{name}: image after isovalue change")
            if name == "jaxiso":
                ax.plot([r["voxels"] for r in rr], [r["build_s"] for r in rr], marker="x",
                        ls="--", label="jaxiso: octree build (once)")
                ax.plot([r["voxels"] for r in rr], [r["compile_s"] for r in rr], marker="+",
                        ls=":", label="jaxiso: render compile (once per volume)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("voxels")
        ax.set_ylabel("seconds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_title(f"peers, {result['peers']['size']}^2 image")
        save(fig, "peers")


# ---------------------------------------------------------------------------- main


def config(args):
    if args.quick:
        size = 32
        # few distinct executables (compiling dominates): one camera, the render tile,
        # one LOD setting, no Marschner-Lobb accuracy rows
        return dict(quick=True, size=size, volume=64, cameras=["far"], tiles=[8], lanes=[LANES],
                    structures=["restart", "grid"],
                    t31_size=32, time_steps=[0.0, 2.0], variances=[4.0],
                    lod_qualities=[2.0], lod_smooth=[True], peer_sizes=[64], ref_size=size,
                    acc_size=size, acc_mixing=64, acc_ml=None)
    sizes = [int(s) for s in args.peer_sizes.split(",")]
    return dict(quick=False, size=args.size, volume=args.volume, cameras=["far", "close"],
                structures=["restart", "neighbor", "grid"],
                tiles=[2, 4, 8, 16, 32], lanes=[LANES], t31_size=args.table31_size,
                time_steps=[0.0, 1.0, 2.0, 4.0], variances=[4.0],
                lod_qualities=list(LOD_QUALITIES), lod_smooth=[True, False],
                peer_sizes=sizes, ref_size=args.ref_size, acc_size=args.acc_size,
                acc_mixing=args.acc_volume, acc_ml=41)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512, help="image size (table32, packets, lod, "
                   "peers)")
    p.add_argument("--volume", type=int, default=256,
                   help="mixing layer grid for table32, packets and lod")
    p.add_argument("--table31-size", type=int, default=256)
    p.add_argument("--peer-sizes", default="64,128,256,512",
                   help="comma-separated volume sizes of the peers section (512 is skipped "
                        "when memory is short)")
    p.add_argument("--ref-size", type=int, default=64,
                   help="pixel subsample edge for the peers' depth error")
    p.add_argument("--acc-size", type=int, default=96, help="accuracy image size")
    p.add_argument("--acc-volume", type=int, default=64, help="accuracy mixing grid")
    args, only = common.parse_args(p, argv, SECTIONS, ROOT / "results")
    cfg = config(args)
    run = common.Run("volume", args, only, cfg)
    b = Bench(args.repeats, args.slow_s)
    funcs = dict(table31=table31, table32=table32, packets=packets,
                 lod=lambda b, cfg: lod(b, cfg, run.path.parent), peers=peers,
                 accuracy=accuracy)
    run.sections(SECTIONS, lambda sec: funcs[sec](b, cfg))
    lod_png = [run.result["lod"]["difference_png"]] if "lod" in run.result else []
    return run.finish(charts, more=lod_png)


if __name__ == "__main__":
    main()
