"""The Dynamo settings around the package's compiled calls: a function keeps a graph per variant
well past torch's default of 8, and the user's settings come back after each call."""

import types

import torch

from energysim.compile_settings import RECOMPILE_LIMIT, package_compile_settings


def _graphs_for_sizes(sizes: range, settings: bool) -> int:
    compiled_graphs = []

    def counting_backend(graph, example_inputs):
        compiled_graphs.append(graph)
        return graph.forward

    def scale(x: torch.Tensor) -> torch.Tensor:
        return 2.0 * x

    # Dynamo keeps its graphs per code object: a fresh one per call starts with none
    fresh = types.FunctionType(scale.__code__.replace(co_name=f"scale_{settings}"), globals())
    function = torch.compile(fresh, backend=counting_backend, dynamic=False)
    for size in sizes:
        x = torch.ones(size)
        if settings:
            with package_compile_settings():
                result = function(x)
        else:
            result = function(x)
        assert torch.equal(result, 2.0 * x)  # compiled or not, the same values
    return len(compiled_graphs)


def test_a_package_function_keeps_a_graph_for_each_of_many_shapes():
    sizes = range(1, 13)  # 12 static shapes: 12 graphs, where torch's default stops at 8
    assert RECOMPILE_LIMIT >= len(sizes)
    assert _graphs_for_sizes(sizes, settings=True) == len(sizes)


def test_outside_the_package_calls_torch_defaults_hold():
    config = torch._dynamo.config
    before = (config.recompile_limit, config.specialize_float)
    assert _graphs_for_sizes(range(1, 13), settings=False) == min(12, config.recompile_limit)
    with package_compile_settings():
        assert config.recompile_limit == RECOMPILE_LIMIT
        assert config.specialize_float
    assert (config.recompile_limit, config.specialize_float) == before


def test_the_settings_are_restored_when_the_call_raises():
    config = torch._dynamo.config
    before = config.recompile_limit
    try:
        with package_compile_settings():
            raise RuntimeError("a failing compiled call")
    except RuntimeError:
        pass
    assert config.recompile_limit == before


def test_nested_scopes_hold_the_settings_until_the_outermost_closes():
    # a step holds the settings once around all its compiled calls, each in a scope of its own
    config = torch._dynamo.config
    before = (config.recompile_limit, config.specialize_float)
    with package_compile_settings():
        with package_compile_settings():
            assert config.recompile_limit == RECOMPILE_LIMIT
        assert config.recompile_limit == RECOMPILE_LIMIT
        assert config.specialize_float
    assert (config.recompile_limit, config.specialize_float) == before
