"""`arithmetic="auto"`: pick the cheapest arithmetic that is tight enough for a scene.

When a scene is prepared (`ImplicitSurface.prepared`, done by its first intersect or
render) its f is extended in interval and in affine arithmetic and both are evaluated on
sample pieces of rays (32 pieces, 1/64 of the domain's diagonal long, at seeded random
places and directions in the box: the scale where bisection spends most of its steps).
Each enclosure's width is compared with f's true range on the piece (9 point samples, a
lower bound of it). Affine costs about twice an interval evaluation per piece, so it is
chosen when its median width ratio is more than 2x smaller (networks: interval
enclosures do not shrink with the piece; polynomials: they are within 2x).
Long programs (the tape path) are measured the same way on their tape, where affine costs
about 8x an interval evaluation (`TAPE_COST_RATIO`).

Compile time is part of the choice: the affine rules are 5-10x the interval rules in
code (a product is ~200 jaxpr equations against ~30), and XLA's compile time grows
faster than linearly with code size. An affine extension of more than
`AFFINE_MAX_EQUATIONS` equations (counted on the traced measurement, before any compile)
is not compiled where interval's enclosures are within `INTERVAL_GOOD_ENOUGH` times the
true range (polynomials): such an f gets interval, and the report says why. Where
interval is hopeless (networks) affine is compiled and measured whatever its length.
"""

from __future__ import annotations

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np

from .._core import concrete, on_points
from ..arith import Interval, aa, equation_count
from ..arith import tape as _tape
from ._field import enclosure, extended, ray_boxes
from ._grid import values_key
from ._memo import BoundedCache
from ._polynomial import MAX_DEGREE
from ._progress import Progress

N_PIECES = 32
PIECE = 2.0**-6   # of the domain's diagonal
SAMPLES = 9
COST_RATIO = 2.0  # affine / interval evaluation cost per piece
# The same on the tape path, measured (`_tape.evaluate`, 64 x 8 boxes, CPU): affine 246-300
# ms against interval 32 ms on a 1,425-instruction CSG tape, 357-398 vs 45 ms on a
# 2,175-instruction MLP. The evaluator computes every opcode's rule at every step and
# selects, and the affine rules (guards, Chebyshev, min/max through relu) are long.
TAPE_COST_RATIO = 8.0
# The largest affine measurement program (jaxpr equations, nested ones included) that is
# compiled. Measured on the 2-core CPU (benchmarks/NOTES.md, session 23): the catalogue's
# surfaces are 0.6k-7.3k equations and compile in 0.1-4.1 s; random polynomials of 20-30
# terms are 18.8k-28.3k and compile in 12.8-34.5 s, and their renders (twice the code
# and more) did not finish in 15 minutes; interval renders them.
AFFINE_MAX_EQUATIONS = 8000
# ... unless interval is hopeless: a long affine program is still compiled where
# interval's median enclosure width is over this many times the true range. Networks
# (200-10,000x, session 23) would otherwise get interval and a render 30x slower (an
# 8 x 32 elu network written with jnp: 11,973 affine equations); polynomials are within
# a few times.
INTERVAL_GOOD_ENOUGH = 16.0
# Polynomials from this degree get arithmetic "polynomial" (`_polynomial`). Measured on
# the catalogue at 128^2 (benchmarks/NOTES.md, session 29): first calls 1.1-1.6 s
# against affine's 1.8-8.6 s, calls as fast or faster from degree 4 (Barth decic 0.09
# against 0.48 s); a quadric's affine form is as tight for fewer operations (sphere
# 14 ms a call against 28 ms), so quadrics are measured as before.
AUTO_MIN_DEGREE = 3


# choices by (f, rounding, box): the choice is a property of the function on its box,
# so scenes with other params or w (a slider, `replace`) reuse it, as `replace` keeps it
_CHOICES = BoundedCache("arithmetic choices", 32)


