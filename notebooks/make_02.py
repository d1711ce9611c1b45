"""Builds notebooks/02_volumes.ipynb; run as a script (python notebooks/make_02.py),
it also executes the notebook and stores it with its outputs (every notebook:
python notebooks/_nbtools.py --all). tests/test_notebooks.py checks that the stored
copy is not stale and executes it small (JAXISO_NB_SIZE=24, which also shrinks its volumes).
"""

from _nbtools import ROW, TIMED, Notebook, helpers, regenerate, setup

NOTEBOOK = Notebook("02_volumes.ipynb")
md, code = NOTEBOOK.md, NOTEBOOK.code


md("""
# Isosurfaces of structured volumes with `jaxiso`

A volume is a grid of voxels `data[i, j, k]` at world points `origin + (i, j, k) * spacing`.
Between 8 neighbouring voxels (a *cell*) the field is their trilinear interpolant, and the
isosurface `F = iso` is the union of those trilinear patches (seed Sec. 3.3.4, Eq. 3.1).
`jaxiso` ray traces it **exactly**: every ray walks a min/max octree, skips every node
whose value range cannot hold the isovalue, and finds the first root of the cubic
`F(o + t d) = iso` in each remaining cell. No mesh is extracted, so a new isovalue costs
one frame, not a new mesh.

The octree is also a compressed copy of the data (Knoll 2009, ch. 3): regions of equal
voxels collapse into single values, and the rays read the voxels back from the tree
itself. This notebook tours:

1. building octree volumes (a turbulent mixing layer, a CT-like phantom),
2. compression: lossless, iso-range clamping, lossy (seed Table 3.1),
3. exploring isovalues: colours, transparency, new values without recompiling,
4. clip boxes,
5. trilinear vs central-difference normals (Sec. 4.5.1),
6. shadows (Sec. 4.5.2),
7. level of detail at dP/dV = 1, 2, 4 (ch. 4, Fig. 4.15),
8. time steps (Sec. 3.5.4),
9. loading volumes from files,
10. the derivative of the depth with respect to the isovalue.

The image size comes from `JAXISO_NB_SIZE` (default 160; the test suite runs this
notebook at 24, with 16^3 volumes). The first render of a new scene *structure* (volume
layout, number of isovalues, shading options, normals, level of detail) compiles, several
seconds on a CPU; renders that only change numbers (isovalues, clip box, camera, time
step, dP/dV) reuse the compiled program. The cells below are arranged to reuse it where
they can.
""")

code(setup("""
import importlib.util
import os
import shutil
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxiso as ji
from jaxiso.io import load_volume, save_volume
from jaxiso.volume import (
    MacrocellGrid,
    OctreeVolume,
    VolumeIsosurface,
    VolumeSequence,
    data,
    lod_for,
)
""", "160", more="""
N = max(16, min(128, SIZE // 2))   # voxels per axis of the example volumes
""", note=", {N}^3 volumes"))

code(helpers(ROW, '''
def difference(reference, image):
    """1 - |reference - image| per channel (the seed's Fig. 4.15): white where equal."""
    return ji.Image(1.0 - np.abs(np.asarray(reference) - np.asarray(image)))


def gray(values):
    """[H, W] values in [0, 1] as a grey image; NaN is white."""
    v = np.nan_to_num(np.asarray(values, np.float32), nan=1.0)
    return ji.Image(np.repeat(np.clip(v, 0.0, 1.0)[..., None], 3, axis=-1))


def signed(values, vmax):
    """[H, W] signed values as an image: blue < 0 < red, white at 0, grey where NaN."""
    values = np.asarray(values, np.float32)
    v = np.clip(np.nan_to_num(values) / vmax, -1.0, 1.0)[..., None]
    red, blue = np.array([0.75, 0.1, 0.1]), np.array([0.1, 0.25, 0.75])
    img = np.where(v > 0, 1.0 - v * (1.0 - red), 1.0 + v * (1.0 - blue))
    return ji.Image(np.where(np.isnan(values)[..., None], 0.85, img).astype(np.float32))
''', TIMED))

