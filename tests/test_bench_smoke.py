"""Smoke test of benchmarks/bench_implicit.py: the --quick run completes in-process and
writes the JSON the full benchmark writes (about 45-60 s on a 2-core CPU, mostly
compilation)."""

import importlib.util
import json
import pathlib

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_implicit.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_implicit", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_quick_run_writes_json(tmp_path):
    bench = load_bench()
    returned = bench.main(["--quick", "--out", str(tmp_path)])
    out = tmp_path / "implicit_cpu.json"
    if not out.exists():  # another backend names the file after itself
        (out,) = tmp_path.glob("implicit_*.json")
    result = json.loads(out.read_text())
    assert result["quick"] is True
    for key in ("jax_version", "backend", "device_kind", "cpu_count", "repeats", "config",
                "table61", "table62", "packets", "sweep", "target", "charts", "total_s"):
        assert key in result, key
    assert result["sections"] == ["table61", "table62", "packets", "sweep"]

    row_keys = ("surface", "method", "arithmetic", "eps", "size", "packet", "compile_s",
                "run_s", "mrays_per_s", "steps_mean", "steps_max", "hit_fraction",
                "exhausted", "lane_utilisation", "ns_per_step")
    for sec in ("table61", "table62", "packets", "sweep"):
        rows = result[sec]["rows"]
        assert rows, sec
        for r in rows:
            for k in row_keys:
                assert k in r, (sec, k)
            assert r["run_s"] > 0 and r["compile_s"] > 0
            assert 0.0 <= r["hit_fraction"] <= 1.0
            assert r["steps_max"] >= r["steps_mean"] >= 0
            assert abs(r["mrays_per_s"] - r["size"] ** 2 / r["run_s"] / 1e6) < 1e-9

    t61 = result["table61"]
    assert {s["surface"] for s in t61["summary"]} == {"barth_sextic", "mitchell"}
    for s in t61["summary"]:
        assert s["faster"] in ("interval", "affine")
        for arith in ("interval", "affine"):
            conv = s[f"converged_eps_{arith}"]
            agree = s[f"agreement_{arith}"]  # scanned coarse to fine, up to the first >= 99.5%
            assert 1 <= len(agree) <= len(t61["conv_eps_grid"])
            assert all(0.0 <= a <= 1.0 for a in agree.values())
            assert conv is None or conv in t61["conv_eps_grid"]
            assert (conv is not None) == (max(agree.values()) >= t61["agree_threshold"])
    methods = {r["method"] for r in result["table62"]["rows"]}
    assert methods == {"t-bisection", "k-bisection", "mitchell"}
    assert result["packets"]["fastest"] in {r["label"] for r in result["packets"]["rows"]}
    for r in result["sweep"]["rows"]:
        assert 0.0 <= r["pixel_error"] <= 1.0
        assert r["axis"] in ("eps", "samples")
    target = result["target"]
    assert target["met"] in (True, False)
    assert target["best"]["surface"] == "barth_sextic"
    assert "steps_per_ray" in target["limits"]
    assert returned["target"]["met"] == target["met"]
