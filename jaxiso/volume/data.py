"""Synthetic test volumes (numpy only, deterministic).

Every generator samples a continuous field at the nodes of a regular grid that spans its
domain box *including both ends*, so ``data[i, j, k]`` lies at
``origin + (i, j, k) * spacing`` with
``(spacing, origin) = box_geometry(data.shape, *DOMAINS[name])``.
`n` is an int (an n x n x n grid) or a shape tuple (each axis still spans the whole box,
so the spacing may differ per axis). `ISOVALUES` gives a value whose isosurface is the
intended test surface.
"""

from __future__ import annotations

import numpy as np

__all__ = ["marschner_lobb", "sphere_distance", "mixing", "ct_phantom", "examples",
           "box_geometry", "DOMAINS", "ISOVALUES"]

# domain box (lo, hi), the same on every axis, of each example
DOMAINS = {
    "marschner_lobb": (-1.0, 1.0),
    "sphere_distance": (0.0, 1.0),
    "mixing": (0.0, 1.0),
    "ct_phantom": (-1.0, 1.0),
}

ISOVALUES = {
    "marschner_lobb": 0.5,
    "sphere_distance": 0.0,
    "mixing": 127.5,  # the middle of the two fluids' values 0 and 255
    "ct_phantom": 150.0,  # between soft tissue (90) and bone (200): the skull
}


def _shape3(n) -> tuple[int, int, int]:
    """(nx, ny, nz) from an int or a 3-tuple of positive ints (2.5 or NaN is an error, not
    silently truncated)."""
    sizes = np.asarray(n)
    if (sizes.dtype.kind not in "iuf" or sizes.shape not in ((), (3,))
            or not np.all(np.isfinite(sizes)) or not np.all(sizes == np.round(sizes))
            or np.any(sizes < 1)):
        raise ValueError(f"need an int or a 3-tuple of positive sizes, got {n!r}")
    return tuple(int(m) for m in np.broadcast_to(sizes, (3,)))


def box_geometry(shape, lo=0.0, hi=1.0) -> tuple[tuple, tuple]:
    """(spacing, origin), 3-tuples of floats, of a grid of `shape` nodes spanning [lo, hi]^3
    with nodes on both faces. An axis of size 1 gets spacing hi - lo (it has no cells)."""
    shape = _shape3(shape)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"need finite lo < hi, got lo={lo!r}, hi={hi!r}")
    spacing = tuple(float((hi - lo) / max(m - 1, 1)) for m in shape)
    return spacing, (float(lo),) * 3


def _axes(shape, lo, hi) -> list[np.ndarray]:
    """Node coordinates (float64) along each axis, both faces included."""
    return [np.linspace(lo, hi, m) if m > 1 else np.array([float(lo)]) for m in shape]


def marschner_lobb(n=41, *, alpha: float = 0.25, f_m: float = 6.0) -> np.ndarray:
    """The Marschner-Lobb test signal on [-1, 1]^3, float32 [n, n, n].

    S. R. Marschner and R. J. Lobb, "An evaluation of reconstruction filters for volume
    rendering", Proc. IEEE Visualization '94, pp. 100-107 (1994), Eq. for rho:

        rho(x, y, z) = (1 - sin(pi z / 2) + alpha (1 + rho_r(sqrt(x^2 + y^2)))) / (2 (1 + alpha))
        rho_r(r)     = cos(2 pi f_M cos(pi r / 2))

    with alpha = 0.25, f_M = 6; values lie in [0, 1]. Its usual isovalue is 0.5. The paper
    samples it on a 40^3 lattice; n = 41 puts nodes on both faces of the cube (spacing 0.05).
    Its ripples are close to the Nyquist limit of such grids, which is why reconstruction
    (here: trilinear) artefacts are visible.
    """
    x, y, z = _axes(_shape3(n), -1.0, 1.0)
    r = np.sqrt(x[:, None] ** 2 + y[None, :] ** 2)                       # [nx, ny]
    radial = np.cos(2.0 * np.pi * f_m * np.cos(np.pi * r / 2.0))
    vertical = np.sin(np.pi * z / 2.0)                                   # [nz]
    rho = ((1.0 - vertical[None, None, :] + alpha * (1.0 + radial[:, :, None]))
           / (2.0 * (1.0 + alpha)))
    return rho.astype(np.float32)


def sphere_distance(n=64, *, radius: float = 0.35, center=(0.5, 0.5, 0.5)) -> np.ndarray:
    """Signed distance |p - center| - radius on the unit cube [0, 1]^3, float32 of shape n
    (an int or a 3-tuple). Negative inside; the sphere is its 0 isosurface."""
    x, y, z = _axes(_shape3(n), 0.0, 1.0)
    cx, cy, cz = (float(c) for c in center)
    d2 = ((x - cx)[:, None, None] ** 2 + (y - cy)[None, :, None] ** 2
          + (z - cz)[None, None, :] ** 2)
    return (np.sqrt(d2) - float(radius)).astype(np.float32)


