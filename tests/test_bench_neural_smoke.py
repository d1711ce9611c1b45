"""Smoke test of benchmarks/bench_neural.py: a tiny run (16^2 pixels, the fox, a coarse
float64 reference, three piece lengths) completes in-process and writes the JSON the
full benchmark writes (~30-40 s on a 2-core CPU, mostly compilation); the float64
network evaluator against the file's weights; Spelunking's harness when a checkout is
present (JAXISO_SPELUNKING, default /work/peers/spelunking)."""

import importlib.util
import json
import os
import pathlib
import sys

import numpy as np
import pytest
import reference_neural64 as ref64

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_neural.py"
DATA = pathlib.Path(os.environ.get("JAXISO_NEURAL_DATA", "/work/shared/data/neural"))
FOX = DATA / "fox.npz"
SPELUNKING = pathlib.Path(os.environ.get("JAXISO_SPELUNKING", "/work/peers/spelunking"))

needs_data = pytest.mark.skipif(not FOX.exists(),
                                reason=f"{FOX} is absent (shared data, not in the repo)")


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_neural", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@needs_data
def test_float64_network_matches_a_hand_evaluation():
    with np.load(FOX) as data:
        w = {k: data[k].astype(np.float64) for k in data.files}
    p = np.array([[0.1, -0.2, 0.3], [0.0, 0.5, -0.4]])
    h = p
    dense = sorted(k for k in w if k.endswith("dense.A"))
    for i, key in enumerate(dense):
        h = h @ w[key] + w[key[:-1] + "b"]
        if i < len(dense) - 1:
            h = np.maximum(h, 0.0)  # the fox is a relu network
    np.testing.assert_allclose(ref64.evaluate(ref64.load_npz64(FOX), p), h[:, 0],
                               rtol=1e-12, atol=1e-12)


# ~75 s on 2 cores (compiles of every bench case): run with the benchmarks, not in CI
@pytest.mark.heavy
@needs_data
def test_tiny_run_writes_json(tmp_path):
    bench = load_bench()
    argv = ["--sizes", "16", "--networks", "fox", "--ref-samples", "200", "--repeats", "1",
            "--tightness", "--tight-points", "8", "--tight-lengths", "3",
            "--out", str(tmp_path), "--cache", str(tmp_path / "cache")]
    returned = bench.main(argv)
    (out,) = tmp_path.glob("neural_*.json")
    result = json.loads(out.read_text())
    assert result["errors"] == {} and returned["total_s"] == result["total_s"]
    assert result["sections"] == ["rays", "tightness"]
    assert "spelunking_skipped" in result["config"]  # no --spelunking: skipped, said why
    assert list(tmp_path.glob("cache/fox_16_*.npz"))  # the reference was cached

    rows = result["rays"]["rows"]
    labels = [r["label"] for r in rows]
    assert labels == ["jaxiso default", "jaxiso interval", "jaxiso affine",
                      "jaxiso verify=sign", "jaxiso culling=none", "sphere L=net",
                      "sphere L=1", "hand sampling 128"]  # the fox is an SDF: L=1 too
    for r in rows:
        assert "error" not in r, r
        assert r["measured"] and r["run_s"] > 0 and r["first_call_s"] > 0
        assert abs(r["rays_per_s"] - 16 * 16 / r["run_s"]) < 1e-6 * r["rays_per_s"]
        assert 0.0 <= r["mask_agreement"] <= 1.0 and r["compared"] == 256
        assert abs(r["mask_agreement"] + r["false_hits"] + r["missed_hits"] - 1) < 1e-9
        assert r["steps_max"] >= r["steps_mean"] >= 0
    default = rows[0]
    assert default["call"] == "ji.intersect(S, rays)"
    assert default["scene"]["arithmetic"] and default["plan"].startswith("Plan(")
    assert rows[1]["scene"]["arithmetic"] == "interval"
    assert rows[2]["scene"]["arithmetic"] == "affine"
    assert rows[3]["scene"]["verify"] == "sign"
    # the default builds a sign grid at construction (timed), culling="none" none
    assert default["scene"]["sign_grid"]["resolution"][0] >= 4 and default["construct_s"] > 0
    assert rows[4]["scene"]["culling"] == "none" and rows[4]["scene"]["sign_grid"] is None
    assert rows[6]["scene"]["lipschitz"] == 1.0 and rows[5]["scene"]["lipschitz"] > 1.0
    # the accurate casters find the fox's few hits where the reference does
    hand = rows[7]
    assert hand["mask_agreement"] > 0.97 and hand["steps_mean"] == 136
    assert hand["depth_err_median"] < 1e-2

    tg = result["tightness"]
    assert set(tg["arithmetics"]) >= {"interval", "affine"} and tg["errors"] == {}
    assert len(tg["rows"]) == 3 * len(tg["arithmetics"])
    for r in tg["rows"]:
        assert r["median_ratio"] >= 1.0 - 1e-4 and r["narrower"] == 0  # sound
    # charts need matplotlib (the bench extra); the test extra alone writes none
    has_mpl = importlib.util.find_spec("matplotlib") is not None
    assert len(result["charts"]) == (2 if has_mpl else 0)


