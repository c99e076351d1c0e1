"""One time step as a minimisation (implicit Euler, or the two-stage second-order TR-BDF2), or
as explicit leapfrog substeps (`energysim.explicit`), and quasi-static equilibrium.

x_{n+1} = argmin_x ½h⁻²‖x − (x_n + h v_n)‖²_M + Σ_i E_i(x),   v_{n+1} = (x_{n+1} − x_n)/h.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim import compiled as compiled_functions
from energysim import explicit
from energysim.contact.obstacles import project_contacts
from energysim.energies.base import EnergyTerm, is_dissipative, limits_steps
from energysim.energies.muscles import check_action_width
from energysim.implicit import ImplicitStep, differentiable_parameters, step_terms, unrolled_step
from energysim.objective import Objective
from energysim.optim import Solver, SolverResult
from energysim.optim.base import ConvergenceError, ConvergenceWarning
from energysim.optim.newton_cg import EAGER_DIRECT_MAX_DOFS
from energysim.scene import EXPLICIT_INTEGRATORS, Scene


@dataclass(frozen=True)
class StepResult:
    """A new state and the statistics of the solve that produced it."""

    state: Tensor
    stats: SolverResult


def _check_action(
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


def _limits_steps(terms: list[EnergyTerm]) -> bool:
    return any(limits_steps(term) for term in terms)


def _warm_start(objective: Objective, predicted: Tensor, x_prev: Tensor, dt: float) -> Tensor:
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
    if not _limits_steps(list(objective.terms)):
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


GRAD_MODES = ("implicit", "unrolled")


def _stage(
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
            start = _warm_start(objective, predicted, xp, dt)
            objective.terms[0].anchor = start  # the inertia term
            objective.anchor = start

            def subset(entries: Tensor) -> Objective:
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


def _acceleration(
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


def _combined(first: SolverResult, second: SolverResult) -> SolverResult:
    """One report for a step made of two solves: counts add up, the worse residual stands."""
    return dataclasses.replace(
        second,
        iterations=first.iterations + second.iterations,
        grad_evals=first.grad_evals + second.grad_evals,
        hvp_evals=first.hvp_evals + second.hvp_evals,
        energy_evals=first.energy_evals + second.energy_evals,
        residual=max(first.residual, second.residual),
        converged=first.converged and second.converged,
    )


def _touching(scene: Scene, x: Tensor, action: Tensor | None) -> Tensor:
    """Which batch entries have a vertex within an obstacle's barrier distance, `[B]` bool: the
    barrier energy is exactly zero farther away."""
    with torch.no_grad():
        barriers = [term for term in scene.terms if _limits_steps([term])]
        if not barriers:
            return torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        return sum(term(x.detach(), action) for term in barriers) > 0


# Relative rounding allowed in the energy comparison of `_gains_energy` (its terms are summed in
# float64 from parts up to the scale of the largest term).
ENERGY_ROUNDING = 1e-9
# The most energy a TR-BDF2 step may gain, as a fraction of the kinetic plus deformation energy.
# On a nonlinear body the scheme is not exactly energy-stable, and its truncation error moves a
# little energy either way: the swinging cantilever gains at most 0.2 % of it in a step at h = 1/24 s.
# The trapezoidal overshoot on a flattened body gains 20–500 %.
ENERGY_GAIN_LIMIT = 1e-2


def _energies(
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


def _gains_energy(
    scene: Scene,
    before: tuple[Tensor, Tensor],
    after: tuple[Tensor, Tensor],
    action: Tensor | None,
    residual: float,
    compiled: bool = False,
) -> Tensor:
    """Which entries end the step with clearly more energy than they started with, `[B]` bool.

    With the action held over the step the scene is conservative (friction only dissipates): an
    exact implicit-Euler step never gains energy, nor does TR-BDF2 on a linear system (its
    amplification matrix is normal with spectral radius ≤ 1). Allowed: the work of the solve's
    residual, |vᵀMρ| ≤ ρ Σ m|v|, rounding, and `ENERGY_GAIN_LIMIT` of the energy of motion and
    deformation for TR-BDF2's own truncation error on a nonlinear body. More than that is the
    trapezoidal stage overshooting on a stiff, strongly nonlinear state (a scrambled or flattened
    body)."""
    (x0, v0), (x1, v1) = before, after
    energy_before, motion_before, scale_before = _energies(scene, x0, v0, action, compiled)
    energy_after, motion_after, scale_after = _energies(scene, x1, v1, action, compiled)
    work = residual * (scene.vertex_mass[:, None] * v1.detach().abs()).sum(dim=(-1, -2))
    allowance = (
        work
        + ENERGY_ROUNDING * torch.maximum(scale_before, scale_after)
        + ENERGY_GAIN_LIMIT * torch.maximum(motion_before, motion_after)
    )
    return energy_after > energy_before + allowance


def _second_order_where_safe(
    scene: Scene,
    x_prev: Tensor,
    v_prev: Tensor,
    action: Tensor | None,
    implicit_euler: Callable[[Tensor, Tensor, Tensor | None], tuple[Tensor, Tensor, SolverResult]],
    tr_bdf2: Callable[[Tensor, Tensor, Tensor | None], tuple[Tensor, Tensor, Tensor, SolverResult]],
    *,
    compiled: bool = False,
) -> tuple[Tensor, Tensor, SolverResult]:
    """TR-BDF2 for the batch entries where it is safe, implicit Euler for the others (`compiled`:
    the energy check evaluates the terms through a compiled function).

    Implicit Euler takes over an entry that
    - touches an obstacle at the step's start or after either stage: a second-order step rebuilds
      the velocity from the kink an impact leaves in the positions (v_{n+1} = (3x_{n+1} − 4x_½ +
      x_n)/h) and turns the impact into a bounce, while contact and friction are first order anyway;
    - would end the step with more energy than it started with (`_gains_energy`): the trapezoidal
      stage takes the force at the step's start at face value, which on a scrambled, flattened or
      inverted body is huge and overshoots (a flattened box went from 290 J to 539 J in one step);
    - or whose TR-BDF2 solves did not converge (they are then all redone, and only the implicit-Euler
      solve reports).
    """

    def entries(rows: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        return x_prev[rows], v_prev[rows], None if action is None else action[rows]

    euler = _touching(scene, x_prev, action)
    pieces: list[tuple[Tensor, Tensor, Tensor]] = []
    reports: list[SolverResult] = []
    rows = torch.nonzero(~euler).reshape(-1)
    if rows.numel():
        x0, v0, act = entries(rows)
        try:
            with warnings.catch_warnings():
                # an attempt that does not converge is discarded and redone, not reported
                warnings.simplefilter("ignore", ConvergenceWarning)
                x_next, v_next, x_half, report = tr_bdf2(x0, v0, act)
        except ConvergenceError:
            euler[rows] = True
        else:
            if report.converged:
                unsafe = _touching(scene, x_half, act) | _touching(scene, x_next, act)
                unsafe |= _gains_energy(scene, (x0, v0), (x_next, v_next), act, report.residual, compiled)
            else:
                unsafe = torch.ones_like(rows, dtype=torch.bool)
            euler[rows[unsafe]] = True
            kept = ~unsafe
            pieces.append((rows[kept], x_next[kept], v_next[kept]))
            reports.append(report)
    rows = torch.nonzero(euler).reshape(-1)
    if rows.numel():
        x_next, v_next, report = implicit_euler(*entries(rows))
        pieces.append((rows, x_next, v_next))
        reports.append(report)
    if len(pieces) == 1 and pieces[0][0].numel() == x_prev.shape[0]:
        return pieces[0][1], pieces[0][2], reports[0]
    order = torch.argsort(torch.cat([piece[0] for piece in pieces]))
    x_next = torch.cat([piece[1] for piece in pieces])[order]
    v_next = torch.cat([piece[2] for piece in pieces])[order]
    stats = reports[0] if len(reports) == 1 else _combined(*reports)
    return x_next, v_next, dataclasses.replace(stats, x=x_next.detach())


def _explicit_step(
    scene: Scene, x_prev: Tensor, v_prev: Tensor, action: Tensor | None, solver: Solver, differentiable: bool
) -> tuple[Tensor, Tensor, SolverResult]:
    """`scene.substeps` leapfrog substeps (`energysim.explicit`), compiled where `solver` compiles and
    nothing needs their graph; raises `InstabilityError` where one blew up."""
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
            return _acceleration(scene, x, action, differentiable, solver, terms)

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
        energy_before, motion_before, scale_before = _energies(
            scene, x_prev, v_start, action, solver.compile, terms
        )
        energy_after, motion_after, scale_after = _energies(
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
        _raise_unstable(scene, terms, x_prev, action, energies, entry, detail)
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


def _stable_limits(
    scene: Scene, terms: list[EnergyTerm], x: Tensor, action: Tensor | None
) -> tuple[float, float]:
    """At positions `x` `[1, n, d]`: the Courant limit 2/ω_max over the force `terms`
    (`explicit.stable_step`) and the viscous kick's limit 1/γ_max (`explicit.stable_damping_step`),
    in s (inf where there is none)."""
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass, action)
    courant = explicit.stable_step(objective.hessian(x), scene.vertex_mass, scene.free, x)
    dissipative = [term for term in terms if is_dissipative(term)]
    return courant, explicit.stable_damping_step(dissipative, x, scene.vertex_mass, scene.free)


def _raise_unstable(
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
    courant, damping = _stable_limits(scene, terms, x_prev[rows].detach(), act)
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
    `energysim.explicit`), and with viscosity the damping limit 1/γ_max (`stable_damping_step`).

    A body stiffens as it deforms, so this is where to start, not a guarantee: a step that blows up
    still raises `InstabilityError`. The shipped worm at rest: 2/ω_max = 0.71 ms, 32 substeps of
    1/60 s (with η = 30 Pa·s its viscous limit 1/γ_max is 0.70 ms: still 32)."""
    if isinstance(x, Tensor):
        scene = scene.matching(x, "x")
    terms, _ = explicit.split_terms(list(scene.terms))
    x = (scene.rest_positions if x is None else x).reshape(1, scene.num_vertices, scene.dim).detach()
    act = None if action is None else _check_action(action, 1, scene, x)
    limit = min(_stable_limits(scene, terms, x, act))
    return max(1, math.ceil(scene.dt / (explicit.COURANT_SAFETY * limit))) if math.isfinite(limit) else 1


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

    "leapfrog": `scene.substeps` explicit position-Verlet substeps of h/substeps (`energysim.explicit`):
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
    solves did not converge; see `_second_order_where_safe`. Resting contact therefore runs
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
    if grad_mode not in GRAD_MODES:
        raise ValueError(f"grad_mode must be one of {GRAD_MODES}, got {grad_mode!r}")
    x_prev, v_prev = scene.split_state(state)
    if not torch.isfinite(state).all():
        raise ValueError("state has non-finite entries")
    # device and dtype follow the state, through a converted copy: the scene itself is unchanged
    scene = scene.matching(state)
    action = _check_action(action, x_prev.shape[0], scene, state)
    solver = solver or scene.solver
    parameters = differentiable_parameters([scene])
    wants_grad = torch.is_grad_enabled() and (
        state.requires_grad or (action is not None and action.requires_grad) or bool(parameters)
    )
    h = scene.dt
    if scene.integrator in EXPLICIT_INTEGRATORS:
        return _result(*_explicit_step(scene, x_prev, v_prev, action, solver, wants_grad), state)
    if scene.substeps != 1:
        raise ValueError(
            f"substeps = {scene.substeps}: an implicit step takes dt whole (substeps = 1); substeps are "
            "for the explicit integrator, integrator='leapfrog'"
        )

    def stage(x_start: Tensor, v_start: Tensor, dt: float, act: Tensor | None) -> tuple[Tensor, SolverResult]:
        return _stage(
            scene, x_start, v_start, dt, act, solver, grad_mode, adjoint_rtol, parameters, wants_grad
        )

    def implicit_euler(x0: Tensor, v0: Tensor, act: Tensor | None) -> tuple[Tensor, Tensor, SolverResult]:
        x1, stats = stage(x0, v0, h, act)
        return x1, (x1 - x0) / h, stats

    def tr_bdf2(x0: Tensor, v0: Tensor, act: Tensor | None) -> tuple[Tensor, Tensor, Tensor, SolverResult]:
        acceleration = _acceleration(scene, x0, act, wants_grad, solver)
        # stage targets written as implicit-Euler predictions x_start + dt·v_start
        x_half, first = stage(x0, 2.0 * v0 + (h / 4.0) * acceleration, h / 4.0, act)
        v_half = 4.0 * (x_half - x0) / h - v0
        x1, second = stage(x_half, (x_half - x0) / h + (4.0 * v_half - v0) / 3.0, h / 3.0, act)
        # (3x₁ − 4x½ + x₀)/h written in differences: exactly zero where nothing moved (pinned vertices)
        v1 = (3.0 * (x1 - x_half) - (x_half - x0)) / h
        return x1, v1, x_half, _combined(first, second)

    if scene.integrator == "implicit_euler":
        x_next, v_next, stats = implicit_euler(x_prev, v_prev, action)
    else:
        x_next, v_next, stats = _second_order_where_safe(
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
        action=_check_action(action, batched.shape[0], scene, batched),
        anchor=batched,
    )
    result = (solver or scene.solver).minimize(objective, batched)
    return StepResult(state=result.x.reshape(x0.shape), stats=result)
