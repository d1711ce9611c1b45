"""jaxiso's pytrees survive how JAX rebuilds them: with every field given, sometimes as
placeholders that are no arrays (explaining a jit cache miss, `tree_structure().unflatten`),
so construction defaults must not read the fields they were given."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji


def _values():
    box = ji.Interval(jnp.zeros(3), jnp.ones(3))
    return dict(interval=box, affine=ji.aa.from_interval(box, 0, 2),
                rays=ji.Rays(jnp.zeros((2, 3)), jnp.ones((2, 3))),
                surface=ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z - 0.25,
                                           (-1, -1, -1), (1, 1, 1)))


@pytest.mark.parametrize("kind", ["interval", "affine", "rays", "surface"])
def test_rebuilt_with_placeholder_leaves(kind):
    value = _values()[kind]
    tree = jax.tree_util.tree_structure(value)
    marks = [object() for _ in range(tree.num_leaves)]
    rebuilt = tree.unflatten(marks)
    assert type(rebuilt) is type(value)
    assert jax.tree_util.tree_leaves(rebuilt) == marks


def test_jit_cache_misses_explained_with_affine_arguments():
    """`jax_explain_cache_misses` (a common debugging switch) rebuilds the arguments of a
    missed call with placeholders: an Affine argument crashed there."""
    f = jax.jit(lambda a: ji.aa.to_interval(a * a).hi)
    old = jax.config.jax_explain_cache_misses
    jax.config.update("jax_explain_cache_misses", True)
    try:
        for n in (3, 5):  # the second shape is a cache miss, explained
            box = ji.Interval(jnp.zeros(n), jnp.ones(n))
            hi = f(ji.aa.from_interval(box, 0, 1))
            np.testing.assert_allclose(np.asarray(hi), np.ones(n), rtol=1e-5)
    finally:
        jax.config.update("jax_explain_cache_misses", old)
