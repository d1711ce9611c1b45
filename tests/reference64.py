"""Float64 numpy versions of the seed's Table B.1 surfaces, written independently of
jaxiso.implicit.surfaces (transcribed from the dissertation, expanded differently).

Decimal constants go through `c32`: a float32 program computes with the float32 value of
each constant, and the float64 reference must evaluate that same real function.
"""

import numpy as np


def c32(v):
    return float(np.float32(v))


TAU = (1 + np.sqrt(5.0)) / 2


def sphere(x, y, z, w=0.0):
    return np.power(x, 2) + np.power(y, 2) + np.power(z, 2) - 1.0


def steiner(x, y, z, w=0.0):
    return (x * y) ** 2 + (y * z) ** 2 + (x * z) ** 2 + x * y * z


def mitchell(x, y, z, w=0.0):
    return (4 * (x**4 + (y**2 + z**2) ** 2) + 17 * x**2 * (y**2 + z**2)
            - 20 * (x**2 + y**2 + z**2) + 17)


def teardrop(x, y, z, w=0.0):
    return (x**5 + x**4) / 2 - y**2 - z**2


def bretzel4(x, y, z, w=0.0):
    return (x**2 * (c32(1.21) - x**2) ** 2 * (c32(3.8) - x**2) ** 3 - 10 * y**2) ** 2 * c32(0.1) \
        + 60 * z**2 - 2


def klein(x, y, z, w=0.0):
    s = x**2 + y**2 + z**2
    return (s + 2 * y - 1) * ((s - 2 * y - 1) ** 2 - 8 * z**2) + 16 * x * z * (s - 2 * y - 1)


def tangle(x, y, z, w=0.0):
    return x**4 - 5 * x**2 + y**4 - 5 * y**2 + z**4 - 5 * z**2 + c32(11.8)


def decocube(x, y, z, w=0.0):
    a = (x**2 + y**2 - c32(0.64)) ** 2 + (z**2 - 1) ** 2
    b = (y**2 + z**2 - c32(0.64)) ** 2 + (x**2 - 1) ** 2
    c = (z**2 + x**2 - c32(0.64)) ** 2 + (y**2 - 1) ** 2
    return a * b * c - c32(0.02)


def barth_sextic(x, y, z, w=0.0):
    t2 = c32(TAU**2)
    return (4 * (t2 * x**2 - y**2) * (t2 * y**2 - z**2) * (t2 * z**2 - x**2)
            - c32(1 + 2 * TAU) * (x**2 + y**2 + z**2 - 1) ** 2)


def barth_decic(x, y, z, w=1.0):
    t4 = c32(TAU**4)
    q = x**4 + y**4 + z**4 - 2 * x**2 * y**2 - 2 * x**2 * z**2 - 2 * y**2 * z**2
    s = x**2 + y**2 + z**2
    return (8 * (x**2 - t4 * y**2) * (y**2 - t4 * z**2) * (z**2 - t4 * x**2) * q
            + c32(3 + 5 * TAU) * (s - w**2) ** 2 * (s - c32(2 - TAU) * w**2) ** 2 * w**2)


def superquadric(x, y, z, w=0.0):
    with np.errstate(over="ignore"):
        return np.power(x, 500) + 0.5 * np.power(np.abs(y), 35) + 0.5 * np.power(z, 4) - 1


SURFACES = {f.__name__: f for f in (sphere, steiner, mitchell, teardrop, bretzel4, klein,
                                     tangle, decocube, barth_sextic, barth_decic,
                                     superquadric)}
