"""The stackless bisection kernels of `jaxiso.implicit._bisect`: the shared walk
`advance`, and t-bisection over a packet (`t_bisect` under vmap, the packet path) and on
persistent lanes (`t_bisect_lanes`), against a depth-first bisection with an explicit
stack per ray written here in numpy."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxiso import surfaces
from jaxiso.implicit import _bisect
from jaxiso.implicit._field import contains_any, enclosure, extended, ray_boxes, ray_segments

# ------------------------------------------------------------------------- reference


def stack_bisect(test, d_max, active, max_steps, d_start=0, verify=None):
    """Depth-first bisection of [0, 1] with an explicit stack per ray; all rays advance
    together so that `test` sees one batch per round. The stack starts with the pieces of
    depth min(d_start, d_max) in order.

    test(s0 [P], s1 [P]) -> (possible, finite, small), numpy bool [P] each. A ray tests
    the piece on top of its stack: it accepts it (possible, finite, and at depth d_max or
    small), splits it (possible, above d_max: first half on top), or drops it; it stops
    on an accepted piece, an empty stack or after max_steps tests. With `verify`
    (``verify(s0, s1) -> bool [P]``), an accepted piece where verify fails is dropped.
    Returns (s [P] float32, midpoint of the accepted piece or inf; hit [P]; steps [P]).
    """
    n = len(d_max)
    d0 = np.minimum(d_start, d_max)
    stacks = [[(k, d0[i]) for k in reversed(range(2 ** int(d0[i])))] if a else []
              for i, a in enumerate(np.asarray(active))]
    steps = np.zeros(n, np.int32)
    hit = np.zeros(n, bool)
    s = np.full(n, np.inf, np.float32)
    while True:
        live = [i for i in range(n) if stacks[i] and steps[i] < max_steps]
        if not live:
            return s, hit, steps
        k = np.zeros(n, np.int64)
        d = np.zeros(n, np.int64)
        for i in live:
            k[i], d[i] = stacks[i].pop()
        w = np.float32(2.0) ** -d.astype(np.float32)  # exact powers of two
        s0, s1 = k.astype(np.float32) * w, (k + 1).astype(np.float32) * w
        possible, finite, small = (np.asarray(a) for a in test(s0, s1)[:3])
        ok = np.ones(n, bool) if verify is None else np.asarray(verify(s0, s1))
        for i in live:
            steps[i] += 1
            if possible[i] and finite[i] and (d[i] >= d_max[i] or small[i]):
                if not ok[i]:
                    continue
                hit[i] = True
                s[i] = (np.float32(k[i]) + np.float32(0.5)) * w[i]
                stacks[i].clear()
            elif possible[i] and d[i] < d_max[i]:
                stacks[i] += [(2 * k[i] + 1, d[i] + 1), (2 * k[i], d[i] + 1)]


def _packet(test, d_max, active, max_steps, verify=None):
    """The packet path: `t_bisect` per ray under vmap (test(p, D, s0, s1) per ray)."""
    def one(p, D, d_max, active):
        check = None if verify is None else functools.partial(verify, p, D)
        return _bisect.t_bisect(functools.partial(test, p, D), d_max, active, max_steps,
                                check)
    return jax.vmap(one)


def _kernels(test, max_steps, lanes, paths=("packet", "lanes", "one_loop"), d_start=0,
             verify=None):
    """{path: jitted (p, D, d_max, active) -> Result}: the packet path, lanes, and
    `t_bisect_lanes` with lanes None (one loop over the batch); the last two start at
    depth `d_start` (the packet path at 0). verify: None or ``verify(p, D, s0, s1)``."""
    def packet(p, D, d_max, active):
        return _packet(test, d_max, active, max_steps, verify)(p, D, d_max, active)

    def on_lanes(p, D, d_max, active):
        return _bisect.t_bisect_lanes(test, p, D, d_max, active, lanes, max_steps, verify,
                                      d_start=d_start)

    def one_loop(p, D, d_max, active):
        return _bisect.t_bisect_lanes(test, p, D, d_max, active, None, max_steps, verify,
                                      d_start=d_start)

    kernels = {"packet": packet, "lanes": on_lanes, "one_loop": one_loop}
    return {path: jax.jit(kernels[path]) for path in paths}


def _assert_same(res, ref, path):
    s, hit, steps = ref
    np.testing.assert_array_equal(np.asarray(res.hit), hit, err_msg=path)
    np.testing.assert_array_equal(np.asarray(res.steps), steps, err_msg=path)
    np.testing.assert_array_equal(np.asarray(res.s), s, err_msg=path)


# ------------------------------------------------------------------------- advance


def _preorder(depth):
    """(k, d) of the full binary tree of pieces down to `depth`, depth first."""
    out = []

    def visit(k, d):
        out.append((k, d))
        if d < depth:
            visit(2 * k, d + 1)
            visit(2 * k + 1, d + 1)
    visit(0, 0)
    return out


@pytest.mark.parametrize("jit", [False, True])
def test_advance_walks_every_piece_depth_first(jit):
    depth = 4
    step = jax.jit(_bisect.advance) if jit else _bisect.advance
    k, d, finished, seen = jnp.int32(0), jnp.int32(0), False, []
    while not finished:
        seen.append((int(k), int(d)))
        k, d, finished = step(k, d, False, d < depth)
        assert len(seen) <= 2 ** (depth + 1)
    assert seen == _preorder(depth)


def test_advance_accept_stays_and_finishes_under_vmap():
    k = jnp.array([5, 5, 5, 7], jnp.int32)
    d = jnp.array([3, 3, 3, 3], jnp.int32)
    accept = jnp.array([True, False, False, False])
    descend = jnp.array([True, True, False, False])
    k2, d2, fin = jax.vmap(_bisect.advance)(k, d, accept, descend)
    # stay; first half; next piece 6 = 0b110 pops one level to (3, 2); 8 pops out of [0, 1]
    np.testing.assert_array_equal(np.asarray(k2), [5, 10, 3, 1])
    np.testing.assert_array_equal(np.asarray(d2), [3, 4, 2, 0])
    np.testing.assert_array_equal(np.asarray(fin), [True, False, False, True])


# ------------------------------------------------------------- t-bisection, exact oracle


def _oracle(p, D, s0, s1):
    """A box test with exact float32 arithmetic (the same bits in numpy and under any
    XLA fusion): p[..., 0] is a root position (nan: none), the enclosure is the piece
    widened by half its width on each side (so neighbours of a root are possible too,
    and the walk backtracks), it is unbounded on pieces that reach into [D[..., 0],
    D[..., 1]], and small where the piece is at most D[..., 2] long."""
    half = 0.5 * (s1 - s0)
    root = p[..., 0]
    possible = (root >= s0 - half) & (root <= s1 + half)
    finite = ~((s1 > D[..., 0]) & (s0 < D[..., 1]))
    return _bisect.BoxTest(possible, finite, (s1 - s0) <= D[..., 2])


def _oracle_rays(n=256, seed=0):
    rng = np.random.default_rng(seed)
    root = rng.uniform(0.0, 1.0, n).astype(np.float32)
    root[rng.random(n) < 0.2] = np.nan  # no root
    root[:4] = [0.0, 1.0, 0.5, 0.75]      # on piece boundaries and the segment's ends
    bad = np.full((n, 2), 2.0, np.float32)  # no asymptote
    pick = rng.random(n) < 0.25
    lo = rng.uniform(0.0, 1.0, n).astype(np.float32)
    bad[pick] = np.stack([lo, lo + 0.1], -1)[pick]
    small = np.where(rng.random(n) < 0.2, 2.0 ** -rng.integers(3, 12, n), 0.0)
    p = np.stack([root, np.zeros(n), np.zeros(n)], -1).astype(np.float32)
    D = np.concatenate([bad, small[:, None]], -1).astype(np.float32)
    d_max = rng.integers(0, _bisect.MAX_DEPTH + 1, n).astype(np.int32)
    d_max[4:8] = _bisect.MAX_DEPTH  # float32(k) rounds past depth 24
    active = rng.random(n) < 0.9
    return p, D, d_max, active


@pytest.mark.parametrize("max_steps", [8, 64, 256 * _bisect.MAX_DEPTH])
def test_t_bisection_matches_stack_reference_exact_oracle(max_steps):
    p, D, d_max, active = _oracle_rays()
    ref = stack_bisect(lambda s0, s1: _oracle(p, D, s0, s1), d_max, active, max_steps)
    assert ref[1].sum() > 10 and (~ref[1]).sum() > 10
    assert ((ref[2] >= max_steps).sum() > 0) == (max_steps < 256)  # some run out
    for path, run in _kernels(_oracle, max_steps, lanes=32).items():
        _assert_same(run(p, D, d_max, active), ref, path)
    # eagerly (packet path)
    _assert_same(_packet(_oracle, d_max, active, max_steps)(p, D, d_max, active), ref,
                 "eager")


@pytest.mark.parametrize("d_start", [3, 9])
def test_t_bisection_from_a_start_depth_matches_stack_reference(d_start):
    """Walks that start on the 2^d_start pieces of a depth (rays whose d_max is smaller
    start at d_max) test and accept exactly what a stack started there does."""
    p, D, d_max, active = _oracle_rays()
    max_steps = 256 * _bisect.MAX_DEPTH
    ref = stack_bisect(lambda s0, s1: _oracle(p, D, s0, s1), d_max, active, max_steps,
                       d_start)
    assert ref[1].sum() > 10 and (~ref[1]).sum() > 10
    for path, run in _kernels(_oracle, max_steps, lanes=32, paths=("lanes", "one_loop"),
                              d_start=d_start).items():
        _assert_same(run(p, D, d_max, active), ref, path)


def _floored_oracle(p, D, s0, s1):
    """`_oracle` with an enclosure floor: the piece widened by D[..., 2] (absolute) on each
    side, as a network's enclosure near its surface, so hundreds of pieces before a
    root are possible at depth d_max and only verification tells them from the root's."""
    root = p[..., 0]
    possible = (root >= s0 - D[..., 2]) & (root <= s1 + D[..., 2])
    return _bisect.BoxTest(possible, jnp.ones_like(possible), jnp.zeros_like(possible))


