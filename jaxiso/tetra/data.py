"""Synthetic tetrahedral meshes and scalar fields for tests and benchmarks (numpy only).

Every function is deterministic and returns plain arrays: points float32 [V, 3] (computed in
float64, cast once), tets int32 [T, 4] with positive signed volume
``dot(b - a, cross(c - a, d - a)) > 0``, and vertex values float32 [V] (or [S, V] for a time
series). Nothing here depends on the rest of `jaxiso.tetra`, so tests can build data without
the code under test.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = [
    "cube_tets",
    "sphere_field",
    "wave_field",
    "random_field",
    "replicate",
    "poisson_cube",
    "poisson_on_ball",
    "time_series",
    "deform",
]

# Unit-cube corners as (x, y, z) bits; a corner's index in the template lists below.
_CORNERS = np.array([(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.int64)


def _corner(bits) -> int:
    return int(np.flatnonzero((_CORNERS == np.asarray(bits)).all(axis=1))[0])


def _orient_template(template: list[tuple]) -> np.ndarray:
    """Corner indices [K, 4] with each tet reordered (swap of the last two) to positive volume."""
    tets = np.array([[_corner(c) for c in tet] for tet in template], np.int64)
    p = _CORNERS[tets].astype(np.float64)
    vol = np.einsum("ki,ki->k", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[vol < 0] = tets[vol < 0][:, [0, 1, 3, 2]]
    return tets


def _kuhn_template() -> np.ndarray:
    """6 tets sharing the (0,0,0)-(1,1,1) diagonal, one per axis order (a monotone lattice path).

    Each cube face is cut by the diagonal through its lowest and highest corner, the same on
    both sides of a face shared by two cubes, so the split is conforming on any grid.
    """
    eye = np.eye(3, dtype=np.int64)
    paths = []
    for order in itertools.permutations(range(3)):
        steps = np.cumsum(eye[list(order)], axis=0)
        paths.append([(0, 0, 0)] + [tuple(s) for s in steps])
    return _orient_template(paths)


def _five_template(central_parity: int) -> np.ndarray:
    """4 corner tets + 1 central tet; the central tet's corners have bit-sum parity
    `central_parity`. Neighbouring cubes must alternate it so that shared faces agree."""
    central = [tuple(c) for c in _CORNERS if c.sum() % 2 == central_parity]
    tets = [central]
    for apex in _CORNERS:
        if apex.sum() % 2 != central_parity:
            # the corner tet cut off at `apex`: apex and its three edge neighbours
            nbrs = [tuple(apex ^ e) for e in np.eye(3, dtype=np.int64)]
            tets.append([tuple(apex)] + nbrs)
    return _orient_template(tets)


def cube_tets(n=8, *, split: int = 6, lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)):
    """A structured grid of n^3 hexahedra (n may be (nx, ny, nz)) split into tets.

    split=6: Kuhn split, 6 congruent tets per cube around its main diagonal.
    split=5: 4 corner tets + 1 central tet per cube, mirrored on alternate cubes (by the parity
    of i + j + k) so that the face diagonals of neighbouring cubes coincide.
    Both are conforming: every interior triangle is shared by exactly two tets.

    Returns (points float32 [(nx+1)(ny+1)(nz+1), 3], tets int32 [split * nx ny nz, 4]).
    Vertex (i, j, k) has index (i * (ny + 1) + j) * (nz + 1) + k.
    """
    counts = np.asarray(n)
    if (counts.dtype.kind not in "iuf" or counts.shape not in ((), (3,))
            or not np.all(np.isfinite(counts)) or not np.all(counts == np.round(counts))
            or np.any(counts < 1)):
        raise ValueError(f"n must be a positive int or 3 of them, got {n!r}")
    counts = np.broadcast_to(counts.astype(np.int64), (3,))
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ValueError(f"need 3-vectors with hi > lo, got lo={lo}, hi={hi}")
    nx, ny, nz = (int(c) for c in counts)
    if (nx + 1) * (ny + 1) * (nz + 1) >= 2**31:
        raise ValueError("too many vertices for int32 indices")

    axes = [np.linspace(lo[a], hi[a], int(counts[a]) + 1) for a in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    strides = np.array([(ny + 1) * (nz + 1), nz + 1, 1], np.int64)
    corner_offsets = _CORNERS @ strides                                   # [8]
    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    base = (np.stack([ci, cj, ck], axis=-1).reshape(-1, 3) @ strides)     # [C]
    if split == 6:
        tets = base[:, None, None] + corner_offsets[_kuhn_template()][None]
    elif split == 5:
        parity = ((ci + cj + ck) % 2).reshape(-1)
        # the central tet takes the corners whose *global* index sum is even
        templates = np.stack([corner_offsets[_five_template(0)],
                              corner_offsets[_five_template(1)]])        # [2, 5, 4]
        tets = base[:, None, None] + templates[parity]
    else:
        raise ValueError(f"split must be 5 or 6, got {split}")
    return points.astype(np.float32), tets.reshape(-1, 4).astype(np.int32)


def _positive_int(value, name: str) -> int:
    """int(value) for a positive whole number; 2.5 or NaN is an error, not truncated."""
    v = np.asarray(value)
    if (v.shape != () or v.dtype.kind not in "iuf" or not np.isfinite(v) or v != np.round(v)
            or v < 1):
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return int(v)


def sphere_field(points, center=(0.5, 0.5, 0.5), radius: float = 0.35):
    """Signed distance to a sphere, |x - center| - radius: float32 [V]."""
    p = np.asarray(points, np.float64)
    return (np.linalg.norm(p - np.asarray(center, np.float64), axis=-1) - radius).astype(
        np.float32)


def wave_field(points, t: float = 0.0, *, frequency: float = 2.0):
    """A smooth travelling-wave field in about [-1.5, 1.5]: float32 [V].

    ``sin(w x + t) cos(w y - t) + 0.5 sin(w z + 2 t)`` with w = 2 pi frequency; `t` is a
    phase in radians, so the field repeats with period 2 pi in t.
    """
    p = np.asarray(points, np.float64)
    w = 2.0 * np.pi * frequency
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    f = np.sin(w * x + t) * np.cos(w * y - t) + 0.5 * np.sin(w * z + 2.0 * t)
    return f.astype(np.float32)


def random_field(points, seed: int = 0):
    """Independent uniform values in [-1, 1) per vertex: float32 [V]."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=np.shape(points)[0]).astype(np.float32)


