"""The examples run (in process, at a small size): the superquadric fit recovers its
exponents through the differentiable tracer; the neural SDF fit learns, renders and
saves weights that `load_mlp` reads back."""

import importlib.util
import pathlib
import re

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"


def load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_fit_superquadric_recovers_exponents(capsys):
    fit = load("fit_superquadric")
    rc = fit.main(["--size", "16", "--steps", "30"])
    out = capsys.readouterr().out
    m = re.search(r"recovered a = ([\d.]+) .*b = ([\d.]+) .*loss ([\d.e+-]+) -> "
                  r"([\d.e+-]+);", out)
    assert m, out
    a, b, first, last = (float(v) for v in m.groups())
    assert rc == 0, out
    assert abs(a - fit.TRUE["a"]) < 0.1 * fit.TRUE["a"], out
    assert abs(b - fit.TRUE["b"]) < 0.1 * fit.TRUE["b"], out
    # much closer than the start, and the depth error fell by orders of magnitude
    for k, v in (("a", a), ("b", b)):
        assert abs(v - fit.TRUE[k]) < 0.25 * abs(fit.START[k] - fit.TRUE[k]), out
    assert last < first / 100, out
    assert out.count("step ") >= 5  # progress is printed


def test_fit_neural_sdf_trains_renders_and_round_trips(tmp_path, capsys):
    import numpy as np
    from PIL import Image

    import jaxiso as ji

    fit = load("fit_neural_sdf")
    png, npz = tmp_path / "net.png", tmp_path / "net.npz"
    result = fit.run(["--steps", "150", "--size", "16", "--every", "50",
                      "--out", str(png), "--save-npz", str(npz)])
    out = capsys.readouterr().out
    assert result["ok"], out
    # the fit learned: held-out error and training loss both fell severalfold
    assert result["error_after"] < result["error_before"] / 4, out
    losses = result["losses"]
    assert len(losses) == 150 and np.mean(losses[-10:]) < np.mean(losses[:10]) / 3, out
    assert out.count("step ") == 3 and "fit error:" in out, out
    # the PNG shows the surface on a white background
    img = np.asarray(Image.open(png))
    assert img.shape == (16, 16, 3), img.shape
    assert result["hit_pixels"] > 0 and (img < 250).any(axis=-1).sum() > 0
    # the .npz has the Spelunking layout and load_mlp reads back the same weights
    keys = sorted(np.load(npz).files)
    assert keys == ["0000.dense.A", "0000.dense.b", "0001.relu._", "0002.dense.A",
                    "0002.dense.b", "0003.relu._", "0004.dense.A", "0004.dense.b",
                    "0005.relu._", "0006.dense.A", "0006.dense.b", "0007.squeeze_last._"]
    loaded = ji.implicit.load_mlp(npz)
    assert loaded.activation == "relu" and result["roundtrip"] == 0.0
    for ours, theirs in zip(result["params"], loaded.params, strict=True):
        for k in ("A", "b"):
            np.testing.assert_array_equal(np.asarray(ours[k]), np.asarray(theirs[k]))