def _root_inside(p, D, s0, s1):
    """Verification for the oracles: the root lies in [s0, s1]."""
    return (p[..., 0] >= s0) & (p[..., 0] <= s1)


@pytest.mark.parametrize("d_start", [0, 4])
def test_verified_walks_go_past_hundreds_of_failed_pieces(d_start):
    """With a floor of 0.05 at depth 12 about 200 pieces before each root pass the test
    and fail verification. Every path (lanes verify between refills, the others in
    rounds of walks) goes on past all of them and agrees with the stack reference with
    verification, bit for bit; and every root is found (once a round limit of 64 walks
    lost these rays)."""
    p, D, d_max, active = _oracle_rays()
    d_max = np.full_like(d_max, 12)
    D[:, 2] = 0.05
    max_steps = 256 * _bisect.MAX_DEPTH
    ref = stack_bisect(lambda s0, s1: _floored_oracle(p, D, s0, s1), d_max, active,
                       max_steps, d_start, verify=lambda s0, s1: _root_inside(p, D, s0, s1))
    rooted = active & np.isfinite(p[:, 0])
    np.testing.assert_array_equal(ref[1], rooted)
    assert np.median(ref[2][rooted]) > 200  # most of them are failed pieces
    paths = ("lanes", "one_loop") if d_start else ("packet", "lanes", "one_loop")
    for path, run in _kernels(_floored_oracle, max_steps, lanes=32, paths=paths,
                              d_start=d_start, verify=_root_inside).items():
        _assert_same(run(p, D, d_max, active), ref, path)


