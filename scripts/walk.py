"""A shipped creature walks an open-loop gait on frictional ground; the run checks itself.

    python scripts/walk.py [--creature worm|quadruped|starfish|jumper|crawler2d|walker2d] [--seconds 5]
                           [--dt 0.01667] [--optimizer newton-cg|lbfgs|adam] [--tol 1e-3]
                           [--integrator implicit_euler|tr_bdf2] [--friction 0.8] [--frequency F]
                           [--amplitude A] [--phase-lag LAG] [--ramp 1] [--refine 1]
                           [--out out/walk_NAME] [--frames-every 1] [--window-size 960 540]
                           [--no-render] [--no-vtk] [--quiet] [--threads 1] [--compile]

The creature (default: the worm) starts at rest on a ground at y = 0 with friction μ = 0.8. Its
muscles follow a_j(t) = A sin(2π f t + φ_j), eased in over the first period; f and A default to the
creature's suggested gait, the phases φ_j follow from one phase lag as `SPECS` says:

- worm (360 tets), crawler2d (200 triangles, plane strain): a bending wave along five segments, the
  bottom muscle of segment s at s·lag, the top one opposite; lag = −2π/5 runs the wave from tail (−x)
  to head (+x). The worm goes about 1.2 body lengths in 5 s.
- quadruped (888 tets): each leg's front and back halves in opposition, front legs at 0, back legs at
  lag = −π/2 (a quarter period behind), 4 Hz: about 4 body lengths in 5 s.
- starfish (1548 tets): arm phases (π, 0, lag, lag, 0) for the front, side, back, back and side arm,
  top layer opposite bottom; lag = −π/2 creeps forward, slowly.
- jumper (816 tets): back leg at 0, front leg at lag = −π/4; a > 0 crouches, a < 0 kicks. It shuffles.
- walker2d (384 triangles): front leg at 0, back leg at lag = −π/2, each leg's halves in opposition,
  3 Hz. The body rocks on its legs, so it sways back within a stride.

What must hold (`check`, see `_locomotion`): no NaN, no vertex in the ground, forward displacement of
the centre of mass of at least the creature's `min_speed` (body lengths per second) after the ramp, and
never a backslide of more than its `max_backslide` (body lengths) behind the farthest point reached.

Writes to ``out/walk_NAME/``: ``frame_*.vtu`` + ``frame.pvd`` (velocity, displacement, strain energy
density, activation), ``NAME.png``, ``NAME.gif`` and ``NAME.mp4`` (when imageio-ffmpeg is installed).
"""

from __future__ import annotations

import math
import sys

from _locomotion import WalkSpec, bending_wave, script_main


def _legs_in_opposition(leg_phases: tuple[float, ...]) -> tuple[float, ...]:
    """Each leg (or arm) at its phase, its second muscle (back half, top layer) opposite."""
    return tuple(phase + math.pi * half for phase in leg_phases for half in (0, 1))


SEGMENTS = 5
# the per-creature gait and what its check asks for (speed in body lengths/s, backslide in body lengths)
SPECS: dict[str, WalkSpec] = {
    spec.creature: spec
    for spec in (
        WalkSpec("worm", bending_wave(SEGMENTS), -2 * math.pi / SEGMENTS, min_speed=0.12, max_backslide=0.02),
        WalkSpec(
            "quadruped",
            lambda lag: _legs_in_opposition((0.0, 0.0, lag, lag)),
            -math.pi / 2,
            min_speed=0.12,
            max_backslide=0.03,
        ),
        WalkSpec(
            "starfish",
            lambda lag: _legs_in_opposition((math.pi, 0.0, lag, lag, 0.0)),
            -math.pi / 2,
            min_speed=0.04,
            max_backslide=0.05,
        ),
        WalkSpec("jumper", lambda lag: (0.0, lag), -math.pi / 4, min_speed=0.03, max_backslide=0.08),
        WalkSpec(
            "crawler2d", bending_wave(SEGMENTS), -2 * math.pi / SEGMENTS, min_speed=0.12, max_backslide=0.02
        ),
        WalkSpec(
            "walker2d",
            lambda lag: _legs_in_opposition((0.0, lag)),
            -math.pi / 2,
            min_speed=0.1,
            max_backslide=0.12,
        ),
    )
}


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns 0 when the run passes its check."""
    return script_main(argv, __doc__, SPECS, default="worm")


if __name__ == "__main__":
    sys.exit(main())
