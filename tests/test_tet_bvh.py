"""Tet mesh container and implicit BVH: validation, quality reports, the flat pre-order layout
(checked by an independent recursive walk), 4D bounds against brute force, refits (numpy and
jax), importers, memory and stats reports."""

import dataclasses
import itertools
import warnings

import jax
import meshio
import numpy as np
import pytest

from jaxiso.tetra._bvh import BVH, build_bvh, bvh_stats, memory_report, refit, refit_jax
from jaxiso.tetra._mesh import TetMesh, from_meshio, from_pyvista, tet_mesh


def cube_mesh(k, jitter=0.0, seed=0):
    """Unit cube cut into k^3 cells of 6 Kuhn tets each, all positively oriented; vertices
    moved by up to `jitter` cell widths (jitter < 0.25 keeps every tet positive)."""
    g = np.arange(k + 1)
    points = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) / k
    cells = np.stack(np.meshgrid(g[:-1], g[:-1], g[:-1], indexing="ij"), -1).reshape(-1, 3)

    def vid(ijk):
        return (ijk[:, 0] * (k + 1) + ijk[:, 1]) * (k + 1) + ijk[:, 2]

    tets = []
    for perm in itertools.permutations(range(3)):
        path, ids = cells.copy(), [vid(cells)]
        for axis in perm:
            path = path.copy()
            path[:, axis] += 1
            ids.append(vid(path))
        ids = np.stack(ids, 1)
        # The Kuhn tet along `perm` has orientation sign(perm): swap two vertices if odd.
        inversions = sum(perm[i] > perm[j] for i in range(3) for j in range(i + 1, 3))
        tets.append(ids[:, [0, 1, 3, 2]] if inversions % 2 else ids)
    tets = np.concatenate(tets)
    if jitter:
        points = points + np.random.default_rng(seed).uniform(-jitter, jitter, points.shape) / k
    return points, tets


def quiet_mesh(points, tets, values):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the fixtures must be clean meshes
        return tet_mesh(points, tets, values)


@pytest.fixture(scope="module")
def mesh():
    points, tets = cube_mesh(3, jitter=0.2, seed=1)
    values = np.random.default_rng(2).normal(size=(3, len(points)))
    return quiet_mesh(points, tets, values)


def walk(bvh):
    """Independent recursive walk with left = i + 1, right = skip[i + 1]: checks the visit
    order is 0..N-1 (pre-order) and skip[i] ends i's subtree; returns per node its slot
    range [begin, end) in `order`."""
    skip, first, count = (np.asarray(a) for a in (bvh.skip, bvh.first, bvh.count))
    visited, ranges = [], {}

    def visit(i):
        visited.append(i)
        if count[i] > 0:
            ranges[i] = (first[i], first[i] + count[i])
            nxt = i + 1
        else:
            after_left = visit(i + 1)
            assert skip[i + 1] == after_left
            nxt = visit(skip[i + 1])
            assert ranges[i + 1][1] == ranges[skip[i + 1]][0]  # children's ranges abut
            ranges[i] = (ranges[i + 1][0], ranges[skip[i + 1]][1])
        assert skip[i] == nxt
        return nxt

    assert visit(0) == bvh.n_nodes
    assert visited == list(range(bvh.n_nodes))
    return ranges


def brute_bounds(points, tets, values, ids):
    """lo, hi [4] over the vertices of tets[ids], in float64."""
    v = np.unique(np.asarray(tets)[ids].ravel())
    xyzv = np.concatenate([np.asarray(points, np.float64)[v],
                           np.asarray(values, np.float64)[v, None]], 1)
    return xyzv.min(0), xyzv.max(0)


