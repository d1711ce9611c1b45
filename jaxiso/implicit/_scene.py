"""`ImplicitSurface`: the zero set (or several level sets) of a plain-JAX function.

Implements the scene protocol (`intersect_packet`) with the methods of the registry
(`_methods.METHODS`: the seed's t-/K-bisection and the comparison baselines). Hits are
differentiable with respect to params, isovalues, w and the rays through the implicit
function theorem (`attach_t`), never through the loops. Constructing a scene only checks
its fields; `prepared` (done by the first `intersect` / `render`) does the expensive work.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from .._core import (
    DEFAULT_MEMORY_BUDGET,
    Hits,
    Plan,
    WithStaticLeaves,
    check_choice,
    isovalues_array,
    pytree_dataclass,
    static_field,
)
from ..arith import ARITHMETICS
from ._culling import GRID_INPUTS, near_possible_cells
from ._field import as_field, on_points, ray_segments
from ._grid import SignGrid
from ._hits import finish_hits
from ._methods import METHODS
from ._options import CULLINGS, DEFAULT_EPS, ImplicitOptions
from ._policy import is_heavy, packet_plan
from ._polynomial import ChebyshevTable
from ._prepare import FunctionFacts, params_structure, prepare_surface
from ._tape_path import intersect_tape
from ._tape_rays import tape_tile
from .program import long_program_tape, tape_of

__all__ = ["ImplicitSurface", "METHODS", "ARITHMETICS"]



@pytree_dataclass
class ImplicitSurface(ImplicitOptions):
    """The level sets ``f = iso`` of a user function inside the box [lo, hi].

    Traced fields (changing them never recompiles):
      lo, hi: [3] corners of the domain box.
      params: pytree of arrays passed to f. Leaves that are not arrays (an equinox
        module's activation function) are static: params is then held as a
        `jaxiso._core.WithStaticLeaves` of it, and f receives it as given.
      isovalues: [I] level values drawn (each hit reports which one in `Hits.surface`).
      w: the 4th coordinate (time / morphing).
      eps: world-space length of the final piece (Eq. 6.19: depth ceil(log2(L / eps))).
      delta: range tolerance: also accept a piece whose enclosure is narrower (0: off).
      lipschitz: Lipschitz bound of f for method "sphere" (None otherwise).
    Static fields (a new value compiles anew):
      f: ``f(x, y, z[, w][, params])`` in plain jax.numpy on scalars (one point in, one
        number out; it need not broadcast over arrays: jaxiso vmaps it).
      arithmetic: "auto" (default), "interval", "affine" or "polynomial". "auto" picks
        "polynomial" for a polynomial f of degree 1-16 (read from its jaxpr), and
        otherwise measures interval and affine on sample ray pieces when the scene is
        prepared and keeps the cheapest that is tight enough (`jaxiso.implicit._auto`);
        the prepared scene holds the choice in `arithmetic` (kept by `replace`) and the
        reason in `arithmetic_report`. "polynomial" encloses a ray piece by f's
        Chebyshev coefficients along it, from degree + 1 point values
        (`jaxiso.implicit._polynomial`; boxes elsewhere, such as sign grids, in
        interval arithmetic).
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
        enclosures of f on up to 64^3 cells of the box) is built when the scene is
        prepared, and each ray bisects only the part of its segment near cells that may
        hold an isovalue. "auto" builds it for heavy functions (networks:
        `_policy.is_heavy`) with t- or K-bisection when f's inputs (params, w, box) are
        concrete, "grid" for any such function. `replace` of f, params, w, lo, hi or
        rounding drops it (the next preparation builds it again; eps, isovalues, ...
        keep it: it holds for every isovalue). `culling_report` says what was built.
        Not used while delta > 0.
    Set by preparation (`prepared`; `replace` keeps them while their inputs stay):
      sign_grid: the grid (None: none, or not prepared).
      polynomial_table: arithmetic "polynomial" on an f of `_polynomial.TABLE_FROM`
        equations or more: f's Chebyshev coefficients on the box
        (`_polynomial.ChebyshevTable`), which the bisection evaluates instead of f's
        own code (hits, normals and derivatives are finished on f).
      facts: what was learnt of f (`_prepare.FunctionFacts`: network, long program).
      ready: the scene is prepared (intersect and render do no further work).
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
    polynomial_table: ChebyshevTable | None = None
    facts: FunctionFacts | None = static_field(None)
    ready: bool = static_field(False)

    arithmetics = ARITHMETICS + ("polynomial", "auto")

    def __post_init__(self):
        self._validate()

    def _validate(self):
        """Checks only: types, shapes, choices, finite values, f's signature."""
        if not callable(self.f):
            raise TypeError(f"f must be callable, got {type(self.f).__name__}")
        object.__setattr__(self, "isovalues", isovalues_array(self.isovalues))
        if WithStaticLeaves.needed(self.params):  # e.g. an equinox module as params
            object.__setattr__(self, "params", WithStaticLeaves(self.params))
        super()._validate()
        check_choice("culling", self.culling, CULLINGS)
        as_field(self.f, self.has_params)  # fail early on a bad signature

    def replace(self, **changes):
        """As `SceneFields.replace`; drops the prepared results whose inputs change (the
        sign grid, the facts of f, the arithmetic when set to "auto")."""
        changes = dict(changes)
        if "f" in changes or ("params" in changes and params_structure(changes["params"])
                              != params_structure(self.params)):
            changes.setdefault("facts", None)
        if changes.keys() & GRID_INPUTS:
            changes.setdefault("sign_grid", None)
            changes.setdefault("polynomial_table", None)
        stale = (changes.get("facts", self.facts) is None
                 or (changes.get("sign_grid", self.sign_grid) is None
                     and changes.keys() & GRID_INPUTS)
                 or changes.get("arithmetic") == "auto")
        if stale:
            changes.setdefault("ready", False)
        return super().replace(**changes)

    def prepared(self) -> ImplicitSurface:
        """This scene ready to trace: the facts of f learnt, "auto" arithmetic measured,
        the sign grid built (`_prepare`); a prepared scene returns itself. Under a trace
        nothing can be measured (see `_auto.choose_arithmetic`): prepare outside it."""
        return self if self.ready else prepare_surface(self)

    @property
    def field(self):
        """``g(x, y, z, w, params)``."""
        return as_field(self.f, self.has_params)

    def params_treedef(self):
        """The treedef of params when every leaf is a scalar (tape coordinates), False
        when some leaf is an array (no tape), None without params."""
        if not self.has_params:
            return None
        leaves, tree = jax.tree_util.tree_flatten(self.params)
        return tree if all(jnp.ndim(x) == 0 for x in leaves) else False

    def long_tape(self):
        """f's instruction tape when f is a long program with scalar params or none
        (else None)."""
        if self.facts is not None:
            return self.facts.tape
        tree = self.params_treedef()
        return None if tree is False else long_program_tape(self.f, tree)

    def is_heavy(self) -> bool:
        """Whether the bisection's function is a network (`_policy.is_heavy`): a long
        polynomial traced through its Chebyshev table (`polynomial_table`) is not, the
        table costs (degree + 1)^3 products a point whatever f's length (8 x 150 at 64^2:
        first intersect 14.0 s as heavy, on lanes; 5.3 s not)."""
        if self.polynomial_table is not None:
            return False
        return self.facts.heavy if self.facts is not None else is_heavy(self.field,
                                                                        self.params)

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """Long programs (`program.TAPE_CROSSOVER` instructions or more) in t-/K-bisection
        with the seed's rounding run on the tape path (interval or affine); others as
        measured per arithmetic and backend (`_policy.packet_plan`)."""
        method = METHODS[self.method]
        # a polynomial has no min / max for the tape to prune, and its enclosure costs
        # as many point evaluations as its degree (`_polynomial`): the straight path
        if (method.bisects and self.rounding == "fast" and self.long_tape() is not None
                and self.arithmetic != "polynomial"):
            return Plan(tile=tape_tile(n_rays), tape=True)
        heavy = method.lanes and self.is_heavy()
        arithmetic = "affine" if self.arithmetic == "auto" else self.arithmetic
        return packet_plan(method.lanes, arithmetic, n_rays, backend, heavy)

    def intersect_tape(self, rays, t_min, t_max, stats: dict | None = None,
                       prune: bool = True, budget: int = DEFAULT_MEMORY_BUDGET) -> Hits:
        """First hits of rays [N] on the tape path (`Plan.tape`). The traversal runs on
        the host with concrete values: eagerly (also under eager `jax.grad` / `jvp`, on
        the primal values), or under jit / vmap in a `jax.pure_callback`. Differentiated,
        t gets its implicit-function-theorem derivative from the straight point function
        at the hits (normals too), which compiles only when derivatives are taken."""
        scene = self.prepared()
        tree = scene.params_treedef()
        tape = scene.long_tape()
        if tape is None and tree is not False:
            with jax.ensure_compile_time_eval():  # concrete under a jit trace too
                tape = tape_of(scene.f, tree)
        if tape is None:
            raise ValueError("the tape path runs params that are pytrees of scalars only")
        return intersect_tape(scene, tape, rays, t_min, t_max, stats, prune, budget)

    def __call__(self, x, y, z):
        """The field f at points x, y, z (arrays of any broadcastable shapes, evaluated
        point by point through `on_points`; the isovalues are not subtracted)."""
        return on_points(self.field)(x, y, z, self.w, self.params)

    def intersect_packet(self, rays, t_min, t_max, *, lanes: int | None = None) -> Hits:
        """First hits of one packet of rays [P] (the scene protocol, `jaxiso.Scene`)."""
        self.check_lanes(lanes)
        me = self.prepared()
        scene = jax.lax.stop_gradient(me)
        t0, t1, inside, p, D = ray_segments(rays, scene.lo, scene.hi, t_min, t_max)
        empty = None
        if scene.sign_grid is not None:
            t0, t1, inside, p, D, empty = near_possible_cells(scene, t0, t1, inside, p, D)
        g = scene.field
        # a long polynomial is traced through its Chebyshev table in the kernel (a few
        # small products per copy, whatever f's length); hits are finished on f itself
        kernel_g = g if scene.polynomial_table is None else scene.polynomial_table
        res = METHODS[scene.method].kernel(kernel_g, scene, p, D, inside, lanes=lanes,
                                           empty=empty)
        t_raw = jnp.where(res.hit, t0 + res.s * (t1 - t0), jnp.inf)
        return finish_hits(g, me, rays, t_raw, res.hit, res.steps, me.normals)
