"""jaxiso: ray tracing implicit surfaces in JAX (after Knoll 2009).

Public API so far: the inclusion arithmetic layer (`Interval`, `Affine`, `extend`,
`register_rule`) and the catalogue of test surfaces (`surfaces`).
"""

from . import arith
from .arith import Affine, Interval, aa, extend, ia, interval, register_rule
from .implicit import surfaces

__version__ = "0.1.0"

__all__ = ["Interval", "interval", "Affine", "extend", "register_rule", "ia", "aa",
           "arith", "surfaces", "__version__"]
