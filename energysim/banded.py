"""Band Cholesky solves of small Hessians on the CPU, through LAPACK's `?pbtrf` / `?pbtrs` (scipy).

A long body couples each vertex only to near neighbours. With the DOFs numbered level by level
(`LevelLayout.band_order`, Cuthill–McKee levels) its Hessian is a band matrix of half-bandwidth u,
and a band Cholesky factorisation costs about N·u² flops against a dense one's N³/3. For the worm
(N = 432, u = 44) a factorisation and solve, gathers included, takes 0.52 ms in the solver against
1.26 ms for the dense Cholesky and solve it replaced (profiled on one core). Unlike
the block-tridiagonal solve, it is one LAPACK call per system, with no Python loop over levels, so it
pays for a single body too. LAPACK has no batched band routine, so a batch is a loop over entries,
and there is no CUDA one: this path is for small batches on the CPU (`prefer_band`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.block_tridiagonal import LevelLayout

# Band storage wins when N·(u+1)² is well below N³/3; LAPACK's band kernels run at a fraction of the
# dense kernel's flop rate at these sizes, so ask for a clear margin.
BAND_MARGIN = 6
# Entries of a batch are factorised one LAPACK call each; past a few, the batched level solve wins.
BAND_MAX_BATCH = 4


def prefer_band(layout: LevelLayout, batch: int, num_dofs: int, device: torch.device) -> bool:
    """Whether a band factorisation is estimated cheaper than a dense one (N = `num_dofs`)."""
    narrow = BAND_MARGIN * (layout.half_bandwidth + 1) ** 2 < num_dofs**2
    return device.type == "cpu" and batch <= BAND_MAX_BATCH and narrow


def band_cholesky_solve(dense: Tensor, rhs: Tensor, layout: LevelLayout) -> tuple[Tensor, Tensor]:
    """Solve symmetric `dense` `[B, N, N]` systems for `rhs` `[B, N]` by band Cholesky in the layout's
    ordering; returns the solutions `[B, N]` (zero where a system is not positive definite) and which
    systems were positive definite `[B]`. CPU tensors, float32 or float64."""
    from scipy.linalg import lapack

    batch, size = rhs.shape
    order = layout.band_order
    # [B, N, u+1] C-contiguous: each entry's transpose is the Fortran-ordered `ab` LAPACK reads
    bands = dense.reshape(batch, size * size)[:, layout.band_entries].contiguous()
    permuted = rhs[:, order].contiguous()
    solution = torch.zeros_like(rhs)
    positive_definite = torch.zeros(batch, dtype=torch.bool, device=rhs.device)
    factorise, substitute = lapack.get_lapack_funcs(("pbtrf", "pbtrs"), (permuted.numpy(),))
    for entry in range(batch):
        factor, info = factorise(bands[entry].numpy().T, lower=0, overwrite_ab=1)
        if info != 0:
            continue
        values, info = substitute(factor, permuted[entry].numpy(), lower=0)
        if info == 0:
            solution[entry, order] = torch.from_numpy(values)
            positive_definite[entry] = True
    return solution, positive_definite
