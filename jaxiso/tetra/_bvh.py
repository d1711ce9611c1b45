"""The implicit BVH over a tet mesh (seed Sec. 5.4): a BVH whose nodes bound x, y, z and
the scalar value, so a traversal culls every subtree whose value range misses the isovalue.

Layout (N nodes in depth-first pre-order; what the traversal relies on). A node is two
rows, so that a traversal step reads one float row and one int row:

* ``bounds`` float32 [N, 8]: ``lo`` (min of x, y, z, value) then ``hi`` (max) over the
  vertices of the node's tets, for the time step last built or refit for;
* ``links`` int32 [N, 12]: ``kind``, ``first``, ``right``, ``skip``, then ``escape`` of the
  8 ray octants:

  - the left child of interior node i is i + 1 and ``right[i]`` (= ``skip[i + 1]``) its
    right child; ``skip[i]`` is the first node after i's subtree (N for the last one);
  - ``kind[i]`` > 0: a leaf of that many tets (1..leaf_size), stored as
    ``order[first[i]:first[i] + count[i]]``; ``kind[i]`` < 0: an interior node whose
    children lie along split code -kind - 1 (below); ``first[i]`` of an interior node is
    where its subtree's tets start, and leaves' ranges follow one another in pre-order;
  - near-child-first order without a stack: the split code (``split_axis``) is 2 axis + 1
    when the right child is the lower one on the axis of largest child-centre separation
    (measured on the build's geometry); a ray whose direction points along +axis visits
    the lower child first. ``escape[o]`` is the node after i's subtree in that order for
    rays of octant o = 4 (dx < 0) + 2 (dy < 0) + (dz < 0). A ray nearer hits first, so
    its best t culls more of the rest (the seed's ordered traversal, Sec. 5.4.2);

* ``order`` int32 [T'] indices of the mesh's non-degenerate tets (degenerate ones bound no
  volume and are left out; tets with a constant value are kept).

`BVH.lo`, `hi`, `count`, `first`, `skip`, `split_axis` and `escape` ([8, N]) read these.

A mesh whose tets are all degenerate has nothing to bound: `build_bvh` raises ValueError.

Builds run in numpy, level by level with no Python loop per node: "bih" splits at spatial
medians through Morton codes (a binary radix tree), "sah" by a 16-bin surface area
heuristic on the largest centroid axis. Both make a leaf exactly when a node has
<= leaf_size tets, so leaves never exceed leaf_size. `refit` (numpy) and `refit_jax` (jit-able)
recompute the bounds for a new time step or moved vertices without touching the topology.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._core import pytree_dataclass, static_field
from ._mesh import TetMesh, check_renderable, corner_points, degenerate_mask

__all__ = ["BVH", "build_bvh", "refit", "refit_jax", "memory_report", "bvh_stats",
           "right_first", "octant_of", "METHODS"]

METHODS = ("bih", "sah")
MORTON_BITS = 10  # per axis: a 1024^3 grid over the centroids' bounding cube
SAH_BINS = 16


@pytree_dataclass
class BVH:
    """An implicit BVH in flat pre-order arrays (layout in the module doc).

    Attributes:
      bounds: float32 [N, 8] lo (x, y, z, value) and hi per node.
      links: int32 [N, 12] kind, first, right, skip and the 8 octants' escapes per node.
      order: int32 [T'] tet indices of the non-degenerate tets.
      depth: int32 [N] depth of each node (root 0).
      levels: int32 [I] the interior nodes, deepest level first (a bottom-up refit order).
      leaf_size, method: static build parameters.
      level_sizes: static tuple, how many of `levels` belong to each depth, deepest first.
    """

    bounds: np.ndarray
    links: np.ndarray
    order: np.ndarray
    depth: np.ndarray
    levels: np.ndarray
    leaf_size: int = static_field(8)
    method: str = static_field("bih")
    level_sizes: tuple = static_field(())

    # views of the two node rows (numpy or jax arrays alike)
    @property
    def lo(self):
        """float32 [N, 4] min of x, y, z, value."""
        return self.bounds[:, :4]

    @property
    def hi(self):
        return self.bounds[:, 4:]

    @property
    def count(self):
        """int32 [N] tets of a leaf, 0 for interior nodes."""
        return self.links[:, 0].clip(0)

    @property
    def first(self):
        """int32 [N] start of the node's tets in `order`."""
        return self.links[:, 1]

    @property
    def skip(self):
        """int32 [N] first node after the subtree."""
        return self.links[:, 3]

    @property
    def split_axis(self):
        """int8 [N] near-child code of interior nodes (0 for leaves)."""
        return (-self.links[:, 0] - 1).clip(0).astype(np.int8)

    @property
    def escape(self):
        """int32 [8, N] the node after each subtree in near-first order, per ray octant."""
        return self.links[:, 4:].T

    @property
    def n_nodes(self) -> int:
        return int(np.shape(self.links)[0])

    @property
    def nbytes(self) -> int:
        return int(sum(np.asarray(a).nbytes for a in jax.tree.leaves(self)))


def build_bvh(mesh: TetMesh, *, method: str = "bih", leaf_size: int = 8,
              step: int = 0) -> BVH:
    """Build the implicit BVH of `mesh` with bounds for time step `step`.

    method: "bih" (spatial median via Morton codes, fast) or "sah" (binned SAH).
    leaf_size: the most tets per leaf (>= 1); the seed used 12.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if int(leaf_size) < 1:
        raise ValueError(f"leaf_size must be >= 1, got {leaf_size}")
    _check_step(mesh, step)
    points, tets = np.asarray(mesh.points), np.asarray(mesh.tets)
    degenerate = degenerate_mask(points, tets)
    # `tet_mesh` refuses such meshes too, but the raw constructor and `with_points` do not;
    # an empty tree would fail much later, as an index error inside the traversal.
    check_renderable(degenerate, tets)
    kept = np.flatnonzero(~degenerate).astype(np.int32)
    corners = corner_points(points, tets[kept])  # 4 x [T', 3]
    if method == "bih":
        perm, split = _morton_splitter(sum(corners) / 4)
    else:
        perm, split = _sah_splitter(corners)
    # `split` may reorder `perm` within the nodes it cuts, so read perm after growing.
    skip, first, count, depth, levels, level_sizes = _preorder(
        *_grow(kept.size, int(leaf_size), split))
    n = skip.size
    right = np.zeros(n, np.int32)
    inner = np.flatnonzero(count == 0)
    right[inner] = skip[inner + 1]
    slot_lo, slot_hi = _slot_bounds(points, tets, np.asarray(mesh.values)[step], kept[perm])
    lo, hi = _node_bounds(slot_lo, slot_hi, count, first, skip, levels, level_sizes)
    split_axis = _split_axes(lo, hi, count, skip, right)
    escape = _escapes(skip, count, depth, split_axis)
    kind = np.where(count > 0, count, -1 - split_axis.astype(np.int32))
    links = np.concatenate([np.stack([kind, first, right, skip], axis=1), escape.T], axis=1)
    return BVH(np.concatenate([lo, hi], axis=1), links.astype(np.int32), kept[perm], depth,
               levels, leaf_size=int(leaf_size), method=method, level_sizes=level_sizes)


def right_first(split_axis, octant):
    """bool: rays of `octant` visit the right child first (arrays broadcast; jnp or np)."""
    axis, lower_right = split_axis // 2, split_axis % 2
    negative = (octant >> (2 - axis)) & 1  # the ray runs towards lower coordinates
    return (negative ^ lower_right) == 1


def octant_of(d):
    """int32 [...] octant 4 (dx < 0) + 2 (dy < 0) + (dz < 0) of directions d [..., 3]."""
    neg = (d < 0).astype(jnp.int32)
    return 4 * neg[..., 0] + 2 * neg[..., 1] + neg[..., 2]


def _split_axes(lo, hi, count, skip, right):
    """int8 [N]: per interior node the axis of largest child-centre separation, + 1 when
    the right child lies lower on it (0 for leaves), from node bounds lo, hi [N, 4]."""
    lo, hi = np.asarray(lo, np.float64)[:, :3], np.asarray(hi, np.float64)[:, :3]
    inner = np.flatnonzero(count == 0)
    left, right = inner + 1, right[inner]
    gap = (lo[right] + hi[right]) - (lo[left] + hi[left])
    gap = np.where(np.isfinite(gap), gap, 0.0)
    axis = np.argmax(np.abs(gap), axis=1)
    lower_right = np.take_along_axis(gap, axis[:, None], 1)[:, 0] < 0
    code = np.zeros(skip.size, np.int8)
    code[inner] = 2 * axis + lower_right
    return code


def _escapes(skip, count, depth, split_axis):
    """int32 [8, N]: per octant the node after each subtree in near-first order (N past
    the end); top-down by depth, vectorised over a level's nodes and the 8 octants."""
    skip, count, depth = np.asarray(skip), np.asarray(count), np.asarray(depth)
    n = skip.size
    escape = np.full((8, n), n, np.int32)
    octants = np.arange(8)[:, None]
    for d in range(int(depth.max()) + 1 if n else 0):
        inner = np.flatnonzero((depth == d) & (count == 0))
        inner = inner[inner + 1 < n]
        if not inner.size:
            continue
        left, right = inner + 1, skip[inner + 1]
        rf = right_first(split_axis[inner][None, :].astype(np.int32), octants)  # [8, I]
        near, far = np.where(rf, right, left), np.where(rf, left, right)
        rows = np.broadcast_to(octants, near.shape)
        escape[rows, near] = far
        escape[rows, far] = escape[:, inner]
    return escape


def refit(bvh: BVH, mesh: TetMesh, step: int = 0) -> BVH:
    """The same tree with bounds recomputed (numpy) for `mesh` at time step `step`: a new
    time step or moved vertices (`mesh.with_points`); the tets must be the build's."""
    _check_step(mesh, step)
    slot_lo, slot_hi = _slot_bounds(np.asarray(mesh.points), np.asarray(mesh.tets),
                                    np.asarray(mesh.values)[step], np.asarray(bvh.order))
    lo, hi = _node_bounds(slot_lo, slot_hi, np.asarray(bvh.count), np.asarray(bvh.first),
                          np.asarray(bvh.skip), np.asarray(bvh.levels), bvh.level_sizes)
    return dataclasses.replace(bvh, bounds=np.concatenate([lo, hi], axis=1))


def refit_jax(bvh: BVH, points, values_step, tets) -> BVH:
    """`refit` in jax.numpy, jit-able (the tree's shapes and `level_sizes` are static):
    points float [V, 3], values_step float [V] (one time step), tets int [T, 4]."""
    corners = tets[bvh.order]  # [T', 4]
    xyz, val = points[corners], values_step[corners][..., None]
    # Bounds as (lo, -hi) [., 8]: one min does both, halving the ops to trace and compile.
    slot = jnp.concatenate([xyz.min(axis=1), val.min(axis=1), -xyz.max(axis=1),
                            -val.max(axis=1)], axis=1)
    n_nodes, n_slots = bvh.links.shape[0], bvh.order.shape[0]
    right = bvh.links[:, 2]
    # Leaf owning each slot of `order`: mark each leaf's first slot with its node index and
    # carry it forward (leaves' ranges increase with the node index in pre-order).
    marks = jnp.zeros(n_slots, jnp.int32).at[jnp.where(bvh.count > 0, bvh.first, n_slots)].max(
        jnp.arange(n_nodes, dtype=jnp.int32), mode="drop")
    bounds = jax.ops.segment_min(slot, jax.lax.cummax(marks), n_nodes, indices_are_sorted=True)
    start = 0
    for size in bvh.level_sizes:  # deepest level first: children are final before parents
        nodes = bvh.levels[start:start + size]
        start += size
        bounds = bounds.at[nodes].set(jnp.minimum(bounds[nodes + 1], bounds[right[nodes]]))
    bounds = bounds.astype(jnp.float32)
    return dataclasses.replace(bvh, bounds=jnp.concatenate([bounds[:, :4], -bounds[:, 4:]],
                                                           axis=1))


def bvh_stats(bvh: BVH) -> dict:
    """nodes, leaves, interior, tets, depth (deepest leaf, root = 0), mean/min/max leaf size."""
    count, depth = np.asarray(bvh.count), np.asarray(bvh.depth)
    leaves = count > 0
    sizes = count[leaves] if leaves.any() else np.zeros(1, np.int32)
    return {
        "nodes": bvh.n_nodes,
        "leaves": int(leaves.sum()),
        "interior": int((~leaves).sum()) if leaves.any() else 0,
        "tets": int(np.shape(bvh.order)[0]),
        "depth": int(depth.max()),
        "mean_leaf_size": float(sizes.mean()),
        "min_leaf_size": int(sizes.min()),
        "max_leaf_size": int(sizes.max()),
    }


def memory_report(bvh: BVH, mesh: TetMesh) -> dict:
    """Bytes of the raw mesh and of the BVH (seed Table 5.5 analog).

    mesh_bytes = points + tets + all value steps; bvh_bytes = node arrays (bounds, links,
    depth, levels) + order; overhead_pct = 100 * bvh_bytes / mesh_bytes for one BVH shared
    by all steps (Schema II), per_step_overhead_pct for one BVH per step (Schema I);
    worst_case_node_bytes: 2T - 1 nodes as the seed pre-allocates.
    """
    arrays = {k: np.asarray(getattr(bvh, k)) for k in ("bounds", "links", "depth", "levels")}
    node_bytes = sum(a.nbytes for a in arrays.values())
    order_bytes = np.asarray(bvh.order).nbytes
    values = np.asarray(mesh.values)
    mesh_bytes = mesh.nbytes
    bvh_bytes = node_bytes + order_bytes
    per_node = (node_bytes - arrays["levels"].nbytes) / max(bvh.n_nodes, 1)
    return {
        "points_bytes": np.asarray(mesh.points).nbytes,
        "tets_bytes": np.asarray(mesh.tets).nbytes,
        "values_bytes_per_step": values[0].nbytes,
        "values_bytes": values.nbytes,
        "mesh_bytes": mesh_bytes,
        "bvh_node_bytes": node_bytes,
        "bvh_order_bytes": order_bytes,
        "bvh_bytes": bvh_bytes,
        "total_bytes": mesh_bytes + bvh_bytes,
        "overhead_pct": 100.0 * bvh_bytes / mesh_bytes,
        "per_step_overhead_pct": 100.0 * bvh_bytes * mesh.n_steps / mesh_bytes,
        "worst_case_node_bytes": int(per_node * (2 * mesh.n_tets - 1)),
    }


# ---------------------------------------------------------------------------- building


def _check_step(mesh, step):
    if not 0 <= int(step) < mesh.n_steps:
        raise IndexError(f"step {step} outside [0, {mesh.n_steps})")


def _ranges(starts, lengths):
    """Concatenated aranges [starts[k], starts[k] + lengths[k]) as one int array."""
    offsets = np.cumsum(lengths) - lengths
    return np.arange(lengths.sum()) + np.repeat(starts - offsets, lengths)


def _grow(n_items, leaf_size, split):
    """Top-down tree over slots [0, n_items), one level per step.

    split(starts, ends) -> mids cuts every node of a level with > leaf_size items into
    [start, mid) and [mid, end). Returns per node (in creation order) start, end, depth,
    rights (how many of the node and its ancestors are right children) and leaf (bool).
    """
    start, end, rights = np.array([0]), np.array([n_items]), np.array([0])
    out, depth = [], 0
    while start.size:
        inner = end - start > leaf_size
        out.append((start, end, np.full(start.size, depth), rights, ~inner))
        start, end, rights = start[inner], end[inner], rights[inner]
        if not start.size:
            break
        mid = split(start, end)
        # Guard: a cut that leaves one side empty would never terminate; halve instead.
        mid = np.where((mid > start) & (mid < end), mid, (start + end) // 2)
        start, end = np.concatenate([start, mid]), np.concatenate([mid, end])
        rights = np.concatenate([rights, rights + 1])
        depth += 1
    return tuple(np.concatenate(a) for a in zip(*out))


def _preorder(start, end, depth, rights, leaf):
    """Pre-order skip, first, count, depth, levels, level_sizes from `_grow`'s nodes.

    The nodes before v in pre-order are its `depth` ancestors plus the subtrees wholly left
    of it; those hold the L leaves that start before v and form one tree per right-child
    ancestor-or-self, so they number 2 L - rights. A subtree with k leaves has 2 k - 1 nodes.
    """
    leaf_starts = np.sort(start[leaf])
    left_leaves = np.searchsorted(leaf_starts, start)
    own_leaves = np.searchsorted(leaf_starts, end) - left_leaves
    pre = depth + 2 * left_leaves - rights
    n = start.size
    skip = np.empty(n, np.int32)
    skip[pre] = pre + 2 * own_leaves - 1
    first, count, node_depth, is_leaf = (np.empty(n, t) for t in (np.int32,) * 3 + (bool,))
    first[pre], count[pre], node_depth[pre], is_leaf[pre] = (
        start, np.where(leaf, end - start, 0), depth, leaf)
    interior = np.flatnonzero(~is_leaf)
    levels = interior[np.argsort(-node_depth[interior], kind="stable")].astype(np.int32)
    _, sizes = np.unique(-node_depth[levels], return_counts=True)
    return skip, first, count, node_depth, levels, tuple(int(s) for s in sizes)


def _morton_splitter(centroids):
    """BIH-style spatial median splits: (perm, split) with perm sorting the centroids
    [T', 3] by Morton code; split cuts a node at its codes' highest differing bit, i.e. at
    the middle of its Morton cell along that bit's axis (a node whose codes are all equal
    is cut at its middle slot)."""
    codes = _morton_codes(centroids)
    perm = np.argsort(codes, kind="stable")
    codes = codes[perm]

    def split(start, end):
        a, b = codes[start], codes[end - 1]
        same = a == b
        bit = np.where(same, 0, np.frexp((a ^ b).astype(np.float64))[1] - 1)
        # First slot whose code has b's prefix down to `bit`: the upper half of the cell.
        mid = np.searchsorted(codes, (b >> bit) << bit)
        return np.where(same, (start + end) // 2, mid)

    return perm, split


def _morton_codes(centroids):
    """int64 [T'] 3 * MORTON_BITS-bit Morton codes on a grid over the bounding cube (a cube,
    not the box, so a long mesh is first cut along its long axis)."""
    if centroids.shape[0] == 0:
        return np.zeros(0, np.int64)
    cmin = centroids.min(axis=0)
    extent = float((centroids.max(axis=0) - cmin).max())
    cells = 1 << MORTON_BITS
    scale = cells / extent if extent > 0 else 0.0
    q = np.clip(((centroids - cmin) * scale).astype(np.int64), 0, cells - 1)
    x, y, z = (_spread_bits(q[:, k]) for k in range(3))
    return (x << 2) | (y << 1) | z


def _spread_bits(v):
    """Insert two zero bits after each of the low 10 bits of int64 v."""
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


def _sah_splitter(corners):
    """Binned SAH splits over tets with corners 4 x [T', 3]: (perm, split). split bins each
    node's tets by centroid into SAH_BINS bins along the node's largest centroid axis,
    reorders its slots by bin (in `perm`, in place) and cuts at the bin boundary of least
    area(left) * n_left + area(right) * n_right, with tet boxes in x, y, z."""
    # Slot-ordered rows (centroid, box lo, box hi), reordered along with `perm`: a node's
    # rows stay contiguous in memory, so the per-level gathers are nearly sequential.
    rows_of_slot = np.concatenate([sum(corners) / 4, _min4(corners), _max4(corners)], axis=1)
    perm = np.arange(rows_of_slot.shape[0])

    def split(start, end):
        n = end - start
        k = n.size
        slots = _ranges(start, n)
        node = np.repeat(np.arange(k), n)
        offsets = np.cumsum(n) - n
        data = rows_of_slot[slots]
        cmin = np.minimum.reduceat(data[:, :3], offsets)
        extent = np.maximum.reduceat(data[:, :3], offsets) - cmin
        axis = np.argmax(extent, axis=1)
        nodes = np.arange(k)
        width = extent[nodes, axis]
        scale = np.divide(SAH_BINS, width, out=np.zeros_like(width), where=width > 0)
        coord = data[np.arange(slots.size), axis[node]] - cmin[nodes, axis][node]
        bins = np.minimum((coord * scale[node]).astype(np.int32), SAH_BINS - 1)
        key = node.astype(np.int32) * SAH_BINS + bins
        by_bin = np.argsort(key, kind="stable")
        data = data[by_bin]
        rows_of_slot[slots] = data
        perm[slots] = perm[slots][by_bin]
        counts = np.bincount(key, minlength=k * SAH_BINS).reshape(k, SAH_BINS)
        n_left = np.cumsum(counts, axis=1)[:, :-1]
        area_left, area_right = _bin_sweep_areas(data[:, 3:6], data[:, 6:], counts)
        cost = area_left * n_left + area_right * (n[:, None] - n_left)
        cost[(n_left == 0) | (n_left == n[:, None])] = np.inf
        best = np.argmin(cost, axis=1)
        cut = n_left[nodes, best]
        # No valid cut: all centroids in one bin (equal centroids); cut the slots in half.
        return start + np.where(np.isfinite(cost[nodes, best]), cut, n // 2)

    return perm, split


def _bin_sweep_areas(lo, hi, counts):
    """Surface areas [K, B - 1] of the boxes left / right of each bin boundary, from slot
    boxes lo, hi [M, 3] sorted by (node, bin) and bin counts [K, B]."""
    k, b = counts.shape
    flat = counts.reshape(-1)
    filled = np.flatnonzero(flat)
    bin_lo = np.full((k * b, 3), np.inf, lo.dtype)
    bin_hi = np.full((k * b, 3), -np.inf, hi.dtype)
    starts = (np.cumsum(flat) - flat)[filled]
    bin_lo[filled] = np.minimum.reduceat(lo, starts)
    bin_hi[filled] = np.maximum.reduceat(hi, starts)
    bin_lo, bin_hi = bin_lo.reshape(k, b, 3), bin_hi.reshape(k, b, 3)
    left = _area(np.minimum.accumulate(bin_lo, axis=1), np.maximum.accumulate(bin_hi, axis=1))
    right = _area(np.minimum.accumulate(bin_lo[:, ::-1], axis=1)[:, ::-1],
                  np.maximum.accumulate(bin_hi[:, ::-1], axis=1)[:, ::-1])
    return left[:, :-1], right[:, 1:]


def _area(lo, hi):
    """Surface area of boxes [..., 3]; 0 for empty (inverted) boxes."""
    d = np.maximum(hi - lo, 0.0)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


# ---------------------------------------------------------------------------- bounds


def _slot_bounds(points, tets, values, order):
    """float32 [T', 4] lo, hi of x, y, z, value over the vertices of tets[order]."""
    ids = tets[order]
    xyz = corner_points(points, ids)
    val = tuple(values[ids[:, j], None] for j in range(4))
    lo = np.concatenate([_min4(xyz), _min4(val)], axis=1)
    hi = np.concatenate([_max4(xyz), _max4(val)], axis=1)
    return lo.astype(np.float32), hi.astype(np.float32)


def _min4(a):
    # Pairwise on contiguous arrays: far faster than min over a short middle axis.
    return np.minimum(np.minimum(a[0], a[1]), np.minimum(a[2], a[3]))


def _max4(a):
    return np.maximum(np.maximum(a[0], a[1]), np.maximum(a[2], a[3]))


def _node_bounds(slot_lo, slot_hi, count, first, skip, levels, level_sizes):
    """Node bounds [N, 4]: leaves by reduceat over their slot ranges, then interior nodes
    as the union of their two children, bottom-up one depth at a time (`levels`, deepest
    first, `level_sizes` per depth)."""
    n_nodes = skip.size
    lo = np.full((n_nodes, 4), np.inf, np.float32)
    hi = np.full((n_nodes, 4), -np.inf, np.float32)
    leaves = np.flatnonzero(count > 0)
    if leaves.size:
        # Leaves tile [0, T') in pre-order, so each reduceat segment is exactly one leaf.
        lo[leaves] = np.minimum.reduceat(slot_lo, first[leaves])
        hi[leaves] = np.maximum.reduceat(slot_hi, first[leaves])
    start = 0
    for size in level_sizes:
        nodes = levels[start:start + size]
        start += size
        left, right = nodes + 1, skip[nodes + 1]
        lo[nodes] = np.minimum(lo[left], lo[right])
        hi[nodes] = np.maximum(hi[left], hi[right])
    return lo, hi
