"""The examples run: the superquadric fit recovers its exponents through the
differentiable tracer (in process, at a small size)."""

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
