"""A step changes nothing it is given; a term belongs to one scene; indices mean what they say."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import energysim as es

G = 9.81


def bar_mesh() -> es.SimplexMesh:
    return es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(3, 1, 1))


def clamped_bar(integrator: str = "implicit_euler", youngs_modulus: float | torch.Tensor = 1e5) -> es.Scene:
    """A bar clamped at x = 0, sagging under gravity, with a ground below it and a spring."""
    mesh = bar_mesh()
    scene = es.Scene(mesh, solver=es.NewtonCG(tol=1e-4), integrator=integrator)
    scene.add(es.NeoHookean(youngs_modulus, 0.3))
    scene.add(es.Springs(edges=[[0, mesh.num_vertices - 1]], stiffness=10.0))
    scene.add(es.Ground(-0.5))
    scene.fix(mesh.vertices[:, 0] < 1e-9)
    return scene


def snapshot(scene: es.Scene) -> dict[str, torch.Tensor]:
    """Every buffer and parameter, persistent or not, by name (cloned)."""
    tensors = dict(scene.named_buffers(remove_duplicate=False))
    tensors.update(dict(scene.named_parameters(remove_duplicate=False)))
    return {name: tensor.detach().clone() for name, tensor in tensors.items()}


def assert_unchanged(scene: es.Scene, before: dict[str, torch.Tensor]) -> None:
    after = snapshot(scene)
    assert after.keys() == before.keys()
    for name, tensor in before.items():
        assert after[name].dtype == tensor.dtype and after[name].device == tensor.device, name
        assert torch.equal(after[name], tensor), name


@pytest.mark.parametrize("integrator", ["implicit_euler", "tr_bdf2"])
def test_steps_in_either_dtype_leave_every_scene_tensor_and_the_state_bitwise_unchanged(integrator):
    scene = clamped_bar(integrator)
    terms, solver = list(scene.terms), scene.solver
    before = snapshot(scene)
    state64 = scene.initial_state(velocities=torch.full((scene.num_vertices, 3), 0.1, dtype=torch.float64))
    for state in (state64.float(), state64, state64[None].float().expand(2, -1).clone()):
        kept, version = state.clone(), state._version
        new = es.timestep(scene, state)
        assert new.dtype == state.dtype and new.shape == state.shape
        assert torch.equal(state, kept) and state._version == version
        assert_unchanged(scene, before)
    es.rollout(scene, state64.float(), steps=2)
    es.solve_static(scene, scene.rest_positions.float(), solver=es.NewtonCG(tol=1e-2))
    assert_unchanged(scene, before)
    assert list(scene.terms) == terms and scene.solver is solver


def test_a_float64_step_after_a_float32_step_is_exactly_a_fresh_scenes_step():
    used, fresh = clamped_bar(), clamped_bar()
    state = used.initial_state(velocities=torch.full((used.num_vertices, 3), -0.2, dtype=torch.float64))
    es.timestep(used, state.float())
    assert torch.equal(es.timestep(used, state), es.timestep(fresh, state))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_half_precision_state_is_refused_with_its_dtype_and_changes_nothing(dtype):
    scene = clamped_bar()
    before = snapshot(scene)
    state = scene.initial_state()
    with pytest.raises(TypeError, match=str(dtype)):
        es.timestep(scene, state.to(dtype))
    with pytest.raises(TypeError, match=str(dtype)):
        es.solve_static(scene, scene.rest_positions.to(dtype))
    assert_unchanged(scene, before)
    assert torch.equal(es.timestep(scene, state), es.timestep(clamped_bar(), state))


def test_the_converted_copy_follows_changes_made_to_the_scene():
    # E doubled in place and dt changed after a float32 step: the next float32 step sees both,
    # exactly as a scene built with them does
    scene, rebuilt = clamped_bar(), clamped_bar(youngs_modulus=2e5)
    scene.dt = rebuilt.dt = 1 / 30
    state = scene.initial_state().float()
    es.timestep(scene, state)
    with torch.no_grad():
        scene.terms[1].youngs_modulus.mul_(2.0)
    assert torch.equal(es.timestep(scene, state), es.timestep(rebuilt, state))


def test_a_float32_steps_gradient_reaches_the_float64_youngs_modulus():
    def tip_drop_gradient(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        youngs_modulus = torch.tensor(1e5, dtype=torch.float64, requires_grad=True)
        scene = clamped_bar(youngs_modulus=youngs_modulus)
        scene.solver = es.NewtonCG(tol=1e-4 if dtype == torch.float32 else 1e-10)
        final = es.rollout(scene, scene.initial_state().to(dtype), steps=3)[-1]
        x, _ = scene.split_state(final)
        x[0, :, 1].sum().backward()
        return youngs_modulus, youngs_modulus.grad

    modulus64, reference = tip_drop_gradient(torch.float64)
    modulus32, gradient = tip_drop_gradient(torch.float32)
    assert gradient is not None and gradient.dtype == torch.float64 and modulus32.dtype == torch.float64
    # a stiffer bar sags less: the sum of heights grows with E
    assert float(reference) > 0
    # float32 rounding and the 1e-4 m/s tolerance move the gradient by a few 1e-5 relative
    assert float(gradient) == pytest.approx(float(reference), rel=1e-2)


def test_a_term_belongs_to_one_scene():
    mesh = bar_mesh()
    first, second = es.Scene(mesh), es.Scene(es.TetMesh.box(size=(2.0, 0.1, 0.1), cells=(4, 1, 1)))
    elastic = first.add(es.NeoHookean(1e5, 0.3))
    with pytest.raises(ValueError, match="another scene.*construct a new"):
        second.add(elastic)
    with pytest.raises(ValueError, match="already in this scene"):
        first.add(elastic)
    assert elastic.scene is first and len(first.terms) == 2 and len(second.terms) == 1
    # the refused adds left the term bound to its own mesh: it steps as on a fresh scene
    fresh = es.Scene(mesh)
    fresh.add(es.NeoHookean(1e5, 0.3))
    state = first.initial_state()
    assert torch.equal(es.timestep(first, state), es.timestep(fresh, state))
    assert second.add(es.NeoHookean(1e5, 0.3)).scene is second


@pytest.mark.parametrize(
    "make_pins",
    [
        lambda left: left,  # a torch mask
        lambda left: left.numpy(),  # a NumPy mask
        lambda left: torch.nonzero(left).reshape(-1).to(torch.int32),
        lambda left: np.flatnonzero(left.numpy()).astype(np.int16),
        lambda left: torch.nonzero(left).reshape(-1).tolist(),
        lambda left: torch.nonzero(left).reshape(-1).double(),  # whole numbers as floats
    ],
)
def test_fix_pins_exactly_the_given_vertices_and_the_others_fall_freely(make_pins):
    mesh = bar_mesh()
    scene = es.Scene(mesh, solver=es.NewtonCG(tol=1e-10))
    left = mesh.vertices[:, 0] < 1e-9
    assert 0 < int(left.sum()) < 5  # the mask is not a list of the indices 0 and 1
    scene.fix(make_pins(left))
    assert torch.equal(scene.fixed, left)
    steps = 4
    states = es.rollout(scene, scene.initial_state(), steps=steps)
    x, _ = scene.split_state(states[-1])
    x = x[0]
    assert torch.equal(x[left], mesh.vertices[left])
    # no elasticity: free vertices follow implicit Euler's free fall, y_n = y_0 − h² g n(n+1)/2
    drop = scene.dt**2 * G * steps * (steps + 1) / 2
    expected = mesh.vertices[~left, 1] - drop
    assert torch.allclose(x[~left, 1], expected, rtol=0, atol=1e-9 * drop)
    assert torch.equal(x[~left][:, [0, 2]], mesh.vertices[~left][:, [0, 2]])


@pytest.mark.parametrize(
    "bad, message",
    [
        ([1.7], r"vertex_indices must hold whole numbers.*\[1\.7\]"),
        (torch.tensor([0.0, 2.5]), r"entries \[1\] are \[2\.5\]"),
        ([float("nan")], "whole numbers"),
        ([True, 2], "mixes bools with integers"),
        (torch.ones(3, dtype=torch.bool), r"mask of shape \(3,\).*one entry per vertex, shape \[16\]"),
        ([16], r"vertex indices \[16\] outside \[0, 16\)"),
        ([-1], r"vertex indices \[-1\] outside"),
    ],
)
def test_bad_vertex_indices_in_fix_are_refused_by_name(bad, message):
    scene = es.Scene(bar_mesh())
    with pytest.raises(ValueError, match=message):
        scene.fix(bad)
    assert not scene.fixed.any()


def test_fractional_indices_are_refused_wherever_a_term_takes_them():
    with pytest.raises(ValueError, match=r"edges must hold whole numbers.*\[1\.7\]"):
        es.Springs(edges=[[0.0, 1.7]])
    with pytest.raises(ValueError, match="actuators must hold whole numbers"):
        es.ActuatedSprings(edges=[[0, 1]], actuators=[0.5])
    with pytest.raises(ValueError, match="vertices must hold integer indices.*boolean"):
        es.Ground(0.0, vertices=torch.ones(16, dtype=torch.bool))
    with pytest.raises(ValueError, match="vertices must hold whole numbers"):
        es.Ground(0.0, vertices=[0.5])
    with pytest.raises(TypeError, match="edges must hold integer indices"):
        es.Springs(edges=[["a", "b"]])
    # whole numbers in a float array are the same springs as integers
    scene = es.Scene(bar_mesh())
    springs = scene.add(es.Springs(edges=np.array([[0.0, 5.0]])))
    assert springs.element_vertices.tolist() == [[0, 5]]


def test_a_tiny_density_is_simulated_in_float64_and_refused_in_float32_with_the_reason():
    mesh = bar_mesh()
    scene = es.Scene(mesh, density=1e-300)
    volume = mesh.vertex_rest_volume().to(torch.float64)
    assert torch.equal(scene.vertex_mass, 1e-300 * volume)
    # free fall is independent of the mass: one implicit-Euler step from rest gives v = −g h
    _, v = scene.split_state(es.timestep(scene, scene.initial_state()))
    assert torch.allclose(v[0, :, 1], torch.full_like(v[0, :, 1], -G * scene.dt), rtol=1e-9)
    with pytest.raises(ValueError, match="vertex_mass cannot be represented in torch.float32.*underflow"):
        es.timestep(scene, scene.initial_state().float())
    with pytest.raises(ValueError, match="underflow to 0 kg in float64"):
        es.Scene(mesh, density=5e-324)
    with pytest.raises(ValueError, match="density must be finite and > 0"):
        es.Scene(mesh, density=0.0)


@pytest.mark.parametrize("batch_size", [0, -2, 2.0, True, "3"])
def test_initial_state_refuses_batch_sizes_that_are_not_positive_integers(batch_size):
    scene = es.Scene(bar_mesh())
    with pytest.raises(ValueError, match=f"batch_size must be an integer >= 1 or None, got {batch_size!r}"):
        scene.initial_state(batch_size=batch_size)


def test_initial_state_takes_any_integer_batch_size():
    scene = es.Scene(bar_mesh())
    batch = scene.initial_state(batch_size=np.int64(3))
    assert batch.shape == (3, 2 * scene.num_dofs)
    assert torch.equal(batch[2], scene.initial_state())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_cuda_step_leaves_the_scene_on_the_cpu_and_agrees_with_it():
    scene = clamped_bar()
    scene.solver = es.NewtonCG(tol=1e-10)
    before = snapshot(scene)
    state = scene.initial_state(velocities=torch.full((scene.num_vertices, 3), 0.1, dtype=torch.float64))
    on_gpu = es.timestep(scene, state.cuda())
    assert on_gpu.device.type == "cuda"
    assert_unchanged(scene, before)
    # the same arithmetic up to the order of reductions
    torch.testing.assert_close(on_gpu.cpu(), es.timestep(scene, state), rtol=0, atol=1e-9)


def test_an_action_in_another_dtype_is_used_in_the_states_and_left_as_it_is():
    mesh = bar_mesh()
    scene = es.Scene(mesh, gravity=None)
    scene.add(es.ActuatedSprings(edges=[[0, mesh.num_vertices - 1]], actuators=[0], stiffness=100.0))
    state = scene.initial_state()
    action = torch.tensor([0.5], dtype=torch.float32, requires_grad=True)
    new = es.timestep(scene, state, action)
    assert new.dtype == torch.float64 and action.dtype == torch.float32
    assert torch.equal(new, es.timestep(scene, state, action.detach().double()))
    x, _ = scene.split_state(new)
    x[0, -1, 0].backward()
    # contracting the spring pulls its far end towards its near one
    assert action.grad is not None and action.grad.dtype == torch.float32 and float(action.grad[0]) < 0


@pytest.mark.parametrize(
    "arguments, message",
    [
        ({"steps": 2.5}, "steps must be an integer >= 0, got 2.5"),
        ({"steps": -1}, "steps must be an integer >= 0, got -1"),
        ({"steps": True}, "steps must be an integer >= 0, got True"),
        ({"steps": 2, "checkpoint_every": 1.5}, "checkpoint_every must be an integer >= 0, got 1.5"),
        ({"actions": torch.zeros(3)}, r"actions must have shape \[T, a\] or \[T, B, a\], got \(3,\)"),
    ],
)
def test_rollout_refuses_step_counts_that_are_not_counts(arguments, message):
    scene = es.Scene(bar_mesh())
    with pytest.raises(ValueError, match=message):
        es.rollout(scene, scene.initial_state(), **arguments)
