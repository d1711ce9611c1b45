"""The options of implicit scenes (`ImplicitSurface`, `CSG`): their choices, defaults and
validation, shared by construction and every `replace` (numeric options are traced
fields, choices static ones)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._core import SceneFields, check_choice, check_count, concrete
from ..arith import ARITHMETICS, ROUNDINGS
from ._bisect import MAX_DEPTH
from ._field import VERIFY
from ._methods import METHODS, check_lanes

__all__ = ["ImplicitOptions", "DEFAULT_EPS", "CULLINGS", "ARITHMETICS", "ROUNDINGS",
           "check_values", "check_static"]

DEFAULT_EPS = 2.0**-11
CULLINGS = ("auto", "grid", "none")


class ImplicitOptions(SceneFields):
    """Validation shared by `ImplicitSurface` and `CSG`. Subclasses name the choices
    they accept in `methods` and `arithmetics`."""

    methods = tuple(METHODS)
    arithmetics = ARITHMETICS

    def _validate(self):
        """Normalise and check the fields (construction and every `replace`)."""
        check_choice("method", self.method, self.methods)
        check_choice("arithmetic", self.arithmetic, self.arithmetics)
        check_choice("rounding", self.rounding, ROUNDINGS)
        if hasattr(self, "verify"):
            check_choice("verify", self.verify, VERIFY)
        set_ = functools.partial(object.__setattr__, self)
        lo, hi = jnp.asarray(self.lo, jnp.float32), jnp.asarray(self.hi, jnp.float32)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"lo and hi must be 3-vectors, got {lo.shape} and {hi.shape}")
        set_("lo", lo)
        set_("hi", hi)
        for name in ("w", "eps", "delta"):
            if hasattr(self, name):
                set_(name, _scalar(name, getattr(self, name)))
        if getattr(self, "lipschitz", None) is not None:
            set_("lipschitz", jnp.asarray(self.lipschitz, jnp.float32))
        check_values(self)
        check_static(self)

    @property
    def has_params(self) -> bool:
        return len(jax.tree_util.tree_leaves(self.params)) > 0

    @property
    def offset_scale(self):
        return self.eps

    def coarser(self, factor):
        """Shadow rays: eps times `factor` (Sec. 6.4.6)."""
        return self.replace(eps=self.eps * factor)

    def check_lanes(self, lanes) -> None:
        """ValueError unless the scene's method runs on `lanes` (None: packets)."""
        check_lanes(self.method, lanes)


def _scalar(name, x):
    v = jnp.asarray(x, jnp.float32)
    if v.ndim != 0:
        raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
    return v


def check_values(scene) -> None:
    """Concrete numeric fields (traced ones are checked where they were concrete)."""
    lo, hi, eps = concrete(scene.lo), concrete(scene.hi), concrete(scene.eps)
    if lo is not None and hi is not None:
        _check_box(lo, hi)
    if eps is not None and not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be a finite positive length, got {eps}")
    if lo is not None and hi is not None and eps is not None:
        check_depth(lo.astype(np.float64), hi.astype(np.float64), float(eps))
    for name in ("isovalues", "w", "delta", "lipschitz"):
        v = concrete(getattr(scene, name, None))
        if v is not None and v.dtype != object and not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite, got {v}")
    _check_params(scene.params)
    delta = concrete(getattr(scene, "delta", 0.0))
    if delta is not None and delta < 0:
        raise ValueError(f"delta must be >= 0 (0: no range tolerance), got {delta}")
    lip = getattr(scene, "lipschitz", None)
    lip = concrete(lip) if lip is not None else None
    if lip is not None and lip.dtype != object and not lip > 0:
        raise ValueError(f"lipschitz must be positive, got {lip}")


def _check_box(lo, hi) -> None:
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"the domain box must be finite, got lo={lo} hi={hi}")
    if np.any(lo >= hi):
        raise ValueError(f"the domain box needs lo < hi on every axis, got lo={lo} hi={hi}")


def _check_params(params) -> None:
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        v = concrete(leaf)
        if v is not None and np.issubdtype(v.dtype, np.inexact) and not np.all(np.isfinite(v)):
            raise ValueError(f"params{jax.tree_util.keystr(path)} must be finite: "
                             f"{int(np.size(v) - np.isfinite(v).sum())} NaN or inf values")


def check_depth(lo, hi, eps) -> None:
    """eps must be reachable: at most 2^MAX_DEPTH pieces per ray (int32 positions) and no
    finer than float32 resolves the box's coordinates."""
    length = float(np.linalg.norm(hi - lo))
    if not length < float(np.finfo(np.float32).max):
        raise ValueError(f"the domain box diagonal {length:.3g} overflows float32; "
                         "scale the model down")
    finest = length * 2.0 ** -MAX_DEPTH
    ulp = float(np.max(np.maximum(np.abs(lo), np.abs(hi)))) * 2.0**-23
    if eps < max(finest, ulp):
        why = (f"more than 2^{MAX_DEPTH} bisection pieces across the domain's "
               f"diagonal {length:.3g}" if finest >= ulp else
               f"a piece below float32 resolution ({ulp:.3g}) at the domain's coordinates "
               f"(up to {ulp * 2**23:.3g})")
        raise ValueError(f"eps={eps:.3g} needs {why}; use eps >= {max(finest, ulp):.3g}, or "
                         "a smaller box nearer the origin")


def check_static(scene) -> None:
    """The static options: stencil width, loop bounds, counts, what a method needs."""
    n = scene.normals
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, float))
                          or not np.isfinite(n) or n <= 0):
        raise ValueError(f"normals must be None (jax.grad) or a positive stencil width, "
                         f"got {n!r}")
    check_count("max_steps", scene.max_steps)
    check_count("refine_steps", getattr(scene, "refine_steps", None))
    if hasattr(scene, "samples"):
        check_count("samples", scene.samples, least=2, optional=False)
    for name in METHODS[scene.method].requires:
        if getattr(scene, name, None) is None:
            raise ValueError(f"method {scene.method!r} needs {METHODS[scene.method].needs}")

