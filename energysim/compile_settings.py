"""The Dynamo settings the package's compiled functions run under, set around each call only, so that a
user's own `torch.compile`d code keeps torch's defaults."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

# Graphs Dynamo may keep per compiled function before it runs the function eagerly. Torch's default
# (8) fits one scene: a compacting batch of 64 worms leaves the line search's trial with eight graphs
# (the whole batch, one row, two to seven rows, more; most of them twice, with the search direction a
# view of the linear solve's storage and a tensor of its own, which Dynamo tells apart). A second
# scene in the same process (a quadruped after the worm, a float32 env beside a float64 one) would
# then get no graphs of its own and run those evaluations eagerly, several times slower, with only a
# log line to tell. The derived kernels compile with static shapes, one graph per element count.
RECOMPILE_LIMIT = 64
# the setting's name since torch 2.6; `cache_size_limit` before
_LIMIT_NAME = next(
    (name for name in ("recompile_limit", "cache_size_limit") if hasattr(torch._dynamo.config, name)), None
)
# A term's float attributes (a barrier's d̂, a friction's ε_v) stay constants of the graphs, guarded,
# so that another value compiles graphs of its own. By default Dynamo makes such a float an input
# of the graph once it has met a second value, and in torch 2.13 those graphs kept the value they
# were first traced with in some operations (`torch.where(t < d, t, d)`, `full_like(t, d)`): the
# barrier's energy of one scene evaluated with the d̂ of another, so two compiled environments with
# different grounds in one process failed their solves.
_SPECIALIZES_FLOATS = hasattr(torch._dynamo.config, "specialize_float")


# How many `package_compile_settings` scopes are open: an inner one finds the settings made and
# costs nothing, so that a whole step holds them once instead of once per compiled call
_DEPTH = [0]


@contextmanager
def package_compile_settings() -> Iterator[None]:
    """Floats specialized and `RECOMPILE_LIMIT` graphs per function while the scope is open.

    Set and restored by hand: `torch._dynamo.config.patch` costs 0.12 ms a call, 6 ms a step of 64
    worms (some 50 calls). Scopes nest: `energysim.integrators.step` opens one around a whole step,
    so that the compiled calls within it (each in a scope of its own) skip reading and writing
    Dynamo's config, some 10 µs a call."""
    if _DEPTH[0]:
        yield
        return
    config = torch._dynamo.config
    wanted: dict[str, object] = {}
    if _SPECIALIZES_FLOATS and not config.specialize_float:
        wanted["specialize_float"] = True
    if _LIMIT_NAME is not None and getattr(config, _LIMIT_NAME) < RECOMPILE_LIMIT:
        wanted[_LIMIT_NAME] = RECOMPILE_LIMIT
    saved = {name: getattr(config, name) for name in wanted}
    for name, value in wanted.items():
        setattr(config, name, value)
    _DEPTH[0] += 1
    try:
        yield
    finally:
        _DEPTH[0] -= 1
        for name, value in saved.items():
            setattr(config, name, value)
