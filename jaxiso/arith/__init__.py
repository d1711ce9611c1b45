"""Inclusion arithmetic: `Interval`, `Affine` (AF1) and `extend` for plain JAX functions.

The modules `ia` and `aa` hold the pure functions of each arithmetic; `tape` the
instruction tapes (programs as data) and their evaluator, for long programs.
"""

from . import _affine as aa
from . import _interval as ia
from . import _tape as tape
from ._affine import Affine
from ._extend import (
    ARITHMETICS,
    ROUNDINGS,
    equation_count,
    extend,
    network_shape,
    register_rule,
    value_elements,
)
from ._interval import Interval, interval
from ._tape import Tape

__all__ = ["Interval", "interval", "Affine", "extend", "register_rule", "ia", "aa", "tape", "Tape",
           "ARITHMETICS", "ROUNDINGS", "equation_count", "value_elements", "network_shape"]
