"""Gradients through the implicit step against central finite differences (float64, tight forward
solves) and against the unrolled Newton reference; gradcheck; strict mode; batches; pinning."""

from __future__ import annotations

import pytest
import torch

import energysim as es

TIGHT = 1e-11  # m/s: forward solves far below the finite-difference signal


def beam(
    youngs_modulus: torch.Tensor | float = 2e4, *, pinned: bool = True, actuated: bool = True
) -> es.Scene:
    """A small beam with one end pinned and two actuated spring groups along it."""
    mesh = es.TetMesh.box(size=(0.6, 0.2, 0.2), cells=(3, 1, 1))
    scene = es.Scene(mesh, dt=1 / 30, solver=es.NewtonCG(tol=TIGHT, max_iter=100))
    scene.add(es.NeoHookean(youngs_modulus, 0.3))
    if actuated:
        edges = mesh.edges()
        top = mesh.vertices[edges].mean(dim=1)[:, 1] > 0.1
        scene.add(es.ActuatedSprings(edges, actuators=top.long(), stiffness=300.0, max_contraction=0.3))
    if pinned:
        scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


def loss_after(
    scene: es.Scene, state: torch.Tensor, steps: int, action=None, grad_mode="implicit"
) -> torch.Tensor:
    weights = torch.linspace(-1.0, 1.0, state.shape[-1], dtype=torch.float64)
    for _ in range(steps):
        state = es.timestep(scene, state, action, grad_mode=grad_mode)
    return (weights * state).sum() + 0.5 * (state**2).sum()


def central_difference(function, value: torch.Tensor, direction: torch.Tensor, eps: float) -> float:
    with torch.no_grad():
        return float((function(value + eps * direction) - function(value - eps * direction)) / (2 * eps))


@pytest.mark.parametrize("steps", [1, 10, 50])
def test_gradients_match_central_differences(steps):
    scene = beam()
    velocity = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    velocity[:, 1] = 0.3
    action = torch.tensor([0.4, -0.2], dtype=torch.float64)

    # initial velocity
    v0 = scene.initial_state(velocities=velocity)[scene.num_dofs :].clone().requires_grad_(True)
    x0 = scene.rest_positions.reshape(-1)
    (grad_v,) = torch.autograd.grad(loss_after(scene, torch.cat([x0, v0]), steps, action), v0)
    direction = torch.randn_like(v0)
    fd = central_difference(
        lambda v: loss_after(scene, torch.cat([x0, v]), steps, action), v0.detach(), direction, 1e-3
    )
    assert float(grad_v @ direction) == pytest.approx(fd, rel=1e-5)

    # action
    a = action.clone().requires_grad_(True)
    (grad_a,) = torch.autograd.grad(loss_after(scene, scene.initial_state(velocities=velocity), steps, a), a)
    for j in range(2):
        unit = torch.zeros(2, dtype=torch.float64)
        unit[j] = 1.0
        fd = central_difference(
            lambda b: loss_after(scene, scene.initial_state(velocities=velocity), steps, b),
            action,
            unit,
            1e-3,
        )
        assert float(grad_a[j]) == pytest.approx(fd, rel=1e-5)

    # Young's modulus
    youngs = torch.tensor(2e4, dtype=torch.float64, requires_grad=True)
    stiff = beam(youngs)
    (grad_e,) = torch.autograd.grad(
        loss_after(stiff, stiff.initial_state(velocities=velocity), steps, action), youngs
    )
    fd = central_difference(
        lambda e: loss_after(beam(e), stiff.initial_state(velocities=velocity), steps, action),
        torch.tensor(2e4, dtype=torch.float64),
        torch.tensor(1.0, dtype=torch.float64),
        20.0,
    )
    assert float(grad_e) == pytest.approx(fd, rel=1e-5)


@pytest.mark.parametrize("steps", [1, 10])
def test_implicit_gradients_match_the_unrolled_reference(steps):
    youngs = torch.tensor(2e4, dtype=torch.float64, requires_grad=True)
    scene = beam(youngs)
    v0 = torch.zeros(scene.num_dofs, dtype=torch.float64)
    v0[1::3] = 0.3
    v0.requires_grad_(True)
    action = torch.tensor([0.4, -0.2], dtype=torch.float64, requires_grad=True)
    inputs = (v0, action, youngs)
    grads = {}
    for mode in ("implicit", "unrolled"):
        state = torch.cat([scene.rest_positions.reshape(-1), v0])
        grads[mode] = torch.autograd.grad(loss_after(scene, state, steps, action, grad_mode=mode), inputs)
    for implicit, unrolled in zip(grads["implicit"], grads["unrolled"], strict=True):
        assert torch.allclose(implicit, unrolled, rtol=1e-6, atol=1e-6 * float(unrolled.abs().max()))


