"""The function every optimizer minimises, and the one convergence measure they share."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.objective import compiled as compiled_functions
from energysim.objective import compiled_hessian, evaluation
from energysim.objective.derivatives import HessianOperator, element_groups, hessian_operator


def _admissible(limits: Tensor) -> bool:
    """Whether every step limit is finite (`max_step` gives NaN where a start is not admissible):
    their sum is, as the limits lie in [0, 1]. One eager operation where `isfinite(...).all()` is
    five, a few times per Newton iteration."""
    return math.isfinite(float(limits.sum()))


@dataclass(frozen=True)
class LineTrial:
    """`Objective.trial`'s results, per batch entry.

    Attributes:
        step: the largest admissible fraction of the direction, at most 1, `[B]`.
        x: where that step lands, `[B, n, d]`, in m.
        energy: E there `[B]`, in J; gradient: ∇E there `[B, n, d]`, in N.
        slope: the slope of E along the direction at the start `[B]`, in J; trial_slope: at `x`.
        residual: the velocity residual at `x` `[B]`, in m/s.
        hints: the curvature hints of an iteration that ends at `x`, one per term that declares
            them, in the terms' order (`Objective.update_curvature_hints`), where the evaluation
            gave them (a compiled batch's); None otherwise.
        verdict: what the caller's `judge` made of the trial (`Objective.trial`).
    """

    step: Tensor
    x: Tensor
    energy: Tensor
    gradient: Tensor
    slope: Tensor
    trial_slope: Tensor
    residual: Tensor
    hints: tuple[Tensor, ...] | None = None
    verdict: tuple[Tensor, ...] | None = None


@dataclass
class Objective:
    """E(x) = Σ_i E_i(x) over the free vertices, with counters of what solvers evaluated.

    Args:
        terms: energy terms; each maps `[B, n, d]` to `[B]`, in J.
        free: which vertices move, shape `[n]`, bool; fixed ones keep their value in `x0`.
        residual_scale: h / m_i per vertex, shape `[n]`, in s/kg: the velocity residual is
            `residual_scale · ∇E` in m/s (the implicit-Euler momentum residual when the inertia
            term is in `terms`).
        action: the step's action, shape `[B, a]`, or None.
        anchor: positions `[B, n, d]` near the solution, or None. Linear terms (gravity) are
            evaluated on x − anchor: that changes E by a constant only, but keeps its rounding
            error proportional to the displacement rather than to the absolute positions, so
            line searches still see the energy fall when the residual is tiny.
        subset: builds the objective of some batch entries alone (their indices, `[k]` int64; the
            same energies, from sliced data), or None. A solver may then drop the entries that
            have converged instead of computing on them until the slowest one has.
        compiled: evaluate through `torch.compile`d functions (`energysim.objective.compiled`) where every
            term has the closed forms they call; solvers set it from their `compile` option.
    """

    terms: Sequence[EnergyTerm]
    free: Tensor
    residual_scale: Tensor
    action: Tensor | None = None
    anchor: Tensor | None = None
    energy_evals: int = 0
    grad_evals: int = 0
    subset: Callable[[Tensor], Objective] | None = field(default=None, repr=False)
    compiled: bool = False

    _closed_forms: dict[bool, bool] = field(default_factory=dict, init=False, repr=False)
    # the Hessian part of the terms with a constant Hessian, per storage, and the terms' float32
    # copies (`compiled_hessian`)
    _constant_hessians: dict[object, object] = field(default_factory=dict, init=False, repr=False)
    _element_groups: list[Tensor] | None = field(default=None, init=False, repr=False)

    def _compiles(self, *, hessian: bool = False) -> bool:
        if not self.compiled:
            return False
        # the terms are fixed for an objective's life: ask them once per kind (it was asked
        # several times per Newton iteration)
        if hessian not in self._closed_forms:
            self._closed_forms[hessian] = compiled_functions.has_closed_forms(self.terms, hessian=hessian)
        return self._closed_forms[hessian]

    def energy(self, x: Tensor) -> Tensor:
        """E(x), shape `[B]`, in J."""
        self.energy_evals += 1
        if self._compiles():
            value = compiled_functions.energy(self.terms, self.anchor, self.action, x)
            if value is not None:
                return value
        with torch.no_grad():
            return self._total(x)

    def _total(self, x: Tensor) -> Tensor:
        return evaluation.total_energy(self.terms, self.anchor, self.action, x)

    def energy_and_gradient(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """E(x) `[B]` in J and ∇E(x) `[B, n, d]` in N, zero on fixed vertices.

        Terms with closed-form kernels (`has_gradient_kernel`) skip autograd; the rest share one
        backward pass (`energysim.objective.evaluation.energy_and_gradient`).
        """
        self.grad_evals += 1
        if self._compiles():
            result = compiled_functions.energy_and_gradient(
                self.terms, self.anchor, self.action, self.free, x
            )
            if result is not None:
                return result
        return evaluation.energy_and_gradient(self.terms, self.anchor, self.action, self.free, x)

    def slice_constant_hessians_of(self, parent: Objective, entries: Tensor) -> None:
        """Take the Hessian part of the terms with a constant Hessian from `parent`'s storage, rows
        `entries` `[k]`, where it has one, instead of assembling it again (`compiled_hessian`). This
        objective must be those rows of `parent`: its constant terms sliced from the parent's."""
        self._constant_hessians[compiled_hessian.PARENT] = (parent._constant_hessians, entries)

    def update_curvature_hints(
        self, previous: Tensor, current: Tensor, hints: Sequence[Tensor] | None = None
    ) -> None:
        """Show one Newton iteration, from `previous` to `current` (`[B, n, d]`), to the terms that
        adapt their next Hessian blocks to it (`EnergyTerm.curvature_hint`). `hints`: those terms'
        hints for it, in their order, where the caller has them (`LineStep.hints`: from the line
        search's compiled trial, and for rows that searched again alone, from their own search); else
        they are computed here, eagerly: a few small operations, which a compiled call of their own
        would cost more than (docs/contact.md)."""
        if hints is None:
            hints = self.curvature_hints(previous, current)
        hinting = [term for term in self.terms if term.has_curvature_hint]
        for term, hint in zip(hinting, hints, strict=True):
            term.set_curvature_hint(hint)

    def curvature_hints(self, previous: Tensor, current: Tensor) -> tuple[Tensor, ...]:
        """The curvature hints of one Newton iteration from `previous` to `current` (`[B, n, d]`) of
        every term that declares them, in the terms' order (`EnergyTerm.curvature_hint`), eagerly."""
        return tuple(term.curvature_hint(previous, current) for term in self.terms if term.has_curvature_hint)

    def residual(self, gradient: Tensor) -> Tensor:
        """‖h M⁻¹ ∇E‖∞ over free DOFs, shape `[B]`, in m/s."""
        scaled = gradient * self.residual_scale[:, None]
        return scaled.abs().amax(dim=(-1, -2))

    def max_step(self, x: Tensor, dx: Tensor) -> Tensor:
        """Largest admissible step fraction along `dx`, shape `[B]`, at most 1.

        Raises:
            ValueError: `x` is not admissible for some term (that term's `max_step` says why).
        """
        limit = compiled_functions.step_limit(self.terms, x, dx)
        if not _admissible(limit):
            for term in self.terms:
                term.max_step(x, dx)  # the term where x is not admissible raises
        return limit

    def trial(
        self,
        x: Tensor,
        direction: Tensor,
        gradient: Tensor,
        judge: Callable[..., tuple[Tensor, ...]],
        judged_with: tuple,
    ) -> LineTrial:
        """The first trial of a line search from `x` along `direction`: the largest admissible step
        (`max_step`), and the energy, gradient and residual where it lands, with the slopes of E along
        `direction` at both ends (`gradient` is ∇E(x)). One compiled call where `compiled` (a line
        search's bookkeeping costs as much as its evaluation on a small body, eagerly).

        `judge`: the search's test of the trial, `judge(step, slope, E there, slope there,
        *judged_with)`, a module-level function of tensors evaluated in the same call
        (`LineTrial.verdict`): in the compiled one where the objective compiles, instead of some
        fifty small eager operations a search. The compiled call is guarded on `judge` and on the
        structure of `judged_with`: keep both the same from call to call (torch 2.13's Dynamo fails
        on a recompilation whose `judged_with` lost a tensor, and the objective then evaluates its
        trials eagerly).

        Raises:
            ValueError: `x` is not admissible for some term (from `max_step`).
        """
        judging = (judge, judged_with)
        if self._compiles():
            result = compiled_functions.trial(
                self.terms, self.anchor, self.action, self.free, self.residual_scale, x, direction, gradient,
                *judging,
            )
            if result is not None:
                self.grad_evals += 1
                trial = LineTrial(*result)
                if not _admissible(trial.step):
                    self.max_step(x, direction)  # raises where x is not admissible
                return trial
        self.grad_evals += 1
        arguments = (self.terms, self.anchor, self.action, self.free, self.residual_scale)
        trial = LineTrial(*evaluation.trial(*arguments, x, direction, gradient, *judging))
        if not _admissible(trial.step):
            self.max_step(x, direction)  # raises where x is not admissible
        return trial

    def cut_back(self, origin: Tensor, targets: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        """Each of `targets` (`[B, n, d]` each) moved back towards `origin` to the largest admissible
        fraction of the way there (`max_step`), and E at `origin` and at every cut: shapes
        `[k, B, n, d]` and `[k + 1, B]`. One compiled call where `compiled` (a warm start's choice).

        Raises:
            ValueError: `origin` is not admissible for some term (from `max_step`).
        """
        self.energy_evals += len(targets) + 1
        if self._compiles():
            result = compiled_functions.cut_back(self.terms, self.anchor, self.action, origin, targets)
            if result is not None:
                cuts, energies, limits = result
                if not _admissible(limits):
                    self.max_step(origin, targets[0] - origin)  # raises where origin is not admissible
                return cuts, energies
        with torch.no_grad():
            arguments = (self.terms, self.anchor, self.action)
            cuts, energies, limits = evaluation.cut_back(*arguments, origin, targets)
        if not _admissible(limits):
            self.max_step(origin, targets[0] - origin)  # raises where origin is not admissible
        return cuts, energies

    def element_groups(self) -> list[Tensor]:
        """The vertex indices `[m, k]` of each group of nonlinear element terms on the same elements
        (`derivatives.element_groups`), in the order `hessian` assembles their summed blocks (what
        the sparsity pattern is built from). Asked once per objective, as `_compiles`."""
        if self._element_groups is None:
            groups = element_groups(self.terms)
            self._element_groups = [self.terms[group[0]].element_vertices for group in groups]
        return list(self._element_groups)

    def dense_hessian(self, x: Tensor) -> Tensor | None:
        """∇²E(x) as dense `[B, n·d, n·d]` matrices by the compiled function, fixed DOFs eliminated;
        None unless `compiled` and every term has closed-form blocks (then use `hessian`)."""
        if not self._compiles(hessian=True):
            return None
        return compiled_hessian.dense_hessian(
            self.terms, self.action, self.free, x, self._constant_hessians
        )

    def band_hessian(self, x: Tensor, layout: LevelLayout, *, single: bool = False) -> Tensor | None:
        """∇²E(x) in `layout`'s band storage `[B, N, u + 1]` (`energysim.linalg.banded`) by the compiled
        function, fixed DOFs eliminated; None as for `dense_hessian`. `single`: in float32, for a
        float32 factorisation (`compiled_hessian.band_hessian`)."""
        if not self._compiles(hessian=True):
            return None
        return compiled_hessian.band_hessian(
            self.terms, self.action, self.free, x, layout, self._constant_hessians, single=single
        )

    def level_hessian(self, x: Tensor, layout: LevelLayout) -> tuple[Tensor, Tensor] | None:
        """∇²E(x) as `layout`'s diagonal `[B, L, S, S]` and sub-diagonal `[B, L−1, S, S]` level blocks
        (`energysim.linalg.block_tridiagonal`) by the compiled function, fixed DOFs eliminated; None
        as for `dense_hessian`."""
        if not self._compiles(hessian=True):
            return None
        return compiled_hessian.level_hessian(
            self.terms, self.action, self.free, x, layout, self._constant_hessians
        )

    def hessian(
        self, x: Tensor, *, use_element_blocks: bool = True, project: bool = False
    ) -> HessianOperator:
        """∇²E(x) as an operator (see `energysim.objective.derivatives.hessian_operator`)."""
        return hessian_operator(
            self.terms, x, self.action, self.free, use_element_blocks=use_element_blocks, project=project
        )
