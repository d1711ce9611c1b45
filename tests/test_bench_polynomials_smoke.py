"""Smoke test of benchmarks/bench_polynomials.py: its float64 reference against dense
sampling (numpy only), and a --quick run (one fresh process, 32^2, about 15-20 s on a
2-core CPU) writing the JSON the full benchmark writes, with the default call's hit
mask agreeing with the reference."""

import json

import numpy as np
from test_bench_smoke import BENCHMARKS, load_module


def load_bench():
    return load_module(BENCHMARKS / "bench_polynomials.py")


def test_reference_roots_match_dense_sampling():
    bench = load_bench()
    rng = np.random.default_rng(1)
    o = np.tile([[4.0, 3.0, 2.5]], (120, 1))
    d = rng.normal(size=(120, 3)) * 0.15 - o[0] / np.linalg.norm(o[0])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ts = np.linspace(0.0, 10.0, 40001)
    for degree, terms in ((4, 20), (10, 200)):
        hit, t = bench.reference_hits(degree, terms, o, d)
        mono = bench.monomials(degree, terms)

        def f64(p):
            x, y, z = p[..., 0], p[..., 1], p[..., 2]
            s = x * x + y * y + z * z - float(np.float32(0.7))
            for k, a, b, c in mono:
                s = s + k * x**a * y**b * z**c
            return s

        assert 0.2 < hit.mean() < 0.8  # the view holds surface and background
        pts = o[:, None, :] + ts[None, :, None] * d[:, None, :]
        inside = np.all(np.abs(pts) <= 1.0, axis=-1)
        v = f64(pts)
        change = inside[:, :-1] & inside[:, 1:] & (np.sign(v[:, :-1]) != np.sign(v[:, 1:]))
        np.testing.assert_array_equal(change.any(axis=1), hit)
        first = ts[np.argmax(change, axis=1)]
        assert np.max(np.abs(first - t)[hit]) <= 2 * (ts[1] - ts[0])


def test_quick_run_writes_json_and_agrees(tmp_path):
    bench = load_bench()
    result = bench.main(["--quick", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "polynomials_cpu.json").read_text())
    assert saved["rows"] == json.loads(json.dumps(result["rows"]))
    (row,) = saved["rows"]
    assert "error" not in row, row
    assert (row["degree"], row["terms"]) == (4, 10)
    assert row["agreement"] >= bench.TARGET_AGREE and 0.1 < row["hit_fraction"] < 0.9
    assert row["first_picture_s"] > row["import_s"] > 0 and row["peak_rss_gb"] > 0
