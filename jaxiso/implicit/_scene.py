"""`ImplicitSurface`: the zero set (or several level sets) of a plain-JAX function.

Implements the scene protocol (`intersect_packet`) with the seed's interval methods
(t-bisection, K-bisection) and the comparison baselines (Mitchell, point sampling,
sphere tracing). Hits are differentiable with respect to params, isovalues, w and the
rays through the implicit function theorem (`attach_t`), never through the loops.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._core import (
    LANES,
    Hits,
    Plan,
    SceneFields,
    attach_t,
    check_choice,
    check_count,
    concrete,
    cpu_lanes,
    isovalues_array,
    on_host,
    pytree_dataclass,
    static_field,
)
from ..arith._extend import network_shape, value_elements
from . import _bisect
from ._auto import choose_arithmetic
from ._field import (
    VERIFY,
    as_field,
    contains_any,
    enclosure,
    extended,
    on_points,
    point_normal,
    ray_boxes,
    ray_segments,
    root_check,
)
from ._grid import (
    SignGrid,
    build_sign_grid,
    free_from,
    samples_per_segment,
    segment_span,
    values_key,
)
from ._tape_rays import DEFAULT_BUDGET, intersect_rays
from .program import long_program_tape, tape_of

__all__ = ["ImplicitSurface", "METHODS", "ARITHMETICS"]

DEFAULT_EPS = 2.0**-11


METHODS = ("t-bisection", "k-bisection", "mitchell", "sampling", "sphere")
CULLINGS = ("auto", "grid", "none")
ARITHMETICS = ("interval", "affine")
ROUNDINGS = ("fast", "outward")

# CPU packet edges from the packet table of benchmarks/bench_implicit.py on the 2-core CPU:
# interval t-bisection was fastest in 4x4 tiles (Barth sextic 0.74 Mrays/s vs 0.57 in 8x8;
# one vmap over the whole image 0.025), affine in 8x8. From 2^16 rays t-bisection runs on
# persistent lanes (affine at 512^2: 1.68 vs 0.41 Mrays/s in 8x8 tiles); K-bisection and
# the baselines have no lanes form. Other backends are unmeasured (8x8 packets).
_CPU_TILES = {"interval": 4, "affine": 8}


# Heavy functions (networks: hundreds of numbers computed per point, `value_elements`)
# gain from persistent lanes from 2^12 rays on the CPU: Spelunking's networks at 128^2,
# affine, eps 2^-10, run_s packets 8x8 -> 4096 lanes: fox 5.16 -> 1.11 s, hammer 4.82 ->
# 1.19, birdcage_occ 6.85 -> 1.55, bunny 43.4 -> 12.5, with a shorter first call too; fox
# at 64^2 1.48 -> 0.44 s. Light ones (the catalogue's polynomials: 6-39 numbers) compile
# 2-4 s longer on lanes, which small images do not win back (Barth sextic 128^2: first
# call 2.9 -> 7.0 s), so they keep packets below 2^16 rays. benchmarks/NOTES.md.
HEAVY_ELEMENTS = 256
HEAVY_LANES_FROM = 2**12


def _plan(method, arithmetic, n_rays, backend, heavy=False) -> Plan:
    if backend != "cpu":
        return Plan(tile=8)
    lanes = None
    if method == "t-bisection":
        lanes = cpu_lanes(n_rays, backend)
        if heavy and n_rays >= HEAVY_LANES_FROM:
            lanes = LANES
    return Plan(tile=_CPU_TILES[arithmetic], lanes=lanes)


_HEAVY: dict = {}  # (f, params shapes) -> bool


def _is_heavy(f, g, params) -> bool:
    """Whether f computes at least HEAVY_ELEMENTS numbers per point (a network)."""
    shapes = tuple((jnp.shape(x), str(jnp.result_type(x)))
                   for x in jax.tree_util.tree_leaves(params))
    key = (f, shapes)
    try:
        if key in _HEAVY:
            return _HEAVY[key]
    except TypeError:
        key = None
    try:
        size = value_elements(lambda x, y, z, w: g(x, y, z, w, params), 4)
    except Exception:  # noqa: BLE001 - a function that cannot be traced on scalars
        size = 0
    heavy = size >= HEAVY_ELEMENTS
    if key is not None:
        _HEAVY[key] = heavy
    return heavy


class _ImplicitOptions(SceneFields):
    """Validation and plan shared by `ImplicitSurface` and `CSG` (numeric options are
    traced fields, choices static ones)."""

    def _validate(self):
        """Normalise and check the fields (construction and every `replace`)."""
        set_ = functools.partial(object.__setattr__, self)
        check_choice("method", self.method, self._methods)
        check_choice("arithmetic", self.arithmetic, self._arithmetics)
        check_choice("rounding", self.rounding, ROUNDINGS)
        if hasattr(self, "verify"):
            check_choice("verify", self.verify, VERIFY)
        lo = jnp.asarray(self.lo, jnp.float32)
        hi = jnp.asarray(self.hi, jnp.float32)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"lo and hi must be 3-vectors, got {lo.shape} and {hi.shape}")
        for name in ("w", "eps", "delta"):
            if not hasattr(self, name):
                continue
            set_(name, jnp.asarray(getattr(self, name), jnp.float32))
            if jnp.ndim(getattr(self, name)) != 0:
                raise ValueError(f"{name} must be a scalar, got shape "
                                 f"{jnp.shape(getattr(self, name))}")
        set_("lo", lo)
        set_("hi", hi)
        if getattr(self, "lipschitz", None) is not None:
            set_("lipschitz", jnp.asarray(self.lipschitz, jnp.float32))
        _check_values(self)
        _check_static(self)

    _arithmetics = ARITHMETICS

    @property
    def has_params(self) -> bool:
        return len(jax.tree_util.tree_leaves(self.params)) > 0

    @property
    def offset_scale(self):
        return self.eps

    def coarser(self, factor):
        """Shadow rays: eps times `factor` (Sec. 6.4.6)."""
        return self.replace(eps=self.eps * factor)

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        return _plan(self.method, self.arithmetic, n_rays, backend)


@pytree_dataclass
class ImplicitSurface(_ImplicitOptions):
    """The level sets ``f = iso`` of a user function inside the box [lo, hi].

    Traced fields (changing them never recompiles):
      lo, hi: [3] corners of the domain box.
      params: pytree of arrays passed to f.
      isovalues: [I] level values drawn (each hit reports which one in `Hits.surface`).
      w: the 4th coordinate (time / morphing).
      eps: world-space length of the final piece (Eq. 6.19: depth ceil(log2(L / eps))).
      delta: range tolerance: also accept a piece whose enclosure is narrower (0: off).
      lipschitz: Lipschitz bound of f for method "sphere" (None otherwise).
    Static fields (a new value compiles anew):
      f: ``f(x, y, z[, w][, params])`` in plain jax.numpy on scalars (one point in, one
        number out; it need not broadcast over arrays: jaxiso vmaps it).
      arithmetic: "auto" (default), "interval" or "affine". "auto" measures both on
        sample ray pieces at construction and keeps the cheapest that is tight enough
        (`jaxiso.implicit._auto`); the scene then holds the choice in `arithmetic` and
        the measurement in `arithmetic_report`.
      method: "t-bisection" | "k-bisection" | "mitchell" | "sampling" | "sphere".
      rounding: "fast" (the seed) or "outward" (enclosures hold against exact arithmetic).
      normals: None (jax.grad of f) or the width of a central-difference stencil.
      max_steps: iteration bound per ray (per packet for K-bisection), None: default;
        rays that run out report no hit and steps == max_steps.
      samples: point samples per ray ("sampling").
      refine_steps: point refinement iterations ("mitchell", "sampling"), None: default.
      verify: when a piece counts as a hit (t- and K-bisection). "sign+distance"
        (default): f - iso changes sign between the piece's ends (or between two of 9
        points spread over it, so a feature thinner than a piece is kept), or its midpoint
        is within the piece's length of the level set at first order (|f - iso| <=
        length |grad f|) where the level set is singular (`_field.touches`: Newton
        converges linearly there, as to a double zero), which keeps surfaces that touch
        a level without crossing it (Steiner's whiskers, the teardrop's cusp) and leaves
        rays that graze a regular surface; "sign": a sign change only (a root is proven;
        touching surfaces are missed); "none": the enclosure alone, the seed's rule (a
        loose enclosure, e.g. of a deep network, becomes a false hit).
      culling: "auto" (default), "grid" or "none". A sign grid (`_grid.SignGrid`:
        enclosures of f on up to 64^3 cells of the box) is built at construction, and
        each ray bisects only the part of its segment near cells that may hold an
        isovalue. "auto" builds it for heavy functions (networks: `_is_heavy`) with
        t- or K-bisection when f's inputs (params, w, box) are concrete, "grid" for any
        such function. Changing f, params, w, lo, hi or rounding through `replace`
        builds it again (eps, isovalues, ... keep it: it holds for every isovalue).
        `culling_report` says what was built. Not used while delta > 0.
      sign_grid: the grid (built by the scene; None: none).
    """

    f: Callable = static_field()
    lo: jax.Array
    hi: jax.Array
    params: object = ()
    isovalues: jax.Array = (0.0,)
    w: jax.Array = 0.0
    eps: jax.Array = DEFAULT_EPS
    arithmetic: str = static_field("auto")
    method: str = static_field("t-bisection")
    delta: jax.Array = 0.0
    lipschitz: jax.Array | None = None
    rounding: str = static_field("fast")
    normals: float | None = static_field(None)
    max_steps: int | None = static_field(None)
    samples: int = static_field(64)
    refine_steps: int | None = static_field(None)
    verify: str = static_field("sign+distance")
    arithmetic_report: str = static_field("")
    culling: str = static_field("auto")
    sign_grid: SignGrid | None = None
    culling_report: str = static_field("")

    _methods = METHODS
    _arithmetics = ARITHMETICS + ("auto",)

    def __post_init__(self):
        self._validate()

    def _validate(self):
        if not callable(self.f):
            raise TypeError(f"f must be callable, got {type(self.f).__name__}")
        object.__setattr__(self, "isovalues", isovalues_array(self.isovalues))
        super()._validate()
        # fail early on a bad signature
        as_field(self.f, self.has_params)
        if self.arithmetic == "auto":
            # a long program is measured on its tape: the straight extension would take
            # minutes to compile
            pick, report = choose_arithmetic(self.f, self.field, self.lo, self.hi, self.w,
                                             self.params, self.rounding, self._long_tape())
            object.__setattr__(self, "arithmetic", pick)
            object.__setattr__(self, "arithmetic_report", report)
        check_choice("culling", self.culling, CULLINGS)
        if self.sign_grid is None:
            grid, report = _sign_grid(self)
            object.__setattr__(self, "sign_grid", grid)
            object.__setattr__(self, "culling_report", report)

    def replace(self, **changes):
        """As `SceneFields.replace`; the sign grid is built again when a field it depends
        on changes."""
        if changes.keys() & _GRID_INPUTS and "sign_grid" not in changes:
            changes = {**changes, "sign_grid": None}
        return super().replace(**changes)

    @property
    def field(self):
        """``g(x, y, z, w, params)``."""
        return as_field(self.f, self.has_params)

    def _params_tree(self):
        """The treedef of params when every leaf is a scalar (tape coordinates), False
        when some leaf is an array (no tape), None without params."""
        if not self.has_params:
            return None
        leaves, tree = jax.tree_util.tree_flatten(self.params)
        return tree if all(jnp.ndim(x) == 0 for x in leaves) else False

    def _long_tape(self):
        """f's instruction tape when f is a long program with scalar params or none
        (else None)."""
        tree = self._params_tree()
        return None if tree is False else long_program_tape(self.f, tree)

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """Long programs (`program.TAPE_CROSSOVER` instructions or more) in t-/K-bisection
        with the seed's rounding run on the tape path (interval or affine); others as
        measured per arithmetic and backend."""
        if (self.method in ("t-bisection", "k-bisection") and self.rounding == "fast"
                and self._long_tape() is not None):
            return Plan(tile=16, tape=True)
        heavy = self.method == "t-bisection" and _is_heavy(self.f, self.field, self.params)
        return _plan(self.method, self.arithmetic, n_rays, backend, heavy)

    def intersect_tape(self, rays, t_min, t_max, stats: dict | None = None,
                       prune: bool = True, budget: int = DEFAULT_BUDGET) -> Hits:
        """First hits of rays [N] on the tape path (`Plan.tape`). The traversal runs on
        the host with concrete values: eagerly (also under eager `jax.grad` / `jvp`, on
        the primal values), or under jit / vmap in a `jax.pure_callback`. Differentiated,
        t gets its implicit-function-theorem derivative from the straight point function
        at the hits (normals too), which compiles only when derivatives are taken."""
        tree = self._params_tree()
        tape = self._long_tape()
        if tape is None and tree is not False:
            with jax.ensure_compile_time_eval():  # concrete under a jit trace too
                tape = tape_of(self.f, tree)
        if tape is None:
            raise ValueError("the tape path runs params that are pytrees of scalars only")
        primal = jax.lax.stop_gradient((self, rays, t_min, t_max))
        leaves = jax.tree_util.tree_leaves((self, rays, t_min, t_max))
        if all(on_host(x) for x in leaves):
            hits = intersect_rays(primal[0], tape, *primal[1:], stats=stats, prune=prune,
                                  budget=budget)
        else:
            hits = _tape_callback(tape, primal, stats, prune, budget)
        if not any(isinstance(x, jax.core.Tracer) for x in leaves):
            return hits
        t, normal = _differentiable_hits(self.normals, (self, rays), hits)
        return dataclasses.replace(hits, t=t, normal=normal)

    def __call__(self, x, y, z):
        """The field f at points x, y, z (arrays of any broadcastable shapes, evaluated
        point by point through `on_points`; the isovalues are not subtracted)."""
        return on_points(self.field)(x, y, z, self.w, self.params)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of one packet of rays [P] (the scene protocol, `jaxiso.Scene`)."""
        _check_lanes(self.method, lanes)
        scene = jax.lax.stop_gradient(self)
        t0, t1, inside, p, D = ray_segments(rays, scene.lo, scene.hi, t_min, t_max)
        empty = None
        if scene.sign_grid is not None:
            t0, t1, inside, p, D, empty = _near_possible_cells(scene, t0, t1, inside, p, D)
        g = scene.field
        if self.method in ("t-bisection", "k-bisection"):
            F = extended(g, self.arithmetic, self.rounding)
            res = _interval_method(F, scene, p, D, inside, lanes, empty)
        else:
            from . import _baselines
            res = _baselines.run(self.method, g, scene, p, D, inside, scene.eps,
                                 self.arithmetic, self.rounding, self.max_steps,
                                 **_method_options(scene))
        t_raw = jnp.where(res.hit, t0 + res.s * (t1 - t0), jnp.inf)
        return finish_hits(g, self, rays, t_raw, res.hit, res.steps, self.normals)


