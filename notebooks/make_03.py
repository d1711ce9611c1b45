"""Builds notebooks/03_tet_meshes.ipynb; run as a script (python notebooks/make_03.py),
it also executes the notebook and stores it with its outputs (every notebook:
python notebooks/_nbtools.py --all). tests/test_notebooks.py checks that the stored
copy is not stale and executes it small (JAXISO_NB_SIZE=24).
"""

from _nbtools import ROW, TIMED, Notebook, heat, helpers, regenerate, setup

NOTEBOOK = Notebook("03_tet_meshes.ipynb")
md, code = NOTEBOOK.md, NOTEBOOK.code


md("""
# Isosurfaces of tetrahedral meshes with `jaxiso`

Unstructured data (finite elements, simulations on adaptive meshes) often comes as a
tetrahedral mesh with one scalar per vertex. Inside a tet the field is the *linear*
interpolant of its 4 vertex values, so the isosurface `F = iso` is a union of planar
polygons, a triangle or a quad per cut tet: the marching-tets cases (Knoll 2009,
Sec. 5.3). `jaxiso` ray traces these isopolygons directly, without extracting a triangle
mesh:

* an **implicit BVH** (Sec. 5.4) whose nodes bound `x, y, z` *and* the value skips every
  subtree whose value range misses all isovalues, so a new isovalue needs no new tree;
* in the tet that was hit the depth has the closed form `t = (iso - F(o)) / (grad F . d)`,
  which makes depth, normals and pixels differentiable in the isovalues, the vertex
  positions and the camera.

This notebook tours:

1. building a mesh (a Poisson solution on a ball) and reading one from a file,
2. the BVH: BIH vs SAH builds, tree statistics, memory (Sec. 5.4),
3. four isosurfaces with a colour each, new isovalues without recompiling,
4. a clip box and shadows,
5. transparency,
6. flat vs smooth normals,
7. time steps and
8. moving vertices (the modalities of Sec. 5.6),
9. the derivative of the depth with respect to the isovalues (`jax.jvp`).

The image size comes from `JAXISO_NB_SIZE` (default 128; the test suite runs this
notebook at 24). The mesh (512 tets) and the images are small because the traversal is
slow on a CPU: of the order of a millisecond per ray. The first render of a new scene
*structure* (mesh and tree sizes, number of isovalues, shading options, normals)
compiles, several seconds on a CPU; renders that only change numbers (isovalues, clip
box, camera, time step, vertex positions) reuse the compiled program. The cells are
arranged to reuse it: the whole notebook compiles five render / intersect programs.
""")

code(setup("""
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import meshio
import numpy as np

import jaxiso as ji
from jaxiso import tetra
from jaxiso.tetra import data
""", "128"))

code(helpers(ROW, heat("quantity"), TIMED))

# ---------------------------------------------------------------------------------------
md("""
## 1. A mesh and a field

The field solves `-laplace(u) = 1` in the unit ball with `u = 0` on the sphere, computed
with linear (P1) finite elements by [scikit-fem](https://scikit-fem.readthedocs.io) on its
refined ball mesh (`data.poisson_on_ball`). The exact solution is `(1 - |x|^2) / 6`, so
the isosurface `u = c` is close to the sphere of radius `sqrt(1 - 6 c)`: a field whose
answer we know. Without scikit-fem (not a `jaxiso` dependency) the notebook puts the
exact solution on a generated cube mesh (`data.cube_tets`) instead.

A mesh holds `S` time steps of the field, `values [S, V]`. Ours has 8: step 0 is `u`
itself, later steps add a travelling wave whose amplitude rises and falls
(`data.time_series`). Sections 2-6 show step 0; section 7 plays the others.

`tetra.tet_mesh(points, tets, values)` checks the arrays, reorients inverted tets and
flags degenerate ones (`mesh.report()`).
""")

