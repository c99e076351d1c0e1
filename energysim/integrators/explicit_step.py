"""One explicit step of `scene.substeps` leapfrog substeps, its blow-up check, and the substeps a
scene needs (`stable_substeps`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from energysim.contact.obstacles import project_contacts
from energysim.energies.base import EnergyTerm, is_dissipative
from energysim.integrators import explicit
from energysim.integrators.common import ENERGY_ROUNDING, acceleration_of, check_action, state_energies
from energysim.model.scene import Scene
from energysim.objective import compiled as compiled_functions
from energysim.objective.objective import Objective
from energysim.solvers import Solver, SolverResult


def explicit_step(
    scene: Scene, x_prev: Tensor, v_prev: Tensor, action: Tensor | None, solver: Solver, differentiable: bool
) -> tuple[Tensor, Tensor, SolverResult]:
    """`scene.substeps` leapfrog substeps (`energysim.integrators.explicit`), compiled where `solver`
    compiles and nothing needs their graph; raises `InstabilityError` where one blew up."""
    explicit.check_terms(list(scene.terms))
    terms, obstacles = explicit.split_terms(list(scene.terms))
    explicit.check_start(obstacles, x_prev)
    h = scene.dt / scene.substeps
    # pinned vertices stay where the state has them, whatever velocity it gives them
    v_start = v_prev * scene.free[:, None].to(v_prev.dtype)
    moved = None
    if solver.compile and not differentiable and compiled_functions.has_closed_forms(terms, hessian=False):
        inverse_mass = scene.free.to(x_prev.dtype) / scene.vertex_mass
        moved = compiled_functions.leapfrog(
            terms,
            obstacles,
            action,
            scene.free,
            inverse_mass,
            x_prev.detach(),
            v_start.detach(),
            h,
            scene.substeps,
        )
    if moved is None:
        dissipative = [term for term in terms if is_dissipative(term)]
        inverse_mass = scene.free.to(x_prev.dtype) / scene.vertex_mass

        def acceleration(x: Tensor) -> Tensor:
            return acceleration_of(scene, x, action, differentiable, solver, terms)

        def damping(x: Tensor, v: Tensor) -> Tensor:
            return -sum(term.dissipation_gradient(x, v) for term in dissipative) * inverse_mass[:, None]

        def contact(x: Tensor, v: Tensor, horizon: float) -> Tensor:
            return project_contacts(obstacles, scene.free, x, v, horizon)

        moved = explicit.leapfrog(
            x_prev,
            v_start,
            h,
            scene.substeps,
            acceleration,
            contact if obstacles else None,
            damping if dissipative else None,
        )
    x_next, v_next = moved
    with torch.no_grad():
        finite = torch.isfinite(x_next).all(dim=(-1, -2)) & torch.isfinite(v_next).all(dim=(-1, -2))
        energy_before, motion_before, scale_before = state_energies(
            scene, x_prev, v_start, action, solver.compile, terms
        )
        energy_after, motion_after, scale_after = state_energies(
            scene,
            x_next.where(finite[:, None, None], x_prev),
            v_next.nan_to_num(),
            action,
            solver.compile,
            terms,
        )
        allowance = (
            explicit.ENERGY_GAIN_LIMIT * motion_before
            + explicit.ENERGY_GAIN_FLOOR * motion_after
            + ENERGY_ROUNDING * torch.maximum(scale_before, scale_after)
        )
        unstable = explicit.blown_up(x_next, v_next, obstacles, energy_before, energy_after, allowance)
    if bool(unstable.any()):
        entry = int(torch.nonzero(unstable)[0])
        energies = (
            float(energy_before[entry]),
            float(energy_after[entry]) if bool(finite[entry]) else math.nan,
        )
        detail = explicit.describe_blow_up(obstacles, x_next[entry : entry + 1], v_next[entry : entry + 1])
        raise_unstable(scene, terms, x_prev, action, energies, entry, detail)
    stats = SolverResult(
        x=x_next.detach(),
        iterations=0,
        grad_evals=scene.substeps,
        hvp_evals=0,
        energy_evals=2,
        residual=0.0,
        converged=True,
        solver="leapfrog",
        tol=0.0,
    )
    return x_next, v_next, stats


def stable_limits(
    scene: Scene, terms: list[EnergyTerm], x: Tensor, action: Tensor | None
) -> tuple[float, float]:
    """At positions `x` `[1, n, d]`: the Courant limit 2/ω_max over the force `terms`
    (`explicit.stable_step`) and the viscous kick's limit 1/γ_max (`explicit.stable_damping_step`),
    in s (inf where there is none)."""
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass, action)
    courant = explicit.stable_step(objective.hessian(x), scene.vertex_mass, scene.free, x)
    dissipative = [term for term in terms if is_dissipative(term)]
    return courant, explicit.stable_damping_step(dissipative, x, scene.vertex_mass, scene.free)


def raise_unstable(
    scene: Scene,
    terms: list[EnergyTerm],
    x_prev: Tensor,
    action: Tensor | None,
    energies: tuple[float, float],
    entry: int,
    detail: str = "",
) -> None:
    """Raise `InstabilityError` for batch entry `entry`, with its energies at the step's start and end
    (J), `detail` (`explicit.describe_blow_up`) and its stable step over `terms` (the force terms:
    contact acts by projection)."""
    rows = slice(entry, entry + 1)
    act = None if action is None else action[rows].detach()
    courant, damping = stable_limits(scene, terms, x_prev[rows].detach(), act)
    limit = min(courant, damping)
    h = scene.dt / scene.substeps
    if math.isfinite(limit):
        substeps = math.ceil(scene.dt / (explicit.COURANT_SAFETY * limit))
        advice = f"at least {substeps} substeps of dt = {scene.dt:.4g} s"
    else:
        advice = "a smaller step"
    viscous = f" and its viscous limit 1/γ_max = {damping:.4g} s" if math.isfinite(damping) else ""
    raise explicit.InstabilityError(
        f"the leapfrog step blew up: h = {h:.4g} s ({scene.substeps} substeps of dt = {scene.dt:.4g} s); "
        f"batch entry {entry}'s energy went from {energies[0]:.6g} J to {energies[1]:.6g} J in one "
        f"step.{detail} Its Courant limit at the step's start is about 2/ω_max = {courant:.4g} s (ω_max² the "
        f"largest eigenvalue of M⁻¹H){viscous}: use {advice}, or an implicit integrator"
    )


def stable_substeps(scene: Scene, x: Tensor | None = None, action: Tensor | None = None) -> int:
    """The leapfrog substeps per `scene.dt` that keep h below `COURANT_SAFETY` of the stable step,
    estimated at positions `x` `[n, d]` (default the rest shape): the Courant limit 2/ω_max, by
    power iteration on M⁻¹H over the scene's force terms (obstacles act by projection,
    `energysim.integrators.explicit`), and with viscosity the damping limit 1/γ_max (`stable_damping_step`).

    A body stiffens as it deforms, so this is where to start, not a guarantee: a step that blows up
    still raises `InstabilityError`. The shipped worm at rest: 2/ω_max = 0.71 ms, 32 substeps of
    1/60 s (with η = 30 Pa·s its viscous limit 1/γ_max is 0.70 ms: still 32)."""
    if isinstance(x, Tensor):
        scene = scene.matching(x, "x")
    terms, _ = explicit.split_terms(list(scene.terms))
    x = (scene.rest_positions if x is None else x).reshape(1, scene.num_vertices, scene.dim).detach()
    act = None if action is None else check_action(action, 1, scene, x)
    limit = min(stable_limits(scene, terms, x, act))
    return max(1, math.ceil(scene.dt / (explicit.COURANT_SAFETY * limit))) if math.isfinite(limit) else 1