def assert_bounds(bvh, points, tets, values):
    """Every node's bounds equal brute-force bounds over its subtree's tets (so leaves are
    tight and interior nodes are the union of their children)."""
    order = np.asarray(bvh.order)
    for i, (b, e) in walk(bvh).items():
        lo, hi = brute_bounds(points, tets, values, order[b:e])
        np.testing.assert_array_equal(np.asarray(bvh.lo[i], np.float64), lo, err_msg=str(i))
        np.testing.assert_array_equal(np.asarray(bvh.hi[i], np.float64), hi, err_msg=str(i))


def independent_volumes(points, tets):
    p = np.asarray(points, np.float64)[np.asarray(tets)]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6


# ---------------------------------------------------------------------------- mesh


def test_fixture_mesh_is_positive_and_complete(mesh):
    vol = independent_volumes(mesh.points, mesh.tets)
    assert (vol > 0).all()
    assert np.isclose(vol.sum(), 1.0, atol=0.3)  # jittered boundary moves the volume a bit
    assert mesh.points.dtype == np.float32 and mesh.tets.dtype == np.int32
    assert mesh.values.shape == (3, 64) and mesh.n_steps == 3
    assert mesh.nbytes == 64 * 12 + 162 * 16 + 3 * 64 * 4


def test_values_of_one_step_become_s_equals_1():
    points, tets = cube_mesh(1)
    m = quiet_mesh(points, tets, np.arange(8.0))
    assert m.values.shape == (1, 8) and m.n_steps == 1
    assert m.with_values(np.ones((4, 8))).n_steps == 4
    np.testing.assert_array_equal(m.tets, tets)  # nothing reoriented in a clean mesh


@pytest.mark.parametrize("change, error, words", [
    (dict(points=np.zeros((8, 2))), ValueError, "[V, 3]"),
    (dict(tets=np.zeros((3, 3), int)), ValueError, "[T, 4]"),
    (dict(tets=np.zeros((0, 4), int)), ValueError, "T == 0"),
    (dict(tets=np.zeros((2, 4))), TypeError, "integer"),
    (dict(values=np.zeros(7)), ValueError, "V = 8"),
    (dict(values=np.zeros((2, 3, 8))), ValueError, "[S, V]"),
])
def test_shape_errors(change, error, words):
    points, tets = cube_mesh(1)
    args = dict(points=points, tets=tets, values=np.zeros(8)) | change
    with pytest.raises(error, match=words.replace("[", r"\[").replace("]", r"\]")):
        tet_mesh(**args)


def test_bad_tet_index_names_first_bad_tet():
    points, tets = cube_mesh(1)
    tets = tets.copy()
    tets[4, 2], tets[2, 0] = 8, -1
    with pytest.raises(IndexError, match=r"tet 2 .*outside \[0, 8\) \(2 bad tets\)"):
        tet_mesh(points, tets, np.zeros(8))


def test_non_finite_points_and_values_are_rejected():
    points, tets = cube_mesh(1)
    bad = points.copy()
    bad[5, 1], bad[6, 0] = np.nan, np.inf
    with pytest.raises(ValueError, match=r"2 points .*first: point 5"):
        tet_mesh(bad, tets, np.zeros(8))
    big = points.copy()
    big[3, 2] = 1e300  # finite in float64 but not in float32
    with pytest.raises(ValueError, match=r"1 points .*first: point 3"):
        tet_mesh(big, tets, np.zeros(8))
    values = np.zeros((2, 8))
    values[1, 4] = np.nan
    with pytest.raises(ValueError, match=r"1 values .*step 1, vertex 4"):
        tet_mesh(points, tets, values)
    m = quiet_mesh(points, tets, np.zeros(8))
    with pytest.raises(ValueError, match="non-finite"):
        m.with_values(values)
    with pytest.raises(ValueError, match="non-finite"):
        m.with_points(bad)


def flawed_mesh():
    """A 2^3 cube mesh plus a flat tet (4 coplanar corners of a face), a tet with a repeated
    vertex, and two of its tets turned inside out."""
    points, tets = cube_mesh(2)
    flat = [0, 2, 6, 8]  # the x = 0 face's corners: i = 0, (j, l) in {0, 2}^2
    assert np.allclose(points[flat, 0], 0)
    tets = np.concatenate([tets, [flat, [1, 1, 4, 5]]])
    tets[[3, 7]] = tets[[3, 7]][:, [1, 0, 2, 3]]
    return points, tets


