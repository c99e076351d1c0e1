"""The one autograd.Function of the project: an implicit-Euler step differentiated by the implicit
function theorem.

At the converged x* the step objective's gradient vanishes, g(x*; θ) = ∇ₓE(x*; θ) = 0, so for a
loss L and any input θ (previous positions and velocities, the action, material parameters,
masses, gravity):

    H u = ∂L/∂x*,     dL/dθ = −uᵀ ∂g/∂θ,     H = ∇²ₓE(x*), the true (unprojected) Hessian.

Backward is one linear solve (pinned DOFs eliminated), the one the forward's Newton direction
takes for the same system (`energysim.linalg.linear_solve`), and one vector-Jacobian product;
the optimizer's iterations are never recorded, so a step keeps only its inputs and x* for backward,
whatever solver ran the forward.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.energies.inertia import Inertia
from energysim.linalg.conjugate_gradient import ConjugateGradient, block_jacobi
from energysim.linalg.linear_solve import choose, eager_system
from energysim.objective.derivatives import HessianOperator
from energysim.objective.objective import Objective
from energysim.solvers.base import ConvergenceError, ConvergenceWarning, SolverResult


class GradientError(RuntimeError):
    """The step's gradient cannot be computed: its Hessian is not positive definite at x*, or the
    adjoint solve did not converge."""


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(-1, -2))


NOT_POSITIVE_DEFINITE = (
    "the step's Hessian is not positive definite at its solution, so x* is not a strict minimum and "
    "the implicit gradient does not exist (buckling, or a free rigid mode in a static solve)"
)
# The most CG iterations of an adjoint solve.
ADJOINT_MAX_CG_ITER = 10000


def solve_adjoint(
    operator: HessianOperator, rhs: Tensor, x: Tensor, rtol: float, direct_max_dofs: int
) -> Tensor:
    """u = H⁻¹ rhs (`[B, n, d]`) at the step's solution x, by the linear solve the forward step's
    Newton direction takes (`energysim.linalg.linear_solve.choose`, with H assembled eagerly: a
    Cholesky factorisation for systems of at most `direct_max_dofs` DOFs per entry), else
    block-Jacobi CG to ‖r‖ ≤ `rtol`·‖rhs‖.

    Raises:
        GradientError: H is not positive definite, or CG did not converge.
    """
    plan = choose([elements for elements, _ in operator.blocks], x, max_dofs=direct_max_dofs)
    system = eager_system(plan, operator, x)
    if system is not None:
        solution, solved = system.solve(rhs, torch.ones(x.shape[0], dtype=torch.bool, device=x.device))
        if not bool(solved.all()):
            raise GradientError(NOT_POSITIVE_DEFINITE)
        return solution
    cg = ConjugateGradient(max_iter=ADJOINT_MAX_CG_ITER).solve(
        operator.matvec, rhs, block_jacobi(operator, x), rtol
    )
    if bool(cg.indefinite.any()):
        raise GradientError(NOT_POSITIVE_DEFINITE)
    if not bool(cg.converged.all()):
        raise GradientError(
            f"the adjoint CG solve did not reach rtol {rtol:g} in {ADJOINT_MAX_CG_ITER} iterations"
        )
    return cg.solution


def step_terms(
    terms: Sequence[EnergyTerm],
    vertex_mass: Tensor,
    dt: float,
    x_prev: Tensor,
    v_prev: Tensor,
    free: Tensor,
    anchor: Tensor | None = None,
) -> list[EnergyTerm]:
    """The terms of one step's objective: inertia, the scene's terms, and the terms they build from
    the step's start (lagged friction). Autograd history of `x_prev` flows into all of them."""
    predicted = x_prev + dt * v_prev * free[:, None].to(v_prev.dtype)
    lagged = [extra for term in terms for extra in term.lagged_terms(x_prev, dt)]
    return [Inertia(vertex_mass, dt, predicted, anchor=anchor), *terms, *lagged]


