"""Persistent lanes with refill: iterative per-ray work (bisection, hierarchy traversal)
over a whole image as one queue.

A batched `while_loop` over a packet runs until its slowest ray is done, so lanes idle
behind it. Here a lane whose ray finishes writes its result and takes the next ray from
the queue, so every iteration does `width` useful steps while the queue lasts. When the
queue runs dry and few lanes are still busy, their rays move, with their state, to a
narrower loop (width / 8, down to `min_width`), so the slow tail does not pay for idle
lanes. Each phase compiles the step again, so by default there are two (width, width /
8): on the 2-core CPU a third and fourth phase (down to 32 lanes) made the first call of
implicits, volumes and tet meshes 1.6-2x longer and the frames no faster
(benchmarks/NOTES.md, session 20). Lanes step `refill_every` times between refills:
refilling costs a gather and a scatter per state array, and a lane that finishes early
idles until the next refill (measured for the implicits in benchmarks/NOTES.md: 4 was
best). An optional `settle` runs after each such stretch, on the lanes' states
together: work that only some lanes need now and then (checking a bisection's hit) is
gathered there instead of being done by every lane at every step.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["run_rays", "run_lanes", "phase_widths", "stable_partition"]


def phase_widths(lanes: int, n: int, min_width: int | None = None) -> list[int]:
    """Lane counts of the successive phases for a queue of n rays: lanes, lanes / 8, ...
    down to min_width (None: lanes / 8, two phases; never more lanes than rays)."""
    if min_width is None:
        min_width = max(1, int(lanes) // 8)
    widths = [max(1, min(int(lanes), n))]
    while widths[-1] > min_width:
        widths.append(max(min_width, widths[-1] // 8))
    return widths


def stable_partition(first):
    """The stable order that puts the entries where `first` [n] bool is true before the
    others (``argsort(~first, stable=True)``), int32 [n], by counting in O(n): XLA's
    comparison sort took 25 ms for 65,536 rays on the 2-core CPU (a fifth of a Barth
    sextic frame at 256^2), this 1.2 ms."""
    n = first.shape[0]
    f = first.astype(jnp.int32)
    before = jnp.cumsum(f) - f  # true entries before each entry
    index = jnp.arange(n, dtype=jnp.int32)
    position = jnp.where(first, before, jnp.sum(f) + index - before)
    return jnp.zeros(n, jnp.int32).at[position].set(index, unique_indices=True)


def _select(mask, new, old):
    """Per-lane where over two state pytrees ([L, ...] leaves)."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(mask.reshape((-1,) + (1,) * (b.ndim - 1)), a, b), new, old)


def run_rays(step, busy, state, results, *, max_steps: int, steps: str, lanes=None,
             settle=None, min_width: int | None = None):
    """Iterate per-ray `state` (leaves [P, ...]) until no ray is busy.

    step: state -> state (rays not busy must come back unchanged); busy: state -> [P]
    bool; results: the state keys to return; steps: the key of the per-ray iteration
    counter, which bounds each ray at `max_steps`. lanes None: one `while_loop` over the
    packet (until its slowest ray is done); an int: persistent lanes with refill. Both
    give the same per-ray results. settle, min_width (lanes only): see `run_lanes`.
    Returns {key: [P, ...]} for `results`.
    """
    if lanes is None:
        def cond(c):
            it, s = c
            return jnp.any(busy(s)) & (it < max_steps)

        _, out = lax.while_loop(cond, lambda c: (c[0] + 1, step(c[1])), (jnp.int32(0), state))
        return {k: out[k] for k in results}
    going = busy(state)
    order = stable_partition(going)
    queue = jax.tree_util.tree_map(lambda a: a[order], state)
    queue["idx"] = order.astype(jnp.int32)
    # a last, retired row (its step count spent): lanes that find the queue empty load it,
    # so an idle lane never looks busy to a step that reads the other lanes' states
    retired = jax.tree_util.tree_map(lambda a: a[-1:], queue)
    retired[steps] = jnp.full_like(retired[steps], max_steps)
    queue = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), queue, retired)

    def write(res, s, target):
        return {k: res[k].at[target].set(s[k], mode="drop") for k in results}

    return run_lanes(step, lambda s: ~busy(s) | (s[steps] >= max_steps), queue,
                     jnp.sum(going).astype(jnp.int32), {k: state[k] for k in results}, write,
                     lanes=min(int(lanes), going.shape[0]), settle=settle, min_width=min_width)


