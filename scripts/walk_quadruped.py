"""The quadruped walks: front legs together, back legs a quarter period behind; the run checks itself.

    python scripts/walk_quadruped.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam]
                                     [--tol 1e-3] [--friction 0.8] [--frequency 4] [--amplitude 1]
                                     [--phase-lag -1.5708] [--ramp 1] [--refine 1] [--out out/walk_quadruped]
                                     [--frames-every 1] [--window-size 960 540] [--no-render] [--no-vtk]
                                     [--quiet] [--threads 1] [--compile]

The shipped quadruped (a 0.25 m body on four legs, 888 tets, E = 200 kPa, ν = 0.4, ρ = 1000 kg/m³)
stands on a ground with friction μ = 0.8. Each leg's front and back halves are muscles with vertical
fibres, driven in opposition, so the leg bends back and forth: front half A sin(2π f t + φ_leg), back
half the opposite (eased in over the first period), with φ = 0 for the front legs and φ = lag for the
back legs. With lag = −π/2 (back legs a quarter period behind) at 4 Hz it goes forward, about 4 body
lengths in 5 s (at h = 1/120 s within about 10 % of that); at 3 Hz it was slower and swayed back by a
tenth of its length in every stride; a trot (diagonal legs together) or the back legs leading went
backwards in trials.

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass ≥ 0.12 body lengths per second after the ramp (so more than half a body length in
5 s), and never a backslide of more than 0.03 body lengths behind the farthest point reached.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``quadruped.png``, ``quadruped.gif`` and ``quadruped.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, script_main


def phases(lag: float) -> tuple[float, ...]:
    """Front legs at phase 0, back legs at `lag` (order as the actuators); a leg's halves opposite."""
    leg_phase = (0.0, 0.0, lag, lag)
    return tuple(leg_phase[leg] + math.pi * half for leg in range(4) for half in (0, 1))


SPEC = WalkSpec(
    creature="quadruped",
    phases=phases,
    phase_lag=-math.pi / 2,
    seconds=5.0,
    min_speed=0.12,
    max_backslide=0.03,
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPEC)


if __name__ == "__main__":
    sys.exit(main())
