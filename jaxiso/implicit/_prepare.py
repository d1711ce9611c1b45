"""Preparing an `ImplicitSurface` to trace: the explicit, visible step that does the work
a constructor never does (constructing a scene only checks its fields; docs/performance.md,
"Preparing a scene").

It learns two facts of f (whether it is a network, whether it is a long program for the
tape path), resolves ``arithmetic="auto"`` by measuring both arithmetics, and builds the
sign grid by the scene's `culling`. Long work prints a progress line; results are held
on the returned scene (and memoised in bounded caches that `jaxiso.clear_caches`
empties). `intersect` and `render` prepare a scene on their first call; a prepared scene
returns itself.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ._auto import choose_arithmetic
from ._culling import sign_grid_for
from ._memo import BoundedCache
from ._policy import is_heavy
from ._polynomial import MAX_DEGREE, TABLE_FROM, chebyshev_table, polynomial_degree

__all__ = ["FunctionFacts", "function_facts", "prepare_surface", "params_structure",
           "check_polynomial"]


@dataclasses.dataclass(frozen=True)
class FunctionFacts:
    """What preparation learnt of f and its params' structure (a static field: equal
    facts compile alike).

    heavy: f computes at least `_policy.HEAVY_ELEMENTS` numbers per point (a network).
    tape: f's instruction tape when it is a long program (the tape path), else None.
    degree: f's total degree in x, y, z when it is a polynomial in them, else None
    (`_polynomial.polynomial_degree`).
    length: the equations of f's jaxpr.
    """

    heavy: bool
    tape: object = None
    degree: int | None = None
    length: int = 0


# facts by (f, params' structure): they depend on nothing else
_FACTS = BoundedCache("facts of functions", 32)


def function_facts(scene) -> FunctionFacts:
    """The facts of the scene's f (traces f once per f and params structure; never
    evaluates it)."""
    def learn():
        degree, length = polynomial_degree(scene.field, scene.w, scene.params)
        return FunctionFacts(is_heavy(scene.field, scene.params), scene.long_tape(), degree,
                             length)

    return _FACTS.get((scene.f, params_structure(scene.params)), learn)


def check_polynomial(degree, rounding: str) -> None:
    """ValueError unless arithmetic "polynomial" applies: f a polynomial in x, y, z of
    degree 1 to `MAX_DEGREE`, with the "fast" rounding (its pad is not outward rounding)."""
    if degree is None:
        raise ValueError('arithmetic="polynomial" needs f to be a polynomial in x, y, z '
                         "(sums, products, integer powers and constants; w and params "
                         'may enter anyhow); use "interval", "affine" or "auto"')
    if not 1 <= degree <= MAX_DEGREE:
        raise ValueError(f'arithmetic="polynomial" encloses degrees 1 to {MAX_DEGREE}; f '
                         f'has degree {degree}: use "interval", "affine" or "auto"')
    if rounding != "fast":
        raise ValueError('arithmetic="polynomial" rounds like rounding="fast" (a padded '
                         'float32 enclosure); with rounding="outward" use "interval" or '
                         '"affine"')


def params_structure(params):
    """params' treedef, shapes and dtypes (what the facts of f depend on)."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    return tree, tuple((jnp.shape(x), str(jnp.result_type(x))) for x in leaves)


def prepare_surface(scene):
    """The scene with facts, arithmetic and sign grid resolved (`ImplicitSurface.prepared`).
    Runs eagerly on the concrete inputs even when asked under a jit trace (a concrete
    scene traced by `intersect` inside a user's jit); traced inputs are not measured."""
    with jax.ensure_compile_time_eval():
        facts = scene.facts if scene.facts is not None else function_facts(scene)
        arithmetic, arithmetic_report = scene.arithmetic, scene.arithmetic_report
        if arithmetic == "auto":
            arithmetic, arithmetic_report = choose_arithmetic(
                scene.f, scene.field, scene.lo, scene.hi, scene.w, scene.params,
                scene.rounding, facts.tape, facts.degree)
        elif arithmetic == "polynomial":
            check_polynomial(facts.degree, scene.rounding)
        table = scene.polynomial_table
        if arithmetic == "polynomial" and table is None and facts.length >= TABLE_FROM:
            table = chebyshev_table(scene.field, facts.degree, scene.lo, scene.hi, scene.w,
                                    scene.params)
        grid, culling_report = scene.sign_grid, scene.culling_report
        if grid is None:
            grid, culling_report = sign_grid_for(scene, facts.heavy)
    return dataclasses.replace(scene, facts=facts, arithmetic=arithmetic,
                               arithmetic_report=arithmetic_report, sign_grid=grid,
                               polynomial_table=table,
                               culling_report=culling_report, ready=True)
