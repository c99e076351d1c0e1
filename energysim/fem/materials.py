"""Pure material densities: energy per unit rest volume as a function of F.

The stable neo-Hookean model of Smith, de Goes and Kim (2018), "Stable Neo-Hookean Flesh
Simulation", in the paper's full form:

    ψ(F) = μ'/2 (I_C − 3) + λ'/2 (J − α)² − μ'/2 log(I_C + 1) + c,
    μ' = 4μ/3,   λ' = λ + 5μ/6,   α = 1 + 3μ'/(4λ'),

with c making ψ(I) = 0. With these μ', λ' and α the rest state is stress-free and the Hessian
at F = I equals linear elasticity with Lamé parameters (μ, λ). Nothing in it is singular (no
log J, no F⁻¹, no SVD): it is finite for every F, including inverted (J < 0) and flat (J = 0)
elements, which it pushes back towards J > 0. The log(I_C + 1) term matters: without it,
F = 0 is a local minimum in 3D (the gradient vanishes there and the Hessian is μI), and a
scrambled or inverted body can collapse to a point; with it the origin is only a saddle.

Since λ'(α − 1) = 3μ'/4, the same function is
    ψ = 3μ'/4 (s/2 − v) + λ'/2 v² + μ'/2 f(s/4),   s = I_C − 3,  v = J − 1,  f(y) = y − log1p(y),
and it is evaluated so, with s/2 − v = |G|²/2 − I₂(G) − det G written in the displacement
gradient G = F − I: every term is then of second order in G. The first form subtracts terms of
size μ (and the obvious rewrite, terms of size μ|G|) from each other to leave an energy of size
μ|G|²; that rounding error would hide the energy decrease line searches must see near convergence.

2D elements use plane strain: the 2×2 F is embedded as diag(F, 1).

The solvers' closed-form stress and stiffness of this density are in `energysim.fem.kernels`,
checked there against the forms `torch.func` derives from it.
"""

from __future__ import annotations

import torch
from torch import Tensor


def lame_parameters(youngs_modulus: Tensor, poissons_ratio: Tensor) -> tuple[Tensor, Tensor]:
    """Lamé parameters (μ, λ) in Pa from Young's modulus (Pa) and Poisson's ratio."""
    mu = youngs_modulus / (2.0 * (1.0 + poissons_ratio))
    lam = youngs_modulus * poissons_ratio / ((1.0 + poissons_ratio) * (1.0 - 2.0 * poissons_ratio))
    return mu, lam


def determinant_of(F: Tensor) -> Tensor:
    # Written out because torch.linalg.det on tiny matrices goes through an LU factorisation,
    # which is several times slower and has a less stable second derivative at J = 0.
    dim = F.shape[-1]
    return _determinant_entries([[F[..., i, j] for j in range(dim)] for i in range(dim)])


def _determinant_entries(F: list[list[Tensor]]) -> Tensor:
    # det F with F given entry by entry (`F[i][j]`)
    if len(F) == 2:
        return F[0][0] * F[1][1] - F[0][1] * F[1][0]
    return (
        F[0][0] * (F[1][1] * F[2][2] - F[1][2] * F[2][1])
        - F[0][1] * (F[1][0] * F[2][2] - F[1][2] * F[2][0])
        + F[0][2] * (F[1][0] * F[2][1] - F[1][1] * F[2][0])
    )


