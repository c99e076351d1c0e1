"""Element Hessians entry by entry with the batch innermost, for the compiled Hessian of many bodies.

Each function here returns the upper triangle of an element's (k·d) × (k·d) Hessian block, one
tensor `[m, B]` per entry in the order of `upper_entries`, from corner positions given as
`corners[i][b]` `[m, B]` (coordinate i of corner b of every element, `energysim.objective.batch_last`).
Written as scalar arithmetic, a compiled Hessian fuses each term's entries into one loop vectorised
over the batch, and the scatter into `[storage, B]` moves rows of B contiguous numbers, where the
element-major blocks (`ElementEnergy.element_hessian`, `[B, m, k·d, k·d]`) run 3- and 12-wide inner
loops and scatter single numbers; only the stored triangle is computed. For a batch of worms this
took the band Hessian to less than half the time (docs/energies.md).
`tests/test_batch_last_entries.py` checks every function against autograd's Hessian of the element
energy.

The neo-Hookean entries use the structure of ∂²ψ/∂F² (`stable_neo_hookean_stress_hessian`): with
the strain map S (F = Σ_b x_b ⊗ ∇N_b), Sᵀ(a I + c f fᵀ + λ' g gᵀ + w ∂²J/∂F²)S has the (b, c) vertex
block a (∇N_b·∇N_c) I + c (F∇N_b)(F∇N_c)ᵀ + λ' (G∇N_b)(G∇N_c)ᵀ + w [F(∇N_b × ∇N_c)]_ε, G = cof F,
where [r]_ε,ik = ε_ikp r_p in 3D and ε_ik (∇N_b × ∇N_c) in 2D: no 9 × 9 matrix is formed.
"""

from __future__ import annotations

from torch import Tensor

from energysim.fem.kinematics import deformation_gradient_entries
from energysim.fem.materials import cofactor_entries, invariant_excess_entries, smith_parameters

Entries = list[list[Tensor]]


def upper_entries(corners: int, dim: int) -> tuple[tuple[int, int], ...]:
    """The (row, column) pairs, row ≤ column, of a (k·d) × (k·d) element block in row-major order;
    row r is coordinate r % d of corner r // d."""
    size = corners * dim
    return tuple((row, column) for row in range(size) for column in range(row, size))


def _mapped(matrix: Entries, gradients: list[list[Tensor]]) -> Entries:
    # (M ∇N_b)_i for every corner b: [b][i]
    dim = len(matrix)
    return [[sum(matrix[i][j] * row[j] for j in range(dim)) for i in range(dim)] for row in gradients]


def _corner_gradients(shape_gradient_t: Tensor) -> list[list[Tensor]]:
    # ∇N_b entry by entry as `[m, 1]` columns, [b][j], from ∇N `[k, d, m]`
    corners, dim, _ = shape_gradient_t.shape
    return [[shape_gradient_t[b, j][:, None] for j in range(dim)] for b in range(corners)]


def stable_neo_hookean_hessian_entries(
    corners: Entries, shape_gradient_t: Tensor, rest_volume: Tensor, mu: Tensor, lam: Tensor
) -> list[Tensor]:
    """V Sᵀ ∂²ψ/∂F² S of `stable_neo_hookean_density`, the upper entries (`upper_entries`) `[m, B]`.

    Args:
        corners: `[i][b]` `[m, B]`, in m; shape_gradient_t: ∇N as `[k, d, m]`, in 1/m;
        rest_volume: V `[m]`; mu, lam: Pa, scalars or `[m, 1]`.
    """
    dim = len(corners)
    F = deformation_gradient_entries(corners, shape_gradient_t)
    mu_smith, lam_smith, alpha = smith_parameters(mu, lam)
    stretch_excess, volume_excess = (
        _per_element(value, rest_volume) for value in invariant_excess_entries(F)[:2]
    )
    inverse = 1.0 / (stretch_excess + 4.0)  # 1/(I_C + 1)
    volume = rest_volume[:, None]
    identity_weight = volume * mu_smith * (1.0 - inverse)
    stretch_weight = volume * 2.0 * mu_smith * inverse * inverse
    volume_weight = volume * lam_smith
    det_weight = volume * lam_smith * (volume_excess + 1.0 - alpha)
    gradients = _corner_gradients(shape_gradient_t)
    stretched = _mapped(F, gradients)
    cofactored = _mapped(cofactor_entries(F), gradients)
    det_blocks = _det_hessian_blocks(F, gradients, det_weight)
    entries = []
    for row, column in upper_entries(dim + 1, dim):
        (b, i), (c, k) = divmod(row, dim), divmod(column, dim)
        value = (
            stretch_weight * stretched[b][i] * stretched[c][k]
            + volume_weight * cofactored[b][i] * cofactored[c][k]
        )
        if i == k:
            value = value + identity_weight * sum(gradients[b][j] * gradients[c][j] for j in range(dim))
        elif b != c:
            value = value + det_blocks[b, c][i][k]
        entries.append(value)
    return entries


