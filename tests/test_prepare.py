"""Constructing a scene only checks; `prepared()` (done by the first intersect / render)
does the expensive work, once, and holds its results on the scene; caches are bounded
and `jaxiso.clear_caches` empties them."""

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji
from jaxiso.implicit import _grid, _memo, _prepare, _scene

CAM = ji.Camera.look_at((3.0, 2.0, 1.0), (0.0, 0.0, 0.0), width=8, height=8)


def _counted():
    calls = []

    def f(x, y, z, params):
        calls.append(1)
        h = jnp.tanh(jnp.stack([x, y, z]) @ params["A"])
        return jnp.sum(h) - 0.2

    params = {"A": jnp.asarray(np.random.default_rng(0).normal(size=(3, 96)) / 10,
                               jnp.float32)}
    return f, params, calls


def _refuse(*args, **kwargs):
    raise AssertionError("preparation ran during construction")


def test_constructor_and_replace_never_evaluate_f(monkeypatch):
    f, params, calls = _counted()
    for name in ("choose_arithmetic", "sign_grid_for", "function_facts"):
        monkeypatch.setattr(_prepare, name, _refuse)
    S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params, culling="grid")
    T = S.replace(eps=2.0**-9, params={"A": params["A"] * 2}, w=0.5)
    assert calls == [] and not S.ready and not T.ready
    assert S.arithmetic == "auto" and S.sign_grid is None


def test_prepared_resolves_once_and_holds_its_results():
    f, params, calls = _counted()
    S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params, culling="grid")
    P = S.prepared()
    assert P.ready and P.arithmetic in ("interval", "affine") and P.sign_grid is not None
    assert P.facts is not None and isinstance(P.facts.heavy, bool)
    assert P.prepared() is P
    assert P.replace(eps=2.0**-9).ready  # eps never invalidates preparation
    assert not P.replace(w=0.5).ready    # the grid depends on w
    assert P.replace(w=0.5).arithmetic == P.arithmetic  # the choice stays


def test_a_prepared_scene_does_no_further_work(monkeypatch):
    f, params, _ = _counted()
    P = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params,
                           arithmetic="interval").prepared()
    monkeypatch.setattr(_scene, "prepare_surface", _refuse)
    hits = ji.intersect(P, CAM.rays())
    assert hits.t.shape == (8, 8)
    jax.jit(lambda s: ji.intersect(s, CAM.rays()).t)(P)


def test_clear_caches_empties_every_cache():
    f, params, _ = _counted()
    ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params=params, culling="grid").prepared()
    assert sum(len(c) for c in _memo.CACHES) > 0
    ji.clear_caches()
    assert all(len(c) == 0 for c in _memo.CACHES)


def test_bounded_cache_keeps_the_newest():
    cache = _memo.BoundedCache("test", 2)
    for k in range(5):
        assert cache.get(k, lambda k=k: k * k) == k * k
    assert len(cache) == 2 and cache.get(4, _refuse) == 16
    assert cache.get([1], lambda: "unhashable") == "unhashable"
    _memo.CACHES.remove(cache)


def test_grid_refinement_stops_where_most_cells_stay_possible():
    """A field whose cells all may hold the level: no finer level is worth building."""
    def g(x, y, z, w, params):
        return jnp.sin(60.0 * x) * jnp.sin(60.0 * y) * jnp.sin(60.0 * z)

    grid, report = _grid.build_sign_grid(g, jnp.full(3, -1.0), jnp.full(3, 1.0), 0.0, (),
                                         jnp.zeros(1))
    assert f"{_grid.FIRST_LEVEL}^3" in report and "most cells possible" in report
    assert grid.resolution == (_grid.RESOLUTION,) * 3
    _, report = _grid.build_sign_grid(g, jnp.full(3, -1.0), jnp.full(3, 1.0), 0.0, (),
                                      jnp.zeros(1), budget_s=0.0)
    assert "stopped" in report


def test_no_grid_under_a_trace_is_reported():
    f, params, _ = _counted()

    @jax.jit
    def build(A):
        S = ji.ImplicitSurface(f, (-1,) * 3, (1,) * 3, params={"A": A},
                               culling="grid").prepared()
        assert S.sign_grid is None and "traced" in S.culling_report
        assert S.arithmetic == "affine" and "trace" in S.arithmetic_report
        return ji.intersect(S, CAM.rays()).t

    assert build(params["A"]).shape == (8, 8)
