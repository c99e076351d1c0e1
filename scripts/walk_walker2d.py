"""The 2D walker walks on two rocking legs, the back leg a quarter period behind; the run checks itself.

    python scripts/walk_walker2d.py [--seconds 5] [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam]
                                    [--tol 1e-3] [--friction 0.8] [--frequency 3] [--amplitude 1]
                                    [--phase-lag -1.5708] [--ramp 1] [--refine 1] [--out out/walk_walker2d]
                                    [--frames-every 1] [--window-size 960 540] [--no-render] [--no-vtk]
                                    [--quiet] [--threads 1] [--compile]

The shipped 2D walker (a 0.24 m × 0.06 m body on a front and a back 0.04 m × 0.06 m leg, 384 triangles
in plane strain, per metre of depth, E = 100 kPa, ν = 0.4, ρ = 1000 kg/m³) stands on a ground line with
friction μ = 0.8 under gravity (0, −9.81) m/s². Each leg's front and back halves are muscles with
vertical fibres, driven in opposition so the leg bends back and forth: the front leg's front half gets
A sin(2π f t), the back leg's front half A sin(2π f t + lag), each back half the opposite, eased in
over the first period. With lag = −π/2 at 3 Hz it walks forward, by the same gait at h = 1/60 s and
1/120 s; with the back leg ahead (lag = π/2) it rocked back by half its length in a stride at 2 Hz and
walked backwards at 3 Hz, and faster gaits changed direction with the time step.

The body rocks on its legs, so its centre of mass sways back within a stride (most, about 0.08 body
lengths, in the first stride after the ramp). What must hold (`check`, see `_locomotion`): no NaN, no
vertex in the ground, forward displacement of the centre of mass ≥ 0.1 body lengths per second after
the ramp, and never a backslide of more than 0.12 body lengths behind the farthest point reached.

Writes ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy density, activation),
``walker2d.png``, ``walker2d.gif`` and ``walker2d.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, script_main


def phases(lag: float) -> tuple[float, ...]:
    """Front leg at phase 0, back leg at `lag` (< 0: behind); a leg's back half opposite its front half."""
    leg_phase = (0.0, lag)
    return tuple(leg_phase[leg] + math.pi * half for leg in range(2) for half in (0, 1))


SPEC = WalkSpec(
    creature="walker2d",
    phases=phases,
    phase_lag=-math.pi / 2,
    seconds=5.0,
    min_speed=0.1,
    max_backslide=0.12,
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPEC)


if __name__ == "__main__":
    sys.exit(main())