_GRID_INPUTS = frozenset({"f", "lo", "hi", "w", "params", "rounding", "method", "culling"})
_GRIDS: dict = {}  # (f, rounding, values digest) -> (grid, report); a few recent ones
_GRIDS_KEPT = 8


def _sign_grid(scene):
    """(SignGrid or None, report) for a scene under construction (`culling`)."""
    if scene.culling == "none":
        return None, ""
    if scene.method not in ("t-bisection", "k-bisection"):
        return None, f"no sign grid: method {scene.method!r} does not bisect"
    inputs = (scene.params, scene.w, scene.lo, scene.hi, scene.isovalues)
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(inputs)):
        return None, "no sign grid: params, w or the box are traced values"
    if scene.culling == "auto" and not _is_heavy(scene.f, scene.field, scene.params):
        return None, "no sign grid: f is light (auto builds one for networks)"
    if scene.culling == "auto" and not _network_like(scene):
        return None, ("no sign grid: f is no network (auto builds one for functions of "
                      f"at most {GRID_EQUATIONS} operations, some on vectors)")
    key = (scene.f, scene.rounding, values_key(inputs))
    if key not in _GRIDS:
        while len(_GRIDS) >= _GRIDS_KEPT:
            _GRIDS.pop(next(iter(_GRIDS)))
        _GRIDS[key] = build_sign_grid(scene.field, scene.lo, scene.hi, scene.w,
                                      scene.params, scene.isovalues, scene.rounding,
                                      key=(scene.f, scene.has_params))
    return _GRIDS[key]


