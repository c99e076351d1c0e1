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


def smith_parameters(mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(μ', λ', α) of the stable neo-Hookean energy from the Lamé parameters (μ, λ), in Pa, Pa, 1."""
    mu_smith = 4.0 / 3.0 * mu
    lam_smith = lam + 5.0 / 6.0 * mu
    return mu_smith, lam_smith, 1.0 + 0.75 * mu_smith / lam_smith


def _invariant_excesses(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """I_C − 3, J − 1 and (I_C − 3)/2 − (J − 1), from G = F − I so that none loses digits near F = I.

    The last one has no first-order part: |G|²/2 − I₂(G) − det G (in 2D, |G|²/2 − det G).
    """
    dim = F.shape[-1]
    G = F.clone()
    G.diagonal(dim1=-2, dim2=-1).sub_(1.0)  # F − I without building I
    trace = G.diagonal(dim1=-2, dim2=-1).sum(-1)
    squares = 0.5 * (G * G).sum(dim=(-1, -2))
    determinant = _determinant(G)
    # plane strain: the out-of-plane stretch is 1, so G has no third row or column
    if dim == 2:
        higher = determinant
    else:
        higher = 0.5 * (trace**2 - (G * G.transpose(-1, -2)).sum(dim=(-1, -2))) + determinant
    return 2.0 * (trace + squares), trace + higher, squares - higher


def _y_minus_log1p(y: Tensor) -> Tensor:
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
    stretch_excess, volume_excess, second_order = _invariant_excesses(F)
    return (
        0.75 * mu_smith * second_order
        + 0.5 * lam_smith * volume_excess**2
        + 0.5 * mu_smith * _y_minus_log1p(0.25 * stretch_excess)
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


def stable_neo_hookean_stress(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """The first Piola–Kirchhoff stress P = ∂ψ/∂F of `stable_neo_hookean_density`, in Pa.

    From ψ = 3μ'/4 (s/2 − v) + λ'/2 v² + μ'/2 f(s/4) with ∂s/∂F = 2F, ∂v/∂F = cof F and
    f'(y) = y/(1 + y): P = 3μ'/4 (F − cof F) + λ' v cof F + μ'/4 · y/(1 + y) · F, y = s/4.
    A closed form for speed (the solvers' gradients); the tests check it against autograd.

    Args:
        F: shape `[..., d, d]`; mu, lam: Pa, broadcastable to `[...]`.
    """
    mu_smith, lam_smith, _ = smith_parameters(mu, lam)
    stretch_excess, volume_excess, _ = _invariant_excesses(F)
    cofactor = cofactor_matrix(F)
    y = 0.25 * stretch_excess
    along_f = 0.75 * mu_smith + 0.25 * mu_smith * y / (1.0 + y)
    along_cofactor = lam_smith * volume_excess - 0.75 * mu_smith
    return along_f[..., None, None] * F + along_cofactor[..., None, None] * cofactor


def stable_neo_hookean_stress_entries(F: list[list[Tensor]], mu: Tensor, lam: Tensor) -> list[list[Tensor]]:
    """`stable_neo_hookean_stress` with F and P given entry by entry: `F[i][j]` are tensors of one
    shape `[...]`, and so are the returned `P[i][j]`, in Pa.

    The same formulas, written as scalar expressions: compiled, they fuse into one loop over the
    entries' elements, where the matrix form's reductions over the last axes and stacks each end a
    loop and store their intermediates (`energysim.objective.compiled`'s batch-last leapfrog, 2.5 → 1.3 ms a
    substep for 64 worms). The tests check the two forms agree.

    Args:
        F: d × d nested lists, d = 2 (plane strain) or 3; mu, lam: Pa, broadcastable to `[...]`.
    """
    dim = len(F)
    mu_smith, lam_smith, _ = smith_parameters(mu, lam)
    # in G = F − I, as `_invariant_excesses`, so that nothing loses digits near F = I
    G = [[F[i][j] - 1.0 if i == j else F[i][j] for j in range(dim)] for i in range(dim)]
    trace = sum(G[i][i] for i in range(dim))
    squares = 0.5 * sum(G[i][j] * G[i][j] for i in range(dim) for j in range(dim))
    if dim == 2:
        higher = G[0][0] * G[1][1] - G[0][1] * G[1][0]
        cofactor = [[F[1][1], -F[1][0]], [-F[0][1], F[0][0]]]
    else:
        determinant = (
            G[0][0] * (G[1][1] * G[2][2] - G[1][2] * G[2][1])
            - G[0][1] * (G[1][0] * G[2][2] - G[1][2] * G[2][0])
            + G[0][2] * (G[1][0] * G[2][1] - G[1][1] * G[2][0])
        )
        higher = (
            0.5 * (trace * trace - sum(G[i][j] * G[j][i] for i in range(3) for j in range(3))) + determinant
        )
        # cof F_ij = (−1)^(i+j) times the minor: cyclic in 3D
        cofactor = [
            [
                F[(i + 1) % 3][(j + 1) % 3] * F[(i + 2) % 3][(j + 2) % 3]
                - F[(i + 1) % 3][(j + 2) % 3] * F[(i + 2) % 3][(j + 1) % 3]
                for j in range(3)
            ]
            for i in range(3)
        ]
    y = 0.5 * (trace + squares)  # (I_C − 3)/4
    along_f = 0.75 * mu_smith + 0.25 * mu_smith * y / (1.0 + y)
    along_cofactor = lam_smith * (trace + higher) - 0.75 * mu_smith
    return [[along_f * F[i][j] + along_cofactor * cofactor[i][j] for j in range(dim)] for i in range(dim)]


def stable_neo_hookean_density_and_stress(F: Tensor, mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor]:
    """`stable_neo_hookean_density` and `stable_neo_hookean_stress` in one pass over the invariants,
    which both need: the solvers ask for energy and gradient together at every iterate.

    Args:
        F: shape `[..., d, d]`; mu, lam: Pa, broadcastable to `[...]`.

    Returns:
        ψ(F) `[...]` in J/m³ and P(F) `[..., d, d]` in Pa.
    """
    mu_smith, lam_smith, _ = smith_parameters(mu, lam)
    stretch_excess, volume_excess, second_order = _invariant_excesses(F)
    y = 0.25 * stretch_excess
    density = (
        0.75 * mu_smith * second_order
        + 0.5 * lam_smith * volume_excess**2
        + 0.5 * mu_smith * _y_minus_log1p(y)
    )
    along_f = 0.75 * mu_smith + 0.25 * mu_smith * y / (1.0 + y)
    along_cofactor = lam_smith * volume_excess - 0.75 * mu_smith
    stress = along_f[..., None, None] * F + along_cofactor[..., None, None] * cofactor_matrix(F)
    return density, stress


def stable_neo_hookean_stress_hessian(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """∂²ψ/∂F² of `stable_neo_hookean_density`, the exact (unprojected) tangent stiffness.

    A closed form for speed only: the tests check it against autograd. With f = vec(F)
    row-major and I_C counting the plane-strain 1 in 2D,

        ∂²ψ/∂F² = μ'(1 − 1/(I_C + 1)) I + 2μ'/(I_C + 1)² f fᵀ + λ' g gᵀ + λ'(J − α) ∂²J/∂F²,

    with g = vec(cof F), and ∂²J/∂F_ij∂F_kl = ε_ikp ε_jlq F_pq in 3D, ε_ik ε_jl in 2D.

    Args:
        F: shape `[..., d, d]`; mu, lam: Pa, broadcastable to `[...]`.

    Returns:
        shape `[..., d*d, d*d]`, in Pa.
    """
    dim = F.shape[-1]
    mu_smith, lam_smith, alpha = smith_parameters(mu, lam)
    stretch_excess, volume_excess, _ = _invariant_excesses(F)
    flat = F.reshape(*F.shape[:-2], dim * dim)
    cofactor = cofactor_matrix(F).reshape(flat.shape)
    # Built with few full-size temporaries: at 50k elements each one is tens of MB, and their
    # allocation, not the arithmetic, dominated. The two rank-one terms are broadcast products
    # accumulated in place: as one `[.., d², 2] @ [.., 2, d²]` batched product they took twice as
    # long (MKL, 14 ms against 7.5 ms at 50k elements), and under torch.compile an external call
    # each time instead of a fused loop.
    shape = flat.shape[:-1]
    inverse = 1.0 / (stretch_excess + 4.0)  # 1/(I_C + 1)
    mu_smith, lam_smith = (
        torch.as_tensor(t, dtype=F.dtype, device=F.device).expand(shape) for t in (mu_smith, lam_smith)
    )
    volume_direction = cofactor * lam_smith.sqrt()[..., None]
    stretch_direction = flat * ((2.0 * mu_smith).sqrt() * inverse)[..., None]
    hessian = volume_direction[..., :, None] * volume_direction[..., None, :]
    hessian.addcmul_(stretch_direction[..., :, None], stretch_direction[..., None, :])
    hessian.diagonal(dim1=-2, dim2=-1).add_((mu_smith * (1.0 - inverse))[..., None])
    # every entry of ∂²J/∂F² is ±1 (2D) or ± one entry of F (3D): a signed gather, no einsum
    index, sign = _DET_HESSIAN[dim]
    padded = torch.cat([flat, torch.ones_like(flat[..., :1])], dim=-1)
    det_hessian = padded.index_select(-1, index.to(F.device)).mul_(sign.to(F))
    weight = lam_smith * (volume_excess + 1.0 - alpha)  # λ'(J − α)
    hessian.view(*shape, -1).addcmul_(det_hessian, weight[..., None])
    return hessian


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