code("""
try:
    points, tets, u = data.poisson_on_ball(level=2)  # 512 tets
    source = "P1 Poisson solution on skfem's ball mesh"
except ImportError:
    points, tets = data.cube_tets(5, lo=(-1.0,) * 3, hi=(1.0,) * 3)  # 750 tets
    u = ((1.0 - np.sum(points.astype(np.float64) ** 2, axis=1)) / 6.0).astype(np.float32)
    source = "exact solution on a generated cube mesh (scikit-fem is not installed)"

STEPS = 8


def rippled(p, t):
    # sin(t / 2) is 0 at t = 0 (step 0 is u itself) and peaks half way through the series
    return u + 0.02 * np.sin(t / 2) * data.wave_field(p, t, frequency=0.75)


mesh = tetra.tet_mesh(points, tets, data.time_series(points, STEPS, field=rippled))
print(source)
print(mesh.report())
""")

md("""
Meshes from files: `tetra.from_meshio(m, values)` takes any mesh
[meshio](https://github.com/nschloe/meshio) reads (`.vtu`, `.msh`, `.xdmf`, ...); its
`tetra` cells, and point data by name (a list of names is a list of time steps).
`tetra.from_pyvista(grid, scalars)` does the same for a pyvista grid. A round trip
through a `.vtu` file:
""")

code("""
names = [f"u{s}" for s in range(STEPS)]
with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "ball.vtu")
    meshio.Mesh(points, [("tetra", tets)],
                point_data=dict(zip(names, mesh.values))).write(path)
    loaded = tetra.from_meshio(meshio.read(path), names)
print(f"{path.rsplit(os.sep, 1)[-1]}: {loaded.n_tets} tets, {loaded.n_points} vertices, "
      f"{loaded.n_steps} steps; same values: {np.array_equal(loaded.values, mesh.values)}")
""")

# ---------------------------------------------------------------------------------------
md("""
## 2. The implicit BVH: BIH vs SAH

`TetIsosurface(mesh, isovalues, bvh=..., leaf_size=8)` builds the tree (in numpy):

* `"bih"` splits at spatial medians (Morton codes, as a bounding interval hierarchy
  does): fast to build;
* `"sah"` places each split by a binned surface area heuristic: slower to build, tighter
  boxes.

Each node stores the min and max of `x, y, z` and of the value over its tets (the 4D
bounds of Sec. 5.4); a leaf lists up to `leaf_size` tets. `tetra.bvh_stats` summarises a
tree; `scene.memory_report()` weighs it against the mesh, the question of the seed's
Table 5.5. One tree serves every time step after a refit of its bounds (Schema II,
Sec. 5.6), so `overhead_pct` is the cost of one tree for all 8 steps, and
`per_step_overhead_pct` that of a tree per step (Schema I).

The surface area heuristic also *predicts* the work: a random ray that crosses the root
box crosses a node's box with probability `area(node) / area(root)`, so the sum of that
ratio over the nodes estimates the boxes such a ray enters, and over the leaves (times
their tet counts) the tets it tests. This ignores the value bounds, which cull much more
(section 9 counts the real visits).
""")

code('''
ISOVALUES = (0.02, 0.05, 0.08, 0.11)  # spheres of radius ~0.94, 0.84, 0.72, 0.58


def box_area(lo, hi):
    """Surface area of boxes [N, 3]."""
    e = np.maximum(hi - lo, 0.0)
    return 2.0 * (e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0])


def sah_estimate(bvh):
    """(boxes, tets) a random ray through the root box meets: area-weighted node counts."""
    lo, hi = np.asarray(bvh.lo)[:, :3], np.asarray(bvh.hi)[:, :3]
    share = box_area(lo, hi) / box_area(lo[:1], hi[:1])[0]
    count = np.asarray(bvh.count)
    return share.sum(), (share * count).sum()


scenes, build_s = {}, {}
for method in ("bih", "sah"):
    t = time.perf_counter()
    scenes[method] = ji.TetIsosurface(mesh, ISOVALUES, bvh=method, leaf_size=8)
    build_s[method] = time.perf_counter() - t

keys = ("nodes", "leaves", "depth", "mean_leaf_size", "max_leaf_size")
print(f"{mesh.n_tets} tets, {mesh.n_points} vertices, {mesh.n_steps} steps")
for method, scene in scenes.items():
    stats, memory = tetra.bvh_stats(scene.bvh), scene.memory_report()
    boxes, tests = sah_estimate(scene.bvh)
    print(f"{method}: build {build_s[method] * 1e3:6.1f} ms; "
          + ", ".join(f"{k} {stats[k]:.3g}" for k in keys))
    print(f"     a random ray enters ~{boxes:.1f} boxes and tests ~{tests:.1f} tets")
    print(f"     mesh {memory['mesh_bytes'] / 1024:.1f} KiB, tree "
          f"{memory['bvh_bytes'] / 1024:.1f} KiB: {memory['overhead_pct']:.0f}% shared by "
          f"all steps, {memory['per_step_overhead_pct']:.0f}% with a tree per step")
''')

