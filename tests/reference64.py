"""Float64 numpy versions of the seed's Table B.1 and B.2 surfaces and the 4D morph,
written independently of jaxiso.implicit.surfaces (transcribed from the dissertation,
expanded differently; the readings of garbled formulas follow the catalogue's notes).

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


# ---- Table B.2 -------------------------------------------------------------------------

def icos_ic(x, y, z, w=0.0):
    # cos(a + b) + cos(a - b) = 2 cos(a) cos(b), pairwise over the printed six terms
    t = c32(TAU)
    return 2 - 2 * (np.cos(x) * np.cos(t * y) + np.cos(y) * np.cos(t * z)
                    + np.cos(z) * np.cos(t * x))


def icos_sphere_inner(x, y, z, w=0.0):  # positive inside, radius 3.5
    return 3.5**2 - np.square(x) - np.square(y) - np.square(z)


def icos_sphere_outer(x, y, z, w=0.0):  # positive inside, radius 4.5
    return 4.5**2 - np.square(x) - np.square(y) - np.square(z)


def sesc_se(x, y, z, w=0.0):
    return np.power(x, 6) + np.power(np.power(y, 4) + np.power(z, 4), 4) / 2 - 20


def sesc_sc(x, y, z, w=0.0):
    s1, s2 = np.sin, lambda v: np.sin(2 * v)
    c1, c2 = np.cos, lambda v: np.cos(2 * v)
    return (x * y + c1(z) + c32(1.741) * s2(x) * s1(z) * c1(y) + s2(y) * s1(x) * c1(z)
            + s2(z) * s1(y) * c1(x) + c2(z) * (c2(x) + c2(y)) - c2(x) * c2(y) + c32(0.05))


def sin_blob(x, y, z, w=0.0):
    r0, r1, r2 = c32(0.104), c32(0.402), c32(-0.347)
    a, b = c32(4 * 0.104 * -0.347), c32(2 * 0.104 * 0.402)  # folded by the float32 program
    waves = (np.sin(a * x) * np.sin(r0 * z) * np.cos(r1 * y)
             + np.sin(b * y) * np.sin(r2 * x) * np.cos(r2 * z)
             + np.sin(2 * r2 * z) * np.sin(r1 * y) * np.cos(r2 * x))
    ripples = (np.cos(2 * r2 * x) * (np.cos(2 * r0 * y) + np.cos(2 * r2 * z))
               + np.cos(b * y) * np.cos(2 * r2 * z))
    return 1 + r1 * (y + w) + np.cos(r2 * z) + 4 * waves - ripples


def cloth(x, y, z, w=0.0):
    return (y - np.sin(x + 3 * w) / 2
            - c32(0.1) * np.cos(z + 3 * w) - c32(0.1) ** 2 * np.sin(x * z) * np.cos(z + 3 * w))


def water(x, y, z, w=0.0):
    def wave(rho, k, phase):
        return np.sin(k * rho - w - phase) / (rho + 10)

    return (wave(np.hypot(x + 15, z), 1, 0) + wave(np.hypot(x - 15, z), 1, 0)
            + wave(np.hypot(x, z - 15), 2, c32(2.736)) - y / 2)


# ---- the 4D morph (Sec. 6.6.7.2) ----------------------------------------------------------

def morph(x, y, z, w=0.5):
    s = 1 / (1 + np.exp(12 * (0.5 - w)))
    return decocube(x, y, z) + s * (x**2 + y**2 + z**2 - c32(1.44) - decocube(x, y, z))


SURFACES = {f.__name__: f for f in (sphere, steiner, mitchell, teardrop, bretzel4, klein,
                                     tangle, decocube, barth_sextic, barth_decic,
                                     superquadric)}
SURFACES.update({"icos.csg": icos_ic, "sesc.csg": sesc_se, "sin.blob": sin_blob,
                 "cloth": cloth, "water": water, "morph": morph})

# the components of the CSG entries, by the catalogue's part names
CSG_PARTS = {"icos.csg": {"ic": icos_ic, "sphere_inner": icos_sphere_inner,
                          "sphere_outer": icos_sphere_outer},
             "sesc.csg": {"se": sesc_se, "sc": sesc_sc}}