# ---------------------------------------------------------------------------------------
md("""
## 1. Building octree volumes

`jaxiso.volume.data` has deterministic test volumes. `data.mixing(n, time=t)` is a
Richtmyer-Meshkov-like mixing layer (a stand-in for the seed's LLNL data, Sec. 3.5.2):
heavy fluid (255) below a wrinkled interface, light fluid (0) above, turbulent noise in
between; the layer widens with `time` (0 to 4; here 2). Every generator samples its
field on a grid spanning a known box; `data.box_geometry(shape, lo, hi)` gives the
matching `(spacing, origin)`.

`OctreeVolume.from_array` builds the min/max octree bottom-up in numpy (Sec. 3.2.1):
equal voxels merge into a scalar leaf of their parent, the nodes just above the voxels
keep their 8 voxels as a *cap*, and every child records the [min, max] of the cells it
touches, which is what lets a ray skip it (Sec. 3.2.3). The result is a pytree of flat
arrays: it goes through `jax.jit` like any other argument.
""")

code("""
mixing = data.mixing(N, time=2.0)                          # float32 [N, N, N] in [0, 255]
mix_spacing, mix_origin = data.box_geometry(mixing.shape, *data.DOMAINS["mixing"])
mix_vol, dt = timed(OctreeVolume.from_array, mixing, spacing=mix_spacing, origin=mix_origin)
print(f"built in {dt:.2f} s: depth {mix_vol.depth}, {mix_vol.n_nodes} interior records, "
      f"{mix_vol.n_caps} caps, values {mix_vol.value_range}")
print(f"{mix_vol.raw_nbytes / 1e6:.2f} MB dense -> {mix_vol.nbytes / 1e6:.2f} MB octree "
      f"({mix_vol.compression_ratio:.1f}x); reconstruction exact: "
      f"{np.array_equal(mix_vol.to_array(), mixing)}")

mix_cam = ji.Camera.look_at(eye=(1.9, -1.0, 1.45), target=(0.5, 0.5, 0.45), up=(0, 0, 1),
                            fov=36, width=SIZE, height=SIZE)
interface = VolumeIsosurface(mix_vol, data.ISOVALUES["mixing"])   # 127.5, between fluids
first, t_first = timed(ji.render, interface, mix_cam)
_, t_again = timed(ji.render, interface, mix_cam)
print(f"first render {t_first:.2f} s (compiles), second {t_again * 1e3:.0f} ms")
first
""")

md("""
The surface is the interface between the two fluids: long waves carry the bubbles and
spikes of the turbulence, and drops of one fluid float in the other. The second `render`
reused the compiled program.

`data.ct_phantom(n)` is a CT-like head: nested constant ellipsoids as uint8 densities
(air 0, fluid 30, tissue 90, lesion 140, bone 200). The octree keeps uint8 voxels as
uint8, so its size is compared with 1 byte per voxel. At isovalue 150
(`data.ISOVALUES["ct_phantom"]`) we see the skull and the spine leaving through the
bottom face. Its constant regions meet in voxel steps, which the default per-cell
normals shade as rings; the head is shaded with central-difference normals (section 5),
which soften them. (One `Shading` object serves every render of the head: a palette of
another length is another array shape, which would compile again.)
""")

code("""
ct = data.ct_phantom(N)                                    # uint8 [N, N, N]
ct_spacing, ct_origin = data.box_geometry(ct.shape, *data.DOMAINS["ct_phantom"])
ct_vol = OctreeVolume.from_array(ct, spacing=ct_spacing, origin=ct_origin)
print(f"{ct_vol.dtype} voxels: {ct_vol.raw_nbytes / 1e6:.3f} MB dense -> "
      f"{ct_vol.nbytes / 1e6:.3f} MB octree ({ct_vol.compression_ratio:.1f}x)")
ct_cam = ji.Camera.look_at(eye=(2.6, -3.4, 1.6), target=(0, 0, -0.05), up=(0, 0, 1), fov=33,
                           width=SIZE, height=SIZE)
bone = ji.Shading(colors=[(0.92, 0.86, 0.74)])
skull = VolumeIsosurface(ct_vol, data.ISOVALUES["ct_phantom"], normals="central")
head, dt = timed(ji.render, skull, ct_cam, shading=bone)
print(f"render {dt:.2f} s (a uint8 volume of another layout: a new compile)")
head
""")

