"""The worm crawls: a bending wave runs from tail to head along its five segments; the run checks itself.

    python scripts/walk_worm.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam] [--tol 1e-3]
                                [--friction 0.8] [--frequency 1.5] [--amplitude 1] [--phase-lag -1.2566]
                                [--ramp 1] [--refine 1] [--out out/walk_worm] [--frames-every 1]
                                [--window-size 960 540] [--no-render] [--no-vtk] [--quiet] [--threads 1]
                                [--compile]

The shipped worm (0.30 m × 0.04 m × 0.04 m, 360 tets, E = 100 kPa, ν = 0.4, ρ = 1000 kg/m³) lies on a
ground with friction μ = 0.8. Each of its five segments has a bottom and a top muscle with fibres along
x; segment s gets a_bottom = A sin(2π f t + s·lag), a_top the opposite (eased in over the first period),
so the body bends up and down, and with lag = −2π/5 the wave runs from tail (−x) to head (+x) and
pushes the worm forward: about 1.2 body lengths in 5 s.

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass ≥ 0.12 body lengths per second after the ramp (so more than half a body length in
5 s), and never a backslide of more than 0.02 body lengths behind the farthest point reached.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``worm.png``, ``worm.gif`` and ``worm.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, bending_wave, script_main

SEGMENTS = 5


SPEC = WalkSpec(
    creature="worm",
    phases=bending_wave(SEGMENTS),
    phase_lag=-2 * math.pi / SEGMENTS,
    seconds=5.0,
    min_speed=0.12,
    max_backslide=0.02,
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPEC)


if __name__ == "__main__":
    sys.exit(main())
