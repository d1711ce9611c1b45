"""The spelling suite (issue 28, item 5): generated networks whose activations are
written in different spellings (`jaxiso.implicit.spellings`) draw the same surface through
the default call, `ji.intersect(ji.ImplicitSurface(f, lo, hi, params=params), rays)`,
as a float64 reference independent of jaxiso (reference_spellings64.py) does.

The fast cases take one small network (2 x 16, no sign grid) in each of the three main
spellings at 24^2 (each 10-35 s on the loaded 2-core CPU, mostly preparation and
compilation); every activation in every spelling, on 3 x 32 networks that build a sign
grid, is the heavy case (benchmarks/bench_spellings.py measures them at 128^2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_spellings64 as ref64

import jaxiso as ji
from jaxiso.implicit import spellings as sp

pytest.importorskip("equinox")

LO, HI = (-1.0,) * 3, (1.0,) * 3
SIZE = 24
AGREEMENT = 0.995  # the bar: hit masks against float64
K = ref64.constants(sp)


def rays_and_reference(net, size=SIZE):
    cam = ji.Camera.look_at((2.0, 1.3, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 32.0,
                            size, size)
    rays = cam.rays()
    o = np.asarray(rays.origin, np.float64).reshape(-1, 3)
    d = np.asarray(rays.direction, np.float64).reshape(-1, 3)
    return rays, ref64.first_hits(net.activation, net.layers, K, o, d, LO, HI)


def check_default_call(activation, spelling, depth, width, seed=0):
    """The default call's hit mask against float64 on SIZE^2 rays (>= AGREEMENT), and
    the hit depths where both hit."""
    net = sp.random_net(seed, activation, depth, width)
    spelled = sp.spell(net, spelling)
    rays, t_ref = rays_and_reference(net)
    hits = ji.intersect(ji.ImplicitSurface(spelled.f, LO, HI, params=spelled.params), rays)
    hit = np.asarray(hits.hit).reshape(-1)
    ref_hit = np.isfinite(t_ref)
    assert 0.05 < ref_hit.mean() < 0.6  # the surface is in view, and not all of it
    agreement = np.mean(hit == ref_hit)
    assert agreement >= AGREEMENT, (net.name, spelling, agreement)
    both = hit & ref_hit
    t = np.asarray(hits.t, np.float64).reshape(-1)
    assert np.median(np.abs(t[both] - t_ref[both])) < 1e-3, (net.name, spelling)


def test_random_net_is_deterministic_and_in_the_box():
    a, b = sp.random_net(7, "elu"), sp.random_net(7, "elu")
    assert a.name == b.name and 2 <= a.depth <= 8 and a.width in sp.WIDTHS
    assert all(np.array_equal(x, y) for la, lb in zip(a.layers, b.layers)
               for x, y in zip(la, lb))
    assert not np.array_equal(sp.random_net(8, "elu", 2, 16).layers[0][0],
                              sp.random_net(7, "elu", 2, 16).layers[0][0])
    # the network's part spans +-AMPLITUDE: inside the sphere's |p| - RADIUS band
    p = np.random.default_rng(0).uniform(-1.0, 1.0, (2048, 3))
    net_part = ref64.evaluate("elu", a.layers, K, p) - (np.linalg.norm(p, axis=1) - sp.RADIUS)
    assert np.abs(net_part).max() <= 1.05 * sp.AMPLITUDE
    with pytest.raises(ValueError, match="unknown activation"):
        sp.random_net(0, "swish")
    with pytest.raises(ValueError, match="unknown spelling of relu"):
        sp.spell(sp.random_net(0, "relu", 2, 16), "jnp.tanh")


@pytest.mark.parametrize("activation", sp.ACTIVATIONS)
def test_every_spelling_is_the_float64_function(activation):
    """Each spelling of a network, at 64 points, is the reference's float64 value to
    float32 rounding: the spellings differ in how they are written, not in what they
    compute."""
    net = sp.random_net(1, activation, 3, 16)
    p = np.random.default_rng(2).uniform(-1.0, 1.0, (64, 3))
    want = ref64.evaluate(activation, net.layers, K, p)
    q = jnp.asarray(p, jnp.float32)
    for spelling in sp.spellings_of(activation):
        s = sp.spell(net, spelling)
        got = jax.vmap(lambda r, s=s: s.point(r[0], r[1], r[2], s.params))(q)
        np.testing.assert_allclose(np.asarray(got, np.float64), want, atol=2e-5,
                                   err_msg=f"{activation} / {spelling}")


@pytest.mark.parametrize("activation, spelling, depth, width", [
    ("relu", "jax.nn", 2, 16),
    ("elu", "jnp", 2, 16),  # the where-spelled elu
    ("tanh", "equinox", 2, 16),
])
def test_default_call_agrees_with_float64(activation, spelling, depth, width):
    check_default_call(activation, spelling, depth, width)


def test_equinox_module_as_params():
    """The whole module as params: its activation (jax.nn.relu, a custom_jvp) is a leaf
    that is no array; it is static (`_core.WithStaticLeaves`), the arrays traced (this
    raised "TypeError: Cannot determine dtype" before)."""
    check_default_call("relu", "equinox.params", 2, 16)


@pytest.mark.parametrize("spelling", ["equinox", "equinox.params"])
def test_a_module_scene_is_prepared_once(spelling, monkeypatch):
    """An equinox module holding arrays is unhashable; as f (or in params) it is keyed
    by identity in the caches of prepared results, so repeated calls on a scene that
    was never `prepared` measure its arithmetic and build its grid once (they ran on
    every call: 19.6 s a call against 0.2 s for jax.nn at 128^2)."""
    from jaxiso.implicit import _auto
    calls = []
    programs = _auto._width_programs
    monkeypatch.setattr(_auto, "_width_programs",
                        lambda *a, **k: calls.append(1) or programs(*a, **k))
    s = sp.spell(sp.random_net(0, "relu", 2, 16), spelling)
    scene = ji.ImplicitSurface(s.f, (-1.0,) * 3, (1.0,) * 3, params=s.params,
                               culling="none")
    rays = ji.Camera.look_at((3.0, 0.8, 1.2), (0, 0, 0), (0, 1, 0), 35.0, 8, 8).rays()
    first, second = ji.intersect(scene, rays), ji.intersect(scene, rays)
    np.testing.assert_array_equal(np.asarray(first.t), np.asarray(second.t))
    assert len(calls) == 1 and np.any(np.asarray(first.hit))


def _all_cases():
    for activation in sp.ACTIVATIONS:
        for spelling in sp.spellings_of(activation):
            yield pytest.param(activation, spelling, id=f"{activation}-{spelling}")


# 51 cases x 10-90 s of preparation (3 x 32 networks build a sign grid) and compiles on
# 2 cores: run with the benchmarks. It holds the crash case, softplus_t8 / jnp
# (logaddexp(8 h, 0) / 8 in a 3-layer network while the sign grid is built), 94 s alone.
@pytest.mark.heavy
@pytest.mark.parametrize("activation, spelling", list(_all_cases()))
def test_every_spelling_agrees_with_float64(activation, spelling):
    check_default_call(activation, spelling, 3, 32, seed=3)
