"""Products of tiny per-element matrices that `torch.compile` can fuse.

Inductor hands every `@` to the BLAS batched matrix product, which it never fuses with the
element-wise code around it and which is slow for matrices this small. Written as a broadcast
product summed over the shared index, the same arithmetic becomes part of the generated loops.
Where this pays was measured, not assumed. On the CPU: for the neo-Hookean Hessian blocks
K = (√V S)ᵀ ∂²ψ/∂F² (√V S) (9×12 strain maps around a 9×9 stiffness) it cut the compiled band
Hessian by 12–20 % (cantilever, one worm, 16 and 64 worms, one thread); for the 3×3 products of the
deformation gradient and the stress it made the compiled energy and gradient slower (0.22 → 0.31 ms
on the 810-tet cantilever), because Inductor then recomputes F inside every consumer's loop, so
those keep `@` there (`fuse_on_cpu=False`). On a GPU every product fuses: there each `@` was one
cuBLAS batched product over millions of 3×3 or 12×9 matrices (4,096 worms of 360 tetrahedra), about
2 ms apiece, and together 85 % of the GPU time of a Newton iteration (docs/envs.md, "On a CUDA GPU").
Eager code keeps `@` (the broadcast form would materialise the whole product).
"""

from __future__ import annotations

import torch
from torch import Tensor


def small_matmul(a: Tensor, b: Tensor, *, fuse_on_cpu: bool = False) -> Tensor:
    """a @ b for batches of small matrices `[..., i, k]` and `[..., k, j]` (broadcast like `@`).

    While `torch.compile` traces tensors off the CPU, or CPU tensors with `fuse_on_cpu`, the
    product is a broadcast multiply and a sum over k, which the compiler fuses into the surrounding
    loops; otherwise it is `a @ b`. The two agree up to the order of the k additions.
    """
    if torch.compiler.is_compiling() and (fuse_on_cpu or a.device.type != "cpu"):
        return (a[..., :, :, None] * b[..., None, :, :]).sum(dim=-2)
    return a @ b
