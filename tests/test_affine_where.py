"""Correlated affine `where` / `select_n` (issue 28): where the condition is uncertain the
cases are joined as one form (their mean, the error covering half their difference) or,
when the condition compares a form with something, by a chord in that form; the result
holds every value of either case (float64 checks, independent of the rule) and a where-
spelled activation is about as tight as the library's rule."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from boxes import assert_encloses, sized_boxes_and_points

import jaxiso as ji
from jaxiso.arith import Affine, Interval, aa, ia

N, SYMBOLS, SAMPLES = 512, 3, 64


def _form(rng, center=None, scale=1.0):
    c = rng.normal(0, 1, N) if center is None else center
    d = rng.normal(0, scale, (N, SYMBOLS)) * (rng.uniform(size=(N, 1)) < 0.9)
    e = np.abs(rng.normal(0, 0.1 * scale, N)) * (rng.uniform(size=N) < 0.7)
    return _f32(c, d, e)


def _f32(*parts):
    """The float32 values the rule sees, in float64."""
    return tuple(np.asarray(p, np.float32).astype(np.float64) for p in parts)


def _affine(c, d, e):
    return Affine(jnp.asarray(c, jnp.float32), jnp.asarray(d, jnp.float32),
                  jnp.asarray(e, jnp.float32))


def _as64(x: Affine):
    return (np.asarray(x.center, np.float64), np.asarray(x.dev, np.float64),
            np.asarray(x.err, np.float64))


def _value(form, eps, u):
    c, d, e = form
    return c[:, None] + np.einsum("ni,nsi->ns", d, eps) + e[:, None] * u


def _symbols(rng):
    eps = rng.uniform(-1, 1, (N, SAMPLES, SYMBOLS))
    eps[:, :8] = np.sign(rng.normal(size=(N, 8, SYMBOLS)))  # corners
    return eps


def _assert_holds(out: Affine, x, eps, what):
    """|x - (centre + dev . eps)| <= err for the same symbols (float64)."""
    c, d, e = _as64(out)
    gap = np.abs(x - c[:, None] - np.einsum("ni,nsi->ns", d, eps))
    bad = gap > e[:, None] + 1e-12 * (1.0 + np.abs(x))  # float64's own rounding here
    worst = np.max(gap - e[:, None])
    assert not bad.any(), f"{what}: {bad.sum()} values outside (worst by {worst:.3g})"


def _pair(rng):
    """Two forms over the same symbols; half the pairs nearly agree (b = 0.9 a + small)."""
    a = _form(rng)
    b = _form(rng)
    close = rng.uniform(size=N) < 0.5
    b = _f32(np.where(close, 0.9 * a[0] + 0.05 * b[0], b[0]),
             np.where(close[:, None], 0.9 * a[1] + 0.05 * b[1], b[1]),
             np.where(close, 0.05 * b[2], b[2]))
    return a, b


def test_join_holds_every_value_of_both_cases():
    rng = np.random.default_rng(0)
    a, b = _pair(rng)
    unknown = Interval(jnp.zeros(N, bool), jnp.ones(N, bool))
    out = aa.where(unknown, _affine(*a), _affine(*b))
    eps = _symbols(rng)
    for name, form in (("true case", a), ("false case", b)):
        x = _value(form, eps, rng.uniform(-1, 1, (N, SAMPLES)))
        _assert_holds(out, x, eps, name)
    # the join of nearly agreeing cases is far narrower than their hull
    hull = ia.select_n(unknown, aa.to_interval(_affine(*b)), aa.to_interval(_affine(*a)))
    assert np.median(np.asarray(out.err)) < 0.5 * np.median(np.asarray(ia.rad(hull)))


def test_chord_on_the_condition_holds_the_case_taken():
    """where(g > 0, a, b) with g a form: at each value of the symbols (and of g's own
    error) the case its sign picks lies in the result."""
    rng = np.random.default_rng(1)
    a, b = _pair(rng)
    g = _form(rng, center=rng.normal(0, 0.5, N))
    mix = rng.uniform(size=N) < 0.5  # half: g is a itself (relu-like), half unrelated
    g = _f32(np.where(mix, a[0], g[0]), np.where(mix[:, None], a[1], g[1]),
             np.where(mix, a[2], g[2]))
    ga = _affine(*g)
    cond = ia.gt(aa.to_interval(ga), 0.0)
    out = aa.select_n(cond, _affine(*b), _affine(*a), sign=ga)
    eps = _symbols(rng)
    gv = _value(g, eps, rng.uniform(-1, 1, (N, SAMPLES)))
    xa = _value(a, eps, rng.uniform(-1, 1, (N, SAMPLES)))
    xb = _value(b, eps, rng.uniform(-1, 1, (N, SAMPLES)))
    # where the error symbol of g is shared with a (mix): a's value and g's coincide
    xa = np.where(mix[:, None], gv, xa)
    _assert_holds(out, np.where(gv > 0, xa, xb), eps, "taken case")
    _assert_holds(out, np.where(gv >= 0, xa, xb), eps, "taken case at g = 0")


def test_relu_written_with_where_is_relus_chord():
    rng = np.random.default_rng(2)
    h = _affine(*_form(rng))
    cond = ia.gt(aa.to_interval(h), 0.0)
    out = aa.select_n(cond, jnp.zeros(N, jnp.float32), h, sign=aa.sub(h, 0.0))
    relu = aa.maximum(h, 0.0)
    # relu's chord scales h's error term; the join cannot know that g's error term is
    # a's (it keeps it whole): equal where h has none, within that error elsewhere
    r_out, r_relu = np.asarray(aa.radius(out)), np.asarray(aa.radius(relu))
    exact = np.asarray(h.err) == 0
    np.testing.assert_allclose(r_out[exact], r_relu[exact], rtol=1e-4, atol=1e-5)
    assert np.all(r_out <= r_relu + np.asarray(h.err) * 1.001 + 1e-5)


def _mlp(act, seed=0, width=16, depth=1):
    rng = np.random.default_rng(seed)
    sizes = [3] + [width] * depth + [1]
    layers = [(rng.normal(size=(a, b)) / np.sqrt(a), rng.normal(size=b) * 0.3)
              for a, b in zip(sizes[:-1], sizes[1:])]

    def f(x, y, z, xp=jnp):
        h = xp.stack([x, y, z])
        for i, (w, b) in enumerate(layers):
            if xp is jnp:
                w, b = jnp.asarray(w, jnp.float32), jnp.asarray(b, jnp.float32)
            h = h @ w + b
            if i < len(layers) - 1:
                h = act(h, xp)
        return h[0]

    return f


SPELLINGS = {  # name: (where-spelled, library rule)
    "elu expm1": (lambda h, xp: xp.where(h > 0, h, xp.expm1(h)), lambda h: jax.nn.elu(h), 1.1),
    "elu exp(min) - 1": (lambda h, xp: xp.where(h > 0, h, xp.exp(xp.minimum(h, 0)) - 1),
                         lambda h: jax.nn.elu(h), 1.6),
    "relu": (lambda h, xp: xp.where(h > 0, h, 0.0), lambda h: jax.nn.relu(h), 1.02),
    "leaky relu": (lambda h, xp: xp.where(h > 0, h, 0.01 * h),
                   lambda h: jnp.maximum(h, 0.01 * h), 1.02),
    "clamp": (lambda h, xp: xp.where(h > 1, 1.0, xp.where(h < -1, -1.0, h)),
              lambda h: jnp.clip(h, -1.0, 1.0), 1.02),
}


def _boxes(rng, n, size):
    lo = rng.uniform(-1, 1 - size, size=(3, n)).astype(np.float32)
    hi = lo + np.float32(size)
    return lo, hi


@pytest.mark.parametrize("name", sorted(SPELLINGS))
def test_where_spelled_activation_is_as_tight_as_the_library_rule(name):
    """Median enclosure width of a 1 x 16 MLP: the where spelling within a small factor
    of the library rule (the interval hull made them 1.4-3x wider)."""
    spelled, library, factor = SPELLINGS[name]
    rng = np.random.default_rng(3)
    lo, hi = _boxes(rng, 64, 0.05)
    boxes = [Interval(jnp.asarray(lo[i]), jnp.asarray(hi[i])) for i in range(3)]
    widths = []
    for act in (lambda h, xp: spelled(h, xp), lambda h, xp: library(h)):
        f = _mlp(act)
        out = aa.to_interval(jax.jit(ji.extend(lambda x, y, z: f(x, y, z), "affine"))(*boxes))
        widths.append(np.median(np.asarray(out.hi - out.lo, np.float64)))
    assert widths[0] <= factor * widths[1], f"{name}: {widths[0]:.4g} vs {widths[1]:.4g}"


def test_where_spellings_are_sound_against_float64():
    """A network mixing where-spelled activations (conditions on forms, negated, nested,
    unrelated to the cases; fresh symbols), outward rounding, float64 reference."""

    def act(h, xp):
        h1 = xp.where(h > 0, h, xp.expm1(xp.minimum(h, 0)))
        h2 = xp.where(~(h1 <= 0.2), 0.5 * h1, xp.where(h1 < -0.3, -0.3, h1 * h1))
        return xp.where(h[::-1] > h, h2 - h, xp.abs(h2) - 0.5)

    f = _mlp(act, seed=4, width=6, depth=2)
    lo, hi, pts = sized_boxes_and_points(np.random.default_rng(5), 24, 24, 6)
    boxes = [Interval(jnp.asarray(lo[i]), jnp.asarray(hi[i])) for i in range(3)]
    F = jax.jit(ji.extend(lambda x, y, z: f(x, y, z), "affine", "outward", fresh_symbols=8))
    out = aa.to_interval(F(*boxes))
    vals = np.array([[f(*p, xp=np) for p in row] for row in pts])
    assert_encloses(out.lo, out.hi, vals, "where-spelled network")
