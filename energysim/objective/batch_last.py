"""Leapfrog kicks, energies, gradients and Hessians of many bodies at once, laid out batch-last, for
the compiled functions of `energysim.objective.compiled`.

States are `[n·d, B]`, the batch innermost: gathers and scatters move rows of B contiguous numbers,
and every element kernel (`ElementEnergy.batch_last_forces`, `batch_last_energy_and_forces`,
`batch_last_hessian_entries`, `DissipativeEnergy.batch_last_dissipation_gradient`) is scalar
arithmetic that the compiler vectorises over the batch. `energysim.objective.compiled` drives the
leapfrog kicks (`energysim.integrators.explicit.leapfrog`'s) and, through
`energysim.objective.compiled_hessian`, the band Hessian of a batch; `energysim.objective.evaluation`
takes the element terms' energy and gradient from here while it is compiled for a CPU batch
(`evaluates_batch_last`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from energysim.contact.projection import project_contacts
from energysim.energies.base import ElementEnergy, EnergyTerm, has_vertex_diagonal, is_dissipative
from energysim.objective.derivatives import element_groups

# Compiled batches from this size on take the batch-last layout where every element term has
# `batch_last_forces`. On the CPU every size does: even one body's compiled evaluations ran faster
# batch-last than per element (docs/envs.md); tests raise it there to cover the per-element
# layout. Elsewhere a batch of fewer would run its vectors mostly empty.
BATCH_LAST_MIN_BATCH = {"cpu": 1}
OTHER_DEVICES_BATCH_LAST_MIN_BATCH = 8


def takes_batch_last(batch: int, device: torch.device) -> bool:
    """Whether a compiled batch of `batch` bodies on `device` is laid out batch-last
    (`BATCH_LAST_MIN_BATCH`), read at each call, so that changing the module's table changes every
    caller."""
    return batch >= BATCH_LAST_MIN_BATCH.get(device.type, OTHER_DEVICES_BATCH_LAST_MIN_BATCH)


class BatchLastPlan(NamedTuple):
    """How `leapfrog` kicks batch-last: the `elastic` terms, their `groups` (indices into
    `elastic`) and the `dissipative` terms, each kicked by a compiled function of its own."""

    elastic: tuple[EnergyTerm, ...]
    groups: tuple[tuple[int, ...], ...]
    dissipative: tuple[EnergyTerm, ...]


def batch_last_plan(terms: Sequence[EnergyTerm]) -> BatchLastPlan | None:
    """For batch-last kicks: the terms with `batch_last_forces` grouped by equal `element_vertices`
    (`element_groups`), and the dissipative terms (`batch_last_dissipation_gradient`); None where
    another term is neither linear with a closed-form gradient (gravity) nor one of those."""
    dissipative = tuple(term for term in terms if is_dissipative(term))
    elastic = tuple(term for term in terms if not is_dissipative(term))
    groups = tuple(tuple(group) for group in element_groups(elastic, _has_batch_last_forces))
    grouped = {index for group in groups for index in group}
    for index, term in enumerate(elastic):
        if index not in grouped and not (term.is_linear and term.has_gradient_kernel):
            return None
    if not all(term.has_batch_last_kernel for term in dissipative):
        return None
    return BatchLastPlan(elastic, groups, dissipative)


def _has_batch_last_forces(term: EnergyTerm) -> bool:
    return isinstance(term, ElementEnergy) and term.has_batch_last_kernel


def _corner_dofs(term: EnergyTerm, dim: int, device: torch.device) -> Tensor:
    # the DOF rows `[d, k, m]` of the corners of `term`'s elements in a `[n·d, B]` state
    return term.element_vertices.T[None] * dim + torch.arange(dim, device=device)[:, None, None]


def _corners(values: Tensor, corner_dofs: Tensor) -> list[list[Tensor]]:
    # rows `corner_dofs` of `values` `[n·d, B]` as corners[i][b] `[m, B]`
    gathered = values[corner_dofs]
    return [[gathered[i, b] for b in range(gathered.shape[1])] for i in range(gathered.shape[0])]


def _scatter_corners(
    gradient: Tensor, corner_dofs: Tensor, forces: Sequence[list[list[Tensor]]], dim: int
) -> Tensor:
    # Σ over `forces` (each [i][b] `[m, B]`) added onto the DOF rows of `gradient` `[n·d, B]`
    corners = corner_dofs.shape[1]
    # one stack in `corner_dofs`' order: from a stack of stacks, the compiled code copied each inner
    # stack into the outer one
    total = torch.stack([sum(f[i][b] for f in forces) for i in range(dim) for b in range(corners)])
    return gradient.index_add(0, corner_dofs.reshape(-1), total.reshape(-1, gradient.shape[1]))


def kick_batch_last(
    terms: tuple[EnergyTerm, ...],
    groups: tuple[tuple[int, ...], ...],
    obstacles: tuple[EnergyTerm, ...],
    action: Tensor | None,
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: Tensor,
    drift: Tensor | None,
) -> tuple[Tensor, Tensor]:
    # One leapfrog kick at the midpoint x, on states laid out `[n·d, B]`, batch innermost: gathers
    # and scatters move rows of B contiguous numbers, and every element kernel (`batch_last_forces`)
    # is one loop vectorised over the batch, the terms of a group sharing one gather and one
    # scatter. Terms outside `groups` (gravity) give their gradient in the usual layout. With a
    # `drift`, the contact projection and the drift follow (`_finish_batch_last`); without one, the
    # caller's viscous kick does them (`viscous_kick_batch_last`).
    dofs, batch = x.shape
    n, dim = inverse_mass.shape[0], dofs // inverse_mass.shape[0]
    action_t = None if action is None else action.T
    grouped = {index for group in groups for index in group}
    gradient = x.new_zeros(dofs, batch)
    for group in groups:
        corner_dofs = _corner_dofs(terms[group[0]], dim, x.device)
        corners = _corners(x, corner_dofs)
        forces = [terms[index].batch_last_forces(corners, action_t) for index in group]
        gradient = _scatter_corners(gradient, corner_dofs, forces, dim)
    for index, term in enumerate(terms):
        if index not in grouped:
            natural = x.T.reshape(batch, n, dim)
            gradient = gradient + term.value_and_gradient(natural, action)[1].reshape(batch, dofs).T
    v = v - h * gradient * inverse_mass.repeat_interleave(dim)[:, None]
    if drift is None:
        return x, v
    return _finish_batch_last(obstacles, free, x, v, h, drift)


def viscous_kick_batch_last(
    terms: tuple[EnergyTerm, ...],
    obstacles: tuple[EnergyTerm, ...],
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: Tensor,
    drift: Tensor,
) -> tuple[Tensor, Tensor]:
    # The viscous kick of the dissipative `terms` at the velocity the elastic kick left
    # (`explicit.leapfrog`), then contact and drift. A compiled function of its own: in one with the
    # elastic kernels, which the compiler fuses with these over the same elements, the kick took
    # 2.1 ms where apart the two take 0.4 and 0.5 (64 worms, one thread).
    dofs, batch = x.shape
    dim = dofs // inverse_mass.shape[0]
    gradient = x.new_zeros(dofs, batch)
    for term in terms:
        corner_dofs = _corner_dofs(term, dim, x.device)
        forces = term.batch_last_dissipation_gradient(_corners(x, corner_dofs), _corners(v, corner_dofs))
        gradient = _scatter_corners(gradient, corner_dofs, [forces], dim)
    v = v - h * gradient * inverse_mass.repeat_interleave(dim)[:, None]
    return _finish_batch_last(obstacles, free, x, v, h, drift)


def _finish_batch_last(
    obstacles: tuple[EnergyTerm, ...], free: Tensor, x: Tensor, v: Tensor, h: Tensor, drift: Tensor
) -> tuple[Tensor, Tensor]:
    # a kick's contact projection and the drift after it, on `[n·d, B]` states
    dofs, batch = x.shape
    n = free.shape[0]
    if obstacles:
        natural = (x.T.reshape(batch, n, -1), v.T.reshape(batch, n, -1))
        v = project_contacts(obstacles, free, *natural, h).reshape(batch, dofs).T
    return x + drift * v, v


def evaluates_batch_last(terms: Sequence[EnergyTerm], x: Tensor) -> tuple[int, ...]:
    """The indices of the element terms whose energy and gradient `energysim.objective.evaluation`
    takes batch-last (`element_energy_and_gradient`): those with a gradient kernel, while a CPU batch
    laid out batch-last (`takes_batch_last`) is compiled; none otherwise (eagerly the entry-wise
    kernels are hundreds of small operations, and a GPU keeps the per-element layout)."""
    cpu = x.device.type == "cpu"
    if not (torch.compiler.is_compiling() and cpu and takes_batch_last(x.shape[0], x.device)):
        return ()
    return tuple(
        index
        for index, term in enumerate(terms)
        if isinstance(term, ElementEnergy) and term.has_gradient_kernel and not term.is_linear
    )


def element_energy_and_gradient(
    terms: Sequence[EnergyTerm], action: Tensor | None, x: Tensor
) -> tuple[Tensor, Tensor]:
    """Σ of the element `terms`' energies `[B]` in J and their gradient `[B, n, d]` in N at `x`
    `[B, n, d]`, batch-last (`batch_last_energy_and_forces`): one gather and one scatter per group
    of terms on the same elements."""
    batch, n, dim = x.shape
    states = x.reshape(batch, n * dim).T
    action_t = None if action is None else action.T
    total = x.new_zeros(batch)
    gradient = x.new_zeros(n * dim, batch)
    for group in _same_elements(terms):
        corner_dofs = _corner_dofs(terms[group[0]], dim, x.device)
        corners = _corners(states, corner_dofs)
        forces = []
        for index in group:
            energy, force = terms[index].batch_last_energy_and_forces(corners, action_t)
            total = total + energy.sum(dim=0)
            forces.append(force)
        gradient = _scatter_corners(gradient, corner_dofs, forces, dim)
    return total, gradient.T.reshape(batch, n, dim)


def curvature_hints(terms: Sequence[EnergyTerm], start: Tensor, end: Tensor) -> tuple[Tensor, ...] | None:
    """The curvature hints of an iteration from `start` to `end` (`[B, n, d]`) of every term that
    declares them (`EnergyTerm.batch_last_curvature_hint`), `[B, m]` each, in the terms' order; None
    where one of them has no batch-last form."""
    batch, n, dim = start.shape
    start_states, states = start.reshape(batch, n * dim).T, end.reshape(batch, n * dim).T
    hints = []
    for term in terms:
        if not term.has_curvature_hint:
            continue
        corner_dofs = _corner_dofs(term, dim, start.device)
        starts, ends = _corners(start_states, corner_dofs), _corners(states, corner_dofs)
        hint = term.batch_last_curvature_hint(starts, ends)
        if hint is None:
            return None
        hints.append(hint.T)
    return tuple(hints)


def _same_elements(terms: Sequence[EnergyTerm]) -> list[list[int]]:
    # `terms` grouped by the identity of their `element_vertices`: `element_groups` compares contents,
    # which a compiled function would have to leave its graph for
    groups: list[list[int]] = []
    for index, term in enumerate(terms):
        vertices = term.element_vertices
        group = next((group for group in groups if terms[group[0]].element_vertices is vertices), None)
        if group is None:
            groups.append([index])
        else:
            group.append(index)
    return groups


def vertex_diagonal(terms: Sequence[EnergyTerm], x: Tensor) -> Tensor | None:
    """Σ of the per-vertex Hessian diagonals (`VertexDiagonalEnergy`, the inertia) as one entry per
    DOF, `[B, n·d]`, or None where no term has one."""
    batch, n, dim = x.shape
    total = None
    for term in terms:
        if has_vertex_diagonal(term):
            diagonal = term.hessian_diagonal().reshape(-1, n, 1).expand(batch, n, dim).reshape(batch, n * dim)
            total = diagonal if total is None else total + diagonal
    return total


def hessian_entries_batch_last(
    terms: tuple[EnergyTerm, ...],
    action: Tensor | None,
    x: Tensor,
    groups: tuple[tuple[tuple[int, ...], Tensor, bool], ...],
    diagonal_positions: Tensor,
    length: int,
    start: Tensor | None = None,
    single: bool = False,
) -> Tensor:
    # `energysim.objective.compiled`'s `_hessian_entries` for a storage that keeps one triangle
    # (band storage), batch-last: each group's summed upper entries (`batch_last_hessian_entries`,
    # stacked element-major, `[m, P, B]`, so that each element's entries are written to one stretch
    # of memory) land at the group's positions (`band_upper_positions`) of a `[length + 1, B]`
    # storage (a copy of `start` where given; float32 with `single`, a `relative` group evaluated
    # in float32 at positions relative to each element's first corner), the per-vertex diagonals at
    # `diagonal_positions`; returned whole and batch-last: the band solve reads it through a
    # transposed view (the C kernels' tiles gather straight from it; LAPACK's path makes the copy
    # it needs)
    batch, n, dim = x.shape
    states = x.reshape(batch, n * dim).T
    dtype = torch.float32 if single else x.dtype
    action_t = None if action is None else action.T
    flat = x.new_zeros(length + 1, batch, dtype=dtype) if start is None else start.clone()
    diagonal = vertex_diagonal(terms, x)
    if diagonal is not None:
        flat.index_add_(0, diagonal_positions, diagonal.T.to(dtype))
    for members, positions, relative in groups:
        corners = _corners(states, _corner_dofs(terms[members[0]], dim, x.device))
        read = action_t
        if relative:
            corners = [[(corner - row[0]).to(dtype) for corner in row] for row in corners]
            read = None if action_t is None else action_t.to(dtype)
        entries = terms[members[0]].batch_last_hessian_entries(corners, read)
        for member in members[1:]:
            more = terms[member].batch_last_hessian_entries(corners, read)
            entries = [first + second for first, second in zip(entries, more, strict=True)]
        flat.index_add_(0, positions, torch.stack(entries, dim=1).reshape(-1, batch).to(dtype))
    return flat
