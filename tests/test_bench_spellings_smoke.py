"""Smoke test of benchmarks/bench_spellings.py: the budget probe's rays, the summary of
what the issue asks, and (heavy) a tiny run that writes the JSON the full benchmark
writes, a crashing spelling recorded beside the others."""

import importlib.util
import json
import pathlib

import numpy as np
import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_spellings.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_spellings", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_probe_rays_turn_every_ray_but_the_pilot_away():
    bench = load_bench()
    rays = bench.camera(8).rays()
    idle, pilot = bench.pilot_rays(rays, np.array([1, 5]))
    d, di, dp = (np.asarray(r.direction) for r in (rays, idle, pilot))
    assert np.array_equal(di, -d) and np.array_equal(np.asarray(idle.origin), rays.origin)
    real = np.zeros((8, 8), bool)
    real[np.ix_([1, 5], [1, 5])] = True
    assert np.array_equal(dp[real], d[real]) and np.array_equal(dp[~real], -d[~real])


def test_summary_names_what_misses_the_issue_bars():
    bench = load_bench()

    def row(spelling, agree=1.0, **kw):
        return dict(activation="elu", spelling=spelling, mask_agreement=agree,
                    ratio_to_dense=0.5, **kw)

    rows = [row("jax.nn"), row("jnp", paired_ratio_to_jax_nn=1.6, ratio_to_jax_nn=1.2),
            row("equinox", 0.99, ratio_to_jax_nn=1.4, paired_ratio_to_dense=1.5),
            dict(activation="elu", spelling="equinox.params", error="TypeError: x")]
    got = bench.summary(rows)
    assert got == dict(crashed=["elu/equinox.params"], disagree=["elu/equinox"],
                       slower_than_1_5x=["elu/jnp"], slower_than_dense=["elu/equinox"])


# ~60-90 s on 2 cores (preparation and compiles of two spellings): with the benchmarks
@pytest.mark.heavy
def test_tiny_run_writes_json(tmp_path):
    bench = load_bench()
    result = bench.main(["--size", "12", "--pilot", "4", "--activations", "relu",
                         "--shapes", "relu=2x16", "--spellings", "jax.nn,equinox.params",
                         "--repeats", "1", "--out", str(tmp_path),
                         "--cache", str(tmp_path / "cache")])
    (out,) = tmp_path.glob("spellings_*.json")
    saved = json.loads(out.read_text())
    assert saved["total_s"] == result["total_s"] and saved["errors"] == {}
    rows = saved["spellings"]["rows"]
    assert [r["spelling"] for r in rows] == ["jax.nn", "equinox.params"]
    for row in rows:  # the module as params crashed before (session 31)
        assert "error" not in row, row
        assert row["measured"] and row["mask_agreement"] >= 0.99 and row["compared"] == 144
        assert row["arithmetic"] in ("interval", "affine") and row["dense"]["run_s"] > 0
    assert saved["spellings"]["summary"]["crashed"] == []
