"""Instruction tapes (jaxiso.arith._tape) and the program path (jaxiso.implicit.program).

References: the straight path (the user's function run op by op, eagerly: the same
float32 operations in the same order), `ji.extend` for intervals, and float64 numpy
(tests/reference_program64.py) for hits.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_program64 import vm64

import jaxiso as ji
from jaxiso.arith import _tape
from jaxiso.implicit import program as P
from jaxiso.implicit import surfaces
from jaxiso.implicit.generate import csg_program

SURFACES = ["sphere", "barth_sextic", "tangle", "sin.blob", "water", "morph"]


def _boxes(rng, lo, hi, n, rad=0.15):
    c = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    r = rng.uniform(0, rad, (n, 3)).astype(np.float32) * (np.asarray(hi) - np.asarray(lo))
    return c - r, c + r


@pytest.mark.parametrize("name", SURFACES)
def test_catalogue_points_bitwise_and_intervals_match_extend(name):
    s = surfaces.get(name)
    tape = P.tape_of(s.f)
    rng = np.random.default_rng(1)
    lo, hi = np.asarray(s.lo, np.float32), np.asarray(s.hi, np.float32)
    p = rng.uniform(lo, hi, (300, 3)).astype(np.float32)
    w = np.float32(s.w)
    got = np.asarray(P.evaluate_points(tape, p[:, 0], p[:, 1], p[:, 2], w))
    straight = np.asarray(jax.vmap(lambda x, y, z: s.f(x, y, z, w))(p[:, 0], p[:, 1], p[:, 2]))
    np.testing.assert_array_equal(got, straight)  # same operations, same order
    blo, bhi = _boxes(rng, lo, hi, 200)
    box = [ji.Interval(blo[:, k], bhi[:, k]) for k in range(3)]
    r = P.evaluate_intervals(tape, *box, w)
    F = ji.extend(s.f, "interval")
    ref = F(*box, w)
    scale = 1.0 + np.abs(np.asarray(ref.lo)) + np.abs(np.asarray(ref.hi))
    ok = np.isfinite(np.asarray(ref.lo))
    assert np.all(np.abs(np.asarray(r.lo) - np.asarray(ref.lo))[ok] <= 1e-5 * scale[ok])
    assert np.all(np.abs(np.asarray(r.hi) - np.asarray(ref.hi))[ok] <= 1e-5 * scale[ok])
    # enclosure of sampled points of every box
    u = rng.uniform(size=(8, 200, 3)).astype(np.float32)
    q = blo + u * (bhi - blo)
    vals = np.asarray(P.evaluate_points(tape, q[..., 0], q[..., 1], q[..., 2], w))
    fin = np.isfinite(vals)
    tol = 1e-5 * scale
    assert np.all(((vals >= np.asarray(r.lo) - tol) & (vals <= np.asarray(r.hi) + tol))[fin])


def test_csg_program_points_intervals_and_float64():
    prog = csg_program(30, seed=3)
    tape = P.tape_of(prog)
    assert int(tape.n) <= len(prog)
    rng = np.random.default_rng(2)
    p = rng.uniform(-1.2, 1.2, (500, 3)).astype(np.float32)
    got = np.asarray(P.evaluate_points(tape, p[:, 0], p[:, 1], p[:, 2]))
    straight = np.asarray(jax.vmap(prog)(p[:, 0], p[:, 1], p[:, 2]))
    np.testing.assert_array_equal(got, straight)
    ref64 = vm64(prog.ops, *(p[:, k].astype(np.float64) for k in range(3)))
    assert np.max(np.abs(got - ref64)) < 1e-5
    blo, bhi = _boxes(rng, -1.2, 1.2, 100, 0.05)
    r = P.evaluate_intervals(tape, *[ji.Interval(blo[:, k], bhi[:, k]) for k in range(3)])
    u = rng.uniform(size=(16, 100, 3))
    q = blo + u * (bhi - blo)
    v64 = vm64(prog.ops, q[..., 0], q[..., 1], q[..., 2])
    assert np.all(v64 >= np.asarray(r.lo) - 1e-5) and np.all(v64 <= np.asarray(r.hi) + 1e-5)


def _csg40_choices(seed: int, R: int):
    """CSG-40's tape, R random small boxes (numpy lo, hi [R, 3] and Interval coords),
    the batch of R copies of the tape, its interval values and recorded choices."""
    tape = P.tape_of(csg_program(40, seed=5))
    rng = np.random.default_rng(seed)
    blo, bhi = _boxes(rng, -1.1, 1.1, R, 0.04)
    coords = [ji.Interval(jnp.asarray(blo[:, k])[:, None], jnp.asarray(bhi[:, k])[:, None])
              for k in range(3)] + [ji.Interval(0.0, 0.0)]
    batch = _tape.take_regions(tape, jnp.zeros(R, jnp.int32))
    f, chosen = jax.jit(_tape.evaluate, static_argnames="record")(batch, coords, record=True)
    return tape, rng, blo, bhi, coords, batch, f, chosen


def test_pruned_tapes_give_the_same_values_in_their_region():
    R = 32
    tape, rng, blo, bhi, coords, batch, f, chosen = _csg40_choices(3, R)
    pruned = jax.jit(_tape.prune)(batch, chosen[:, :, 0])
    n = np.asarray(pruned.n)
    assert np.all(n <= int(tape.n)) and n.mean() < 0.5 * int(tape.n)
    u = rng.uniform(size=(R, 64, 3)).astype(np.float32)
    q = (blo[:, None] + u * (bhi - blo)[:, None]).astype(np.float32)
    pts = [jnp.asarray(q[..., k]) for k in range(3)] + [jnp.float32(0)]
    ev = jax.jit(_tape.evaluate)
    full = np.asarray(ev(batch, pts))
    short = np.asarray(ev(pruned, pts))
    np.testing.assert_array_equal(short, full)
    # the pruned tape's interval on its own box still encloses (and is no wider)
    g = ev(pruned, coords)
    assert np.all(np.asarray(g.lo) >= np.asarray(f.lo) - 1e-6)
    assert np.all(np.asarray(g.hi) <= np.asarray(f.hi) + 1e-6)


def test_a_store_read_through_an_index_equals_the_gathered_tapes():
    """`evaluate(store, coords, index=)` (regions reading their tapes in place, as the tape
    path's children that are not pruned) gives what the tapes gathered per region give:
    points, and intervals with their min/max choices; and `chunked_eval` splits the index
    into chunks the same way."""
    R = 16
    tape, rng, blo, bhi, coords, batch, f, chosen = _csg40_choices(4, R)
    store = jax.jit(_tape.prune)(batch, chosen[:, :, 0])  # R tapes of different lengths
    ix = rng.integers(0, R, 48).astype(np.int32)
    index = jnp.asarray(ix)
    own = _tape.take_regions(store, index)
    u = rng.uniform(size=(48, 8, 3)).astype(np.float32)
    q = (blo[ix][:, None] + u * (bhi - blo)[ix][:, None]).astype(np.float32)
    pts = [jnp.asarray(q[..., k]) for k in range(3)] + [jnp.float32(0)]
    ev = jax.jit(_tape.evaluate, static_argnames="record")
    np.testing.assert_array_equal(np.asarray(ev(store, pts, index=index)),
                                  np.asarray(ev(own, pts)))
    boxes = [ji.Interval(jnp.asarray(blo[ix][:, None, k]), jnp.asarray(bhi[ix][:, None, k]))
             for k in range(3)] + [ji.Interval(jnp.float32(0), jnp.float32(0))]
    a, ca = ev(store, boxes, record=True, index=index)
    b, cb = ev(own, boxes, record=True)
    np.testing.assert_array_equal(np.asarray(a.lo), np.asarray(b.lo))
    np.testing.assert_array_equal(np.asarray(a.hi), np.asarray(b.hi))
    np.testing.assert_array_equal(np.asarray(ca), np.asarray(cb))
    chunked = jax.jit(lambda t, c, i: P.chunked_eval(t, c, False, 2**8, 4, i))
    np.testing.assert_array_equal(np.asarray(chunked(store, pts, index)),
                                  np.asarray(ev(own, pts)))


def test_inactive_regions_run_nothing_and_change_nothing():
    """`evaluate(..., active=)` gives the active regions bitwise the values of a run
    without the mask (whole tapes, a store through an index, `chunked_eval`'s chunks);
    with no region active the loop runs no step (every register stays 0, so the
    result is 0)."""
    R = 16
    tape, rng, blo, bhi, coords, batch, f, chosen = _csg40_choices(6, R)
    store = jax.jit(_tape.prune)(batch, chosen[:, :, 0])
    ix = jnp.asarray(rng.integers(0, R, 32).astype(np.int32))
    active = jnp.asarray(rng.uniform(size=32) < 0.5)
    u = rng.uniform(size=(32, 4, 3)).astype(np.float32)
    q = blo[np.asarray(ix)][:, None] + u * (bhi - blo)[np.asarray(ix)][:, None]
    pts = [jnp.asarray(q[..., k], jnp.float32) for k in range(3)] + [jnp.float32(0)]
    ev = jax.jit(_tape.evaluate, static_argnames="record")
    whole = np.asarray(ev(store, pts, index=ix))
    masked = np.asarray(ev(store, pts, index=ix, active=active))
    a = np.asarray(active)
    np.testing.assert_array_equal(masked[a], whole[a])
    chunked = jax.jit(lambda t, c, i, m: P.chunked_eval(t, c, False, 2**8, 4, i, m))
    np.testing.assert_array_equal(np.asarray(chunked(store, pts, ix, active))[a], whole[a])
    none = np.asarray(ev(store, pts, index=ix, active=jnp.zeros(32, bool)))
    np.testing.assert_array_equal(none, np.zeros_like(none))


def test_narrowed_tapes_evaluate_bitwise_as_the_wide_ones():
    """Tapes held narrow (int8 opcodes, int16 operands and registers: the tape path's
    stores that are no longer pruned) give bitwise the values and choices of the int32
    tapes, read whole or through an index, on points, intervals and affine forms; and
    take 15 bytes an instruction."""
    R = 16
    tape, rng, blo, bhi, coords, batch, f, chosen = _csg40_choices(5, R)
    store = jax.jit(_tape.prune)(batch, chosen[:, :, 0])
    narrow = _tape.narrowed(store)
    per_instruction = sum(x.dtype.itemsize * x[..., 0].size for x in
                          (narrow.op, narrow.a, narrow.b, narrow.imm, narrow.reg))
    assert per_instruction == 15 * narrow.length
    ix = jnp.asarray(rng.integers(0, R, 40).astype(np.int32))
    ev = jax.jit(_tape.evaluate, static_argnames="record")
    u = rng.uniform(size=(40, 8, 3)).astype(np.float32)
    q = blo[np.asarray(ix)][:, None] + u * (bhi - blo)[np.asarray(ix)][:, None]
    pts = [jnp.asarray(q[..., k], jnp.float32) for k in range(3)] + [jnp.float32(0)]
    np.testing.assert_array_equal(np.asarray(ev(narrow, pts, index=ix)),
                                  np.asarray(ev(store, pts, index=ix)))
    lo, hi = jnp.asarray(blo, jnp.float32), jnp.asarray(bhi, jnp.float32)
    boxes = [ji.Interval(lo[:, None, k], hi[:, None, k]) for k in range(3)]
    zero = ji.Interval(jnp.float32(0), jnp.float32(0))
    a, ca = ev(narrow, boxes + [zero], record=True)
    b, cb = ev(store, boxes + [zero], record=True)
    for x, y in ((a.lo, b.lo), (a.hi, b.hi), (ca, cb)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    forms = [ji.aa.from_interval(b, k, 3) for k, b in enumerate(boxes)]
    forms.append(ji.aa.as_affine(jnp.zeros((R, 1), jnp.float32), 3))
    a, b = ev(narrow, forms), ev(store, forms)
    for x, y in ((a.center, b.center), (a.dev, b.dev), (a.err, b.err)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="int16"):
        _tape.narrowed(_tape.resize(store, 2**15))


def test_pruning_in_two_stages_equals_pruning_at_once():
    """Pruning by choices a group shares, then by one region's own on the shorter tape
    (mapped through `prune(..., origins=True)`), gives the tape one pruning gives; and
    each pruned instruction's origin holds the same opcode and constant."""
    R = 16
    tape, _, _, _, _, batch, _, chosen = _csg40_choices(4, R)
    own = chosen[:, :, 0]
    once = jax.jit(_tape.prune)(batch, own)
    # the group's shared choices: those of regions 0-7 and 8-15 that all agree
    pairs = own.reshape(own.shape[0], 2, 8)
    shared = jnp.where(jnp.all(pairs == pairs[..., :1], axis=-1), pairs[..., 0], 0)
    group = _tape.take_regions(tape, jnp.zeros(2, jnp.int32))
    first, origin = jax.jit(_tape.prune, static_argnames="origins")(group, shared, origins=True)
    m = np.asarray(first.n)
    for g in range(2):
        o = np.asarray(origin)[:m[g], g]
        assert np.all(np.diff(o) > 0)
        np.testing.assert_array_equal(np.asarray(first.op)[:m[g], g], np.asarray(tape.op)[o])
        np.testing.assert_array_equal(np.asarray(first.imm)[:m[g], g], np.asarray(tape.imm)[o])
    parents = _tape.take_regions(first, jnp.arange(R) // 8)
    mapped = jnp.take_along_axis(own, jnp.asarray(origin)[:, jnp.arange(R) // 8], axis=0)
    twice = jax.jit(_tape.prune)(parents, mapped)
    np.testing.assert_array_equal(np.asarray(twice.n), np.asarray(once.n))
    for field in ("op", "a", "b", "imm"):
        k = np.arange(once.length)[:, None] < np.asarray(once.n)[None]
        np.testing.assert_array_equal(np.where(k, np.asarray(getattr(twice, field)), 0),
                                      np.where(k, np.asarray(getattr(once, field)), 0))


def test_one_compiled_evaluator_runs_any_program_of_a_bucket():
    a = P.tape_of(csg_program(10, seed=0))
    b = P.tape_of(csg_program(10, seed=1))
    L = max(a.length, b.length)
    ops = set(a.opset) | set(b.opset)
    a, b = (_tape.with_opset(_tape.resize(t, L), ops) for t in (a, b))
    traces = []

    @jax.jit
    def ev(tape, coords):
        traces.append(1)
        return _tape.evaluate(tape, coords)

    x = jnp.linspace(-1, 1, 16)[None]
    for t in (a, b):
        ev(_tape.take_regions(t, jnp.zeros(1, jnp.int32)), [x, x, x, jnp.float32(0)])
    assert len(traces) == 1


def test_unsupported_primitives_are_named():
    with pytest.raises(NotImplementedError, match="'lt'"):
        P.tape_of(lambda x, y, z: jnp.where(x < y, x, z))
    with pytest.raises(NotImplementedError, match="no tape opcode"):
        P.tape_of(ji.implicit.load_vm("a var-x\nb tan a\n"))


CIRCLES = """a var-x
b var-y
c const 0.3
d sub a c
e square d
f square b
g add e f
h sqrt g
r const 0.45
i sub h r
j const -0.35
k sub a j
l square k
m add l f
n sqrt m
o sub n r
p min i o
"""


def test_slab_of_a_2d_program_on_the_tape_path_matches_pixel_centres():
    """A 2D program (no z) as a slab |z| < 0.25, rays straight down z, through the tape
    path: hit where the program is negative at the pixel centre, on the slab's top face."""
    prog = ji.implicit.load_vm(CIRCLES)
    scene = ji.ImplicitSurface(lambda x, y, z: jnp.maximum(prog(x, y, z), jnp.abs(z) - 0.25),
                               (-1, -1, -1), (1, 1, 1))
    cam = ji.Camera.orthographic_view((0, 0, 3), (0, 0, 0), (0, 1, 0), 1.0, 48, 48)
    rays = cam.rays().reshape((-1,))
    stats = {}
    hits = scene.intersect_tape(rays, jnp.zeros(rays.shape), jnp.full(rays.shape, jnp.inf),
                                stats=stats)
    o = np.asarray(rays.origin, np.float64)
    inside = vm64(prog.ops, o[..., 0], o[..., 1], o[..., 2])
    hit = np.asarray(hits.hit)
    assert 0.1 < (inside < 0).mean() < 0.9
    sure = np.abs(inside) > 2 * scene.eps  # pixel centres not on a circle's rim
    np.testing.assert_array_equal(hit[sure], (inside < 0)[sure])
    np.testing.assert_allclose(np.asarray(hits.t)[hit], 2.75, atol=2 * scene.eps)
    assert stats["levels"] and stats["tape_length"] > 10  # the tape path ran


def test_tape_dataclass_roundtrip():
    t = P.tape_of(lambda x, y, z: x * x + y)
    assert t.n_vars == 4 and int(t.n) == 4  # var x, var y, square, add
    t2 = dataclasses.replace(t, n=jnp.int32(4))
    assert float(P.evaluate_points(t2, 2.0, 1.0, 0.0)) == 5.0


def _random_program(rng, size, n_vars=3):
    """A random SSA program of about `size` operations (min/max-heavy, as CSG is) in which
    every value is read: operations take their operands from a pool of up to 24 pending
    values (a constant or coordinate read afresh when the pool runs low), and the pool is
    folded by min at the end."""
    ops, pool = [], []

    def leaf():
        if rng.uniform() < 0.5:
            ops.append(("const", 0, 0, float(rng.uniform(-1, 1))))
        else:
            ops.append(("var", int(rng.integers(n_vars)), 0, 0.0))
        return len(ops) - 1

    unary = ["neg", "abs", "square"]
    binary = ["add", "sub", "mul", "min", "max", "min", "max"]
    while len(ops) < size:
        while len(pool) < 2 or (len(pool) < 24 and rng.uniform() < 0.3):
            pool.append(leaf())
        x = pool.pop(int(rng.integers(len(pool))))
        if rng.uniform() < 0.2:
            ops.append((unary[rng.integers(len(unary))], x, 0, 0.0))
        else:
            y = pool.pop(int(rng.integers(len(pool))))
            ops.append((binary[rng.integers(len(binary))], x, y, 0.0))
        pool.append(len(ops) - 1)
    while len(pool) > 1:
        ops.append(("min", pool.pop(), pool.pop(), 0.0))
        pool.append(len(ops) - 1)
    return _tape.tidy(ops, len(ops) - 1, n_vars)


def _ssa64(op, a, b, imm, n, x):
    """Independent float64 interpreter of an SSA tape (one region, points x [3, P])."""
    v = []
    unary = {"neg": np.negative, "abs": np.abs, "square": np.square, "sqrt": np.sqrt}
    binary = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide,
              "min": np.minimum, "max": np.maximum}
    for i in range(n):
        name = _tape.OPS[op[i]]
        if name == "const":
            v.append(np.full(x.shape[1], imm[i], np.float64))
        elif name == "var":
            v.append(x[a[i]].astype(np.float64))
        elif name in unary:
            v.append(unary[name](v[a[i]]))
        else:
            v.append(binary[name](v[a[i]], v[b[i]]))
    return v[n - 1]


@pytest.mark.parametrize("size", [300, 3000])
def test_registers_stay_few_and_pruned_tapes_fit_their_file(size):
    """The register file is sized by the values live at once, not by the program's length;
    tapes pruned by any choices (random here) are allocated within it, and the evaluator
    on those registers computes what an independent float64 SSA interpreter computes."""
    rng = np.random.default_rng(size)
    tape = _random_program(rng, size)
    assert tape.registers <= 64 < int(tape.n)
    R, Pn = 24, 5
    batch = _tape.take_regions(tape, jnp.zeros(R, jnp.int32))
    choice = jnp.asarray(rng.integers(0, 3, (tape.length, R)).astype(np.int8))
    pruned = jax.jit(_tape.prune)(batch, choice)
    _, used = jax.jit(_tape.allocate, static_argnums=4)(pruned.op, pruned.a, pruned.b,
                                                        pruned.n, tape.registers)
    assert np.all(np.asarray(used) <= tape.registers)
    x = rng.uniform(-1, 1, (3, R, Pn)).astype(np.float32)
    got = np.asarray(jax.jit(_tape.evaluate)(pruned, [jnp.asarray(c) for c in x]))
    arrays = [np.asarray(v) for v in (pruned.op, pruned.a, pruned.b, pruned.imm, pruned.n)]
    for r in range(R):
        op, a, b, imm = (v[:, r] for v in arrays[:4])
        ref = _ssa64(op, a, b, imm, arrays[4][r], x[:, r])
        np.testing.assert_allclose(got[r], ref, rtol=1e-4, atol=1e-4 * (1 + np.abs(ref).max()))
    # the file cut to the registers the pruned tapes use: the same values, bitwise
    cut = _tape.registers_in_use(pruned, minimum=4)
    assert cut.registers == _tape.bucket(int(np.max(np.asarray(used))), 4) <= tape.registers
    np.testing.assert_array_equal(
        np.asarray(jax.jit(_tape.evaluate)(cut, [jnp.asarray(c) for c in x])), got)
    # a file longer than the program needs: tapes up to IN_ORDER_MAX long keep their
    # instructions in order, longer ones are packed low by the scan
    wide = jax.jit(_tape.prune)(_tape.with_registers(batch, tape.length), choice)
    if int(np.max(np.asarray(pruned.n))) <= _tape.IN_ORDER_MAX:
        assert np.array_equal(np.asarray(wide.reg[:, 2]), np.broadcast_to(
            np.arange(tape.length)[:, None], (tape.length, R)))
    else:
        assert _tape.registers_in_use(wide, minimum=4).registers == cut.registers
    np.testing.assert_array_equal(
        np.asarray(jax.jit(_tape.evaluate)(wide, [jnp.asarray(c) for c in x])), got)


def test_short_pruned_tapes_keep_registers_in_order():
    """Pruned tapes no longer than IN_ORDER_MAX skip the scan: each instruction writes
    its own register, and the values match the scanned file's."""
    rng = np.random.default_rng(7)
    tape = _random_program(rng, 300)
    R = 16
    batch = _tape.with_registers(_tape.take_regions(tape, jnp.zeros(R, jnp.int32)), 64)
    choice = jnp.asarray(rng.integers(1, 3, (tape.length, R)).astype(np.int8))  # all decided
    pruned = jax.jit(_tape.prune)(batch, choice)
    n = np.asarray(pruned.n)
    assert n.max() <= _tape.IN_ORDER_MAX  # every min/max decided: short tapes
    reg = np.asarray(pruned.reg[:, 2])
    for r in range(R):
        assert np.array_equal(reg[:n[r], r], np.arange(n[r]))


def test_register_count_is_flat_in_program_length():
    counts = [P.tape_of(csg_program(k, seed=2)).registers for k in (10, 40, 160)]
    lengths = [P.tape_of(csg_program(k, seed=2)).length for k in (10, 40, 160)]
    assert lengths[-1] >= 8 * lengths[0]
    assert max(counts) <= 32


def test_the_evaluators_product_agrees_with_the_interval_rule():
    """The tape evaluator's product (plain endpoint products, `ia.mul` only in a step
    where a hull is NaN) gives `ia.mul`'s bounds, up to the sign of a zero, on ordinary
    boxes, on 0 x inf (the interval convention's 0) and on empty (NaN) factors."""
    from jaxiso.arith import _interval as ia
    rng = np.random.default_rng(3)
    lo = rng.normal(size=(2, 64)).astype(np.float32)
    hi = lo + rng.uniform(0, 2, size=(2, 64)).astype(np.float32)
    lo[0, :8] = 0.0
    hi[0, :4] = 0.0  # [0, 0] and [0, h] factors
    inf_lo, inf_hi = lo.copy(), hi.copy()
    inf_hi[1, :8] = np.inf  # times [0, 0] and [0, h]: 0 x inf
    empty_lo, empty_hi = lo.copy(), hi.copy()
    empty_lo[1, 10:12] = np.nan
    empty_hi[1, 10:12] = np.nan
    for a_lo, a_hi in ((lo, hi), (inf_lo, inf_hi), (empty_lo, empty_hi)):
        a = ia.Interval(jnp.asarray(a_lo[0]), jnp.asarray(a_hi[0]))
        b = ia.Interval(jnp.asarray(a_lo[1]), jnp.asarray(a_hi[1]))
        got = jax.jit(_tape._interval_product)(a, b)
        want = jax.jit(ia.mul)(a, b)
        for g, w in ((got.lo, want.lo), (got.hi, want.hi)):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
