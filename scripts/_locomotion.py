"""What the walking scripts share: a creature on frictional ground, an open-loop gait, metrics and a check.

`walk.py` holds one `WalkSpec` per creature (its defaults and how its gait's phases follow from one
phase lag) and calls `script_main`. The scene: the shipped creature (`energysim.creatures`), stable
neo-Hookean body, fibre muscles, gravity and an IPC ground at y = 0 with lagged Coulomb friction,
stepped by implicit Euler. The creature starts at rest, lifted by half the ground's barrier distance so it
touches the ground without being inside it.

The gait is open loop: actuator j gets a_j(t) = r(t) A sin(2π f t + φ_j), eased in by r over the first
period (see `Gait`), and the step that ends at t uses a(t). Forward is +x. The figures (`measure`), with
X_k the x of the centre of mass after step k:
- distance: X_T − X_0, in m and in body lengths (the rest mesh's extent along x);
- speed: distance / T;
- backslide: max_k (max_{j≤k} X_j − X_k), the farthest the centre of mass ever fell back behind the
  farthest point it had reached (the start counts as reached). A gait sways the body back and forth
  within each cycle; "sliding backwards" is a backslide beyond a small tolerance, so a creature
  that loses ground it had made, or starts by going backwards, fails;
- min height: the lowest vertex over all steps (the ground is y = 0; the barrier keeps it > 0).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from _common import SOLVERS, Rollout, gif_frames, make_solver, simulate
from torch import Tensor

import energysim as es
from energysim.cpu import configure as configure_cpu
from energysim.creatures import CREATURES, Creature, load_creature, resting_state, scene_ground
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.export import element_activation, export_rollout, render_gif, render_mp4, render_png


@dataclass(frozen=True)
class Gait:
    """An open-loop gait: actuator j gets a_j(t) = r(t) · A · sin(2π f t + φ_j).

    The ramp r(t) = sin²(π t / 2T) for t < T (then 1) eases the muscles in over T = `ramp` s: switched
    on at full strength, muscles whose phase starts near ±π/2 would jolt the body in the first step.

    Attributes:
        frequency: f in Hz, > 0.
        amplitude: A, dimensionless, in [0, 1] (the muscles clamp activations to [−1, 1]).
        phases: φ_j in rad, one per actuator.
        ramp: T in s, ≥ 0; 0: full strength from the start.
    """

    frequency: float
    amplitude: float
    phases: tuple[float, ...]
    ramp: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.frequency) and self.frequency > 0):
            raise ValueError(f"frequency must be finite and > 0 Hz, got {self.frequency}")
        if not 0 <= self.amplitude <= 1:
            raise ValueError(f"amplitude must lie in [0, 1], got {self.amplitude}")
        if not self.phases or not all(math.isfinite(p) for p in self.phases):
            raise ValueError(f"phases must be finite, one per actuator, got {self.phases}")
        if not (math.isfinite(self.ramp) and self.ramp >= 0):
            raise ValueError(f"ramp must be finite and >= 0 s, got {self.ramp}")

    def action(self, time: float) -> Tensor:
        """The action at time `time` (s), shape `[a]`, float64."""
        phases = torch.tensor(self.phases, dtype=torch.float64)
        envelope = math.sin(0.5 * math.pi * min(time / self.ramp, 1.0)) ** 2 if self.ramp > 0 else 1.0
        return envelope * self.amplitude * torch.sin(2 * math.pi * self.frequency * time + phases)


@dataclass(frozen=True)
class WalkSpec:
    """One creature's walking scene: its defaults and what its check asks for.

    Attributes:
        creature: a name in `energysim.creatures.CREATURES`.
        phases: φ of every actuator, in rad, from one phase lag in rad (what the lag means is the
            creature's: between segments of a wave, between front and back legs, ...).
        phase_lag: the default lag, rad; `phases(phase_lag)` is the creature's suggested gait.
        seconds: default simulated time, s.
        dt: default time step h, s.
        friction: default Coulomb coefficient μ of the ground.
        min_speed: the forward speed the check asks for, in body lengths per second.
        max_backslide: the backslide the check tolerates, in body lengths.
        tol: default velocity-residual tolerance of the solver, m/s. At 1e-3 the worm's 5 s walk
            ends 0.24 µm from the same walk at 1e-5 (other creatures: 0.2 µm to 38 µm), while the
            time step's own error is 12.6 mm there (its centre of mass at h = 1/60 against 1/240):
            a tighter tolerance buys nothing visible, at half a Newton iteration per step.
        ramp_periods: the gait's ramp-in, in gait periods (see `Gait`).
    """

    creature: str
    phases: Callable[[float], tuple[float, ...]]
    phase_lag: float
    seconds: float = 5.0
    dt: float = 1 / 60
    friction: float = 0.8
    min_speed: float = 0.0
    max_backslide: float = 0.05
    tol: float = 1e-3
    ramp_periods: float = 1.0


def bending_wave(segments: int) -> Callable[[float], tuple[float, ...]]:
    """Phases of a wave along `segments` segments with a bottom and a top muscle each (worm, crawler):
    segment s's bottom muscle at s·lag, its top muscle opposite; lag < 0 runs the wave forward."""

    def phases(lag: float) -> tuple[float, ...]:
        return tuple(lag * s + math.pi * layer for s in range(segments) for layer in (0, 1))

    return phases


def default_gait(spec: WalkSpec, creature: Creature) -> Gait:
    """The creature's suggested frequency and amplitude with the spec's phases and ramp."""
    frequency = creature.gait_frequency
    return Gait(
        frequency, creature.gait_amplitude, tuple(spec.phases(spec.phase_lag)), spec.ramp_periods / frequency
    )


def refined_creature(name: str, refine: int = 1) -> Creature:
    """The shipped creature, or with `refine` > 1 its voxel design with every voxel split `refine`
    times along each axis (`refine`^d as many elements; same shape, muscles and gait)."""
    if refine == 1:
        return load_creature(name)
    if refine < 1:
        raise ValueError(f"refine must be an integer >= 1, got {refine}")
    import make_creatures  # a sibling script; only this path needs it

    design = make_creatures.DESIGNS[name]()
    axes = range(design.occupancy.ndim)

    def split(grid: np.ndarray) -> np.ndarray:
        for axis in axes:
            grid = np.repeat(grid, refine, axis=axis)
        return grid

    finer = replace(
        design,
        occupancy=split(design.occupancy),
        actuator=split(design.actuator),
        fibre=split(design.fibre),
        voxel_size=design.voxel_size / refine,
    )
    with tempfile.TemporaryDirectory() as folder:
        make_creatures.write_creature(make_creatures.build_creature(finer), Path(folder))
        return load_creature(name, folder)


def build_scene(
    creature: Creature,
    dt: float = 1 / 60,
    friction: float = 0.8,
    solver: str = "newton-cg",
    tol: float = 1e-3,
    compile: bool = False,
) -> es.Scene:
    """The creature (suggested material and muscles) under gravity on a ground at y = 0 with friction μ.

    Args:
        creature: from `load_creature` or `refined_creature`.
        dt: time step h in s.
        friction: Coulomb coefficient μ ≥ 0.
        solver: "newton-cg", "lbfgs" or "adam".
        tol: the solver's velocity-residual tolerance in m/s.
        compile: the solver evaluates the objective through compiled functions.
    """
    return creature.scene(dt, friction, make_solver(solver, tol, compile))


def ground(scene: es.Scene) -> es.Ground:
    """The scene's ground term."""
    return scene_ground(scene)


def initial_state(scene: es.Scene) -> Tensor:
    """At rest in the rest shape, lifted by half the ground's barrier distance d̂ (in contact, outside)."""
    return resting_state(scene)


def centre_of_mass(scene: es.Scene, x: Tensor) -> Tensor:
    """Mass-weighted mean of positions `x` `[n, d]`, shape `[d]`, in m."""
    mass = scene.vertex_mass
    return (mass[:, None] * x).sum(dim=0) / mass.sum()


def run(
    scene: es.Scene,
    gait: Gait,
    seconds: float,
    *,
    frames_every: int = 1,
    progress: bool = True,
) -> Rollout:
    """Walk for `seconds` (whole steps) from `initial_state`; `history` holds per step ``com`` `[d]` (m),
    ``min_height`` (lowest vertex, m) and ``finite`` (every position and velocity finite)."""
    if len(gait.phases) != _num_actuators(scene):
        raise ValueError(f"the gait has {len(gait.phases)} phases; the muscles have {_num_actuators(scene)}")

    def observe(x: Tensor, v: Tensor) -> dict[str, Tensor]:
        return {
            "com": centre_of_mass(scene, x),
            "min_height": x[:, 1].min(),
            "finite": torch.isfinite(x).all() & torch.isfinite(v).all(),
        }

    return simulate(
        scene,
        initial_state(scene),
        seconds,
        observe,
        frames_every=frames_every,
        progress=progress,
        action=gait.action,
    )


def _num_actuators(scene: es.Scene) -> int:
    return max(term.num_actuators for term in scene.terms if isinstance(term, FibreMuscles))


def body_length(scene: es.Scene) -> float:
    """Extent of the rest mesh along x (forward), in m."""
    x = scene.rest_positions[:, 0]
    return float(x.max() - x.min())


def measure(rollout: Rollout, length: float) -> dict[str, float]:
    """The figures `check` judges, by name (units in the names); `length` is the body length in m."""
    com = rollout.history["com"]
    forward = com[:, 0] - com[0, 0]
    seconds = len(rollout.stats) * rollout.dt
    backslide = (forward.cummax(dim=0).values.clamp_min(0.0) - forward).max()
    sideways = (com[-1, 2] - com[0, 2]).abs() if com.shape[1] == 3 else torch.zeros(())
    return {
        "distance (m)": float(forward[-1]),
        "distance (body lengths)": float(forward[-1] / length),
        "speed (m/s)": float(forward[-1] / seconds),
        "speed (body lengths/s)": float(forward[-1] / length / seconds),
        "backslide (m)": float(backslide),
        "backslide (body lengths)": float(backslide / length),
        "sideways drift (m)": float(sideways),
        "min height (m)": float(rollout.history["min_height"].min()),
        "non-finite steps": float((~rollout.history["finite"]).sum()),
        "unconverged steps": float(sum(not s.converged for s in rollout.stats)),
        "seconds": seconds,
    }


def check(
    rollout: Rollout, length: float, min_speed: float, max_backslide: float, settle: float = 0.0
) -> None:
    """Raise AssertionError, naming the figure, unless the creature walked forward without sliding back.

    Args:
        rollout: from `run`.
        length: body length in m.
        min_speed: the forward distance must be positive and at least `min_speed` body lengths per second
            of the run after the first `settle` s.
        max_backslide: the largest backslide allowed, in body lengths (see the module docstring).
        settle: s not held to `min_speed`: the gait's ramp-in.
    """
    f = measure(rollout, length)
    assert f["non-finite steps"] == 0, f"{f['non-finite steps']:.0f} steps have NaN or inf"
    assert f["min height (m)"] >= 0.0, f"a vertex went {-f['min height (m)']:.3g} m into the ground"
    needed = min_speed * max(f["seconds"] - settle, 0.0)
    assert f["distance (m)"] > 0 and f["distance (body lengths)"] >= needed, (
        f"went {f['distance (m)']:+.4f} m = {f['distance (body lengths)']:+.3f} body lengths in "
        f"{f['seconds']:.3g} s; the check asks for more than 0 and {needed:.3f} ({min_speed:g} body "
        f"lengths/s after the first {settle:.3g} s)"
    )
    assert f["backslide (body lengths)"] <= max_backslide, (
        f"slid back {f['backslide (m)']:.4f} m = {f['backslide (body lengths)']:.3f} body lengths behind "
        f"the farthest point reached; at most {max_backslide:g} allowed"
    )


def vertex_activation(scene: es.Scene, actions: Tensor) -> Tensor:
    """Per-vertex mean of the activations of the elements around each vertex, `[F, n]`, for colouring."""
    activation = element_activation(scene, actions)
    elements = scene.mesh.elements
    corners = elements.shape[1]
    total = activation.new_zeros(actions.shape[0], scene.num_vertices)
    total = total.index_add(1, elements.reshape(-1), activation.repeat_interleave(corners, dim=1))
    count = torch.bincount(elements.reshape(-1), minlength=scene.num_vertices).to(total)
    return total / count


def write_outputs(
    rollout: Rollout,
    scene: es.Scene,
    out: Path,
    name: str,
    *,
    render: bool = True,
    window_size: tuple[int, int] = (960, 540),
) -> list[Path]:
    """VTK frames + ``frame.pvd`` (positions, velocity, strain energy density, activation) in `out`;
    with `render`, ``NAME.png`` (last frame), ``NAME.gif`` and, if an encoder is installed, ``NAME.mp4``,
    coloured by muscle activation. Returns the paths written."""
    frames = rollout.positions.shape[0]
    states = torch.cat([rollout.positions.reshape(frames, -1), rollout.velocities.reshape(frames, -1)], 1)
    written = [export_rollout(scene, states, out, actions=rollout.actions, times=rollout.times)]
    if not render:
        return written
    faces = scene.mesh.surface()
    colour = vertex_activation(scene, rollout.actions)
    written.append(
        render_png(
            out / f"{name}.png",
            rollout.positions[-1],
            faces,
            scalars=colour[-1],
            scalar_name="activation",
            window_size=window_size,
            ground_height=0.0,
            title=f"{name}, t = {float(rollout.times[-1]):.2f} s",
        )
    )
    shown, fps = gif_frames(rollout.frame_steps, rollout.dt)
    animation = dict(scalars=colour[shown], fps=fps, window_size=window_size, ground_height=0.0)
    positions = list(rollout.positions[shown])
    written.append(render_gif(out / f"{name}.gif", positions, faces, **animation))
    movie = render_mp4(out / f"{name}.mp4", positions, faces, **animation)
    if movie is not None:
        written.append(movie)
    return written


# With --compile, the mean step time is also given without this much simulated time at the start,
# whose steps include the compilation.
COMPILED_WARMUP = 0.5


def summary(name: str, scene: es.Scene, rollout: Rollout, figures: dict[str, float]) -> str:
    """Size, solver effort, timing and the figures, a few lines."""
    iterations = [s.iterations for s in rollout.stats]
    step_seconds = rollout.step_seconds.tolist()
    mean, median = statistics.fmean(step_seconds), statistics.median(step_seconds)
    kind = "tets" if scene.dim == 3 else "triangles"
    lines = [
        f"{name}: {len(rollout.stats)} steps of h = {rollout.dt:.4g} s, {scene.num_vertices} vertices, "
        f"{scene.mesh.num_elements} {kind}, {rollout.stats[0].solver} (tol {rollout.stats[0].tol:.0e} m/s), "
        f"{scene.integrator}",
        f"  mean {1e3 * mean:.1f} ms per step (median {1e3 * median:.1f}) = "
        f"{rollout.dt / mean:.2f}x real time; "
        f"iterations per step mean {statistics.fmean(iterations):.2f}, max {max(iterations)}",
        f"  travelled {figures['distance (m)']:+.4f} m = {figures['distance (body lengths)']:+.3f} body "
        f"lengths in {figures['seconds']:.3g} s: {figures['speed (m/s)']:+.4f} m/s = "
        f"{figures['speed (body lengths/s)']:+.3f} body lengths/s",
    ]
    warmed = round(COMPILED_WARMUP / rollout.dt)
    if getattr(scene.solver, "compile", False) and len(step_seconds) > 2 * warmed:
        # the first steps compile (seconds each): the mean above counts them, this one does not
        steady = statistics.fmean(step_seconds[warmed:])
        lines.insert(
            2,
            f"  compiled: from {COMPILED_WARMUP:g} s on (compilation done) mean {1e3 * steady:.1f} ms per "
            f"step = {rollout.dt / steady:.2f}x real time",
        )
    lines += [
        f"  {key}: {value:.6g}" for key, value in figures.items() if not key.startswith(("distance", "speed"))
    ]
    return "\n".join(lines)


def make_parser(doc: str, spec: WalkSpec, creature: Creature) -> argparse.ArgumentParser:
    """The walking flags, with `spec`'s and the creature's defaults (``--creature`` is read first)."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--creature", choices=CREATURES, default=spec.creature, help="which shipped creature walks")
    add("--seconds", type=float, default=spec.seconds, help="simulated time in s")
    add("--dt", type=float, default=spec.dt, help="time step h in s")
    add("--optimizer", "--solver", dest="optimizer", choices=SOLVERS, default="newton-cg")
    add("--tol", type=float, default=spec.tol, help="velocity-residual tolerance in m/s")
    # steps that touch the ground are implicit Euler either way; TR-BDF2 helps airborne phases (the jumper)
    add(
        "--integrator",
        choices=es.IMPLICIT_INTEGRATORS,
        default="implicit_euler",
        help="time integrator, see es.step",
    )
    add("--friction", type=float, default=spec.friction, help="Coulomb coefficient of the ground")
    add("--frequency", type=float, default=creature.gait_frequency, help="gait frequency f in Hz")
    add("--amplitude", type=float, default=creature.gait_amplitude, help="gait amplitude A in [0, 1]")
    add("--phase-lag", type=float, default=spec.phase_lag, help="the gait's phase lag in rad (see above)")
    add("--ramp", type=float, default=spec.ramp_periods, help="ease the muscles in over this many periods")
    add("--refine", type=int, default=1, metavar="N", help="split each voxel N times per axis (N^d elements)")
    add("--out", type=Path, default=Path("out") / f"walk_{spec.creature}", help="output folder")
    add("--frames-every", type=int, default=1, metavar="N", help="save every N-th step")
    add("--window-size", type=int, nargs=2, default=(960, 540), metavar=("W", "H"), help="render size, px")
    add("--no-render", action="store_true", help="skip the PNG, GIF and MP4")
    add("--no-vtk", action="store_true", help="write no files at all")
    add("--quiet", action="store_true", help="no progress bar")
    # meshes this small gain nothing from intra-op threads, and on a shared machine they lose a lot
    add("--threads", type=int, default=1, help="torch intra-op threads")
    add("--compile", action="store_true", help="compile the objective's evaluations (seconds first)")
    return parser


def script_main(argv: list[str] | None, doc: str, specs: dict[str, WalkSpec], default: str) -> int:
    """Build, walk, write, render, summarise and check the creature named by ``--creature`` (`default`
    when absent; its defaults come from `specs`); returns 0 when the check passes, else 1."""
    chooser = argparse.ArgumentParser(add_help=False)
    chooser.add_argument("--creature", choices=sorted(specs), default=default)
    name = chooser.parse_known_args(argv)[0].creature  # exits with the valid names on an unknown one
    spec = specs[name]
    args = make_parser(doc, spec, load_creature(name)).parse_args(argv)
    configure_cpu(args.threads)
    creature = refined_creature(name, args.refine)
    ramp = args.ramp / args.frequency if args.frequency > 0 else 0.0  # Gait itself rejects f <= 0
    gait = Gait(args.frequency, args.amplitude, tuple(spec.phases(args.phase_lag)), ramp)
    scene = build_scene(creature, args.dt, args.friction, args.optimizer, args.tol, args.compile)
    scene.integrator = args.integrator
    rollout = run(scene, gait, args.seconds, frames_every=args.frames_every, progress=not args.quiet)
    length = body_length(scene)
    figures = measure(rollout, length)
    print(summary(name, scene, rollout, figures))
    print(
        f"  gait: f = {gait.frequency:g} Hz, A = {gait.amplitude:g}, phases (rad) "
        + ", ".join(f"{p:.3f}" for p in gait.phases)
    )
    if not args.no_vtk:
        written = write_outputs(
            rollout, scene, args.out, name, render=not args.no_render, window_size=tuple(args.window_size)
        )
        print("  wrote " + ", ".join(str(p) for p in written))
    try:
        check(rollout, length, spec.min_speed, spec.max_backslide, settle=gait.ramp)
    except AssertionError as err:
        print(f"CHECK FAILED: {err}", file=sys.stderr)
        return 1
    print("  check passed")
    return 0
