"""Newton–CG: truncated preconditioned CG on Hessian-vector products, with a line search.

Each Newton iteration solves H p = −∇E inexactly by CG (no matrix is factorised). CG stops
early when the linear residual falls below a forcing fraction of the gradient (inexact Newton:
loose far from the minimum, tight near it), or on negative curvature (Steihaug), where it keeps
the last descent iterate, or the preconditioned gradient if there is none. The step is then cut
to the largest one every term allows (`max_step`) and backtracked until the energy decreases.

Small systems are factorised instead (`direct_max_dofs`). Where H is not positive definite there,
CG takes the entry over, or (`indefinite="shift"`) the factorisation is tried again on
H + τ·|diag H| for growing τ (`INDEFINITE_SHIFTS`): a Levenberg–Marquardt step, scaled per DOF,
that stays on the direct path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from energysim.energies.inertia import Inertia
from energysim.linalg.assembly import cached_pattern
from energysim.linalg.banded import (
    BandFactor,
    band_cholesky_solve,
    factorise_bands,
    prefer_band,
    solve_bands,
    substitute_bands,
)
from energysim.linalg.block_tridiagonal import LevelLayout, cached_layout, level_solve, prefer_levels
from energysim.objective.derivatives import HessianOperator
from energysim.objective.objective import Objective
from energysim.solvers.arguments import require_bool, require_choice, require_integer, require_real
from energysim.solvers.base import Solver, SolverResult, Stagnation, line_step

# The default DOF limits of the direct solve per batch entry (`NewtonCG.direct_max_dofs=None`).
# Assembled eagerly, a direct solve builds dense or level blocks, whose cost grows much faster than
# CG's. Compiled, the Hessian goes straight into band storage and a band Cholesky costs N·u²:
# with compile=True the quadruped (918 DOFs) walked at 35 instead of 120 ms per step, the jumper
# (765) at 29 instead of 133 and the starfish (1,620) at 65 instead of 139, against CG.
EAGER_DIRECT_MAX_DOFS = 600
COMPILED_BAND_MAX_DOFS = 5000
# τ tried in turn where H is not positive definite and `indefinite="shift"`: the direct paths
# factorise H + τ·|diag H|. The first that factorises wins, so a barely indefinite H keeps most of
# its Newton step; past the last, truncated CG takes over. On the worm environment with random
# actions 46% of the Newton iterations met an indefinite H, and most took τ = 1 or 10.
INDEFINITE_SHIFTS = (1e-2, 1e-1, 1.0, 10.0)
# Kept factorisations (`NewtonCG.reuse_factorization`): one per kind of solve a scene alternates
# between (TR-BDF2's two stages have different M/h², implicit Euler a third).
KEPT_FACTORISATIONS = 4


def _dot(a: Tensor, b: Tensor) -> Tensor:
    # a [1, N] × [N, 1] product per batch entry: BLAS's dot, with no [B, n, d] temporary (at 58k
    # DOFs 18 µs against 140 µs for multiply-then-sum, three times per CG iteration)
    batch = a.shape[0]
    return torch.bmm(a.reshape(batch, 1, -1), b.reshape(batch, -1, 1)).reshape(batch)


def _cholesky_directions(
    dense: Tensor, rhs: Tensor, wanted: Tensor, band: LevelLayout | None = None
) -> tuple[Tensor, Tensor]:
    """Solve dense `[B, N, N]` systems for `rhs` `[B, n, d]` by Cholesky where positive definite;
    returns the solutions (zero elsewhere) and which `wanted` entries they solved. With `band`, the
    factorisation is LAPACK's band Cholesky in that layout's ordering (`energysim.linalg.banded`)."""
    if band is not None:
        return _band_directions(band_cholesky_solve(dense, rhs.reshape(rhs.shape[0], -1), band), rhs, wanted)
    factor, info = torch.linalg.cholesky_ex(dense)
    solved = wanted & (info == 0)
    if not solved.any():
        return torch.zeros_like(rhs), solved
    if not bool((info == 0).all()):
        # a failed factor holds garbage: swap in identities so the batched solve stays finite
        eye = torch.eye(dense.shape[-1], dtype=dense.dtype, device=dense.device)
        factor = torch.where((info == 0)[:, None, None], factor, eye)
    direction = torch.cholesky_solve(rhs.reshape(rhs.shape[0], -1, 1), factor).reshape(rhs.shape)
    return direction * solved[:, None, None], solved


def _shifted_diagonal(matrices: Tensor, shift: float) -> Tensor:
    """`matrices` `[..., N, N]` plus `shift` times the absolute value of their diagonals."""
    diagonal = matrices.diagonal(dim1=-2, dim2=-1)
    return matrices + shift * torch.diag_embed(diagonal.abs())


def _retry_shifted(
    solve: Callable[[Tensor, float], tuple[Tensor, Tensor]],
    direction: Tensor,
    solved: Tensor,
    wanted: Tensor,
) -> tuple[Tensor, Tensor]:
    """`direction` and `solved` after solving the `wanted` entries that did not factorise again
    with each shift of `INDEFINITE_SHIFTS` in turn; `solve(rows, τ)` returns those rows'
    directions of H + τ·|diag H| and which of them factorised."""
    for shift in INDEFINITE_SHIFTS:
        missing = wanted & ~solved
        if not bool(missing.any()):
            break
        rows = torch.nonzero(missing).reshape(-1)
        retried, factorised = solve(rows, shift)
        kept = torch.where(factorised[:, None, None], retried, direction[rows])
        direction = direction.index_copy(0, rows, kept)
        solved = solved.index_copy(0, rows, factorised)
    return direction, solved


def _all(rows: Tensor) -> Tensor:
    # every one of `rows` wanted
    return torch.ones(rows.shape, dtype=torch.bool, device=rows.device)


def _band_directions(
    solved_bands: tuple[Tensor, Tensor], rhs: Tensor, wanted: Tensor
) -> tuple[Tensor, Tensor]:
    # a band solve's `[B, N]` solutions, shaped as `rhs`, zero where not wanted or not solved
    direction, positive_definite = solved_bands
    solved = wanted & positive_definite
    return direction.reshape(rhs.shape) * solved[:, None, None], solved


def block_jacobi_preconditioner(operator: HessianOperator, like: Tensor) -> Tensor:
    """Inverses of the per-vertex d×d diagonal blocks of H, shape `[B, n, d, d]`.

    A block that is not positive definite (compressed or inverted elements) is replaced by its
    diagonal's absolute value, so the preconditioner stays SPD and CG stays well defined.
    """
    blocks = operator.vertex_blocks(like)
    eye = torch.eye(like.shape[-1], dtype=like.dtype, device=like.device)
    blocks = torch.where(operator.free[None, :, None, None], blocks, eye)
    factor, info = torch.linalg.cholesky_ex(blocks)
    bad = info != 0
    if bad.any():
        diag = blocks.diagonal(dim1=-2, dim2=-1).abs().clamp_min(torch.finfo(like.dtype).tiny)
        fallback = torch.diag_embed(diag)
        factor = torch.where(bad[..., None, None], torch.linalg.cholesky(fallback), factor)
    # (L Lᵀ)⁻¹ = L⁻ᵀ L⁻¹ by one batched triangular solve: torch.cholesky_inverse is as fast on the
    # CPU, but on CUDA it took 16 ms for 256 × 144 blocks of 3 × 3 (a loop over the batch)
    inverse_factor = torch.linalg.solve_triangular(factor, eye.expand_as(factor), upper=False)
    return inverse_factor.mT @ inverse_factor


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
            entry (N = n·d), ≈ B·N³/3 flops. "banded": LAPACK's band Cholesky in the level order
            (`energysim.linalg.banded`), ≈ B·N·u² flops for half-bandwidth u, one call per entry, CPU only
            (elsewhere it factorises dense). "levels": block-tridiagonal Cholesky over breadth-first
            vertex levels (`energysim.linalg.block_tridiagonal`), ≈ B·L·S³ flops for L levels of at most
            S DOFs, plus a fixed cost per level (a Python loop of small batched kernels). "auto"
            picks by those estimates (`prefer_levels`, measured on the worm, N = 432, L = 18,
            S = 27, u = 44; then `prefer_band`): banded for one worm on the CPU (dense on CUDA),
            levels for batches of them (≈ 6× faster per Newton direction at B = 16); with
            `compile=True` banded on the CPU for any batch (its Hessian is then assembled in band
            storage by a compiled function).
        compact_below: in a batch, once at most this fraction of the entries still iterates, go on
            with those alone (`Objective.subset`: the step builds their objective from their slice
            of the state), instead of computing on every entry until the slowest has converged.
            Each later halving compacts again. 0 turns it off. On 64 worms with random actions
            the slowest entry took about twice the mean number of iterations.
        project_hessian: project every element block to positive semidefinite (projected Newton,
            as IPC does) instead of truncating CG on negative curvature. Off by default: on the
            hard cases in the tests (inverted, scrambled and flattened bodies, 20 m/s impacts) the
            exact Hessian with Steihaug truncation needs fewer iterations.
        indefinite: what a direct solve does where H is not positive definite. "cg" (default):
            hand the entry to truncated CG (Steihaug). "shift": factorise H + τ·|diag H| for τ in
            `INDEFINITE_SHIFTS` in turn, and hand the entry to CG only if none factorises. Both
            give a descent direction. The shift keeps the direct path, which is the compiled one
            with `compile=True`: the worm environment with random actions took the same Newton
            iterations per step (20.3 against 20.6) and a third of the time compiled. Not the default:
            a fixed shift converges only linearly where H stays indefinite up to the solution
            (a muscle alone, extended, has minimisers in a whole family of shapes), where
            Steihaug's CG converged in 22 iterations and the shift had not in 100.
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
    # the kept factorisations: per (layout, batch size, M/h²), one factor per batch entry
    _factors: dict[tuple, tuple[LevelLayout, list[BandFactor | None]]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        name = self.name
        require_integer(name, "max_cg_iter", self.max_cg_iter, minimum=1)
        require_real(name, "forcing", self.forcing, above=0.0, below=1.0)
        require_choice(name, "hessian", self.hessian, ("elements", "autograd"))
        require_choice(name, "preconditioner", self.preconditioner, ("block_jacobi", "none"))
        require_choice(name, "direct", self.direct, ("auto", "dense", "banded", "levels"))
        require_choice(name, "indefinite", self.indefinite, ("shift", "cg"))
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
        for _ in range(self.max_iter):
            active = (residual >= self.tol) & ~stalled
            if not active.any():
                break
            if self._compacts(root, active):
                rows = torch.nonzero(active).reshape(-1)
                solved_x = solved_x.index_copy(0, entries, x)
                solved_residual = solved_residual.index_copy(0, entries, residual)
                solved_stalled = solved_stalled.index_copy(0, entries, stalled)
                stagnation = stagnation.rows(rows)
                entries = entries[rows]
                objective = self.prepare(root.subset(entries))
                used.append(objective)
                x, energy, gradient, residual = x[rows], energy[rows], gradient[rows], residual[rows]
                first_residual, steepest, stalled = first_residual[rows], steepest[rows], stalled[rows]
                refresh = refresh[rows]
                active = active[rows]
            iterations += 1
            ratio = torch.sqrt(residual / first_residual.clamp_min(torch.finfo(x.dtype).tiny))
            eta = torch.clamp(ratio, max=self.forcing)
            wanted = active & ~steepest
            direction, precondition, products = self._newton_direction(
                objective, x, gradient, eta, wanted, refresh
            )
            hvps += products
            if steepest.any():
                direction = torch.where(steepest[:, None, None], precondition(-gradient), direction)
            # descent safeguard: a direction that does not go downhill becomes the preconditioned gradient.
            # Only active entries count: a converged one has no direction (slope 0), and building the
            # preconditioner for it cost a whole-batch eager Hessian in half of the iterations of a
            # batch of 64 worms
            slope = _dot(gradient, direction)
            uphill = active & (slope >= 0)
            if uphill.any():
                direction = torch.where(uphill[:, None, None], precondition(-gradient), direction)
            direction = direction * active[:, None, None]
            search = line_step(objective, x, energy, gradient, direction)
            if self.reuse_factorization is not None:
                slow = search.residual > self.reuse_factorization * residual
                refresh = active & (slow | (search.step < 1))
            failed = active & (search.step == 0)
            stalled = stalled | (failed & steepest)
            steepest = failed
            # a step too small for the energy to judge stands only if the residual fell; if not,
            # this is as far as the precision goes: keep the better point and stop that entry
            worse = active & search.unjudged & (search.residual >= residual)
            stalled = stalled | worse
            keep = worse[:, None, None]
            x = torch.where(keep, x, search.x)
            gradient = torch.where(keep, gradient, search.gradient)
            new_energy = torch.where(worse, energy, search.energy)
            residual = torch.where(worse, residual, search.residual)
            stagnation, stuck = stagnation.update(active, energy, x, new_energy, residual, search.allowance)
            energy = new_energy
            stalled = stalled | stuck
        x, residual = stagnation.best_of(x, residual, stalled)
        if len(used) > 1:
            x = solved_x.index_copy(0, entries, x)
            residual = solved_residual.index_copy(0, entries, residual)
            stalled = solved_stalled.index_copy(0, entries, stalled)
            root.grad_evals = sum(part.grad_evals for part in used)
            root.energy_evals = sum(part.energy_evals for part in used)
        return self.finish(root, x, residual, iterations, hvps, stalled)

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
            # built on first use: a compiled dense solve that succeeds needs none
            if not operators:
                operators.append(
                    objective.hessian(
                        x, use_element_blocks=self.hessian == "elements", project=self.project_hessian
                    )
                )
            return operators[0]

        built: list[Callable[[Tensor], Tensor]] = []

        def precondition(r: Tensor) -> Tensor:
            # built on first use: when the dense solve succeeds, nothing needs it
            if not built:
                built.append(self._preconditioner(operator(), x, objective))
            return built[0](r)

        compiled = self._compiled_direct(objective, -gradient, x, wanted, refresh)
        direction, solved = compiled or self._direct(operator(), -gradient, x, wanted)
        if (wanted & ~solved).any():
            unsolved = wanted & ~solved
            iterative = self._truncated_cg(operator(), -gradient, precondition, eta, unsolved, objective)
            direction = torch.where(solved[:, None, None], direction, iterative)
        return direction, precondition, operator().products if operators else 0

    def _compiled_direct(
        self, objective: Objective, rhs: Tensor, x: Tensor, wanted: Tensor, refresh: Tensor | None = None
    ) -> tuple[Tensor, Tensor] | None:
        """`_direct`'s dense solve from the compiled dense Hessian (`Objective.dense_hessian`): the
        directions and which entries they solved, or None where `_direct` would not take the dense
        path or the objective has no compiled Hessian. On the band path with
        `reuse_factorization`, from the kept factors where they serve (`_kept_directions`)."""
        size = x.shape[1] * x.shape[2]
        if (
            not objective.compiled
            or self.hessian != "elements"
            or self.project_hessian
            or size > self.direct_limit(compiled_band=True)
        ):
            return None
        groups = objective.element_groups()
        method = self._method_for(groups, x, compiled=True)
        if method == "levels":
            return None
        band = self._band(method, groups, x)
        if band is None and size > self.direct_limit():
            return None  # a dense matrix of this size: CG
        if band is not None:
            if self.reuse_factorization is not None:
                kept = self._kept_directions(objective, x, band, rhs, wanted, refresh)
                if kept is not None:
                    return kept
            bands = objective.band_hessian(x, band)
            if bands is None:
                return None
            flat_rhs = rhs.reshape(rhs.shape[0], -1)
            if self.indefinite != "shift":
                return _band_directions(solve_bands(bands, flat_rhs, band), rhs, wanted)
            # the band solve overwrites its input with the factors: a shifted retry needs H itself
            pristine = bands.clone()
            direction, solved = _band_directions(solve_bands(bands, flat_rhs, band), rhs, wanted)

            def solve_band(rows: Tensor, shift: float) -> tuple[Tensor, Tensor]:
                shifted = pristine[rows].clone()
                shifted[..., 0] += shift * shifted[..., 0].abs()  # column 0 holds the diagonal
                return _band_directions(solve_bands(shifted, flat_rhs[rows], band), rhs[rows], _all(rows))

            return _retry_shifted(solve_band, direction, solved, wanted)
        dense = objective.dense_hessian(x)
        if dense is None:
            return None
        return self._dense_directions(dense, rhs, wanted, None)

    def _kept_directions(
        self,
        objective: Objective,
        x: Tensor,
        band: LevelLayout,
        rhs: Tensor,
        wanted: Tensor,
        refresh: Tensor | None,
    ) -> tuple[Tensor, Tensor] | None:
        """Directions from the kept band factors (`reuse_factorization`), factorising H anew (the
        compiled band Hessian) for the wanted entries without one or flagged in `refresh`; None
        where H is not positive definite at such an entry, and the caller's usual path (with its
        shifted retries or CG) takes the iteration."""
        batch = x.shape[0]
        # a new M/h² (another step size or stage) needs its own factors; the sum identifies it
        inertia = tuple(
            float(term.mass_per_dt_squared.sum()) for term in objective.terms if isinstance(term, Inertia)
        )
        key = (id(band), batch, x.dtype, inertia)
        record = self._factors.pop(key, None)
        factors = list(record[1]) if record is not None and record[0] is band else [None] * batch
        need = torch.tensor([factor is None for factor in factors], device=wanted.device)
        if refresh is not None:
            need |= refresh
        renew = torch.nonzero(wanted & need).reshape(-1).tolist()
        if renew:
            bands = objective.band_hessian(x, band)
            if bands is None:
                return None
            for row, factor in zip(renew, factorise_bands(bands[renew]), strict=True):
                factors[row] = factor
        # kept even where a new factor failed: the other entries' factors still serve
        self._factors[key] = (band, factors)
        while len(self._factors) > KEPT_FACTORISATIONS:
            del self._factors[next(iter(self._factors))]
        if any(factors[row] is None for row in renew):
            return None
        return _band_directions(substitute_bands(factors, rhs.reshape(batch, -1), band), rhs, wanted)

    def _shifted(
        self,
        solve: Callable[[Tensor, float], tuple[Tensor, Tensor]],
        direction: Tensor,
        solved: Tensor,
        wanted: Tensor,
    ) -> tuple[Tensor, Tensor]:
        # `_retry_shifted` where `indefinite` asks for it
        if self.indefinite != "shift":
            return direction, solved
        return _retry_shifted(solve, direction, solved, wanted)

    def _dense_directions(
        self, dense: Tensor, rhs: Tensor, wanted: Tensor, band: LevelLayout | None
    ) -> tuple[Tensor, Tensor]:
        """`_cholesky_directions`, with shifted retries where `dense` is not positive definite."""
        direction, solved = _cholesky_directions(dense, rhs, wanted, band)

        def solve_dense(rows: Tensor, shift: float) -> tuple[Tensor, Tensor]:
            return _cholesky_directions(_shifted_diagonal(dense[rows], shift), rhs[rows], _all(rows), band)

        return self._shifted(solve_dense, direction, solved, wanted)

    def _direct(
        self, operator: HessianOperator, rhs: Tensor, x: Tensor, wanted: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Exact Newton directions by Cholesky (dense or block-tridiagonal, see `direct`) where the
        system is small and H is positive definite; returns them and which batch entries they solved."""
        none = torch.zeros_like(wanted)
        if x.shape[1] * x.shape[2] > self.direct_limit() or self.hessian != "elements":
            return torch.zeros_like(rhs), none
        groups = [elements for elements, _ in operator.blocks]
        method = self._method_for(groups, x)
        if method == "levels":
            levels = operator.level_blocks(x)
            if levels is None:
                return torch.zeros_like(rhs), none
            diagonal, lower, layout = levels
            direction, positive_definite = level_solve(diagonal, lower, layout, rhs)
            solved = wanted & positive_definite

            def solve_levels(rows: Tensor, shift: float) -> tuple[Tensor, Tensor]:
                return level_solve(_shifted_diagonal(diagonal[rows], shift), lower[rows], layout, rhs[rows])

            direction, solved = self._shifted(solve_levels, direction, solved, wanted)
            return direction * solved[:, None, None], solved
        dense = operator.dense(x)
        if dense is None:
            return torch.zeros_like(rhs), none
        return self._dense_directions(dense, rhs, wanted, self._band(method, groups, x))

    def _method_for(self, element_groups: list[Tensor], x: Tensor, *, compiled: bool = False) -> str:
        """"dense", "banded" or "levels" for a Hessian whose blocks couple the vertices of
        `element_groups`: `direct` unless "auto", else the cheapest by the cost estimates. With
        `compiled` the Hessian can be assembled by a compiled function straight into band storage
        (not into level blocks), which makes the band path the cheaper one wherever it runs."""
        if self.direct != "auto":
            return self.direct
        if not element_groups:
            return "dense"  # no element couples vertices: nothing to order by levels
        batch, n, dim = x.shape
        layout = self._layout(element_groups, x)
        if compiled and prefer_band(layout, batch, n * dim, x.device, compiled=True):
            return "banded"
        if prefer_levels(layout, batch, n * dim):
            return "levels"
        return "banded" if prefer_band(layout, batch, n * dim, x.device) else "dense"

    def _layout(self, element_groups: list[Tensor], x: Tensor) -> LevelLayout:
        batch, n, dim = x.shape
        return cached_layout(cached_pattern(element_groups, n, dim, batch), element_groups, n, dim)

    def _band(self, method: str, element_groups: list[Tensor], x: Tensor) -> LevelLayout | None:
        """The layout whose band ordering the dense path factorises in, or None for a dense
        factorisation (the band routines are LAPACK's: CPU only, and they need coupled vertices)."""
        if method != "banded" or not element_groups or x.device.type != "cpu":
            return None
        return self._layout(element_groups, x)

    def _preconditioner(
        self, operator: HessianOperator, x: Tensor, objective: Objective
    ) -> Callable[[Tensor], Tensor]:
        """z = P⁻¹ r: per-vertex block-Jacobi, or the lumped-mass scaling h/m when there are no blocks."""
        if self.preconditioner == "block_jacobi" and (operator.blocks or operator.diagonal is not None):
            inverse = block_jacobi_preconditioner(operator, x)
            return lambda r: (inverse @ r[..., None])[..., 0]
        scale = objective.residual_scale[:, None]
        return lambda r: r * scale

    def _truncated_cg(
        self,
        operator: HessianOperator,
        rhs: Tensor,
        precondition: Callable[[Tensor], Tensor],
        eta: Tensor,
        active: Tensor,
        objective: Objective,
    ) -> Tensor:
        """Approximately solve H p = rhs, per batch entry; entries not `active` get p = 0.

        CG takes most of a Newton step's time, in many small tensor operations per iteration: the
        loop below keeps them few (fused in-place updates, squared norms, one sync per iteration).
        """
        solution = torch.zeros_like(rhs)
        remainder = rhs.clone()
        z = precondition(remainder)
        search = z.clone()
        rz = _dot(remainder, z)
        target_squared = eta**2 * _dot(rhs, rhs)
        # no need to solve the linear model more finely than the velocity tolerance itself
        velocity_target = 0.1 * self.tol
        scale = objective.residual_scale[:, None]
        running = active.clone()
        first = True
        for _ in range(self.max_cg_iter):
            product = operator.matvec(search)
            curvature = _dot(search, product)
            negative = running & (curvature <= 0)
            if negative.any():
                # Steihaug: stop along negative curvature; with no iterate yet, go down the gradient
                if first:
                    solution = torch.where(negative[:, None, None], search, solution)
                running = running & ~negative
            alpha = (rz / curvature.where(running, torch.ones_like(curvature))) * running
            solution.addcmul_(search, alpha[:, None, None])
            remainder.addcmul_(product, alpha[:, None, None], value=-1.0)
            first = False
            velocity = (remainder * scale).abs().amax(dim=(-1, -2))
            running = running & (_dot(remainder, remainder) > target_squared) & (velocity > velocity_target)
            if not running.any():
                break
            z = precondition(remainder)
            rz_new = _dot(remainder, z)
            beta = (rz_new / rz.where(rz != 0, torch.ones_like(rz))) * running
            search = z.addcmul_(search, beta[:, None, None])
            rz = rz_new
        return solution
