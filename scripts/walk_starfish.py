"""The starfish creeps: its five arms push in a fixed phase pattern; the run checks itself.

    python scripts/walk_starfish.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam]
                                    [--tol 1e-3] [--friction 0.8] [--frequency 1.5] [--amplitude 1]
                                    [--phase-lag -1.5708] [--ramp 1] [--refine 1] [--out out/walk_starfish]
                                    [--frames-every 1] [--window-size 960 540] [--no-render] [--no-vtk]
                                    [--quiet] [--threads 1] [--compile]

The shipped starfish (a flat 0.29 m five-armed star, 1548 tets, E = 100 kPa, ν = 0.4, ρ = 1000 kg/m³)
lies on a ground with friction μ = 0.8. Arm k points at angle 2πk/5 from +x towards +z; its bottom and
top layers are muscles with radial fibres, driven in opposition so the arm curls up and down (eased in
over the first period). The arm phases are π for the front arm (0), 0 for the side arms (1, 4) and
`lag` for the back arms (2, 3): with lag = −π/2 the back arms push a quarter period after the side
arms and the star creeps forward, slowly (a wave running round the arms went nowhere in trials).

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass ≥ 0.04 body lengths per second after the ramp, and never a backslide of more than
0.05 body lengths behind the farthest point reached.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``starfish.png``, ``starfish.gif`` and ``starfish.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, script_main

ARMS = 5


def phases(lag: float) -> tuple[float, ...]:
    """Arm phases (π, 0, lag, lag, 0) for the front, side, back, back, side arm; top layer opposite bottom."""
    arm_phase = (math.pi, 0.0, lag, lag, 0.0)
    return tuple(arm_phase[arm] + math.pi * layer for arm in range(ARMS) for layer in (0, 1))


SPEC = WalkSpec(
    creature="starfish",
    phases=phases,
    phase_lag=-math.pi / 2,
    seconds=5.0,
    min_speed=0.04,
    max_backslide=0.05,
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPEC)


if __name__ == "__main__":
    sys.exit(main())
