"""Builds notebooks/01_implicits.ipynb; run as a script (python notebooks/make_01.py),
it also executes the notebook and stores it with its outputs (every notebook:
python notebooks/_nbtools.py --all). tests/test_notebooks.py checks that the stored
copy is not stale and executes it small (JAXISO_NB_SIZE=24).
"""

from _nbtools import ROW, TIMED, Notebook, heat, helpers, regenerate, setup

NOTEBOOK = Notebook("01_implicits.ipynb")
md, code = NOTEBOOK.md, NOTEBOOK.code


md("""
# Ray tracing implicit surfaces with `jaxiso`

`jaxiso` ray traces surfaces `f(x, y, z) = c` written as **plain JAX code**. A ray is cut
into pieces; on each piece `f` is evaluated with *inclusion arithmetic* (interval or
reduced affine), which returns a range guaranteed to contain every value `f` takes there.
A piece whose range excludes the isovalue cannot hold the surface and is skipped; the
others are bisected until they are shorter than `eps` (Knoll 2009, ch. 6). Nothing about
`f` has to be known in advance: no Lipschitz constant, no derivatives, no polynomial form.

This notebook tours the library:

1. a gallery of the catalogue surfaces (Knoll 2009, Tables B.1/B.2),
2. your own implicit, and changing its parameters without recompiling,
3. interval vs affine arithmetic,
4. the ray precision `eps`,
5. 4D surfaces (morphing, time),
6. CSG,
7. shadows, transparency and reflections.

Every `ji.render` returns an `Image` (a float `[H, W, 3]` numpy array) that Jupyter
shows inline. The image size comes from `JAXISO_NB_SIZE` (default 160; the test suite
runs this notebook at 24). The first render of a new scene *compiles* (a few seconds on a
CPU); later renders that only change numbers (parameters, `w`, `eps`, camera) reuse it.
""")

code(setup("""
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji
from jaxiso.implicit import csg
""", "160"))

code(helpers(ROW, heat("count"), TIMED))

# ---------------------------------------------------------------------------------------
md("""
## 1. Gallery

`ji.surfaces.names()` lists the catalogue; `ji.surfaces.scene(name)` is a ready-to-render
scene (domain box, the seed's converged `eps`, default arithmetic) and
`ji.surfaces.camera(name, size)` a camera that frames it. `ji.surfaces.get(name).notes`
records how each ambiguous printed formula was read.
""")

code("""
print(ji.surfaces.names())
print()
print("klein:", ji.surfaces.get("klein").notes)
""")

code("""
gallery = ["steiner", "klein", "tangle", "barth_sextic", "bretzel4"]
images = {}
for name in gallery:
    images[name], dt = timed(ji.render, ji.surfaces.scene(name),
                             ji.surfaces.camera(name, SIZE))
    print(f"{name:13s} {dt:6.2f} s (compile + render)")
row(*images.values())
""")

# ---------------------------------------------------------------------------------------
md("""
## 2. Your own implicit

Write `f(x, y, z, params)` (or `(x, y, z)`, `(x, y, z, w)`, `(x, y, z, w, params)`) with
`jax.numpy`; `params` is any pytree of numbers. `ji.ImplicitSurface` adds the domain box
the surface is traced in. Here: a torus `(|p|^2 + R^2 - r^2)^2 = 4 R^2 (x^2 + y^2)` whose
tube radius wobbles around the ring (`a` sets the amplitude).
""")

code('''
traces = 0  # counts how often JAX traces f (Python runs f only while tracing)


def wavy_torus(x, y, z, params):
    global traces
    traces += 1
    R, r, a = params["R"], params["r"], params["a"]
    rho2 = x * x + y * y
    tube = r * (1.0 + a * jnp.sin(3.0 * x) * jnp.sin(3.0 * y))  # wavy tube radius
    s = rho2 + z * z + R * R - tube * tube
    return s * s - 4.0 * R * R * rho2


torus = ji.ImplicitSurface(wavy_torus, lo=(-1.7, -1.7, -0.8), hi=(1.7, 1.7, 0.8),
                           params={"R": 1.0, "r": 0.35, "a": 0.0}, eps=2.0**-10)
cam = ji.Camera.look_at(eye=(2.6, 2.0, 2.2), target=(0, 0, 0), up=(0, 0, 1), fov=40,
                        width=SIZE, height=SIZE)
first, t_first = timed(ji.render, torus, cam)
print(f"first render: {t_first:.2f} s (traces f, compiles), f traced {traces} times")
''')

