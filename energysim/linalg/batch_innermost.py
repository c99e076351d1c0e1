"""Per-entry data laid out with the batch innermost, in rows padded apart, for the batch-last kernels.

The batch-last element kernels (`energysim.objective.batch_last`) read each term's per-entry data
(a lagged viscosity's F_n, a lagged friction's x_n and projectors) as `[..., m, B]` arrays. Packed,
such an array is also one flat run of m·B numbers, and Inductor's CPU code generator then iterates
every node that reads only such arrays (and intermediates of the same shape) as one flat loop,
while the nodes that read a per-element constant or gather the positions keep (element, entry)
loops. The two kinds of loop do not fuse, so the flat ones wrote their results to memory and the
others read them back: some twenty `[m, B]` buffers for the lagged viscosity alone in the worm's
line-search trial. With the rows `BATCH_ROW_PADDING` numbers further apart than B, no loop over
them can be flattened, and they fuse: the 64-worm trial took 2.00 instead of 2.23 ms, the step
0.94× (docs/envs.md, "Batch-innermost data in padded rows").
"""

from __future__ import annotations

from torch import Tensor

# extra numbers between consecutive rows: 8 float64 keep each row's start 64-byte aligned where B is
# a multiple of 8
BATCH_ROW_PADDING = 8


def batch_innermost(values: Tensor, *dims: int) -> Tensor:
    """`values.permute(*dims)` (its last dimension the batch) copied into rows `BATCH_ROW_PADDING`
    numbers longer than the batch: the same values and shape, the last dimension contiguous, the
    others strided past the padding."""
    permuted = values.permute(*dims)
    batch = permuted.shape[-1]
    storage = permuted.new_empty(*permuted.shape[:-1], batch + BATCH_ROW_PADDING)
    view = storage[..., :batch]
    view.copy_(permuted)
    return view
