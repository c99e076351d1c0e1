"""Pure material densities: energy per unit rest volume as a function of F.

The stable neo-Hookean model of Smith, de Goes and Kim (2018), in the form the authors use in
production (the optional log(I_C + 1) term dropped):

    ψ(F) = μ/2 (I_C − 3) + λ'/2 (J − α)² − μ²/(2λ'),   λ' = λ + μ,   α = 1 + μ/λ'

It is a polynomial in F (no log J, no F⁻¹, no SVD), so it is finite for every F, including
inverted (J < 0) and flat (J = 0) elements, which it pushes back towards J = α > 0. With these
λ' and α the rest state is stress-free (P(I) = 0) and the Hessian at F = I equals linear
elasticity with Lamé parameters (μ, λ). The constant makes ψ(I) = 0.

2D elements use plane strain: the 2×2 F is embedded as diag(F, 1).
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor


def lame_parameters(youngs_modulus: Tensor, poissons_ratio: Tensor) -> tuple[Tensor, Tensor]:
    """Lamé parameters (μ, λ) in Pa from Young's modulus (Pa) and Poisson's ratio."""
    mu = youngs_modulus / (2.0 * (1.0 + poissons_ratio))
    lam = youngs_modulus * poissons_ratio / ((1.0 + poissons_ratio) * (1.0 - 2.0 * poissons_ratio))
    return mu, lam


def _determinant(F: Tensor) -> Tensor:
    # Written out because torch.linalg.det on tiny matrices goes through an LU factorisation,
    # which is several times slower and has a less stable second derivative at J = 0.
    if F.shape[-1] == 2:
        return F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


def stable_neo_hookean_density(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """Stable neo-Hookean energy per unit rest volume, in J/m³.

    Args:
        F: deformation gradients, shape `[..., d, d]` with d = 2 (plane strain) or 3.
        mu, lam: Lamé parameters in Pa, broadcastable to `[...]`.

    Returns:
        ψ(F), shape `[...]`; zero at F = I and at any rotation.
    """
    dim = F.shape[-1]
    lam_shifted = lam + mu
    alpha = 1.0 + mu / lam_shifted
    # plane strain: the out-of-plane stretch is 1, which adds 1 to I_C and nothing to J
    stretch_invariant = (F * F).sum(dim=(-1, -2)) + (3 - dim)
    J = _determinant(F)
    return (
        0.5 * mu * (stretch_invariant - 3.0)
        + 0.5 * lam_shifted * (J - alpha) ** 2
        - 0.5 * mu**2 / lam_shifted
    )


def stable_neo_hookean_stress_hessian(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """∂²ψ/∂F² of `stable_neo_hookean_density`, the exact (unprojected) tangent stiffness.

    A closed form for speed only: the tests check it against autograd. With vec(F) row-major,

        ∂²ψ/∂F² = μ I + λ' vec(cof F) vec(cof F)ᵀ + λ' (J − α) ∂²J/∂F²,

    where ∂²J/∂F_ij∂F_kl = ε_ikp ε_jlq F_pq in 3D, and ε_ik ε_jl in 2D.

    Args:
        F: shape `[..., d, d]`; mu, lam: Pa, broadcastable to `[...]`.

    Returns:
        shape `[..., d*d, d*d]`, in Pa.
    """
    dim = F.shape[-1]
    lam_shifted = lam + mu
    alpha = 1.0 + mu / lam_shifted
    J = _determinant(F)
    flat = F.reshape(*F.shape[:-2], dim * dim)
    if dim == 2:
        cofactor = torch.stack([F[..., 1, 1], -F[..., 1, 0], -F[..., 0, 1], F[..., 0, 0]], dim=-1)
    else:
        c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
        # columns of cof F are cross products of the other two columns of F
        cofactor = torch.stack(
            [torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0), torch.linalg.cross(c0, c1)], dim=-1
        ).reshape(flat.shape)
    # every entry of ∂²J/∂F² is ±1 (2D) or ± one entry of F (3D): a signed gather, no einsum
    index, sign = _DET_HESSIAN[dim]
    padded = torch.cat([flat, torch.ones_like(flat[..., :1])], dim=-1)
    det_hessian = (padded[..., index.to(F.device)] * sign.to(F)).reshape(*flat.shape, dim * dim)
    mu_, lam_, J_, alpha_ = (
        torch.as_tensor(t, dtype=F.dtype, device=F.device)[..., None, None]
        for t in (mu, lam_shifted, J, alpha)
    )
    eye = torch.eye(dim * dim, dtype=F.dtype, device=F.device)
    return mu_ * eye + lam_ * (cofactor[..., :, None] * cofactor[..., None, :] + (J_ - alpha_) * det_hessian)


def _det_hessian_tables() -> dict[int, tuple[Tensor, Tensor]]:
    # For row-major vec(F), ∂²J/∂F_ij∂F_kl = ε_ikp ε_jlq F_pq in 3D (one term survives) and
    # ε_ik ε_jl in 2D. Index d·d points at an appended constant 1.
    tables = {}
    for dim in (2, 3):
        size = dim * dim
        index = torch.full((size, size), size, dtype=torch.int64)
        sign = torch.zeros(size, size, dtype=torch.float64)
        for i, j, k, m in itertools.product(range(dim), repeat=4):
            if i == k or j == m:
                continue
            row, col = i * dim + j, k * dim + m
            if dim == 2:
                sign[row, col] = (1 if i < k else -1) * (1 if j < m else -1)
            else:
                p, q = 3 - i - k, 3 - j - m
                sign[row, col] = _permutation_sign(i, k, p) * _permutation_sign(j, m, q)
                index[row, col] = p * dim + q
        tables[dim] = (index.reshape(-1), sign.reshape(-1))
    return tables


def _permutation_sign(a: int, b: int, c: int) -> int:
    return 1 if (a, b, c) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1


_DET_HESSIAN = _det_hessian_tables()