md("""
`params`, `w`, `isovalues` (same count), `eps` and the camera are *traced* inputs of the
compiled renderer: changing them re-runs the compiled code and never calls `f` again.
A new `f`, a different arithmetic/method or a different image size compiles anew.
""")

code("""
n = traces
renders = [first]
for p in ({"R": 1.0, "r": 0.35, "a": 0.3}, {"R": 0.9, "r": 0.5, "a": -0.25}):
    img, dt = timed(ji.render, torus.replace(params=p), cam)
    renders.append(img)
    print(f"params {p}: {dt * 1e3:7.1f} ms")
print(f"f traced {traces - n} more times; speed-up of a re-render "
      f"~{t_first / max(dt, 1e-9):.0f}x")
row(*renders)
""")

code("""
# the scene is callable: the field at points (here the ring centre and the origin)
print(torus.replace(params={"R": 1.0, "r": 0.35, "a": 0.3})(
    jnp.array([1.0, 0.0]), jnp.array([0.0, 0.0]), jnp.array([0.0, 0.0])))
""")

# ---------------------------------------------------------------------------------------
md("""
## 3. Interval vs affine arithmetic

Interval arithmetic (IA) treats every occurrence of a variable as independent: on
`x in [-1, 1]` it gives `x - x = [-2, 2]`. On polynomials whose terms partly cancel, like
the Barth decic (degree 10, with products such as `(x^2 - tau^4 y^2)(y^2 - tau^4 z^2)...`),
the enclosure of a box grows much wider than the true range of `f`: on random boxes
4.35x the true width for IA, 2.51x for affine (`benchmarks/NOTES.md`). This *bound
overestimation* (seed Sec. 6.6.2) costs twice:

* **work**: a piece near (but off) the surface still "may contain" the isovalue, so it is
  bisected instead of skipped — more steps per ray;
* **accuracy at coarse `eps`**: the tracer accepts the first piece of length `eps` whose
  enclosure holds the isovalue; with a loose enclosure that piece may lie in front of
  the surface, so thin features look bloated at coarse `eps`.

Reduced affine arithmetic (AF1: `x0 + x1 e1 + x2 e2 + x3 e3 + err`) keeps the linear
correlation between `x`, `y`, `z` along a piece, so such terms cancel and bounds are
tighter — at a higher cost per evaluation. `ji.intersect` returns the raw hits;
`hits.steps` counts the enclosure evaluations of each ray (the work).
""")

code("""
decic_cam = ji.surfaces.camera("barth_decic", SIZE)
decic = ji.surfaces.scene("barth_decic", eps=2.0**-7)   # coarse; the seed converges at 2^-11
trace = jax.jit(lambda scene, rays: ji.intersect(scene, rays))

panels, steps = [], {}
for arithmetic in ("interval", "affine"):
    scene = decic.replace(arithmetic=arithmetic)
    img, t_compile = timed(ji.render, scene, decic_cam)
    img, t_render = timed(ji.render, scene, decic_cam)
    hits = trace(scene, decic_cam.rays())
    hit = np.asarray(hits.hit)
    steps[arithmetic] = np.asarray(hits.steps).reshape(SIZE, SIZE)
    panels.append(img)
    print(f"{arithmetic:8s}: mean steps {steps[arithmetic].mean():5.1f} per ray, "
          f"{hit.mean():5.1%} of pixels hit, render {t_render * 1e3:6.1f} ms "
          f"(first call {t_compile:.1f} s)")
vmax = np.percentile(steps["interval"], 99)
row(*panels, *(heat(s, vmax) for s in steps.values()))
""")

