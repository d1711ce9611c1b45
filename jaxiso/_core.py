"""The floor every layer stands on: rays, hits, the execution plan, the scene protocol,
the one pytree mechanism, the ray-box clip, facing normals and the implicit-function-
theorem attachment of hit parameters.

Nothing here imports another jaxiso module; scenes (implicit, volume, tetra) import this
and never `render`; `render` sees scenes only through `Scene`.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Rays", "Hits", "Plan", "Scene", "SceneFields", "pytree_dataclass", "static_field",
           "slab", "facing", "unit_or_facing", "on_points", "attach_t", "miss_like",
           "concrete", "check_finite", "check_choice", "check_count", "isovalues_array",
           "cpu_lanes", "ByIdentity", "WithStaticLeaves", "is_array_leaf", "unwrapped"]


# -- the one pytree mechanism ---------------------------------------------------------

def static_field(default=dataclasses.MISSING, **kwargs):
    """A dataclass field that is pytree metadata (static under jit: a new value compiles
    anew); every other field is a traced leaf."""
    return dataclasses.field(default=default, metadata=dict(static=True), **kwargs)


def pytree_dataclass(cls):
    """A frozen dataclass registered as a pytree: fields made with `static_field` are
    metadata, the others children. Unflattening bypasses ``__init__`` (JAX rebuilds nodes
    with tracers and placeholders; validation belongs to user-facing construction)."""
    # eq=False: identity equality and hashing (array fields have no truth value)
    cls = dataclasses.dataclass(frozen=True, eq=False)(cls)
    fields = dataclasses.fields(cls)
    data = tuple(f.name for f in fields if not f.metadata.get("static"))
    meta = tuple(f.name for f in fields if f.metadata.get("static"))

    def flatten(x):
        return (tuple(getattr(x, n) for n in data), tuple(getattr(x, n) for n in meta))

    def flatten_with_keys(x):
        return (tuple((jax.tree_util.GetAttrKey(n), getattr(x, n)) for n in data),
                tuple(getattr(x, n) for n in meta))

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for n, v in zip(data, children):
            object.__setattr__(obj, n, v)
        for n, v in zip(meta, aux):
            object.__setattr__(obj, n, v)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
    return cls


class ByIdentity:
    """A hashable stand-in for an unhashable object (an equinox module holding arrays),
    equal only to a stand-in for the same object. It holds the object, so while the
    stand-in lives (as a cache key, in a pytree's static data) the object's id is not
    reused."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __hash__(self) -> int:
        return id(self.obj)

    def __eq__(self, other) -> bool:
        return isinstance(other, ByIdentity) and other.obj is self.obj

    @staticmethod
    def wrap(x):
        """x if it is hashable, else its stand-in."""
        try:
            hash(x)
        except TypeError:
            return ByIdentity(x)
        return x

    @staticmethod
    def unwrap(x):
        return x.obj if isinstance(x, ByIdentity) else x


def is_array_leaf(x) -> bool:
    """x can be a traced argument of a jitted function (an array, a number, or the
    shape of one)."""
    return isinstance(x, (jax.Array, jax.ShapeDtypeStruct, jax.core.Tracer, np.ndarray,
                          np.generic, bool, int, float, complex))


@jax.tree_util.register_pytree_node_class
class WithStaticLeaves:
    """A pytree (`value`) whose array leaves are its children and whose other leaves
    (functions, strings, custom_jvp objects: an equinox module's activation) are static
    data, so that it passes through `jax.jit` as `equinox.filter_jit` would pass it.
    Which leaves are arrays is decided once, on the values given (`mask`): JAX rebuilds
    pytrees with placeholders in the children's places while it traces."""

    def __init__(self, value, mask=None):
        self.value = value
        self.mask = (tuple(is_array_leaf(x) for x in jax.tree_util.tree_leaves(value))
                     if mask is None else mask)

    @staticmethod
    def needed(tree) -> bool:
        """tree has a leaf that is not an array (jit cannot trace it)."""
        return not all(WithStaticLeaves(tree).mask)

    def tree_flatten(self):
        leaves, tree = jax.tree_util.tree_flatten(self.value)
        static = tuple(ByIdentity.wrap(x) for x, m in zip(leaves, self.mask) if not m)
        return [x for x, m in zip(leaves, self.mask) if m], (tree, self.mask, static)

    @classmethod
    def tree_unflatten(cls, aux, arrays):
        tree, mask, static = aux
        arrays, static = iter(arrays), iter(static)
        leaves = [next(arrays) if m else ByIdentity.unwrap(next(static)) for m in mask]
        return cls(jax.tree_util.tree_unflatten(tree, leaves), mask)


def unwrapped(params):
    """params as the user gave them (a `WithStaticLeaves` opened)."""
    return params.value if isinstance(params, WithStaticLeaves) else params


class SceneFields:
    """`replace` and `with_isovalues` for scene dataclasses: every change is validated by
    the scene's ``_validate`` (the same checks as construction), whatever the kind."""

    def replace(self, **changes):
        """The same scene with other field values; traced fields (eps, isovalues, w,
        clip box, ...) never recompile, static ones (method, normals, ...) do."""
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise TypeError(f"{type(self).__name__} has no field(s) {unknown}; its fields: "
                            f"{names}")
        new = object.__new__(type(self))
        for n in names:
            object.__setattr__(new, n, changes.get(n, getattr(self, n)))
        new._validate()
        return new

    def with_isovalues(self, isovalues):
        """The same scene at other isovalues (same count: no recompile)."""
        return self.replace(isovalues=isovalues)

    def _validate(self) -> None:
        raise NotImplementedError


# -- validation helpers (shared by every scene) ---------------------------------------

def concrete(x):
    """x as a numpy array, or None when it is traced or not numeric (checks of traced values
    happen where they were concrete)."""
    try:
        a = np.asarray(x)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            TypeError):
        return None
    return a if a.dtype != object else None


