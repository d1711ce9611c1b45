"""Fit a small neural signed distance field to a catalogue surface, then ray trace it.

The network is a plain-JAX point function ``mlp(x, y, z, params)`` (3 -> 32 -> 32 -> 32
-> 1, relu or softplus) whose weights ``params`` are a list of ``{"A": [in, out],
"b": [out]}``, the layout `ji.implicit.load_mlp` returns. It is trained with optax's Adam
on a distance-like field of a catalogue surface (`ji.surfaces`): the first-order
distance ``f / |grad f|`` of the catalogue's ``f``, clipped to ``[-clip, clip]``, at
points drawn uniformly in the surface's box and near its surface. The trained network is
rendered with ``ji.render(ji.ImplicitSurface(mlp, lo, hi, params=weights), cam)``; the
weights are traced fields of the scene, so the renderer never sees them as constants.
`--save-npz` writes the weights in the "Spelunking the Deep" layout that
`ji.implicit.load_mlp` reads, and checks that they load back to the same network.

    python examples/fit_neural_sdf.py --steps 2000 --size 128 --out neural_tangle.png

Exits 0 when the held-out fit error fell, the image shows the surface and (with
`--save-npz`) the weights round-trip through `load_mlp`.
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxiso as ji

WIDTHS = (3, 32, 32, 32, 1)  # inputs, hidden layers, one output
ACTIVATIONS = ("relu", "softplus")

# jaxiso's own point-code MLP (h @ A + b, activation between layers), built once per
# activation: a scene's f is a static field compared by identity, so one function per
# activation keeps every render of that network on one compiled program
NETWORKS = {name: ji.implicit.MLP(name, []) for name in ACTIVATIONS}


def init_params(key, widths=WIDTHS) -> list:
    """He-initialised weights ``[{"A": [in, out], "b": [out]}, ...]`` (float32)."""
    params = []
    for n_in, n_out in zip(widths[:-1], widths[1:]):
        key, sub = jax.random.split(key)
        params.append({"A": jax.random.normal(sub, (n_in, n_out)) * np.sqrt(2.0 / n_in),
                       "b": jnp.zeros(n_out)})
    return params


def distance_target(name: str, clip: float):
    """``d(points [N, 3]) -> [N]``: the catalogue surface's f divided by |grad f| (its
    first-order distance to the surface, exact for a sphere written |p| - r), clipped to
    [-clip, clip] (far from the surface, and where grad f vanishes, it means nothing)."""
    entry = ji.surfaces.get(name)

    def d(p):
        value, grad = jax.value_and_grad(lambda q: entry.f(q[0], q[1], q[2], entry.w))(p)
        return jnp.clip(value / (jnp.linalg.norm(grad) + 1e-6), -clip, clip)

    return jax.jit(jax.vmap(d))


def save_npz(params, path, activation: str = "relu") -> str:
    """Write `params` in the layout `ji.implicit.load_mlp` reads: "NNNN.dense.A",
    "NNNN.dense.b", then "NNNN.<activation>._" between dense layers, and a final
    "NNNN.squeeze_last._", numbered in the order they apply. Returns the path."""
    arrays, k = {}, 0
    for i, layer in enumerate(params):
        if i:
            arrays[f"{k:04d}.{activation}._"] = np.zeros(0, np.float32)
            k += 1
        arrays[f"{k:04d}.dense.A"] = np.asarray(layer["A"], np.float32)
        arrays[f"{k:04d}.dense.b"] = np.asarray(layer["b"], np.float32)
        k += 1
    arrays[f"{k:04d}.squeeze_last._"] = np.zeros(0, np.float32)
    np.savez(path, **arrays)
    return str(path)


def roundtrip_error(params, path, activation: str, points) -> float:
    """Largest |difference| between this network and the one `load_mlp` reads from
    `path`, on `points` [N, 3] (weights and outputs; 0 when the file is faithful)."""
    loaded = ji.implicit.load_mlp(path)
    if loaded.activation != activation or len(loaded.params) != len(params):
        return float("inf")
    weights = max(float(jnp.max(jnp.abs(a[k] - b[k])))
                  for a, b in zip(params, loaded.params) for k in ("A", "b"))
    x, y, z = points.T
    ours = jax.vmap(NETWORKS[activation], (0, 0, 0, None))(x, y, z, params)
    theirs = jax.vmap(loaded, (0, 0, 0, None))(x, y, z, loaded.params)
    return max(weights, float(jnp.max(jnp.abs(ours - theirs))))


def run(argv=None) -> dict:
    """Parse `argv`, fit, render, print progress. Returns the held-out errors before and
    after training, the training losses, the number of hit pixels, the weights, the PNG
    path and (with --save-npz) the round-trip error."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surface", default="tangle", help="catalogue surface to fit")
    parser.add_argument("--steps", type=int, default=2000, help="Adam steps")
    parser.add_argument("--size", type=int, default=128, help="image edge in pixels")
    parser.add_argument("--out", default="fit_neural_sdf.png", help="PNG to write")
    parser.add_argument("--save-npz", default=None,
                        help="also write the weights here (load_mlp's .npz layout)")
    parser.add_argument("--activation", choices=sorted(ACTIVATIONS), default="relu")
    parser.add_argument("--lr", type=float, default=3e-3, help="peak Adam learning rate")
    parser.add_argument("--batch", type=int, default=2048, help="points per step")
    parser.add_argument("--clip", type=float, default=0.5, help="distance clip")
    parser.add_argument("--every", type=int, default=200, help="print every N steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    entry = ji.surfaces.get(args.surface)
    if entry.parts:
        parser.error(f"{args.surface} is a CSG entry; pick a single-function surface")

    start_time = time.perf_counter()
    lo, hi = jnp.asarray(entry.lo, jnp.float32), jnp.asarray(entry.hi, jnp.float32)
    target = distance_target(args.surface, args.clip)
    k_init, k_pool, k_test, k_steps = jax.random.split(jax.random.PRNGKey(args.seed), 4)

    def uniform(key, n):
        return jax.random.uniform(key, (n, 3), minval=lo, maxval=hi)

    # half of every batch lies near the surface: thin shapes hold little of the box's
    # volume, and a fit to uniform points alone can miss them altogether
    pool = uniform(k_pool, 200_000)
    pool = pool[np.asarray(jnp.abs(target(pool)) < 0.1 * args.clip)]
    jitter = 0.01 * float(jnp.max(hi - lo))
    test = jnp.concatenate([uniform(k_test, 4096), pool[:1024]])  # held out from training
    pool = pool[1024:]
    if pool.shape[0] < 256:
        parser.error(f"{args.surface}: too few sample points near the surface")
    test_target = target(test)

    mlp = NETWORKS[args.activation]
    net = jax.vmap(mlp, (0, 0, 0, None))

    def loss_fn(params, points):
        return jnp.mean(jnp.abs(net(*points.T, params) - target(points)))

    schedule = optax.cosine_decay_schedule(args.lr, max(args.steps, 1), alpha=0.05)
    opt = optax.adam(schedule)

    @jax.jit
    def step(params, opt_state, key):
        k_u, k_i, k_n = jax.random.split(key, 3)
        half = args.batch // 2
        near = (pool[jax.random.randint(k_i, (half,), 0, pool.shape[0])]
                + jitter * jax.random.normal(k_n, (half, 3)))
        points = jnp.concatenate([uniform(k_u, args.batch - half), near])
        loss, grads = jax.value_and_grad(loss_fn)(params, points)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    @jax.jit
    def fit_error(params):
        """Mean |net - target| on the held-out points and the fraction of them on the
        right side of the surface."""
        pred = net(*test.T, params)
        return (jnp.mean(jnp.abs(pred - test_target)),
                jnp.mean((pred < 0) == (test_target < 0)))

    params = init_params(k_init)
    opt_state = opt.init(params)
    err0, side0 = (float(v) for v in fit_error(params))
    print(f"{args.surface}: {pool.shape[0]} near-surface points; network "
          f"{' -> '.join(map(str, WIDTHS))} {args.activation}; held-out error {err0:.4f}",
          flush=True)
    losses = []
    for i, key in enumerate(jax.random.split(k_steps, args.steps)):
        params, opt_state, loss = step(params, opt_state, key)
        losses.append(float(loss))
        if (i + 1) % args.every == 0 or i + 1 == args.steps:
            err, _ = fit_error(params)
            print(f"step {i + 1:5d}  loss {np.mean(losses[-args.every:]):.4f}  "
                  f"held-out {float(err):.4f}", flush=True)
    err, side = (float(v) for v in fit_error(params))
    train_s = time.perf_counter() - start_time
    print(f"fit error: held-out mean |net - distance| {err0:.4f} -> {err:.4f} (clip "
          f"{args.clip}), right side {side0:.1%} -> {side:.1%}; {train_s:.1f} s", flush=True)

    result = {"error_before": err0, "error_after": err, "side": side, "losses": losses,
              "params": params, "out": args.out}
    if args.save_npz:
        path = save_npz(params, args.save_npz, args.activation)
        result["roundtrip"] = roundtrip_error(params, path, args.activation, test[:512])
        print(f"saved {path}; load_mlp round trip: max |difference| "
              f"{result['roundtrip']:.1e}", flush=True)

    scene = ji.ImplicitSurface(mlp, entry.lo, entry.hi, params=params)
    cam = ji.surfaces.camera(args.surface, args.size)
    render_time = time.perf_counter()
    img = ji.render(scene, cam)
    render_s = time.perf_counter() - render_time
    ji.save_png(img, args.out)
    result["hit_pixels"] = int(np.any(np.asarray(img) < 0.999, axis=-1).sum())
    print(f"rendered {args.size}x{args.size} in {render_s:.1f} s (compile included): "
          f"{result['hit_pixels']} pixels show the surface; wrote {args.out}", flush=True)
    result["ok"] = (err < err0 and result["hit_pixels"] > 0
                    and result.get("roundtrip", 0.0) <= 1e-6)
    return result


def main(argv=None) -> int:
    """Command line entry: exit status 0 when the fit improved, the render hit and the
    saved weights (if any) round-trip."""
    return 0 if run(argv)["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