md("""
From left: interval, affine (both at `eps = 2^-7`), then the steps per pixel of each on
the same scale (white = few, red = many). IA covers more pixels (its spikes are fatter)
and works hardest around the silhouettes, where pieces pass close to the surface. Whether
fewer, costlier affine steps win in time depends on the surface and the device (the
seed's GPU found affine faster overall on such surfaces).
""")

# ---------------------------------------------------------------------------------------
md("""
## 4. Ray precision `eps`

`eps` is the world-space length of the final piece (depth `ceil(log2(L / eps))` for a ray
segment of length `L` in the box). Coarse `eps` is fast but fattens what is thinner than
`eps` — here the singular lines of Steiner's Roman surface along the axes; each halving
adds one bisection level. `eps` is traced, so these renders reuse the Steiner scene
compiled for the gallery.
""")

code("""
steiner = ji.surfaces.scene("steiner")
steiner_cam = ji.surfaces.camera("steiner", SIZE)
panels = []
for k in (6, 9, 12):
    scene = steiner.replace(eps=2.0**-k)
    img, dt = timed(ji.render, scene, steiner_cam)
    hits = trace(scene, steiner_cam.rays())
    panels.append(img)
    print(f"eps = 2^-{k:<2d}: {np.asarray(hits.hit).mean():5.1%} of pixels hit, "
          f"mean steps {np.asarray(hits.steps).mean():5.1f}, render {dt * 1e3:6.1f} ms")
row(*panels)
""")

# ---------------------------------------------------------------------------------------
md("""
## 5. 4D surfaces: morphing and time

`f(x, y, z, w)` takes a fourth coordinate `w`, a scene field like `eps`. The catalogue's
`morph` blends the decocube into a sphere (seed Sec. 6.6.7.2, Fig. 6.12) as `w` goes from
0 to 1; `cloth` is a height field animated by time `w`.
""")

code("""
morph = ji.surfaces.scene("morph")
morph_cam = ji.surfaces.camera("morph", SIZE)
print(ji.surfaces.get("morph").notes)
row(*(ji.render(morph.replace(w=w), morph_cam) for w in (0.0, 0.5, 1.0)))
""")

code("""
cloth = ji.surfaces.scene("cloth")
cloth_cam = ji.surfaces.camera("cloth", SIZE)
print("w range:", ji.surfaces.get("cloth").w_range)
row(*(ji.render(cloth.replace(w=w), cloth_cam) for w in (0.0, 1.0)))
""")

# ---------------------------------------------------------------------------------------
md("""
## 6. Constructive solid geometry

`csg.Solid(g)` is the region `g < 0`; `csg.union`, `csg.intersection`, `csg.difference`
and `csg.complement` combine solids. The tracer never forms `min`/`max` of the fields
(which would make the enclosures loose and the normals undefined at creases): on each
piece every solid is *certainly inside*, *certainly outside* or *unknown*, the boolean
expression is evaluated in three-valued logic, and only a leaf whose flip could change the
result can bound the solid there (seed Sec. 6.6.7.3). `hits.surface` tells which leaf was
hit, and `ji.Shading(colors=...)` colours by it. A `Solid(g, draw=False)` only trims.

The catalogue has the seed's two CSG objects (Table B.2): `icos.csg`, an icosahedral
cosine lattice trimmed to a spherical shell (walls left open), and `sesc.csg`, a
superellipsoid cut by a trigonometric surface.
""")

code("""
def part_counts(scene, camera):
    hits = trace(scene, camera.rays())
    surface = np.asarray(hits.surface)[np.asarray(hits.hit)]
    names = [leaf.name or f"leaf {i}" + ("" if leaf.draw else " (trims)")
             for i, leaf in enumerate(scene.leaves)]
    return {name: int((surface == i).sum()) for i, name in enumerate(names)}


colors = ji.Shading(colors=[(0.85, 0.55, 0.25), (0.30, 0.55, 0.85), (0.45, 0.75, 0.40),
                            (0.80, 0.35, 0.45)])
panels = []
for name in ("icos.csg", "sesc.csg"):
    scene, camera = ji.surfaces.scene(name), ji.surfaces.camera(name, SIZE)
    panels.append(ji.render(scene, camera, shading=colors))
    print(f"{name}: {ji.surfaces.get(name).csg}\\n    pixels per part: "
          f"{part_counts(scene, camera)}")
row(*panels)
""")