# ---------------------------------------------------------------------------------------
md("""
## 3. Four isosurfaces, four colours

`ji.render` shades the first hit of every pixel; `Hits.surface` says which isovalue was
hit, and `ji.Shading(colors=...)` gives each isovalue its colour. From outside, the
outer shell hides the other three.
""")

code("""
palette = ((0.85, 0.55, 0.25), (0.30, 0.55, 0.85), (0.45, 0.75, 0.40), (0.80, 0.35, 0.45))
opaque = ji.Shading(colors=palette)
cam = ji.Camera.look_at(eye=(2.4, 1.8, 1.5), target=(0, 0, 0), up=(0, 0, 1), fov=40,
                        width=SIZE, height=SIZE)
scene = scenes["bih"]
first, t_compile = timed(ji.render, scene, cam, shading=opaque)
print(f"first render: {t_compile:.1f} s (compiles)")
first
""")

md("""
The isovalues are a traced input of the compiled renderer: `scene.with_isovalues(...)`
(the same number of them) re-renders without recompiling and without touching the tree,
whose value bounds hold for any isovalue. Raising every isovalue shrinks the shells.
""")

code("""
panels = []
for shift in (0.0, 0.025, 0.05):
    iso = np.asarray(ISOVALUES) + shift
    img, dt = timed(ji.render, scene.with_isovalues(iso), cam, shading=opaque)
    panels.append(img)
    print(f"isovalues {np.round(iso, 3)}: {dt * 1e3:7.1f} ms")
row(*panels)
""")

# ---------------------------------------------------------------------------------------
md("""
## 4. Clip box and shadows

`clip_box=(lo, hi)` keeps the part of the mesh's bounding box inside `[lo, hi]`; rays
start on its faces. Keeping `z <= 0` opens the nested shells as bowls. Passing the tree
(`bvh=scene.bvh`) shares it, and the clip box is a traced field, so the clipped render
reuses the compiled program.

`Shading(shadows=True)` casts a ray from every hit towards the light through the same
(clipped) scene: with a low light from the side, the rims of the outer bowls shadow the
inner ones. Shadows are a *static* option (they change the program), so the shadowed
render compiles once more; the light itself (`ji.Light`) is a traced input.
""")

code("""
lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
cut = ji.TetIsosurface(mesh, ISOVALUES, bvh=scene.bvh, clip_box=(lo, (hi[0], hi[1], 0.0)))
side_light = ji.Light((1.0, 0.2, 0.4))  # low, from the side
clipped, dt = timed(ji.render, cut, cam, shading=opaque, light=side_light)
print(f"clipped: {dt * 1e3:.1f} ms (reuses the compiled render)")
shadows = ji.Shading(colors=palette, shadows=True)
shadowed, dt = timed(ji.render, cut, cam, shading=shadows, light=side_light)
print(f"clipped, shadows: {dt:.1f} s (compiles)")
row(clipped, shadowed)
""")

md("""
Moving the light re-renders the shadows without compiling:
""")

code("""
row(*(ji.render(cut, cam, shading=shadows, light=ji.Light(v))
      for v in ((-0.6, 0.9, 0.5), (-0.2, 1.0, 0.35), (1.0, 0.2, 0.4))))
""")

# ---------------------------------------------------------------------------------------
md("""
## 5. Transparency

`Shading(layers=3, opacity=0.45)` composites the first three surfaces along each ray
front to back: the next layer is traced from just behind the last hit, so inner shells
show through outer ones without a clip. Each layer is one more traversal in the compiled
program; raise `layers` to see deeper. Four shells seen through one another blend to
grey, so this scene keeps two of the isovalues (the outer and the inner shell; a new
number of isovalues would compile anew, but this program compiles anyway).
""")

