"""Where a Hessian's entries go when it is assembled straight into level blocks.

`energysim.linalg.block_tridiagonal` factorises a Hessian from its diagonal `[B, L, S, S]` and
sub-diagonal `[B, L−1, S, S]` blocks over breadth-first vertex levels. Eagerly these are gathered
from an assembled CSR matrix (`gather_blocks`); the compiled Hessian
(`energysim.objective.compiled_hessian.level_hessian`) instead scatters every element block straight into one
flat buffer per batch entry, L diagonal blocks then L − 1 sub-diagonal ones, laid out as
`gather_blocks` lays them out, with no CSR matrix in between. The maps here say where each entry
lands; they are built once per layout and cached.
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.linalg.assembly import dof_indices
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.linalg.caching import IdentityCache

_MAPS: IdentityCache[Tensor] = IdentityCache(capacity=32)


def level_length(layout: LevelLayout) -> int:
    """Entries of one matrix's level storage, (2L − 1)·S²."""
    return (2 * layout.num_levels - 1) * layout.level_size**2


def level_positions(layout: LevelLayout, element_vertices: Tensor, dim: int) -> Tensor:
    """Where each entry of element Hessian blocks `[m, k·d, k·d]` (flattened) lands in one matrix's
    level storage, flattened, shape `[m·(k·d)²]`: a diagonal block where both DOFs lie in one level,
    the sub-diagonal block A_{k,k−1} where the row's level is one below the column's. Entries above
    the block diagonal (they enter through their transposes) go to the extra slot `level_length`."""

    def build() -> Tensor:
        size = layout.level_size
        slots = layout.dof_slots[dof_indices(element_vertices, dim)]
        level, local = slots // size, slots % size
        row_level, column_level = level[:, :, None], level[:, None, :]
        pair = local[:, :, None] * size + local[:, None, :]
        diagonal = row_level * size**2 + pair
        below = (layout.num_levels + row_level - 1) * size**2 + pair
        dropped = torch.full_like(pair, level_length(layout))
        placed = torch.where(row_level == column_level + 1, below, dropped)
        return torch.where(row_level == column_level, diagonal, placed).reshape(-1)

    return _MAPS.get((layout, element_vertices), ("positions", dim), build)


def level_diagonal_positions(layout: LevelLayout) -> Tensor:
    """Where each DOF's diagonal entry lies in level storage, shape `[N]` (DOF order)."""

    def build() -> Tensor:
        size = layout.level_size
        return (layout.dof_slots // size) * size**2 + (layout.dof_slots % size) * (size + 1)

    return _MAPS.get((layout,), "diagonal", build)


def padding_identity(layout: LevelLayout, dtype: torch.dtype) -> Tensor:
    """1 on the diagonal slots of the padding DOFs (levels narrower than S), else 0, shape
    `[(2L − 1)·S²]`: added to an assembled buffer, it gives the padding identity rows."""

    def build() -> Tensor:
        padding = layout.padding.clone()
        padding[level_diagonal_positions(layout)] = False
        return padding.to(dtype)

    return _MAPS.get((layout,), ("padding", dtype), build)


def eliminate_fixed_in_levels(flat: Tensor, layout: LevelLayout, fixed_dofs: Tensor) -> Tensor:
    """Level storage `flat` `[B, (2L − 1)·S²]` with the rows and columns of `fixed_dofs` (`[N]` bool,
    DOF order) replaced by the identity's, as `energysim.linalg.assembly.assemble` eliminates them.
    The mask and the identity are built once per layout and set of fixed DOFs, as for the band
    storage (`energysim.linalg.banded.eliminate_fixed_in_bands`)."""

    def build() -> Tensor:
        size, levels = layout.level_size, layout.num_levels
        slot_fixed = torch.zeros(levels * size, dtype=torch.bool, device=flat.device)
        slot_fixed[layout.dof_slots] = fixed_dofs
        kept = (~slot_fixed).to(flat.dtype).reshape(levels, size)
        diagonal = kept[:, :, None] * kept[:, None, :]
        lower = kept[1:, :, None] * kept[:-1, None, :]
        mask = torch.cat([diagonal.reshape(-1), lower.reshape(-1)])
        identity = torch.zeros_like(mask)
        identity[level_diagonal_positions(layout)[fixed_dofs]] = 1.0
        return torch.stack([mask, identity])

    key = ("fixed", fixed_dofs.cpu().numpy().tobytes(), flat.dtype, flat.device)
    mask, identity = _MAPS.get((layout,), key, build)
    return flat * mask + identity