def choose_arithmetic(f, g, lo, hi, w, params, rounding: str, tape=None, degree=None
                      ) -> tuple[str, str]:
    """(arithmetic, report) for the field g (of the user's f) on the box [lo, hi] at w
    and params. A polynomial f (`degree`, its total degree in x, y, z, from
    `AUTO_MIN_DEGREE` to `_polynomial.MAX_DEGREE`) with the "fast" rounding gets
    "polynomial" unmeasured: its
    Chebyshev enclosure is exact up to rounding for linear f and converges quadratically,
    and it compiles as f's point evaluations do. Otherwise, for a long program, `tape`
    (its instruction tape), measured on the tape
    evaluator; measured once per f, rounding and box (`_CHOICES`, emptied by
    `jaxiso.clear_caches`). Traced inputs (a scene prepared under jit) are not
    measured: they get "affine", which converges on every f jaxiso
    extends ("interval" for a long program, the tape path's first arithmetic, or where
    the affine extension is over `AFFINE_MAX_EQUATIONS`: nothing tells there whether
    interval is good enough), and the report says so (prepare the scene outside the
    trace, `ImplicitSurface.prepared`)."""
    if rounding == "fast" and degree is not None and AUTO_MIN_DEGREE <= degree <= MAX_DEGREE:
        return "polynomial", (f"auto: polynomial (f is a polynomial of degree {degree} in "
                              f"x, y, z: each ray piece is enclosed by f's Chebyshev "
                              f"coefficients along it, from {degree + 1} point values)")
    leaves = [lo, hi, w] + jax.tree_util.tree_leaves(params)
    if any(concrete(x) is None for x in leaves):
        if tape is not None:
            return "interval", "auto: interval (prepared under a trace: nothing measured)"
        # the count depends on shapes only: once per f, rounding and shapes (a traced
        # optimisation loop prepares its scene at every step)
        leaves, tree = jax.tree_util.tree_flatten((w, params))
        key = (f, rounding, tree, tuple((jnp.shape(v), str(jnp.result_type(v)))
                                        for v in leaves))
        too_long = _CHOICES.get(key, lambda: _width_programs(g, w, params, rounding)[1])
        if too_long:
            return "interval", f"auto: interval ({too_long}; prepared under a trace)"
        return "affine", "auto: affine (prepared under a trace: nothing measured)"
    progress = Progress()

    def measure():
        if tape is None:
            return _measure(g, lo, hi, w, params, rounding)
        return _measure_tape(tape, lo, hi, [w, *jax.tree_util.tree_leaves(params)])

    choice = _CHOICES.get((f, rounding, values_key(lo, hi)), measure)
    progress.done(choice[1])
    return choice