# A sign grid compiles f's affine extension with fresh symbols: cheap for networks (fox:
# 30 operations), minutes for long scalar programs, which gain nothing from the symbols
# (they only take the errors of vector operations) and run on the tape path.
GRID_EQUATIONS = 256


def _network_like(scene) -> bool:
    g = scene.field
    try:
        eqns, vectors = network_shape(lambda x, y, z, w: g(x, y, z, w, scene.params), 4)
    except Exception:  # noqa: BLE001 - a function that cannot be traced on scalars
        return False
    return eqns <= GRID_EQUATIONS and vectors > 0


def _near_possible_cells(scene, t0, t1, inside, p, D):
    """The ray segments cut to the part near the sign grid's possible cells (all of it
    while delta > 0: a narrow enclosure is accepted there without holding an isovalue),
    and the stretches of them that the grid shows empty: (ahead, aux) for the walk
    (`_bisect.t_bisect_lanes`; none while delta > 0)."""
    span = segment_span(scene.sign_grid, scene.lo, scene.hi, scene.isovalues, p, D, inside)
    off = scene.delta > 0
    s0 = jnp.where(off, 0.0, span.s0)
    s1 = jnp.where(off, 1.0, span.s1)
    inside = jnp.where(off, inside, span.inside)
    length = t1 - t0
    # the walk's s in [0, 1] is the span's; the marks count gaps of the whole segment
    gaps = samples_per_segment(scene.sign_grid) - 1
    u0, du = s0 * gaps, (s1 - s0) * gaps
    marks = jnp.where(off, ~jnp.uint32(0), span.marks)
    return (t0 + s0 * length, t0 + s1 * length, inside, p + s0[:, None] * D,
            D * (s1 - s0)[:, None], (_grid_empty_until, (marks, u0, du)))


