"""Render the README's contact sheet: one panel per scene kind, side by side.

    python examples/make_contact_sheet.py                      # -> docs/images/contact_sheet.png
    python examples/make_contact_sheet.py --size 96 --out sheet.png

Panels, left to right: an implicit (the Barth sextic of the catalogue, with shadows), a
neural implicit (the "Spelunking the Deep" fox, read from $JAXISO_NEURAL_DATA or
/work/shared/data/neural; where that file is absent, a small ReLU network written here
that computes a rounded zonotope), a volume isosurface (two isovalues of the synthetic
mixing layer, clipped) and a tetrahedral mesh isosurface (three isovalues of a wave on a
cube of tets, clipped). Only public jaxiso names are used. Each panel prints its time, most of it
compilation.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import time

import jax.numpy as jnp
import numpy as np
from PIL import Image, ImageDraw

import jaxiso as ji
from jaxiso import tetra
from jaxiso.volume import OctreeVolume, VolumeIsosurface
from jaxiso.volume import data as volume_data

ROOT = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "docs" / "images" / "contact_sheet.png"
NEURAL_DIR = pathlib.Path(os.environ.get("JAXISO_NEURAL_DATA", "/work/shared/data/neural"))


def implicit_panel(size):
    scene = ji.surfaces.scene("barth_sextic")
    cam = ji.surfaces.camera("barth_sextic", size)
    return "implicit: Barth sextic", ji.render(scene, cam, shading=ji.Shading(shadows=True))


def _zonotope_network(directions=7):
    """A two-layer ReLU network: sum_k |n_k . p| - 1.2, with |s| = relu(s) + relu(-s)."""
    rng = np.random.default_rng(3)
    n = rng.normal(size=(directions, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True) * 2.2
    first = {"A": jnp.asarray(np.concatenate([n, -n]).T, jnp.float32),
             "b": jnp.zeros(2 * directions, jnp.float32)}
    second = {"A": jnp.ones((2 * directions, 1), jnp.float32),
              "b": jnp.asarray([-1.2], jnp.float32)}
    return ji.implicit.MLP("relu", [first, second])


def neural_panel(size):
    path = NEURAL_DIR / "fox.npz"
    if path.exists():
        net, label = ji.implicit.load_mlp(path), "neural: fox (8 x 32 ReLU)"
        eye, target = (2.0, 1.2, 0.8), (0.0, -0.1, -0.05)
    else:
        net, label = _zonotope_network(), "neural: ReLU zonotope"
        eye, target = (2.4, 1.6, 1.2), (0.0, 0.0, 0.0)
    scene = ji.ImplicitSurface(net, (-1.0,) * 3, (1.0,) * 3, params=net.params, eps=2.0**-8)
    cam = ji.Camera.look_at(eye=eye, target=target, up=(0, 0, 1), fov=38, width=size,
                            height=size)
    return label, ji.render(scene, cam)


def volume_panel(size):
    voxels = volume_data.mixing(64, time=2.0)
    vol = OctreeVolume.from_array(voxels, spacing=1 / 63, origin=0.0)
    scene = VolumeIsosurface(vol, isovalues=(60.0, 127.5),
                             clip_box=((0, 0, 0), (1, 0.6, 1)), normals="central")
    cam = ji.Camera.look_at(eye=(1.9, -1.0, 1.45), target=(0.5, 0.5, 0.45), up=(0, 0, 1),
                            fov=36, width=size, height=size)
    return "volume: mixing layer 64^3", ji.render(scene, cam,
                                                   shading=ji.Shading(shadows=True))


def tet_panel(size):
    points, tets = tetra.data.cube_tets(12)
    mesh = tetra.tet_mesh(points, tets, tetra.data.wave_field(points, frequency=1.0))
    scene = ji.TetIsosurface(mesh, (-0.5, 0.0, 0.5), normals="smooth",
                             clip_box=((0, 0, 0), (1, 1, 0.6)))
    cam = ji.Camera.look_at(eye=(2.3, -1.3, 1.8), target=(0.5, 0.5, 0.4), up=(0, 0, 1),
                            fov=36, width=size, height=size)
    return f"tet mesh: {len(tets)} tets", ji.render(scene, cam)


PANELS = (implicit_panel, neural_panel, volume_panel, tet_panel)


def sheet(images, labels, size):
    """The panels in a row, each with its label on a strip beneath it."""
    strip = max(12, size // 12)
    out = Image.new("RGB", (size * len(images), size + strip), "white")
    draw = ImageDraw.Draw(out)
    for k, (img, label) in enumerate(zip(images, labels, strict=True)):
        pixels = np.clip(np.asarray(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        out.paste(Image.fromarray(pixels), (k * size, 0))
        draw.text((k * size + 4, size + 1), label, fill=(40, 40, 40))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=192, help="panel edge in pixels")
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    args = ap.parse_args(argv)
    images, labels = [], []
    for panel in PANELS:
        t0 = time.perf_counter()
        label, img = panel(args.size)
        print(f"{label:32s} {time.perf_counter() - t0:6.1f} s", flush=True)
        images.append(img)
        labels.append(label)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet(images, labels, args.size).save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
