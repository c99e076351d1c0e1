"""One creature model, two discretisations: the suggested gait's distance in the implicit and the
explicit env as each is refined, their extrapolated limits and the gap between them.

Both envs share the body model (`energysim.envs.config`: η = 30 Pa·s, τ = 0.05 s, μ = 0.8); they
differ in the time discretisation and the ground contact (the IPC barrier with smoothed, lagged
friction in the implicit step; an inelastic projection with Coulomb friction in the leapfrog). The
creature walks its open-loop gait (`Creature.gait_action`, held over each env step of 1/60 s, so
every run sees the same command) for `--seconds` from a noiseless reset; the distance is that of the
centre of mass along +x.

- implicit Euler at h = 1/60, 1/120, 1/240, 1/480 s (frame_skip 1, 2, 4, 8) at `--tol` m/s, plus
  the env's defaults (h = 1/60 s, tol 1e-4 m/s);
- leapfrog at h = 1/60, 1/120, 1/240, 1/480 s (frame_skip 1, 2, 4, 8) with 32 substeps each, so
  32, 64, 128, 256 substeps per 1/60 s (the first is the env's default for the worm).

Both envs advance the muscles' activation (τ = 0.05 s) once per physics step and hold it over that
step, so both sequences refine the activation's sampling with the time step and converge to the same
model: continuous activation dynamics. `--friction-smoothing` (ε_v, m/s) and `--barrier-distance`
(d̂, m, at an unchanged κ·d̂) replace the implicit ground's settings in the refined implicit runs, to
measure how far the contact's regularisation moves the implicit limit; the default run keeps the
env's own.

Each sequence's limit is extrapolated from its three finest runs (Richardson with the observed
order p = log2(|d₂ − d₁| / |d₃ − d₂|), p kept in [0.5, 3]); its error estimate is the distance of
the finest run from that limit. The largest velocity residual any implicit solve left is reported
beside each implicit run.

Run:  python scripts/bench_env_models.py                     # the worm, 2 s (about 10 minutes)
      python scripts/bench_env_models.py --quick             # 0.1 s, two levels each (a test)
      python scripts/bench_env_models.py --barrier-distance 1e-4 --friction-smoothing 1e-2
Writes: <out>/bench_env_models.csv and <out>/bench_env_models.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from _bench import configure_threads, make_parser, table, write_outputs

from energysim.creatures import CREATURES, resting_state, scene_ground
from energysim.envs import CreatureEnv

ENV_STEP = 1 / 60
IMPLICIT_FRAME_SKIPS = (1, 2, 4, 8)
EXPLICIT_FRAME_SKIPS = (1, 2, 4, 8)
EXPLICIT_SUBSTEPS = 32
TIGHT_TOL = 1e-6
DEFAULT_TOL = 1e-4


@dataclass(frozen=True)
class Run:
    """One gait of one discretisation: `dt` the physics step h in s, `frame_skip` physics steps per
    env step, `substeps` leapfrog substeps per env step of 1/60 s (0 for an implicit run), the ground's
    `friction_smoothing` ε_v in m/s and `barrier_distance` d̂ in m (NaN for the leapfrog)."""

    integrator: str
    dt: float
    frame_skip: int
    substeps: int
    solver_tol: float
    friction_smoothing: float
    barrier_distance: float
    distance: float
    max_residual: float
    mean_iterations: float
    seconds: float


@dataclass(frozen=True)
class Limit:
    """A sequence's extrapolated limit (m), its observed order and the finest run's distance from it."""

    distance: float
    order: float
    finest_error: float


def set_contact(env: CreatureEnv, friction_smoothing: float | None, barrier_distance: float | None) -> None:
    """Replace the implicit ground's ε_v (m/s) and d̂ (m) of a freshly built `env`, before its reset.

    A new d̂ scales κ by the old d̂ over the new one, so κ·d̂ (the barrier's force scale) stays that of
    the env, and the rest state is placed again at d̂/2 above the ground. None keeps a setting."""
    for name, value in (("friction_smoothing", friction_smoothing), ("barrier_distance", barrier_distance)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and > 0, got {value}")
    if env.config.integrator == "leapfrog" and (friction_smoothing, barrier_distance) != (None, None):
        raise ValueError("friction_smoothing and barrier_distance set the implicit ground; the leapfrog "
                         "ground is an inelastic projection without either")
    ground = scene_ground(env.simulation.scene)
    if friction_smoothing is not None:
        ground.friction_smoothing = float(friction_smoothing)
    if barrier_distance is not None:
        old = ground.barrier_distance
        ground.barrier_distance = float(barrier_distance)
        ground.barrier_stiffness.mul_(old / float(barrier_distance))
        env.simulation.rest_state = resting_state(env.simulation.scene)


def gait(
    creature: str,
    seconds: float,
    friction_smoothing: float | None = None,
    barrier_distance: float | None = None,
    **options: object,
) -> Run:
    """The suggested gait for `seconds` in one `CreatureEnv` with `options` (its `dt`, `frame_skip`
    with frame_skip·dt = 1/60 s, `integrator`, ...), from a noiseless reset; `friction_smoothing` and
    `barrier_distance` replace the implicit ground's (`set_contact`)."""
    env = CreatureEnv(creature, reset_noise_scale=0.0, **options)
    set_contact(env, friction_smoothing, barrier_distance)
    _, info = env.reset(seed=0)
    start = info["x_position"]
    residuals, iterations = [0.0], []
    began = time.perf_counter()
    for k in range(round(seconds / ENV_STEP)):
        action = env.simulation.creature.gait_action(k * ENV_STEP).numpy()
        _, _, terminated, _, info = env.step(action)
        if terminated:
            raise RuntimeError(f"the {creature}'s gait failed at env step {k} with {options}")
        residuals.append(info["solver_residual"])
        iterations.append(info["solver_iterations"] / env.config.frame_skip)
    config = env.config
    explicit = config.integrator == "leapfrog"
    ground = scene_ground(env.simulation.scene)
    return Run(
        integrator=config.integrator,
        dt=config.dt,
        frame_skip=config.frame_skip,
        substeps=env.simulation.scene.substeps * config.frame_skip if explicit else 0,
        solver_tol=float("nan") if explicit else config.solver_tol,
        friction_smoothing=float("nan") if explicit else ground.friction_smoothing,
        barrier_distance=float("nan") if explicit else ground.barrier_distance,
        distance=info["x_position"] - start,
        max_residual=max(residuals),
        mean_iterations=float(np.mean(iterations)) if iterations else float("nan"),
        seconds=time.perf_counter() - began,
    )


def extrapolate(distances: list[float]) -> Limit:
    """The limit of a refined sequence (each level twice as fine as the last) from its last three
    values; with two values, first order."""
    if len(distances) < 2:
        return Limit(distances[-1], float("nan"), float("nan"))
    order = 1.0
    if len(distances) >= 3:
        d1, d2, d3 = distances[-3:]
        if abs(d3 - d2) > 0 and abs(d2 - d1) > 0:
            order = min(3.0, max(0.5, math.log2(abs(d2 - d1) / abs(d3 - d2))))
    limit = distances[-1] + (distances[-1] - distances[-2]) / (2**order - 1)
    return Limit(limit, order, abs(distances[-1] - limit))


@dataclass(frozen=True)
class Study:
    """Both sequences, their limits and the gaps (relative to the explicit value)."""

    creature: str
    seconds: float
    implicit: list[Run]
    implicit_default: Run
    explicit: list[Run]
    implicit_limit: Limit
    explicit_limit: Limit

    @property
    def gap_default(self) -> float:
        """|implicit − explicit| / |explicit| at the envs' default settings."""
        return relative_gap(self.implicit_default.distance, self.explicit[0].distance)

    @property
    def gap_finest(self) -> float:
        return relative_gap(self.implicit[-1].distance, self.explicit[-1].distance)

    @property
    def gap_limits(self) -> float:
        return relative_gap(self.implicit_limit.distance, self.explicit_limit.distance)


def relative_gap(a: float, b: float) -> float:
    return abs(a - b) / abs(b) if b != 0 else float("inf")


def run(
    creature: str = "worm",
    seconds: float = 2.0,
    frame_skips: tuple[int, ...] = IMPLICIT_FRAME_SKIPS,
    explicit_frame_skips: tuple[int, ...] = EXPLICIT_FRAME_SKIPS,
    tol: float = TIGHT_TOL,
    friction_smoothing: float | None = None,
    barrier_distance: float | None = None,
) -> Study:
    """Both envs' gaits at every level, and the implicit env's at its defaults; `friction_smoothing`
    (m/s) and `barrier_distance` (m) replace the ground's in the refined implicit runs only."""
    contact = {"friction_smoothing": friction_smoothing, "barrier_distance": barrier_distance}
    implicit = [
        gait(creature, seconds, dt=ENV_STEP / k, frame_skip=k, solver_tol=tol, solver_max_iter=200, **contact)
        for k in frame_skips
    ]
    default = gait(creature, seconds, solver_tol=DEFAULT_TOL)
    explicit = [
        gait(creature, seconds, integrator="leapfrog", dt=ENV_STEP / k, frame_skip=k,
             substeps=EXPLICIT_SUBSTEPS)
        for k in explicit_frame_skips
    ]
    for r in [*implicit, default, *explicit]:
        print(f"{r.integrator} h={r.dt:.5f} substeps/env step={r.substeps} tol={r.solver_tol:g}: "
              f"{r.distance:.5f} m, residual {r.max_residual:.1e}, {r.seconds:.1f} s", flush=True)
    return Study(
        creature=creature,
        seconds=seconds,
        implicit=implicit,
        implicit_default=default,
        explicit=explicit,
        implicit_limit=extrapolate([r.distance for r in implicit]),
        explicit_limit=extrapolate([r.distance for r in explicit]),
    )


def check(study: Study) -> None:
    """Every gait finished finite, every implicit solve reached its tolerance, and the limits exist."""
    for r in [*study.implicit, study.implicit_default, *study.explicit]:
        assert math.isfinite(r.distance), r
        if r.integrator != "leapfrog":
            assert r.max_residual <= r.solver_tol, r
    assert math.isfinite(study.implicit_limit.distance) and math.isfinite(study.explicit_limit.distance)


def markdown(study: Study) -> str:
    """Both sequences and the gaps as markdown."""
    lines = [
        f"The {study.creature}'s suggested gait for {study.seconds:g} s, one body model (η = 30 Pa·s, "
        "τ = 0.05 s, μ = 0.8), centre-of-mass distance along +x. Implicit: Newton–CG with the IPC "
        "ground (barrier distance d̂, friction smoothing ε_v); residual: the largest velocity residual "
        "a solve left. Explicit: leapfrog substeps with the inelastic ground. Both update the "
        "activation once per physics step h.",
        "",
    ]
    rows = []
    for r in [*study.implicit, study.implicit_default, *study.explicit]:
        implicit = r.integrator != "leapfrog"
        rows.append([
            r.integrator, f"1/{round(1 / r.dt)}", "" if implicit else r.substeps,
            f"{r.solver_tol:.0e}" if implicit else "", f"{r.friction_smoothing:.0e}" if implicit else "",
            f"{r.barrier_distance:.2e}" if implicit else "", f"{r.distance:.5f}",
            f"{r.max_residual:.1e}" if implicit else "", f"{r.mean_iterations:.1f}" if implicit else "",
            f"{r.seconds:.1f}",
        ])
    lines += table(["integrator", "h (s)", "substeps per 1/60 s", "tol (m/s)", "ε_v (m/s)", "d̂ (m)",
                    "distance (m)", "max residual (m/s)", "Newton its/step", "wall (s)"], rows)
    il, el = study.implicit_limit, study.explicit_limit
    lines += [
        "",
        f"- implicit limit {il.distance:.5f} m (observed order {il.order:.2f}; finest run "
        f"{il.finest_error:.1e} m from it)",
        f"- explicit limit {el.distance:.5f} m (observed order {el.order:.2f}; finest run "
        f"{el.finest_error:.1e} m from it)",
        f"- gap at the default settings (implicit h = 1/60 s, tol {DEFAULT_TOL:g}; explicit "
        f"h = 1/{round(1 / study.explicit[0].dt)} s, {study.explicit[0].substeps} substeps per 1/60 s): "
        f"{100 * study.gap_default:.1f} %",
        f"- gap at the finest settings: {100 * study.gap_finest:.1f} %; between the limits: "
        f"{100 * study.gap_limits:.1f} %",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> Study:
    parser = make_parser(__doc__, "bench_env_models", plot=False)
    parser.add_argument("--creature", default="worm", choices=CREATURES)
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated time of the gait, s")
    parser.add_argument("--tol", type=float, default=TIGHT_TOL, help="the refined implicit runs' tol, m/s")
    parser.add_argument("--friction-smoothing", type=float, default=None,
                        help="ε_v of the refined implicit runs' ground, m/s (default: the env's)")
    parser.add_argument("--barrier-distance", type=float, default=None,
                        help="d̂ of the refined implicit runs' ground, m, κ·d̂ kept (default: the env's)")
    parser.add_argument("--quick", action="store_true", help="0.1 s, two levels each")
    args = parser.parse_args(argv)
    configure_threads(args.threads)
    contact = {"friction_smoothing": args.friction_smoothing, "barrier_distance": args.barrier_distance}
    if args.quick:
        study = run(args.creature, 0.1, (1, 2), (1, 2), args.tol, **contact)
    else:
        study = run(args.creature, args.seconds, tol=args.tol, **contact)
    check(study)
    text = markdown(study)
    print(text)
    rows = [*study.implicit, study.implicit_default, *study.explicit]
    write_outputs(args.out, "bench_env_models", rows, text)
    return study


if __name__ == "__main__":
    main()