def on_host(x) -> bool:
    """Whether x has a concrete value (arrays; tracers of eager grad/jvp do, of jit and
    vmap do not)."""
    if not isinstance(x, jax.core.Tracer):
        return True
    try:
        bool(jnp.ravel(jax.lax.stop_gradient(x))[:1].sum() == 0)
    except Exception:  # ConcretizationTypeError and its kin: a jit / vmap tracer
        return False
    return True


def check_finite(name: str, x) -> None:
    """ValueError naming `name` if a concrete x holds NaN or inf."""
    a = concrete(x)
    if a is not None and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")


def isovalues_array(x) -> jax.Array:
    """Isovalues as float32 [K], K >= 1, finite where concrete (every scene kind)."""
    iso = jnp.atleast_1d(jnp.asarray(x, jnp.float32))
    if iso.ndim != 1 or iso.size == 0:
        raise ValueError(f"isovalues must be a scalar or a non-empty 1-D list, got shape "
                         f"{iso.shape}")
    check_finite("isovalues", iso)
    return iso


def check_count(name: str, value, least: int = 1, optional: bool = True) -> None:
    """A static whole-number option (max_steps, samples, ...): an int >= least, or None
    where optional."""
    if value is None and optional:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        none = "None or " if optional else ""
        raise ValueError(f"{name} must be {none}an int >= {least}, got {value!r}")


