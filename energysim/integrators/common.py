"""What the steps of every integrator share: the action's checks, the acceleration −M⁻¹∇E, which
entries touch an obstacle, and the energies of a state that the energy-gain checks compare."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm, limits_steps
from energysim.energies.muscles import check_action_width
from energysim.model.scene import Scene
from energysim.objective import compiled as compiled_functions
from energysim.objective.objective import Objective
from energysim.solvers import Solver


def check_action(
    action: Tensor | None, batch: int, scene: Scene, like: Tensor | None = None
) -> Tensor | None:
    """`action` as `[batch, a]`, in the dtype and on the device of `like` (the state) where given:
    a conversion autograd records, so the action's own tensor is neither changed nor cut off. Its
    width and type are checked against `scene`'s actuated terms first (`check_action_width`)."""
    if action is None:
        return None
    if not isinstance(action, Tensor):
        action = torch.as_tensor(action)
    # before the conversion, which would drop a complex action's imaginary part
    check_action_width(scene.terms, action)
    if like is not None:
        action = action.to(dtype=like.dtype, device=like.device)
    if action.ndim == 1:
        action = action.expand(batch, -1)
    if action.ndim != 2 or action.shape[0] != batch:
        raise ValueError(f"action must have shape [a] or [{batch}, a], got {tuple(action.shape)}")
    if not torch.isfinite(action).all():
        raise ValueError("action has non-finite entries")
    return action


def any_limits_steps(terms: list[EnergyTerm]) -> bool:
    return any(limits_steps(term) for term in terms)




def acceleration_of(
    scene: Scene,
    x: Tensor,
    action: Tensor | None,
    differentiable: bool,
    solver: Solver,
    terms: list[EnergyTerm] | None = None,
) -> Tensor:
    """a = −M⁻¹∇E(x) over `terms` (default the scene's), zero on pinned vertices, shape `[B, n, d]`,
    in m/s².

    With `differentiable` the gradient keeps its graph, so the step's backward reaches x, the
    action and the parameters through it too; otherwise it is evaluated as `solver` evaluates its
    objectives (compiled where it compiles)."""
    terms = list(scene.terms) if terms is None else terms
    if differentiable:
        with torch.enable_grad():
            at = x if x.requires_grad else x.detach().requires_grad_(True)
            energy = sum(term(at, action) for term in terms)
            (gradient,) = torch.autograd.grad(energy.sum(), at, create_graph=True)
    else:
        objective = solver.prepare(Objective(terms, scene.free, scene.dt / scene.vertex_mass, action))
        _, gradient = objective.energy_and_gradient(x)
    scale = scene.free.to(x.dtype) / scene.vertex_mass
    return -gradient * scale[:, None]




def touching(scene: Scene, x: Tensor, action: Tensor | None) -> Tensor:
    """Which batch entries have a vertex within an obstacle's barrier distance, `[B]` bool: the
    barrier energy is exactly zero farther away."""
    with torch.no_grad():
        barriers = [term for term in scene.terms if any_limits_steps([term])]
        if not barriers:
            return torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        return sum(term(x.detach(), action) for term in barriers) > 0


# Relative rounding allowed in the energy comparison of `gains_energy` (its terms are summed in
# float64 from parts up to the scale of the largest term).
ENERGY_ROUNDING = 1e-9


def state_energies(
    scene: Scene,
    x: Tensor,
    v: Tensor,
    action: Tensor | None,
    compiled: bool,
    terms: list[EnergyTerm] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """At the step's action, `[B]` each in J: the total (kinetic plus the potential `terms`, default
    the scene's), the energy of motion and deformation (kinetic plus the nonlinear terms'
    magnitudes: gravity's value depends on where the origin is), and the sum of every part's
    magnitude (the scale of the total's rounding). With `compiled`, the terms' values come from one
    compiled call."""
    terms = list(scene.terms) if terms is None else terms
    with torch.no_grad():
        kinetic = 0.5 * (scene.vertex_mass[:, None] * v.detach() ** 2).sum(dim=(-1, -2))
        values = compiled_functions.term_energies(terms, action, x.detach()) if compiled else None
        if values is None:
            values = torch.stack([term(x.detach(), action) for term in terms])
        total = kinetic + values.sum(dim=0)
        motion = kinetic + sum(
            value.abs() for value, term in zip(values, terms, strict=True) if not term.is_linear
        )
        return total, motion, kinetic + values.abs().sum(dim=0)
