"""Plan policy of implicit scenes: packet edges, persistent lanes and what counts as a
heavy function, as measured (benchmarks/NOTES.md)."""

from __future__ import annotations

from .._core import LANES, Plan, cpu_lanes
from ..arith import value_elements

__all__ = ["packet_plan", "is_heavy", "HEAVY_ELEMENTS", "HEAVY_LANES_FROM", "CPU_TILES"]

# CPU packet edges from the packet table of benchmarks/bench_implicit.py on the 2-core CPU:
# interval t-bisection was fastest in 4x4 tiles (Barth sextic 0.74 Mrays/s vs 0.57 in 8x8;
# one vmap over the whole image 0.025), affine in 8x8. From 2^16 rays t-bisection runs on
# persistent lanes (affine at 512^2: 1.68 vs 0.41 Mrays/s in 8x8 tiles); K-bisection and
# the baselines have no lanes form. Other backends are unmeasured (8x8 packets).
# "polynomial" (point evaluations, like interval's cost per piece) takes interval's edge,
# unmeasured: its scenes of 2^16 rays and more run on lanes
CPU_TILES = {"interval": 4, "affine": 8, "polynomial": 4}

# Heavy functions (networks: hundreds of numbers computed per point, `value_elements`)
# gain from persistent lanes from 2^12 rays on the CPU: Spelunking's networks at 128^2,
# affine, eps 2^-10, run_s packets 8x8 -> 4096 lanes: fox 5.16 -> 1.11 s, hammer 4.82 ->
# 1.19, birdcage_occ 6.85 -> 1.55, bunny 43.4 -> 12.5, with a shorter first call too; fox
# at 64^2 1.48 -> 0.44 s. Light ones (the catalogue's polynomials: 6-39 numbers) compile
# 2-4 s longer on lanes, which small images do not win back (Barth sextic 128^2: first
# call 2.9 -> 7.0 s), so they keep packets below 2^16 rays. benchmarks/NOTES.md.
HEAVY_ELEMENTS = 256
HEAVY_LANES_FROM = 2**12


def packet_plan(lanes_form: bool, arithmetic: str, n_rays: int, backend: str,
                heavy: bool = False) -> Plan:
    """The measured plan of the straight path: tiles per arithmetic on the CPU, and
    persistent lanes for a method with a lanes form (`lanes_form`) on large batches
    (heavy functions from HEAVY_LANES_FROM rays)."""
    if backend != "cpu":
        return Plan(tile=8)
    lanes = None
    if lanes_form:
        lanes = cpu_lanes(n_rays, backend)
        if heavy and n_rays >= HEAVY_LANES_FROM:
            lanes = LANES
    return Plan(tile=CPU_TILES[arithmetic], lanes=lanes)


def is_heavy(g, params) -> bool:
    """Whether the point field ``g(x, y, z, w, params)`` computes at least HEAVY_ELEMENTS
    numbers per point (a network). Traces g once (no evaluation)."""
    try:
        size = value_elements(lambda x, y, z, w: g(x, y, z, w, params), 4)
    except Exception:  # noqa: BLE001 - a function that cannot be traced on scalars
        size = 0
    return size >= HEAVY_ELEMENTS
