"""The step objective's Hessian by the compiled function (`energysim.objective.compiled`), scattered
straight into the storage a direct solve factorises: dense `[B, N, N]` matrices, LAPACK's band storage
(`energysim.linalg.banded`, the CPU's solve) or the level blocks of the block-tridiagonal solve
(`energysim.linalg.level_storage`, a batch's solve on a GPU), fixed DOFs eliminated, with no CSR
matrix in between. One compiled function computes the entries for all three; only where each entry
lands differs.

The terms whose Hessian does not depend on x (`EnergyTerm.has_constant_hessian`: the inertia, the
lagged viscosity) are assembled once per objective, into a storage kept in the `constant` cache the
objective passes; every later call starts from a copy of it and adds the other terms' entries. For 64
worms that took a band Hessian from 14.8 to 12.4 ms a call (docs/benchmarks.md). An objective of
some rows of another (a solver's subset of the entries still iterating) takes that part from its
parent's storage, sliced (`PARENT`), rather than assembling it again.
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
from energysim.objective.batch_last import takes_batch_last
from energysim.objective.compiled import call
from energysim.objective.derivatives import element_groups

__all__ = ["band_hessian", "dense_hessian", "level_hessian"]


# storage → positions of an element group's entries in it
Positions = Callable[[Tensor], Tensor]

# Where a subset objective's cache names its parent's cache and its rows there
# (`Objective.slice_constant_hessians_of`)
PARENT = "parent"


def _constant_start(constant: dict[object, object], key: object, batch_last: bool) -> Tensor | None:
    # the constant terms' storage under `key` (batch-last `[length + 1, B]` or element-major
    # `[B, length + 1]`), from this cache or sliced from the parent's; None where neither has it
    stored = constant.get(key)
    if stored is not None:
        return stored[0]
    link = constant.get(PARENT)
    if link is None:
        return None
    parent, rows = link
    stored = parent.get(key)
    if stored is None:
        return None
    storage, parent_batch_last = stored
    # `index_select`, not `storage[:, rows]`: 5× faster on the inner axis of a batch-last storage
    if parent_batch_last:
        return storage.index_select(1, rows) if batch_last else storage.T.index_select(0, rows)
    part = storage.index_select(0, rows)
    return part.T.contiguous() if batch_last else part


def _entries(
    name: str,
    terms: Sequence[EnergyTerm],
    action: Tensor | None,
    x: Tensor,
    positions: Positions,
    diagonal: Tensor,
    length: int,
    constant: dict[object, object] | None,
    key: object,
    single: bool = False,
) -> Tensor | None:
    """Every term's Hessian entries by the compiled function `name`, as it returns them (element-major
    `[B, length + 1]`, batch-last `[length + 1, B]`, the last slot taking what the storage drops): each
    group's element blocks at `positions(element_vertices)`, per-vertex diagonals at `diagonal`.
    With a `constant` cache, the constant terms' part is computed once under `key` (by
    `constant_<name>`, as the whole storage, or sliced from a parent's, `PARENT`; `key` names the
    storage, not the batch size) and the others' entries are added to a copy of it; None
    where compiling failed. `single`: a float32 storage, see `band_hessian`."""
    copies = {} if constant is None else constant  # float32 copies of terms, kept with the objective's

    def arguments(of: tuple[EnergyTerm, ...]) -> tuple[tuple[EnergyTerm, ...], tuple]:
        # the terms as the compiled function reads them, and their groups (members, positions,
        # relative): a relative group is evaluated in float32 at positions relative to each element's
        # first corner, from float32 copies of its terms (`EnergyTerm.in_precision`)
        evaluated, grouped = list(of), []
        for members in element_groups(of):
            relative = single and all(of[member].is_translation_invariant for member in members)
            for member in members if relative else ():
                copy_key = ("float32", id(of[member]))
                if copy_key not in copies:
                    kept = _kept_copy(copies, copy_key)
                    copies[copy_key] = of[member].in_precision(torch.float32) if kept is None else kept
                evaluated[member] = copies[copy_key]
            grouped.append((members, positions(of[members[0]].element_vertices), relative))
        return tuple(evaluated), tuple(grouped)

    def entries(function: str, of: tuple[EnergyTerm, ...], start: Tensor | None) -> Tensor | None:
        # built once per function and storage: an objective's terms are fixed for its life
        evaluated, grouped = _kept(copies, ("arguments", function, key), lambda: arguments(of))
        arguments_of = (evaluated, action, x, grouped, diagonal, length, start, single)
        return call(function, *arguments_of, batch=x.shape[0])

    fixed = tuple(term for term in terms if term.has_constant_hessian and not term.is_linear)
    if constant is None or not fixed:
        return entries(name, tuple(terms), None)
    batch_last = name.endswith("_batch_last")
    start = _constant_start(constant, key, batch_last)
    if start is None:
        start = entries(f"constant_{name}", fixed, None)
        if start is None:
            return None
    constant[key] = (start, batch_last)
    # (no varying terms: the call copies the start into the returned storage)
    varying = tuple(term for term in terms if not term.has_constant_hessian and not term.is_linear)
    return entries(name, varying, start)


def _kept(cache: dict[object, object], key: object, build: Callable[[], object]) -> object:
    # `cache[key]`, built by `build` where missing
    if key not in cache:
        cache[key] = build()
    return cache[key]


def _kept_copy(cache: dict[object, object], key: object) -> EnergyTerm | None:
    # the float32 copy of a term under `key` that the objective this one is rows of keeps (`PARENT`),
    # or None. A term without per-entry data is the same object in every subset of a solve (its
    # `rows` is itself), and the parent holds it alive, so its id names it there too.
    link = cache.get(PARENT)
    while link is not None:
        cache = link[0]
        if key in cache:
            return cache[key]
        link = cache.get(PARENT)
    return None


def _fixed_dofs(free: Tensor, dim: int, cache: dict[object, object] | None = None) -> Tensor | None:
    # the fixed DOFs `[n·d]` (DOF = vertex·d + axis) of the per-vertex `free` `[n]`; None if none is.
    # Kept in `cache` for this `free` tensor (an objective's, asked every Newton iteration)
    kept = None if cache is None else cache.get("fixed")
    if kept is not None and kept[0] is free and kept[1] == dim:
        return kept[2]
    fixed = None if bool(free.all()) else (~free)[:, None].expand(free.shape[0], dim).reshape(-1)
    if cache is not None:
        cache["fixed"] = (free, dim, fixed)
    return fixed


def dense_hessian(
    terms: Sequence[EnergyTerm],
    action: Tensor | None,
    free: Tensor,
    x: Tensor,
    constant: dict[object, object] | None = None,
) -> Tensor | None:
    """∇²E(x) as dense `[B, n·d, n·d]` matrices, fixed DOFs eliminated (identity rows and columns),
    by the compiled function, or None. `constant`: the objective's cache of its constant terms'
    part (see the module's docstring), or None to assemble every term each call."""
    batch, n, dim = x.shape
    size = n * dim

    def positions(element_vertices: Tensor) -> Tensor:
        dofs = dof_indices(element_vertices, dim)
        return (dofs[:, :, None] * size + dofs[:, None, :]).reshape(-1)

    diagonal = torch.arange(size, device=x.device) * (size + 1)
    key = ("dense", x.shape[1:], x.dtype, x.device)
    flat = _entries("hessian_entries", terms, action, x, positions, diagonal, size * size, constant, key)
    if flat is None:
        return None
    dense = flat[:, : size * size].reshape(batch, size, size)
    fixed = _fixed_dofs(free, dim)
    if fixed is not None:
        # fixed DOFs get the rows and columns of the identity, as in `energysim.linalg.assembly.assemble`
        kept = (~fixed).to(x.dtype)
        dense = dense * kept[:, None] * kept[None, :] + torch.diag(fixed.to(x.dtype))
    return dense


def band_hessian(
    terms: Sequence[EnergyTerm],
    action: Tensor | None,
    free: Tensor,
    x: Tensor,
    layout: LevelLayout,
    constant: dict[object, object] | None = None,
    *,
    single: bool = False,
) -> Tensor | None:
    """∇²E(x) in `layout`'s band storage, `[B, N, u + 1]` (`energysim.linalg.banded`), fixed DOFs
    eliminated, by the compiled function, or None. `constant`: as for `dense_hessian`. Where the batch
    is laid out batch-last (`takes_batch_last`), a transposed view of batch-last memory.

    `single`: the storage in float32, for a float32 factorisation. The translation-invariant terms
    (`EnergyTerm.is_translation_invariant`) are evaluated in float32 at positions relative to each
    element's first corner, so their blocks keep float32's relative precision however far the body
    has moved; the others in float64, their entries rounded as they are added."""
    batch, n, dim = x.shape
    diagonal = band_diagonal_positions(layout)
    length = band_length(layout)
    key = ("band", id(layout), x.shape[1:], x.dtype, x.device, single)
    if takes_batch_last(batch, x.device):
        # batch-last: every element kernel one loop vectorised over the batch, half the entries
        positions = functools.partial(band_upper_positions, layout, dim=dim)
        name = "hessian_entries_batch_last"
        flat = _entries(name, terms, action, x, positions, diagonal, length, constant, key, single)
        flat = None if flat is None else flat[:length].T
    else:
        positions = functools.partial(band_positions, layout, dim=dim)
        arguments = (terms, action, x, positions, diagonal, length, constant, key, single)
        flat = _entries("hessian_entries", *arguments)
        flat = None if flat is None else flat[:, :length]
    if flat is None:
        return None
    bands = flat.reshape(batch, n * dim, layout.half_bandwidth + 1)
    fixed = _fixed_dofs(free, dim, constant)
    return bands if fixed is None else eliminate_fixed_in_bands(bands, layout, fixed)


def level_hessian(
    terms: Sequence[EnergyTerm],
    action: Tensor | None,
    free: Tensor,
    x: Tensor,
    layout: LevelLayout,
    constant: dict[object, object] | None = None,
) -> tuple[Tensor, Tensor] | None:
    """∇²E(x) as `layout`'s level blocks (`energysim.linalg.level_storage`): the diagonal blocks
    `[B, L, S, S]` and the sub-diagonal ones `[B, L−1, S, S]`, padding and fixed DOFs given identity
    rows, by the compiled function, or None. `constant`: as for `dense_hessian`."""
    batch, _, dim = x.shape
    positions = functools.partial(level_positions, layout, dim=dim)
    diagonal = level_diagonal_positions(layout)
    key = ("levels", id(layout), x.shape[1:], x.dtype, x.device)
    length = level_length(layout)
    flat = _entries("hessian_entries", terms, action, x, positions, diagonal, length, constant, key)
    if flat is None:
        return None
    flat = flat[:, :length] + padding_identity(layout, x.dtype)
    fixed = _fixed_dofs(free, dim)
    if fixed is not None:
        flat = eliminate_fixed_in_levels(flat, layout, fixed)
    levels, size = layout.num_levels, layout.level_size
    split = levels * size * size
    return (
        flat[:, :split].reshape(batch, levels, size, size),
        flat[:, split:].reshape(batch, levels - 1, size, size),
    )