# The walk's position in the grid's sample coordinates is rounded (and so are the span's
# ends and the cut segment): the stretch it leaps is shortened by this many samples
_EMPTY_MARGIN = 1e-3


def _grid_empty_until(aux, s):
    """``ahead`` of the walk from a sign grid: the end of the empty stretch from s on
    (s itself or less where s's gap may hold a crossing; inf past the last one)."""
    marks, u0, du = aux
    u = u0 + s * du
    free = free_from(marks, u - _EMPTY_MARGIN) - _EMPTY_MARGIN
    return jnp.where(du > 0, (free - u0) / jnp.where(du > 0, du, 1.0), s)


def _method_options(scene):
    if scene.method == "sphere":
        return dict(lipschitz=scene.lipschitz)
    opts = {} if scene.refine_steps is None else dict(refine_steps=scene.refine_steps)
    if scene.method == "sampling":
        opts["samples"] = scene.samples
    return opts


def _check_lanes(method, lanes):
    if lanes is not None and method != "t-bisection":
        raise ValueError(f"persistent lanes run t-bisection only; method {method!r} runs in "
                         "packets: pass plan=jaxiso.Plan(tile=...) without lanes")


def _interval_method(F, scene, p, D, inside, lanes=None, empty=None):
    tol = scene.delta

    def test(p, D, s0, s1):
        boxes = ray_boxes(p, D, s0, s1, scene.arithmetic)
        r = enclosure(F, boxes, scene.w, scene.params, scene.arithmetic)
        possible, finite = contains_any(r, scene.isovalues)
        return _bisect.BoxTest(possible, finite, (r.hi - r.lo) < tol)

    verify = root_check(scene.field, scene.w, scene.params, scene.isovalues, scene.verify)
    heavy = _is_heavy(scene.f, scene.field, scene.params)
    return run_bisection(scene.method, test, p, D, inside, scene.eps, scene.max_steps,
                         lanes, verify, lanes is not None and heavy, empty,
                         HEAVY_VERIFY_LEVELS if heavy else 0)


