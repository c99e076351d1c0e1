"""Every derivative the solvers use comes from here, and from autograd.

Gradients and Hessian-vector products are autograd's. Hessian *blocks* of element energies
(one dense `[(k·d), (k·d)]` matrix per element) are autograd's too, unless a term supplies a
closed-form `element_hessian` kernel, which the tests check against autograd. With the blocks
in hand, a Hessian-vector product is a gather, a batched mat-vec and a scatter-add: far cheaper
than a double backward through the energy, which is what makes Newton–CG fast.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from energysim.energies.base import ElementEnergy, EnergyTerm, has_element_blocks, has_vertex_diagonal
from energysim.linalg.assembly import SparsityPattern, assemble, cached_pattern
from energysim.linalg.block_tridiagonal import LevelLayout, cached_layout, gather_blocks
from energysim.linalg.caching import IdentityCache

EnergyFn = Callable[[Tensor], Tensor]


def _private_graph() -> torch.autograd.graph.saved_tensors_hooks:
    """Saved-tensor hooks that keep tensors as they are, shadowing any outer ones.

    The solvers' own derivative evaluations build and consume a graph at once. Inside a
    checkpointed region (`torch.utils.checkpoint`), the outer hooks would replace those saved
    tensors by placeholders, and reading them back would recompute the whole region, recursively.
    """
    return torch.autograd.graph.saved_tensors_hooks(lambda tensor: tensor, lambda tensor: tensor)


def energy_and_gradient(energy: EnergyFn, x: Tensor) -> tuple[Tensor, Tensor]:
    """E(x) and ∇E(x).

    Args:
        energy: maps positions `[B, n, d]` to energies `[B]` in J.
        x: positions, shape `[B, n, d]`, in m.

    Returns:
        energies `[B]` (detached) and gradients `[B, n, d]` in N.
    """
    with torch.enable_grad(), _private_graph():
        x = x.detach().requires_grad_(True)
        value = energy(x)
        (gradient,) = torch.autograd.grad(value.sum(), x)
    return value.detach(), gradient


def hessian_vector_product(energy: EnergyFn, x: Tensor, v: Tensor) -> Tensor:
    """H(x) v by double backward; H is never formed. Shapes as `x`; units N/m × units of `v`."""
    with torch.enable_grad(), _private_graph():
        x = x.detach().requires_grad_(True)
        (gradient,) = torch.autograd.grad(energy(x).sum(), x, create_graph=True)
        (product,) = torch.autograd.grad(gradient, x, grad_outputs=v)
    return product


def autograd_element_hessian(term: ElementEnergy, x: Tensor, action: Tensor | None) -> Tensor:
    """Per-element Hessian blocks of an element energy by autograd, shape `[B, m, k·d, k·d]`.

    Elements are independent, so column j of every block comes from one backward pass of the
    j-th component of the per-element gradients: k·d passes in all, whatever m is.
    """
    with torch.enable_grad(), _private_graph():
        element_positions = x.detach()[:, term.element_vertices].requires_grad_(True)
        batch, count, corners, dim = element_positions.shape
        energy = term.element_energy(element_positions, action).sum()
        (gradient,) = torch.autograd.grad(energy, element_positions, create_graph=True)
        gradient = gradient.reshape(batch, count, corners * dim)
        columns = []
        for j in range(corners * dim):
            if not gradient.requires_grad:  # the energy is linear in x
                columns.append(torch.zeros_like(gradient))
                continue
            (column,) = torch.autograd.grad(
                gradient[..., j].sum(), element_positions, retain_graph=True, allow_unused=True
            )
            columns.append(torch.zeros_like(gradient) if column is None else column.reshape(batch, count, -1))
    return torch.stack(columns, dim=-1).detach()


def element_hessian(term: ElementEnergy, x: Tensor, action: Tensor | None) -> Tensor:
    """Per-element Hessian blocks `[B, m, k·d, k·d]`: the term's closed form if it has one, else autograd."""
    if term.has_hessian_kernel:
        with torch.no_grad():
            return term.element_hessian(x[:, term.element_vertices], action)
    return autograd_element_hessian(term, x, action)