# ---------------------------------------------------------------------------------------
md("""
## 2. Compression (seed Sec. 3.4, Table 3.1)

Three knobs, all at build time:

* **lossless** (`variance=0`, the default): only exactly equal voxels merge. Sparse data
  compress best: the seed reports 3-5x typically, but 84% of the original for the CT head
  and 101% for a femur scan whose soft tissue is noisy.
* **iso-range clamping** (`iso_range=(a, b)`): values are clamped into `[a, b]` first, so
  everything outside collapses while isovalues inside `[a, b]` still render exactly
  (Table 3.1: RM at 64-127; the femur's bone range 100-163 gives 5.5%).
* **lossy** (`variance=s`): a node merges when the variance of its voxels is at most `s`
  (Sec. 3.4.2); each of its voxels then differs from the stored mean by at most
  `sqrt(s (count - 1))`.

Sizes include everything the octree holds (min/max tree, child pointers, caps and the
coarse averages kept for level of detail), as Table 3.1's do.
""")

code("""
def compression_row(name, raw, **options):
    vol = OctreeVolume.from_array(raw, **options)
    error = np.abs(vol.to_array().astype(np.float64) - raw.astype(np.float64)).max()
    print(f"{name:36s} {vol.raw_nbytes / 1e6:8.3f} MB {vol.nbytes / 1e6:8.3f} MB "
          f"{100 / vol.compression_ratio:6.1f} %   {error:6.1f}")


mixing_u8 = data.mixing(N, quantize=True)           # uint8, as the seed's 8-bit RM data
print(f"{'data, options':36s} {'original':>11s} {'octree':>11s} {'size':>8s}   max |error|")
compression_row("mixing float32, lossless", mixing)
compression_row("mixing uint8, lossless", mixing_u8)
compression_row("mixing uint8, iso_range 64-127", mixing_u8, iso_range=(64, 127))
for variance in (4.0, 25.0, 100.0):
    compression_row(f"mixing float32, variance {variance:g}", mixing, variance=variance)
compression_row("ct_phantom uint8, lossless", ct)
compression_row("ct_phantom uint8, iso_range 100-163", ct, iso_range=(100, 163))
grid = MacrocellGrid.from_array(mixing, spacing=mix_spacing, origin=mix_origin)
print(f"\\nmacrocell grid baseline: dense float32 voxels + min/max of "
      f"{', '.join(str(2**k) for k in grid.levels)}-cell macrocells = "
      f"{grid.nbytes / 1e6:.3f} MB")
""")

md("""
"max |error|" compares the octree's reconstruction with the input: 0 for lossless
builds; with clamping it is the change *outside* the kept range (inside it values are
exact); lossy builds show their quantisation. Quantising the mixing layer to uint8 (as the
seed's 8-bit data) shrinks the dense array 4x, and the octree by another factor: rounding
makes more neighbouring voxels equal, so more of them merge, but the tree's pointers do
not shrink with the values. The phantom is already mostly uniform, so clamping away the
soft tissue gains little there; on real CT data with noisy tissue it is the large win of
Table 3.1. The macrocell grid (Parker et al., the baseline of Sec. 3.5.1) keeps every
voxel and adds its min/max grids: larger than the data it accelerates.
""")

# ---------------------------------------------------------------------------------------
md("""
## 3. Exploring isovalues

The isovalues are a traced array of the scene: `with_isovalues` returns the same scene at
other values, and as long as their *count* stays the same the compiled renderer just
runs again: no tracing, no rebuild (the min/max tree holds the range of every node, so
culling works for any isovalue). A sweep through single isovalues reuses the program
compiled in section 1:
""")

