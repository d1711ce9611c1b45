"""Sign grids (`culling`): cells' enclosures built at construction, rays cut to the part
near possible cells; fresh noise symbols in `extend` (issue 13, speed)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_trace64 import first_roots

import jaxiso as ji
from jaxiso.arith import Affine, Interval, _extend, aa, extend

LO, HI = -1.0, 1.0
SIZE = 24
CAM = ji.Camera.look_at((2.4, 1.1, 1.6), (0, 0, 0), (0, 0, 1), 42.0, SIZE, SIZE)
EPS = 2.0**-10


def _weights(width=40, depth=3, seed=3, activation="relu"):
    """A wiggly sphere: 0.15 net(p) + |p| - 0.7, net a random `depth`-layer MLP."""
    rng = np.random.default_rng(seed)
    sizes = [3] + [width] * depth + [1]
    return {"layers": [{"A": jnp.asarray(rng.normal(0, 1 / np.sqrt(a), (a, b)), jnp.float32),
                        "b": jnp.asarray(rng.normal(0, 0.3, b), jnp.float32)}
                       for a, b in zip(sizes[:-1], sizes[1:])],
            "activation": activation}


ACT = {"relu": jax.nn.relu, "tanh": jnp.tanh, "elu": jax.nn.elu}
ACT64 = {"relu": lambda h: np.maximum(h, 0.0), "tanh": np.tanh,
         "elu": lambda h: np.where(h > 0, h, np.expm1(np.minimum(h, 0.0)))}


def _field(activation):
    act = ACT[activation]

    def f(x, y, z, params):
        p = jnp.stack([x, y, z])
        h = p
        for i, layer in enumerate(params):
            h = (act(h) if i else h) @ layer["A"] + layer["b"]
        return 0.15 * h[0] + jnp.sqrt(x * x + y * y + z * z) - 0.7
    return f


def _field64(params, activation):
    layers = [(np.asarray(q["A"], np.float64), np.asarray(q["b"], np.float64))
              for q in params]
    act = ACT64[activation]

    def f(P):
        h = P
        for i, (A, b) in enumerate(layers):
            h = (act(h) if i else h) @ A + b
        return 0.15 * h[..., 0] + np.linalg.norm(P, axis=-1) - 0.7
    return f


def _reference(f64, rays, iso=0.0):
    """Whether each ray crosses f64 = iso inside the box (float64 samples, bisection)."""
    t, _ = first_roots(lambda x, y, z, w: f64(np.stack([x, y, z], -1)), (LO,) * 3,
                       (HI,) * 3, np.asarray(rays.origin).reshape(-1, 3),
                       np.asarray(rays.direction).reshape(-1, 3), isovalues=(iso,),
                       samples=3000)
    return np.isfinite(t)


def _scene(activation="relu", **kw):
    w = _weights(activation=activation)
    return ji.ImplicitSurface(_field(activation), (LO,) * 3, (HI,) * 3,
                              params=w["layers"], eps=EPS, **kw)


@pytest.fixture(scope="module")
def relu_scene():
    return _scene().prepared()


# -- fresh noise symbols in extend ------------------------------------------------------

@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
def test_fresh_symbols_enclose_and_are_tighter_than_af1(activation):
    """Boxes of half-width 2^-5 .. 2^-3: the enclosure holds float64 samples, and on
    most boxes it is narrower than AF1's (each nonlinearity keeps its error as symbols,
    which the next layer's weights mix with their signs)."""
    w = _weights(activation=activation)
    f = _field(activation)
    f64 = _field64(w["layers"], activation)
    af1 = extend(f, "affine", n_symbols=3)
    zono = extend(f, "affine", n_symbols=3, fresh_symbols=24, fresh_per_op=8)
    rng = np.random.default_rng(0)
    narrower = []
    for half in (2.0**-3, 2.0**-4, 2.0**-5):
        c = rng.uniform(-0.8, 0.8, (64, 3)).astype(np.float32)
        boxes = [Interval(jnp.asarray(c[:, i] - half), jnp.asarray(c[:, i] + half))
                 for i in range(3)]
        a = aa.to_interval(af1(*boxes, params=w["layers"]))
        z = aa.to_interval(zono(*boxes, params=w["layers"]))
        pts = c[:, None] + rng.uniform(-half, half, (64, 200, 3))
        v = f64(pts)
        tol = 1e-5 * (1 + np.abs(v).max())
        assert np.all(np.asarray(z.lo)[:, None] <= v + tol)
        assert np.all(np.asarray(z.hi)[:, None] >= v - tol)
        narrower.append(np.asarray(z.hi - z.lo) < np.asarray(a.hi - a.lo))
    assert np.mean(narrower) > 0.8, np.mean(narrower)