def project_positive_semidefinite(blocks: Tensor) -> Tensor:
    """The nearest positive semidefinite matrices to symmetric `blocks` `[..., k, k]`: negative
    eigenvalues clipped to zero (projected Newton, Teran et al. 2005)."""
    eigenvalues, eigenvectors = torch.linalg.eigh(blocks)
    return (eigenvectors * eigenvalues.clamp_min(0.0)[..., None, :]) @ eigenvectors.transpose(-1, -2)


@dataclass
class HessianOperator:
    """H = diagonal + Σ element blocks (+ autograd HVPs of other nonlinear terms), on free DOFs only.

    The diagonal and blocks are assembled once into a CSR matrix. Fixed DOFs are eliminated:
    the operator acts as the identity on them, so a solve leaves them untouched.
    """

    free: Tensor  # [n] bool
    diagonal: Tensor | None  # [n] or [B, n], per vertex (isotropic), N/m
    blocks: list[tuple[Tensor, Tensor]] = field(default_factory=list)  # ([m, k], [B, m, kd, kd])
    extra_products: list[Callable[[Tensor], Tensor]] = field(default_factory=list)
    products: int = 0  # Hessian-vector products taken so far
    _matrix: Tensor | None = None

    def matrix(self, like: Tensor) -> Tensor | None:
        """The assembled CSR matrix of diagonal + blocks, size B·n·d, or None if there is neither."""
        if self._matrix is None and (self.blocks or self.diagonal is not None):
            batch, n, dim = like.shape
            pattern = self._pattern(like)
            diagonal = None
            if self.diagonal is not None:
                diagonal = self.diagonal.reshape(-1, n, 1).expand(batch, n, dim)
            fixed = (~self.free)[None, :, None].expand(batch, n, dim).reshape(-1)
            self._matrix = assemble(pattern, diagonal, [block for _, block in self.blocks], like.dtype, fixed)
        return self._matrix

    def matvec(self, v: Tensor) -> Tensor:
        """H v for `v` of shape `[B, n, d]`."""
        self.products += 1
        matrix = self.matrix(v)
        if not self.extra_products:  # fixed DOFs are already eliminated inside the matrix
            return (matrix @ v.reshape(-1)).reshape(v.shape)
        free = self.free[:, None].to(v.dtype)
        v_free = v * free
        out = torch.zeros_like(v) if matrix is None else (matrix @ v_free.reshape(-1)).reshape(v.shape)
        for product in self.extra_products:
            out = out + product(v_free)
        return out * free + v * (1 - free)

    def dense(self, like: Tensor) -> Tensor | None:
        """The matrix of every batch entry as a dense `[B, n·d, n·d]` tensor (for small systems), or
        None when some term has no assembled blocks."""
        matrix = self.matrix(like)
        if matrix is None or self.extra_products:
            return None
        batch, n, dim = like.shape
        size = n * dim
        pattern = self._pattern(like)
        out = like.new_zeros(batch, size, size)
        rows, cols = pattern.row_indices, pattern.col_indices
        out.index_put_((rows // size, rows % size, cols % size), matrix.values())
        return out

    def level_blocks(self, like: Tensor) -> tuple[Tensor, Tensor, LevelLayout] | None:
        """The matrix in block-tridiagonal form over breadth-first vertex levels (see
        `energysim.linalg.block_tridiagonal`): diagonal blocks `[B, L, S, S]`, sub-diagonal blocks
        `[B, L−1, S, S]` and the layout, or None when some term has no assembled blocks."""
        matrix = self.matrix(like)
        if matrix is None or self.extra_products:
            return None
        layout = self.level_layout(like)
        diagonal, lower = gather_blocks(matrix.values(), layout)
        return diagonal, lower, layout

    def level_layout(self, like: Tensor) -> LevelLayout:
        """The block-tridiagonal layout of this operator's sparsity pattern (cached per pattern)."""
        _, n, dim = like.shape
        groups = [elements for elements, _ in self.blocks]
        return cached_layout(self._pattern(like), groups, n, dim)

    def vertex_blocks(self, like: Tensor) -> Tensor:
        """The d×d diagonal block of H at every vertex, shape `[B, n, d, d]`, for block-Jacobi.

        Read from the assembled values (fixed DOFs are already identity there). Products from
        `extra_products` are not included: they have no cheap diagonal. Without an assembled
        matrix the blocks are identities.
        """
        batch, n, dim = like.shape
        matrix = self.matrix(like)
        if matrix is None:
            return torch.eye(dim, dtype=like.dtype, device=like.device).expand(batch, n, dim, dim)
        return matrix.values()[self._pattern(like).vertex_block_positions].reshape(batch, n, dim, dim)

    def _pattern(self, like: Tensor) -> SparsityPattern:
        batch, n, dim = like.shape
        return cached_pattern([elements for elements, _ in self.blocks], n, dim, batch)


_GROUPS: IdentityCache[list[list[int]]] = IdentityCache(capacity=16)


def element_groups(
    terms: Sequence[EnergyTerm], member: Callable[[EnergyTerm], bool] = has_element_blocks
) -> list[tuple[int, ...]]:
    """The indices of the terms that are `member`s (default: those with element blocks), grouped by
    equal `element_vertices` (a muscle term on every element of the mesh shares the elastic term's
    elements): one gather and one scatter per group. Cached per tuple of vertex tensors."""
    members = [index for index, term in enumerate(terms) if member(term)]
    vertices = [terms[index].element_vertices for index in members]

    def build() -> list[list[int]]:
        groups: list[list[int]] = []
        for position, tensor in enumerate(vertices):
            for group in groups:
                first = vertices[group[0]]
                if first is tensor or (first.shape == tensor.shape and torch.equal(first, tensor)):
                    group.append(position)
                    break
            else:
                groups.append([position])
        return groups

    return [tuple(members[position] for position in group) for group in _GROUPS.get(vertices, None, build)]


def hessian_operator(
    terms: Sequence[EnergyTerm],
    x: Tensor,
    action: Tensor | None,
    free: Tensor,
    *,
    use_element_blocks: bool = True,
    project: bool = False,
) -> HessianOperator:
    """The Hessian of Σ terms at `x`, as an operator on `[B, n, d]` tensors.

    Args:
        terms: the objective's energy terms.
        x: positions, shape `[B, n, d]`, in m.
        action: the step's action or None.
        free: which vertices are free, shape `[n]`, bool.
        use_element_blocks: False takes every product by double backward (the plain reference);
            True builds per-element blocks once and takes products from them.
        project: make every element block positive semidefinite (a convex model that always gives
            descent directions, no longer the exact Hessian); needs element blocks.
    """
    diagonal = None
    blocks: list[tuple[Tensor, Tensor]] = []
    others: list[EnergyTerm] = []
    for term in terms:
        if term.is_linear:
            continue
        if has_vertex_diagonal(term):
            diagonal = term.hessian_diagonal() if diagonal is None else diagonal + term.hessian_diagonal()
        elif not (use_element_blocks and has_element_blocks(term)):
            others.append(term)
    if use_element_blocks:
        # terms on the same elements (a user's term beside the elastic one on every tet) share one
        # group: their blocks are summed, and the matrix takes one scatter per group
        for group in element_groups(terms):
            block = None
            for index in group:
                term_block = element_hessian(terms[index], x, action)
                term_block = project_positive_semidefinite(term_block) if project else term_block
                block = term_block if block is None else block + term_block
            blocks.append((terms[group[0]].element_vertices, block))
    extra = []
    if others:
        x_fixed = x.detach()

        def others_energy(y: Tensor) -> Tensor:
            return sum(term(y, action) for term in others)

        extra.append(lambda v: hessian_vector_product(others_energy, x_fixed, v))
    return HessianOperator(free=free, diagonal=diagonal, blocks=blocks, extra_products=extra)