def smith_parameters(mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(μ', λ', α) of the stable neo-Hookean energy from the Lamé parameters (μ, λ), in Pa, Pa, 1."""
    mu_smith = 4.0 / 3.0 * mu
    lam_smith = lam + 5.0 / 6.0 * mu
    return mu_smith, lam_smith, 1.0 + 0.75 * mu_smith / lam_smith


def invariant_excesses(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """I_C − 3, J − 1 and (I_C − 3)/2 − (J − 1), from G = F − I so that none loses digits near F = I.

    The last one has no first-order part: |G|²/2 − I₂(G) − det G (in 2D, |G|²/2 − det G).
    """
    dim = F.shape[-1]
    G = F.clone()
    G.diagonal(dim1=-2, dim2=-1).sub_(1.0)  # F − I without building I
    trace = G.diagonal(dim1=-2, dim2=-1).sum(-1)
    squares = 0.5 * (G * G).sum(dim=(-1, -2))
    determinant = determinant_of(G)
    # plane strain: the out-of-plane stretch is 1, so G has no third row or column
    if dim == 2:
        higher = determinant
    else:
        higher = 0.5 * (trace**2 - (G * G.transpose(-1, -2)).sum(dim=(-1, -2))) + determinant
    return 2.0 * (trace + squares), trace + higher, squares - higher


def invariant_excess_entries(F: list[list[Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """`invariant_excesses` with F given entry by entry (`F[i][j]`, tensors of one shape): scalar
    arithmetic, which a compiler fuses into one loop over the entries' elements."""
    dim = len(F)
    G = [[F[i][j] - 1.0 if i == j else F[i][j] for j in range(dim)] for i in range(dim)]
    trace = sum(G[i][i] for i in range(dim))
    squares = 0.5 * sum(G[i][j] * G[i][j] for i in range(dim) for j in range(dim))
    determinant = _determinant_entries(G)
    if dim == 2:
        higher = determinant
    else:
        crossed = sum(G[i][j] * G[j][i] for i in range(3) for j in range(3))
        higher = 0.5 * (trace * trace - crossed) + determinant
    return 2.0 * (trace + squares), trace + higher, squares - higher


def cofactor_entries(F: list[list[Tensor]]) -> list[list[Tensor]]:
    """`cofactor_matrix` with F and cof F given entry by entry (`[i][j]`)."""
    if len(F) == 2:
        return [[F[1][1], -F[1][0]], [-F[0][1], F[0][0]]]
    # cof F_ij = (−1)^(i+j) times the minor: cyclic in 3D
    return [
        [
            F[(i + 1) % 3][(j + 1) % 3] * F[(i + 2) % 3][(j + 2) % 3]
            - F[(i + 1) % 3][(j + 2) % 3] * F[(i + 2) % 3][(j + 1) % 3]
            for j in range(3)
        ]
        for i in range(3)
    ]


def y_minus_log1p(y: Tensor) -> Tensor:
    """y − log(1 + y) for y > −1, accurate for small y where the difference cancels."""
    small = y.abs() < 1e-2
    ys = torch.where(small, y, torch.zeros_like(y))
    # Taylor series y²/2 − y³/3 + y⁴/4 − …; ten terms reach double precision for |y| < 1e-2
    series = torch.zeros_like(y)
    for k in range(11, 1, -1):
        series = ys * ((-1) ** k / k + series)
    yl = torch.where(small, torch.ones_like(y), y)
    return torch.where(small, ys * series, yl - torch.log1p(yl))


def stable_neo_hookean_density(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """Stable neo-Hookean energy per unit rest volume, in J/m³.

    Args:
        F: deformation gradients, shape `[..., d, d]` with d = 2 (plane strain) or 3.
        mu, lam: Lamé parameters in Pa, broadcastable to `[...]`.

    Returns:
        ψ(F), shape `[...]`; zero at F = I and at any rotation.
    """
    mu_smith, lam_smith, _ = smith_parameters(mu, lam)
    stretch_excess, volume_excess, second_order = invariant_excesses(F)
    return (
        0.75 * mu_smith * second_order
        + 0.5 * lam_smith * volume_excess**2
        + 0.5 * mu_smith * y_minus_log1p(0.25 * stretch_excess)
    )


def cofactor_matrix(F: Tensor) -> Tensor:
    """cof F = ∂J/∂F (= J F⁻ᵀ where F is invertible, but defined for every F), shape `[..., d, d]`."""
    if F.shape[-1] == 2:
        entries = [F[..., 1, 1], -F[..., 1, 0], -F[..., 0, 1], F[..., 0, 0]]
        return torch.stack(entries, dim=-1).reshape(F.shape)
    c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    # columns of cof F are cross products of the other two columns of F
    columns = [torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0), torch.linalg.cross(c0, c1)]
    return torch.stack(columns, dim=-1)