def check_choice(name: str, value, choices) -> None:
    """ValueError listing the valid choices."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")


# -- rays and hits ----------------------------------------------------------------------

@pytree_dataclass
class Rays:
    """A batch of rays ``p(t) = origin + t * direction``.

    Attributes:
      origin: [..., 3] float.
      direction: [..., 3] float, nonzero (need not be unit length; `t` is in its units).
    """

    origin: jax.Array
    direction: jax.Array

    @property
    def shape(self) -> tuple:
        return tuple(jnp.shape(self.origin)[:-1])

    def reshape(self, shape) -> Rays:
        shape = tuple(shape)
        return Rays(self.origin.reshape(shape + (3,)), self.direction.reshape(shape + (3,)))

    def at(self, t) -> jax.Array:
        """Points [..., 3] at parameters t [...]."""
        return self.origin + jnp.asarray(t)[..., None] * self.direction


@pytree_dataclass
class Hits:
    """First hits of a batch of rays (all arrays share the batch shape S).

    Attributes:
      t: [S] ray parameter of the hit, inf where none.
      hit: [S] bool.
      normal: [S, 3] unit normal (world space; (0, 0, 0) on a miss).
      surface: [S] int32, which isovalue or CSG part was hit (-1 on a miss).
      steps: [S] int32, loop iterations spent (a work counter for benchmarks).
    """

    t: jax.Array
    hit: jax.Array
    normal: jax.Array
    surface: jax.Array
    steps: jax.Array

    def reshape(self, shape) -> Hits:
        shape = tuple(shape)
        return Hits(self.t.reshape(shape), self.hit.reshape(shape),
                    self.normal.reshape(shape + (3,)), self.surface.reshape(shape),
                    self.steps.reshape(shape))


def miss_like(t) -> Hits:
    """Hits with no hit, shaped like t."""
    shape = jnp.shape(t)
    return Hits(jnp.full(shape, jnp.inf, jnp.float32), jnp.zeros(shape, bool),
                jnp.zeros(shape + (3,), jnp.float32), jnp.full(shape, -1, jnp.int32),
                jnp.zeros(shape, jnp.int32))


# -- the execution plan and the scene protocol ---------------------------------------

# The tape path's working-set budget, bytes (`Plan.memory_budget`). 512 MiB lowers the slab's
# peak at 1024^2 from 3.06 to 2.37 GB at the same call time, but its batches leave more
# distinct shapes to compile: first call at 256^2 50 -> 83 s (benchmarks/NOTES.md, session 26).
DEFAULT_MEMORY_BUDGET = 2**30


@dataclasses.dataclass(frozen=True)
class Plan:
    """How a batch of rays runs (static: a new plan compiles anew).

    Attributes:
      tile: packet edge in pixels: `render` orders camera rays in tiles of tile x tile
        pixels, and rays run in packets of tile**2 consecutive rays (a batched
        ``while_loop`` runs until its slowest ray is done, so coherent packets waste least).
      lanes: None (packets), or the width of persistent lanes with refill that run the
        whole batch as one queue (faster per frame for large images, slower to compile).
      tape: run the scene's program as an instruction tape, breadth-first over ray
        groups with per-region pruning (`ImplicitSurface` of a long program: its
        `preferred_plan` says when). Host-driven: under jit / vmap it runs in a
        `jax.pure_callback` (tested on CPU).
      memory_budget: bytes the tape path's working set may take (its regions run in
        batches sized from it; a program whose single region does not fit raises
        MemoryError naming both figures). Default 1 GiB (`DEFAULT_MEMORY_BUDGET`).
    """

    tile: int = 8
    lanes: int | None = None
    tape: bool = False
    memory_budget: int = DEFAULT_MEMORY_BUDGET

    def __post_init__(self):
        if isinstance(self.tile, bool) or not isinstance(self.tile, (int, np.integer)) \
                or self.tile < 1:
            raise ValueError(f"Plan.tile must be a positive int, got {self.tile!r}")
        if self.lanes is not None and (isinstance(self.lanes, bool) or not isinstance(
                self.lanes, (int, np.integer)) or self.lanes < 1):
            raise ValueError(f"Plan.lanes must be None or a positive int, got {self.lanes!r}")
        if not isinstance(self.tape, (bool, np.bool_)):
            raise ValueError(f"Plan.tape must be a bool, got {self.tape!r}")
        if self.tape and self.lanes is not None:
            raise ValueError("Plan.tape runs its own breadth-first traversal: lanes must "
                             "be None")
        if isinstance(self.memory_budget, bool) or not isinstance(
                self.memory_budget, (int, np.integer)) or self.memory_budget < 2**20:
            raise ValueError(f"Plan.memory_budget must be an int of at least 2**20 bytes, "
                             f"got {self.memory_budget!r}")
        object.__setattr__(self, "memory_budget", int(self.memory_budget))
        object.__setattr__(self, "tile", int(self.tile))
        object.__setattr__(self, "tape", bool(self.tape))
        if self.lanes is not None:
            object.__setattr__(self, "lanes", int(self.lanes))

    @property
    def packet(self) -> int:
        return self.tile * self.tile

    def __repr__(self) -> str:
        tape = ", tape=True" if self.tape else ""
        if self.memory_budget != DEFAULT_MEMORY_BUDGET:
            tape += f", memory_budget={self.memory_budget}"
        return f"Plan(tile={self.tile}, lanes={self.lanes}{tape})"


# Persistent lanes pay off on the CPU from 2^16 rays for every traversal measured (Barth
# sextic at 512^2: 1.60 vs 0.88 Mrays/s in 4x4 tiles; volumes and tets in
# benchmarks/NOTES.md) but compile 2-6x longer, so smaller batches keep packets. Other
# backends are unmeasured here (no GPU was lent) and keep packets.
LANES = 4096
LANES_FROM = 2**16


def cpu_lanes(n_rays: int, backend: str) -> int | None:
    """The lane count of a scene that gains from persistent lanes (None: packets)."""
    return LANES if backend == "cpu" and n_rays >= LANES_FROM else None


@typing.runtime_checkable
class Scene(typing.Protocol):
    """What `intersect` and `render` need of a scene (ImplicitSurface, CSG,
    VolumeIsosurface, TetIsosurface implement it; tests check each).

    Scenes are pytrees: static choices (method, arithmetic, normals, ...) are metadata,
    numeric knobs (eps, isovalues, w, clip box, level of detail) traced leaves, so changing
    a knob with `replace` never recompiles. Every option lives on the scene.
    """

    @property
    def lo(self) -> jax.Array:
        """[3] min corner of the drawn region's bounding box."""

    @property
    def hi(self) -> jax.Array:
        """[3] max corner."""

    @property
    def offset_scale(self) -> jax.Array:
        """[] world length by which secondary rays (shadows, layers, reflections) leave
        a surface (the ray precision for implicits; a fraction of a cell otherwise)."""

    def replace(self, **changes) -> Scene:
        """The same scene with other option values, validated as at construction."""

    def coarser(self, factor) -> Scene:
        """The scene for rays that may be `factor` (>= 1) times coarser (shadow rays,
        seed Sec. 6.4.6): a larger eps, a coarser level of detail, or itself."""

    def preferred_plan(self, n_rays: int, backend: str) -> Plan:
        """The fastest measured plan for a batch of n_rays on this backend."""

    def intersect_packet(self, rays: Rays, t_min, t_max, *, lanes: int | None = None
                         ) -> Hits:
        """First hits of one packet of rays [P] with t in [t_min, t_max] ([P] each).
        lanes: run the packet on that many persistent lanes with refill (same hits)."""