class ImplicitStep(torch.autograd.Function):
    """x* = argmin_x E(x; x_n, v_n, action, θ), differentiable in every tensor argument.

    `apply(context, x_prev, v_prev, action, *parameters)`; `context` carries the scene pieces
    (terms, masses, free mask, h) and the solver; its `result` slot receives the solver report.
    """

    @staticmethod
    def forward(
        ctx, context: dict, x_prev: Tensor, v_prev: Tensor, action: Tensor | None, *parameters: Tensor
    ):  # noqa: ANN001
        run: Callable[[], SolverResult] = context["run"]
        with torch.no_grad():
            result = run()
        context["result"] = result
        ctx.context = context
        ctx.converged = result.converged
        ctx.summary = result.summary()
        ctx.parameter_count = len(parameters)
        ctx.save_for_backward(result.x, x_prev, v_prev, *(() if action is None else (action,)), *parameters)
        ctx.has_action = action is not None
        return result.x.clone()

    @staticmethod
    def backward(ctx, grad_x: Tensor):  # noqa: ANN001, ANN205
        context = ctx.context
        saved = ctx.saved_tensors
        x_star, x_prev, v_prev = saved[:3]
        action = saved[3] if ctx.has_action else None
        parameters = saved[3 + ctx.has_action :]
        if not ctx.converged:
            if context["strict"]:
                raise ConvergenceError("refusing to differentiate an unconverged step: " + ctx.summary)
            warnings.warn(
                "differentiating an unconverged step; its gradient is approximate: " + ctx.summary,
                ConvergenceWarning,
                stacklevel=2,
            )
        free = context["free"]
        free_f = free[:, None].to(grad_x.dtype)
        dt = context["dt"]
        terms_now = step_terms(
            context["terms"], context["vertex_mass"].detach(), dt, x_prev.detach(), v_prev.detach(), free
        )
        objective = Objective(
            terms_now, free, dt / context["vertex_mass"].detach(), None if action is None else action.detach()
        )
        with torch.no_grad():
            operator = objective.hessian(x_star.detach())
            adjoint = solve_adjoint(
                operator, grad_x * free_f, x_star, context["adjoint_rtol"], context["direct_max_dofs"]
            )
        # −uᵀ ∂g/∂θ for every input, from one vector-Jacobian product of g = ∇ₓE(x*; θ)
        wanted = [
            ctx.needs_input_grad[1],
            ctx.needs_input_grad[2],
            ctx.has_action and ctx.needs_input_grad[3],
        ]
        with torch.enable_grad():
            xp = x_prev.detach().requires_grad_(wanted[0])
            vp = v_prev.detach().requires_grad_(wanted[1])
            act = None if action is None else action.detach().requires_grad_(bool(wanted[2]))
            terms = step_terms(context["terms"], context["vertex_mass"], dt, xp, vp, free)
            x = x_star.detach().requires_grad_(True)
            # pinned vertices sit at x_prev, and through the elastic terms they pull on their free
            # neighbours: taking them from xp puts that coupling, −uᵀ ∂g_free/∂x_pinned, in the VJP
            at = x * free_f + xp * (1 - free_f) if wanted[0] else x

            def energy(y: Tensor) -> Tensor:
                return sum(term(y, act) for term in terms)

            (gradient,) = torch.autograd.grad(energy(at).sum(), x, create_graph=True)
            inputs = [xp, vp, *(() if act is None else (act,)), *parameters]
            needs = [t.requires_grad for t in inputs]
            grads = [None] * len(inputs)
            chosen = [t for t, need in zip(inputs, needs, strict=True) if need]
            if chosen and gradient.requires_grad:
                computed = torch.autograd.grad(gradient, chosen, grad_outputs=-adjoint, allow_unused=True)
                it = iter(computed)
                grads = [next(it) if need else None for need in needs]
        grad_x_prev, grad_v_prev = grads[0], grads[1]
        # pinned vertices stay where x_prev put them: their gradient passes straight through
        passthrough = grad_x * (1 - free_f)
        grad_x_prev = passthrough if grad_x_prev is None else grad_x_prev + passthrough
        rest = grads[2:]
        grad_action = rest.pop(0) if ctx.has_action else None
        return (None, grad_x_prev if ctx.needs_input_grad[1] else None, grad_v_prev, grad_action, *rest)


