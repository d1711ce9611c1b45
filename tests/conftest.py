import gc
import os

import jax
import pytest
from hypothesis import HealthCheck, Phase, settings

# Each example evaluates a fixed-size batch under jit, so few examples cover many boxes.
settings.register_profile(
    "jaxiso", max_examples=int(os.environ.get("JAXISO_HYPOTHESIS_EXAMPLES", "40")),
    deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True,
    # no shrinking: a failing batch is reported as is (its message names the box)
    phases=[Phase.explicit, Phase.reuse, Phase.generate])
settings.load_profile("jaxiso")


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches():
    """Each test file leaves JAX's caches empty. An xdist worker runs many files in one
    process and every compiled program holds a few memory maps; past the kernel's
    vm.max_map_count (65,530 here) XLA's compiler fails ("LLVM compilation error: Cannot
    allocate memory") and segfaults, which killed a worker and left the suite waiting on
    it (CI stop 20)."""
    yield
    jax.clear_caches()
    gc.collect()