def test_every_kind_of_scene_parameter_gets_the_finite_difference_gradient():
    def build(density, gravity, stiffness, rest_scale, poisson):
        mesh = es.TetMesh.box(size=(0.4, 0.2, 0.2), cells=(2, 1, 1))
        scene = es.Scene(mesh, density=density, dt=1 / 30, gravity=gravity, solver=es.NewtonCG(tol=TIGHT))
        scene.add(es.NeoHookean(2e4, poisson))
        edges = mesh.edges()
        rest = (mesh.vertices[edges[:, 1]] - mesh.vertices[edges[:, 0]]).norm(dim=-1) * rest_scale
        scene.add(es.Springs(edges, stiffness=stiffness, rest_length=rest))
        scene.fix([0, 1])
        return scene

    base = {
        "density": torch.tensor(800.0, dtype=torch.float64),
        "gravity": torch.tensor([0.5, -9.81, 0.0], dtype=torch.float64),
        "stiffness": torch.tensor(150.0, dtype=torch.float64),
        "rest_scale": torch.tensor(1.05, dtype=torch.float64),
        "poisson": torch.tensor(0.35, dtype=torch.float64),
    }
    eps = {"density": 0.5, "gravity": 1e-3, "stiffness": 0.1, "rest_scale": 1e-4, "poisson": 1e-4}
    for name in base:
        leaf = base[name].clone().requires_grad_(True)
        scene = build(**{**base, name: leaf})
        loss = loss_after(scene, scene.initial_state(), 5)
        (grad,) = torch.autograd.grad(loss, leaf)
        direction = (
            torch.ones_like(leaf) if leaf.ndim == 0 else torch.tensor([0.3, 1.0, -0.5], dtype=torch.float64)
        )

        def evaluate(value, name=name):
            scene = build(**{**base, name: value})
            return loss_after(scene, scene.initial_state(), 5)

        fd = central_difference(evaluate, base[name], direction, eps[name])
        assert float((grad * direction).sum()) == pytest.approx(fd, rel=1e-5), name


def test_gradcheck_through_one_step():
    scene = beam(actuated=False)
    scene.solver = es.NewtonCG(tol=1e-12, max_iter=100)
    state = scene.initial_state(velocities=0.1 * torch.randn(scene.num_vertices, 3, dtype=torch.float64))
    state.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: es.timestep(scene, s), (state,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_batched_backward_equals_separate_backwards():
    scene = beam()
    velocities = 0.2 * torch.randn(2, scene.num_vertices, 3, dtype=torch.float64)
    states = torch.stack([scene.initial_state(velocities=v) for v in velocities]).requires_grad_(True)
    actions = torch.tensor([[0.5, 0.0], [-0.3, 0.8]], dtype=torch.float64, requires_grad=True)
    out = es.timestep(scene, es.timestep(scene, states, actions), actions)
    weights = torch.randn_like(out)
    grad_states, grad_actions = torch.autograd.grad((weights * out).sum(), (states, actions))
    for b in range(2):
        state = states[b].detach().clone().requires_grad_(True)
        action = actions[b].detach().clone().requires_grad_(True)
        single = es.timestep(scene, es.timestep(scene, state, action), action)
        gs, ga = torch.autograd.grad((weights[b] * single).sum(), (state, action))
        assert torch.allclose(grad_states[b], gs, atol=1e-9)
        assert torch.allclose(grad_actions[b], ga, atol=1e-9)


def test_pinned_vertices_pass_their_position_gradient_through():
    scene = beam(actuated=False)
    state = scene.initial_state().requires_grad_(True)
    out = es.timestep(scene, state)
    pinned = torch.nonzero(scene.fixed).reshape(-1)
    # d x_{n+1} / d x_n = I on pinned vertices, and their velocity stays zero whatever x_n
    x_index = (pinned[:, None] * 3 + torch.arange(3)).reshape(-1)
    (grad,) = torch.autograd.grad(out[x_index].sum(), state, retain_graph=True)
    assert torch.allclose(grad[x_index], torch.ones_like(grad[x_index]))
    v_index = x_index + scene.num_dofs
    (grad_v,) = torch.autograd.grad(out[v_index].sum(), state)
    assert float(grad_v.abs().max()) < 1e-12


def test_strict_mode_refuses_to_differentiate_an_unconverged_step_and_the_default_warns():
    scene = beam(actuated=False)
    velocity = torch.randn(scene.num_vertices, 3, dtype=torch.float64)
    state = scene.initial_state(velocities=velocity).requires_grad_(True)
    scene.solver = es.NewtonCG(tol=1e-14, max_iter=1)
    with pytest.warns(es.ConvergenceWarning):
        out = es.timestep(scene, state)
    with pytest.warns(es.ConvergenceWarning, match="differentiating an unconverged step"):
        out.sum().backward()
    scene.solver = es.NewtonCG(tol=1e-14, max_iter=1, strict=True)
    with pytest.raises(es.ConvergenceError):
        es.timestep(scene, state)


def test_rollout_with_checkpoints_gives_the_same_gradient():
    scene = beam()
    actions = (0.5 * torch.randn(12, 2, dtype=torch.float64)).requires_grad_(True)
    grads = []
    for every in (0, 4):
        states = es.rollout(scene, scene.initial_state(), actions, checkpoint_every=every)
        assert states.shape == (13, 2 * scene.num_dofs)
        (grad,) = torch.autograd.grad(states[-1].square().sum() + states[6].sum(), actions)
        grads.append(grad)
    assert torch.allclose(grads[0], grads[1], rtol=1e-9, atol=1e-12)


def test_the_gradient_does_not_depend_on_which_optimizer_solved_the_step():
    youngs = torch.tensor(2e4, dtype=torch.float64, requires_grad=True)
    scene = beam(youngs)
    action = torch.tensor([0.4, -0.2], dtype=torch.float64, requires_grad=True)
    velocity = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    velocity[:, 1] = 0.3
    grads = []
    # torch's L-BFGS stops near 5e-8 m/s here (its line search reaches rounding): ask for what it reaches
    for solver in (es.NewtonCG(tol=1e-10), es.LBFGS(tol=2e-7, max_iter=5000)):
        scene.solver = solver
        state = scene.initial_state(velocities=velocity)
        grads.append(torch.autograd.grad(loss_after(scene, state, 3, action), (youngs, action)))
    for newton, lbfgs in zip(*grads, strict=True):
        assert torch.allclose(newton, lbfgs, rtol=1e-6, atol=1e-12)
