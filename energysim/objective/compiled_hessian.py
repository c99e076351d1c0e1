"""The step objective's Hessian by the compiled function (`energysim.objective.compiled`), scattered
straight into the storage a direct solve factorises: dense `[B, N, N]` matrices, LAPACK's band storage
(`energysim.linalg.banded`, the CPU's solve) or the level blocks of the block-tridiagonal solve
(`energysim.linalg.level_storage`, a batch's solve on a GPU), fixed DOFs eliminated, with no CSR
matrix in between. One compiled function computes the entries for all three; only where each entry
lands differs.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.linalg.assembly import dof_indices
from energysim.linalg.banded import (
    band_diagonal_positions,
    band_length,
    band_positions,
    band_upper_positions,
    eliminate_fixed_in_bands,
)
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.linalg.level_storage import (
    eliminate_fixed_in_levels,
    level_diagonal_positions,
    level_length,
    level_positions,
    padding_identity,
)
from energysim.objective.compiled import BATCH_LAST_MIN_BATCH, call
from energysim.objective.derivatives import element_groups

__all__ = ["band_hessian", "dense_hessian", "level_hessian"]


def _hessian_in_storage(
    terms: Sequence[EnergyTerm],
    action: Tensor | None,
    x: Tensor,
    positions: Callable[[Tensor], Tensor],
    diagonal: Tensor,
    length: int,
) -> Tensor | None:
    """Every term's Hessian entries in one flat storage of `length` entries per batch entry, `[B,
    length]`, by the compiled function: each group's element blocks at `positions(element_vertices)`
    (the extra slot `length` takes what the storage drops), per-vertex diagonals at `diagonal`."""
    groups = tuple(
        (members, positions(terms[members[0]].element_vertices)) for members in element_groups(terms)
    )
    return call("hessian_entries", tuple(terms), action, x, groups, diagonal, length)


def _fixed_dofs(free: Tensor, dim: int) -> Tensor | None:
    # the fixed DOFs `[n·d]` (DOF = vertex·d + axis) of the per-vertex `free` `[n]`; None if none is
    if bool(free.all()):
        return None
    return (~free)[:, None].expand(free.shape[0], dim).reshape(-1)


def dense_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor
) -> Tensor | None:
    """∇²E(x) as dense `[B, n·d, n·d]` matrices, fixed DOFs eliminated (identity rows and columns),
    by the compiled function, or None."""
    batch, n, dim = x.shape
    size = n * dim

    def positions(element_vertices: Tensor) -> Tensor:
        dofs = dof_indices(element_vertices, dim)
        return (dofs[:, :, None] * size + dofs[:, None, :]).reshape(-1)

    diagonal = torch.arange(size, device=x.device) * (size + 1)
    flat = _hessian_in_storage(terms, action, x, positions, diagonal, size * size)
    if flat is None:
        return None
    dense = flat.reshape(batch, size, size)
    fixed = _fixed_dofs(free, dim)
    if fixed is not None:
        # fixed DOFs get the rows and columns of the identity, as in `energysim.linalg.assembly.assemble`
        kept = (~fixed).to(x.dtype)
        dense = dense * kept[:, None] * kept[None, :] + torch.diag(fixed.to(x.dtype))
    return dense


def band_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor, layout: LevelLayout
) -> Tensor | None:
    """∇²E(x) in `layout`'s band storage, `[B, N, u + 1]` (`energysim.linalg.banded`), fixed DOFs
    eliminated, by the compiled function, or None."""
    batch, n, dim = x.shape
    diagonal = band_diagonal_positions(layout)
    if batch >= BATCH_LAST_MIN_BATCH:
        # batch-last: every element kernel one loop vectorised over the batch, half the entries
        groups = tuple(
            (members, band_upper_positions(layout, terms[members[0]].element_vertices, dim))
            for members in element_groups(terms)
        )
        length = band_length(layout)
        flat = call("hessian_entries_batch_last", tuple(terms), action, x, groups, diagonal, length)
    else:
        positions = functools.partial(band_positions, layout, dim=dim)
        flat = _hessian_in_storage(terms, action, x, positions, diagonal, band_length(layout))
    if flat is None:
        return None
    bands = flat.reshape(batch, n * dim, layout.half_bandwidth + 1)
    fixed = _fixed_dofs(free, dim)
    return bands if fixed is None else eliminate_fixed_in_bands(bands, layout, fixed)


def level_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor, layout: LevelLayout
) -> tuple[Tensor, Tensor] | None:
    """∇²E(x) as `layout`'s level blocks (`energysim.linalg.level_storage`): the diagonal blocks
    `[B, L, S, S]` and the sub-diagonal ones `[B, L−1, S, S]`, padding and fixed DOFs given identity
    rows, by the compiled function, or None."""
    batch, _, dim = x.shape
    positions = functools.partial(level_positions, layout, dim=dim)
    diagonal = level_diagonal_positions(layout)
    flat = _hessian_in_storage(terms, action, x, positions, diagonal, level_length(layout))
    if flat is None:
        return None
    flat = flat + padding_identity(layout, x.dtype)
    fixed = _fixed_dofs(free, dim)
    if fixed is not None:
        flat = eliminate_fixed_in_levels(flat, layout, fixed)
    levels, size = layout.num_levels, layout.level_size
    split = levels * size * size
    return (
        flat[:, :split].reshape(batch, levels, size, size),
        flat[:, split:].reshape(batch, levels - 1, size, size),
    )
