"""More than one process (issue 30): strong scaling of `ji.render` from 1 to 2 local
processes with one thread each, the collective's share of the frame time, and the bytes
each device holds when a volume is cut into bricks.

Every configuration runs as fresh processes of this script (`--worker`), pinned one core
each with taskset and single-threaded XLA (XLA_FLAGS="--xla_cpu_multi_thread_eigen=false
intra_op_parallelism_threads=1"), joined by `jaxiso.distributed.initialize` on
127.0.0.1 (gloo). The volume is written once to a .npy file that workers memory-map, so a
brick worker reads only its own planes.

Configurations (scene, how it is split):
  implicit  barth_sextic, rays split over the processes
  volume    marschner_lobb n^3, rays split (every process holds the whole octree)
  bricks    the same volume cut into one brick per process (rays not split)

Per configuration and process count: first call (compile + run), frame time (median of
`--repeats` eager `ji.render` calls, the image back in every process), the collective
alone (rays: the all-gather of the image's colours; bricks: the `nearest_hits` composite
of one packet per 8x8 tile, as the render runs it), the scene bytes this process's device
holds and its peak RSS. Writes <out>/distributed_cpu.json and distributed_cpu.png.

Brick grids (`--grids`, one process with as many CPU devices as bricks, through
XLA_FLAGS=--xla_force_host_platform_device_count): the volume cut by grids (2,1,1),
(2,2,1), (2,2,2) and the tet mesh of `tetra.data.cube_tets(--tets)` split into as many
parts: bytes each device holds (one brick / part, padded to the largest) against the
whole scene's, their sum over devices (the shared planes and padding), build and first
call seconds, the frame, and the largest depth difference (voxels) and hit-mask
agreement against the whole scene rendered alone. The devices of one process share the
2 cores, so these frames show the cost of the composite, not a speedup.

    python benchmarks/bench_distributed.py [--size 128] [--n 96] [--repeats 5]
        [--grids 2,1,1 2,2,1 2,2,2] [--grid-size 64] [--tets 12]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import resource
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
CONFIGS = ("implicit", "volume", "bricks")


# ------------------------------------------------------------------------------ worker


def _scene(config, volume_file, size):
    """(scene, camera, whole-volume octree bytes or None) of a configuration."""
    import numpy as np

    import jaxiso as ji
    from jaxiso.distributed import process_mesh
    from jaxiso.volume import OctreeVolume, VolumeIsosurface, brick_volume, data

    if config == "implicit":
        return ji.surfaces.scene("barth_sextic"), ji.surfaces.camera("barth_sextic", size)
    vox = np.load(volume_file, mmap_mode="r")
    spacing, origin = data.box_geometry(vox.shape, *data.DOMAINS["marschner_lobb"])
    iso = data.ISOVALUES["marschner_lobb"]
    cam = ji.Camera.look_at((2.6, 1.8, 1.4), (0, 0, 0), (0, 0, 1), 40.0, size)
    if config == "bricks":
        return brick_volume(vox, iso, process_mesh("bricks"), spacing=spacing,
                            origin=origin), cam
    vol = OctreeVolume.from_array(np.asarray(vox), spacing=spacing, origin=origin,
                                  progress=False)
    return VolumeIsosurface(vol, iso), cam


def _local_nbytes(scene) -> int:
    import jax

    return int(sum(sum(s.data.nbytes for s in leaf.addressable_shards)
                   for leaf in jax.tree_util.tree_leaves(scene) if isinstance(leaf, jax.Array)))


def _median_s(call, repeats, cpu=False):
    """Median wall seconds of `repeats` calls (and, with cpu, this process's median CPU
    seconds: what another job on the same cores does not inflate as much)."""
    import jax

    times, cpu_times = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    if cpu:
        return statistics.median(times), statistics.median(cpu_times)
    return statistics.median(times)


def _gather_time(mesh, n_rays, repeats):
    """Seconds of the all-gather that returns an image's colours [N, 3] float32, split
    over the mesh, to every device (what `render` does after tracing)."""
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    n = -(-n_rays // mesh.devices.size) * mesh.devices.size
    host = np.random.default_rng(0).random((n, 3), np.float32)
    split = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    x = jax.make_array_from_callback(host.shape, split, lambda i: host[i])
    gather = jax.jit(lambda a: a, out_shardings=NamedSharding(mesh, PartitionSpec()))
    jax.block_until_ready(gather(x))
    return _median_s(lambda: gather(x), repeats)


def _composite_time(mesh, n_rays, packet, repeats):
    """Seconds of the brick composite alone: one `nearest_hits` (pmin of t, pmin of the
    winner, one psum of hit/normal/surface/steps) per packet of `packet` rays, as a
    BrickedVolume's render runs it (one per packet; on lanes one for all rays)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import PartitionSpec

    import jaxiso as ji
    from jaxiso.volume import nearest_hits

    axis = mesh.axis_names[0]
    n_packets = -(-n_rays // packet)

    def per_device(seed):
        me = jax.lax.axis_index(axis).astype(jnp.float32)

        def one(i):
            t = jnp.sin(me + i + jnp.arange(packet, dtype=jnp.float32)) + seed[0] + 2.0
            hits = ji.Hits(t=t, hit=t > 1.5, normal=jnp.stack([t, t, t], -1),
                           surface=jnp.zeros(packet, jnp.int32),
                           steps=jnp.ones(packet, jnp.int32))
            return nearest_hits(hits, axis).t.sum()

        return jax.lax.map(one, jnp.arange(n_packets, dtype=jnp.float32)).sum()[None]

    run = jax.jit(jax.shard_map(per_device, mesh=mesh, in_specs=PartitionSpec(),
                                out_specs=PartitionSpec(axis), check_vma=False))
    seed = jnp.zeros(1)
    jax.block_until_ready(run(seed))
    return _median_s(lambda: run(seed), repeats)


def grid_worker(args) -> None:
    """One process with prod(grid) CPU devices: the volume as a brick grid and the tet
    mesh in as many parts against the whole scenes (bytes, times, agreement)."""
    import jax
    import numpy as np

    import jaxiso as ji
    from jaxiso.distributed import process_mesh
    from jaxiso.tetra import TetIsosurface, split_tets, tet_mesh
    from jaxiso.tetra import data as tdata
    from jaxiso.volume import OctreeVolume, VolumeIsosurface, brick_volume, data

    grid = tuple(int(g) for g in args.grid.split(","))
    assert len(jax.devices()) == int(np.prod(grid)), jax.devices()
    vox = np.load(args.volume_file, mmap_mode="r")
    spacing, origin = data.box_geometry(vox.shape, *data.DOMAINS["marschner_lobb"])
    iso = data.ISOVALUES["marschner_lobb"]
    points, tets = tdata.cube_tets(args.tets)
    mesh = tet_mesh(points, tets, tdata.sphere_field(points))
    cases = {
        "volume": (lambda: VolumeIsosurface(OctreeVolume.from_array(
                       np.asarray(vox), spacing=spacing, origin=origin, progress=False), iso),
                   lambda: brick_volume(vox, iso, process_mesh("bricks"), grid=grid,
                                        spacing=spacing, origin=origin),
                   ji.Camera.look_at((2.6, 1.8, 1.4), (0, 0, 0), (0, 0, 1), 40.0,
                                     args.grid_size), spacing[0]),
        "tets": (lambda: TetIsosurface(mesh, 0.0),
                 lambda: split_tets(mesh, 0.0, process_mesh("parts"), grid=grid),
                 ji.Camera.look_at((1.9, 1.5, 1.3), (0.5, 0.5, 0.5), (0, 0, 1), 40.0,
                                   args.grid_size), 1.0 / args.tets),
    }
    for kind, (whole_fn, split_fn, cam, cell) in cases.items():
        row = dict(section="grid", kind=kind, grid=list(grid), devices=len(jax.devices()))
        for name, make in (("whole", whole_fn), ("split", split_fn)):
            t0 = time.perf_counter()
            scene = make()
            row[f"{name}_build_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            jax.block_until_ready(ji.render(scene, cam))
            row[f"{name}_first_call_s"] = time.perf_counter() - t0
            row[f"{name}_frame_s"] = _median_s(lambda s=scene: ji.render(s, cam),
                                               args.repeats)
            hits = jax.device_get(ji.intersect(scene, cam.rays()))
            row[f"{name}_hits"] = hits
            if name == "whole":
                row["whole_nbytes"] = int(sum(
                    np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(scene)))
            else:
                row["per_device_nbytes"] = scene.part_nbytes()
                row["all_devices_nbytes"] = scene.part_nbytes() * scene.n_parts
        a, b = row.pop("whole_hits"), row.pop("split_hits")
        both = a.hit & b.hit
        row["hit_agreement"] = float((a.hit == b.hit).mean())
        row["max_depth_diff_cells"] = float(np.abs(a.t - b.t)[both].max() / cell
                                            if both.any() else 0.0)
        row["per_device_share"] = row["per_device_nbytes"] / row["whole_nbytes"]
        print("RESULT " + json.dumps(row), flush=True)


def worker(args) -> None:
    if args.grid:
        return grid_worker(args)
    from jaxiso import distributed

    if args.processes > 1:
        distributed.initialize(args.coordinator, args.processes, args.rank,
                               heartbeat_timeout_seconds=60)
    import jax

    import jaxiso as ji

    t0 = time.perf_counter()
    scene, cam = _scene(args.config, args.volume_file, args.size)
    build_s = time.perf_counter() - t0
    mesh = distributed.process_mesh() if args.processes > 1 else None
    devices = None if args.config == "bricks" else mesh
    t0 = time.perf_counter()
    img = ji.render(scene, cam, devices=devices)
    first_s = time.perf_counter() - t0
    frame_s, frame_cpu_s = _median_s(lambda: ji.render(scene, cam, devices=devices),
                                     args.repeats, cpu=True)
    n_rays = args.size * args.size
    collective_s = None
    if args.processes > 1 and args.config == "bricks":
        plan = ji.plan_for(scene, n_rays)  # lanes: one composite of all rays per trace
        packet = n_rays if plan.lanes else plan.packet
        collective_s = _composite_time(scene.mesh, n_rays, packet, args.repeats)
    elif args.processes > 1:
        collective_s = _gather_time(mesh, n_rays, args.repeats)
    result = dict(config=args.config, processes=args.processes, rank=jax.process_index(),
                  build_s=build_s, first_call_s=first_s, frame_s=frame_s,
                  frame_cpu_s=frame_cpu_s,
                  collective_s=collective_s, scene_nbytes_here=_local_nbytes(scene),
                  peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  plan=repr(ji.plan_for(scene, n_rays if devices is None
                                        else -(-n_rays // args.processes))),
                  covered=float((img.sum(-1) < 2.97).mean()))
    if args.config == "bricks":
        result["brick_nbytes"] = scene.brick_nbytes()
    print("RESULT " + json.dumps(result), flush=True)


# ------------------------------------------------------------------------------ driver


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(config, processes, args, volume_file) -> list[dict]:
    """One configuration on `processes` fresh local processes, core k for process k."""
    env = dict(os.environ, XLA_FLAGS=ONE_THREAD, JAX_PLATFORMS="cpu")
    port = _free_port()
    pin = shutil.which("taskset")
    procs = []
    for rank in range(processes):
        cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker",
               "--config", config, "--processes", str(processes), "--rank", str(rank),
               "--coordinator", f"127.0.0.1:{port}", "--size", str(args.size),
               "--repeats", str(args.repeats), "--volume-file", volume_file]
        if pin:
            cmd = [pin, "-c", str(rank % (os.cpu_count() or 1))] + cmd
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True))
    results = []
    for p in procs:
        out, err = p.communicate(timeout=args.timeout)
        lines = [ln for ln in out.splitlines() if ln.startswith("RESULT ")]
        if p.returncode != 0 or not lines:
            raise RuntimeError(f"{config} x{processes} failed:\n{err[-3000:]}")
        results.append(json.loads(lines[-1][7:]))
    return results


def _run_grid(grid, args, volume_file) -> list[dict]:
    """The brick-grid section for one grid: a fresh process with prod(grid) devices."""
    count = 1
    for g in grid.split(","):
        count *= int(g)
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=f"--xla_force_host_platform_device_count={count}")
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", "--grid",
           grid, "--grid-size", str(args.grid_size), "--tets", str(args.tets),
           "--repeats", str(args.repeats), "--volume-file", volume_file]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"grid {grid} failed:\n{out.stderr[-3000:]}")
    return [json.loads(ln[7:]) for ln in lines]


