"""The surface catalogue: float32 functions against the independent float64 references,
zero sets inside their domains, default cameras framing them."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
import reference64

import jaxiso as ji

S = ji.surfaces
NAMES = S.names()

# zero sets that the domain box necessarily cuts: unbounded (steiner holds the coordinate
# axes, teardrop's sheet for x > 0, the Barth cones), periodic or quasi-periodic (the CSG
# entries are bounded by their conditions instead, see test_csg_object_inside_domain)
CUT_BY_BOX = {"steiner", "teardrop", "barth_sextic", "barth_decic", "icos.csg", "sin.blob",
              "cloth", "water"}

# float32 vs float64: relative to |f| + sum_i |df/dx_i| (1 + |x_i|), which bounds the
# rounding of the terms (and of the arguments of transcendentals); observed <= 6e-7
RTOL = 2.0**-16


def test_names_order():
    b1 = ["sphere", "steiner", "mitchell", "teardrop", "bretzel4", "klein", "tangle",
          "decocube", "barth_sextic", "barth_decic", "superquadric"]
    assert NAMES == b1 + ["icos.csg", "sesc.csg", "sin.blob", "cloth", "water", "morph"]
    assert set(reference64.SURFACES) == set(NAMES)


def test_fields():
    for name in NAMES:
        s = S.get(name)
        assert s.name == name
        assert 2.0**-13 <= s.eps <= 2.0**-9, name
        assert len(s.lo) == len(s.hi) == 3 and all(a < b for a, b in zip(s.lo, s.hi)), name
        assert s.isovalues == (0.0,), name
        if s.w_range is not None:
            assert s.w_range[0] < s.w_range[1] and s.w_range[0] <= s.w <= s.w_range[1], name
        assert bool(s.parts) == bool(s.csg) == name.endswith(".csg"), name
        for part, _ in s.parts:
            assert part in s.csg, (name, part)
    assert dict(S.get("icos.csg").parts)["ic"] is S.get("icos.csg").f
    assert dict(S.get("sesc.csg").parts)["se"] is S.get("sesc.csg").f
    assert S.get("cloth").eps == S.get("water").eps == 2.0**-9  # Table 6.1
    assert S.get("sesc.csg").eps == 2.0**-13


def _functions():
    """(label, float32 catalogue function, float64 reference, surface)."""
    out = []
    for name in NAMES:
        s = S.get(name)
        out.append((name, s.f, reference64.SURFACES[name], s))
        for part, g in s.parts:
            out.append((f"{name}:{part}", g, reference64.CSG_PARTS[name][part], s))
    return out


FUNCTIONS = _functions()


CHUNK = 4096  # one array shape throughout, so eager jnp ops compile once per primitive


def _eval32(g, p, w):
    p = np.asarray(p, np.float32)
    flat = p.reshape(-1, 3)
    n = len(flat)
    flat = np.concatenate([flat, np.zeros((-n % CHUNK, 3), np.float32)])
    out = [np.asarray(g(*(jnp.asarray(c[:, i]) for i in range(3)), w), np.float64)
           for c in np.split(flat, len(flat) // CHUNK)]
    return np.concatenate(out)[:n].reshape(p.shape[:-1])


@pytest.mark.parametrize("label,f32,f64,s", FUNCTIONS, ids=[f[0] for f in FUNCTIONS])
def test_agrees_with_reference64(label, f32, f64, s):
    rng = np.random.default_rng(abs(hash(label)) % 2**32)
    lo, hi = np.array(s.lo), np.array(s.hi)
    ws = [s.w] if s.w_range is None else [s.w, *np.linspace(*s.w_range, 3).tolist()]
    for w in ws:
        p = rng.uniform(lo, hi, (2000, 3)).astype(np.float32)
        v32 = _eval32(f32, p, w)
        p = p.astype(np.float64)
        h = 1e-6 * (hi - lo)
        with np.errstate(over="ignore", invalid="ignore"):
            v64 = f64(p[:, 0], p[:, 1], p[:, 2], w)
            grad = np.stack([(f64(*(p + h[i] * np.eye(3)[i]).T, w)
                              - f64(*(p - h[i] * np.eye(3)[i]).T, w)) / (2 * h[i])
                             for i in range(3)], -1)
            mag = np.abs(v64) + np.sum(np.abs(grad) * (1 + np.abs(p)), -1)
        big = ~(np.abs(v64) < np.finfo(np.float32).max)  # superquadric: x^500 overflows
        assert np.all(v32[big] == np.inf), label
        err = np.abs(v32 - v64)[~big] / mag[~big]
        assert err.max() < RTOL, f"{label} w={w}: {err.max():.3g} at {p[~big][err.argmax()]}"


def _sample(s, n, rng, w=None):
    p = rng.uniform(s.lo, s.hi, (n, 3))
    return p, _eval32(s.f, p, s.w if w is None else w)


@pytest.mark.parametrize("name", NAMES)
def test_zero_set_meets_domain(name):
    s = S.get(name)
    rng = np.random.default_rng(1)
    ws = [s.w] if s.w_range is None else [s.w, *s.w_range]
    for w in ws:
        _, v = _sample(s, 4000, rng, w)
        assert (v < 0).any() and (v > 0).any(), (name, w)


def _face_points(s, n=41):
    lo, hi = np.array(s.lo), np.array(s.hi)
    t = np.linspace(0, 1, n)
    faces = []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        A, B = np.meshgrid(lo[a] + t * (hi[a] - lo[a]), lo[b] + t * (hi[b] - lo[b]))
        for v in (lo[ax], hi[ax]):
            p = np.zeros(A.shape + (3,))
            p[..., a], p[..., b], p[..., ax] = A, B, v
            faces.append(p.reshape(-1, 3))
    return np.concatenate(faces)


@pytest.mark.parametrize("name", [n for n in NAMES if n not in CUT_BY_BOX])
def test_zero_set_inside_domain(name):
    """Bounded surfaces: f keeps one sign (outside) on the faces of the box."""
    s = S.get(name)
    p = _face_points(s)
    for w in [s.w] if s.w_range is None else [s.w, *s.w_range]:
        v = _eval32(s.f, p, w)
        assert (v > 0).all(), (name, w, p[v <= 0][:3])


def test_csg_object_inside_domain():
    s = S.get("icos.csg")
    parts = dict(s.parts)
    half = min(min(-a, b) for a, b in zip(s.lo, s.hi))
    r_in = math.sqrt(float(parts["sphere_inner"](0.0, 0.0, 0.0, 0.0)))
    r_out = math.sqrt(float(parts["sphere_outer"](0.0, 0.0, 0.0, 0.0)))
    assert 0 < r_in < r_out <= half
    # the shell holds both signs of ic: the condition keeps part of the lattice
    rng = np.random.default_rng(2)
    p, v = _sample(s, 20000, rng)
    r = np.linalg.norm(p, axis=-1)
    shell = (r > r_in) & (r < r_out)
    assert shell.sum() > 100 and (v[shell] < 0).any() and (v[shell] > 0).any()
    # sesc: the object lies inside se <= 0 (se > 0 on the faces: test_zero_set_inside_domain);
    # sc changes sign inside, so both branches of the union are drawn
    s = S.get("sesc.csg")
    sc = dict(s.parts)["sc"]
    p, v = _sample(s, 20000, rng)
    inside = _eval32(sc, p[v < 0], s.w)
    assert (inside < 0).any() and (inside > 0).any()


def _surface_points(s, n=24):
    """Midpoints of grid edges where the drawn surface changes sign (CSG conditions applied)."""
    g = [np.linspace(s.lo[i], s.hi[i], n) for i in range(3)]
    X = np.stack(np.meshgrid(*g, indexing="ij"), -1)

    def crossings(fn):
        v, out = fn(X), []
        for ax in range(3):
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[ax], b[ax] = slice(0, -1), slice(1, None)
            m = np.sign(v[tuple(a)]) != np.sign(v[tuple(b)])
            out.append(0.5 * (X[tuple(a)][m] + X[tuple(b)][m]))
        return np.concatenate(out)

    ev = lambda g_: (lambda p: _eval32(g_, p, s.w))
    if not s.parts:
        return crossings(ev(s.f))
    parts = {k: ev(g_) for k, g_ in s.parts}
    if s.name == "icos.csg":
        p = crossings(parts["ic"])
        return p[(parts["sphere_inner"](p) < 0) & (parts["sphere_outer"](p) > 0)]
    assert s.name == "sesc.csg"
    p, q = crossings(parts["se"]), crossings(parts["sc"])
    return np.concatenate([p[parts["sc"](p) > 0], q[parts["se"](q) < 0]])


def _camera(s):
    eye, target, up = (np.asarray(v, np.float64) for v in (s.eye, s.target, s.up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    assert np.linalg.norm(right) > 0.1 * np.linalg.norm(up), f"{s.name}: up ~ view direction"
    right /= np.linalg.norm(right)
    return eye, fwd, right, np.cross(right, fwd)


@pytest.mark.parametrize("name", NAMES)
def test_default_camera(name):
    s = S.get(name)
    assert 0 < s.fov < 180
    eye, fwd, right, up = _camera(s)
    lo, hi = np.array(s.lo), np.array(s.hi)
    assert not ((lo <= eye) & (eye <= hi)).all(), "eye inside the domain"
    c = 0.5 * (lo + hi) - eye
    cos = np.clip(c @ fwd / np.linalg.norm(c), -1.0, 1.0)
    assert np.degrees(np.arccos(cos)) < s.fov / 2, "centre not seen"
    # the surface is in front, inside a square frame, and fills a good part of it
    d = _surface_points(s) - eye
    depth = d @ fwd
    assert (depth > 0).all()
    t = math.tan(math.radians(s.fov) / 2)
    ndc = np.abs(np.stack([d @ right, d @ up], -1) / (depth[:, None] * t)).max(-1)
    assert ndc.max() <= 1.0, f"{name}: surface outside the frame ({ndc.max():.3f})"
    assert ndc.max() >= 0.6, f"{name}: surface fills too little of the frame ({ndc.max():.3f})"
