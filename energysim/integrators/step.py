"""One time step as a minimisation (implicit Euler, or the two-stage second-order TR-BDF2), or
as explicit leapfrog substeps (`energysim.integrators.explicit`), and quasi-static equilibrium.

x_{n+1} = argmin_x ½h⁻²‖x − (x_n + h v_n)‖²_M + Σ_i E_i(x),   v_{n+1} = (x_{n+1} − x_n)/h.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.compile_settings import package_compile_settings
from energysim.integrators.adjoint import differentiable_parameters
from energysim.integrators.common import acceleration_of, check_action
from energysim.integrators.explicit_step import explicit_step, stable_substeps
from energysim.integrators.implicit_stage import GRAD_MODES, solve_stage
from energysim.integrators.tr_bdf2 import combined, second_order_where_safe
from energysim.model.scene import EXPLICIT_INTEGRATORS, Scene
from energysim.objective.objective import Objective
from energysim.solvers import Solver, SolverResult


@dataclass(frozen=True)
class StepResult:
    """A new state and the statistics of the solve that produced it."""

    state: Tensor
    stats: SolverResult


def step(
    scene: Scene,
    state: Tensor,
    action: Tensor | None = None,
    solver: Solver | None = None,
    *,
    grad_mode: str = "implicit",
    adjoint_rtol: float = 1e-10,
) -> StepResult:
    """Advance `state` by one step of `scene.dt` with `scene.integrator` and report the solve.

    "implicit_euler": x_{n+1} = argmin ½h⁻²‖x − (x_n + h v_n)‖²_M + Σ E_i(x), v_{n+1} = (x_{n+1} − x_n)/h;
    first order, and it damps every oscillation by 1/sqrt(1 + (ωh)²) per step.

    "leapfrog": `scene.substeps` explicit position-Verlet substeps of h/substeps
    (`energysim.integrators.explicit`):
    second order and symplectic, one gradient per substep and no solve, stable only below the
    Courant limit h ω_max < 2. Half-space and sphere obstacles act after every kick as an inelastic
    contact with Coulomb friction (`Obstacle.contact_velocity`); other contact is refused. A step
    that blew up raises `InstabilityError` with the limit's estimate. The solver only says whether
    to compile.

    "tr_bdf2": the composite trapezoidal / three-point backward-difference step with γ = ½
    (Bank et al. 1985; Bathe & Baig 2005), second order and L-stable: slow motion keeps its
    amplitude, stiff modes and impacts are still damped. Both stages are argmin problems of the
    same kind, so contact barriers keep every stage feasible:

        x_½ = argmin ½(h/4)⁻²‖x − (x_n + ½h v_n + h²/16 a_n)‖²_M + Σ E_i(x),  a_n = −M⁻¹∇E(x_n),
        v_½ = 4(x_½ − x_n)/h − v_n,
        x_{n+1} = argmin ½(h/3)⁻²‖x − ((4x_½ − x_n)/3 + h(4v_½ − v_n)/9)‖²_M + Σ E_i(x),
        v_{n+1} = (3x_{n+1} − 4x_½ + x_n)/h.

    It costs two solves per step (each of a smaller effective step, so better conditioned) and
    the statistics add them up. Friction is lagged from each stage's start. A batch entry takes
    an implicit-Euler step instead where the second-order one is not safe: where it touches an
    obstacle during the step (a second-order step rebuilds the velocity from the kink an impact
    leaves in the positions: a 20 m/s drop came back up at 23 m/s), where the step would gain
    energy (the trapezoidal stage overshooting on a scrambled or flattened body), or where its
    solves did not converge; see `second_order_where_safe`. Resting contact therefore runs
    implicit Euler; free flight, swinging and vibration get the second-order step.

    The step is differentiable in `state`, `action` and every scene tensor that requires grad
    (Young's modulus, Poisson's ratio, spring stiffness and rest length, masses, gravity). With
    `grad_mode="implicit"` backward solves one linear system per solve at its solution (implicit
    function theorem) and keeps nothing of the optimizer's iterations; `"unrolled"` records Newton
    iterations instead (memory grows with them; a reference for checks). A solver with
    `strict=True` refuses to differentiate a step that did not converge; otherwise backward warns.

    A state in another dtype or on another device than the scene is stepped with the scene's copy
    in that dtype and on that device (`Scene.matching`); float16 and bfloat16 are refused. The step
    changes nothing it is given: neither the scene, its terms and solver, nor `state` or `action`.

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
    # the compiled calls' Dynamo settings made once for the whole step (`package_compile_settings`)
    with package_compile_settings():
        return _step(scene, state, action, solver, grad_mode, adjoint_rtol)


