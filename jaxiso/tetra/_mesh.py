"""Tetrahedral meshes with per-vertex scalar fields (seed ch. 5).

A `TetMesh` holds vertex positions, tets (4 vertex indices each) and S time steps of a
per-vertex scalar field. Build it with `tet_mesh` (alias `TetMesh.create`), `from_meshio`
or `from_pyvista`, which validate the input:

* shapes (``ValueError``), real coordinates and values and integer tets (``TypeError``),
  tet indices in [0, V) (``IndexError`` naming the first bad tet), at least one tet;
* non-finite coordinates or values: ``ValueError`` with the count and the first index
  (non-finite values are rejected, not masked: a NaN vertex would poison every min/max
  bound of the implicit BVH above it);
* inverted tets (negative signed volume) are reoriented by swapping their last two vertices;
* degenerate tets (a repeated vertex, or ``|volume| <= 1e-12 * bbox_diag**3``) are kept in
  the mesh, so vertex and tet indices stay those of the input, but `build_bvh` leaves them
  out: they bound no volume, so no ray can cross their interior. A mesh whose tets are
  *all* degenerate has nothing to render: ``ValueError`` (here and in `build_bvh`).

Both are reported by a ``UserWarning`` with counts and by `TetMesh.report()`.

The arrays are stored as numpy (float32 / int32), which jax accepts as pytree leaves. The
dataclass constructor ``TetMesh(points, tets, values)`` runs the same shape, dtype, index
and finiteness checks when it is given host data (numpy arrays or lists; values [V] become
one step [1, V]) but does not reorient or look for degenerate tets. jax arrays and anything
else (tracers, axis specs) pass unchecked, so jit, vmap and `jax.tree.map` can rebuild
meshes from them.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .._core import pytree_dataclass

__all__ = ["TetMesh", "tet_mesh", "from_meshio", "from_pyvista", "signed_volumes",
           "corner_points", "degenerate_mask", "check_renderable", "DEGENERATE_RTOL"]

# A tet is degenerate when |volume| <= DEGENERATE_RTOL * (bbox diagonal)^3 of the mesh.
DEGENERATE_RTOL = 1e-12

# VTK's cell type id of a linear tetrahedron (pyvista.CellType.TETRA == 10).
VTK_TETRA = 10


@pytree_dataclass
class TetMesh:
    """A tetrahedral mesh with S time steps of a per-vertex scalar field.

    Attributes:
      points: float32 [V, 3] vertex positions.
      tets: int32 [T, 4] vertex indices, positively oriented after `tet_mesh`.
      values: float32 [S, V] scalar field per time step ([V] given to the constructor is
        stored as [1, V]).
      reoriented: static int, how many inverted tets `tet_mesh` / `with_points` swapped.
    """

    points: np.ndarray
    tets: np.ndarray
    values: np.ndarray
    reoriented: int = dataclasses.field(default=0, metadata=dict(static=True))

    def __post_init__(self):
        # Host data is what a user hands in: check it here, where a bad shape is still easy
        # to name, rather than as an IndexError deep in the BVH build. jax arrays, tracers
        # and pytree placeholders come from jit / vmap / tree.map and pass as they are.
        if not all(isinstance(a, (np.ndarray, list, tuple))
                   for a in (self.points, self.tets, self.values)):
            return
        points = _checked_points(self.points)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", _checked_tets(self.tets, points.shape[0]))
        object.__setattr__(self, "values", _checked_values(self.values, points.shape[0]))

    @staticmethod
    def create(points, tets, values) -> TetMesh:
        """Checked constructor; see `tet_mesh`."""
        return tet_mesh(points, tets, values)

    @property
    def n_points(self) -> int:
        return int(np.shape(self.points)[0])

    @property
    def n_tets(self) -> int:
        return int(np.shape(self.tets)[0])

    @property
    def n_steps(self) -> int:
        return int(np.shape(self.values)[0])

    @property
    def nbytes(self) -> int:
        """Bytes of points, tets and all value steps."""
        return int(sum(np.asarray(a).nbytes for a in (self.points, self.tets, self.values)))

    def with_values(self, values) -> TetMesh:
        """A mesh with a new scalar field ([V] or [S, V]), same points and tets."""
        return dataclasses.replace(self, values=_checked_values(values, self.n_points))

    def with_points(self, points) -> TetMesh:
        """A mesh with moved vertices (float [V, 3]), same tets (Schema II deformation).

        Tets the motion inverted are reoriented again (vertex order only, so tet indices
        and any BVH `order` stay valid); a warning counts them and new degenerate tets.
        Host-side (numpy); under jit use ``dataclasses.replace(mesh, points=...)``.
        """
        points = _checked_points(points)
        if points.shape[0] != self.n_points:
            raise ValueError(f"points has {points.shape[0]} vertices, the mesh {self.n_points}")
        tets, flipped, degenerate = _orient(points, np.asarray(self.tets))
        _warn_quality(flipped, degenerate, points, tets)
        return TetMesh(points, tets, self.values, self.reoriented + int(flipped.sum()))

    def degenerate(self) -> np.ndarray:
        """bool [T]: tets left out of the BVH (repeated vertex or ~zero volume)."""
        return degenerate_mask(self.points, self.tets)

    def report(self) -> dict:
        """Mesh quality counts: tets, vertices, steps, degenerate (of which repeated_vertex
        and zero_volume), inverted (now), reoriented (by construction), first_degenerate
        (tet index or None), value_range over all steps."""
        points, tets = np.asarray(self.points), np.asarray(self.tets)
        repeated = _repeated_vertex(tets)
        volumes, degenerate = _quality(points, tets)
        inverted = (volumes < 0) & ~degenerate
        values = np.asarray(self.values)
        return {
            "tets": self.n_tets,
            "vertices": self.n_points,
            "steps": self.n_steps,
            "degenerate": int(degenerate.sum()),
            "repeated_vertex": int(repeated.sum()),
            "zero_volume": int((degenerate & ~repeated).sum()),
            "inverted": int(inverted.sum()),
            "reoriented": int(self.reoriented),
            "first_degenerate": _first(degenerate),
            "value_range": (float(values.min()), float(values.max())),
        }


def signed_volumes(points, tets) -> np.ndarray:
    """float64 [T] signed volumes (b - a) . ((c - a) x (d - a)) / 6 of tets [T, 4]."""
    a, b, c, d = corner_points(np.asarray(points, np.float64), tets)
    e1, e2, e3 = b - a, c - a, d - a
    # Component-wise triple product: much faster than a batched det on [T, 3, 3].
    cross = (e2[:, 1] * e3[:, 2] - e2[:, 2] * e3[:, 1],
             e2[:, 2] * e3[:, 0] - e2[:, 0] * e3[:, 2],
             e2[:, 0] * e3[:, 1] - e2[:, 1] * e3[:, 0])
    return (e1[:, 0] * cross[0] + e1[:, 1] * cross[1] + e1[:, 2] * cross[2]) / 6.0


def corner_points(points, tets) -> tuple:
    """The four corners of every tet: a tuple of 4 arrays [T, 3] (one gather per corner
    keeps them contiguous, unlike points[tets] of shape [T, 4, 3])."""
    points, tets = np.asarray(points), np.asarray(tets)
    return tuple(points[tets[:, j]] for j in range(4))


def degenerate_mask(points, tets) -> np.ndarray:
    """bool [T]: a repeated vertex or |volume| <= DEGENERATE_RTOL * bbox_diag^3."""
    return _quality(points, tets)[1]


def _quality(points, tets):
    """(signed volumes float64 [T], degenerate bool [T])."""
    points, tets = np.asarray(points), np.asarray(tets)
    diag = float(np.linalg.norm(np.ptp(points.astype(np.float64), axis=0)))
    volumes = signed_volumes(points, tets)
    tiny = np.abs(volumes) <= DEGENERATE_RTOL * diag**3
    return volumes, tiny | _repeated_vertex(tets)


def tet_mesh(points, tets, values) -> TetMesh:
    """A validated `TetMesh` (float32 points [V, 3], int32 tets [T, 4], values [V] or
    [S, V]); inverted tets are reoriented and quality problems warned about (module doc)."""
    points = _checked_points(points)
    tets = _checked_tets(tets, points.shape[0])
    values = _checked_values(values, points.shape[0])
    tets, flipped, degenerate = _orient(points, tets)
    check_renderable(degenerate, tets)
    _warn_quality(flipped, degenerate, points, tets)
    return TetMesh(points, tets, values, int(flipped.sum()))


def from_meshio(mesh, values=None) -> TetMesh:
    """A `TetMesh` from a `meshio.Mesh`: its "tetra" cell blocks (others are ignored with a
    warning naming them) and `values`: a point_data name, a list of names (one time step
    each) or an array [V] / [S, V]. None picks the only point_data array."""
    blocks = [np.asarray(c.data) for c in mesh.cells if c.type == "tetra"]
    ignored = sorted({c.type for c in mesh.cells if c.type != "tetra"})
    if ignored:
        warnings.warn(f"from_meshio: ignoring non-tetra cell blocks {ignored}", UserWarning,
                      stacklevel=2)
    if not blocks:
        raise ValueError("from_meshio: the mesh has no 'tetra' cells")
    values = _named_values(values, dict(mesh.point_data), "from_meshio")
    return tet_mesh(mesh.points, np.concatenate(blocks), values)


def from_pyvista(grid, scalars=None) -> TetMesh:
    """A `TetMesh` from a `pyvista.UnstructuredGrid`: its TETRA cells (others are ignored
    with a warning naming their VTK type ids) and point scalars `scalars` (a name, a list of
    names as time steps, an array, or None for the active scalars).

    Reads only `grid.points`, `grid.cells_dict` ({VTK type id: [n, k] ids}) or, where that
    is missing, the flat `grid.cells` / `grid.celltypes` arrays, and `grid.point_data`.
    """
    cells = _pyvista_cells(grid)
    ignored = sorted(int(k) for k in cells if int(k) != VTK_TETRA)
    if ignored:
        warnings.warn(f"from_pyvista: ignoring non-tetra cells of VTK types {ignored}",
                      UserWarning, stacklevel=2)
    tets = [np.asarray(v) for k, v in cells.items() if int(k) == VTK_TETRA]
    if not tets:
        raise ValueError("from_pyvista: the grid has no TETRA cells")
    if scalars is None and getattr(grid, "active_scalars_name", None):
        scalars = grid.active_scalars_name
    values = _named_values(scalars, dict(grid.point_data), "from_pyvista")
    return tet_mesh(grid.points, np.concatenate(tets), values)


# ---------------------------------------------------------------------------- helpers


def _first(mask) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


def _repeated_vertex(tets) -> np.ndarray:
    s = np.sort(tets, axis=1)
    return np.any(s[:, 1:] == s[:, :-1], axis=1)


def check_renderable(degenerate, tets):
    """ValueError when every tet is degenerate: the BVH would hold no tet at all."""
    if degenerate.size and degenerate.all():
        repeated = int(_repeated_vertex(np.asarray(tets)).sum())
        raise ValueError(f"all {degenerate.size} tets are degenerate (zero volume; {repeated}"
                         " with a repeated vertex); nothing to render")


def _real(a, name) -> np.ndarray:
    """np.asarray(a), TypeError unless it holds real numbers (a complex array would lose
    its imaginary part silently in the float32 cast)."""
    a = np.asarray(a)
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{name} must hold real numbers, got dtype {a.dtype}")
    return a


def _checked_points(points) -> np.ndarray:
    points = _real(points, "points")
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"points must be [V, 3] with V >= 1, got shape {points.shape}")
    # Cast first: float64 coordinates beyond float32's range become inf and are caught here.
    with np.errstate(over="ignore"):
        points = points.astype(np.float32)
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise ValueError(f"{int(bad.sum())} points have non-finite coordinates "
                         f"(first: point {_first(bad)})")
    return points


def _checked_tets(tets, n_points) -> np.ndarray:
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must be [T, 4], got shape {tets.shape}")
    if tets.shape[0] == 0:
        raise ValueError("the mesh has no tets (T == 0)")
    if tets.dtype.kind not in "iu":
        raise TypeError(f"tets must hold integer vertex indices, got dtype {tets.dtype}")
    bad = np.any((tets < 0) | (tets >= n_points), axis=1)
    if bad.any():
        i = _first(bad)
        raise IndexError(f"tet {i} has vertex indices {tets[i].tolist()} outside "
                         f"[0, {n_points}) ({int(bad.sum())} bad tets)")
    return tets.astype(np.int32)


def _checked_values(values, n_points) -> np.ndarray:
    values = _real(values, "values")
    given = values.shape
    if values.ndim == 1:
        values = values[None]
    if values.ndim != 2 or values.shape[1] != n_points or values.shape[0] == 0:
        raise ValueError(f"values must be [V] or [S, V] with V = {n_points}, "
                         f"got shape {given}")
    with np.errstate(over="ignore"):
        values = values.astype(np.float32)
    bad = ~np.isfinite(values)
    if bad.any():
        step, vertex = np.argwhere(bad)[0]
        raise ValueError(f"{int(bad.sum())} values are non-finite "
                         f"(first: step {step}, vertex {vertex})")
    return values


def _orient(points, tets):
    """(tets with inverted ones reoriented, flipped mask, degenerate mask)."""
    volumes, degenerate = _quality(points, tets)
    flipped = (volumes < 0) & ~degenerate
    if flipped.any():
        tets = tets.copy()
        tets[flipped] = tets[flipped][:, [0, 1, 3, 2]]
    return tets, flipped, degenerate


def _warn_quality(flipped, degenerate, points, tets):
    parts = []
    if flipped.any():
        parts.append(f"{int(flipped.sum())} inverted tets reoriented (first: tet "
                     f"{_first(flipped)})")
    if degenerate.any():
        repeated = int(_repeated_vertex(tets).sum())
        parts.append(f"{int(degenerate.sum())} degenerate tets ({repeated} with a repeated "
                     f"vertex; first: tet {_first(degenerate)}) kept but left out of the BVH")
    if parts:
        warnings.warn("TetMesh: " + "; ".join(parts), UserWarning, stacklevel=3)


def _named_values(values, point_data, who):
    """An array [V] / [S, V] from a point_data name, a list of names, or an array."""
    if values is None:
        if len(point_data) != 1:
            raise ValueError(f"{who}: pass values= one of the point data {sorted(point_data)}")
        values = next(iter(point_data))
    if isinstance(values, str):
        values = [values]
    if isinstance(values, (list, tuple)) and values and all(isinstance(v, str) for v in values):
        missing = [v for v in values if v not in point_data]
        if missing:
            raise KeyError(f"{who}: no point data {missing}; have {sorted(point_data)}")
        # Point data of one component may come as [V, 1].
        return np.stack([np.asarray(point_data[v]).reshape(-1) for v in values])
    return values


def _pyvista_cells(grid) -> dict:
    """{VTK type id: int [n, k]} from `cells_dict`, or from the flat legacy cell array
    [k0, ids..., k1, ids...] with `celltypes`."""
    cells = getattr(grid, "cells_dict", None)
    if cells is not None:
        return dict(cells)
    flat, types = np.asarray(grid.cells), np.asarray(grid.celltypes)
    if np.all(types == VTK_TETRA) and flat.size == 5 * types.size:
        return {VTK_TETRA: flat.reshape(-1, 5)[:, 1:]}
    out, pos = {}, 0
    for t in types:  # one short step per cell: only for grids without cells_dict
        k = int(flat[pos])
        out.setdefault(int(t), []).append(flat[pos + 1:pos + 1 + k])
        pos += 1 + k
    return {t: np.stack(v) for t, v in out.items()}
