"""Builds notebooks/04_neural_implicits.ipynb; run as a script (python notebooks/make_04.py),
it also executes the notebook and stores it with its outputs (every notebook:
python notebooks/_nbtools.py --all). tests/test_notebooks.py checks that the stored
copy is not stale and executes it small (JAXISO_NB_SIZE=24).
It needs optax (the `test` and `notebooks` extras).
"""

from _nbtools import ROW, TIMED, Notebook, heat, helpers, regenerate, setup

NOTEBOOK = Notebook("04_neural_implicits.ipynb")
md, code = NOTEBOOK.md, NOTEBOOK.code


md("""
# Neural implicits

A neural implicit is a small network `f(x, y, z)` whose zero set is a surface. To
`jaxiso` it is one more plain-JAX point function: `ji.ImplicitSurface` traces it with
interval or affine arithmetic like any other implicit, and its weights are a traced
field of the scene (`params`), so changing them never recompiles and `jax.grad` reaches
them through the hits.

1. fit a small ReLU network to a catalogue surface with optax, and render it,
2. load a network in the "Spelunking the Deep" `.npz` layout (Sharp & Jacobson 2022),
3. interval vs affine arithmetic on networks: time, hits and enclosure widths,
4. gradients of a depth image with respect to the weights, and one optimiser step.

The image size comes from `JAXISO_NB_SIZE` (default 64; the test suite runs this
notebook at 24). Training is 800 small steps (seconds): the point is the workflow, not
a faithful fit (`examples/fit_neural_sdf.py` trains longer).
""")

code(setup("""
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxiso as ji
""", "64"))

code(helpers(ROW, heat("value"), TIMED))

# ---------------------------------------------------------------------------------------
md("""
## 1. A network is a point function

The network takes one point and returns one number: `h = (x, y, z)`, then
`h = h @ A + b` per layer with a ReLU between layers. The weights are a list of
`{"A": [in, out], "b": [out]}`, the layout `ji.implicit.load_mlp` returns, passed as the
last argument `params`. jaxiso vmaps the function itself; the training loss below vmaps
it too.
""")

code('''
def mlp(x, y, z, params):
    """A ReLU network at one point: 3 inputs, one output."""
    h = jnp.stack([x, y, z])
    for i, layer in enumerate(params):
        if i:
            h = jax.nn.relu(h)
        h = h @ layer["A"] + layer["b"]
    return h[0]


def init_params(key, widths=(3, 32, 32, 32, 1)):
    """He-initialised weights [{"A": [in, out], "b": [out]}, ...]."""
    params = []
    for n_in, n_out in zip(widths[:-1], widths[1:]):
        key, sub = jax.random.split(key)
        params.append({"A": jax.random.normal(sub, (n_in, n_out)) * np.sqrt(2.0 / n_in),
                       "b": jnp.zeros(n_out)})
    return params


net = jax.vmap(mlp, (0, 0, 0, None))  # points [N] each -> values [N]
''')

md("""
The target is the tangle cube of the catalogue. Its `f` is a quartic, far from a
distance; `f / |grad f|` (the first-order distance to the surface), clipped to
`[-0.5, 0.5]`, is a field a small ReLU network can follow. Half of every batch is drawn
uniformly in the surface's box, half near the surface.
""")

code('''
tangle = ji.surfaces.get("tangle")
lo, hi = jnp.asarray(tangle.lo), jnp.asarray(tangle.hi)


def distance(p):
    """Clipped first-order distance to the tangle cube at a point p [3]."""
    value, grad = jax.value_and_grad(lambda q: tangle.f(q[0], q[1], q[2], tangle.w))(p)
    return jnp.clip(value / (jnp.linalg.norm(grad) + 1e-6), -0.5, 0.5)


distance = jax.vmap(distance)
pool = jax.random.uniform(jax.random.PRNGKey(1), (100_000, 3), minval=lo, maxval=hi)
pool = pool[np.asarray(jnp.abs(distance(pool)) < 0.05)]  # points near the surface
held_out = jax.random.uniform(jax.random.PRNGKey(2), (4096, 3), minval=lo, maxval=hi)


def batch(key, n=2048):
    k_u, k_i, k_n = jax.random.split(key, 3)
    near = (pool[jax.random.randint(k_i, (n // 2,), 0, len(pool))]
            + 0.06 * jax.random.normal(k_n, (n // 2, 3)))
    return jnp.concatenate([jax.random.uniform(k_u, (n // 2, 3), minval=lo, maxval=hi),
                            near])


def fit_loss(params, p):
    return jnp.mean(jnp.abs(net(p[:, 0], p[:, 1], p[:, 2], params) - distance(p)))


print(f"{len(pool)} sample points near the surface")
''')