# Heavy functions' walks stop this many levels above d_max, and verification finds the hit
# among the piece's 2^levels pieces at d_max by point evaluations (`_bisect.first_verified`)
HEAVY_VERIFY_LEVELS = 2


def run_bisection(method, test, p, D, inside, eps, max_steps=None, lanes=None, verify=None,
                  heavy=False, empty=None, verify_levels=0):
    """Drive t- or K-bisection over a packet with a box test ``test(p, D, s0, s1)`` and
    an optional root check ``verify(p, D, s0, s1)`` (`root_check`). `heavy` (a costly
    function, e.g. a network) changes two things on lanes: the walks start at the depth
    `_bisect.start_depth` measures (on the catalogue at 512^2 that gained nothing clear
    and cost 0.4-1.4 s of compile), and the narrowest lane phase is 64 wide, not 32
    (every phase compiles the walk again: on the networks at 128^2 the 32-lane phase cost
    1.3-1.4 s of first call and saved 1-2% of the run). `empty`: None or (ahead, aux),
    stretches of the rays that hold no root, which t-bisection's walks leap
    (`_bisect.t_bisect_lanes`; K-bisection's shared pieces do not). `verify_levels`:
    t-bisection's walks with verify accept pieces that many levels above d_max and take
    the first verified of their pieces at d_max (`_bisect.t_bisect`)."""
    length = jnp.linalg.norm(D, axis=-1)
    d_max = _bisect.depth_for(length, eps)
    if max_steps is None:
        # enough for eps 2^-22 with IA on the Barth decic (1920 was not); a K-bisection
        # packet visits the union of its rays' candidate pieces
        max_steps = 256 * _bisect.MAX_DEPTH * (8 if method == "k-bisection" else 1)
    if method == "t-bisection" and lanes is not None:
        d_start = _bisect.start_depth(test, p, D, d_max, inside) if heavy else 0
        ahead, aux = (None, None) if empty is None else empty
        return _bisect.t_bisect_lanes(test, p, D, d_max, inside, lanes, max_steps, verify,
                                      d_start, min_width=64 if heavy else 32, ahead=ahead,
                                      aux=aux, verify_levels=verify_levels)
    if method == "t-bisection":
        return _t_bisection(test, p, D, d_max, inside, max_steps, verify, empty,
                            verify_levels)
    if method == "k-bisection":
        return _k_bisection(test, p, D, d_max, inside, length, max_steps, verify)
    raise ValueError(f"unknown bisection method {method!r}")