def _summary(rows) -> dict:
    """Per configuration: frame times at 1 and 2 processes, speedup, collective share,
    bytes per device and peak RSS (max over processes)."""
    out = {}
    for config in CONFIGS:
        one = [r for r in rows if r["config"] == config and r["processes"] == 1]
        two = [r for r in rows if r["config"] == config and r["processes"] == 2]
        if not one or not two:
            continue
        f1 = one[0]["frame_s"]
        f2 = max(r["frame_s"] for r in two)
        coll = max(r["collective_s"] for r in two)
        c1 = one[0]["frame_cpu_s"]
        c2 = max(r["frame_cpu_s"] for r in two)
        out[config] = dict(frame_1_s=f1, frame_2_s=f2, speedup=f1 / f2,
                           efficiency=f1 / f2 / 2, collective_s=coll,
                           frame_cpu_1_s=c1, frame_cpu_2_s=c2, cpu_speedup=c1 / c2,
                           collective_share=coll / f2,
                           first_call_1_s=one[0]["first_call_s"],
                           first_call_2_s=max(r["first_call_s"] for r in two),
                           scene_mib_per_device_1=one[0]["scene_nbytes_here"] / 2**20,
                           scene_mib_per_device_2=max(r["scene_nbytes_here"]
                                                      for r in two) / 2**20,
                           peak_rss_mib_1=one[0]["peak_rss_mib"],
                           peak_rss_mib_2=max(r["peak_rss_mib"] for r in two))
    return out