def test_verified_walks_stop_at_max_steps():
    """An enclosure that holds a root everywhere and a verification that never passes
    (a loose network far from its surface): 2^20 pieces would each be accepted and fail,
    so every path stops each ray at max_steps with no hit, as the stack reference does."""
    p, D, d_max, active = _oracle_rays()
    d_max = np.full_like(d_max, 20)
    D[:, 2] = 2.0
    max_steps = 300

    def never(p, D, s0, s1):
        return jnp.zeros(jnp.shape(s0), bool)

    ref = stack_bisect(lambda s0, s1: _floored_oracle(p, D, s0, s1), d_max, active,
                       max_steps, verify=lambda s0, s1: np.zeros(len(s0), bool))
    rooted = active & np.isfinite(p[:, 0])  # (rootless rays are excluded at once)
    assert not ref[1].any() and (ref[2][rooted] == max_steps).all() and rooted.sum() > 100
    for path, run in _kernels(_floored_oracle, max_steps, lanes=32, verify=never).items():
        _assert_same(run(p, D, d_max, active), ref, path)


def test_start_depth_reaches_the_longest_pieces_excluded_half_the_time():
    """A test that excludes a piece only when it is at most 2^-5 long in space (|D| times
    its share of the segment) and holds no root (`_oracle` otherwise): pieces of
    2^-6 .. 2^-5 are excluded for nearly every rootless ray and most others, longer ones
    never, so each ray starts at the first depth whose pieces are at most 2^-5 long
    (segments of different lengths at different depths); with exclusion from 2^-2 at
    the first depth at most 2^-2; a test excluding nothing: at the pilot's deepest
    depth for a segment of the pilot's median length."""
    p, D, d_max, active = _oracle_rays()
    d_max = np.full_like(d_max, 20)
    norm = np.linalg.norm(D.astype(np.float64), axis=-1)
    assert norm.max() > 2 * norm.min()  # segments of different lengths

    def test_from(length):
        def test(p, D, s0, s1):
            r = _oracle(p, D, s0, s1)
            too_long = jnp.linalg.norm(D, axis=-1) * (s1 - s0) > length
            return r._replace(possible=r.possible | too_long)
        return test

    pilot = np.nonzero(active)[0][(np.arange(_bisect.PILOT_RAYS) * active.sum())
                                  // _bisect.PILOT_RAYS]
    median_top = np.log2(np.median(norm[pilot])) - _bisect.PILOT_DEPTH
    for length, top in ((2.0**-5, -5.0), (2.0**-2, -2.0), (0.0, median_top)):
        got = jax.jit(functools.partial(_bisect.start_depth, test_from(length)))(
            p, D, d_max, active)
        x = np.log2(norm) - top
        expected = np.clip(np.ceil(x), 0, 20)
        # float32 against float64 may round differently where x is within 1e-4 of an
        # integer (segments as long as the median, in the last case): there +-1
        clear = active & (np.abs(x - np.round(x)) > 1e-4)
        got = np.asarray(got)
        np.testing.assert_array_equal(got[clear], expected[clear], str(length))
        assert np.abs(got[active] - expected[active]).max() <= 1, length
        assert clear.sum() > 50, length


# ------------------------------------------------------- t-bisection, catalogue surfaces


def _surface_test(scene, arithmetic):
    F = extended(scene.field, arithmetic, "fast")

    def test(p, D, s0, s1):
        boxes = ray_boxes(p, D, s0, s1, arithmetic)
        r = enclosure(F, boxes, scene.w, scene.params, arithmetic)
        possible, finite = contains_any(r, scene.isovalues)
        return _bisect.BoxTest(possible, finite, jnp.zeros_like(possible))
    return test


@pytest.mark.parametrize("name,arithmetic", [("sphere", "interval"),
                                             ("barth_sextic", "affine"),
                                             ("steiner", "interval"),
                                             ("teardrop", "interval")])
def test_t_bisection_matches_stack_reference_on_surfaces(name, arithmetic):
    """32 x 32 camera rays: the kernels and the reference see the same box test, so hits,
    step counts and hit parameters are equal bit for bit."""
    scene = surfaces.scene(name)
    rays = surfaces.camera(name, 32).rays().reshape((-1,))
    _, _, inside, p, D = ray_segments(rays, scene.lo, scene.hi, 0.0, jnp.inf)
    d_max = _bisect.depth_for(jnp.linalg.norm(D, axis=-1), scene.eps)
    test = _surface_test(scene, arithmetic)
    batch_test = jax.jit(test)
    max_steps = 256 * _bisect.MAX_DEPTH
    ref = stack_bisect(lambda s0, s1: batch_test(p, D, s0, s1), np.asarray(d_max),
                       np.asarray(inside), max_steps)
    assert ref[1].sum() > 50
    for path, run in _kernels(test, max_steps, lanes=64, paths=("packet", "lanes")).items():
        _assert_same(run(p, D, d_max, inside), ref, path)


# ----------------------------------------------------- leaps (stretches with no root)


def _roots_oracle(p, D, s0, s1):
    """An exact box test over up to three roots per ray (p[..., :3], nan: none): a piece
    is possible where it holds a root."""
    roots = p[..., :3]
    possible = jnp.any((roots >= s0[..., None]) & (roots <= s1[..., None]), axis=-1)
    return _bisect.BoxTest(possible, jnp.ones_like(possible), jnp.zeros_like(possible))


def _next_root(aux, s):
    """ahead for `_roots_oracle`: no root in [s, the first root at or after s)."""
    roots = aux
    later = jnp.where(roots >= s[..., None], roots, jnp.inf)
    return jnp.min(later, axis=-1)


def _roots_rays(n=256, seed=3):
    rng = np.random.default_rng(seed)
    roots = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    roots[rng.random((n, 3)) < 0.4] = np.nan
    p = roots
    D = np.zeros((n, 3), np.float32)
    d_max = rng.integers(1, 21, n).astype(np.int32)
    active = rng.random(n) < 0.9
    return p, D, d_max, active


def test_leaps_keep_the_first_root_in_fewer_steps():
    """Walks that leap over stretches known to hold no root (`ahead`, `leap`) find the
    piece at d_max that holds each ray's first root, as the stack reference without them
    does (a root on the boundary of two pieces may be reported in either), in fewer
    steps; on lanes, in one loop and in the packet path alike."""
    p, D, d_max, active = _roots_rays()
    max_steps = 256 * _bisect.MAX_DEPTH
    ref = stack_bisect(lambda s0, s1: _roots_oracle(p, D, s0, s1), d_max, active,
                       max_steps)
    first = np.nanmin(np.where(np.isnan(p), np.inf, p), axis=-1)
    rooted = active & np.isfinite(first)
    np.testing.assert_array_equal(ref[1], rooted)
    width = 2.0 ** -d_max.astype(np.float64)

    def packet(p, D, d_max, active):
        def one(p, D, d_max, active):
            return _bisect.t_bisect(functools.partial(_roots_oracle, p, D), d_max, active,
                                    max_steps, ahead=functools.partial(_next_root, p))
        return jax.vmap(one)(p, D, d_max, active)

    runs = {lanes: jax.jit(lambda p, D, d_max, active, lanes=lanes: _bisect.t_bisect_lanes(
        _roots_oracle, p, D, d_max, active, lanes, max_steps, ahead=_next_root, aux=p))
        for lanes in (32, None)}
    runs["packet"] = jax.jit(packet)
    for path, run in runs.items():
        res = run(p, D, d_max, active)
        hit, s, steps = (np.asarray(a) for a in (res.hit, res.s, res.steps))
        np.testing.assert_array_equal(hit, rooted, err_msg=str(path))
        # the hit piece [s - w/2, s + w/2] holds the first root
        assert np.all(np.abs(s[rooted] - first[rooted]) <= 0.5 * width[rooted] + 1e-7)
        assert np.all(steps <= ref[2])
        assert steps[rooted].mean() < 0.5 * ref[2][rooted].mean()


@pytest.mark.parametrize("seed", [0, 1])
def test_leap_lands_on_the_largest_piece_in_the_stretch(seed):
    """leap against a brute-force search over depths: the piece it lands on starts after
    the walk's piece and at most at s_free, and no depth from d0 up holds a larger one;
    it stays where no piece starts in (start, s_free]; past when s_free >= 1."""
    rng = np.random.default_rng(seed)
    n = 2000
    d = rng.integers(0, 16, n)
    k = (rng.random(n) * 2.0**d).astype(np.int64)
    d0 = np.minimum(d, rng.integers(0, 6, n))
    d_max = np.maximum(d, rng.integers(0, 20, n))
    start = k * 2.0**-d
    s_free = np.where(rng.random(n) < 0.2, start + rng.uniform(0, 1e-4, n),
                      start + rng.uniform(0, 1.2, n) * (1 - start)).astype(np.float32)
    k2, d2, past = (np.asarray(a) for a in _bisect.leap(
        jnp.asarray(k, jnp.int32), jnp.asarray(d, jnp.int32), jnp.asarray(s_free),
        jnp.asarray(d0, jnp.int32), jnp.asarray(d_max, jnp.int32)))
    for i in range(n):
        free = min(float(s_free[i]), 1.0)
        best = None
        for depth in range(int(d0[i]), int(d_max[i]) + 1):
            m = np.floor(free * 2.0**depth)
            if m * 2.0**-depth > start[i] and m < 2.0**depth:
                best = (int(m), depth)
                break
        assert past[i] == (s_free[i] >= 1.0)
        if past[i]:  # the walk is over: where it stands does not matter
            continue
        if best is None:
            assert (k2[i], d2[i]) == (k[i], d[i]), i
        else:
            assert (k2[i], d2[i]) == best, (i, k[i], d[i], float(s_free[i]), d0[i], d_max[i])


def _root_parts(p, D, s0, s1, parts=None):
    """Verification for `_floored_oracle` by parts: the root lies in [s0, s1], and in
    which of `parts` equal parts."""
    root = p[..., 0]
    inside = (root >= s0) & (root <= s1)
    if parts is None:
        return inside
    part = jnp.clip(jnp.floor((root - s0) / (s1 - s0) * parts), 0, parts - 1)
    return inside, jnp.where(inside, part.astype(jnp.int32), -1)


@pytest.mark.parametrize("levels", [1, 3])
def test_walks_verify_levels_above_d_max_and_hit_the_root_part(levels):
    """With verify_levels, walks accept pieces that many levels above d_max and the hit is
    the part at d_max that holds the root: the same hits as the walk to d_max, the hit
    piece holds the root, in fewer steps (the enclosure floor makes dozens of d_max
    pieces before each root possible); on lanes, in one loop and per ray alike."""
    p, D, d_max, active = _oracle_rays()
    d_max = np.full_like(d_max, 12)
    D[:, 2] = 0.01
    max_steps = 256 * _bisect.MAX_DEPTH
    ref = stack_bisect(lambda s0, s1: _floored_oracle(p, D, s0, s1), d_max, active,
                       max_steps, verify=lambda s0, s1: _root_inside(p, D, s0, s1))
    rooted = active & np.isfinite(p[:, 0])
    np.testing.assert_array_equal(ref[1], rooted)

    def packet(p, D, d_max, active):
        def one(p, D, d_max, active):
            return _bisect.t_bisect(functools.partial(_floored_oracle, p, D), d_max, active,
                                    max_steps, functools.partial(_root_parts, p, D),
                                    verify_levels=levels)
        return jax.vmap(one)(p, D, d_max, active)

    runs = {lanes: jax.jit(lambda p, D, d_max, active, lanes=lanes: _bisect.t_bisect_lanes(
        _floored_oracle, p, D, d_max, active, lanes, max_steps, _root_parts,
        verify_levels=levels)) for lanes in (32, None)}
    runs["packet"] = jax.jit(packet)
    for path, run in runs.items():
        res = run(p, D, d_max, active)
        hit, s, steps = (np.asarray(a) for a in (res.hit, res.s, res.steps))
        np.testing.assert_array_equal(hit, rooted, err_msg=str(path))
        assert np.all(np.abs(s[rooted] - p[rooted, 0]) <= 2.0**-13 + 1e-7), path
        assert steps[rooted].mean() < 0.7 * ref[2][rooted].mean(), path


@pytest.mark.parametrize("n", [1, 7, 512, 4099])
@pytest.mark.parametrize("share", [0.0, 0.03, 0.5, 1.0])
def test_stable_partition_is_a_stable_argsort_of_the_flags(n, share):
    """The lanes' queue order (counting, not sorting) equals numpy's stable argsort."""
    from jaxiso._lanes import stable_partition
    flags = np.random.default_rng(n).uniform(size=n) < share
    got = np.asarray(jax.jit(stable_partition)(jnp.asarray(flags)))
    np.testing.assert_array_equal(got, np.argsort(~flags, kind="stable"))