def test_degenerate_and_inverted_are_reported_and_handled():
    points, tets = flawed_mesh()
    assert (independent_volumes(points, tets)[[3, 7]] < 0).all()
    with pytest.warns(UserWarning) as record:
        m = tet_mesh(points, tets, np.arange(len(points), dtype=float))
    text = " ".join(str(r.message) for r in record)
    assert "2 inverted tets reoriented (first: tet 3)" in text
    assert "2 degenerate tets (1 with a repeated vertex; first: tet 48)" in text
    vol = independent_volumes(m.points, m.tets)
    assert (vol[:48] > 0).all() and np.allclose(vol[48:], 0)
    assert sorted(m.tets[3]) == sorted(tets[3])  # same vertices, other order
    rep = m.report()
    assert rep["degenerate"] == 2 and rep["repeated_vertex"] == 1 and rep["zero_volume"] == 1
    assert rep["inverted"] == 0 and rep["reoriented"] == 2 and rep["first_degenerate"] == 48
    assert rep["tets"] == 50 and rep["vertices"] == 27
    np.testing.assert_array_equal(m.degenerate(), np.arange(50) >= 48)
    for method in ("bih", "sah"):
        bvh = build_bvh(m, method=method, leaf_size=4)
        np.testing.assert_array_equal(np.sort(bvh.order), np.arange(48))
        assert_bounds(bvh, m.points, m.tets, m.values[0])


def test_with_points_reorients_and_warns():
    points, tets = cube_mesh(2)
    m = quiet_mesh(points, tets, np.zeros(len(points)))
    mirrored = points * np.array([-1.0, 1.0, 1.0])  # a reflection inverts every tet
    with pytest.warns(UserWarning, match="48 inverted tets reoriented"):
        moved = m.with_points(mirrored)
    assert (independent_volumes(moved.points, moved.tets) > 0).all()
    assert moved.reoriented == 48 and moved.report()["inverted"] == 0
    with pytest.raises(ValueError, match="vertices"):
        m.with_points(points[:-1])


def test_tiny_but_valid_tets_are_not_degenerate():
    """The threshold is relative to the mesh size: a 1e-3 scaled cube is still clean."""
    points, tets = cube_mesh(2)
    m = quiet_mesh(points * 1e-3, tets, np.zeros(len(points)))
    assert m.report()["degenerate"] == 0


def test_mesh_is_a_pytree(mesh):
    leaves, tree = jax.tree.flatten(mesh)
    assert len(leaves) == 3
    again = jax.tree.unflatten(tree, leaves)
    assert isinstance(again, TetMesh)
    total = jax.jit(lambda m: m.points.sum() + m.values.sum())(mesh)
    assert np.isclose(total, mesh.points.sum() + mesh.values.sum(), rtol=1e-5)


# ---------------------------------------------------------------------------- importers


def test_from_meshio_tetra_only_with_named_values():
    points, tets = cube_mesh(2)
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=len(points)), rng.normal(size=(len(points), 1))
    mio = meshio.Mesh(points, [("triangle", [[0, 1, 2]]), ("tetra", tets[:20]),
                               ("tetra", tets[20:])], point_data={"a": a, "b": b})
    with pytest.warns(UserWarning, match=r"\['triangle'\]"):
        m = from_meshio(mio, values="a")
    np.testing.assert_array_equal(m.tets, tets)
    np.testing.assert_array_equal(m.values[0], a.astype(np.float32))
    with pytest.warns(UserWarning):
        two = from_meshio(mio, values=["a", "b"])
    np.testing.assert_array_equal(two.values, np.stack([a, b[:, 0]]).astype(np.float32))
    with pytest.warns(UserWarning):
        arr = from_meshio(mio, values=np.ones((2, len(points))))
    assert arr.n_steps == 2
    with pytest.warns(UserWarning), pytest.raises(ValueError, match=r"\['a', 'b'\]"):
        from_meshio(mio)  # two candidates: the name must be given
    with pytest.warns(UserWarning), pytest.raises(ValueError, match="no 'tetra'"):
        from_meshio(meshio.Mesh(points, [("triangle", [[0, 1, 2]])]), values="a")