code('''
STEPS = 800
SNAPSHOTS = (100, 300, 800)  # steps after which the weights are kept
optimizer = optax.adam(optax.cosine_decay_schedule(3e-3, STEPS, alpha=0.05))


@jax.jit
def train_step(params, opt_state, key):
    loss, grads = jax.value_and_grad(fit_loss)(params, batch(key))
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss


params = init_params(jax.random.PRNGKey(0))
opt_state = optimizer.init(params)
snapshots = {}
start = time.perf_counter()
print(f"held-out error before training {float(fit_loss(params, held_out)):.4f}")
for i, key in enumerate(jax.random.split(jax.random.PRNGKey(3), STEPS)):
    params, opt_state, loss = train_step(params, opt_state, key)
    if i + 1 in SNAPSHOTS:
        snapshots[i + 1] = params
        print(f"step {i + 1}: batch loss {float(loss):.4f}, held-out error "
              f"{float(fit_loss(params, held_out)):.4f}")
print(f"{STEPS} steps in {time.perf_counter() - start:.1f} s")
''')

md("""
The trained weights go into the scene as `params`. From left: the catalogue's tangle
cube, the network. The network's surface is faceted: a ReLU network is piecewise
linear.
""")

code("""
cam = ji.surfaces.camera("tangle", SIZE)
scene = ji.ImplicitSurface(mlp, tangle.lo, tangle.hi, params=params)
fitted, dt = timed(ji.render, scene, cam)
print(f"network render: {dt:.1f} s (compiles)")
row(ji.render(ji.surfaces.scene("tangle"), cam), fitted)
""")

md("""
The weights are a traced field: the networks saved after 100, 300 and 800 steps render
with the program compiled above (`scene.replace(params=...)`).
""")

code("""
panels = []
for step, weights in snapshots.items():
    img, dt = timed(ji.render, scene.replace(params=weights), cam)
    panels.append(img)
    print(f"after {step} steps: {dt:.2f} s")
row(*panels)
""")

# ---------------------------------------------------------------------------------------
md("""
## 2. A shared network: the fox

`ji.implicit.load_mlp(path)` reads the `.npz` layout of the sample networks of
"Spelunking the Deep" (keys `NNNN.dense.A`, `NNNN.dense.b`, `NNNN.relu._`, ...,
`NNNN.squeeze_last._`) into an `MLP`: a point function `f(x, y, z, params)` with the
weights in `.params`, the same layout as above. The fox (8 ReLU layers of 32) is a shared
data file; the cell says so and draws nothing when it is absent (set
`JAXISO_NEURAL_DATA` to the folder that holds `fox.npz`).

Both arithmetics are shown: interval arithmetic loses every correlation between the 32
neurons of a layer, so on a deep network its enclosures can stay wide down to the last
level of bisection, where a piece of length `eps` is accepted as a hit; affine
arithmetic keeps the linear part of each layer exact.
""")

code("""
fox_path = pathlib.Path(os.environ.get("JAXISO_NEURAL_DATA", "/work/shared/data/neural"))
fox_path = fox_path / "fox.npz"
if fox_path.exists():
    fox = ji.implicit.load_mlp(fox_path)
    print(f"{fox_path.name}: {fox.activation}, layers "
          + " -> ".join(str(p["A"].shape[0]) for p in fox.params) + " -> 1")
    fox_scene = ji.ImplicitSurface(fox, (-1.0,) * 3, (1.0,) * 3, params=fox.params,
                                   eps=2.0**-8)
    fox_cam = ji.Camera.look_at(eye=(2.0, 1.2, 0.8), target=(0.0, -0.1, -0.05),
                                up=(0, 0, 1), fov=32, width=SIZE, height=SIZE)
    fox_panels = []
    for arithmetic in ("interval", "affine"):
        img, dt = timed(ji.render, fox_scene.replace(arithmetic=arithmetic), fox_cam)
        fox_panels.append(img)
        covered = np.any(np.asarray(img) < 0.999, axis=-1).mean()
        print(f"{arithmetic:8s}: {dt:.1f} s (compiles), {covered:.0%} of pixels drawn")
    display(row(*fox_panels))
else:
    print(f"{fox_path} is absent: skipping the fox (a shared data file; the other "
          "cells do not need it)")
""")