code("""
sweep = []
for iso in (30.0, 127.5, 225.0):
    img, dt = timed(ji.render, interface.with_isovalues(iso), mix_cam)
    sweep.append(img)
    print(f"isovalue {iso:6.1f}: {dt * 1e3:6.0f} ms")
row(*sweep)
""")

md("""
Low isovalues sit at the top of the mixing layer (the first wisps of heavy fluid), high
ones at its bottom; 127.5 is the interface of section 1.

Several isovalues render in one pass: `hits.surface` says which one a ray hit, and
`Shading(colors=...)` gives each its colour. Opaque, the nested level sets would hide each
other, so here they are also transparent: `layers=3, opacity=0.45` composites the first
three surfaces along each ray front to back, re-tracing from just behind each hit (the
same mechanism as for implicit surfaces: the renderer only asks the scene for hits).
""")

code("""
glass = ji.Shading(colors=[(0.30, 0.55, 0.85), (0.85, 0.55, 0.25), (0.45, 0.75, 0.40)],
                   layers=3, opacity=0.45)
levels = VolumeIsosurface(mix_vol, (30.0, 127.5, 225.0))
nested, t_compile = timed(ji.render, levels, mix_cam, shading=glass)
shifted, t_again = timed(ji.render, levels.with_isovalues((60.0, 160.0, 240.0)), mix_cam,
                         shading=glass)
print(f"3 isovalues, 3 layers: first render {t_compile:.2f} s (compiles), "
      f"with_isovalues {t_again * 1e3:.0f} ms (no retrace)")
row(nested, shifted)
""")

md("""
Left: isovalues 30 (blue), 127.5 (orange), 225 (green). Right: the same compiled program
at 60, 160, 240. The low isovalue wraps the top of the mixing zone and its drops of heavy
fluid; through it the interface and, deeper, the bottom of the zone show, each level set
tinting what lies behind it.
""")

# ---------------------------------------------------------------------------------------
md("""
## 4. Clip box

`clip_box=(lo, hi)` intersects the volume's box with a world-space box; rays look for the
surface inside it only. It is a traced field: moving the box does not recompile (these
renders reuse the program of the head in section 1). The cut itself is not drawn; rays
entering the box there find the next crossing of the isovalue behind it.
""")

code("""
cuts = [head]
for iso, lo, what in ((115.0, -0.47, "lesion"), (60.0, -0.2, "ventricles")):
    scene = VolumeIsosurface(ct_vol, iso, clip_box=((-1, lo, -1), (1, 1, 1)),
                             normals="central")
    img, dt = timed(ji.render, scene, ct_cam, shading=bone)
    cuts.append(img)
    print(f"isovalue {iso:5.1f}, keep y >= {lo}: {dt * 1e3:5.0f} ms ({what})")
row(*cuts)
""")

md("""
Left: the closed skull (isovalue 150). Middle: isovalue 115 with the front cut away at
`y = -0.47`: the inner wall of the skull, the spine below, and the lesion (density 140
in tissue 90), which only an isovalue between 90 and 140 shows. Right: isovalue 60 with
the cut at `y = -0.2`: the fluid-filled ventricles (30) inside the tissue, in front of the
far wall.
""")

# ---------------------------------------------------------------------------------------
md("""
## 5. Normals: trilinear vs central differences (Sec. 4.5.1)

By default the normal is the gradient of the hit cell's own trilinear patch (the seed's
forward differences): continuous inside a cell, but it jumps across cell faces, so the
cell grid shows through the shading. `normals="central"` takes central differences of the
voxels at the cell's 8 corners (a 4x4x4 neighbourhood, 64 voxels) and interpolates them:
continuous across cells, at 8x the voxel lookups for each hit. Only the shading changes;
the hit points are the same. A close-up shows the difference.
""")

