"""Smoke test of benchmarks/bench_volume.py: the --quick run completes in-process and
writes the JSON the full benchmark writes (mostly compilation: five executables)."""

import importlib.util
import json
import pathlib

import numpy as np
import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_volume.py"
SECTIONS = ["table31", "table32", "packets", "lod", "peers", "accuracy"]


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_volume", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def check_timing_row(r):
    assert r["run_s"] > 0 and r["compile_s"] > 0
    assert abs(r["mrays_per_s"] - r["pixels"] / r["run_s"] / 1e6) < 1e-9
    assert r["steps_max"] >= r["steps_mean"] >= 0
    assert 0.0 <= r["hit_fraction"] <= 1.0
    assert r["plan"] == f"Plan(tile={r['tile']}, lanes={r['lanes']})"
    if r["lanes"] is None:  # packets: a packet waits for its slowest ray
        assert 0.0 < r["lane_utilisation"] <= 1.0
    else:  # persistent lanes refill: not measured
        assert r["lane_utilisation"] is None


# ~45-90 s on 2 cores (five compiles): run with the benchmarks, not in the CI suite
@pytest.mark.heavy
def test_quick_run_writes_json(tmp_path):
    bench = load_bench()
    returned = bench.main(["--quick", "--out", str(tmp_path)])
    (out,) = tmp_path.glob("volume_*.json")
    result = json.loads(out.read_text())
    assert result["quick"] is True
    assert result["errors"] == {}
    for key in ("jax_version", "backend", "device_kind", "cpu_count", "repeats", "config",
                "charts", "total_s", *SECTIONS):
        assert key in result, key
    assert result["sections"] == SECTIONS
    assert returned["total_s"] == result["total_s"]

    t31 = result["table31"]["rows"]
    for r in t31:
        assert r["octree_nbytes"] > 0 and r["raw_nbytes"] > 0 and r["build_s"] >= 0
        assert abs(r["percent"] - 100.0 * r["octree_nbytes"] / r["raw_nbytes"]) < 1e-9
        if r["variance"] == 0.0:  # lossless rows reproduce the (clamped) input exactly
            assert r["max_abs_error"] == 0.0, r
    names = {r["data"] for r in t31}
    assert {"mixing", "mixing u8", "mixing u8 sequence", "ct_phantom", "marschner_lobb",
            "sphere_distance"} <= names
    assert any(r["iso_range"] for r in t31) and any(r["variance"] > 0 for r in t31)
    # a clamp to a narrower range never needs more bytes than the full range
    full = {(r["data"], r["time"] if "time" in r else None): r["octree_nbytes"] for r in t31
            if r["iso_range"] is None and r["variance"] == 0.0}
    for r in t31:
        key = (r["data"], r.get("time"))
        if r["iso_range"] and key in full:
            assert r["octree_nbytes"] <= full[key], r

    for sec in ("table32", "packets", "lod", "accuracy"):
        rows = result[sec]["rows"]
        assert rows, sec
        for r in rows:
            check_timing_row(r)
    t32 = result["table32"]["rows"]
    assert {r["structure"] for r in t32} == {"octree", "grid"}
    # the grid and the octree intersect the same interpolant: identical hit masks
    assert all(r["mask_diff_vs_restart"] < 0.01 for r in t32)
    assert result["packets"]["fastest"] in {r["label"] for r in result["packets"]["rows"]}
    assert any(r["lanes"] for r in result["packets"]["rows"])
    # the calls a user writes first, timed beside the tuned plans, with the plan they ran
    defaults = result["packets"]["defaults"]
    assert [d["call"] for d in defaults] == ["ji.intersect(scene, camera.rays())",
                                             "ji.render(scene, camera)"]
    for d in defaults:
        assert d["plan"] == result["packets"]["user_plan"]
        assert d["first_call_s"] > 0 and d["run_s"] > 0
        assert abs(d["mrays_per_s"] - d["pixels"] / d["run_s"] / 1e6) < 1e-9
    assert 0.0 <= defaults[0]["hit_fraction"] <= 1.0

    lod = result["lod"]["rows"]
    assert lod[0]["label"] == "full" and lod[0]["mask_diff"] == 0.0
    assert all(0.0 <= r["mask_diff"] <= 1.0 and r["colour_diff"] >= 0.0 for r in lod)
    assert pathlib.Path(result["lod"]["difference_png"]).exists()

    peers = result["peers"]
    assert peers["sizes"] == [64]
    jaxiso_rows = [r for r in peers["rows"] if r["pipeline"] == "jaxiso"]
    assert len(jaxiso_rows) == 1
    r = jaxiso_rows[0]
    assert r["image_s"] > 0 and r["build_s"] > 0 and r["compile_s"] > 0
    assert r["plan"].startswith("Plan(") and r["user_call"]["plan"] == r["plan"]
    assert r["user_image_s"] > 0
    # exact trilinear roots: far below a voxel against the float64 reference
    assert r["mask_agreement"] >= 0.99 and r["depth_err_p99"] < 1e-2
    pipelines = {p["pipeline"] for p in peers["rows"]}
    assert len(pipelines) + len(peers["skipped"]) == 3  # every peer ran or says why not
    for p in peers["rows"]:
        assert p["image_s"] > 0 and 0.0 <= p["mask_agreement"] <= 1.0

    acc = result["accuracy"]["rows"]
    assert {r["method"] for r in acc} == {"neubauer", "analytic"}
    for r in acc:
        assert r["mask_agreement"] >= 0.99
        assert r["depth_err_median"] is not None and np.isfinite(r["depth_err_max"])


