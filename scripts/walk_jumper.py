"""The jumper hops: two thick legs crouch and kick, the back leg ahead of the front; the run checks itself.

    python scripts/walk_jumper.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam]
                                  [--tol 1e-3] [--friction 0.8] [--frequency 1] [--amplitude 1]
                                  [--phase-lag -0.7854] [--ramp 1] [--refine 1] [--out out/walk_jumper]
                                  [--frames-every 1] [--window-size 960 540] [--no-render] [--no-vtk]
                                  [--quiet] [--threads 1] [--compile]

The shipped jumper (a 0.20 m body on two 3×3×4-voxel legs, 816 tets, E = 100 kPa, ν = 0.4,
ρ = 1000 kg/m³, strong vertical fibres: k = 1 MPa, c = 0.35) stands on a ground with friction μ = 0.8.
The back leg gets A sin(2π f t), the front leg A sin(2π f t + lag) (eased in over the first period):
a > 0 shortens a leg (crouch), a < 0 lengthens it (kick), and with lag < 0 the back leg kicks first,
tipping the body forward. It does not leave the ground: it shuffles, a few centimetres per stride.

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass ≥ 0.03 body lengths per second after the ramp, and never a backslide of more than
0.08 body lengths behind the farthest point reached (it rocks back a little as the front leg kicks).

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``jumper.png``, ``jumper.gif`` and ``jumper.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, script_main


def phases(lag: float) -> tuple[float, ...]:
    """Back leg at phase 0, front leg at `lag`."""
    return (0.0, lag)


SPEC = WalkSpec(
    creature="jumper",
    phases=phases,
    phase_lag=-math.pi / 4,
    seconds=5.0,
    min_speed=0.03,
    max_backslide=0.08,
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPEC)


if __name__ == "__main__":
    sys.exit(main())