# -- geometry shared by the scenes ----------------------------------------------------

def slab(q0, dq, lo, hi):
    """Entry and exit t [P] of rays q0 + t dq [P, 3] through the boxes [lo, hi] (closed);
    an axis-parallel ray is inside that axis's slab for all t or for none."""
    safe = jnp.where(dq == 0, 1.0, dq)
    ta = (lo - q0) / safe
    tb = (hi - q0) / safe
    inside = (q0 >= lo) & (q0 <= hi)
    near = jnp.where(dq == 0, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(ta, tb))
    far = jnp.where(dq == 0, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(ta, tb))
    return jnp.max(near, axis=-1), jnp.min(far, axis=-1)


def facing(normal, direction):
    """Normals [..., 3] flipped to face the incoming rays (two-sided shading)."""
    s = jnp.sum(normal * direction, axis=-1, keepdims=True)
    return jnp.where(s > 0, -normal, normal)


def unit_or_facing(grad, direction):
    """grad / |grad| [..., 3]; where the gradient vanishes or is not finite, a normal that
    faces the ray (-direction / |direction|), never NaN."""
    norm = jnp.linalg.norm(grad, axis=-1, keepdims=True)
    ok = (norm > 0) & jnp.all(jnp.isfinite(grad), axis=-1, keepdims=True) & jnp.isfinite(norm)
    back = -direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    return jnp.where(ok, grad / jnp.where(ok, norm, 1.0), back)


def on_points(g: Callable) -> Callable:
    """``G(x, y, z, *rest)``: the point function ``g(x, y, z, *rest)`` (written for one
    point: scalar coordinates in, a scalar or a pytree of arrays out) evaluated on
    batches of points by `jax.vmap`.

    x, y and z broadcast to a batch shape S; `rest` (w, params, ...) is shared by every
    point, unbatched. Each output leaf gets S in front of its per-point shape. Every place
    that evaluates a user's function on many points goes through here, so that any
    scalar JAX function works (``jnp.stack([x, y, z]) @ W`` included), and functions
    that broadcast by themselves give the same values as called on arrays (up to float
    rounding where either is compiled: XLA may fuse a * b + c into an FMA)."""
    @functools.wraps(g)
    def G(x, y, z, *rest):
        x, y, z = jnp.broadcast_arrays(x, y, z)
        shape = x.shape
        out = jax.vmap(lambda x, y, z: g(x, y, z, *rest))(
            x.reshape(-1), y.reshape(-1), z.reshape(-1))
        return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), out)
    return G


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def attach_t(g: Callable, t, o, d, w, params, iso, hit):
    """The hit parameter t [P] of rays o + t d on g(x, y, z, w, params) = iso (g a point
    function, evaluated through `on_points`), returned as is; its derivative comes from
    the implicit function theorem: dt = -(dg - diso) / (grad g . d), with dg the change
    of g at the fixed hit point."""
    return t


@attach_t.defjvp
def _attach_t_jvp(g, primals, tangents):
    t, o, d, w, params, iso, hit = primals
    _, do, dd, dw, dparams, diso, _ = tangents
    value = on_points(g)
    partials = on_points(jax.grad(g, argnums=(0, 1, 2)))

    def at(q, w, params):
        return value(q[:, 0], q[:, 1], q[:, 2], w, params)

    q = o + t[:, None] * d
    dq = do + t[:, None] * dd
    _, dg = jax.jvp(at, (q, w, params), (dq, dw, dparams))
    grad = jnp.stack(partials(q[:, 0], q[:, 1], q[:, 2], w, params), axis=-1)
    denom = jnp.sum(grad * d, axis=-1)
    ok = hit & (jnp.abs(denom) > 1e-20) & jnp.isfinite(denom)
    dt = jnp.where(ok, -(dg - diso) / jnp.where(ok, denom, 1.0), 0.0)
    return t, dt