def replicate(points, tets, values, k: int, *, gap: float = 0.1):
    """k x k x k translated copies of a mesh, no shared vertices (the Table 5.3 analog).

    Copies sit on a grid with spacing ``(1 + gap) * extent`` per axis (extent: the mesh's
    bounding box). values may be [V] or [..., V] (e.g. a time series [S, V]).
    Returns (points float32 [k^3 V, 3], tets int32 [k^3 T, 4], values [..., k^3 V]); copy
    c = (a * k + b) * k + d holds vertices c V .. (c + 1) V - 1 and tets c T .. (c + 1) T - 1.
    """
    k = _positive_int(k, "k")
    p = np.asarray(points, np.float64)
    t = np.asarray(tets, np.int64)
    v = np.asarray(values)
    n_vertices = p.shape[0]
    if k**3 * n_vertices >= 2**31:
        raise ValueError("too many vertices for int32 indices")
    spacing = (1.0 + gap) * (p.max(axis=0) - p.min(axis=0))
    grid = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    shifts = grid * spacing                                               # [k^3, 3]
    out_points = (p[None] + shifts[:, None]).reshape(-1, 3)
    out_tets = (t[None] + (np.arange(k**3) * n_vertices)[:, None, None]).reshape(-1, 4)
    out_values = np.tile(v, (1,) * (v.ndim - 1) + (k**3,))
    return out_points.astype(np.float32), out_tets.astype(np.int32), out_values