def test_fresh_symbols_a_smooth_operation_takes_twice_a_kinks_and_forms_carry_only_those():
    """One layer of 6 neurons, budget 100, 2 per kink: a max takes 2 symbols, a tanh
    2 * _SMOOTH_SHARE (at most the 6 neurons), and the forms carry 3 + those, not the whole
    budget (each symbol costs in every form); a smaller budget caps it."""
    A = jnp.asarray(np.random.default_rng(1).normal(size=(3, 6)), jnp.float32)

    def layer(activation):
        return lambda x, y, z: jnp.sum(activation(jnp.stack([x, y, z]) @ A))

    box = [Interval(jnp.full(5, -0.5, jnp.float32), jnp.full(5, 0.5, jnp.float32))] * 3
    smooth = min(6, 2 * _extend._SMOOTH_SHARE)
    for activation, budget, taken in ((lambda h: jnp.maximum(h, 0.0), 100, 2),
                                      (jnp.tanh, 100, smooth), (jnp.tanh, 3, 3)):
        F = extend(layer(activation), "affine", n_symbols=3, fresh_symbols=budget,
                   fresh_per_op=2)
        out = F(*box)
        assert out.dev.shape == (5, 3 + taken)


def test_fresh_symbols_need_affine():
    with pytest.raises(ValueError, match="fresh_symbols"):
        extend(lambda x: x * x, "interval", fresh_symbols=4)


def test_fresh_symbols_leave_infinite_errors_alone():
    """An unbounded error (exp of a huge range) stays in the error term: a symbol with an
    infinite deviation would turn 0 * inf into NaN downstream."""
    F = extend(lambda x, y: jnp.sum(jnp.exp(jnp.stack([x, y])) * 0.0 + 1.0), "affine",
               fresh_symbols=4, fresh_per_op=2)
    out = F(Interval(jnp.float32(-1.0), jnp.float32(1e3)), Interval(jnp.float32(0.0),
                                                                     jnp.float32(1.0)))
    assert isinstance(out, Affine)
    assert not np.any(np.isnan(np.asarray(out.dev)))


# -- the grid -----------------------------------------------------------------------------

def test_grid_is_built_for_networks_and_encloses(relu_scene):
    S = relu_scene
    g = S.sign_grid
    assert g is not None and "sign grid" in S.culling_report, S.culling_report
    low, high = np.asarray(g.low), np.asarray(g.high)
    n = low.shape[0]
    assert low.shape == (n, n, n) and n >= 16
    f64 = _field64(S.params, "relu")
    rng = np.random.default_rng(1)
    cells = rng.integers(0, n, (300, 3))
    edge = (HI - LO) / n
    pts = LO + (cells[:, None] + rng.uniform(0, 1, (300, 50, 3))) * edge
    v = f64(pts)
    lo_c, hi_c = low[tuple(cells.T)], high[tuple(cells.T)]
    assert np.all(lo_c[:, None] <= v + 1e-5) and np.all(hi_c[:, None] >= v - 1e-5)
    # most cells are decided: the grid is worth building
    possible = (low <= 0) & (0 <= high)
    assert possible.mean() < 0.25, possible.mean()