code("""
close_cam = ji.Camera.look_at(eye=(0.9, 0.1, 0.8), target=(0.55, 0.45, 0.47), up=(0, 0, 1),
                              fov=28, width=SIZE, height=SIZE)
forward, t_fwd = timed(ji.render, interface, close_cam)
central_scene = VolumeIsosurface(mix_vol, data.ISOVALUES["mixing"], normals="central")
central, t_compile = timed(ji.render, central_scene, close_cam)
central, t_ctr = timed(ji.render, central_scene, close_cam)
print(f"trilinear normals {t_fwd * 1e3:.0f} ms, central {t_ctr * 1e3:.0f} ms "
      f"(first call {t_compile:.1f} s: compiles)")
row(forward, central, difference(forward, central))
""")

md("""
Left, trilinear normals: facets along the cell faces. Middle, central differences: the
same surface shaded smoothly. Right: their difference, largest where the surface bends
most within a cell.
""")

# ---------------------------------------------------------------------------------------
md("""
## 6. Shadows (Sec. 4.5.2)

`Shading(shadows=True)` casts a ray from each hit towards the light; a hit before the
light puts the point in shadow. The seed adds them as a depth cue and casts them through
a coarser level of detail; here too, with `lod=` (next section) shadow rays run at
`shadow_eps_scale` (default 4) times the dP/dV of the primary rays. A low light brings out
the relief of the interface:
""")

code("""
low_light = ji.Light((0.8, -0.45, 0.35))
lit, t_lit = timed(ji.render, interface, mix_cam, light=low_light)
shadowed, t_compile = timed(ji.render, interface, mix_cam, light=low_light,
                            shading=ji.Shading(shadows=True))
_, dt = timed(ji.render, interface, mix_cam, light=low_light,
              shading=ji.Shading(shadows=True))
print(f"with shadows: {dt * 1e3:.0f} ms (without: {t_lit * 1e3:.0f} ms; first call "
      f"{t_compile:.1f} s: compiles)")
row(lit, shadowed)
""")

# ---------------------------------------------------------------------------------------
md("""
## 7. Level of detail (ch. 4)

Where one pixel covers several voxels, tracing every fine cell costs time and only adds
aliasing. With `multires=True` (the default) the build also stores the average of each
node's voxels, and `lod=lod_for(camera, quality)` lets a ray stop at a node whose cells
are at most `quality` pixel footprints wide, and intersect it as one coarse cell of
averaged voxels. `quality` is the seed's dP/dV, the pixel-to-voxel width ratio
(Sec. 4.4.1.2): at 1 a coarse cell is about a pixel wide, 2 and 4 go coarser. The level is
a function of position only, so neighbouring rays (and shadow rays) see the same cells,
and corners are blended near each switch of level so the surface stays continuous across
it (Sec. 4.4.3).

`quality` is traced: one compile serves every dP/dV. The difference images
`1 - |full - lod|` are the seed's Fig. 4.15: grey where the shading changed, dark where a
surface exists at one resolution but not the other.
""")

code("""
far_cam = ji.Camera.look_at(eye=(3.0, -2.0, 2.5), target=(0.5, 0.5, 0.42), up=(0, 0, 1),
                            fov=28, width=SIZE, height=SIZE)
full, t_full = timed(ji.render, interface, far_cam)
print(f"full resolution: {t_full * 1e3:6.0f} ms")
panels, diffs = [full], []
for quality in (1.0, 2.0, 4.0):
    scene = interface.with_lod(lod_for(far_cam, quality))
    img, dt = timed(ji.render, scene, far_cam)
    if quality == 1.0:                                # that call compiled; time it again
        img, dt = timed(ji.render, scene, far_cam)
    panels.append(img)
    diffs.append(difference(full, img))
    changed = np.abs(np.asarray(full) - np.asarray(img)).max(axis=-1) > 0.1
    print(f"dP/dV = {quality:g}: {dt * 1e3:6.0f} ms, {changed.mean():6.1%} of pixels "
          f"changed by more than 0.1")
row(*panels)
""")

code("""
row(*diffs)
""")

