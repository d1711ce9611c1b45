"""Any scalar JAX function works everywhere (issue 13, item 1).

The user's f is written for one point (scalars in, one number out) and need not broadcast
over arrays: ``jnp.stack([x, y, z]) @ W`` is a dot_general of a [3] vector, which fails
on [P]-shaped coordinates. Bisection (through `extend`, which traces f on scalars),
the hit finisher, normals, the implicit-function-theorem derivatives, CSG's part choice,
the baselines and `render` all evaluate f through `on_points` (a `jax.vmap`).

Hits of small ReLU networks are checked against an independent float64 numpy tracer:
4000 uniform samples of the same network along each ray inside the box, then bisection
of the first sign change.
"""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji
from jaxiso.implicit import csg
from jaxiso.implicit._field import on_points

LO, HI = -1.5, 1.5
SIZE = 24
CAM = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 50.0, SIZE, SIZE)
NEURAL = pathlib.Path("/work/shared/data/neural")


def _weights(hidden=16, seed=7):
    """A 3 -> hidden -> 1 ReLU network f(p) = sum_i a_i relu(n_i . p + c_i) - 2 with unit
    n_i and a_i > 0: a sum of convex functions, so {f < 0} is a convex (rounded
    polytope) solid around the origin, well inside the box."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(3, hidden))
    n /= np.linalg.norm(n, axis=0)
    return {"W1": n.astype(np.float32),
            "b1": rng.uniform(-0.2, 0.2, hidden).astype(np.float32),
            "W2": rng.uniform(0.5, 1.5, (hidden, 1)).astype(np.float32),
            "b2": np.array([-2.0], np.float32)}


WEIGHTS = _weights()
_W = {k: jnp.asarray(v) for k, v in WEIGHTS.items()}


def mlp(x, y, z):
    """Scalar-only: weights are closure constants; does not broadcast over arrays."""
    h = jax.nn.relu(jnp.stack([x, y, z]) @ _W["W1"] + _W["b1"])
    return (h @ _W["W2"] + _W["b2"])[0]


def mlp_params(x, y, z, params):
    h = jax.nn.relu(jnp.stack([x, y, z]) @ params["W1"] + params["b1"])
    return (h @ params["W2"] + params["b2"])[0]


# -- the float64 reference ------------------------------------------------------------

def _net64(weights):
    layers = [(np.asarray(A, np.float64), np.asarray(b, np.float64)) for A, b in weights]

    def f(P):
        h = P
        for i, (A, b) in enumerate(layers):
            h = h @ A + b
            if i < len(layers) - 1:
                h = np.maximum(h, 0.0)
        return h[..., 0]
    return f


def _reference(f64, rays, lo=LO, hi=HI, samples=4000):
    """First root t of f64 along each ray inside the box [lo, hi]^3 (inf: none)."""
    o = np.asarray(rays.origin, np.float64).reshape(-1, 3)
    d = np.asarray(rays.direction, np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.maximum(np.max(np.minimum(ta, tb), -1), 0.0)
    t1 = np.min(np.maximum(ta, tb), -1)
    out = np.full(len(o), np.inf)
    for i in np.nonzero(t0 <= t1)[0]:
        ts = np.linspace(t0[i], t1[i], samples)
        v = f64(o[i] + ts[:, None] * d[i])
        change = np.nonzero((v[:-1] <= 0) != (v[1:] <= 0))[0]
        if len(change) == 0:
            continue
        a, b = ts[change[0]], ts[change[0] + 1]
        inside_a = v[change[0]] <= 0
        for _ in range(60):
            m = 0.5 * (a + b)
            if (f64(o[i] + m * d[i]) <= 0) == inside_a:
                a = m
            else:
                b = m
        out[i] = 0.5 * (a + b)
    return out


def _mlp64(weights=WEIGHTS):
    return _net64([(weights["W1"], weights["b1"]), (weights["W2"], weights["b2"])])


@pytest.fixture(scope="module")
def reference():
    return _reference(_mlp64(), CAM.rays())


def _scene(**kw):
    return ji.ImplicitSurface(mlp, (LO,) * 3, (HI,) * 3, **kw)


# -- the helper -----------------------------------------------------------------------

def test_on_points_matches_a_broadcasting_function():
    sextic = ji.surfaces.scene("barth_sextic").field
    x = jnp.linspace(-1.0, 1.0, 20).reshape(4, 5)
    y, z = jnp.float32(0.3), jnp.linspace(-0.5, 0.5, 5)
    direct = np.asarray(sextic(x, y, z, 0.0, ()))
    # equal up to float32 rounding: a field's f is compiled (once), and XLA may contract
    # a * b + c into an FMA differently for the two shapes
    np.testing.assert_allclose(np.asarray(on_points(sextic)(x, y, z, 0.0, ())), direct,
                               rtol=0, atol=4 * 2.0**-24 * np.abs(direct).max())
    grads = on_points(jax.grad(sextic, argnums=(0, 1, 2)))(x, y, z, 0.0, ())
    assert [g.shape for g in grads] == [(4, 5)] * 3


def test_scalar_function_is_evaluated_on_arrays_through_the_scene():
    P = np.random.default_rng(0).uniform(-1, 1, (7, 3)).astype(np.float32)
    val = _scene()(P[:, 0], P[:, 1], P[:, 2])
    np.testing.assert_allclose(np.asarray(val), _mlp64()(P.astype(np.float64)), atol=1e-5)


def test_one_number_per_point_is_required():
    def f(x, y, z):
        return jnp.stack([x, y, z]) @ _W["W1"][:, :1] - 0.5

    with pytest.raises(ValueError, match="per point"):  # measuring "auto" evaluates f
        ji.ImplicitSurface(f, (LO,) * 3, (HI,) * 3).prepared()
    scene = ji.ImplicitSurface(f, (LO,) * 3, (HI,) * 3, arithmetic="interval")
    for method in ("t-bisection", "sampling"):  # through `extend`, through `on_points`
        with pytest.raises(ValueError, match="per point"):
            ji.intersect(scene.replace(method=method), CAM.rays())
    with pytest.raises(ValueError, match="one number per point, got shape \\(1,\\)"):
        scene(jnp.zeros(4), 0.0, 0.0)


# -- (a) closure weights: hits against the float64 reference ---------------------------

@pytest.mark.parametrize("method, arithmetic", [
    ("t-bisection", "interval"), ("t-bisection", "affine"), ("mitchell", "interval"),
    ("mitchell", "affine"), ("sampling", "interval")])
def test_mlp_hits_match_the_float64_reference(reference, method, arithmetic):
    scene = _scene(method=method, arithmetic=arithmetic)
    eps = float(scene.eps)
    hits = ji.intersect(scene, CAM.rays())
    hit = np.asarray(hits.hit).ravel()
    t = np.asarray(hits.t).ravel()
    ref_hit = np.isfinite(reference)
    assert ref_hit.sum() > 50
    assert np.mean(hit == ref_hit) >= 0.99
    both = hit & ref_hit
    err = t[both] - reference[both]  # the camera's directions are unit vectors
    # never past the first root; early by at most the enclosure's slack: interval
    # t-bisection accepts the first eps-piece whose (loose, ~9 eps here: 16 ReLU units on
    # independent x, y, z intervals) enclosure holds 0; the others bracket a sign change
    assert err.max() <= eps
    assert -err.max() <= (16 if (method, arithmetic) == ("t-bisection", "interval") else 2) * eps
    assert np.abs(err).min() <= eps
    normal = np.asarray(hits.normal).reshape(-1, 3)[hit]
    assert np.all(np.isfinite(normal))
    np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-5)


@pytest.mark.parametrize("method", ["k-bisection", "sphere"])
def test_mlp_other_methods_run(reference, method):
    # sum(W2) bounds |grad f| (unit n_i): a valid Lipschitz constant, so no overshoot
    scene = _scene(method=method, arithmetic="affine",
                   lipschitz=float(WEIGHTS["W2"].sum()) if method == "sphere" else None)
    hits = ji.intersect(scene, CAM.rays())
    hit = np.asarray(hits.hit).ravel()
    t = np.asarray(hits.t).ravel()
    assert np.mean(hit == np.isfinite(reference)) >= 0.99
    both = hit & np.isfinite(reference)
    assert np.all(t[both] <= reference[both] + float(scene.eps))
    assert np.all(np.isfinite(np.asarray(hits.normal)))


def test_mlp_normals_and_render():
    scene = _scene(arithmetic="affine")
    rays = CAM.rays()
    grad = ji.intersect(scene, rays)
    central = ji.intersect(scene.replace(normals=1e-3), rays)
    hit = np.asarray(grad.hit)
    assert hit.sum() > 50
    ng, nc = np.asarray(grad.normal)[hit], np.asarray(central.normal)[hit]
    assert np.all(np.isfinite(nc))
    # piecewise linear: the stencil agrees off the creases between linear pieces
    assert np.mean(np.sum(ng * nc, axis=-1) > 0.999) >= 0.9
    for shading in (None, ji.Shading(shadows=True)):
        img = np.asarray(ji.render(scene, CAM, shading=shading))
        assert img.shape == (SIZE, SIZE, 3)
        assert np.all(np.isfinite(img)) and img.min() >= 0 and img.max() <= 1
        assert np.all(img[~hit] == 1.0)  # the white background
        assert np.all(np.any(img[hit] < 1.0, axis=-1))


def test_csg_of_scalar_functions():
    """The solid minus a ball, both written for scalars only; the part choice and
    the normals evaluate them through `on_points`."""
    def ball(x, y, z):
        p = jnp.stack([x, y, z]) - jnp.array([0.8, 0.5, 0.4])
        return jnp.sum(p * p) - 0.5**2  # (jnp.dot(p, p): no box-by-box dot rule)

    scene = ji.CSG(csg.difference(mlp, ball), (LO,) * 3, (HI,) * 3, arithmetic="affine")
    hits = ji.intersect(scene, CAM.rays())
    hit = np.asarray(hits.hit).ravel()
    f_solid = _mlp64()

    def f64(P):
        q = P - np.array([0.8, 0.5, 0.4])
        return np.maximum(f_solid(P), -(np.sum(q * q, -1) - 0.25))

    ref = _reference(f64, CAM.rays())
    assert np.mean(hit == np.isfinite(ref)) >= 0.99
    both = hit & np.isfinite(ref)
    t = np.asarray(hits.t).ravel()
    assert np.max(np.abs(t[both] - ref[both])) <= 2 * float(scene.eps)
    part = np.asarray(hits.surface).ravel()[hit]
    assert set(part) == {0, 1}
    assert np.all(np.isfinite(np.asarray(hits.normal)))


# -- (b) weights as params: derivatives by the implicit function theorem ---------------

def test_mlp_params_depth_gradient_matches_finite_differences():
    rays = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 50.0, 16, 16).rays()
    params = dict(_W)
    scene = ji.ImplicitSurface(mlp_params, (LO,) * 3, (HI,) * 3, params=params,
                               arithmetic="affine")
    mask = ji.intersect(scene, rays).hit
    assert int(mask.sum()) > 20

    def loss(params):
        hits = ji.intersect(scene.replace(params=params), rays)
        return jnp.sum(jnp.where(mask, hits.t, 0.0))

    grad = jax.grad(loss)(params)
    for k, g in grad.items():
        assert np.all(np.isfinite(np.asarray(g))), k
    m = np.asarray(mask).ravel()

    def loss64(key, index, delta):
        w = {k: np.array(v, np.float64) for k, v in WEIGHTS.items()}
        w[key][index] += delta
        t = _reference(_mlp64(w), rays)[m]
        assert np.all(np.isfinite(t))
        return t.sum()

    h = 1e-3
    for key, index, rtol in (("W1", (1, 5), 1e-2), ("W1", (0, 2), 1e-2), ("b2", (0,), 2e-2)):
        fd = (loss64(key, index, h) - loss64(key, index, -h)) / (2 * h)
        np.testing.assert_allclose(float(grad[key][index]), fd, rtol=rtol, err_msg=key)


# -- (c) a network built with equinox --------------------------------------------------

def test_equinox_mlp_intersect_and_render():
    eqx = pytest.importorskip("equinox")
    model = eqx.nn.MLP(3, "scalar", 16, 2, key=jax.random.PRNGKey(0))  # ReLU hidden layers
    weights, static = eqx.partition(model, eqx.is_array)

    def f(x, y, z, params):  # a ball of radius 0.8 bent by the network
        net = eqx.combine(params, static)
        return jnp.sqrt(x * x + y * y + z * z) - 0.8 + 0.2 * net(jnp.stack([x, y, z]))

    cam = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 40.0, 16, 16)
    rays = cam.rays()
    scene = ji.ImplicitSurface(f, (LO,) * 3, (HI,) * 3, params=weights, arithmetic="affine")
    hits = ji.intersect(scene, rays)

    net64 = _net64([(np.asarray(layer.weight).T, np.asarray(layer.bias))
                    for layer in model.layers])
    ref = _reference(lambda P: np.linalg.norm(P, axis=-1) - 0.8 + 0.2 * net64(P), rays)
    hit = np.asarray(hits.hit).ravel()
    assert np.isfinite(ref).sum() > 20
    assert np.mean(hit == np.isfinite(ref)) >= 0.99
    both = hit & np.isfinite(ref)
    assert np.max(np.abs(np.asarray(hits.t).ravel()[both] - ref[both])) <= 2 * float(scene.eps)
    assert np.all(np.isfinite(np.asarray(hits.normal)))

    # the model itself as a closure constant, interval arithmetic
    closure = ji.ImplicitSurface(
        lambda x, y, z: f(x, y, z, weights), (LO,) * 3, (HI,) * 3)
    np.testing.assert_array_equal(np.asarray(ji.intersect(closure, rays).hit),
                                  np.asarray(hits.hit))

    img = np.asarray(ji.render(scene, cam))
    assert np.all(np.isfinite(img)) and np.any(img < 1.0)


# -- a real network: the fox of neural-implicit-queries -------------------------------

def _npz_network(path):
    """The network of a data/neural .npz file as a scalar jnp function (format: its
    README): "NNNN.dense.A"/"b", "NNNN.relu._", "NNNN.elu._", "NNNN.squeeze_last._"."""
    data = np.load(path)
    ops = []
    for key in sorted(data.files):
        _, kind, part = key.split(".")
        if kind == "dense" and part == "A":
            ops.append((jnp.asarray(data[key]), jnp.asarray(data[key[:-1] + "b"])))
        elif kind in ("relu", "elu", "squeeze_last"):
            ops.append(kind)
        elif kind != "dense":
            raise ValueError(f"unknown layer {key}")

    def f(x, y, z):
        h = jnp.stack([x, y, z])
        for op in ops:
            if op == "relu":
                h = jax.nn.relu(h)
            elif op == "elu":
                h = jax.nn.elu(h)
            elif op == "squeeze_last":
                h = h[0]
            else:
                h = h @ op[0] + op[1]
        return h
    return f


@pytest.mark.skipif(not (NEURAL / "fox.npz").exists(),
                    reason=f"{NEURAL / 'fox.npz'} is absent (a shared data file)")
def test_fox_network_intersects():
    """Runs and gives finite hits; whether they are right is another issue's subject."""
    fox = _npz_network(NEURAL / "fox.npz")
    scene = ji.ImplicitSurface(fox, (-1.0,) * 3, (1.0,) * 3, arithmetic="affine",
                               eps=2.0**-7)
    cam = ji.Camera.look_at((2.5, 1.5, 1.0), (0, 0, 0), (0, 0, 1), 45.0, 16, 16)
    hits = ji.intersect(scene, cam.rays())
    hit = np.asarray(hits.hit)
    assert hit.any()
    assert np.all(np.isfinite(np.asarray(hits.t)[hit]))
    assert np.all(np.isfinite(np.asarray(hits.normal)))