def test_culled_hits_match_the_walk_and_float64(relu_scene):
    S = relu_scene
    rays = CAM.rays()
    culled = ji.intersect(S, rays)
    whole = ji.intersect(S.replace(culling="none"), rays)
    ref = _reference(_field64(S.params, "relu"), rays)
    hit, hit_whole = np.asarray(culled.hit).reshape(-1), np.asarray(whole.hit).reshape(-1)
    assert ref.sum() > 100 and np.sum(hit != ref) <= 1, (np.sum(hit & ~ref),
                                                           np.sum(~hit & ref))
    both = hit & hit_whole
    dt = np.abs(np.asarray(culled.t).reshape(-1)[both] - np.asarray(whole.t).reshape(-1)[both])
    assert np.max(dt) < 4 * EPS
    # fewer steps: rays whose segment meets no possible cell walk none
    steps, steps_whole = np.asarray(culled.steps), np.asarray(whole.steps)
    assert np.mean(steps == 0) > np.mean(steps_whole == 0) + 0.2
    assert np.mean(steps) < np.mean(steps_whole)


def test_grid_holds_at_other_isovalues(relu_scene):
    """The grid is built for the scene's isovalues; other ones (a slider) keep it and
    still get every crossing."""
    S = relu_scene.replace(isovalues=(0.25,))
    assert S.sign_grid is relu_scene.sign_grid
    rays = CAM.rays()
    hit = np.asarray(ji.intersect(S, rays).hit).reshape(-1)
    ref = _reference(_field64(S.params, "relu"), rays, iso=0.25)
    assert ref.sum() > 100 and np.sum(hit != ref) <= 1


def test_replace_rebuilds_the_grid_only_when_f_changes(relu_scene):
    S = relu_scene
    assert S.replace(eps=2.0**-9).sign_grid is S.sign_grid
    assert S.replace(eps=2.0**-9).ready  # nothing to prepare again
    assert S.replace(culling="none").prepared().sign_grid is None
    other = _weights(seed=4)["layers"]
    T = S.replace(params=other)
    assert T.sign_grid is None and not T.ready  # dropped; built by the next preparation
    T = T.prepared()
    assert T.sign_grid is not None and T.sign_grid is not S.sign_grid
    assert T.sign_grid.resolution == S.sign_grid.resolution == (64,) * 3  # no recompile
    assert not np.array_equal(np.asarray(T.sign_grid.high), np.asarray(S.sign_grid.high))


def test_no_grid_under_a_trace_and_for_light_functions():
    w = _weights()["layers"]

    @jax.jit
    def depth(params):
        S = ji.ImplicitSurface(_field("relu"), (LO,) * 3, (HI,) * 3, params=params,
                               eps=EPS).prepared()
        assert S.sign_grid is None and "traced" in S.culling_report
        return ji.intersect(S, CAM.rays()).t

    t = np.asarray(depth(w))
    assert np.isfinite(t).sum() > 100
    sphere = ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z - 0.5, (LO,) * 3,
                                (HI,) * 3).prepared()
    assert sphere.sign_grid is None and "light" in sphere.culling_report
    forced = sphere.replace(culling="grid").prepared()
    assert forced.sign_grid is not None
    np.testing.assert_array_equal(np.asarray(ji.intersect(forced, CAM.rays()).hit),
                                  np.asarray(ji.intersect(sphere, CAM.rays()).hit))


def test_undefined_cells_are_never_culled():
    """Where f is NaN the cells' enclosures are unbounded: possible, so rays there walk
    as without the grid."""
    def f(x, y, z):
        return jnp.where(x > 0.3, jnp.nan, x * x + y * y + z * z - 0.5)

    S = ji.ImplicitSurface(f, (LO,) * 3, (HI,) * 3, culling="grid",
                           arithmetic="interval").prepared()
    assert not np.all(np.isfinite(np.asarray(S.sign_grid.high)))
    rays = CAM.rays()
    np.testing.assert_array_equal(
        np.asarray(ji.intersect(S, rays).hit),
        np.asarray(ji.intersect(S.replace(culling="none"), rays).hit))