# ---- turbulent mixing layer -------------------------------------------------------------

_NOISE_K = 12           # largest wave number (cycles per unit length) of the 3-D noise
_NOISE_K_MIN = 2.0      # scales above 1/2 are left to the interface perturbation
_NOISE_GAIN = 1.5       # noise displacement in units of the layer half width
_INTERFACE_K = 4        # largest wave number of the interface perturbation


def _layer_half_width(time: float) -> float:
    """Half width of the mixing layer; RM layers grow like a power of time (here t^1/2)."""
    return 0.025 + 0.05 * np.sqrt(time)


def _interface_amplitude(time: float) -> float:
    """Amplitude of the interface perturbation; linear growth as in Richtmyer's impulsive model."""
    return 0.03 + 0.015 * time


def _wave_numbers(k_max: int) -> np.ndarray:
    return np.arange(-k_max, k_max + 1, dtype=np.float64)


def _hermitian(coef: np.ndarray) -> np.ndarray:
    """Coefficients on the symmetric wave-number grid whose Fourier sum is real and equals
    the real part of the sum with `coef` (so the field's mean square is sum |coef|^2)."""
    flipped = coef[(slice(None, None, -1),) * coef.ndim]
    return 0.5 * (coef + np.conj(flipped))


def _random_spectrum(rng, k_max: int, dims: int, exponent: float, k_min: float):
    """Complex Gaussian coefficients on {-k_max..k_max}^dims with amplitude |k|^-exponent in
    the band k_min <= |k| <= k_max, zero elsewhere; also returns |k| on the grid."""
    ks = np.meshgrid(*([_wave_numbers(k_max)] * dims), indexing="ij")
    kmag = np.sqrt(sum(k * k for k in ks))
    size = kmag.shape
    coef = rng.standard_normal(size) + 1j * rng.standard_normal(size)
    band = (kmag >= k_min) & (kmag <= k_max)
    amp = np.where(band, np.maximum(kmag, 1.0) ** -exponent, 0.0)
    return coef * amp, kmag


def _fourier_basis(coords: np.ndarray, k_max: int) -> np.ndarray:
    """exp(2 pi i k x) [len(coords), 2 k_max + 1]: period 1 on every axis."""
    return np.exp(2j * np.pi * coords[:, None] * _wave_numbers(k_max)[None, :])


def _interface_height(x, y, rng, time: float) -> np.ndarray:
    """Height [nx, ny] of the perturbed interface plane z = 1/2 (few long waves)."""
    coef, _ = _random_spectrum(rng, _INTERFACE_K, 2, 1.0, 1.0)
    coef = _hermitian(coef)
    rms = np.sqrt(np.sum(np.abs(coef) ** 2))
    wave = np.real(_fourier_basis(x, _INTERFACE_K) @ coef @ _fourier_basis(y, _INTERFACE_K).T)
    # tanh bounds the displacement, so the layer's extent is known without evaluating it
    return 0.5 + _interface_amplitude(time) * np.tanh(wave / (2.0 * rms))


def _noise_coefficients(rng, time: float) -> tuple[np.ndarray, float]:
    """Hermitian 3-D coefficients at `time` and their rms. Spectrum k^-11/6 per mode
    (Kolmogorov's k^-5/3 energy spectrum in 3-D); phases drift at an eddy rate k^2/3."""
    coef, kmag = _random_spectrum(rng, _NOISE_K, 3, 11.0 / 6.0, _NOISE_K_MIN)
    coef = coef * np.exp(1j * 0.8 * kmag ** (2.0 / 3.0) * time)
    coef = _hermitian(coef)
    return coef, float(np.sqrt(np.sum(np.abs(coef) ** 2)))


def _noise_chunks(x, y, z, coef, rms, z_chunk: int = 16):
    """Yields (z0, noise [nx, ny, <= z_chunk] float32 in (-1, 1)) over chunks of z planes.

    The Fourier sum is separable, so it is contracted one axis at a time (BLAS matmuls):
    cost O(nx ny nz K), memory O(nx ny K) plus one chunk of z planes."""
    ex, ey, ez = (_fourier_basis(c, _NOISE_K) for c in (x, y, z))
    a = np.einsum("xa,abc->xbc", ex, coef, optimize=True)
    b = np.einsum("yb,xbc->xyc", ey, a, optimize=True).reshape(len(x) * len(y), -1)
    # the big contraction in float32 (twice BLAS's float64 speed); values are O(1)
    scale = np.float32(1.0 / (2.0 * rms))
    br, bi = (np.ascontiguousarray(v, np.float32) * scale for v in (b.real, b.imag))
    ezr, ezi = (np.ascontiguousarray(v.T, np.float32) for v in (ez.real, ez.imag))
    for z0 in range(0, len(z), z_chunk):
        val = br @ ezr[:, z0:z0 + z_chunk] - bi @ ezi[:, z0:z0 + z_chunk]  # Re(b e^T)
        yield z0, np.tanh(val).reshape(len(x), len(y), -1)


