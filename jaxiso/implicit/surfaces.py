"""The seed's test surfaces (Knoll 2009, Table B.1) as plain jax.numpy functions.

Each `Surface` holds ``f(x, y, z, w)`` (w is the 4D/morphing parameter; ignored by most),
and the domain box it is shown in. Where the printed formula is ambiguous the choice is
recorded in `notes`. Use `get(name)` and `names()`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax.numpy as jnp

__all__ = ["Surface", "get", "names", "TAU"]

TAU = (1.0 + math.sqrt(5.0)) / 2.0  # golden ratio


@dataclasses.dataclass(frozen=True)
class Surface:
    """A catalogue entry.

    Attributes:
      name: catalogue key.
      f: ``f(x, y, z, w) -> scalar``, plain jnp code (w defaults to `w`).
      lo, hi: corners of the domain box (world space).
      w: default value of the 4th coordinate.
      notes: how an ambiguous printed formula was read.
    """

    name: str
    f: Callable
    lo: tuple
    hi: tuple
    w: float = 0.0
    notes: str = ""


def _sphere(x, y, z, w):
    return x * x + y * y + z * z - 1.0


def _steiner(x, y, z, w):
    return x * x * y * y + y * y * z * z + x * x * z * z + x * y * z


def _mitchell(x, y, z, w):
    r2 = y * y + z * z
    return (4.0 * (x**4 + r2 * r2) + 17.0 * x * x * r2
            - 20.0 * (x * x + y * y + z * z) + 17.0)


def _teardrop(x, y, z, w):
    return 0.5 * (x**5 + x**4) - y * y - z * z


def _bretzel4(x, y, z, w):
    x2 = x * x
    g = x2 * (1.21 - x2) ** 2 * (3.8 - x2) ** 3 - 10.0 * y * y
    return 0.1 * g * g + 60.0 * z * z - 2.0


def _klein(x, y, z, w):
    r2 = x * x + y * y + z * z
    a = r2 - 2.0 * y - 1.0
    return (r2 + 2.0 * y - 1.0) * (a * a - 8.0 * z * z) + 16.0 * x * z * a


def _tangle(x, y, z, w):
    return x**4 - 5.0 * x * x + y**4 - 5.0 * y * y + z**4 - 5.0 * z * z + 11.8


def _decocube(x, y, z, w):
    x2, y2, z2 = x * x, y * y, z * z
    c = 0.8 * 0.8
    return (((x2 + y2 - c) ** 2 + (z2 - 1.0) ** 2)
            * ((y2 + z2 - c) ** 2 + (x2 - 1.0) ** 2)
            * ((z2 + x2 - c) ** 2 + (y2 - 1.0) ** 2) - 0.02)


def _barth_sextic(x, y, z, w):
    t2 = TAU * TAU
    x2, y2, z2 = x * x, y * y, z * z
    s = x2 + y2 + z2 - 1.0
    return (4.0 * (t2 * x2 - y2) * (t2 * y2 - z2) * (t2 * z2 - x2)
            - (1.0 + 2.0 * TAU) * s * s)


def _barth_decic(x, y, z, w):
    t4 = TAU**4
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    r2 = x2 + y2 + z2
    a = r2 - w2
    b = r2 - (2.0 - TAU) * w2
    return (8.0 * (x2 - t4 * y2) * (y2 - t4 * z2) * (z2 - t4 * x2)
            * (x2 * x2 + y2 * y2 + z2 * z2 - 2.0 * x2 * y2 - 2.0 * x2 * z2 - 2.0 * y2 * z2)
            + (3.0 + 5.0 * TAU) * a * a * b * b * w2)


def _superquadric(x, y, z, w):
    return x**500 + 0.5 * jnp.abs(y) ** 35 + 0.5 * z**4 - 1.0


_CATALOGUE = {s.name: s for s in (
    Surface("sphere", _sphere, (-1.5,) * 3, (1.5,) * 3, notes="r = 1"),
    Surface("steiner", _steiner, (-1.0,) * 3, (1.0,) * 3,
            notes="Steiner's Roman surface; singular lines along the axes"),
    Surface("mitchell", _mitchell, (-2.0,) * 3, (2.0,) * 3,
            notes="printed with an unbalanced parenthesis; read as Mitchell's surface "
                  "4(x^4 + (y^2+z^2)^2) + 17 x^2 (y^2+z^2) - 20 (x^2+y^2+z^2) + 17"),
    Surface("teardrop", _teardrop, (-1.25, -0.5, -0.5), (0.25, 0.5, 0.5),
            notes="cusp at the origin"),
    Surface("bretzel4", _bretzel4, (-2.0, -1.5, -0.5), (2.0, 1.5, 0.5),
            notes="read as 0.1 (x^2 (1.21-x^2)^2 (3.8-x^2)^3 - 10 y^2)^2 + 60 z^2 - 2 "
                  "(four holes: two lobes of the x-polynomial above sqrt(20) per side)"),
    Surface("klein", _klein, (-3.0,) * 3, (3.0,) * 3,
            notes="figure-8 Klein bottle immersion as printed"),
    Surface("tangle", _tangle, (-3.0,) * 3, (3.0,) * 3,
            notes="printed 'x^4 - r x^2'; read as the tangle cube x^4 - 5x^2 + ..."),
    Surface("decocube", _decocube, (-1.5,) * 3, (1.5,) * 3),
    Surface("barth_sextic", _barth_sextic, (-1.5,) * 3, (1.5,) * 3),
    Surface("barth_decic", _barth_decic, (-2.0,) * 3, (2.0,) * 3, w=1.0,
            notes="w is the homogenising coordinate; w = 1 gives the Barth decic"),
    Surface("superquadric", _superquadric, (-1.5,) * 3, (1.5,) * 3,
            notes="printed 'y ^35'; read as |y|^35 (an odd power of y is not a "
                  "superquadric); x^500 overflows float32 beyond |x| ~ 1.19"),
)}


def names() -> list[str]:
    return list(_CATALOGUE)


def get(name: str) -> Surface:
    try:
        return _CATALOGUE[name]
    except KeyError:
        raise KeyError(f"unknown surface {name!r}; known: {', '.join(_CATALOGUE)}") from None