class FakeGrid:
    """The attributes of pyvista.UnstructuredGrid that from_pyvista reads (pyvista itself is
    not installed here)."""

    def __init__(self, points, tets, point_data, legacy=False, active=None):
        self.points = points
        self.point_data = point_data
        self.active_scalars_name = active
        triangle = np.array([[0, 1, 2]])
        if legacy:  # flat VTK cell array [n, ids...] and per-cell types
            cells = [np.r_[4, t] for t in tets] + [np.r_[3, triangle[0]]]
            self.cells = np.concatenate(cells)
            self.celltypes = np.array([10] * len(tets) + [5], np.uint8)
        else:
            self.cells_dict = {10: tets, 5: triangle}


@pytest.mark.parametrize("legacy", [False, True])
def test_from_pyvista_fake_grid(legacy):
    points, tets = cube_mesh(2)
    s = np.random.default_rng(4).normal(size=len(points))
    grid = FakeGrid(points, tets, {"s": s, "t": -s}, legacy=legacy, active="t")
    with pytest.warns(UserWarning, match=r"VTK types \[5\]"):
        m = from_pyvista(grid, scalars="s")
    np.testing.assert_array_equal(m.tets, tets)
    np.testing.assert_array_equal(m.values[0], s.astype(np.float32))
    with pytest.warns(UserWarning):
        active = from_pyvista(grid)
    np.testing.assert_array_equal(active.values[0], (-s).astype(np.float32))


# ---------------------------------------------------------------------------- BVH


@pytest.mark.parametrize("method", ["bih", "sah"])
@pytest.mark.parametrize("leaf_size", [1, 3, 8])
def test_layout_and_bounds(mesh, method, leaf_size):
    bvh = build_bvh(mesh, method=method, leaf_size=leaf_size, step=1)
    n = bvh.n_nodes
    assert (bvh.lo.dtype, bvh.skip.dtype, bvh.first.dtype, bvh.count.dtype,
            bvh.order.dtype) == (np.float32, np.int32, np.int32, np.int32, np.int32)
    assert bvh.lo.shape == bvh.hi.shape == (n, 4)
    assert bvh.skip.shape == bvh.first.shape == bvh.count.shape == (n,)
    np.testing.assert_array_equal(np.sort(bvh.order), np.arange(mesh.n_tets))
    leaves = bvh.count > 0
    assert bvh.count[leaves].max() <= leaf_size
    assert leaves.sum() * 2 - 1 == n  # a full binary tree
    ranges = walk(bvh)
    # Leaves' ranges tile the order array in pre-order.
    leaf_ranges = [ranges[i] for i in np.flatnonzero(leaves)]
    assert leaf_ranges[0][0] == 0 and leaf_ranges[-1][1] == mesh.n_tets
    assert all(a[1] == b[0] for a, b in zip(leaf_ranges, leaf_ranges[1:]))
    np.testing.assert_array_equal(bvh.first, [ranges[i][0] for i in range(n)])
    assert_bounds(bvh, mesh.points, mesh.tets, mesh.values[1])
    # Depth of each node from the walk's parent links.
    depth = np.zeros(n, int)
    for i in np.flatnonzero(~leaves):
        depth[[i + 1, bvh.skip[i + 1]]] = depth[i] + 1
    np.testing.assert_array_equal(bvh.depth, depth)


