"""The ray-segment methods of implicit scenes: one registry, name -> kernel and the scene
options it reads, so that dispatch, validation and plans ask one place.

Every kernel is called as ``kernel(g, scene, p, D, inside, lanes=, empty=)`` on a packet
of ray segments ``p + s D`` (p, D: [P, 3], inside: [P]) of the point field g, and returns
`_bisect.Result` [P] (s in [0, 1], hit, steps).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

from . import _baselines
from ._bisect import Bisection, BoxTest, run_bisection
from ._field import contains_any, enclosure, extended, ray_boxes, root_check
from ._polynomial import chebyshev_enclosure

__all__ = ["Method", "METHODS", "BISECTIONS", "check_lanes", "scene_options",
           "HEAVY_VERIFY_LEVELS"]

# Heavy functions' walks stop this many levels above d_max, and verification finds the hit
# among the piece's 2^levels pieces at d_max by point evaluations (`_bisect.first_verified`)
HEAVY_VERIFY_LEVELS = 2


@dataclasses.dataclass(frozen=True)
class Method:
    """One method: its kernel, the scene fields passed to it as keywords (those not
    None), the fields it cannot run without (`needs` says what they are), whether it
    bisects enclosures (sign grid culling, the tape path) and whether it has a
    persistent-lanes form."""

    kernel: Callable
    options: tuple = ()
    requires: tuple = ()
    needs: str = ""
    bisects: bool = False
    lanes: bool = False


def scene_options(scene, names) -> dict:
    """The scene's values of the fields `names` that are set (not None)."""
    values = {name: getattr(scene, name, None) for name in names}
    return {name: v for name, v in values.items() if v is not None}


def _bisection(g, scene, p, D, inside, lanes=None, empty=None):
    """t- or K-bisection of f's enclosures in the scene's arithmetic, hits verified by
    the scene's `verify` policy."""
    if scene.arithmetic == "polynomial":
        enclose = functools.partial(chebyshev_enclosure, g, scene.facts.degree)
    else:
        F = extended(g, scene.arithmetic, scene.rounding)

        def enclose(p, D, s0, s1, w, params):
            return enclosure(F, ray_boxes(p, D, s0, s1, scene.arithmetic), w, params,
                             scene.arithmetic)

    def test(p, D, s0, s1):
        r = enclose(p, D, s0, s1, scene.w, scene.params)
        possible, finite = contains_any(r, scene.isovalues)
        return BoxTest(possible, finite, (r.hi - r.lo) < scene.delta)

    heavy = scene.is_heavy()
    how = Bisection(scene.method, scene.eps, scene.max_steps, lanes,
                    root_check(g, scene.w, scene.params, scene.isovalues, scene.verify),
                    lanes is not None and heavy, empty, HEAVY_VERIFY_LEVELS if heavy else 0)
    return run_bisection(test, p, D, inside, how)


def _baseline(kernel, options):
    """A baseline of `_baselines` as a registry kernel (no lanes, no culling)."""
    def run(g, scene, p, D, inside, lanes=None, empty=None):
        return kernel(g, scene, p, D, inside, **scene_options(scene, options))
    return run


METHODS = {
    "t-bisection": Method(_bisection, bisects=True, lanes=True),
    "k-bisection": Method(_bisection, bisects=True),
    "mitchell": Method(_baseline(_baselines.mitchell, (
        "eps", "arithmetic", "rounding", "max_steps", "refine_steps"))),
    "sampling": Method(_baseline(_baselines.sampling, ("eps", "samples", "refine_steps"))),
    "sphere": Method(_baseline(_baselines.sphere, ("eps", "max_steps", "lipschitz")),
                     requires=("lipschitz",),
                     needs="a Lipschitz bound of f: lipschitz=L on the scene"),
}
BISECTIONS = tuple(name for name, m in METHODS.items() if m.bisects)


def check_lanes(method: str, lanes) -> None:
    """ValueError unless `method` runs on `lanes` persistent lanes (None: packets)."""
    if lanes is not None and not METHODS[method].lanes:
        raise ValueError(f"persistent lanes run t-bisection only; method {method!r} runs in "
                         "packets: pass plan=jaxiso.Plan(tile=...) without lanes")