def run_lanes(step, done, queue, n_queue, results, write, *, lanes: int,
              refill_every: int = 4, min_width: int | None = None, settle=None):
    """Run the rays of `queue` to completion on persistent lanes.

    Args:
      step: state -> state, one iteration of every lane (leaves [L, ...]); lanes that are
        done or empty keep their old state whatever step returns.
      done: state -> [L] bool, the lane's ray is finished (it must turn true within a
        bounded number of steps: step counters belong in the state).
      queue: pytree of per-ray start states, leaves [Q, ...]; the first `n_queue` (traced
        int32) entries are the rays to run, in order.
      n_queue: [] int32.
      results: pytree of outputs, leaves [N, ...].
      write: (results, state, target) -> results, where target [L] int32 is the output row
        of each finished lane and N elsewhere (scatter with mode="drop").
      lanes: static width of the first phase; min_width: of the last (each phase compiles
        `step` and `settle` again; None: lanes / 8, two phases).
      settle: None or ``(state, live) -> state``, run on all lanes ([L, ...] leaves; live
        [L] bool: the lane holds a queued ray) after every `refill_every` steps, before
        finished lanes are written.

    Returns:
      results after every queued ray was written.
    """
    q_len = jax.tree_util.tree_leaves(queue)[0].shape[0]
    n_out = jax.tree_util.tree_leaves(results)[0].shape[0]
    widths = phase_widths(lanes, q_len, min_width)
    for i, width in enumerate(widths):
        stop_busy = widths[i + 1] if i + 1 < len(widths) else 0
        results, queue, n_queue = _phase(step, done, queue, n_queue, results, write, n_out,
                                         width, stop_busy, refill_every, settle)
    return results


def _phase(step, done, queue, n_queue, results, write, n_out, width, stop_busy,
           refill_every, settle):
    """Run queued rays on `width` lanes until the queue is empty and at most `stop_busy`
    lanes are busy; return (results, the busy lanes' states as a queue, their count)."""
    q_len = jax.tree_util.tree_leaves(queue)[0].shape[0]

    def load(slot):
        """(live [L], states [L, ...]) of queue slots [L] (slots past the queue: not live)."""
        j = jnp.minimum(slot, q_len - 1)
        return slot < n_queue, jax.tree_util.tree_map(lambda a: a[j], queue)

    def one(_, lane):
        live, state = lane
        busy = live & ~done(state)
        return live, _select(busy, step(state), state)

    def cond(carry):
        nxt, (live, state), _ = carry
        busy = live & ~done(state)
        return (nxt < n_queue) | (jnp.sum(busy) > stop_busy)

    def body(carry):
        nxt, lane, results = carry
        live, state = lax.fori_loop(0, refill_every, one, lane)
        if settle is not None:
            state = settle(state, live)
        finished = live & done(state)
        results = write(results, state, jnp.where(finished, state["idx"], n_out))
        fresh_live, fresh = load(nxt + jnp.cumsum(finished.astype(jnp.int32)) - 1)
        live = jnp.where(finished, fresh_live, live)
        state = _select(finished, fresh, state)
        return nxt + jnp.sum(finished).astype(jnp.int32), (live, state), results

    carry = (jnp.int32(width), load(jnp.arange(width, dtype=jnp.int32)), results)
    _, (live, state), results = lax.while_loop(cond, body, carry)
    busy = live & ~done(state)
    order = stable_partition(busy)
    rest = jax.tree_util.tree_map(lambda a: a[order], state)
    return results, rest, jnp.sum(busy).astype(jnp.int32)
