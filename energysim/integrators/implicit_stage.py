"""One implicit-Euler solve, the building block of every implicit integrator: where the solver
starts (`warm_start`) and the differentiable argmin of one stage (`stage`)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.integrators.adjoint import ImplicitStep, step_terms, unrolled_step
from energysim.integrators.common import any_limits_steps
from energysim.model.scene import Scene
from energysim.objective.objective import Objective
from energysim.solvers import Solver, SolverResult
from energysim.solvers.newton_cg import EAGER_DIRECT_MAX_DOFS


def warm_start(objective: Objective, predicted: Tensor, x_prev: Tensor, dt: float) -> Tensor:
    """Where the solver starts, per batch entry; `objective` is the whole step objective.

    Without obstacles: the inertial prediction x_n + h v_n plus the displacement the linear terms
    (gravity) alone would cause in one step, h² M⁻¹ f, which saves a Newton iteration. With
    obstacles every candidate is first cut back along the way from x_n to the largest fraction
    every term allows (`max_step`, which also refuses a state that starts inside an obstacle), and
    x_n itself joins them: the one of lowest energy wins. A body resting on the ground then starts
    where it rests, not pushed into the barrier by a step of free fall. Before that, every term
    may move a candidate (`EnergyTerm.warm_start`): friction holds its contact vertices at x_n.
    The plain prediction, unmoved, competes as well. (On the worm's 5 s walk the held plain
    prediction won 199 of 300 steps, the unmoved one 99, x_n 2.)
    """
    candidates = [predicted]
    linear = [term for term in objective.terms if term.is_linear]
    if linear:
        # closed forms where the terms have them (gravity does): no autograd pass
        forces = Objective(linear, objective.free, objective.residual_scale, objective.action)
        _, gradient = forces.energy_and_gradient(predicted)
        candidates.insert(0, predicted - (dt * objective.residual_scale[:, None]) * gradient)
    for term in objective.terms:
        candidates = [term.warm_start(x_prev, candidate) for candidate in candidates]
    if not any_limits_steps(list(objective.terms)):
        return candidates[0]
    # the prediction as inertia alone makes it stays a candidate: held contact vertices suit a gait,
    # but a body at rest starts better from x_n + h v_n (the worm at zero action: 1.4 Newton
    # iterations per step from there, 2.3 when only the held candidates and x_n compete). Lowest
    # energy is not always the best start: the quadruped's walk took 10.3 iterations, not 8.9
    candidates.append(predicted)
    cuts, energies = objective.cut_back(x_prev, candidates)
    best, best_energy = x_prev, energies[0]
    for candidate, energy in zip(cuts, energies[1:], strict=True):
        better = energy < best_energy
        best = torch.where(better[:, None, None], candidate, best)
        best_energy = torch.where(better, energy, best_energy)
    return best


def rows_of(objective: Objective, scene_terms: Sequence[EnergyTerm], entries: Tensor) -> Objective | None:
    """The step objective of the batch entries `entries` alone, sliced from `objective`: the scene's
    terms hold no per-entry data and serve as they are, the step's own terms slice themselves
    (`EnergyTerm.rows`); None where one cannot."""
    shared = {id(term) for term in scene_terms}
    terms = []
    for term in objective.terms:
        part = term if id(term) in shared else term.rows(entries)
        if part is None:
            return None
        terms.append(part)
    action = None if objective.action is None else objective.action[entries]
    anchor = None if objective.anchor is None else objective.anchor[entries]
    part = Objective(terms, objective.free, objective.residual_scale, action, anchor)
    part.slice_constant_hessians_of(objective, entries)
    return part


GRAD_MODES = ("implicit", "unrolled")


def solve_stage(
    scene: Scene,
    x_start: Tensor,
    v_start: Tensor,
    dt: float,
    action: Tensor | None,
    solver: Solver,
    grad_mode: str,
    adjoint_rtol: float,
    parameters: list[Tensor],
    wants_grad: bool,
) -> tuple[Tensor, SolverResult]:
    """argmin_x ½dt⁻²‖x − (x_start + dt v_start)‖²_M + Σ E_i(x): one implicit-Euler solve of step
    `dt` from (`x_start`, `v_start`), differentiable as `grad_mode` says. Every integrator is a
    sequence of these; friction is lagged from `x_start`."""

    def objective_of(xp: Tensor, vp: Tensor, act: Tensor | None, anchor: Tensor | None) -> Objective:
        terms = step_terms(list(scene.terms), scene.vertex_mass.detach(), dt, xp, vp, scene.free, anchor)
        return Objective(
            terms=terms,
            free=scene.free,
            residual_scale=dt / scene.vertex_mass.detach(),
            action=act,
            anchor=anchor,
        )

    def solve() -> SolverResult:
        # densely strided (a one-entry batch sliced from the state is "contiguous" with the state's
        # batch stride), and anchored from the start (at the prediction, which changes the energy by
        # a constant only): compiled evaluations then meet one layout and one anchor kind, so each
        # keeps one graph instead of three to try its guards against
        xp, vp = x_start.detach().clone(memory_format=torch.contiguous_format), v_start.detach()
        act = None if action is None else action.detach()
        free = scene.free[:, None].to(xp.dtype)
        predicted = xp + dt * vp * free
        with torch.no_grad():
            # prepared before the warm start, whose energy evaluations then compile too
            objective = solver.prepare(objective_of(xp, vp, act, predicted))
            start = warm_start(objective, predicted, xp, dt)
            objective.terms[0].anchor = start  # the inertia term
            objective.anchor = start

            def subset(entries: Tensor) -> Objective:
                sliced = rows_of(objective, scene.terms, entries)
                if sliced is not None:
                    return sliced
                return objective_of(
                    xp[entries], vp[entries], None if act is None else act[entries], start[entries]
                )

            objective.subset = subset
            return solver.minimize(objective, start)

    if not wants_grad:
        stats = solve()
        return stats.x, stats
    if grad_mode == "implicit":
        direct_limit = getattr(solver, "direct_limit", None)
        context = {
            "run": solve,
            "terms": list(scene.terms),
            "vertex_mass": scene.vertex_mass,
            "free": scene.free,
            "dt": dt,
            "strict": solver.strict,
            "adjoint_rtol": adjoint_rtol,
            # the adjoint assembles eagerly: the eager limit
            "direct_max_dofs": direct_limit() if direct_limit else EAGER_DIRECT_MAX_DOFS,
        }
        x_next = ImplicitStep.apply(context, x_start, v_start, action, *parameters)
        return x_next, context["result"]
    x_next, iterations, residual = unrolled_step(
        list(scene.terms),
        scene.vertex_mass,
        dt,
        x_start,
        v_start,
        scene.free,
        action,
        tol=solver.tol,
        max_iter=solver.max_iter,
    )
    return x_next, solver.finish_unrolled(x_next, residual, iterations)
