"""When a solve stops for lack of progress: the record of iterations that no longer improve anything
beyond the rounding of E and ∇E, per batch entry, and the best iterate met meanwhile."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Iterations in a row without progress (`Stagnation`) after which an entry stops: Newton's residual
# falls by orders of magnitude per iteration near a minimum; L-BFGS's, superlinearly at best, can
# take dozens of iterations whose energy changes lie below the noise before it falls by 10 %
# (a stiff rotated box, at 1e-3 m/s).
STALL_ITERATIONS = 5
LBFGS_STALL_ITERATIONS = 50
# A new best residual must be below this fraction of the previous best to count as progress.
STALL_RESIDUAL_FRACTION = 0.9


@dataclass(frozen=True)
class Stagnation:
    """Per batch entry, the iterations in a row that made no progress, so that a solve stuck at the
    rounding floor stops after `window` such iterations instead of spinning until `max_iter`, and returns
    the best iterate it met there.

    An iteration makes progress where the velocity residual falls below `STALL_RESIDUAL_FRACTION` of
    the best so far, or the energy falls by more than its rounding: the largest allowance of the
    solve's line searches (`LineStep.allowance`: the noise, where they measured it; a search whose
    first trial passes does not measure it, and its allowance is far below the noise measured a step
    before) and 64 ulps of the largest |E| of the solve. That scale stands for the magnitude of the
    terms E sums, which set its rounding where the noise was never measured: E itself can vanish at
    the minimum while they do not (an unloaded body at rest), so |E| there says nothing. Far from
    the minimum the energy falls by far more; near it Newton's residual falls by orders of magnitude
    per iteration: only an iterate whose steps the rounding decides stops. At that floor the steps
    are rounding's, and may raise the residual by orders of magnitude while the energy "falls" by
    its noise: hence the best iterate is kept.

    Attributes:
        best: the smallest residual so far `[B]`, in m/s; best_x: where it was met `[B, n, d]`, in m.
        scale: the largest |E| so far `[B]`, in J; noise: the largest line-search allowance so far
            `[B]`, in J.
        count: iterations in a row without progress `[B]`.
        window: how many of them stop an entry.
    """

    best: Tensor
    best_x: Tensor
    scale: Tensor
    noise: Tensor
    count: Tensor
    window: int = STALL_ITERATIONS

    @staticmethod
    def start(x: Tensor, energy: Tensor, residual: Tensor, window: int = STALL_ITERATIONS) -> Stagnation:
        """The record at the start of a solve from `x` `[B, n, d]`, with E `[B]` and the residual
        `[B]` there."""
        count = torch.zeros_like(residual, dtype=torch.long)
        return Stagnation(residual.clone(), x, energy.abs(), torch.zeros_like(energy), count, window)

    def update(
        self,
        active: Tensor,
        energy: Tensor,
        new_x: Tensor,
        new_energy: Tensor,
        new_residual: Tensor,
        allowance: Tensor,
    ) -> tuple[Stagnation, Tensor]:
        """The record after an iteration of the `active` entries from E `energy` to `new_energy` `[B]`
        at `new_x` `[B, n, d]`, with `new_residual` `[B]` there and the line search's rounding
        `allowance` `[B]` in J, and which entries now stop `[B]`."""
        eps = torch.finfo(energy.dtype).eps
        scale = torch.maximum(self.scale, new_energy.abs())
        noise = torch.maximum(self.noise, allowance)
        improved = new_residual < STALL_RESIDUAL_FRACTION * self.best
        descended = energy - new_energy > torch.maximum(64 * eps * scale, noise)
        progress = improved | descended
        count = torch.where(active & ~progress, self.count + 1, torch.zeros_like(self.count))
        better = new_residual < self.best
        best_x = torch.where(better[:, None, None], new_x, self.best_x)
        best = torch.where(better, new_residual, self.best)
        record = Stagnation(best, best_x, scale, noise, count, self.window)
        return record, active & (count >= self.window)

    def rows(self, rows: Tensor) -> Stagnation:
        """The record of the batch entries `rows` alone."""
        return Stagnation(
            self.best[rows],
            self.best_x[rows],
            self.scale[rows],
            self.noise[rows],
            self.count[rows],
            self.window,
        )

    def best_of(self, x: Tensor, residual: Tensor, stopped: Tensor) -> tuple[Tensor, Tensor]:
        """`x` `[B, n, d]` and `residual` `[B]`, with the best iterate where an entry `stopped` `[B]`
        short of it."""
        back = stopped & (self.best < residual)
        return torch.where(back[:, None, None], self.best_x, x), torch.where(back, self.best, residual)