def differentiable_parameters(modules: Sequence[torch.nn.Module]) -> list[Tensor]:
    """Every tensor in `modules`' buffers and parameters that requires grad, each once."""
    found: dict[int, Tensor] = {}
    for module in modules:
        for tensor in [*module.buffers(), *module.parameters()]:
            if tensor.requires_grad:
                found.setdefault(id(tensor), tensor)
    return list(found.values())


def unrolled_step(
    terms: Sequence[EnergyTerm],
    vertex_mass: Tensor,
    dt: float,
    x_prev: Tensor,
    v_prev: Tensor,
    free: Tensor,
    action: Tensor | None,
    *,
    tol: float,
    max_iter: int = 50,
) -> tuple[Tensor, int, float]:
    """x* by Newton iterations whose every operation autograd records: the unrolled reference.

    Each iteration solves H p = −g by CG on double-backward Hessian-vector products, to a tight
    tolerance, with the CG iterations recorded too. Memory grows with every iteration; use it
    to check `ImplicitStep` on small scenes, or where an unrolled gradient is wanted.

    Returns:
        x* `[B, n, d]` (with its graph), the Newton iterations taken, and the final residual (m/s).
    """
    free_f = free[:, None].to(x_prev.dtype)
    objective_terms = step_terms(terms, vertex_mass, dt, x_prev, v_prev, free)
    scale = (dt / vertex_mass)[:, None]

    def energy(y: Tensor) -> Tensor:
        return sum(term(y, action) for term in objective_terms)

    x = objective_terms[0].predicted_positions
    if not x.requires_grad:  # the state is a constant; only parameters carry gradients
        x = x.detach().requires_grad_(True)
    residual = previous = float("inf")
    for iteration in range(max_iter + 1):
        (gradient,) = torch.autograd.grad(energy(x).sum(), x, create_graph=True)
        gradient = gradient * free_f
        residual = float((gradient.detach() * scale.detach()).abs().amax())
        # stop at the tolerance, or where rounding stops Newton's progress (every recorded
        # iteration costs memory, and past that point it only records noise)
        if residual < tol or iteration == max_iter or (iteration >= 2 and residual > 0.5 * previous):
            return x, iteration, residual
        previous = residual

        def product(v: Tensor, x: Tensor = x, gradient: Tensor = gradient) -> Tensor:
            (hv,) = torch.autograd.grad(gradient, x, grad_outputs=v, create_graph=True)
            return hv * free_f + v * (1 - free_f)

        # CG preconditioned by the (constant) inertia diagonal h²/m, recorded: unrolled all the way down
        mass_scale = (dt**2 / vertex_mass.detach())[:, None]
        direction = torch.zeros_like(gradient)
        remainder = -gradient
        search = remainder * mass_scale
        rr = _dot(remainder, search)
        target = 1e-20 * rr
        # CG solves an n-DOF system in n iterations in exact arithmetic; a few more absorb rounding
        for _ in range(x.shape[1] * x.shape[2] + 10):
            if bool((rr <= target).all()):
                break
            hs = product(search)
            curvature = _dot(search, hs)
            if bool((curvature <= 0).any()):  # Steihaug: keep the descent direction found so far
                if not bool(direction.detach().abs().max() > 0):
                    direction = -gradient
                break
            alpha = rr / curvature
            direction = direction + alpha[:, None, None] * search
            remainder = remainder - alpha[:, None, None] * hs
            z = remainder * mass_scale
            rr_new = _dot(remainder, z)
            search = z + (rr_new / rr)[:, None, None] * search
            rr = rr_new
        # backtracking chosen off the record (a constant to autograd); near the solution the
        # steps are whole, so the recorded derivative tends to the exact one
        with torch.no_grad():
            current = energy(x.detach()).sum()
            slope = float((gradient.detach() * direction.detach()).sum())
            fraction = 1.0
            rounding = 64 * torch.finfo(x.dtype).eps * abs(float(current))
            for _ in range(40):
                trial = energy(x.detach() + fraction * direction.detach()).sum()
                if (
                    bool(torch.isfinite(trial))
                    and float(trial) <= float(current) + 1e-4 * fraction * slope + rounding
                ):
                    break
                fraction *= 0.5
        x = x + fraction * direction
    return x, max_iter, residual