@pytest.mark.parametrize("method", ["bih", "sah"])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_separated_clusters_split_at_the_root(method, axis):
    """Two blocks far apart along `axis`: the root's children must hold one block each."""
    points, tets = cube_mesh(2)
    shift = np.full(3, 0.3)
    shift[axis] = 5.0
    both = np.concatenate([points, points + shift])
    tets = np.concatenate([tets, tets + len(points)])
    m = quiet_mesh(both, tets, np.zeros(len(both)))
    bvh = build_bvh(m, method=method, leaf_size=4)
    a, b = sorted([1, bvh.skip[1]], key=lambda i: bvh.lo[i, axis])
    assert bvh.hi[a, axis] <= 1.0 and bvh.lo[b, axis] >= 5.0
    assert bvh.count[1] == 0 and bvh.count[bvh.skip[1]] == 0


@pytest.mark.parametrize("method", ["bih", "sah"])
def test_equal_centroids_still_respect_leaf_size(method):
    """20 copies of one tet (plus a clean block) have one centroid: split by count."""
    points, tets = cube_mesh(2)
    tets = np.concatenate([tets, np.repeat(tets[:1], 20, axis=0)])
    m = quiet_mesh(points, tets, np.zeros(len(points)))
    bvh = build_bvh(m, method=method, leaf_size=3)
    assert bvh.count.max() <= 3
    np.testing.assert_array_equal(np.sort(bvh.order), np.arange(len(tets)))
    walk(bvh)


def test_build_arguments_are_checked(mesh):
    with pytest.raises(ValueError, match="method"):
        build_bvh(mesh, method="median")
    with pytest.raises(ValueError, match="leaf_size"):
        build_bvh(mesh, leaf_size=0)
    with pytest.raises(IndexError, match="step 3"):
        build_bvh(mesh, step=3)


@pytest.mark.parametrize("method", ["bih", "sah"])
def test_refit_to_other_steps_matches_fresh_builds(mesh, method):
    """Both builds use geometry only, so a fresh build for step 2 has the same tree and must
    equal the refit of the step-0 tree."""
    built0 = build_bvh(mesh, method=method, leaf_size=4, step=0)
    refitted = refit(built0, mesh, 2)
    fresh = build_bvh(mesh, method=method, leaf_size=4, step=2)
    for name in ("skip", "first", "count", "order", "lo", "hi"):
        np.testing.assert_array_equal(getattr(refitted, name), getattr(fresh, name), name)
    assert not np.array_equal(built0.lo[:, 3], refitted.lo[:, 3])  # the values did change
    np.testing.assert_array_equal(built0.lo[:, :3], refitted.lo[:, :3])
    assert_bounds(refitted, mesh.points, mesh.tets, mesh.values[2])


def test_refit_after_moving_points(mesh):
    bvh = build_bvh(mesh, method="bih", leaf_size=4)
    rng = np.random.default_rng(5)
    moved = mesh.with_points(mesh.points + rng.uniform(-0.02, 0.02, mesh.points.shape))
    refitted = refit(bvh, moved, 1)
    assert not np.array_equal(refitted.lo[:, :3], bvh.lo[:, :3])
    assert_bounds(refitted, moved.points, moved.tets, moved.values[1])


@pytest.mark.parametrize("method", ["bih", "sah"])
def test_refit_jax_matches_numpy(mesh, method):
    bvh = build_bvh(mesh, method=method, leaf_size=3)
    rng = np.random.default_rng(6)
    moved = mesh.with_points(mesh.points + rng.uniform(-0.02, 0.02, mesh.points.shape))
    expected = refit(bvh, moved, 2)
    got = jax.jit(refit_jax)(bvh, moved.points, moved.values[2], moved.tets)
    assert isinstance(got, BVH) and got.level_sizes == bvh.level_sizes
    np.testing.assert_array_equal(np.asarray(got.lo), expected.lo)
    np.testing.assert_array_equal(np.asarray(got.hi), expected.hi)
    np.testing.assert_array_equal(np.asarray(got.skip), bvh.skip)