def test_delta_turns_culling_off(relu_scene):
    S = relu_scene.replace(delta=1e-3)
    rays = CAM.rays()
    a = ji.intersect(S, rays)
    b = ji.intersect(S.replace(culling="none"), rays)
    np.testing.assert_array_equal(np.asarray(a.t), np.asarray(b.t))


def test_culling_is_validated():
    with pytest.raises(ValueError, match="culling"):
        _scene(culling="octree")


def test_span_holds_the_first_crossing_and_ends_soon_after(relu_scene):
    """segment_span's [s0, s1] holds each ray's first float64 crossing; after it the span
    ends within a few cells where the ray enters surely-inside cells (a sign change). The
    gap of the samples that holds the crossing is marked, and the marks leave out part
    of the spans (stretches that pass no possible cell)."""
    from jaxiso.implicit._field import ray_segments
    from jaxiso.implicit._grid import free_from, samples_per_segment, segment_span

    S = relu_scene
    rays = CAM.rays().reshape((-1,))
    t, _ = first_roots(lambda x, y, z, w: _field64(S.params, "relu")(np.stack([x, y, z], -1)),
                       (LO,) * 3, (HI,) * 3, np.asarray(rays.origin),
                       np.asarray(rays.direction), samples=3000)
    t0, t1, inside, p, D = ray_segments(rays, S.lo, S.hi, 0.0, jnp.inf)
    span = segment_span(S.sign_grid, S.lo, S.hi, S.isovalues, p, D, inside)
    s0, s1, near = np.asarray(span.s0), np.asarray(span.s1), np.asarray(span.inside)
    hit = np.isfinite(t)
    s = (t[hit] - np.asarray(t0)[hit]) / np.asarray(t1 - t0)[hit]
    assert hit.sum() > 100 and np.all(near[hit])
    assert np.all(s0[hit] <= s + 1e-6) and np.all(s <= s1[hit] + 1e-6)
    cell = (HI - LO) / S.sign_grid.resolution[0]
    length = np.linalg.norm(np.asarray(D)[hit], axis=-1)
    assert np.median((s1[hit] - s) * length) < 6 * cell
    # the crossing's gap is marked: the first marked gap from the span's start is at or
    # before it
    gaps = samples_per_segment(S.sign_grid) - 1
    marks = np.asarray(span.marks)
    u = s * gaps
    bits = (marks[hit][np.arange(hit.sum()), (u // 32).astype(int)]
            >> (np.floor(u) % 32).astype(np.uint32)) & 1
    assert np.all(bits == 1)
    free = np.asarray(free_from(jnp.asarray(marks[hit]), jnp.asarray(s0[hit] * gaps)))
    assert np.all(free <= np.floor(u))
    # some gaps inside the spans are empty (the walks leap over them)
    i = np.arange(gaps)
    inside_span = (i[None] >= np.floor(s0[near] * gaps)[:, None]) & (
        i[None] < np.ceil(s1[near] * gaps)[:, None])
    marked = (marks[near][:, i // 32] >> (i % 32).astype(np.uint32)) & 1
    assert (marked[inside_span] == 0).sum() > 40  # 89 of 1,279 when written

def test_free_from_finds_the_next_marked_gap():
    """free_from against a loop over the bits: the first marked gap at or after floor(u)
    (inf when none), over words of 32 gaps."""
    from jaxiso.implicit._grid import free_from

    rng = np.random.default_rng(0)
    n, words = 500, 3
    bits = rng.random((n, 32 * words)) < rng.choice([0.0, 0.02, 0.3], (n, 1))
    marks = np.zeros((n, words), np.uint32)
    for w in range(words):
        for b in range(32):
            marks[:, w] |= bits[:, 32 * w + b].astype(np.uint32) << np.uint32(b)
    u = rng.uniform(-1.0, 32 * words + 1.0, n).astype(np.float32)
    got = np.asarray(free_from(jnp.asarray(marks), jnp.asarray(u)))
    for i in range(n):
        at = [j for j in range(32 * words) if bits[i, j] and j >= max(np.floor(u[i]), 0)]
        assert got[i] == (at[0] if at else np.inf), (i, u[i])
