"""The linear solves H u = b of a Newton direction and of the implicit backward, and the one rule that
chooses among them.

Four solves: `DenseCholesky` (one `[N, N]` factorisation per batch entry, ≈ B·N³/3 flops),
`BandCholesky` (LAPACK's band Cholesky in the breadth-first level order, ≈ B·N·u² for
half-bandwidth u, CPU only, `energysim.linalg.banded`), `LevelCholesky` (block-tridiagonal Cholesky
over vertex levels, ≈ B·L·S³ for L levels of at most S DOFs plus a fixed cost per level,
`energysim.linalg.block_tridiagonal`), and `ConjugateGradient` on Hessian-vector products
(`energysim.linalg.conjugate_gradient`) for systems too large to factorise. `choose` picks one from
the size of the system, the batch, the device and the cost estimates (`prefer_levels`,
`prefer_band`); the forward step and the backward both ask it, so both take the same path.

A direct solve reports which entries it solved: one whose matrix is not positive definite is left
for the caller (Newton hands it to truncated CG, or factorises H + τ·|diag H| again:
`solve_with_shifts`; the backward refuses it).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import torch
from torch import Tensor

from energysim.linalg.assembly import cached_pattern
from energysim.linalg.banded import (
    BandFactor,
    factorise_bands,
    prefer_band,
    solve_bands,
    solve_keeps_bands,
    substitute_bands,
    tiles_solve,
)
from energysim.linalg.block_tridiagonal import LevelLayout, cached_layout, level_solve, prefer_levels

if TYPE_CHECKING:
    from energysim.objective.derivatives import HessianOperator
    from energysim.objective.objective import Objective

# The default DOF limits of a direct solve per batch entry. Assembled eagerly, a direct solve builds
# dense or level blocks, whose cost grows much faster than CG's. Compiled, the Hessian goes straight
# into band storage and a band Cholesky costs N·u²: with compile=True the quadruped (918 DOFs)
# walked at 35 instead of 120 ms per step, the jumper (765) at 29 instead of 133 and the starfish
# (1,620) at 65 instead of 139, against CG.
EAGER_DIRECT_MAX_DOFS = 600
COMPILED_BAND_MAX_DOFS = 5000
# τ tried in turn where H is not positive definite and shifts are asked for: the direct solves
# factorise H + τ·|diag H|. The first that factorises wins, so a barely indefinite H keeps most of
# its Newton step. On the worm environment with random actions 46% of the Newton iterations met an
# indefinite H, and most took τ = 1 or 10.
INDEFINITE_SHIFTS = (1e-2, 1e-1, 1.0, 10.0)
METHODS = ("auto", "dense", "banded", "levels")


class DirectSolve(Protocol):
    """A factorisable system, one matrix per batch entry."""

    def solve(self, rhs: Tensor, wanted: Tensor) -> tuple[Tensor, Tensor]:
        """Solutions for `rhs` `[B, n, d]` (zero where not `wanted` `[B]` or not positive definite)
        and which entries they solved `[B]`."""
        ...

    def shifted(self, rows: Tensor, shift: float) -> DirectSolve:
        """The system of the entries `rows` alone, with H + `shift`·|diag H|."""
        ...


def _shifted_diagonal(matrices: Tensor, shift: float) -> Tensor:
    """`matrices` `[..., N, N]` plus `shift` times the absolute value of their diagonals."""
    diagonal = matrices.diagonal(dim1=-2, dim2=-1)
    return matrices + shift * torch.diag_embed(diagonal.abs())


@dataclass(frozen=True)
class DenseCholesky:
    """Dense symmetric systems `[B, N, N]` (N = n·d, fixed DOFs eliminated), by batched Cholesky."""

    matrices: Tensor

    def solve(self, rhs: Tensor, wanted: Tensor) -> tuple[Tensor, Tensor]:
        factor, info = torch.linalg.cholesky_ex(self.matrices)
        solved = wanted & (info == 0)
        if not solved.any():
            return torch.zeros_like(rhs), solved
        if not bool((info == 0).all()):
            # a failed factor holds garbage: swap in identities so the batched solve stays finite
            eye = torch.eye(self.matrices.shape[-1], dtype=self.matrices.dtype, device=rhs.device)
            factor = torch.where((info == 0)[:, None, None], factor, eye)
        solution = torch.cholesky_solve(rhs.reshape(rhs.shape[0], -1, 1), factor).reshape(rhs.shape)
        return solution * solved[:, None, None], solved

    def shifted(self, rows: Tensor, shift: float) -> DenseCholesky:
        return DenseCholesky(_shifted_diagonal(self.matrices[rows], shift))


@dataclass(frozen=True)
class BandCholesky:
    """Systems in `layout`'s band storage `[B, N, u + 1]` (`LevelLayout.band_entries`), by band
    Cholesky (`solve_bands`; float32 bands in float32). `solve` may factorise `bands` in place;
    `pristine` keeps H for shifted retries."""

    bands: Tensor
    layout: LevelLayout
    pristine: Tensor | None = None

    @staticmethod
    def of(bands: Tensor, layout: LevelLayout, *, keep: bool = False) -> BandCholesky:
        """The system of `bands`; `keep`: keep H, so that `shifted` can read it: a copy where the
        solve overwrites `bands` (LAPACK), `bands` themselves where the batched C kernel solves,
        which only reads them (no copy of the whole batch's Hessians every Newton iteration)."""
        if not keep:
            return BandCholesky(bands, layout)
        return BandCholesky(bands, layout, bands if solve_keeps_bands(bands) else bands.clone())

    @staticmethod
    def from_dense(matrices: Tensor, layout: LevelLayout, *, keep: bool = False) -> BandCholesky:
        """The system of dense `matrices` `[B, N, N]`, gathered into band storage."""
        batch, size = matrices.shape[0], matrices.shape[-1]
        bands = matrices.reshape(batch, size * size)[:, layout.band_entries]
        return BandCholesky.of(bands, layout, keep=keep)

    def solve(self, rhs: Tensor, wanted: Tensor) -> tuple[Tensor, Tensor]:
        solution, positive_definite = solve_bands(self.bands, rhs.reshape(rhs.shape[0], -1), self.layout)
        return _band_result(solution, positive_definite, rhs, wanted)

    def shifted(self, rows: Tensor, shift: float) -> BandCholesky:
        if self.pristine is None:
            raise ValueError("BandCholesky.shifted needs the matrix kept: build it with keep=True")
        bands = self.pristine[rows].clone()
        bands[..., 0] += shift * bands[..., 0].abs()  # column 0 holds the diagonal
        return BandCholesky(bands, self.layout)


def _band_result(
    solution: Tensor, positive_definite: Tensor, rhs: Tensor, wanted: Tensor
) -> tuple[Tensor, Tensor]:
    # a band solve's `[B, N]` solutions, shaped as `rhs`, zero where not wanted or not solved (no
    # copy where every row is both)
    solved = wanted & positive_definite
    if bool(solved.all()):
        return solution.reshape(rhs.shape), solved
    return solution.reshape(rhs.shape) * solved[:, None, None], solved


@dataclass(frozen=True)
class LevelCholesky:
    """Block-tridiagonal systems over vertex levels: diagonal blocks `[B, L, S, S]`, sub-diagonal
    blocks `[B, L - 1, S, S]` and their `layout` (`HessianOperator.level_blocks`)."""

    diagonal: Tensor
    lower: Tensor
    layout: LevelLayout

    def solve(self, rhs: Tensor, wanted: Tensor) -> tuple[Tensor, Tensor]:
        solution, positive_definite = level_solve(self.diagonal, self.lower, self.layout, rhs)
        solved = wanted & positive_definite
        return solution * solved[:, None, None], solved

    def shifted(self, rows: Tensor, shift: float) -> LevelCholesky:
        return LevelCholesky(_shifted_diagonal(self.diagonal[rows], shift), self.lower[rows], self.layout)


def solve_with_shifts(
    system: DirectSolve, rhs: Tensor, wanted: Tensor, shifts: Sequence[float] = ()
) -> tuple[Tensor, Tensor]:
    """`system.solve(rhs, wanted)`, then the wanted entries that did not factorise solved again with
    H + τ·|diag H| for each τ of `shifts` in turn (a Levenberg–Marquardt step, scaled per DOF: a
    descent direction that stays on the direct path). Returns the solutions and which entries were
    solved."""
    solution, solved = system.solve(rhs, wanted)
    for shift in shifts:
        missing = wanted & ~solved
        if not bool(missing.any()):
            break
        rows = torch.nonzero(missing).reshape(-1)
        every = torch.ones_like(rows, dtype=torch.bool)
        retried, factorised = system.shifted(rows, shift).solve(rhs[rows], every)
        kept = torch.where(factorised[:, None, None], retried, solution[rows])
        solution = solution.index_copy(0, rows, kept)
        solved = solved.index_copy(0, rows, factorised)
    return solution, solved


@dataclass(frozen=True)
class LinearSolvePlan:
    """How to solve one Newton or adjoint system.

    Attributes:
        method: "dense", "banded", "levels" or "cg".
        layout: the level layout whose band ordering "banded" factorises in, or whose level blocks
            a compiled "levels" assembles (None otherwise).
        compiled: assemble H by a compiled function (`Objective.band_hessian`, `level_hessian`,
            `dense_hessian`) rather than from the eager Hessian operator.
    """

    method: str
    layout: LevelLayout | None = None
    compiled: bool = False


CG_PLAN = LinearSolvePlan("cg")


def level_layout_of(element_groups: Sequence[Tensor], like: Tensor) -> LevelLayout:
    """The (cached) level layout of a Hessian whose blocks couple the vertices of `element_groups`,
    for positions like `like` `[B, n, d]`."""
    _, n, dim = like.shape
    # the layout reads one entry's pattern: built for one entry, it serves every batch size (a
    # batch that drops its converged entries meets several in one solve)
    return cached_layout(cached_pattern(element_groups, n, dim, 1), element_groups, n, dim)


def cheapest_method(element_groups: Sequence[Tensor], like: Tensor, *, compiled: bool = False) -> str:
    """"dense", "banded" or "levels", the cheapest by the cost estimates for a Hessian whose blocks
    couple the vertices of `element_groups` (measured on the worm, N = 432, L = 18, S = 27):
    banded for one worm on the CPU (dense on CUDA), levels for batches of them (≈ 6× faster per
    direction at B = 16). With `compiled` the Hessian can be assembled by a compiled function
    straight into band storage (not into level blocks), which makes the band path the cheaper one
    wherever it runs."""
    if not element_groups:
        return "dense"  # no element couples vertices: nothing to order by levels
    batch, n, dim = like.shape
    layout = level_layout_of(element_groups, like)
    if compiled and prefer_band(layout, batch, n * dim, like.device, compiled=True):
        return "banded"
    if prefer_levels(layout, batch, n * dim):
        return "levels"
    return "banded" if prefer_band(layout, batch, n * dim, like.device) else "dense"


def choose(
    element_groups: Sequence[Tensor],
    like: Tensor,
    *,
    method: str = "auto",
    max_dofs: int = EAGER_DIRECT_MAX_DOFS,
    compiled_max_dofs: int | None = None,
) -> LinearSolvePlan:
    """The linear solve for a Hessian whose blocks couple the vertices of `element_groups`, at
    positions like `like` `[B, n, d]`.

    Args:
        method: "auto" (`cheapest_method`), or "dense", "banded", "levels" to force one where a
            direct solve is taken at all. "banded" factorises dense off the CPU (LAPACK only) and
            where no element couples vertices.
        max_dofs: the most DOFs per batch entry a direct solve of an eagerly assembled H takes;
            larger systems take CG. 0 turns direct solves off.
        compiled_max_dofs: where a compiled function can assemble H, the most DOFs per batch entry
            it assembles into band storage (dense matrices and level blocks keep `max_dofs`); None:
            eager only.

    Returns:
        the plan; with `compiled_max_dofs` its `compiled` says whether the compiled assembly serves.
    """
    size = like.shape[1] * like.shape[2]
    if compiled_max_dofs is not None and size <= compiled_max_dofs:
        chosen = cheapest_method(element_groups, like, compiled=True) if method == "auto" else method
        band = _band_layout(chosen, element_groups, like)
        if band is not None:
            return LinearSolvePlan("banded", band, compiled=True)
        if size <= max_dofs:
            if chosen == "levels" and element_groups:
                return LinearSolvePlan("levels", level_layout_of(element_groups, like), compiled=True)
            return LinearSolvePlan("dense", compiled=True)
    if size > max_dofs:
        return CG_PLAN
    chosen = cheapest_method(element_groups, like) if method == "auto" else method
    if chosen == "levels":
        return LinearSolvePlan("levels")
    band = _band_layout(chosen, element_groups, like)
    return LinearSolvePlan("dense") if band is None else LinearSolvePlan("banded", band)


def _band_layout(method: str, element_groups: Sequence[Tensor], like: Tensor) -> LevelLayout | None:
    """The layout whose band ordering a "banded" solve factorises in, or None for a dense
    factorisation (the band routines are LAPACK's: CPU only, and they need coupled vertices)."""
    if method != "banded" or not element_groups or like.device.type != "cpu":
        return None
    return level_layout_of(element_groups, like)


def eager_system(
    plan: LinearSolvePlan, operator: HessianOperator, like: Tensor, *, keep: bool = False
) -> DirectSolve | None:
    """The direct system of `plan` from the eager Hessian `operator` at positions like `like`; None
    for CG, or where the operator has no assembled matrix (autograd products only). `keep`: keep H
    for `shifted` retries where the factorisation overwrites it."""
    if plan.method == "cg":
        return None
    if plan.method == "levels":
        levels = operator.level_blocks(like)
        return None if levels is None else LevelCholesky(*levels)
    dense = operator.dense(like)
    if dense is None:
        return None
    if plan.layout is not None:
        return BandCholesky.from_dense(dense, plan.layout, keep=keep)
    return DenseCholesky(dense)


def compiled_system(
    plan: LinearSolvePlan, objective: Objective, like: Tensor, *, keep: bool = False, single: bool = False
) -> DirectSolve | None:
    """The direct system of a compiled `plan` (`LinearSolvePlan.compiled`), from the Hessian the
    objective's compiled function assembles straight into the plan's storage (`Objective.dense_hessian`,
    `band_hessian`, `level_hessian`) at `like`; None where it has none. `keep`: as for `eager_system`;
    `single`: band systems are assembled and factorised in float32 where the C kernel solves them."""
    if plan.method == "levels":
        levels = objective.level_hessian(like, plan.layout)
        return None if levels is None else LevelCholesky(*levels, plan.layout)
    if plan.layout is not None:
        # float32 storage where the C kernel takes the batch (LAPACK's path stays float64)
        single = single and tiles_solve(like.shape[0], like.device)
        bands = objective.band_hessian(like, plan.layout, single=single)
        return None if bands is None else BandCholesky.of(bands, plan.layout, keep=keep)
    dense = objective.dense_hessian(like)
    return None if dense is None else DenseCholesky(dense)


class KeptBandFactors:
    """Band Cholesky factors kept across Newton iterations and steps (a chord method), per key.

    A key names one kind of system (a layout, a batch size, a dtype, an M/h²); each holds one factor
    per batch entry, matched by row. The `capacity` most recently used keys are kept: a scene
    alternates between a few (TR-BDF2's two stages have different M/h², implicit Euler a third).
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._factors: dict[Hashable, tuple[LevelLayout, list[BandFactor | None]]] = {}

    def solve(
        self,
        key: Hashable,
        layout: LevelLayout,
        rhs: Tensor,
        wanted: Tensor,
        renew: Tensor | None,
        assemble: Callable[[], Tensor | None],
    ) -> tuple[Tensor, Tensor] | None:
        """Solutions of the wanted entries of `rhs` `[B, n, d]` from the kept factors, factorising H
        anew (`assemble()`: its band storage `[B, N, u + 1]`) for the wanted entries without one
        or flagged in `renew` `[B]`. None where H is not positive definite at such an entry (or
        `assemble` returns None): the caller's usual path takes it."""
        batch = rhs.shape[0]
        record = self._factors.pop(key, None)
        factors = list(record[1]) if record is not None and record[0] is layout else [None] * batch
        need = torch.tensor([factor is None for factor in factors], device=wanted.device)
        if renew is not None:
            need |= renew
        rows = torch.nonzero(wanted & need).reshape(-1).tolist()
        if rows:
            bands = assemble()
            if bands is None:
                return None
            for row, factor in zip(rows, factorise_bands(bands[rows]), strict=True):
                factors[row] = factor
        # kept even where a new factor failed: the other entries' factors still serve
        self._factors[key] = (layout, factors)
        while len(self._factors) > self.capacity:
            del self._factors[next(iter(self._factors))]
        if any(factors[row] is None for row in rows):
            return None
        solution, positive_definite = substitute_bands(factors, rhs.reshape(batch, -1), layout)
        return _band_result(solution, positive_definite, rhs, wanted)