md("""
Top: full resolution, then dP/dV = 1, 2, 4; below: `1 - |full - lod|` for dP/dV = 1, 2, 4.
From this camera a voxel is about a pixel wide, so dP/dV = 1 keeps (nearly) every fine
cell and its difference is (nearly) blank. At 2 and 4, cells 2 and 4 voxels wide take
over, first in the distance: the major features stay, as in the seed's Fig. 4.15, but small drops
vanish, the surface shifts by up to half a coarse cell (a coarse value sits at its node's
min corner, the seed's layout) and the shading changes (grey).

The [min, max] of a node's *fine* cells does not bound the coarse cells that reach into
it, so where coarse (or blended) cells may be drawn, nodes are not culled by it (the seed
loosens its min/max tree for the same reason, Sec. 4.2.2). Remaining gaps at dP/dV = 4
are surface that the coarse field does not have. The level test and the lost culling
cost work, so level of detail pays off where it replaces many fine cells per pixel: far
views of volumes much larger than the image, the seed's case. Compare the timings above.
""")

# ---------------------------------------------------------------------------------------
md("""
## 8. Time steps (Sec. 3.5.4)

`VolumeSequence.from_arrays(frames, ...)` builds one lossless octree per time step (steps
compress differently, as Table 3.1's heptane rows show) and stacks their arrays, padded to
the largest, so `seq.at(step)` selects a step *without recompiling*: the step may even be
a traced integer inside `jax.jit`. The mixing layer's `time` argument widens the layer and
drifts its turbulence; time 2 is the volume of the sections above.
""")

code("""
times = (0.0, 1.0, 2.0, 4.0)
frames = [data.mixing(N, time=t) for t in times]
seq, dt = timed(VolumeSequence.from_arrays, frames, spacing=mix_spacing, origin=mix_origin)
print(f"{seq.n_steps} steps built in {dt:.2f} s: {seq.raw_nbytes / 1e6:.2f} MB dense, "
      f"{seq.nbytes / 1e6:.3f} MB in octrees ({seq.compression_ratio:.1f}x), "
      f"{seq.padded_nbytes / 1e6:.3f} MB held (each padded to the largest step)")
print("per step:", ", ".join(f"{b / 1e3:.0f} kB" for b in seq.volume_nbytes))
movie = []
for step, t in enumerate(times):
    scene = VolumeIsosurface(seq.at(step), data.ISOVALUES["mixing"])
    img, dt = timed(ji.render, scene, mix_cam)
    movie.append(img)
    print(f"time {t:3.1f} (step {step}): {dt * 1e3:6.0f} ms")
row(*movie)
""")

md("""
Later steps are wider and more turbulent, and their octrees larger (more distinct
voxels), like the seed's later heptane and RM time steps. Only the first step's render
compiled.
""")

# ---------------------------------------------------------------------------------------
md("""
## 9. Loading volumes from files

`jaxiso.io.load_volume(path)` returns `(array, meta)` for `.npy`, `.npz`, NIfTI (`.nii`,
`.nii.gz`, with nibabel), VTK image data (`.vti`) and headerless raw bricks (pass
`shape=` and `dtype=`). `meta` holds the spacing and origin where the file records
them; `save_volume` writes them (`.npz`, NIfTI). Here the phantom makes a round trip
through a temporary folder.
""")

code("""
folder = Path(tempfile.mkdtemp())
np.save(folder / "head.npy", ct)                              # voxels only
array, meta = load_volume(folder / "head.npy")
print("npy :", array.shape, array.dtype, meta)
save_volume(folder / "head.npz", ct, spacing=ct_spacing, origin=ct_origin)
array, meta = load_volume(folder / "head.npz")                # voxels and geometry
print("npz :", array.shape, array.dtype, meta)
loaded = OctreeVolume.from_array(array, spacing=meta["spacing"], origin=meta["origin"])
img, dt = timed(ji.render, VolumeIsosurface(loaded, 150.0, normals="central"), ct_cam,
                shading=bone)
print(f"render {dt * 1e3:.0f} ms: the same layout as the head of section 1, no compile")
img
""")