def _positive_orientation(points, tets):
    """Tets [T, 4] with negatively oriented ones reordered (swap of the last two vertices)."""
    p = np.asarray(points, np.float64)[tets]
    vol = np.einsum("ti,ti->t", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = np.array(tets, copy=True)
    tets[vol < 0] = tets[vol < 0][:, [0, 1, 3, 2]]
    return tets


def _import_skfem():
    try:
        import skfem
    except ImportError as err:
        raise ImportError("the Poisson test data needs scikit-fem: pip install scikit-fem "
                          "(not a jaxiso dependency)") from err
    return skfem


def _solve_unit_poisson(points, tets):
    """P1 solution of -laplace(u) = 1 with u = 0 on the boundary: float64 [V]."""
    skfem = _import_skfem()
    from skfem.models.poisson import laplace, unit_load

    # skfem wants [3, V] and [4, T]; contiguous copies avoid its conversion warning
    mesh = skfem.MeshTet(np.ascontiguousarray(np.asarray(points, np.float64).T),
                         np.ascontiguousarray(np.asarray(tets, np.int64).T))
    basis = skfem.Basis(mesh, skfem.ElementTetP1())
    stiffness = laplace.assemble(basis)
    load = unit_load.assemble(basis)
    return skfem.solve(*skfem.condense(stiffness, load, D=mesh.boundary_nodes()))


def poisson_cube(n: int = 8, *, split: int = 6, lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)):
    """-laplace(u) = 1 in a box, u = 0 on its boundary, P1 on `cube_tets(n, split=...)`.

    Needs scikit-fem. Returns (points float32 [V, 3], tets int32 [T, 4], values float32 [V]);
    on the unit cube max u = u(centre) ~ 0.0562.
    """
    points, tets = cube_tets(n, split=split, lo=lo, hi=hi)
    values = _solve_unit_poisson(points.astype(np.float64), tets)
    return points, tets, values.astype(np.float32)


def poisson_on_ball(level: int = 3):
    """-laplace(u) = 1 in the unit ball, u = 0 on the boundary, P1 on skfem's
    `MeshTet.init_ball(level)` (8^(level + 1) tets: 64, 512, 4096, ... for level 1, 2, 3).

    Needs scikit-fem. The exact solution is (1 - |x|^2) / 6; at level 3 the nodal values are
    within 0.007 of it (the mesh is a polyhedron inscribed in the ball).
    Returns (points float32 [V, 3], tets int32 [T, 4], values float32 [V]).
    """
    skfem = _import_skfem()
    mesh = skfem.MeshTet.init_ball(int(level))
    points = mesh.p.T.astype(np.float64)
    tets = _positive_orientation(points, mesh.t.T.astype(np.int64))
    values = _solve_unit_poisson(points, tets)
    return points.astype(np.float32), tets.astype(np.int32), values.astype(np.float32)


def time_series(points, steps: int, *, duration: float = 2.0 * np.pi, field=None):
    """`field(points, t)` at times t_s = s * duration / steps, s = 0 .. steps - 1.

    field defaults to `wave_field` (period 2 pi, so the default series loops seamlessly).
    Returns float32 [steps, V].
    """
    steps = _positive_int(steps, "steps")
    field = wave_field if field is None else field
    times = np.arange(steps) * (duration / steps)
    return np.stack([np.asarray(field(points, t), np.float32) for t in times])


def deform(points, t: float, *, amplitude: float = 0.02):
    """Points moved by a smooth periodic displacement (the "moving vertices" case).

    Displacement ``A L (sin(w y + t), sin(w z + 2 t), sin(w x - t))`` with L the largest
    bounding-box extent, w = 2 pi / L and A = amplitude: period 2 pi in t, and a Jacobian of
    norm <= 2 pi A (0.13 by default), small enough that cube_tets meshes stay uninverted.
    float32 [V, 3].
    """
    p = np.asarray(points, np.float64)
    size = float(np.max(p.max(axis=0) - p.min(axis=0))) if p.size else 0.0
    size = size if size > 0 else 1.0
    w = 2.0 * np.pi / size
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    shift = np.stack([np.sin(w * y + t), np.sin(w * z + 2.0 * t), np.sin(w * x - t)], -1)
    return (p + amplitude * size * shift).astype(np.float32)
