"""Products of tiny per-element matrices that `torch.compile` can fuse on the CPU.

Inductor hands every `@` to the BLAS batched matrix product, which it never fuses with the
element-wise code around it and which is slow for matrices this small. Written as a broadcast
product summed over the shared index, the same arithmetic becomes part of the generated loops.
Where this pays was measured, not assumed: for the neo-Hookean Hessian blocks
K = (√V S)ᵀ ∂²ψ/∂F² (√V S) (9×12 strain maps around a 9×9 stiffness) it cut the compiled band
Hessian by 12–20 % (cantilever, one worm, 16 and 64 worms, one thread); for the 3×3 products of the
deformation gradient and the stress it made the compiled energy and gradient slower (0.22 → 0.31 ms
on the 810-tet cantilever), because Inductor then recomputes F inside every consumer's loop, so
those keep `@`. Eager code keeps `@` too (the broadcast form would materialise the whole product),
and so does compiled GPU code, which was not measured.
"""

from __future__ import annotations

import torch
from torch import Tensor


def small_matmul(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for batches of small matrices `[..., i, k]` and `[..., k, j]` (broadcast like `@`).

    While `torch.compile` traces CPU tensors, the product is a broadcast multiply and a sum over k,
    which the compiler fuses into the surrounding loops; otherwise it is `a @ b`. The two agree up
    to the order of the k additions.
    """
    if torch.compiler.is_compiling() and a.device.type == "cpu":
        return (a[..., :, :, None] * b[..., None, :, :]).sum(dim=-2)
    return a @ b
