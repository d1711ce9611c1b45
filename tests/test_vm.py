"""`.vm` programs (fidget / Prospero format) read into jaxiso functions.

References: closed forms written by hand, and for Prospero an independent float64 numpy
interpreter below (a dict of names, no shared code with jaxiso.implicit.vm).
"""

import math
import pathlib

import numpy as np
import pytest

import jaxiso as ji
from jaxiso.implicit import load_vm

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"

CIRCLE = """# x^2 + y^2 - 0.5^2, as the Prospero programs write it
_0 var-x
_1 var-y
_2 square _0
_3 square _1
_4 add _2 _3
_5 sqrt _4
_6 const 0.5
_7 sub _5 _6
"""


def test_circle_program_matches_its_closed_form():
    prog = load_vm(CIRCLE)
    assert len(prog) == 8 and prog.variables == ("x", "y")
    x, y = np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 7))
    got = np.asarray(prog(x.astype(np.float32), y.astype(np.float32), 0.0))
    np.testing.assert_allclose(got, np.hypot(x, y) - 0.5, atol=1e-6)


def test_every_opcode_evaluates_like_numpy():
    text = "\n".join([
        "a var-x", "b var-y", "c var-z", "k const -1.25",
        "u0 neg a", "u1 abs k", "u2 recip u1", "u3 exp b", "u4 ln u3", "u5 sin a",
        "u6 cos b", "u7 tan c", "u8 atan a", "u9 floor k", "u10 ceil k", "u11 round k",
        "u12 copy c", "b0 add a b", "b1 sub a c", "b2 mul b c", "b3 div a u1", "b4 min a b",
        "b5 max b c", "b6 atan2 a b", "s0 asin u8", "s1 acos u8",
        "r add u0 u2", "r2 add r u4", "r3 add r2 u5", "r4 add r3 u6", "r5 add r4 u7",
        "r6 add r5 u9", "r7 add r6 u10", "r8 add r7 u11", "r9 add r8 u12", "r10 add r9 b0",
        "r11 add r10 b1", "r12 add r11 b2", "r13 add r12 b3", "r14 add r13 b4",
        "r15 add r14 b5", "r16 add r15 b6", "r17 add r16 s0", "r18 add r17 s1"])
    x, y, z = 0.3, -0.7, 0.2
    u8 = math.atan(x)
    expect = (-x + 1 / 1.25 + y + math.sin(x) + math.cos(y) + math.tan(z) + math.floor(-1.25)
              + math.ceil(-1.25) + round(-1.25) + z + (x + y) + (x - z) + y * z + x / 1.25
              + min(x, y) + max(y, z) + math.atan2(x, y) + math.asin(u8) + math.acos(u8))
    got = float(load_vm(text + "\n")(np.float32(x), np.float32(y), np.float32(z)))
    assert got == pytest.approx(expect, abs=1e-5)


@pytest.mark.parametrize("text, message", [
    ("a var-x\nb foo a\n", r"line 2: unsupported opcode 'foo' \(supported: const, var-x"),
    ("a var-x\nb add a\n", r"line 2: add takes 2 operands, got 1"),
    ("a var-x\nb neg q\n", r"line 2: operand 'q' is not defined on an earlier line"),
    ("a const 1.5x\n", r"line 1: const value '1.5x' is not a number"),
    ("a const nan\n", r"line 1: const value 'nan' is not finite"),
    ("a var-x\na var-y\n", r"line 2: 'a' is defined twice"),
    ("a var-x 3\n", r"line 1: var-x takes no operands"),
    ("# only a comment\n\n", r"no instructions"),
    ("# c\nlonely\n", r"line 2: expected 'name opcode args...'"),
])
def test_malformed_programs_name_the_line(text, message):
    with pytest.raises(ValueError, match=message):
        load_vm(text)


def test_a_file_that_is_not_text(tmp_path):
    path = tmp_path / "x.vm"
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ValueError, match=r"x.vm: not a text .vm program"):
        load_vm(path)


def test_circle_program_renders_as_an_extruded_implicit():
    scene = ji.ImplicitSurface(load_vm(CIRCLE), (-1, -1, -1), (1, 1, 1), eps=2.0**-9)
    cam = ji.Camera.orthographic_view((0, 0, 3), (0, 0, 0), (0, 1, 0), 1.0, 16, 16)
    hits = ji.intersect(scene, cam.rays())
    o = np.asarray(cam.rays().origin)
    inside = np.hypot(o[..., 0], o[..., 1]) < 0.5
    # axis-parallel rays down z: a ray inside the disc starts inside the extruded cylinder
    # (f < 0 all along, no crossing), outside it never meets it; only the rim is hit
    rim = np.abs(np.hypot(o[..., 0], o[..., 1]) - 0.5) < 2.0**-8
    assert not np.any(np.asarray(hits.hit) & ~rim & ~inside)
    # from the side the cylinder wall is hit where the closed form says
    side = ji.Camera.orthographic_view((3, 0, 0), (0, 0, 0), (0, 0, 1), 0.9, 16, 16)
    rays = side.rays()
    hits = ji.intersect(scene, rays)
    o = np.asarray(rays.origin)
    expect = np.abs(o[..., 1]) < 0.5
    t_ref = 3.0 - np.sqrt(np.maximum(0.25 - o[..., 1] ** 2, 0.0))
    hit = np.asarray(hits.hit)
    assert np.array_equal(hit, expect) and expect.sum() > 50
    assert np.max(np.abs(np.asarray(hits.t)[hit] - t_ref[hit])) < 4 * 2.0**-9


def _numpy_vm(path, x, y):
    """Independent float64 reference interpreter of the Prospero opcodes."""
    env = {}
    last = None
    for line in pathlib.Path(path).read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, op, *args = line.split()
        a = [env[k] for k in args] if op != "const" else None
        env[name] = {
            "const": lambda: np.full_like(x, float(args[0])), "var-x": lambda: x,
            "var-y": lambda: y, "add": lambda: a[0] + a[1], "sub": lambda: a[0] - a[1],
            "mul": lambda: a[0] * a[1], "neg": lambda: -a[0], "square": lambda: a[0] ** 2,
            "sqrt": lambda: np.sqrt(a[0]), "min": lambda: np.minimum(a[0], a[1]),
            "max": lambda: np.maximum(a[0], a[1])}[op]()
        last = name
    return env[last]


def test_prospero_loads_and_agrees_with_a_float64_interpreter():
    path = DATA / "prospero.vm"
    if not path.exists():
        pytest.skip(f"{path} is absent (shared third-party data, not in the repository)")
    prog = load_vm(path)
    assert len(prog) == 7866 and prog.variables == ("x", "y")
    assert prog.counts()["max"] == 2094 and prog.counts()["min"] == 784
    g = np.linspace(-1, 1, 33)
    x, y = np.meshgrid(g, g)
    ref = _numpy_vm(path, x, y)
    got = np.asarray(prog(x.astype(np.float32), y.astype(np.float32), 0.0), np.float64)
    # same sign (inside/outside) wherever the reference is not within float32 noise of 0
    clear = np.abs(ref) > 1e-4
    assert np.array_equal(got[clear] < 0, ref[clear] < 0)
    assert 0.05 < np.mean(ref < 0) < 0.95  # the text covers part of the square