code("""
pair = ji.TetIsosurface(mesh, (ISOVALUES[0], ISOVALUES[-1]), bvh=scene.bvh)
glass = ji.Shading(colors=(palette[0], palette[-1]), layers=3, opacity=0.45)
transparent, dt = timed(ji.render, pair, cam, shading=glass)
print(f"3 layers: {dt:.1f} s (compiles)")
transparent
""")

# ---------------------------------------------------------------------------------------
md("""
## 6. Flat vs smooth normals

Inside a tet the field's gradient is constant, so the default `normals="flat"` gives each
isopolygon one normal and the tessellation shows. `normals="smooth"` stores one gradient
per vertex (the volume-weighted mean of the gradients of the tets around it) and
interpolates it linearly over the tet that was hit, as Phong shading does for triangle
meshes. Only the shading changes; depths are the same.
""")

code("""
smooth = ji.TetIsosurface(mesh, ISOVALUES, bvh=scene.bvh, normals="smooth",
                          clip_box=(lo, (hi[0], hi[1], 0.0)))
smoothed, dt = timed(ji.render, smooth, cam, shading=opaque, light=side_light)
print(f"smooth normals: {dt:.1f} s (compiles)")
row(clipped, smoothed)
""")

# ---------------------------------------------------------------------------------------
md("""
## 7. Time steps

`scene.with_time_step(k)` switches to step `k` of the mesh's values. It keeps the tree
and refits its value bounds (Schema II of Sec. 5.6); the refit is jit-able, and jitted it
is one small program compiled once (eagerly, each of its many small operations would
compile on first use). The step is a traced field of the scene, so no frame retraces or
recompiles the render: compare the time per frame with the first render's compile above
(the first frame also compiles the refit). A second pass over the same steps shows the
steady frame time.
""")

code("""
at_step = jax.jit(lambda scene, k: scene.with_time_step(k))


def step_frame(k):
    return ji.render(at_step(cut, k), cam, shading=opaque)


frames = list(range(0, STEPS, 2))
for attempt in ("first pass", "second pass"):
    images, times = [], []
    for k in frames:
        img, dt = timed(step_frame, k)
        images.append(img)
        times.append(dt)
    print(f"{attempt}: steps {frames}, " + ", ".join(f"{t * 1e3:.0f}" for t in times) + " ms")
row(*images)
""")

# ---------------------------------------------------------------------------------------
md("""
## 8. Moving vertices

`scene.with_points(p)` moves the vertices (same tets, same values). The tree's boxes are
refit, its topology kept: fine for the small motion of a deforming mesh, while a large
one loosens the boxes, and then a rebuild (`TetIsosurface(mesh, ...)`, Schema I) pays
off. `data.deform` moves every vertex along a smooth periodic displacement. The new
positions are traced values too: the compiled render is reused (the time includes the
jitted refit, compiled on the first frame).
""")

code("""
moved_to = jax.jit(lambda scene, points: scene.with_points(points))


def moved_frame(points):
    return ji.render(moved_to(cut, points), cam, shading=opaque)


images = []
for phase in (0.0, 2.0, 4.0):
    moved = data.deform(points, phase, amplitude=0.04)
    img, dt = timed(moved_frame, moved)
    images.append(img)
    shift = np.abs(moved - points).max()
    print(f"phase {phase}: vertices moved up to {shift:.3f}, {dt * 1e3:.0f} ms")
row(*images)
""")

# ---------------------------------------------------------------------------------------
md("""
## 9. Derivatives: depth with respect to the isovalues

`ji.intersect(scene, rays)` returns the raw hits. The traversal loop itself is not
differentiated: the depth is recomputed in closed form in the tet that was hit, so
`jax.jvp` (or `jax.grad`) gives exact derivatives of the piecewise-linear model. Here
one forward-mode pass raises all four isovalues together (`d_iso = (1, 1, 1, 1)`).

For the exact field `|x|^2 = 1 - 6 c`, a hit `x` on the ray `o + t d` (unit `d`) moves
with `dt / dc = -3 / (x . d)`: positive on the near side of a shell (it shrinks away from
the camera), negative on the far side seen inside the bowls. The mesh's shells are
polyhedra, so that is only a guide; central finite differences of the same intersect are
the check of the derivative itself.
""")

