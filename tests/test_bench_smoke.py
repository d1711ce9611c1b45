"""Smoke test of benchmarks/bench_implicit.py: the --quick run completes in-process and
writes the JSON the full benchmark writes (about 45-60 s on a 2-core CPU, mostly
compilation); and the scaffolding every benchmark shares (benchmarks/_common.py)."""

import argparse
import importlib.util
import json
import pathlib

import pytest

BENCHMARKS = pathlib.Path(__file__).resolve().parent.parent / "benchmarks"
BENCH = BENCHMARKS / "bench_implicit.py"


def load_module(path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_bench():
    return load_module(BENCH)


def test_common_options_and_their_errors(capsys):
    common = load_module(BENCHMARKS / "_common.py")

    def parse(*argv, repeat_flags=("--repeats",)):
        p = argparse.ArgumentParser()
        return common.parse_args(p, list(argv), ("a", "b", "c"), "out_dir", repeat_flags)

    args, only = parse("--only", " c,a ", "--repeats", "2")
    assert only == ["c", "a"]  # as asked; Run.sections still runs them in section order
    assert (args.repeats, args.slow_s, args.quick, args.out) == (2, 2.0, False, "out_dir")
    args, only = parse("--quick", repeat_flags=("--repeats", "--build-repeats"))
    assert only == ["a", "b", "c"] and args.build_repeats == 3 and args.quick
    for argv, message in ((["--only", "a,x"], "unknown section(s) ['x']"),
                          (["--repeats", "0"], "--repeats must be >= 1")):
        with pytest.raises(SystemExit):
            parse(*argv)
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse("--build-repeats", "0", repeat_flags=("--repeats", "--build-repeats"))
    assert "--repeats and --build-repeats must be >= 1" in capsys.readouterr().err


def test_time_calls_counts_the_calls():
    common = load_module(BENCHMARKS / "_common.py")
    calls = []

    def call():
        calls.append(1)
        return len(calls)

    out, timing = common.time_calls(call, 3, slow_s=60.0)
    assert (out, timing["repeats_used"], len(calls)) == (4, 3, 4)  # warm-up + 3
    assert timing["run_s"] >= 0 and timing["cpu_s"] >= 0 and timing["warmup_s"] >= 0
    calls.clear()
    _, timing = common.time_calls(call, 3, slow_s=-1.0)  # warm-up "too slow": alone
    assert (timing["repeats_used"], len(calls), timing["run_s"]) == (0, 1, timing["warmup_s"])
    calls.clear()
    _, timing = common.time_calls(call, 3, slow_s=60.0, timed=False)
    assert (timing["repeats_used"], len(calls)) == (0, 1)


def test_user_call_times_the_first_call_apart():
    common = load_module(BENCHMARKS / "_common.py")
    import jaxiso as ji

    calls = []

    def call():
        calls.append(1)
        return len(calls)

    out, row = common.user_call(call, ji.Plan(tile=4, lanes=256), "f()", 3, slow_s=60.0)
    assert (out, len(calls), row["repeats_used"]) == (5, 5, 3)  # first + warm-up + 3
    assert row["call"] == "f()" and row["plan"] == "Plan(tile=4, lanes=256)"
    assert (row["plan_tile"], row["plan_lanes"]) == (4, 256)
    assert row["first_call_s"] >= 0 and row["run_s"] >= 0


def test_run_keeps_the_other_sections_when_one_fails(tmp_path, capsys):
    common = load_module(BENCHMARKS / "_common.py")
    args = argparse.Namespace(out=str(tmp_path / "res"), repeats=1, slow_s=1.0, quick=True)
    run = common.Run("demo", args, ["b", "a", "c"], {"k": 1}, extra_key="x",
                     stamp=lambda r: r.update(stamped=True))

    def section(name):
        if name == "b":
            raise ValueError("broken")
        return {"value": name}

    run.sections(("a", "b", "c", "d"), section)
    result = run.finish(lambda plt, save, result: None, more=["other.png"])
    written = json.loads(run.path.read_text())
    assert run.path.name.startswith("demo_") and run.path.parent == tmp_path / "res"
    assert written["a"]["value"] == "a" and written["c"]["value"] == "c"
    assert "b" not in written and "d" not in written
    assert written["errors"] == {"b": "ValueError: broken"}
    assert written["sections"] == ["b", "a", "c"] and written["config"] == {"k": 1}
    assert written["extra_key"] == "x" and written["stamped"] is True
    # JSON key order: metadata, extra keys, timing, then sections and stamps as they came
    assert list(written)[:4] == ["benchmark", "jax_version", "jaxiso_version",
                                 "numpy_version"]
    assert list(written)[-7:] == ["extra_key", "timing", "a", "total_s", "stamped", "c",
                                  "charts"]
    assert result["charts"] == [] and written["charts"] == []
    out = capsys.readouterr().out
    assert "b FAILED: ValueError: broken" in out and "wrote other.png" in out
    assert "ERRORS in ['b']" in out


# ~45-60 s on 2 cores (compilation): run with the benchmarks, not in the CI suite
@pytest.mark.heavy
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
    assert result["sections"] == ["table61", "table62", "packets", "sweep", "scalar"]

    row_keys = ("surface", "method", "arithmetic", "eps", "size", "plan", "tile", "lanes",
                "packet", "compile_s",
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
            assert r["plan"] == f"Plan(tile={r['tile']}, lanes={r['lanes']})"

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
    # the calls a user writes first, timed beside the tuned plans, with the plan they ran
    defaults = result["packets"]["defaults"]
    assert [d["call"] for d in defaults] == ["ji.intersect(scene, camera.rays())",
                                             "ji.render(scene, camera)"]
    for d in defaults:
        assert d["plan"] == result["packets"]["user_plan"]
        assert d["first_call_s"] > 0 and d["run_s"] > 0 and d["repeats_used"] >= 1
        assert abs(d["mrays_per_s"] - d["size"] ** 2 / d["run_s"] / 1e6) < 1e-9
    assert 0.0 <= defaults[0]["hit_fraction"] <= 1.0
    assert result["target"]["best_plan"].startswith("Plan(tile=")
    for r in result["sweep"]["rows"]:
        assert 0.0 <= r["pixel_error"] <= 1.0
        assert r["axis"] in ("eps", "samples")
    target = result["target"]
    assert target["met"] in (True, False)
    assert target["best"]["surface"] == "barth_sextic"
    assert "steps_per_ray" in target["limits"]
    assert returned["target"]["met"] == target["met"]