def _pieces(lo, hi):
    """The sample pieces p + s D, s in [0, 1] (p, D: [N_PIECES, 3]) and their SAMPLES
    points [N_PIECES, SAMPLES, 3]."""
    rng = np.random.default_rng(0)
    lo_, hi_ = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    diag = float(np.linalg.norm(hi_ - lo_))
    centre = lo_ + rng.uniform(0.1, 0.9, (N_PIECES, 3)) * (hi_ - lo_)
    direction = rng.normal(size=(N_PIECES, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # numpy, not eager jnp: each eager op compiles on its first call (a second in all)
    D = (direction * PIECE * diag).astype(np.float32)
    p = centre.astype(np.float32) - np.float32(0.5) * D
    s = np.linspace(0.0, 1.0, SAMPLES, dtype=np.float32)
    return p, D, p[:, None, :] + s[None, :, None] * D[:, None, :]


def _median_ratio(vals, width) -> float:
    """Median over the pieces of enclosure width / true range (vals: [pieces, samples]
    point values, a lower bound of the range; pieces where f is not finite or constant
    are left out)."""
    vals = np.asarray(vals, np.float64).reshape(N_PIECES, -1)
    true = vals.max(axis=1) - vals.min(axis=1)
    ok = np.isfinite(vals).all(axis=1) & (true > 0)
    width = np.asarray(width, np.float64)
    ratio = np.where(np.isfinite(width), width, np.inf)[ok] / true[ok]
    return float(np.median(ratio)) if ratio.size else np.inf


def _pick(vals, widths: dict, cost: float, what: str) -> tuple[str, str]:
    """Affine when its median width / true range is more than `cost` times smaller."""
    ratios = {a: _median_ratio(vals, width) for a, width in widths.items()}
    ia_, af = ratios["interval"], ratios["affine"]
    pick = "affine" if ia_ > cost * af else "interval"
    return pick, (f"auto: {pick} ({what}median enclosure width / true range on {N_PIECES} "
                  f"ray pieces of 1/{round(1 / PIECE)} of the diagonal: interval {ia_:.3g}, "
                  f"affine {af:.3g})")


def _width_program(g, arithmetic: str, w, params, rounding: str):
    """The traced (not compiled) program of the enclosures' widths on the sample pieces
    in `arithmetic`, a `jax.stages.Traced` of (p, D, s0, s1, w, params); traced on the
    arguments' shapes, so it works for traced w and params too."""
    piece = jax.ShapeDtypeStruct((N_PIECES, 3), jnp.float32)
    ends = jax.ShapeDtypeStruct((N_PIECES,), jnp.float32)
    shapes = (piece, piece, ends, ends) + jax.tree_util.tree_map(
        lambda v: jax.ShapeDtypeStruct(jnp.shape(v), jnp.result_type(v)), (w, params))
    F = extended(g, arithmetic, rounding)

    # one compile: eager, the interpreter dispatches thousands of small ops (and the
    # piece ends are arguments: constants would be computed eagerly under the
    # preparation's `ensure_compile_time_eval`, a compile per operation)
    def width(p, D, s0, s1, w, params):
        r = enclosure(F, ray_boxes(p, D, s0, s1, arithmetic), w, params, arithmetic)
        return r.hi - r.lo

    return jax.jit(width).trace(*shapes)


# An affine program is at least this many times its interval one (measured 1.9x on the
# fox network to 12x on a superquadric, session 23), so an interval program over
# AFFINE_MAX_EQUATIONS / AFFINE_OVER_INTERVAL equations is not traced in affine at all
# (tracing a 79k-equation affine program took 9 s)
AFFINE_OVER_INTERVAL = 1.9


# Lower bounds of the affine rules' sizes (jaxpr equations per operation on a form of
# the coordinates, the smallest over operand kinds: a product by a constant is ~160, of
# two forms ~290; x**2 ~180, x**3 ~770), checked against the rules by
# tests/test_neural.py. Their sum over f's distinct operations is a floor of the affine
# extension's length, known from f's own jaxpr (traced in milliseconds) where tracing the
# extension itself takes seconds (a 216-operation polynomial: 4.9 s for 29.8k equations).
AFFINE_RULE_FLOOR = {"mul": 150, "integer_pow": 150, "exp": 250, "log": 300, "sqrt": 300,
                     "max": 180, "min": 180, "abs": 200, "sin": 200, "cos": 200,
                     "tanh": 200}


def affine_floor(g, w, params) -> int:
    """A lower bound of the equations of g's affine extension: `AFFINE_RULE_FLOOR` summed
    over g's distinct operations on values that depend on x, y or z (nested calls
    included; other nested jaxprs, such as a cond's branches, count nothing)."""
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    rest = jax.tree_util.tree_map(
        lambda v: jax.ShapeDtypeStruct(jnp.shape(v), jnp.result_type(v)), (w, params))
    closed = jax.make_jaxpr(g)(scalar, scalar, scalar, *rest)
    n_in = len(closed.jaxpr.invars)
    return _floor(closed.jaxpr, [True] * 3 + [False] * (n_in - 3), set())


def _floor(jaxpr, lifted_in, seen) -> int:
    lifted = {v for v, on in zip(jaxpr.invars, lifted_in) if on}
    n = 0
    for eqn in jaxpr.eqns:
        ins = [not isinstance(v, jax.extend.core.Literal) and v in lifted
               for v in eqn.invars]
        if not any(ins):
            continue
        lifted.update(eqn.outvars)
        body = eqn.params.get("jaxpr")
        if eqn.primitive.name in ("pjit", "jit", "closed_call") and body is not None:
            n += _floor(getattr(body, "jaxpr", body), ins, seen)
            continue
        name = eqn.primitive.name
        if name == "integer_pow" and eqn.params.get("y", 0) < 2:
            continue
        key = (name, str(sorted(eqn.params.items())),
               tuple(repr(v.val) if isinstance(v, jax.extend.core.Literal) else id(v)
                     for v in eqn.invars))
        if key not in seen:  # a repeated operation is extended once (`extend`)
            seen.add(key)
            n += AFFINE_RULE_FLOOR.get(name, 0)
    return n


def _width_programs(g, w, params, rounding: str) -> tuple[dict, str | None]:
    """({arithmetic: its width program (`_width_program`)}, None), or ({...}, why) when
    the affine program is too long to compile (it is not traced at all, and not in the
    dict, when the interval program's length or `affine_floor` already shows it)."""
    programs = {"interval": _width_program(g, "interval", w, params, rounding)}
    n = equation_count(programs["interval"].jaxpr)
    if n * AFFINE_OVER_INTERVAL > AFFINE_MAX_EQUATIONS:
        return programs, (f"the interval extension of f is {n:,} equations, its affine "
                          f"one at least {AFFINE_OVER_INTERVAL}x that, over "
                          f"{AFFINE_MAX_EQUATIONS:,}")
    floor = affine_floor(g, w, params)
    if floor > AFFINE_MAX_EQUATIONS:
        return programs, (f"the affine extension of f is at least {floor:,} equations "
                          f"(its operations' rules), over {AFFINE_MAX_EQUATIONS:,}")
    programs["affine"] = _width_program(g, "affine", w, params, rounding)
    n = equation_count(programs["affine"].jaxpr)
    if n > AFFINE_MAX_EQUATIONS:
        return programs, (f"the affine extension of f is {n:,} equations, over "
                          f"{AFFINE_MAX_EQUATIONS:,}")
    return programs, None


def _measure(g, lo, hi, w, params, rounding: str) -> tuple[str, str]:
    p, D, pts = _pieces(lo, hi)
    programs, too_long = _width_programs(g, w, params, rounding)
    vals = jax.jit(on_points(g))(pts[..., 0], pts[..., 1], pts[..., 2], w, params)
    ends = np.zeros(N_PIECES, np.float32), np.ones(N_PIECES, np.float32)
    widths = {"interval": programs["interval"].lower().compile()(p, D, *ends, w, params)}
    if too_long is not None:
        ratio = _median_ratio(vals, widths["interval"])
        if ratio <= INTERVAL_GOOD_ENOUGH:
            return "interval", (f"auto: interval ({too_long}, and interval's median "
                                f"enclosure width / true range is {ratio:.3g}: affine "
                                "not compiled)")
        if "affine" not in programs:
            programs["affine"] = _width_program(g, "affine", w, params, rounding)
    widths["affine"] = programs["affine"].lower().compile()(p, D, *ends, w, params)
    return _pick(vals, widths, COST_RATIO, "")


def _measure_tape(tape, lo, hi, rest) -> tuple[str, str]:
    """`_measure` for a long program, on its tape (the tape evaluator is compiled once
    for all programs: this costs about a second where the straight extension would take
    minutes to compile). `rest`: the coordinates after x, y, z (w, scalar params)."""
    p, D, pts = _pieces(lo, hi)
    vals, widths = _tape_widths(tape, p, D, pts, list(rest))
    return _pick(np.asarray(vals).reshape(N_PIECES, SAMPLES), widths, TAPE_COST_RATIO,
                 f"a program of {int(tape.n)} instructions on the tape path; ")


@jax.jit
def _tape_widths(tape, p, D, pts, rest):
    """The tape's values at the points pts [N_PIECES, SAMPLES, 3] and the widths of its
    interval and affine enclosures of the pieces p + s D, s in [0, 1] (p, D
    [N_PIECES, 3]), in one compiled call (eagerly, each small step compiled on its own:
    ~30 programs, a second and ~2 MB each)."""
    one = _tape.take_regions(tape, jnp.zeros(1, jnp.int32))
    rest = [jnp.asarray(v, jnp.float32) for v in rest]
    s0, s1 = jnp.zeros((1, N_PIECES)), jnp.ones((1, N_PIECES))
    vals = _tape.evaluate(one, [pts[None, ..., c].reshape(1, -1) for c in range(3)] + rest)
    widths = {}
    for arithmetic in ("interval", "affine"):
        boxes = ray_boxes(p[None], D[None], s0, s1, arithmetic)
        point = (lambda v: Interval(v, v)) if arithmetic == "interval" else (
            lambda v: aa.as_affine(v, 1))
        r = _tape.evaluate(one, boxes + [point(v) for v in rest])
        r = aa.to_interval(r) if arithmetic == "affine" else r
        widths[arithmetic] = (r.hi - r.lo)[0]
    return vals, widths