def _per_element(values: Tensor, rest_volume: Tensor) -> Tensor:
    # `values` `[m, B]` times one read per element that is 1 (V `[m]` is positive and finite).
    # Compiled batch-last, an intermediate computed from stored intermediates alone (the invariants,
    # from F) runs as a flat loop over m·B numbers that does not fuse with the loops over (element,
    # batch) before and after it, which must then store what it and they read; with one read per
    # element it joins them, and the block's arithmetic is one loop (docs/energies.md).
    return values * (rest_volume[:, None] * 0.0 + 1.0)


def _det_hessian_blocks(
    F: Entries, gradients: list[list[Tensor]], weight: Tensor
) -> dict[tuple[int, int], Entries]:
    # w Sᵀ ∂²J/∂F² S's (b, c) blocks for b < c (zero for b = c): [F(∇N_b × ∇N_c)]_ε in 3D,
    # (∇N_b × ∇N_c) ε in 2D; ε_ikp r_p has r_2 at (0, 1), −r_1 at (0, 2), r_0 at (1, 2)
    dim = len(F)
    blocks = {}
    for b in range(dim + 1):
        for c in range(b + 1, dim + 1):
            p, q = gradients[b], gradients[c]
            if dim == 2:
                cross = weight * (p[0] * q[1] - p[1] * q[0])
                blocks[b, c] = [[None, cross], [-cross, None]]
                continue
            normal = (p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0])
            r = [weight * sum(F[s][t] * normal[t] for t in range(3)) for s in range(3)]
            blocks[b, c] = [[None, r[2], -r[1]], [-r[2], None, r[0]], [r[1], -r[0], None]]
    return blocks


def fibre_hessian_entries(
    corners: Entries, fibre_weights: Tensor, stiffness: Tensor, target_stretch: Tensor | float
) -> list[Tensor]:
    """`energysim.fem.kernels.fibre_hessian_blocks` entry by entry: w_b w_c V k [n nᵀ + (1 − λ*/λ)(I −
    n nᵀ)], the upper entries `[m, B]`. `corners` `[i][b]` `[m, B]`, `fibre_weights` `[m, k]`,
    `stiffness` V k `[m, 1]` or a scalar, `target_stretch` λ* `[m, B]` or a scalar."""
    dim = len(corners)
    weight = [fibre_weights[:, b][:, None] for b in range(dim + 1)]
    fibre = [sum(weight[b] * corners[i][b] for b in range(dim + 1)) for i in range(dim)]
    squared = sum(component * component for component in fibre) + 1e-30
    stretch = squared.sqrt()
    transverse = stiffness * (1.0 - target_stretch / stretch)
    along = (stiffness - transverse) / squared  # V k (1 − τ) / λ², τ the transverse factor
    block = [[along * fibre[i] * fibre[k] for k in range(dim)] for i in range(dim)]
    for i in range(dim):
        block[i][i] = block[i][i] + transverse
    entries = []
    for row, column in upper_entries(dim + 1, dim):
        (b, i), (c, k) = divmod(row, dim), divmod(column, dim)
        entries.append(weight[b] * weight[c] * block[i][k])
    return entries


def lagged_viscosity_hessian_entries(
    start_gradient: Entries, shape_gradient_t: Tensor, weight: Tensor
) -> list[Tensor]:
    """`energysim.fem.kernels.lagged_viscosity_hessian_blocks` entry by entry: w[(F_nF_nᵀ)_ik
    ∇N_b·∇N_c + (F_n∇N_c)_i (F_n∇N_b)_k], the upper entries `[m, B]`. `start_gradient` F_n as
    `[i][j]` `[m, B]`, ∇N as `[k, d, m]`, w = ηV/h `[m]`."""
    dim = len(start_gradient)
    F = start_gradient
    w = weight[:, None]
    gradients = _corner_gradients(shape_gradient_t)
    mapped = _mapped(F, gradients)
    gram = [[w * sum(F[i][j] * F[k][j] for j in range(dim)) for k in range(dim)] for i in range(dim)]
    entries = []
    for row, column in upper_entries(dim + 1, dim):
        (b, i), (c, k) = divmod(row, dim), divmod(column, dim)
        dots = sum(gradients[b][j] * gradients[c][j] for j in range(dim))
        entries.append(gram[i][k] * dots + w * mapped[c][i] * mapped[b][k])
    return entries
