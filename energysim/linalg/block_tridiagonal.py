"""Direct solves of batched Hessians in block-tridiagonal form, by breadth-first level sets.

Number the vertices by their breadth-first distance (level) from a peripheral vertex of the mesh
graph (Cuthill–McKee levels). Every edge of the graph joins vertices in the same or in adjacent
levels, so with the DOFs ordered level by level the Hessian is block tridiagonal. Padding every
level to the widest one (s vertices, S = s·d DOFs; the padding DOFs get identity rows) gives
diagonal blocks `[B, L, S, S]` and sub-diagonal blocks `[B, L−1, S, S]`, read straight from the
CSR values with index maps computed once per sparsity pattern. A block Cholesky factorisation
then costs about B·L·S³ flops instead of the B·N³/3 of a dense one (N = n·d): for a long body
with L levels of a few vertices each, and a batch of them, that is tens of times cheaper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.linalg.assembly import SparsityPattern
from energysim.linalg.caching import IdentityCache

# a pseudo-peripheral start is found by a few sweeps of breadth-first search (George & Liu);
# more than this many hardly ever lengthens the level structure further
_PERIPHERAL_SWEEPS = 4
# components of at most this many vertices try every vertex as the start too (one breadth-first
# search each: 0.3 s for the starfish's 540 vertices, once per mesh): the sweeps' ends are not
# always the best, the quadruped's and the jumper's levels cost 0.57× and 0.47× theirs from the best
_EVERY_START_MAX_VERTICES = 640


def _breadth_first(neighbours: tuple[Tensor, Tensor], start: Tensor, num_vertices: int) -> Tensor:
    """Distance of every vertex from the vertices in `start` (`[n]` bool), −1 where unreachable.

    `neighbours` = (source, target) edge lists, both directions present. One Python iteration per
    level; each is a vectorised sweep over all edges.
    """
    source, target = neighbours
    level = torch.full((num_vertices,), -1, dtype=torch.int64, device=start.device)
    level[start] = 0
    frontier = start.clone()
    depth = 0
    while bool(frontier.any()):
        depth += 1
        reached = torch.zeros_like(frontier)
        reached[target[frontier[source]]] = True
        frontier = reached & (level < 0)
        level[frontier] = depth
    return level


def _vertex_edges(element_groups: Sequence[Tensor]) -> Tensor:
    """The mesh graph's edges `[2, E]` (source, target), both directions, each once: the vertex pairs
    that share an element of some group."""
    device = element_groups[0].device if element_groups else torch.device("cpu")
    pairs = [
        torch.stack([e[:, i], e[:, j]])
        for e in element_groups
        for i in range(e.shape[1])
        for j in range(e.shape[1])
        if i != j
    ]
    edges = torch.cat(pairs, dim=1) if pairs else torch.zeros(2, 0, dtype=torch.int64, device=device)
    return torch.unique(edges, dim=1)


def vertex_levels(element_groups: Sequence[Tensor], num_vertices: int) -> Tensor:
    """Breadth-first level of every vertex, shape `[n]` (int64, levels 0 … L−1).

    The levels of each connected component start from a pseudo-peripheral vertex (the end of a
    longest breadth-first path found by repeated sweeps), which makes them many and narrow; of the
    sweeps, the one of least factorisation cost L·s³ is kept, and in a small component (at most
    `_EVERY_START_MAX_VERTICES`) that of every vertex as the start. Components follow one another.
    Every element's vertices then lie in one level or two adjacent ones.

    Args:
        element_groups: vertex indices of the elements, each `[m, k]` (k vertices per element).
        num_vertices: n; vertices in no element form components of their own.
    """
    device = element_groups[0].device if element_groups else torch.device("cpu")
    edges = _vertex_edges(element_groups)
    neighbours = (edges[0], edges[1])
    degree = torch.bincount(edges[0], minlength=num_vertices)
    levels = torch.full((num_vertices,), -1, dtype=torch.int64, device=device)

    def levels_from(vertex: int) -> tuple[Tensor, int, int]:
        # the breadth-first levels from `vertex` (−1 outside its component), their cost L·S³ and L
        start = torch.zeros(num_vertices, dtype=torch.bool, device=device)
        start[vertex] = True
        level = _breadth_first(neighbours, start, num_vertices)
        widths = torch.bincount(level[level >= 0])
        return level, widths.numel() * int(widths.max()) ** 3, widths.numel()

    offset = 0
    while bool((levels < 0).any()):
        vertex = int(torch.nonzero(levels < 0)[0])
        best, best_cost, depth = None, None, -1
        for _ in range(_PERIPHERAL_SWEEPS):
            level, cost, count = levels_from(vertex)
            if best is None or cost < best_cost:
                best, best_cost = level, cost
            if count - 1 <= depth:
                break  # the eccentricity stopped growing: the start is pseudo-peripheral
            depth = count - 1
            # restart from a vertex of least degree in the last level
            last = torch.nonzero(level == depth).flatten()
            vertex = int(last[torch.argmin(degree[last])])
        component = torch.nonzero(best >= 0).flatten()
        if component.numel() <= _EVERY_START_MAX_VERTICES:
            for vertex in component.tolist():
                level, cost, _ = levels_from(vertex)
                if cost < best_cost:
                    best, best_cost = level, cost
        reached = best >= 0
        levels[reached] = best[reached] + offset
        offset = int(levels.max()) + 1
    return levels


def level_ranks(levels: Tensor, element_groups: Sequence[Tensor], num_vertices: int) -> Tensor:
    """Every vertex's place within its level, shape `[n]` (0 … width − 1): Cuthill–McKee's order.

    The first level by degree; each later one by the earliest place of a vertex's neighbours in
    the level before (then by degree, then by index), so that vertices coupled across two levels
    sit at similar places in both. With the DOFs level by level that keeps the band narrow: the
    worm's half-bandwidth is u = 32 instead of 44 with the vertices of a level in index order
    (a band Cholesky costs ∝ u²), the quadruped's 110 instead of 140 in the same levels
    (docs/solvers.md).
    """
    source, target = _vertex_edges(element_groups)
    degree = torch.bincount(source, minlength=num_vertices)
    degrees = int(degree.max()) + 1 if num_vertices else 1
    unplaced = num_vertices  # the "place" of a vertex not ordered yet: after every real one
    place = torch.full((num_vertices,), unplaced, dtype=torch.int64, device=levels.device)
    ranks = torch.empty_like(levels)
    source_level, target_level = levels[source], levels[target]
    offset = 0
    for level in range(int(levels.max()) + 1 if levels.numel() else 0):
        members = torch.nonzero(levels == level).flatten()
        back = (source_level == level) & (target_level == level - 1)
        earliest = torch.full_like(place, unplaced).scatter_reduce(
            0, source[back], place[target[back]], reduce="amin"
        )
        # one integer key: earliest neighbour place, then degree, then index
        key = (earliest[members] * degrees + degree[members]) * num_vertices + members
        ordered = members[torch.argsort(key)]
        width = torch.arange(ordered.numel(), device=levels.device)
        ranks[ordered] = width
        place[ordered] = offset + width
        offset += ordered.numel()
    return ranks


@dataclass(frozen=True)
class LevelLayout:
    """Where the DOFs and the CSR entries of one batch entry go in the block-tridiagonal form.

    Attributes:
        num_levels: L.
        level_size: S = s·d, DOFs per (padded) level.
        entries: stored entries of one batch entry's CSR matrix (nnz).
        dof_slots: padded position in `[0, L·S)` of every DOF, shape `[n·d]` (DOF = vertex·d + axis).
        value_positions: positions in one batch entry's CSR values that lie on or below the block
            diagonal, shape `[q]`.
        block_positions: where each lands in the flat buffer of L diagonal then L−1 sub-diagonal
            S×S blocks, shape `[q]`.
        padding: the buffer's values before the entries land, shape `[(2L−1)·S²]`: 1 on every
            diagonal slot, so padding DOFs get identity rows (real DOFs' diagonals are overwritten).
        band_order: the DOFs level by level without padding, shape `[n·d]` (position → DOF): an
            ordering in which the matrix is banded (`energysim.linalg.banded`).
        band_position: the inverse of `band_order` (DOF → position), shape `[n·d]`.
        half_bandwidth: u, the largest |i − j| of a stored entry in that ordering.
        band_entries: flat indices into a dense `[N, N]` matrix of LAPACK's lower band storage,
            transposed, shape `[N, u + 1]`: `[j, r]` is A[p(j + r), p(j)] for p = `band_order`
            (where j + r ≥ N, the corner LAPACK never reads, it points at entry 0).
    """

    num_levels: int
    level_size: int
    entries: int
    dof_slots: Tensor
    value_positions: Tensor
    block_positions: Tensor
    padding: Tensor
    band_order: Tensor
    band_position: Tensor
    half_bandwidth: int
    band_entries: Tensor

    @property
    def cost(self) -> int:
        """L·S³: the factorisation's flops per batch entry, up to a constant."""
        return self.num_levels * self.level_size**3


def level_layout(
    pattern: SparsityPattern, element_groups: Sequence[Tensor], num_vertices: int, dim: int
) -> LevelLayout:
    """The block-tridiagonal layout of `pattern` (built for `element_groups`, n vertices, d dims)."""
    levels = vertex_levels(element_groups, num_vertices)
    device = levels.device
    num_levels = int(levels.max()) + 1
    widths = torch.bincount(levels, minlength=num_levels)
    level_size = int(widths.max()) * dim
    rank = level_ranks(levels, element_groups, num_vertices)
    axes = torch.arange(dim, device=device)
    dof_level = levels.repeat_interleave(dim)
    dof_local = (rank[:, None] * dim + axes).reshape(-1)
    dof_slots = dof_level * level_size + dof_local

    size = num_vertices * dim
    nnz = pattern.col_indices.numel() * size // pattern.size
    rows, cols = pattern.row_indices[:nnz], pattern.col_indices[:nnz]
    row_level, col_level = dof_level[rows], dof_level[cols]
    if bool(((row_level - col_level).abs() > 1).any()):
        raise ValueError("the sparsity pattern couples vertices more than one level apart")
    square = level_size * level_size
    local = dof_local[rows] * level_size + dof_local[cols]
    on_diagonal = row_level == col_level
    below = row_level == col_level + 1
    keep = on_diagonal | below
    target = torch.where(on_diagonal, row_level * square, (num_levels + row_level - 1) * square) + local
    band_order = torch.argsort(dof_slots)
    band_position = torch.empty_like(band_order)
    band_position[band_order] = torch.arange(size, device=device)
    half_bandwidth = int((band_position[rows] - band_position[cols]).abs().max())
    band_column = torch.arange(size, device=device)[:, None]
    band_row = band_column + torch.arange(half_bandwidth + 1, device=device)
    inside = band_row < size
    padding = torch.zeros((2 * num_levels - 1) * square, dtype=torch.bool, device=device)
    diagonal_slots = torch.arange(num_levels * level_size, device=device)
    padding[(diagonal_slots // level_size) * square + (diagonal_slots % level_size) * (level_size + 1)] = True
    return LevelLayout(
        num_levels=num_levels,
        level_size=level_size,
        entries=nnz,
        dof_slots=dof_slots,
        value_positions=torch.nonzero(keep).flatten(),
        block_positions=target[keep],
        padding=padding,
        band_order=band_order,
        band_position=band_position,
        half_bandwidth=half_bandwidth,
        band_entries=torch.where(
            inside, band_order[band_row.clamp(max=size - 1)] * size + band_order[band_column], 0
        ),
    )


_LAYOUTS: IdentityCache[LevelLayout] = IdentityCache(capacity=8)


def cached_layout(
    pattern: SparsityPattern, element_groups: Sequence[Tensor], num_vertices: int, dim: int
) -> LevelLayout:
    """`level_layout`, for a few recently used patterns (keyed by the pattern's identity: patterns
    are cached and immutable)."""
    return _LAYOUTS.get((pattern,), None, lambda: level_layout(pattern, element_groups, num_vertices, dim))


def gather_blocks(values: Tensor, layout: LevelLayout) -> tuple[Tensor, Tensor]:
    """The diagonal `[B, L, S, S]` and sub-diagonal `[B, L−1, S, S]` blocks (A_{k,k−1}) from the CSR
    values of a batch, shape `[B·nnz]` (batch-major, as `assembly.assemble` lays them out)."""
    L, S = layout.num_levels, layout.level_size
    batch = values.numel() // layout.entries
    buffer = layout.padding.to(values.dtype).expand(batch, -1).clone()
    picked = values.reshape(batch, -1)[:, layout.value_positions]
    buffer.index_copy_(1, layout.block_positions, picked)
    square = S * S
    diagonal = buffer[:, : L * square].reshape(batch, L, S, S)
    lower = buffer[:, L * square :].reshape(batch, L - 1, S, S)
    return diagonal, lower


@dataclass(frozen=True)
class BlockCholesky:
    """H = G Gᵀ with G block lower bidiagonal: G_kk = `diagonal[k]` (lower triangular), G_{k,k−1} =
    `coupling[k−1]`; `positive_definite` `[B]` is False where some level's factorisation failed
    (those entries' factors are placeholders: identities, finite but meaningless)."""

    diagonal: list[Tensor]
    coupling: list[Tensor]
    positive_definite: Tensor


def block_cholesky(diagonal: Tensor, lower: Tensor) -> BlockCholesky:
    """Factor symmetric block-tridiagonal matrices, batched.

    L_0 L_0ᵀ = A_00;  M_k = A_{k,k−1} L_{k−1}⁻ᵀ;  L_k L_kᵀ = A_kk − M_k M_kᵀ.
    H is positive definite exactly when every Schur complement A_kk − M_k M_kᵀ is.

    Args:
        diagonal: A_kk, shape `[B, L, S, S]`.
        lower: A_{k,k−1}, shape `[B, L−1, S, S]`.
    """
    batch, num_levels, size, _ = diagonal.shape
    eye = torch.eye(size, dtype=diagonal.dtype, device=diagonal.device)
    positive_definite = torch.ones(batch, dtype=torch.bool, device=diagonal.device)
    factors: list[Tensor] = []
    couplings: list[Tensor] = []
    for k in range(num_levels):
        block = diagonal[:, k]
        if k > 0:
            coupling = torch.linalg.solve_triangular(factors[-1].mT, lower[:, k - 1], upper=True, left=False)
            couplings.append(coupling)
            block = torch.baddbmm(block, coupling, coupling.mT, alpha=-1.0)
        factor, info = torch.linalg.cholesky_ex(block)
        good = info == 0
        positive_definite = positive_definite & good
        # a failed factor holds garbage: an identity keeps the later levels (and the solve) finite
        factors.append(torch.where(good[:, None, None], factor, eye))
    return BlockCholesky(diagonal=factors, coupling=couplings, positive_definite=positive_definite)


def block_cholesky_solve(factor: BlockCholesky, rhs: Tensor) -> Tensor:
    """Solve G Gᵀ u = rhs by block forward and back substitution; `rhs`, `u`: shape `[B, L, S]`."""
    num_levels = len(factor.diagonal)
    forward: list[Tensor] = []
    for k in range(num_levels):
        column = rhs[:, k, :, None]
        if k > 0:
            column = column - factor.coupling[k - 1] @ forward[-1]
        forward.append(torch.linalg.solve_triangular(factor.diagonal[k], column, upper=False))
    backward: list[Tensor] = [forward[-1]] * num_levels
    for k in reversed(range(num_levels)):
        column = forward[k]
        if k < num_levels - 1:
            column = column - factor.coupling[k].mT @ backward[k + 1]
        backward[k] = torch.linalg.solve_triangular(factor.diagonal[k].mT, column, upper=True)
    return torch.stack(backward, dim=1)[..., 0]


def to_levels(v: Tensor, layout: LevelLayout) -> Tensor:
    """`[B, n, d]` → `[B, L, S]` in level order (padding DOFs zero)."""
    batch = v.shape[0]
    out = v.new_zeros(batch, layout.num_levels * layout.level_size)
    out[:, layout.dof_slots] = v.reshape(batch, -1)
    return out.reshape(batch, layout.num_levels, layout.level_size)


def from_levels(u: Tensor, layout: LevelLayout, like: Tensor) -> Tensor:
    """`[B, L, S]` in level order → shape of `like`, `[B, n, d]`."""
    return u.reshape(u.shape[0], -1)[:, layout.dof_slots].reshape(like.shape)


# the cost model for choosing this path over a dense Cholesky (B·N³/3 flops), in units of one dense
# flop: about LEVELS_WORK·B·L·S³ plus a fixed LEVELS_OVERHEAD per level (its Python loop issues a few
# small batched kernels per level whatever B is). Measured on the worm (N = 432, L = 18, S = 27).
LEVELS_WORK = 4.0
LEVELS_OVERHEAD = 2.5e6


def prefer_levels(layout: LevelLayout, batch: int, num_dofs: int) -> bool:
    """Whether the block-tridiagonal factorisation is estimated cheaper than a dense one (N = `num_dofs`)."""
    dense_cost = batch * num_dofs**3 / 3
    return LEVELS_WORK * batch * layout.cost + LEVELS_OVERHEAD * layout.num_levels < dense_cost


def level_solve(diagonal: Tensor, lower: Tensor, layout: LevelLayout, rhs: Tensor) -> tuple[Tensor, Tensor]:
    """Solve H u = rhs (`[B, n, d]`) from H's level blocks; returns u and which entries were positive
    definite `[B]` (elsewhere u is finite but meaningless)."""
    factor = block_cholesky(diagonal, lower)
    solution = from_levels(block_cholesky_solve(factor, to_levels(rhs, layout)), layout, rhs)
    return solution, factor.positive_definite