def test_pilot_stands_in_for_a_row_over_budget():
    import jax.numpy as jnp

    import jaxiso as ji

    bench = load_bench()
    calls = []

    def make(rays):
        h, w = rays.origin.shape[:2]

        def call():
            calls.append(h)
            return jnp.zeros((h, w))
        return call, lambda out: (np.zeros((h, w), bool), np.full((h, w), np.inf),
                                  np.ones((h, w), int))

    def rays(n):
        return ji.Rays(jnp.zeros((n, n, 3)), jnp.ones((n, n, 3)))

    # budget 0: no pilot, first call + warm-up + repeats at full size
    timing, (hit, _, _), ran = bench.measure(make, rays(8), rays(2), 0, 3, 60.0)
    assert ran is not None and timing["measured"] and calls == [8] * 5  # the call
    calls.clear()
    # a budget no run can meet: the pilot's two calls only
    timing, (hit, _, _), ran = bench.measure(make, rays(8), rays(2), 1e-12, 3, 60.0)
    assert ran is None and not timing["measured"] and calls == [2, 2]
    assert hit.shape == (2, 2) and timing["est_run_s"] == timing["run_s"] * 16


def test_paired_speedups_time_each_peer_in_turn_with_the_base():
    """Calls that sleep 10, 20 and 5 ms: each round runs the base once and each peer once,
    in turn; the medians of peer / base are ~2 and ~0.5."""
    import time

    bench = load_bench()
    order = []

    def sleeper(label, seconds):
        def call():
            order.append(label)
            time.sleep(seconds)
            return np.zeros(1)
        return call

    calls = dict(base=sleeper("base", 0.01), slow=sleeper("slow", 0.02),
                 fast=sleeper("fast", 0.005))
    got = bench.paired_speedups(calls, "base", 3)
    assert order == ["base", "slow", "fast"] * 3
    assert 1.5 < got["slow"] < 3.0 and 0.3 < got["fast"] < 0.75 and "base" not in got


@needs_data
@pytest.mark.skipif(not (SPELUNKING / "src" / "queries.py").exists(),
                    reason=f"no Spelunking checkout at {SPELUNKING} (JAXISO_SPELUNKING)")
def test_spelunking_harness_casts_the_same_rays():
    import jax

    import jaxiso as ji

    bench = load_bench()
    sp = bench.Spelunking(SPELUNKING)
    assert "polyscope" not in sys.modules and "queries" not in sys.modules  # cleaned up
    net = bench.Network("fox", FOX, ji.implicit.load_mlp(FOX), True, bench.VIEWS["fox"])
    rays = bench.camera(net, 8).rays()
    call, extract = sp.caster(net, "affine_fixed")(rays)
    hit, t, steps = extract(jax.block_until_ready(call()))
    o, d = bench.flat64(rays)
    t_ref = ref64.first_hits(ref64.load_npz64(FOX), o, d, samples=400).reshape(8, 8)
    assert np.mean(hit == np.isfinite(t_ref)) > 0.9
    both = hit & np.isfinite(t_ref)
    assert both.any() and np.max(np.abs(t[both] - t_ref[both])) < 0.01  # its hit_eps 1e-3