# ---------------------------------------------------------------------------------------
md("""
## 3. Interval vs affine on the fitted network

The same rays, traced in both arithmetics (`ji.intersect`, jitted; the second call is
timed). `hits.steps` counts the enclosure evaluations of each ray: the work.
""")

code("""
trace = jax.jit(lambda scene, rays: ji.intersect(scene, rays))
rays = cam.rays()
traced = {}
for arithmetic in ("interval", "affine"):
    s = scene.replace(arithmetic=arithmetic)
    _, t_first = timed(trace, s, rays)
    traced[arithmetic], t_run = timed(trace, s, rays)
    steps = np.asarray(traced[arithmetic].steps)
    print(f"{arithmetic:8s}: {int(traced[arithmetic].hit.sum())} hits of {steps.size} "
          f"rays, mean steps {steps.mean():6.1f}, {t_run * 1e3:6.1f} ms "
          f"(first call {t_first:.1f} s)")
vmax = np.log2(np.percentile(np.asarray(traced["interval"].steps), 99))
row(*(heat(np.log2(np.maximum(np.asarray(h.steps), 1)), vmax) for h in traced.values()))
""")

md("""
Steps per pixel, interval then affine, on one logarithmic scale (white = one step, dark
red = interval's 99th percentile). Why so different: the enclosure of `f` on a piece of
a ray. `ji.extend(f, arithmetic)` is the inclusion extension the tracer uses; here it
runs on pieces `[t - h, t + h]` around hits with, as in the tracer, the ray parameter as
one `Interval` (IA) or one noise symbol (affine: `ji.aa.from_interval(T, symbol=0)`).
The table gives the median of enclosure width / true range (the range from 257 samples
along the piece) over the hit rays. Interval's ratio stays roughly constant as pieces
shrink (the product of the layers' weight magnitudes); affine's falls towards 1 once the
pieces are short enough that few neurons switch inside them.
""")

code('''
hit = np.asarray(traced["affine"].hit).ravel()
flat = rays.reshape((rays.shape[0] * rays.shape[1],))
o, d = flat.origin[hit][:64], flat.direction[hit][:64]
t_hit = traced["affine"].t.ravel()[hit][:64]
extended = {a: jax.jit(ji.extend(mlp, a)) for a in ("interval", "affine")}


def width_ratio(h):
    """Median enclosure width / sampled range of f on [t - h, t + h], per arithmetic."""
    T = ji.Interval(t_hit - h, t_hit + h)
    pieces = {"interval": T, "affine": ji.aa.from_interval(T, symbol=0, n=1)}
    s = t_hit[:, None] + jnp.linspace(-h, h, 257)[None]
    p = o[:, None] + s[..., None] * d[:, None]
    v = net(p[..., 0].ravel(), p[..., 1].ravel(), p[..., 2].ravel(), params)
    v = v.reshape(s.shape)
    true = np.asarray(v.max(1) - v.min(1))
    out = {}
    for a, t in pieces.items():
        enc = extended[a](*(o[:, k] + d[:, k] * t for k in range(3)), params=params)
        enc = ji.aa.to_interval(enc) if a == "affine" else enc
        out[a] = float(np.median(np.asarray(enc.hi - enc.lo) / true))
    return out


print("half-length h   interval   affine   (enclosure width / true range, median)")
for k in (2, 4, 6, 8, 10):
    r = width_ratio(2.0**-k)
    print(f"2^-{k:<2d}          {r['interval']:8.1f}   {r['affine']:6.2f}")
''')

