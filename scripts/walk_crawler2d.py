"""The 2D crawler crawls: a bending wave runs from tail to head along its five segments; checks itself.

    python scripts/walk_crawler2d.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam]
                                     [--tol 1e-3] [--friction 0.8] [--frequency 1.5] [--amplitude 1]
                                     [--phase-lag -1.2566] [--ramp 1] [--refine 1] [--out out/walk_crawler2d]
                                     [--frames-every 1] [--window-size 960 540] [--no-render] [--no-vtk]
                                     [--quiet] [--threads 1] [--compile]

The shipped 2D crawler (a 0.30 m × 0.048 m strip, 200 triangles in plane strain, quantities per metre
of depth, E = 100 kPa, ν = 0.4, ρ = 1000 kg/m³) lies on a ground line with friction μ = 0.8. Each of its
five segments has a bottom and a top muscle with fibres along x; segment s gets a_bottom =
A sin(2π f t + s·lag), a_top the opposite (eased in over the first period), and with lag = −2π/5 the
bending wave runs from tail (−x) to head (+x). Gravity is (0, −9.81) m/s².

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass ≥ 0.12 body lengths per second after the ramp, and never a backslide of more than
0.02 body lengths behind the farthest point reached.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``crawler2d.png``, ``crawler2d.gif`` and ``crawler2d.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, bending_wave, script_main

SEGMENTS = 5


SPEC = WalkSpec(
    creature="crawler2d",
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