def test_helpers_against_hand_counts():
    bench = load_bench()
    # lane utilisation: packets of 2 rays with steps (1, 3) and (2, 2): 8 / (3*2 + 2*2)
    w = bench.work(np.array([1, 3, 2, 2]), 2, run_s=1.0)
    assert w["lane_utilisation"] == 8 / 10 and w["steps_max"] == 3 and w["steps_total"] == 8
    # one interior miss surrounded by hits counts; a miss on the silhouette does not
    full = np.ones((5, 5), bool)
    hit = full.copy()
    hit[2, 2] = False
    hit[0, 1] = False
    assert bench.pinholes(hit, full) == 1
    assert bench.pinholes(hit, np.zeros_like(full)) == 0
    assert list(bench.subsample(8, 4)) == [1, 3, 5, 7]
    assert list(bench.subsample(4, 8)) == [0, 1, 2, 3]


def test_peer_meshes_agree_on_a_non_cubic_volume():
    # flying edges gets the array with its axes reversed (no copy): its mesh must match
    # marching cubes', and both must lie near the exact trilinear surface
    for name in ("skimage", "open3d", "vtk"):
        pytest.importorskip(name)
    import reference_volume64 as ref

    bench = load_bench()
    a = bench.vdata.mixing(20, time=1.0)[:, :16, :]
    sp, org = (0.05, 0.05, 0.05), (0.0, 0.0, 0.0)
    v = bench.view("mixing", "far")
    o, d = ref.camera_rays(v["eye"], v["target"], v["up"], v["fov"], 24, 24)
    t_ref, hit_ref, _ = ref.first_hits(a, o, d, 96.0, spacing=sp, origin=org)
    o, d = o.astype(np.float32), d.astype(np.float32)
    _, t_mc = bench.peer_marching_cubes(a, 96.0, sp, org, o, d)
    _, t_fe = bench.peer_flying_edges(a, 96.0, sp, org, o, d)
    hit_mc, hit_fe = np.isfinite(t_mc), np.isfinite(t_fe)
    assert hit_ref.mean() > 0.2
    assert np.mean(hit_mc == hit_ref) > 0.97 and np.mean(hit_fe == hit_mc) > 0.99
    both = hit_mc & hit_ref
    assert np.median(np.abs(t_mc[both] - t_ref[both])) < 0.5 * sp[0]
    both = hit_mc & hit_fe
    assert np.median(np.abs(t_mc[both] - t_fe[both])) < 1e-3 * sp[0]
