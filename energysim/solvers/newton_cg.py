"""Newton–CG: inexact Newton on the step objective, with a line search.

Each Newton iteration solves H p = −∇E for its direction by the linear solve that
`energysim.linalg.linear_solve.choose` picks: a Cholesky factorisation (dense, band or
block-tridiagonal) for small systems, else truncated preconditioned CG on Hessian-vector products
(`energysim.linalg.conjugate_gradient`). CG stops early when the linear residual falls below a
forcing fraction of the gradient (inexact Newton: loose far from the minimum, tight near it), or on
negative curvature (Steihaug), where it keeps the last descent iterate, or the preconditioned
gradient if there is none. The step is then cut to the largest one every term allows (`max_step`)
and backtracked until the energy decreases (`energysim.solvers.line_search`).

Where H is not positive definite on the direct path, CG takes the entry over, or
(`indefinite="shift"`) the factorisation is tried again on H + τ·|diag H| for growing τ
(`INDEFINITE_SHIFTS`): a Levenberg–Marquardt step, scaled per DOF, that stays on the direct path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from energysim.energies.inertia import Inertia
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.linalg.conjugate_gradient import ConjugateGradient, block_jacobi
from energysim.linalg.linear_solve import (
    COMPILED_BAND_MAX_DOFS,
    EAGER_DIRECT_MAX_DOFS,
    INDEFINITE_SHIFTS,
    METHODS,
    KeptBandFactors,
    LinearSolvePlan,
    choose,
    compiled_system,
    eager_system,
    solve_with_shifts,
)
from energysim.objective.derivatives import HessianOperator
from energysim.objective.objective import Objective
from energysim.solvers.arguments import require_bool, require_choice, require_integer, require_real
from energysim.solvers.base import Solver, SolverResult, in_layout_of
from energysim.solvers.line_search import line_step
from energysim.solvers.stagnation import Stagnation

__all__ = ["COMPILED_BAND_MAX_DOFS", "EAGER_DIRECT_MAX_DOFS", "INDEFINITE_SHIFTS", "NewtonCG"]

# Kept factorisations (`NewtonCG.reuse_factorization`): one per kind of solve a scene alternates
# between (TR-BDF2's two stages have different M/h², implicit Euler a third).
KEPT_FACTORISATIONS = 4


@dataclass(frozen=True)
class NewtonCG(Solver):
    """Inexact Newton with truncated preconditioned CG on Hessian-vector products.

    Args:
        tol: velocity-residual tolerance in m/s.
        max_iter: most Newton iterations.
        strict: raise instead of warning when `tol` is not reached.
        max_cg_iter: most CG iterations per Newton iteration.
        forcing: the largest CG relative tolerance η; η_k = min(forcing, sqrt(r_k / r_0)).
        hessian: "elements" builds per-element Hessian blocks once per Newton iteration and
            takes products from them; "autograd" takes every product by double backward
            (slower; the plain reference).
        preconditioner: "block_jacobi" (per-vertex d×d blocks) or "none" (mass scaling only).
        direct_max_dofs: systems of at most this many DOFs per batch entry are solved exactly by a
            Cholesky factorisation instead of CG (far cheaper for small bodies, where CG is all
            per-iteration overhead); where H is not positive definite, see `indefinite`.
            0 turns direct solves off. None (default): `EAGER_DIRECT_MAX_DOFS` (600), and up to
            `COMPILED_BAND_MAX_DOFS` (5,000) where the Hessian is assembled by a compiled function
            straight into band storage (`compile=True`, the band method, on the CPU).
        direct: how the direct solve factorises. "dense": one dense `[N, N]` Cholesky per batch
            entry (N = n·d), ≈ B·N³/3 flops. "banded": band Cholesky in the level order
            (`energysim.linalg.banded`: LAPACK's per entry, the C tile kernel for batches), ≈ B·N·u²
            flops for half-bandwidth u, CPU only (elsewhere dense). "levels": block-tridiagonal
            Cholesky over breadth-first vertex levels (`energysim.linalg.block_tridiagonal`), ≈ B·L·S³
            flops for L levels of at most S DOFs, plus a Python loop of small batched kernels per
            level. "auto" picks by those estimates (`prefer_levels`, then `prefer_band`): banded for
            one worm on the CPU (dense on CUDA), levels for batches of them; with `compile=True`
            banded on the CPU for any batch (H assembled in band storage by a compiled function),
            and on a GPU the level blocks by a compiled function (`Objective.level_hessian`).
        compact_below: once at most this fraction of a batch's entries still iterates, go on with those alone
            (`Objective.subset`: the step builds their objective from their slice of the state) rather than
            compute on every entry until the slowest has converged; each later halving compacts again.
            0 turns it off.
        project_hessian: project every element block to positive semidefinite (projected Newton,
            as IPC does) instead of truncating CG on negative curvature. Off by default: on the
            hard cases in the tests (inverted, scrambled and flattened bodies, 20 m/s impacts) the
            exact Hessian with Steihaug truncation needs fewer iterations.
        indefinite: what a direct solve does where H is not positive definite. "cg" (default):
            hand the entry to truncated CG (Steihaug). "shift": factorise H + τ·|diag H| for τ in
            `INDEFINITE_SHIFTS` in turn, and hand the entry to CG only if none factorises. Both
            give a descent direction. The shift keeps the direct path, the compiled one with
            `compile=True`. Not the default: a fixed shift converges only linearly where H stays
            indefinite up to the solution (docs/solvers.md has both measured).
        reuse_factorization: None (default): factorise H at every Newton iteration. A fraction ρ in
            (0, 1): on the compiled band path (`compile=True`, CPU), keep each band Cholesky factor
            and solve with it in later iterations and later steps (a chord method) as long as every
            iteration it serves shrinks the entry's velocity residual to at most ρ times its previous
            value and its step is taken whole; where one does not, H is factorised anew at the
            current iterate. The solve still stops on `tol` alone, so the result is as accurate;
            the directions are those of an older H, which costs iterations where H changes fast
            (contact, switching muscles) and saves the Hessian assembly and factorisation where it
            changes slowly (a swinging beam). The factors are kept by this solver object, per batch
            size and M/h² (`KEPT_FACTORISATIONS` of them), and entries are matched by their row in
            the batch: results depend on what the solver solved before, within `tol`.
        factor_precision: "single" assembles and factorises H in float32 where the C band kernel
            solves (`compile=True`, CPU, batches of 3 or more; `solve_bands_in_tiles`,
            `Objective.band_hessian`): only the direction is rounded, the residual and line search
            stay float64. The RL envs use it.
    """

    max_iter: int = 100
    max_cg_iter: int = 1000
    forcing: float = 0.01
    hessian: str = "elements"
    preconditioner: str = "block_jacobi"
    direct_max_dofs: int | None = None
    direct: str = "auto"
    project_hessian: bool = False
    compact_below: float = 0.5
    indefinite: str = "cg"
    reuse_factorization: float | None = None
    factor_precision: str = "double"
    # the kept factorisations: per (layout, batch size, M/h²), one factor per batch entry
    _factors: KeptBandFactors = field(
        default_factory=lambda: KeptBandFactors(KEPT_FACTORISATIONS), init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        name = self.name
        require_integer(name, "max_cg_iter", self.max_cg_iter, minimum=1)
        require_real(name, "forcing", self.forcing, above=0.0, below=1.0)
        require_choice(name, "hessian", self.hessian, ("elements", "autograd"))
        require_choice(name, "preconditioner", self.preconditioner, ("block_jacobi", "none"))
        require_choice(name, "direct", self.direct, METHODS)
        require_choice(name, "indefinite", self.indefinite, ("shift", "cg"))
        require_choice(name, "factor_precision", self.factor_precision, ("double", "single"))
        if self.direct_max_dofs is not None:
            require_integer(name, "direct_max_dofs (or None)", self.direct_max_dofs, minimum=0)
        require_bool(name, "project_hessian", self.project_hessian)
        if self.project_hessian and self.hessian != "elements":
            raise ValueError("project_hessian needs hessian='elements' (blocks to project)")
        require_real(name, "compact_below", self.compact_below, at_least=0.0, below=1.0)
        if self.reuse_factorization is not None:
            require_real(
                name, "reuse_factorization (or None)", self.reuse_factorization, above=0.0, below=1.0
            )

    def minimize(self, objective: Objective, x0: Tensor) -> SolverResult:
        root = self.prepare(objective)
        x = x0.detach().clone()
        energy, gradient = objective.energy_and_gradient(x)
        residual = objective.residual(gradient)
        first_residual = residual.clone()
        hvps = 0
        iterations = 0
        steepest = torch.zeros_like(residual, dtype=torch.bool)  # entries whose last Newton step failed
        stalled = torch.zeros_like(steepest)
        # entries whose kept factorisation served poorly (`reuse_factorization`): factorise anew
        refresh = torch.zeros_like(steepest)
        # the whole batch's results; `entries` are the batch indices of the rows still computed on
        solved_x, solved_residual, solved_stalled = x, residual, stalled
        stagnation = Stagnation.start(x, energy, residual)
        entries = torch.arange(x.shape[0], device=x.device)
        used = [objective]
        noise = None  # the energy's noise, once a line search has measured it (`line_step`)
        taken = torch.zeros_like(residual, dtype=torch.int64)  # iterations per entry
        solved_taken = taken

        searched: list[Objective] = []  # the objectives of rows a line search evaluated alone

        def rows_alone(rows: Tensor) -> Objective:
            # the objective of some rows of the current one (`entries` maps them to the batch's)
            part = self.prepare(root.subset(entries[rows]))
            searched.append(part)
            return part

        # alone on a CPU only: a GPU evaluates the whole batch at about the cost of a few rows, and each
        # new number of refusing rows would compile the evaluations again (docs/solvers.md)
        restrict = rows_alone if root.subset is not None and x.device.type == "cpu" else None
        skips_copies = x.device.type == "cpu"  # checking costs less than a whole-batch copy (no GPU sync)
        for _ in range(self.max_iter):
            active = (residual >= self.tol) & ~stalled
            if not active.any():
                break
            if self._compacts(root, active):
                rows = torch.nonzero(active).reshape(-1)
                solved_x = solved_x.index_copy(0, entries, x)
                solved_residual = solved_residual.index_copy(0, entries, residual)
                solved_stalled = solved_stalled.index_copy(0, entries, stalled)
                solved_taken = solved_taken.index_copy(0, entries, taken)
                stagnation = stagnation.rows(rows)
                entries = entries[rows]
                objective = self.prepare(root.subset(entries))
                used.append(objective)
                x, energy, gradient, residual = x[rows], energy[rows], gradient[rows], residual[rows]
                first_residual, steepest, stalled = first_residual[rows], steepest[rows], stalled[rows]
                refresh = refresh[rows]
                active = active[rows]
                noise = None if noise is None else noise[rows]
                taken = taken[rows]
            iterations += 1
            taken = taken + active
            ratio = torch.sqrt(residual / first_residual.clamp_min(torch.finfo(x.dtype).tiny))
            eta = torch.clamp(ratio, max=self.forcing)
            wanted = active & ~steepest
            direction, precondition, products = self._newton_direction(
                objective, x, gradient, eta, wanted, refresh
            )
            hvps += products
            if steepest.any():
                direction = torch.where(steepest[:, None, None], precondition(-gradient), direction)
            # descent safeguard: an uphill direction becomes the preconditioned gradient. Only active
            # entries count: a converged one has no direction (slope 0), and preconditioning it cost a
            # whole-batch eager Hessian. (Multiply-then-sum: several times faster here than a BLAS dot.)
            slope = (gradient * direction).sum(dim=(-1, -2))
            uphill = active & (slope >= 0)
            if uphill.any():
                direction = torch.where(uphill[:, None, None], precondition(-gradient), direction)
            if not (skips_copies and bool(active.all())):
                direction = direction * active[:, None, None]
            search = line_step(objective, x, energy, gradient, direction, noise=noise, restrict=restrict)
            noise = search.noise
            if self.reuse_factorization is not None:
                slow = search.residual > self.reuse_factorization * residual
                refresh = active & (slow | (search.step < 1))
            failed = active & (search.step == 0)
            stalled = stalled | (failed & steepest)
            steepest = failed
            # a step too small for the energy to judge stands only if the residual fell; if not,
            # this is as far as the precision goes: keep the better point and stop that entry
            worse = active & search.unjudged & (search.residual >= residual)
            previous, hints = x, search.hints
            if skips_copies and not bool(worse.any()):  # most iterations take every row's search
                x, new_energy, residual = search.x, search.energy, search.residual
                gradient = in_layout_of(gradient, search.gradient)
            else:
                stalled = stalled | worse
                keep = worse[:, None, None]
                x = torch.where(keep, x, search.x)
                gradient = torch.where(keep, gradient, search.gradient)
                new_energy = torch.where(worse, energy, search.energy)
                residual = torch.where(worse, residual, search.residual)
                # a row kept where it was made no iteration: no slip turned back there
                hints = None if hints is None else tuple(hint & ~worse[:, None] for hint in hints)
            objective.update_curvature_hints(previous, x, hints)
            stagnation, stuck = stagnation.update(active, energy, x, new_energy, residual, search.allowance)
            energy = new_energy
            stalled = stalled | stuck
        x, residual = stagnation.best_of(x, residual, stalled)
        if len(used) > 1:
            x = solved_x.index_copy(0, entries, x)
            residual = solved_residual.index_copy(0, entries, residual)
            stalled = solved_stalled.index_copy(0, entries, stalled)
            taken = solved_taken.index_copy(0, entries, taken)
        if len(used) + len(searched) > 1:
            root.grad_evals = sum(part.grad_evals for part in used + searched)
            root.energy_evals = sum(part.energy_evals for part in used + searched)
        return self.finish(root, x, residual, iterations, hvps, stalled, taken)

    def direct_limit(self, *, compiled_band: bool = False) -> int:
        """The most DOFs per batch entry a direct solve takes: `direct_max_dofs`, or where that is
        None, `COMPILED_BAND_MAX_DOFS` for a Hessian a compiled function assembles in band storage
        (`compiled_band`) and `EAGER_DIRECT_MAX_DOFS` otherwise."""
        if self.direct_max_dofs is not None:
            return self.direct_max_dofs
        return COMPILED_BAND_MAX_DOFS if compiled_band else EAGER_DIRECT_MAX_DOFS

    def _compacts(self, root: Objective, active: Tensor) -> bool:
        """Whether to go on with the `active` rows alone: when at most `compact_below` of the rows
        still compute and the objective can be restricted to them (`Objective.subset`)."""
        if root.subset is None or self.compact_below <= 0 or active.numel() < 2:
            return False
        return int(active.sum()) <= self.compact_below * active.numel()

    def _newton_direction(
        self,
        objective: Objective,
        x: Tensor,
        gradient: Tensor,
        eta: Tensor,
        wanted: Tensor,
        refresh: Tensor | None = None,
    ) -> tuple[Tensor, Callable[[Tensor], Tensor], int]:
        """Solve H p = −∇E for the `wanted` entries; returns p, the preconditioner, and the
        Hessian-vector products taken. `refresh`: entries whose kept factorisation must be
        renewed (`reuse_factorization`)."""
        operators: list[HessianOperator] = []

        def operator() -> HessianOperator:
            # built on first use: a compiled direct solve that succeeds needs none
            if not operators:
                blocks, project = self.hessian == "elements", self.project_hessian
                operators.append(objective.hessian(x, use_element_blocks=blocks, project=project))
            return operators[0]

        built: list[Callable[[Tensor], Tensor]] = []

        def precondition(r: Tensor) -> Tensor:
            # built on first use: when the direct solve succeeds, nothing needs it
            if not built:
                built.append(self._preconditioner(operator(), x, objective))
            return built[0](r)

        compiled = self._compiled_direct(objective, -gradient, x, wanted, refresh)
        direction, solved = compiled or self._direct(operator(), -gradient, x, wanted)
        unsolved = wanted & ~solved
        if unsolved.any():
            cg = ConjugateGradient(max_iter=self.max_cg_iter, truncate=True).solve(
                operator().matvec,
                -gradient,
                precondition,
                eta,
                active=unsolved,
                # no need to solve the linear model more finely than the velocity tolerance itself
                scale=objective.residual_scale[:, None],
                scaled_target=0.1 * self.tol,
            )
            direction = torch.where(solved[:, None, None], direction, cg.solution)
        return direction, precondition, operator().products if operators else 0

    def _shifts(self) -> tuple[float, ...]:
        # the shifted retries of a direct solve where H is not positive definite, if asked for
        return INDEFINITE_SHIFTS if self.indefinite == "shift" else ()

    def _compiled_direct(
        self, objective: Objective, rhs: Tensor, x: Tensor, wanted: Tensor, refresh: Tensor | None = None
    ) -> tuple[Tensor, Tensor] | None:
        """The direct solve from the Hessian a compiled function assembles (`compiled_system`): the
        directions and which entries they solved, or None where the plan is not a compiled one or the
        objective has no compiled Hessian (then `_direct`). On the band path with
        `reuse_factorization`, from the kept factors where they serve."""
        if not objective.compiled or self.hessian != "elements" or self.project_hessian:
            return None
        plan = self._plan(objective.element_groups(), x, compiled=True)
        if not plan.compiled:
            return None
        if self.reuse_factorization is not None and plan.method == "banded":
            kept = self._kept_directions(objective, x, plan.layout, rhs, wanted, refresh)
            if kept is not None:
                return kept
        single = self.factor_precision == "single"
        system = compiled_system(plan, objective, x, keep=bool(self._shifts()), single=single)
        return None if system is None else solve_with_shifts(system, rhs, wanted, self._shifts())

    def _kept_directions(
        self,
        objective: Objective,
        x: Tensor,
        band: LevelLayout,
        rhs: Tensor,
        wanted: Tensor,
        refresh: Tensor | None,
    ) -> tuple[Tensor, Tensor] | None:
        """Directions from the kept band factors (`reuse_factorization`), factorising the compiled
        band Hessian anew for the wanted entries without one or flagged in `refresh`; None where H
        is not positive definite at such an entry, and the usual path takes the iteration."""
        # a new M/h² (another step size or stage) needs its own factors; the sum identifies it
        inertia = tuple(
            float(term.mass_per_dt_squared.sum()) for term in objective.terms if isinstance(term, Inertia)
        )
        key = (id(band), x.shape[0], x.dtype, inertia)
        return self._factors.solve(key, band, rhs, wanted, refresh, lambda: objective.band_hessian(x, band))

    def _direct(
        self, operator: HessianOperator, rhs: Tensor, x: Tensor, wanted: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Exact Newton directions by Cholesky (dense, band or block-tridiagonal, see `direct`) of
        the eager Hessian where the system is small; returns them and which batch entries they
        solved (those where H, or a shift of it, is positive definite)."""
        if self.hessian != "elements":
            return torch.zeros_like(rhs), torch.zeros_like(wanted)
        plan = self._plan([elements for elements, _ in operator.blocks], x)
        system = eager_system(plan, operator, x, keep=bool(self._shifts()))
        if system is None:
            return torch.zeros_like(rhs), torch.zeros_like(wanted)
        return solve_with_shifts(system, rhs, wanted, self._shifts())

    def _plan(self, element_groups: list[Tensor], x: Tensor, *, compiled: bool = False) -> LinearSolvePlan:
        """`choose` with this solver's `direct` and DOF limits; `compiled`: the objective can
        assemble H by a compiled function."""
        return choose(
            element_groups,
            x,
            method=self.direct,
            max_dofs=self.direct_limit(),
            compiled_max_dofs=self.direct_limit(compiled_band=True) if compiled else None,
        )

    def _preconditioner(
        self, operator: HessianOperator, x: Tensor, objective: Objective
    ) -> Callable[[Tensor], Tensor]:
        """z = P⁻¹ r: per-vertex block-Jacobi, or the lumped-mass scaling h/m when there are no blocks."""
        if self.preconditioner == "block_jacobi" and (operator.blocks or operator.diagonal is not None):
            return block_jacobi(operator, x)
        scale = objective.residual_scale[:, None]
        return lambda r: r * scale
