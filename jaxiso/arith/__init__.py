"""Inclusion arithmetic: `Interval`, `Affine` (AF1) and `extend` for plain JAX functions.

The modules `ia` and `aa` hold the pure functions of each arithmetic.
"""

from . import _affine as aa
from . import _interval as ia
from ._affine import Affine
from ._extend import ARITHMETICS, ROUNDINGS, extend, register_rule
from ._interval import Interval, interval

__all__ = ["Interval", "interval", "Affine", "extend", "register_rule", "ia", "aa",
           "ARITHMETICS", "ROUNDINGS"]
