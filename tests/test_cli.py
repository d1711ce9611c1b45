"""The main job (README quick start, step 1) runs and prints every catalogue surface."""

import subprocess
import sys

import jaxiso as ji


def test_demo_runs_and_lists_catalogue():
    out = subprocess.run([sys.executable, "-m", "jaxiso.cli", "demo", "--names", "sphere",
                          "barth_sextic"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "barth_sextic" in out.stdout and "sphere" in out.stdout
    assert "certainly true" in out.stdout


def test_catalogue_lookup():
    assert "barth_sextic" in ji.surfaces.names()
    try:
        ji.surfaces.get("nope")
    except KeyError as e:
        assert "known" in str(e)
    else:
        raise AssertionError("unknown surface did not raise")


def test_gallery_writes_images_with_progress(tmp_path):
    out = subprocess.run([sys.executable, "-m", "jaxiso.cli", "gallery", "--out", str(tmp_path),
                          "--size", "16", "--names", "sphere", "sesc.csg"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "[ 1/2] sphere" in out.stdout and "[ 2/2] sesc.csg" in out.stdout
    from PIL import Image
    for name in ("sphere", "sesc.csg", "gallery"):
        img = Image.open(tmp_path / f"{name}.png")
        assert img.size[1] == 16
    sphere = __import__("numpy").asarray(Image.open(tmp_path / "sphere.png"))
    assert (sphere.sum(-1) < 3 * 250).mean() > 0.3  # the sphere covers the frame centre


def test_gallery_rejects_unknown_names(tmp_path):
    out = subprocess.run([sys.executable, "-m", "jaxiso.cli", "gallery", "--out", str(tmp_path),
                          "--names", "nope"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "unknown surfaces: nope" in out.stderr