def _step(
    scene: Scene,
    state: Tensor,
    action: Tensor | None,
    solver: Solver | None,
    grad_mode: str,
    adjoint_rtol: float,
) -> StepResult:
    if grad_mode not in GRAD_MODES:
        raise ValueError(f"grad_mode must be one of {GRAD_MODES}, got {grad_mode!r}")
    x_prev, v_prev = scene.split_state(state)
    if not torch.isfinite(state).all():
        raise ValueError("state has non-finite entries")
    # device and dtype follow the state, through a converted copy: the scene itself is unchanged
    scene = scene.matching(state)
    action = check_action(action, x_prev.shape[0], scene, state)
    solver = solver or scene.solver
    parameters = differentiable_parameters([scene])
    wants_grad = torch.is_grad_enabled() and (
        state.requires_grad or (action is not None and action.requires_grad) or bool(parameters)
    )
    h = scene.dt
    if scene.integrator in EXPLICIT_INTEGRATORS:
        return _result(*explicit_step(scene, x_prev, v_prev, action, solver, wants_grad), state)
    if scene.substeps != 1:
        raise ValueError(
            f"substeps = {scene.substeps}: an implicit step takes dt whole (substeps = 1); substeps are "
            "for the explicit integrator, integrator='leapfrog'"
        )

    def stage(x_start: Tensor, v_start: Tensor, dt: float, act: Tensor | None) -> tuple[Tensor, SolverResult]:
        return solve_stage(
            scene, x_start, v_start, dt, act, solver, grad_mode, adjoint_rtol, parameters, wants_grad
        )

    def implicit_euler(x0: Tensor, v0: Tensor, act: Tensor | None) -> tuple[Tensor, Tensor, SolverResult]:
        x1, stats = stage(x0, v0, h, act)
        return x1, (x1 - x0) / h, stats

    def tr_bdf2(x0: Tensor, v0: Tensor, act: Tensor | None) -> tuple[Tensor, Tensor, Tensor, SolverResult]:
        acceleration = acceleration_of(scene, x0, act, wants_grad, solver)
        # stage targets written as implicit-Euler predictions x_start + dt·v_start
        x_half, first = stage(x0, 2.0 * v0 + (h / 4.0) * acceleration, h / 4.0, act)
        v_half = 4.0 * (x_half - x0) / h - v0
        x1, second = stage(x_half, (x_half - x0) / h + (4.0 * v_half - v0) / 3.0, h / 3.0, act)
        # (3x₁ − 4x½ + x₀)/h written in differences: exactly zero where nothing moved (pinned vertices)
        v1 = (3.0 * (x1 - x_half) - (x_half - x0)) / h
        return x1, v1, x_half, combined(first, second)

    if scene.integrator == "implicit_euler":
        x_next, v_next, stats = implicit_euler(x_prev, v_prev, action)
    else:
        x_next, v_next, stats = second_order_where_safe(
            scene, x_prev, v_prev, action, implicit_euler, tr_bdf2, compiled=solver.compile
        )
    return _result(x_next, v_next, stats, state)


def _result(x_next: Tensor, v_next: Tensor, stats: SolverResult, like: Tensor) -> StepResult:
    """The new state `[x.flatten(), v.flatten()]`, shaped like the old one `like`, and the report."""
    new_state = torch.cat([x_next.reshape(x_next.shape[0], -1), v_next.reshape(v_next.shape[0], -1)], dim=-1)
    return StepResult(state=new_state.reshape(like.shape), stats=stats)


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
    scene = scene.matching(x0, "x0")
    batched = x0.reshape(-1, scene.num_vertices, scene.dim).detach()
    objective = Objective(
        terms=list(scene.terms),
        free=scene.free,
        residual_scale=scene.dt / scene.vertex_mass,
        action=check_action(action, batched.shape[0], scene, batched),
        anchor=batched,
    )
    result = (solver or scene.solver).minimize(objective, batched)
    return StepResult(state=result.x.reshape(x0.shape), stats=result)


__all__ = ["GRAD_MODES", "StepResult", "solve_static", "stable_substeps", "step", "timestep"]