def test_bvh_is_a_pytree_with_static_meta(mesh):
    bvh = build_bvh(mesh, method="sah", leaf_size=5)
    leaves, tree = jax.tree.flatten(bvh)
    assert len(leaves) == 5  # bounds, links, order, depth, levels
    again = jax.tree.unflatten(tree, leaves)
    assert (again.leaf_size, again.method) == (5, "sah")
    bumped = jax.tree.map(lambda a: a, dataclasses.replace(bvh, leaf_size=7))
    assert bumped.leaf_size == 7


def test_stats_and_memory_report(mesh):
    bvh = build_bvh(mesh, leaf_size=4)
    ranges = walk(bvh)
    leaf_sizes = [e - b for i, (b, e) in ranges.items() if bvh.count[i] > 0]
    stats = bvh_stats(bvh)
    assert stats["nodes"] == len(ranges) and stats["leaves"] == len(leaf_sizes)
    assert stats["max_leaf_size"] == max(leaf_sizes) and stats["tets"] == 162
    assert np.isclose(stats["mean_leaf_size"], np.mean(leaf_sizes))
    assert stats["depth"] >= np.ceil(np.log2(len(leaf_sizes)))

    rep = memory_report(bvh, mesh)
    n = bvh.n_nodes
    interior = n - len(leaf_sizes)
    assert rep["points_bytes"] == 64 * 3 * 4 and rep["tets_bytes"] == 162 * 4 * 4
    assert rep["values_bytes_per_step"] == 64 * 4 and rep["values_bytes"] == 3 * 64 * 4
    assert rep["mesh_bytes"] == 768 + 2592 + 768
    # bounds (lo, hi); links (kind, first, right, skip, 8 escapes); depth; levels
    assert rep["bvh_node_bytes"] == n * (2 * 16 + 12 * 4 + 4) + interior * 4
    assert rep["bvh_order_bytes"] == 162 * 4
    assert rep["total_bytes"] == rep["mesh_bytes"] + rep["bvh_bytes"]
    assert np.isclose(rep["overhead_pct"], 100 * rep["bvh_bytes"] / rep["mesh_bytes"])
    assert np.isclose(rep["per_step_overhead_pct"], 3 * rep["overhead_pct"])


@pytest.mark.parametrize("method", ["bih", "sah"])
def test_escape_pointers_walk_the_tree_near_child_first_for_every_octant(mesh, method):
    bvh = build_bvh(mesh, method=method, leaf_size=3)
    skip, count = np.asarray(bvh.skip), np.asarray(bvh.count)
    centre = (np.asarray(bvh.lo, np.float64) + np.asarray(bvh.hi, np.float64))[:, :3] / 2
    escape, axes = np.asarray(bvh.escape), np.asarray(bvh.split_axis)
    n = bvh.n_nodes
    for octant in range(8):
        sign = np.array([-1.0 if octant >> (2 - a) & 1 else 1.0 for a in range(3)])
        expected = []

        def visit(i):
            expected.append(i)
            if count[i]:
                return
            left, right = i + 1, skip[i + 1]
            gap = centre[right] - centre[left]
            axis = int(np.argmax(np.abs(gap)))
            assert axes[i] // 2 == axis
            # the child whose centre comes first along the ray's direction on that axis
            first, second = (right, left) if gap[axis] * sign[axis] < 0 else (left, right)
            if gap[axis] != 0:
                assert (centre[first] - centre[second])[axis] * sign[axis] < 0
            visit(first)
            visit(second)

        visit(0)
        walked, node = [], 0
        while node < n:  # a ray that enters every node
            walked.append(node)
            if count[node]:
                node = escape[octant, node]
            else:
                axis, lower_right = divmod(int(axes[node]), 2)
                right = (octant >> (2 - axis) & 1) ^ lower_right
                node = skip[node + 1] if right else node + 1
            assert len(walked) <= n
        assert walked == expected, octant
