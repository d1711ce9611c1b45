"""Bounded caches of results derived from a user's function, all emptied by
`jaxiso.clear_caches`.

A cache holds the function object itself in its keys (never a bare `id`, which Python
reuses once the function is gone; an unhashable callable, such as an equinox module
holding arrays, is keyed by identity through a stand-in that holds it), keeps at most
`size` entries (the oldest goes first) and memoises only deterministic results: what a
key maps to is what computing it again would give, so a cache saves time and never
changes an answer.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

from .._core import ByIdentity

__all__ = ["BoundedCache", "clear_caches", "CACHES"]

CACHES: list = []  # every BoundedCache made, for clear_caches


class BoundedCache:
    """At most `size` results of `make()` by key (least recently used out first)."""

    def __init__(self, name: str, size: int):
        self.name = name
        self.size = size
        self._entries: OrderedDict = OrderedDict()
        CACHES.append(self)

    def get(self, key: Hashable, make: Callable):
        """The result for `key`, made by ``make()`` once; a key that stays unhashable
        (`_hashable`), or None, is never cached."""
        try:
            key = None if key is None else _hashable(key)
        except TypeError:  # unhashable: compute every time
            return make()
        if key is not None and key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key]
        value = make()
        if key is not None:
            self._entries[key] = value
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()


def _hashable(key):
    """key, with unhashable callables in it (nested in tuples) keyed by identity: a
    module's call is its code and its held arrays, which JAX keeps immutable. Any other
    unhashable part (a mutable numpy array) raises TypeError."""
    try:
        hash(key)
        return key
    except TypeError:
        pass
    if isinstance(key, tuple):
        return tuple(_hashable(k) for k in key)
    if callable(key):
        return ByIdentity(key)
    raise TypeError(f"unhashable cache key part {type(key).__name__}")


def clear_caches() -> None:
    """Empty every jaxiso cache of derived results (arithmetic choices, sign grids,
    compiled grid enclosures). JAX's own compilation caches are `jax.clear_caches`."""
    for cache in CACHES:
        cache.clear()