def _t_bisection(test, p, D, d_max, inside, max_steps, verify, empty=None,
                 verify_levels=0):
    """Per-ray t-bisection under vmap (one batched loop per packet)."""
    ahead, aux = (None, None) if empty is None else empty

    def one(p, D, d_max, active, aux):
        check = None if verify is None else functools.partial(verify, p, D)
        leap = None if ahead is None else functools.partial(ahead, aux)
        return _bisect.t_bisect(functools.partial(test, p, D), d_max, active, max_steps,
                                check, leap, verify_levels)
    return jax.vmap(one)(p, D, d_max, inside, aux)


def _k_bisection(test, p, D, d_max, inside, length, max_steps, verify):
    """K-bisection for the rays that march coherently along the packet's dominant axis;
    the rest (opposite or too oblique K direction) fall back to t-bisection."""
    mean = jnp.sum(jnp.where(inside[:, None], D, 0.0), axis=0)
    axis = jnp.argmax(jnp.abs(mean))
    dk = jnp.take(D, axis, axis=1)
    sign = jnp.sign(jnp.take(mean, axis))
    coherent = inside & (jnp.sign(dk) == sign) & (jnp.abs(dk) >= 0.25 * length)
    k_enter = jnp.take(p, axis, axis=1)
    check = None if verify is None else functools.partial(verify, p, D)
    res_k = _bisect.k_bisect(lambda s0, s1: test(p, D, s0, s1), k_enter, k_enter + dk,
                             d_max, coherent, max_steps, check)
    res_t = _t_bisection(test, p, D, d_max, inside & ~coherent, max_steps, verify)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(coherent, a, b), res_k, res_t)