# ---------------------------------------------------------------------------------------
md("""
## 4. Gradients of a depth image with respect to the weights

`ji.intersect` attaches the implicit function theorem to the hit parameter `t`: on
`f(o + t d, params) = 0`, `dt/dparams = -(df/dparams) / (grad f . d)`. The bisection
loops are never differentiated, so `jax.grad` of any loss on `hits.t` reaches the
weights at the cost of one extra evaluation of `f` per hit.

The target is the depth image of the same network scaled by 1.1 (`f(p / 1.1)`: the first
layer's `A / 1.1`). The loss is the mean squared depth difference over pixels both
images see well (facing the camera, on the same sheet: depths within 0.5); the pixel
weights are constants (`stop_gradient`), since pixels appearing and vanishing have no
gradient.
""")

code('''
target_params = [dict(params[0], A=params[0]["A"] / 1.1)] + params[1:]
target_hits = trace(scene.replace(params=target_params), rays)
target_t = jnp.where(target_hits.hit, target_hits.t, 0.0)
unit = rays.direction / jnp.linalg.norm(rays.direction, axis=-1, keepdims=True)


def facing(hits):
    """1 where the hit surface faces the ray (cosine >= 0.4), 0 for misses."""
    cos = -jnp.sum(hits.normal * unit, axis=-1)
    return jnp.where(hits.hit, jnp.clip((cos - 0.1) / 0.3, 0.0, 1.0), 0.0)


def image_loss(params):
    """(mean squared depth error over the weighted pixels, (pixel count, depth error))."""
    hits = ji.intersect(scene.replace(params=params), rays)
    error = jnp.where(hits.hit, hits.t, 0.0) - target_t
    w = facing(hits) * facing(target_hits) * (jnp.abs(error) < 0.5)
    w = jax.lax.stop_gradient(w)
    loss = jnp.sum(w * error**2) / jnp.maximum(jnp.sum(w), 1.0)
    return loss, (jnp.sum(w > 0), jnp.where(w > 0, jnp.abs(error), 0.0))


loss_and_grad = jax.jit(jax.value_and_grad(image_loss, has_aux=True))
(loss_before, (pixels_before, error_before)), grads = loss_and_grad(params)
for i, g in enumerate(grads):
    print(f"layer {i}: |d loss / dA| = {float(jnp.linalg.norm(g['A'])):.3g}, "
          f"|d loss / db| = {float(jnp.linalg.norm(g['b'])):.3g}")
''')

md("""
One Adam step with these gradients (Adam's first step moves every weight by about the
learning rate), then the loss again, on the pixels the new network and the target both
see well.
""")

code("""
step_optimizer = optax.adam(1e-4)
updates, _ = step_optimizer.update(grads, step_optimizer.init(params), params)
stepped = optax.apply_updates(params, updates)
(loss_after, (pixels_after, error_after)), _ = loss_and_grad(stepped)
print(f"image loss {float(loss_before):.5f} on {int(pixels_before)} pixels -> "
      f"{float(loss_after):.5f} on {int(pixels_after)} pixels")
assert float(loss_after) < float(loss_before), "the step did not lower the image loss"
assert int(pixels_after) > int(pixels_before) // 2, "the step lost the pixels"
""")

md("""
From left: the network's depth, the target's depth (red = near), and the depth error
before and after the step on the same scale (white = none, also where a pixel does not
count).
""")

code('''
current = trace(scene, rays)
depth = np.where(np.asarray(current.hit), np.asarray(current.t), np.nan)
near, far = np.nanmin(depth), np.nanmax(depth)


def nearness(hits):
    """0 (far or missed) to 1 (nearest)."""
    t = np.where(np.asarray(hits.hit), np.asarray(hits.t), far)
    return np.clip((far - t) / (far - near + 1e-9), 0.0, 1.0)


vmax = float(np.percentile(np.asarray(error_before)[np.asarray(error_before) > 0], 95))
row(heat(nearness(current), 1.0), heat(nearness(target_hits), 1.0),
    heat(np.asarray(error_before), vmax), heat(np.asarray(error_after), vmax))
''')

md("""
## Where next

* `examples/fit_neural_sdf.py` trains the network longer from the command line and
  saves its weights in the `.npz` layout `load_mlp` reads (`--save-npz`).
* Fitting the weights to images of a target (many steps of section 4) is inverse
  rendering of a neural implicit; `examples/fit_superquadric.py` does it for the two
  exponents of a superquadric.
* `ji.extend` runs on any plain-JAX function: the enclosures of section 3 are the same
  object the tracer bisects with.
""")

if __name__ == "__main__":
    regenerate(__file__)  # builds, executes and stores the notebook
