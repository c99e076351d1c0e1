"""A small least-recently-used cache keyed by the identity of the objects a value is built from.

Sparsity patterns, level layouts, band positions and element groupings are derived from index
tensors that live as long as their scene, and they are asked for every Newton iteration. Hashing a
tensor's contents each time would cost more than the lookup saves, so the key is the tensors'
`id`. Each entry holds references to those objects: an identity cannot be reused by another object
while its entry lives, so a hit always means the same objects.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from typing import Generic, TypeVar

Value = TypeVar("Value")


class IdentityCache(Generic[Value]):
    """The `capacity` most recently used values, each keyed by the identities of its source objects
    and a hashable `extra` (sizes, versions: whatever else the value depends on)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._entries: OrderedDict[tuple, tuple[tuple[object, ...], Value]] = OrderedDict()

    def get(self, sources: Sequence[object], extra: Hashable, build: Callable[[], Value]) -> Value:
        """The value for `sources` and `extra`, built by `build()` on a miss."""
        key = (tuple(id(source) for source in sources), extra)
        if key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key][1]
        value = build()
        self._entries[key] = (tuple(sources), value)
        if len(self._entries) > self.capacity:
            self._entries.popitem(last=False)
        return value