def _tape_callback(tape, primal, stats, prune, budget) -> Hits:
    """`intersect_rays` on values that exist only at run time (under jit / vmap): the
    host driver runs in a `jax.pure_callback` on the concrete values (vmap: once per
    batch element)."""
    flat, tree = jax.tree_util.tree_flatten(primal)
    n = primal[1].shape[0]
    out = Hits(t=jax.ShapeDtypeStruct((n,), jnp.float32),
               hit=jax.ShapeDtypeStruct((n,), jnp.bool_),
               normal=jax.ShapeDtypeStruct((n, 3), jnp.float32),
               surface=jax.ShapeDtypeStruct((n,), jnp.int32),
               steps=jax.ShapeDtypeStruct((n,), jnp.int32))

    def run(*values):
        scene, rays, t_min, t_max = jax.tree_util.tree_unflatten(
            tree, [jnp.asarray(v) for v in values])
        hits = intersect_rays(scene, tape, rays, t_min, t_max, stats=stats, prune=prune,
                              budget=budget)
        return jax.tree_util.tree_map(np.asarray, hits)

    return jax.pure_callback(run, out, *flat, vmap_method="sequential")


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _differentiable_hits(normals, scene_rays, hits: Hits):
    """(t, normal) of `hits` found on the tape path, with the derivatives of
    `finish_hits` (the implicit function theorem on the straight point function) with
    respect to the scene and rays: a custom JVP, so that a jitted call that is not
    differentiated never compiles the point function of a long program."""
    return hits.t, hits.normal


@_differentiable_hits.defjvp
def _differentiable_hits_jvp(normals, primals, tangents):
    scene_rays, hits = primals

    def finished(scene_rays):
        scene, rays = scene_rays
        h = finish_hits(scene.field, scene, rays, hits.t, hits.hit, hits.steps, normals)
        return h.t, h.normal

    _, (dt, dnormal) = jax.jvp(finished, (scene_rays,), (tangents[0],))
    return (hits.t, hits.normal), (dt, dnormal)


def finish_hits(g, scene, rays, t_raw, hit, steps, normals, which=None) -> Hits:
    """Which isovalue (unless `which` is given: then g vanishes on every part), a
    differentiable t and the normal of each hit (g, a point function, is evaluated on
    the packet through `on_points`)."""
    o, d = rays.origin, rays.direction
    safe_t = jnp.where(hit, t_raw, 0.0)
    if which is None:
        p_raw = jax.lax.stop_gradient(o + safe_t[:, None] * d)
        val = on_points(g)(p_raw[:, 0], p_raw[:, 1], p_raw[:, 2], scene.w, scene.params)
        iso = scene.isovalues
        which = jnp.argmin(jnp.abs(val[:, None] - iso[None, :]), axis=-1).astype(jnp.int32)
        level = iso[which]
    else:
        level = jnp.zeros(t_raw.shape, jnp.float32)
    t = attach_t(g, safe_t, o, d, scene.w, scene.params, level, hit)
    pts = o + t[:, None] * d
    normal = point_normal(g, pts, scene.w, scene.params, d, stencil=normals)
    return Hits(t=jnp.where(hit, t, jnp.inf), hit=hit,
                normal=jnp.where(hit[:, None], normal, 0.0),
                surface=jnp.where(hit, which, -1), steps=steps.astype(jnp.int32))




