"""Kinematics of linear simplices (triangles in 2D, tetrahedra in 3D), dimension-generic.

A linear simplex maps its rest shape onto its current shape affinely, so its deformation
gradient is constant: F = Ds Dm⁻¹, with Ds and Dm the edge matrices [x1 - x0, ..., xd - x0]
of the current and rest shapes.
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.linalg.small_matmul import small_matmul


def edge_matrix(element_positions: Tensor) -> Tensor:
    """Edge matrices [x1 - x0, ..., xd - x0] as columns.

    Args:
        element_positions: vertex positions per element, shape `[..., d+1, d]`, in m.

    Returns:
        shape `[..., d, d]`; column a is the edge from vertex 0 to vertex a + 1.
    """
    return (element_positions[..., 1:, :] - element_positions[..., :1, :]).transpose(-1, -2)


def simplex_rest_frame(rest_positions: Tensor, elements: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse rest edge matrices and rest volumes of every element.

    Args:
        rest_positions: shape `[n, d]`, in m.
        elements: vertex indices, shape `[m, d+1]`, positively oriented.

    Returns:
        `rest_edge_inverse` Dm⁻¹, shape `[m, d, d]` in 1/m, and `rest_volume`, shape `[m]`,
        in m^d (area per metre of depth in 2D).
    """
    dim = rest_positions.shape[-1]
    Dm = edge_matrix(rest_positions[elements])
    det = torch.linalg.det(Dm)
    rest_volume = det / (2.0 if dim == 2 else 6.0)
    return torch.linalg.inv(Dm), rest_volume


def deformation_gradient(element_positions: Tensor, rest_edge_inverse: Tensor) -> Tensor:
    """F = Ds Dm⁻¹ for every element.

    Args:
        element_positions: shape `[..., m, d+1, d]`, in m.
        rest_edge_inverse: Dm⁻¹, shape `[m, d, d]`.

    Returns:
        F, shape `[..., m, d, d]`, dimensionless.
    """
    return small_matmul(edge_matrix(element_positions), rest_edge_inverse)


def shape_gradients(rest_edge_inverse: Tensor) -> Tensor:
    """Gradients of the linear shape functions, ∇N_b, constant over each element.

    F = Σ_b x_b ⊗ ∇N_b, so these map nodal quantities to element gradients and back.

    Args:
        rest_edge_inverse: Dm⁻¹, shape `[m, d, d]`.

    Returns:
        shape `[m, d+1, d]` in 1/m; row b is ∇N_b, and the rows sum to zero.
    """
    rows = rest_edge_inverse  # row a of Dm⁻¹ is ∇N_{a+1}
    return torch.cat([-rows.sum(dim=-2, keepdim=True), rows], dim=-2)


def deformation_gradient_entries(corners: list[list[Tensor]], shape_gradient_t: Tensor) -> list[list[Tensor]]:
    """F_ij = Σ_b x_bi ∇N_bj entry by entry, with the batch innermost: `corners[i][b]` is coordinate
    i of every element's corner b, `[m, B]` (positions in m, or velocities, which give Ḟ);
    `shape_gradient_t` is ∇N as `[k, d, m]`. Returns F[i][j], `[m, B]` each. Scalar arithmetic that a
    compiler fuses into one loop over the elements (see `energysim.objective.compiled`)."""
    dim = len(corners)
    return [
        [sum(corners[i][b] * shape_gradient_t[b, j][:, None] for b in range(dim + 1)) for j in range(dim)]
        for i in range(dim)
    ]


def corner_forces_entries(
    stress: list[list[Tensor]], shape_gradient_t: Tensor, rest_volume: Tensor
) -> list[list[Tensor]]:
    """V Σ_j P_ij ∇N_bj entry by entry: the corner gradients `[i][b]`, `[m, B]` each, of a first
    Piola–Kirchhoff stress P given as `stress[i][j]` `[m, B]` (`deformation_gradient_entries`'s
    layout), `rest_volume` V `[m]`."""
    dim = len(stress)
    volume = rest_volume[:, None]
    return [
        [
            volume * sum(stress[i][j] * shape_gradient_t[b, j][:, None] for j in range(dim))
            for b in range(dim + 1)
        ]
        for i in range(dim)
    ]