code('''
rays = cam.rays()


@jax.jit
def depth_slope(scene, iso, d_iso):
    """Hits at isovalues `iso` and d t / d iso along `d_iso`: ([H, W] slopes, Hits)."""
    def depth(iso):
        hits = ji.intersect(scene.with_isovalues(iso), rays)
        return jnp.where(hits.hit, hits.t, 0.0), hits

    _, slope, hits = jax.jvp(depth, (iso,), (d_iso,), has_aux=True)
    return slope, hits


iso, d_iso, h = jnp.asarray(ISOVALUES), jnp.ones(4), 1e-3
(slope, hits), dt = timed(depth_slope, cut, iso, d_iso)
print(f"jvp of intersect: {dt:.1f} s (compiles)")
# the primal outputs at iso +- h give central differences (same compiled program)
(_, up), (_, down) = (depth_slope(cut, iso + s * h * d_iso, d_iso) for s in (1, -1))

slope, t, hit = np.asarray(slope), np.asarray(hits.t), np.asarray(hits.hit)
x = np.asarray(rays.at(np.where(hit, t, 0.0)))
exact = np.where(hit, -3.0 / np.sum(x * np.asarray(rays.direction), axis=-1), 0.0)
# central differences only where both neighbours hit the same shell
same = hit & np.asarray(up.hit & down.hit & (up.surface == hits.surface)
                        & (down.surface == hits.surface))
fd = (np.asarray(up.t)[same] - np.asarray(down.t)[same]) / (2 * h)
rel_fd = np.abs(slope[same] - fd) / np.abs(fd)
rel_exact = np.abs(slope - exact)[hit] / np.abs(exact[hit])
print(f"{hit.sum()} pixels hit; jvp vs central differences: median relative difference "
      f"{np.median(rel_fd):.1e} over {same.sum()} pixels")
print(f"jvp vs the exact sphere: median {np.median(rel_exact):.1%} (the mesh's facets tilt "
      f"against the sphere)")
''')

md("""
From left: the depth `t` (red = near), `dt / d iso` from `jax.jvp`, and the exact
sphere's `dt / dc`, the last two on the same scale (red = moves away fastest; negative
slopes, on the far sides of the bowls, which move towards the camera, show white).
""")

code("""
depth = np.where(hit, t, np.nan)
near, far = np.nanmin(depth), np.nanmax(depth)
vmax = np.percentile(np.abs(exact[hit]), 95)
row(heat(np.where(hit, (far - depth) / (far - near + 1e-9), 0.0), 1.0),
    heat(np.maximum(slope, 0.0), vmax), heat(np.maximum(exact, 0.0), vmax))
""")

md("""
The same call counted the work: `hits.steps` is the number of BVH nodes each ray visited
(white = few). Rays work hardest where they pass close to several shells, whose tets
hold isovalues all the way down the tree; rays through the clipped-away half or past the
ball stop after a few boxes.
""")

code("""
nodes = np.asarray(hits.steps)
print(f"nodes visited per ray: mean {nodes.mean():.1f}, max {nodes.max()} "
      f"of {scene.bvh.n_nodes}")
heat(nodes, np.percentile(nodes, 99))
""")

md("""
## Where next

* The same scene protocol runs implicits (`ji.ImplicitSurface`, notebook 01) and
  structured volumes (`ji.VolumeIsosurface`, notebook 02): `ji.render`, `ji.intersect`
  and `ji.Shading` work on all of them.
* `jax.grad` through `ji.intersect` or `ji.render` also reaches the vertex positions
  (`scene.with_points`) and the rays: fitting a shape or a camera to images.
* `tetra.refit` / `tetra.refit_jax` and `tetra.build_bvh` expose the two schemas
  directly.
""")

if __name__ == "__main__":
    regenerate(__file__)  # builds, executes and stores the notebook