def _check_values(scene) -> None:
    """Concrete numeric fields (traced ones are checked where they were concrete)."""
    lo, hi, eps = concrete(scene.lo), concrete(scene.hi), concrete(scene.eps)
    if lo is not None and hi is not None:
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError(f"the domain box must be finite, got lo={lo} hi={hi}")
        if np.any(lo >= hi):
            raise ValueError(f"the domain box needs lo < hi on every axis, got lo={lo} "
                             f"hi={hi}")
    if eps is not None and not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be a finite positive length, got {eps}")
    if lo is not None and hi is not None and eps is not None:
        _check_depth(lo.astype(np.float64), hi.astype(np.float64), float(eps))
    for name in ("isovalues", "w", "delta", "lipschitz"):
        v = concrete(getattr(scene, name, None))
        if v is not None and v.dtype != object and not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite, got {v}")
    for path, leaf in jax.tree_util.tree_leaves_with_path(scene.params):
        v = concrete(leaf)
        if v is not None and np.issubdtype(v.dtype, np.inexact) and not np.all(np.isfinite(v)):
            raise ValueError(f"params{jax.tree_util.keystr(path)} must be finite: "
                             f"{int(np.size(v) - np.isfinite(v).sum())} NaN or inf values")
    delta = concrete(getattr(scene, "delta", 0.0))
    if delta is not None and delta < 0:
        raise ValueError(f"delta must be >= 0 (0: no range tolerance), got {delta}")
    lip = getattr(scene, "lipschitz", None)
    lip = concrete(lip) if lip is not None else None
    if lip is not None and lip.dtype != object and not lip > 0:
        raise ValueError(f"lipschitz must be positive, got {lip}")


def _check_depth(lo, hi, eps) -> None:
    """eps must be reachable: at most 2^MAX_DEPTH pieces per ray (int32 positions) and no
    finer than float32 resolves the box's coordinates."""
    length = float(np.linalg.norm(hi - lo))
    if not length < float(np.finfo(np.float32).max):
        raise ValueError(f"the domain box diagonal {length:.3g} overflows float32; "
                         "scale the model down")
    finest = length * 2.0 ** -_bisect.MAX_DEPTH
    ulp = float(np.max(np.maximum(np.abs(lo), np.abs(hi)))) * 2.0**-23
    if eps < max(finest, ulp):
        why = (f"more than 2^{_bisect.MAX_DEPTH} bisection pieces across the domain's "
               f"diagonal {length:.3g}" if finest >= ulp else
               f"a piece below float32 resolution ({ulp:.3g}) at the domain's coordinates "
               f"(up to {ulp * 2**23:.3g})")
        raise ValueError(f"eps={eps:.3g} needs {why}; use eps >= {max(finest, ulp):.3g}, or "
                         "a smaller box nearer the origin")


def _check_static(scene) -> None:
    n = scene.normals
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, float))
                          or not np.isfinite(n) or n <= 0):
        raise ValueError(f"normals must be None (jax.grad) or a positive stencil width, "
                         f"got {n!r}")
    check_count("max_steps", scene.max_steps)
    check_count("refine_steps", getattr(scene, "refine_steps", None))
    if hasattr(scene, "samples"):
        check_count("samples", scene.samples, least=2, optional=False)
    if scene.method == "sphere" and getattr(scene, "lipschitz", None) is None:
        raise ValueError("method 'sphere' needs a Lipschitz bound of f: "
                         "lipschitz=L on the scene")