def _smoothstep(s: np.ndarray) -> np.ndarray:
    """0 for s <= -1, 1 for s >= 1, C1 cubic in between."""
    u = np.clip(0.5 * s + 0.5, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def mixing(n=64, *, seed: int = 0, time: float = 0.0, quantize: bool = False) -> np.ndarray:
    """A Richtmyer-Meshkov-like mixing layer on [0, 1]^3: float32 in [0, 255] (uint8 with
    `quantize`), heavy fluid (255) below, light fluid (0) above.

    A continuous field, sampled at the grid nodes (so grids of different n sample the same
    field): the interface z = h(x, y) is the plane z = 1/2 perturbed by a few long random
    waves; around it a mixing layer of half width w(t) is filled by multi-octave
    band-limited noise N (random Fourier modes, wave numbers 2..12, spectrum k^-11/6,
    periodic in x and y):

        s = (z - h(x, y)) / w(t) - 1.5 N(x, y, z, t),   value = 255 (1 - smoothstep(s))

    where smoothstep goes from 0 at s = -1 to 1 at s = 1. Away from the layer the value is
    exactly 0 or 255: those large constant regions are what octree compression exploits.
    `time` (nominally 0..4) widens the layer (w = 0.025 + 0.05 sqrt(t)), grows the interface
    perturbation linearly and drifts the noise phases, so a sequence of times gives a
    sequence of distinct, coherent volumes; `seed` picks the random modes. The isosurface
    127.5 is the wrinkled interface with bubbles and spikes.
    """
    shape = _shape3(n)
    time = float(time)
    if not time >= 0:  # NaN too
        raise ValueError(f"time must be >= 0, got {time}")
    x, y, z = _axes(shape, 0.0, 1.0)
    rng = np.random.default_rng(seed)  # draws depend on seed only, not on the grid
    height = _interface_height(x, y, rng, time)
    coef, rms = _noise_coefficients(rng, time)
    half = _layer_half_width(time)

    # |N| < 1 bounds the layer: below it all is heavy fluid, above it light
    reach = half * (1.0 + _NOISE_GAIN)
    lo = int(np.searchsorted(z, height.min() - reach, side="left"))
    hi = int(np.searchsorted(z, height.max() + reach, side="right"))
    out = np.empty(shape, np.float32)
    out[:, :, :lo] = 255.0
    out[:, :, hi:] = 0.0
    for z0, noise in _noise_chunks(x, y, z[lo:hi], coef, rms):
        zs = z[lo + z0:lo + z0 + noise.shape[2]]
        s = ((zs[None, None, :] - height[:, :, None]) / half).astype(np.float32)
        s -= np.float32(_NOISE_GAIN) * noise
        out[:, :, lo + z0:lo + z0 + noise.shape[2]] = 255.0 * (1.0 - _smoothstep(s))
    if quantize:
        return np.rint(out).astype(np.uint8)
    return out


# ---- CT-like phantom --------------------------------------------------------------------

# (centre, semi-axes, value) painted in order, later ones over earlier ones; values are
# uint8 "densities": air 0, fluid 30, soft tissue 90, lesion 140, bone 200
_PHANTOM = (
    ((0.0, 0.0, 0.05), (0.72, 0.88, 0.86), 200),     # skull (outer surface)
    ((0.0, 0.0, 0.05), (0.65, 0.81, 0.79), 90),      # brain inside the bone shell
    ((-0.2, 0.1, 0.15), (0.08, 0.26, 0.12), 30),     # ventricles
    ((0.2, 0.1, 0.15), (0.08, 0.26, 0.12), 30),
    ((0.25, -0.35, -0.2), (0.1, 0.1, 0.1), 140),     # a lesion
    ((0.0, -0.05, -0.85), (0.14, 0.14, 0.3), 200),   # spine leaving through the bottom face
)


def ct_phantom(n=64) -> np.ndarray:
    """A CT-like head phantom on [-1, 1]^3, uint8 of shape n: nested constant-valued
    ellipsoids (a bone shell 200 around tissue 90, fluid-filled ventricles 30, a lesion
    140, a spine) in air 0. Mostly large uniform regions, for compression tables; the
    isovalue 150 gives the outside and inside of the skull, the spine and nothing else."""
    x, y, z = _axes(_shape3(n), -1.0, 1.0)
    out = np.zeros(_shape3(n), np.uint8)
    for (cx, cy, cz), (ax, ay, az), value in _PHANTOM:
        inside = (((x - cx) / ax)[:, None, None] ** 2 + ((y - cy) / ay)[None, :, None] ** 2
                  + ((z - cz) / az)[None, None, :] ** 2) <= 1.0
        out[inside] = value
    return out


def examples() -> dict:
    """Names -> generators ``f(n) -> array``; see `DOMAINS` and `ISOVALUES` for each."""
    return {
        "marschner_lobb": marschner_lobb,
        "sphere_distance": sphere_distance,
        "mixing": mixing,
        "ct_phantom": ct_phantom,
    }
