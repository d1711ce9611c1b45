import os

from hypothesis import HealthCheck, Phase, settings

# Each example evaluates a fixed-size batch under jit, so few examples cover many boxes.
settings.register_profile(
    "jaxiso", max_examples=int(os.environ.get("JAXISO_HYPOTHESIS_EXAMPLES", "40")),
    deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True,
    # no shrinking: a failing batch is reported as is (its message names the box)
    phases=[Phase.explicit, Phase.reuse, Phase.generate])
settings.load_profile("jaxiso")