def _chart(summary, grid_rows, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    names = list(summary)
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(15, 3.6))
    x = range(len(names))
    a.bar([i - 0.2 for i in x], [summary[n]["frame_1_s"] for n in names], 0.4,
          label="1 process")
    a.bar([i + 0.2 for i in x], [summary[n]["frame_2_s"] for n in names], 0.4,
          label="2 processes")
    a.bar([i + 0.2 for i in x], [summary[n]["collective_s"] for n in names], 0.4,
          label="of which the collective", color="k", alpha=0.5)
    a.set_xticks(list(x), names)
    a.set_ylabel("frame s (median, 1 thread per process)")
    a.legend(fontsize=8)
    b.bar([i - 0.2 for i in x], [summary[n]["scene_mib_per_device_1"] for n in names], 0.4,
          label="1 process")
    b.bar([i + 0.2 for i in x], [summary[n]["scene_mib_per_device_2"] for n in names], 0.4,
          label="2 processes")
    b.set_xticks(list(x), names)
    b.set_ylabel("scene MiB per device")
    b.legend(fontsize=8)
    for kind, marker in (("volume", "o"), ("tets", "s")):
        rows = [r for r in grid_rows if r["kind"] == kind]
        c.plot([r["devices"] for r in rows], [r["per_device_share"] for r in rows],
               marker=marker, label=f"{kind}: one part / whole")
        c.plot([r["devices"] for r in rows],
               [r["all_devices_nbytes"] / r["whole_nbytes"] for r in rows], marker=marker,
               ls="--", label=f"{kind}: all parts / whole")
    if grid_rows:
        c.plot([1, 8], [1, 1 / 8], color="grey", lw=0.8, label="1 / devices")
        c.set_xscale("log", base=2)
        c.set_yscale("log", base=2)
        c.set_xlabel("devices (bricks " + ", ".join(
            "x".join(map(str, r["grid"])) for r in grid_rows if r["kind"] == "volume")
            + ")")
        c.set_ylabel("bytes, share of the whole scene")
        c.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return str(path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="image edge in pixels")
    parser.add_argument("--n", type=int, default=96, help="volume edge in voxels")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--configs", nargs="*", default=list(CONFIGS), choices=CONFIGS)
    parser.add_argument("--grids", nargs="*", default=["2,1,1", "2,2,1", "2,2,2"],
                        help="brick grids gx,gy,gz of the one-process section (none: skip)")
    parser.add_argument("--grid-size", type=int, default=64,
                        help="image edge of the brick-grid section")
    parser.add_argument("--tets", type=int, default=12, help="cube_tets(N) of that section")
    parser.add_argument("--out", default=str(HERE / "results"))
    parser.add_argument("--timeout", type=int, default=900, help="seconds per run")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--config", help=argparse.SUPPRESS)
    parser.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--rank", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--coordinator", help=argparse.SUPPRESS)
    parser.add_argument("--volume-file", help=argparse.SUPPRESS)
    parser.add_argument("--grid", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        worker(args)
        return 0

    import jax
    import numpy as np

    from jaxiso.volume import data

    print(f"bench_distributed: {args.size}^2 pixels, volume {args.n}^3, 1 vs 2 processes "
          f"one thread each (jax {jax.__version__}, {os.cpu_count()} cores)", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        volume_file = os.path.join(tmp, "volume.npy")
        np.save(volume_file, data.marschner_lobb(args.n))
        for config in args.configs:
            for processes in (1, 2):
                if config == "bricks" and processes == 1:
                    # one brick = the whole volume, as one device sees it
                    got = _run("volume", 1, args, volume_file)
                    got = [dict(r, config="bricks") for r in got]
                else:
                    got = _run(config, processes, args, volume_file)
                rows.extend(got)
                for r in got:
                    coll = r["collective_s"]
                    print(f"  {config:<9} x{processes} rank {r['rank']}: first "
                          f"{r['first_call_s']:6.2f} s, frame {r['frame_s'] * 1e3:8.1f} ms"
                          f" (cpu {r['frame_cpu_s'] * 1e3:7.1f} ms)"
                          + (f", collective {coll * 1e3:7.2f} ms" if coll else "")
                          + f", scene here {r['scene_nbytes_here'] / 2**20:6.2f} MiB, "
                          f"peak RSS {r['peak_rss_mib']:6.0f} MiB", flush=True)
        grid_rows = []
        for grid in args.grids:
            got = _run_grid(grid, args, volume_file)
            grid_rows.extend(got)
            for r in got:
                print(f"  grid {grid:<6} {r['kind']:<7} per device "
                      f"{r['per_device_nbytes'] / 2**20:6.2f} MiB of "
                      f"{r['whole_nbytes'] / 2**20:6.2f} ({r['per_device_share']:.3f}), "
                      f"all devices {r['all_devices_nbytes'] / 2**20:6.2f} MiB; build "
                      f"{r['whole_build_s']:.2f} / {r['split_build_s']:.2f} s, first "
                      f"{r['whole_first_call_s']:.1f} / {r['split_first_call_s']:.1f} s, "
                      f"frame {r['whole_frame_s'] * 1e3:.0f} / "
                      f"{r['split_frame_s'] * 1e3:.0f} ms; hits agree "
                      f"{r['hit_agreement']:.5f}, depth within "
                      f"{r['max_depth_diff_cells']:.1e} cells", flush=True)
    summary = _summary(rows)
    print(f"\n{'config':<10}{'1 proc ms':>10}{'2 proc ms':>10}{'speedup':>9}"
          f"{'cpu x':>7}{'coll %':>8}{'MiB/dev 1':>11}{'MiB/dev 2':>11}")
    for name, s in summary.items():
        print(f"{name:<10}{s['frame_1_s'] * 1e3:>10.1f}{s['frame_2_s'] * 1e3:>10.1f}"
              f"{s['speedup']:>9.2f}{s['cpu_speedup']:>7.2f}"
              f"{100 * s['collective_share']:>8.1f}"
              f"{s['scene_mib_per_device_1']:>11.2f}{s['scene_mib_per_device_2']:>11.2f}")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    chart = _chart(summary, grid_rows, out / "distributed_cpu.png")
    result = dict(benchmark="distributed", backend="cpu", jax=jax.__version__,
                  machine=platform.machine(), cpu_count=os.cpu_count(),
                  size=args.size, volume_n=args.n, repeats=args.repeats,
                  threads_per_process=1, xla_flags=ONE_THREAD,
                  pinned=shutil.which("taskset") is not None,
                  timing="frame: median of repeats eager ji.render calls after the first "
                         "(image back in every process), wall and this process's CPU "
                         "seconds; collective: the same median of a jit running only the "
                         "collective; 2-process figures: the slower process's",
                  load_average=os.getloadavg(),
                  rows=rows, summary=summary, chart=chart,
                  grids=dict(image_size=args.grid_size, tets=args.tets, rows=grid_rows,
                             timing="one process, as many CPU devices as bricks on 2 "
                                    "shared cores: whole / split; bytes per device are "
                                    "one brick or part padded to the largest"))
    path = out / "distributed_cpu.json"
    path.write_text(json.dumps(result, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
