"""Smoke test of benchmarks/bench_tetra.py: the --quick run completes in-process and writes
the JSON the full benchmark writes, with figures that agree with independent facts (tet
counts of cube_tets / replicate, binary-tree node counts, float32 accuracy). About 40 s on
an idle 2-core CPU, mostly compilation (about 75 s while the CPU is shared)."""

import importlib.util
import json
import pathlib

import pytest

# ~50-90 s on 2 cores (about 11 compiles): run with the benchmarks, not in the CI suite
pytestmark = pytest.mark.heavy

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_tetra.py"
SECTIONS = ["table51", "table53", "table54", "modalities", "timevarying", "peers", "accuracy"]


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_tetra", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("bench_tetra")
    returned = load_bench().main(["--quick", "--out", str(out_dir)])
    out = out_dir / "tetra_cpu.json"
    if not out.exists():  # another backend names the file after itself
        (out,) = out_dir.glob("tetra_*.json")
    return json.loads(out.read_text()), returned


def test_header_and_sections(run):
    result, returned = run
    assert result["quick"] is True
    assert result["errors"] == {}
    for key in ("jax_version", "backend", "device_kind", "cpu_count", "repeats", "config",
                "total_s", "charts", "load_average_start", *SECTIONS):
        assert key in result, key
    assert result["sections"] == SECTIONS
    assert len(result["source"]["tetra_sources_sha256"]) == 64
    assert returned["total_s"] == pytest.approx(result["total_s"])
    for chart in result["charts"]:
        assert pathlib.Path(chart).exists()


def test_table51_counts_and_rates(run):
    result, _ = run
    sec = result["table51"]
    assert {r["method"] for r in sec["rows"]} == {"bih", "sah"}
    for r in sec["rows"]:
        assert r["tets"] == 6 * r["n"] ** 3  # cube_tets: 6 Kuhn tets per cube
        assert r["bvh_tets"] == r["tets"]  # no degenerate tets in a cube grid
        assert r["nodes"] == 2 * r["leaves"] - 1  # a full binary tree
        assert r["mean_leaf_size"] * r["leaves"] == pytest.approx(r["tets"])
        assert 1 <= r["max_leaf_size"] <= 8
        assert r["pixels"] == r["size"] ** 2
        assert r["run_s"] > 0 and r["cpu_s"] > 0 and r["compile_s"] > 0 and r["build_ms"] > 0
        assert r["mrays_per_s"] == pytest.approx(r["pixels"] / r["run_s"] / 1e6)
        # the plan it ran, and the same image as a user asks for it (no plan, no jit)
        assert r["plan"] == "Plan(tile=16, lanes=None)"  # TetIsosurface's below 2^16 rays
        user = r["user_call"]
        assert user["call"] == "ji.render(scene, camera)" and user["plan"] == r["plan"]
        assert user["first_call_s"] > 0 and user["run_s"] == r["user_run_s"] > 0
    target = sec["build_target"]
    assert target["checked"] is False and target["met"] is None  # quick meshes are tiny


def test_table53_replication(run):
    result, _ = run
    sec = result["table53"]
    base_tets = 6 * sec["base_n"] ** 3
    assert [r["k"] for r in sec["rows"]] == [1, 2]
    for r in sec["rows"]:
        assert r["tets"] == r["k"] ** 3 * base_tets
        assert r["nodes"] == 2 * r["leaves"] - 1
    assert sec["rows"][0]["render_ratio"] == 1.0 and sec["rows"][0]["render_ratio_cpu"] == 1.0
    assert sec["rows"][1]["render_ratio"] == pytest.approx(
        sec["rows"][1]["run_s"] / sec["rows"][0]["run_s"])
    assert sec["target"]["ratio"] is None and sec["target"]["met"] is None  # no k = 4


def test_table54_work_counters(run):
    result, _ = run
    rows = result["table54"]["rows"]
    assert {(r["method"], r["view"]) for r in rows} == {
        (m, v) for m in ("bih", "sah") for v in ("default", "opposite")}
    for r in rows:
        assert r["plan"] == f"Plan(tile={r['tile']}, lanes={r['lanes']})"
        assert 0.0 < r["hit_fraction"] < 1.0
        # every leaf intersected is a node visited, and a hitting ray enters some leaf
        assert r["nodes_mean"] >= r["leaves_mean"] > 0
        assert r["nodes_max"] >= r["nodes_mean"]
        assert r["nodes_mean_hit"] >= 1
        assert r["tet_tests_bound_mean"] == pytest.approx(r["leaves_mean"] * r["leaf_size"])
        assert r["tet_tests_est_mean"] <= r["tet_tests_bound_mean"]


def test_table54_hits_match_accuracy_rays(run):
    """table54 (jaxiso camera rays) and accuracy (reference rays in float32) trace the same
    view of the same wave mesh in the quick config: the hit fractions agree to a ray or two."""
    result, _ = run
    cfg = result["config"]
    assert cfg["t51_n"] == [cfg["acc_n"]] and cfg["work_size"] == cfg["acc_size"]
    acc = {r["method"]: r for r in result["accuracy"]["rows"] if r["field"] == "wave"}
    for r in (r for r in result["table54"]["rows"] if r["view"] == "default"):
        assert abs(r["hit_fraction"] - acc[r["method"]]["ref_hit_fraction"]) <= 2 / r["size"] ** 2


def test_modalities_and_timevarying(run):
    result, _ = run
    rows = result["modalities"]["rows"]
    assert [r["label"] for r in rows] == ["plain", "clip box"]
    assert rows[0]["relative"] == 1.0
    assert rows[1]["relative"] == pytest.approx(rows[1]["run_s"] / rows[0]["run_s"])
    hows = {r["how"] for r in result["timevarying"]["rows"]}
    assert {"with_time_step (jit refit)", "rebuild (numpy build + scene)",
            "with_points (jit refit)", "refit (numpy)", "rebuild (numpy build)"} <= hows
    for r in result["timevarying"]["rows"]:
        assert r["seconds"] > 0
        assert r["render_s"] is None or r["render_s"] > 0


def test_peers(run):
    result, _ = run
    sec = result["peers"]
    rows = {r["pipeline"]: r for r in sec["rows"]}
    assert "jaxiso" in rows
    have_peers = sec["versions"]["vtk"] is not None and sec["versions"]["open3d"] is not None
    assert ("VTK contour + open3d" in rows) == have_peers
    assert bool(sec["skipped"]) != have_peers
    for r in rows.values():
        assert r["image_s"] == pytest.approx(sum(r["stages"].values()))
        # both intersect the same linear tets: the float64 reference up to float32 rounding
        assert r["mask_agreement"] >= 0.99
        assert r["depth_rel_max"] < 1e-4
    if have_peers:
        assert rows["VTK contour + open3d"]["triangles"] > 0


def test_accuracy(run):
    result, _ = run
    rows = result["accuracy"]["rows"]
    assert {(r["field"], r["method"]) for r in rows} == {
        (f, m) for f in ("sphere", "wave", "random") for m in ("bih", "sah")}
    for r in rows:
        assert r["ref_hit_fraction"] > 0
        assert r["mask_agreement"] >= 0.99
        assert r["depth_rel_max"] < 1e-4
