"""One implicit-Euler step as a minimisation, and quasi-static equilibrium.

x_{n+1} = argmin_x ½h⁻²‖x − (x_n + h v_n)‖²_M + Σ_i E_i(x),   v_{n+1} = (x_{n+1} − x_n)/h.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.derivatives import energy_and_gradient
from energysim.energies.base import EnergyTerm
from energysim.implicit import ImplicitStep, differentiable_parameters, step_terms, unrolled_step
from energysim.objective import Objective
from energysim.optim import Solver, SolverResult
from energysim.scene import Scene


@dataclass(frozen=True)
class StepResult:
    """A new state and the statistics of the solve that produced it."""

    state: Tensor
    stats: SolverResult


def _match_scene(scene: Scene, like: Tensor) -> None:
    # device and dtype follow the state: move the scene's buffers the first time they differ
    if scene.vertex_mass.dtype != like.dtype or scene.vertex_mass.device != like.device:
        scene.to(dtype=like.dtype, device=like.device)


def _check_action(action: Tensor | None, batch: int) -> Tensor | None:
    if action is None:
        return None
    if not isinstance(action, Tensor):
        action = torch.as_tensor(action)
    if action.ndim == 1:
        action = action.expand(batch, -1)
    if action.ndim != 2 or action.shape[0] != batch:
        raise ValueError(f"action must have shape [a] or [{batch}, a], got {tuple(action.shape)}")
    if not torch.isfinite(action).all():
        raise ValueError("action has non-finite entries")
    return action


def _limits_steps(terms: list[EnergyTerm]) -> bool:
    return any(type(term).max_step is not EnergyTerm.max_step for term in terms)


def _warm_start(objective: Objective, predicted: Tensor, x_prev: Tensor, dt: float) -> Tensor:
    """Where the solver starts, per batch entry; `objective` is the whole step objective.

    Without obstacles: the inertial prediction x_n + h v_n plus the displacement the linear terms
    (gravity) alone would cause in one step, h² M⁻¹ f, which saves a Newton iteration. With
    obstacles every candidate is first cut back along the way from x_n to the largest fraction
    every term allows (`max_step`, which also refuses a state that starts inside an obstacle), and
    x_n itself joins them: the one of lowest energy wins. A body resting on the ground then starts
    where it rests, not pushed into the barrier by a step of free fall.
    """
    candidates = [predicted]
    linear = [term for term in objective.terms if term.is_linear]
    if linear:
        _, gradient = energy_and_gradient(
            lambda y: sum(term(y, objective.action) for term in linear), predicted
        )
        shift = (dt * objective.residual_scale[:, None] * objective.free[:, None]) * gradient
        candidates.insert(0, predicted - shift)
    if not _limits_steps(list(objective.terms)):
        return candidates[0]
    best, best_energy = x_prev, objective.energy(x_prev)
    for candidate in candidates:
        motion = candidate - x_prev
        candidate = x_prev + objective.max_step(x_prev, motion)[:, None, None] * motion
        energy = objective.energy(candidate)
        better = energy < best_energy
        best = torch.where(better[:, None, None], candidate, best)
        best_energy = torch.where(better, energy, best_energy)
    return best


GRAD_MODES = ("implicit", "unrolled")


def step(
    scene: Scene,
    state: Tensor,
    action: Tensor | None = None,
    solver: Solver | None = None,
    *,
    grad_mode: str = "implicit",
    adjoint_rtol: float = 1e-10,
) -> StepResult:
    """Advance `state` by one implicit-Euler step of `scene.dt` and report the solve.

    The step is differentiable in `state`, `action` and every scene tensor that requires grad
    (Young's modulus, Poisson's ratio, spring stiffness and rest length, masses, gravity). With
    `grad_mode="implicit"` backward solves one linear system at the solution (implicit function
    theorem) and keeps nothing of the optimizer's iterations; `"unrolled"` records Newton
    iterations instead (memory grows with them; a reference for checks). A solver with
    `strict=True` refuses to differentiate a step that did not converge; otherwise backward warns.

    Args:
        scene: the model.
        state: `[x.flatten(), v.flatten()]`, shape `[2·num_dofs]` or `[B, 2·num_dofs]`, in m and m/s.
        action: shape `[a]` or `[B, a]`, or None.
        solver: overrides `scene.solver` for this step.
        grad_mode: "implicit" or "unrolled".
        adjoint_rtol: relative tolerance of the adjoint CG solve in backward.

    Returns:
        the new state (same shape, device and dtype as `state`) and the solver's statistics.
    """
    if grad_mode not in GRAD_MODES:
        raise ValueError(f"grad_mode must be one of {GRAD_MODES}, got {grad_mode!r}")
    x_prev, v_prev = scene.split_state(state)
    if not torch.isfinite(state).all():
        raise ValueError("state has non-finite entries")
    _match_scene(scene, state)
    action = _check_action(action, x_prev.shape[0])
    solver = solver or scene.solver
    parameters = differentiable_parameters([scene])
    wants_grad = torch.is_grad_enabled() and (
        state.requires_grad or (action is not None and action.requires_grad) or bool(parameters)
    )

    def solve() -> SolverResult:
        xp, vp = x_prev.detach(), v_prev.detach()
        free = scene.free[:, None].to(xp.dtype)
        predicted = xp + scene.dt * vp * free
        with torch.no_grad():
            terms = step_terms(list(scene.terms), scene.vertex_mass.detach(), scene.dt, xp, vp, scene.free)
            objective = Objective(
                terms=terms,
                free=scene.free,
                residual_scale=scene.dt / scene.vertex_mass.detach(),
                action=None if action is None else action.detach(),
            )
            start = _warm_start(objective, predicted, xp, scene.dt)
            terms[0].anchor = start  # the inertia term
            objective.anchor = start
            return solver.minimize(objective, start)

    if not wants_grad:
        stats = solve()
        x_next = stats.x
    elif grad_mode == "implicit":
        context = {
            "run": solve,
            "terms": list(scene.terms),
            "vertex_mass": scene.vertex_mass,
            "free": scene.free,
            "dt": scene.dt,
            "strict": solver.strict,
            "adjoint_rtol": adjoint_rtol,
            "direct_max_dofs": getattr(solver, "direct_max_dofs", 600),
        }
        x_next = ImplicitStep.apply(context, x_prev, v_prev, action, *parameters)
        stats = context["result"]
    else:
        x_next, iterations, residual = unrolled_step(
            list(scene.terms),
            scene.vertex_mass,
            scene.dt,
            x_prev,
            v_prev,
            scene.free,
            action,
            tol=solver.tol,
            max_iter=solver.max_iter,
        )
        stats = solver.finish_unrolled(x_next, residual, iterations)
    v_next = (x_next - x_prev) / scene.dt
    new_state = torch.cat([x_next.reshape(x_next.shape[0], -1), v_next.reshape(v_next.shape[0], -1)], dim=-1)
    return StepResult(state=new_state.reshape(state.shape), stats=stats)


def timestep(
    scene: Scene, state: Tensor, action: Tensor | None = None, *, grad_mode: str = "implicit"
) -> Tensor:
    """The new state after one step, like `nimble.timestep(world, state, action)`; see `step`.

    Differentiable: `loss.backward()` through any number of steps reaches the initial state, the
    actions and the scene's parameters that require grad.
    """
    return step(scene, state, action, grad_mode=grad_mode).state


def solve_static(
    scene: Scene, x0: Tensor | None = None, action: Tensor | None = None, solver: Solver | None = None
) -> StepResult:
    """Quasi-static equilibrium: argmin of the scene's potential terms (no inertia).

    Fixed vertices stay where `x0` puts them. The stopping rule is the same velocity residual,
    h M⁻¹ ∇E with h = `scene.dt`. Without enough fixed vertices the minimum is not unique
    (rigid motions) or does not exist (gravity with nothing fixed): the solve then reports
    that it did not converge.

    Args:
        x0: initial positions, shape `[n, d]` or `[B, n, d]`, in m; default the rest positions.

    Returns:
        `StepResult` whose `state` holds the equilibrium positions, shaped like `x0`.
    """
    x0 = scene.rest_positions if x0 is None else x0
    if not isinstance(x0, Tensor):
        x0 = torch.as_tensor(x0, dtype=scene.rest_positions.dtype)
    if x0.shape[-2:] != (scene.num_vertices, scene.dim) or x0.ndim not in (2, 3):
        raise ValueError(
            f"x0 must have shape [{scene.num_vertices}, {scene.dim}] or [B, ...], got {tuple(x0.shape)}"
        )
    _match_scene(scene, x0)
    batched = x0.reshape(-1, scene.num_vertices, scene.dim).detach()
    objective = Objective(
        terms=list(scene.terms),
        free=scene.free,
        residual_scale=scene.dt / scene.vertex_mass,
        action=_check_action(action, batched.shape[0]),
        anchor=batched,
    )
    result = (solver or scene.solver).minimize(objective, batched)
    return StepResult(state=result.x.reshape(x0.shape), stats=result)