md("""
Your own CSG: the classic "cube ∩ sphere minus three drilled cylinders". The cube is
the intersection of three slabs `x^2 < a^2` (each slab is one part, both of its faces), so every
face, the sphere and each drill hole gets its own colour.
""")

code("""
a, rs, rc = 0.75, 1.0, 0.42   # half cube edge, sphere radius, drill radius


def slab(i):                  # |coordinate i| < a
    return lambda x, y, z: (x, y, z)[i] ** 2 - a * a


def drill(i):                 # cylinder of radius rc along axis i
    return lambda x, y, z: sum(c * c for j, c in enumerate((x, y, z)) if j != i) - rc * rc


slabs = [csg.Solid(slab(i), name=f"slab {'xyz'[i]}") for i in range(3)]
ball = csg.Solid(lambda x, y, z: x * x + y * y + z * z - rs * rs, name="sphere")
drills = [csg.Solid(drill(i), name=f"drill {'xyz'[i]}") for i in range(3)]
part = csg.CSG(csg.difference(csg.intersection(*slabs, ball), csg.union(*drills)),
               lo=(-1.1,) * 3, hi=(1.1,) * 3, eps=2.0**-10)
part_cam = ji.Camera.look_at(eye=(2.6, 2.0, 1.7), target=(0, 0, 0), up=(0, 0, 1), fov=40,
                             width=SIZE, height=SIZE)
palette = ji.Shading(colors=[(0.85, 0.55, 0.25)] * 3 + [(0.30, 0.55, 0.85)]
                     + [(0.80, 0.35, 0.45)] * 3)
print("pixels per part:", part_counts(part, part_cam))
ji.render(part, part_cam, shading=palette)
""")

# ---------------------------------------------------------------------------------------
md("""
## 7. Shading: shadows, transparency, reflections

`ji.Shading` sets the Phong material and the effects; `ji.Light` the light.

* `shadows=True` casts a shadow ray from every hit, at a coarser `eps` (seed Sec. 6.4.6).
* `layers=3, opacity=0.5` composites the first three surfaces along each ray front to
  back — with two `isovalues` the inner level set shows through the outer one (colours go
  by isovalue).
* `reflections=2` adds two mirror bounces (`reflectivity` weights each).
""")

code("""
deco = ji.surfaces.scene("decocube")
deco_cam = ji.surfaces.camera("decocube", SIZE)
light = ji.Light((0.2, 0.9, 0.6))
plain = ji.render(deco, deco_cam, light=light)
shadowed = ji.render(deco, deco_cam, shading=ji.Shading(shadows=True), light=light)
mirror = ji.render(deco, deco_cam, shading=ji.Shading(reflections=2), light=light)

tangle = ji.surfaces.scene("tangle", isovalues=(0.0, -4.0))
nested = ji.render(tangle, ji.surfaces.camera("tangle", SIZE),
                   shading=ji.Shading(layers=3, opacity=0.5))
row(plain, shadowed, mirror, nested)
""")

md("""
From left: plain, shadows, two reflections, and the tangle cube with two transparent
isovalues (`f = 0` outside, `f = -4` inside; colours go by isovalue).

## Where next

* Every option is a scene field: `ji.intersect(scene.replace(method=...), rays)` with
  `"k-bisection"`, `"mitchell"`, and the non-inclusion baselines `"sampling"` and
  `"sphere"` (which miss thin features by design); traced fields (eps, isovalues, w,
  params) never recompile.
* `ji.plan_for(scene, n_rays)` shows the execution plan (tile edge, persistent lanes) that
  `intersect` and `render` use; pass `plan=ji.Plan(...)` to choose another.
* `ji.render(..., devices=jax.devices())` splits ray packets across devices.
* Hits are differentiable (implicit function theorem) w.r.t. params, isovalues, `w` and
  the rays: see `examples/fit_superquadric.py`.
""")

if __name__ == "__main__":
    regenerate(__file__)  # builds, executes and stores the notebook
