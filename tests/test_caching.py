"""The identity-keyed cache behind patterns, layouts, band positions and element groupings."""

from __future__ import annotations

import pytest
import torch

from energysim.linalg.caching import IdentityCache


def test_hits_return_the_built_value_and_only_the_same_objects_hit():
    cache: IdentityCache[int] = IdentityCache(capacity=2)
    builds = []

    def build(value: int):
        return lambda: builds.append(value) or value

    a, equal_to_a = torch.arange(3), torch.arange(3)
    assert cache.get((a,), 1, build(10)) == 10
    assert cache.get((a,), 1, build(11)) == 10  # a hit: not built again
    assert cache.get((a,), 2, build(12)) == 12  # another extra key
    assert cache.get((equal_to_a,), 1, build(13)) == 13  # equal contents, another object
    assert builds == [10, 12, 13]


def test_the_least_recently_used_entry_is_dropped_beyond_capacity():
    cache: IdentityCache[str] = IdentityCache(capacity=2)
    a, b, c = object(), object(), object()
    cache.get((a,), None, lambda: "a")
    cache.get((b,), None, lambda: "b")
    cache.get((a,), None, lambda: "rebuilt a")  # a is now the most recent
    cache.get((c,), None, lambda: "c")  # drops b
    assert cache.get((a,), None, lambda: "rebuilt a") == "a"
    assert cache.get((b,), None, lambda: "rebuilt b") == "rebuilt b"


def test_a_capacity_below_one_is_refused():
    with pytest.raises(ValueError, match="capacity"):
        IdentityCache(capacity=0)