code("""
if importlib.util.find_spec("nibabel"):
    import nibabel as nib

    affine = np.diag(list(ct_spacing) + [1.0])              # voxel -> world (mm, say)
    affine[:3, 3] = ct_origin
    nib.save(nib.Nifti1Image(ct, affine), folder / "head.nii.gz")
    array, meta = load_volume(folder / "head.nii.gz")
    print("nifti:", array.shape, array.dtype, "spacing", meta["spacing"], "origin",
          meta["origin"], "axis aligned:", meta["axis_aligned"])
else:
    print("nibabel is not installed: pip install 'jaxiso[data]' to read NIfTI files")
shutil.rmtree(folder)                                         # drop the temporary copies
""")

# ---------------------------------------------------------------------------------------
md("""
## 10. Derivatives: d depth / d isovalue

The hit distance `t` solves `F(o + t d) = iso` in the hit cell, so by the implicit
function theorem `dt/diso = 1 / (grad F . d)`. `jaxiso` attaches this derivative to `t`
(a `custom_jvp`) instead of differentiating through the traversal loop; the same rule
gives derivatives with respect to the rays and to float voxel values. `jax.jvp` returns
the depth and its derivative in one call; central finite differences of the depth check
it.
""")

code("""
@jax.jit
def depth_and_slope(iso):
    \"\"\"([H, W] distance to the isosurface (inf: miss), its derivative in iso).\"\"\"
    def depth(iso):
        return ji.intersect(VolumeIsosurface(mix_vol, iso), mix_cam.rays()).t
    return jax.jvp(depth, (iso,), (jnp.ones_like(iso),))


iso, h = jnp.float32(127.5), 0.5
t, dt_diso = (np.asarray(a) for a in depth_and_slope(iso))
t_up, t_down = (np.asarray(depth_and_slope(iso + s)[0]) for s in (h, -h))
both = np.isfinite(t) & np.isfinite(t_up) & np.isfinite(t_down)
finite_diff = np.full_like(t, np.nan)
finite_diff[both] = (t_up[both] - t_down[both]) / (2 * h)
close = np.isclose(dt_diso[both], finite_diff[both], rtol=0.05, atol=1e-5)
print(f"dt/diso: median {np.median(dt_diso[both]):.2e} per unit of isovalue; within 5% of "
      f"finite differences on {close.mean():.0%} of the {both.sum()} pixels hit")
near, far = np.nanmin(np.where(both, t, np.nan)), np.nanmax(np.where(both, t, np.nan))
scale = np.percentile(np.abs(dt_diso[both]), 95)
row(gray(np.where(both, 0.15 + 0.8 * (t - near) / (far - near), np.nan)),
    signed(np.where(both, dt_diso, np.nan), scale), signed(finite_diff, scale))
""")

md("""
Left: depth (dark = near). Middle: `dt/diso` from `jax.jvp`; right: finite differences,
on the same colour scale (red: the surface moves away from the camera as the isovalue
rises, since the heavy fluid, with the higher values, lies below). The derivative is
largest where rays graze the surface (`grad F . d` near 0). Finite differences disagree
where the surface's topology changes within `+-h` (a bubble appears or vanishes in front
of the hit): there the depth jumps, and the tangent describes only the surface that was
hit.

## Where next

* `VolumeIsosurface(..., method="analytic")` solves the cell cubic in closed form instead
  of Marmitt/Neubauer's iteration (Sec. 3.3.4); `traversal="neighbor"` resumes at the
  deepest common ancestor instead of the root (Sec. 3.3.2.2).
* `MacrocellGrid.from_array(data)` is the dense baseline the octree is measured against
  (Table 3.2): `VolumeIsosurface` takes it in place of an `OctreeVolume`.
* Volumes are pytrees: `jax.jvp`/`jax.grad` of depths or images with respect to float
  voxel values work as above.
""")
if __name__ == "__main__":
    regenerate(__file__)  # builds, executes and stores the notebook
