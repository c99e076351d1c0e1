"""What the example scripts share: command line, solver choice, the stepping loop and the output files."""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor
from tqdm import tqdm

import energysim as es
from energysim.export import VTKSeries, render_gif, render_png
from energysim.fem.kinematics import deformation_gradient
from energysim.fem.materials import stable_neo_hookean_density

SOLVERS = ("newton-cg", "lbfgs", "adam")
# each of `es.INTEGRATORS`' order of accuracy in h away from contact (on a step that touches an
# obstacle TR-BDF2 takes an implicit-Euler step): what the benchmarks' convergence checks expect
# GIF players clamp very short frame delays (under 2 cs) to slow ones, so the GIF plays at most this fast.
MAX_GIF_FPS = 25.0


@dataclass(frozen=True)
class Rollout:
    """A simulated run.

    Attributes:
        times: time of each saved frame, shape `[F]`, in s.
        positions: vertex positions of each saved frame, shape `[F, n, 3]`, in m.
        velocities: vertex velocities of each saved frame, shape `[F, n, 3]`, in m/s.
        frame_steps: step index of each saved frame, shape `[F]` (0 is the initial state).
        stats: the solver's report of every step, S of them.
        step_seconds: wall time of each `es.step` call, shape `[S]`, in s.
        dt: time step h in s.
        gravity: the scene's acceleration of gravity, shape `[d]`, in m/s².
        history: per-step diagnostics, name -> shape `[S + 1, ...]`, entry k after step k (0: initial).
        vtk: the ``.pvd`` written, or None when no output folder was given.
        actions: the action at each saved frame's time, shape `[F, a]`, or None for an unactuated run.
    """

    times: Tensor
    positions: Tensor
    velocities: Tensor
    frame_steps: Tensor
    stats: tuple[es.SolverResult, ...]
    step_seconds: Tensor
    dt: float
    gravity: Tensor
    history: dict[str, Tensor]
    vtk: Path | None = None
    actions: Tensor | None = None


def make_solver(name: str, tol: float, compile: bool = False) -> es.Solver:
    """The optimizer named on the command line, stopping at velocity residual `tol` (m/s), with
    compiled objective evaluations if `compile` (see `energysim.objective.compiled`)."""
    if name == "newton-cg":
        return es.NewtonCG(tol=tol, compile=compile)
    if name == "lbfgs":
        return es.LBFGS(tol=tol, compile=compile)
    if name == "adam":
        return es.Adam(tol=tol, compile=compile)
    raise ValueError(f"solver must be one of {SOLVERS}, got {name!r}")


def make_parser(doc: str, script: str, *, seconds: float, resolution: int) -> argparse.ArgumentParser:
    """The flags every script takes; `doc` is the module docstring, `script` the default output name."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=seconds, help="simulated time in s")
    parser.add_argument("--dt", type=float, default=1 / 60, help="time step h in s")
    parser.add_argument("--solver", choices=SOLVERS, default="newton-cg")
    parser.add_argument("--tol", type=float, default=1e-5, help="velocity-residual tolerance in m/s")
    parser.add_argument("--resolution", type=int, default=resolution, help="cells along the shortest side")
    parser.add_argument("--out", type=Path, default=Path("out") / script, help="output folder")
    parser.add_argument("--frames-every", type=int, default=1, metavar="N", help="save every N-th step")
    parser.add_argument("--no-render", action="store_true", help="skip the PNG and the GIF")
    return parser


def neo_hookean(scene: es.Scene) -> es.NeoHookean:
    """The scene's (single) elasticity term."""
    terms = [term for term in scene.terms if isinstance(term, es.NeoHookean)]
    if len(terms) != 1:
        raise ValueError(f"expected one NeoHookean term in the scene, found {len(terms)}")
    return terms[0]


def gravity(scene: es.Scene) -> Tensor:
    """The scene's acceleration of gravity, shape `[d]`, in m/s² (zero without a gravity term)."""
    g = torch.zeros(scene.dim, dtype=scene.vertex_mass.dtype)
    for term in scene.terms:
        if isinstance(term, es.Gravity):
            g = g + term.acceleration
    return g


def deformation(scene: es.Scene, x: Tensor) -> tuple[Tensor, Tensor]:
    """Deformation gradients `[m, d, d]` and neo-Hookean energy densities `[m]` (J/m³) at `x` `[n, d]`."""
    term = neo_hookean(scene)
    F = deformation_gradient(x[term.element_vertices], term.rest_edge_inverse)
    return F, stable_neo_hookean_density(F, *term.lame())


def simulate(
    scene: es.Scene,
    state: Tensor,
    seconds: float,
    observe: Callable[[Tensor, Tensor], dict[str, Tensor]],
    *,
    out: Path | None = None,
    frames_every: int = 1,
    progress: bool = True,
    action: Callable[[float], Tensor] | None = None,
) -> Rollout:
    """Step `state` for `seconds` (rounded to whole steps), recording `observe(x, v)` after every step.

    Saves every `frames_every`-th state and the last one; with `out`, writes them as VTK frames
    (``velocity`` point data, ``energy_density`` cell data) and a ``frame.pvd`` into `out`, which
    lists them once the run is complete (an older series stays until then). With
    `action`, the step from t − h to t is taken with `action(t)` (t in s): implicit Euler balances
    the forces at the end of the step, so that is where the muscles' command belongs.
    """
    if frames_every < 1:
        raise ValueError(f"frames_every must be >= 1, got {frames_every}")
    steps = max(1, round(seconds / scene.dt))
    series = None if out is None else VTKSeries(out, cells=scene.mesh.elements, name="frame")
    frames: list[tuple[int, Tensor, Tensor]] = []
    frame_actions: list[Tensor] = []
    records: list[dict[str, Tensor]] = []
    stats: list[es.SolverResult] = []
    walls: list[float] = []

    def record(k: int, state: Tensor) -> None:
        x, v = (part[0] for part in scene.split_state(state))
        records.append(observe(x, v))
        if k % frames_every == 0 or k == steps:
            frames.append((k, x, v))
            if action is not None:
                frame_actions.append(action(k * scene.dt))
            if series is not None:
                _, psi = deformation(scene, x)
                series.write(k * scene.dt, x, point_data={"velocity": v}, cell_data={"energy_density": psi})

    record(0, state)
    for k in tqdm(range(1, steps + 1), desc="steps", disable=not progress, leave=False):
        start = time.perf_counter()
        result = es.step(scene, state, None if action is None else action(k * scene.dt))
        walls.append(time.perf_counter() - start)
        state = result.state
        stats.append(result.stats)
        record(k, state)
    if series is not None:
        series.commit()  # the .pvd switches to the new frames only now that all are written

    frame_steps = torch.tensor([k for k, _, _ in frames])
    return Rollout(
        times=frame_steps.to(torch.float64) * scene.dt,
        positions=torch.stack([x for _, x, _ in frames]),
        velocities=torch.stack([v for _, _, v in frames]),
        frame_steps=frame_steps,
        stats=tuple(stats),
        step_seconds=torch.tensor(walls, dtype=torch.float64),
        dt=scene.dt,
        gravity=gravity(scene),
        history={name: torch.stack([r[name] for r in records]) for name in records[0]},
        vtk=None if series is None else series.pvd_path,
        actions=torch.stack(frame_actions) if frame_actions else None,
    )


def render(rollout: Rollout, scene: es.Scene, out: Path, name: str) -> tuple[Path, Path]:
    """A PNG of the last frame and a GIF of all saved frames (real time, at most `MAX_GIF_FPS`), by speed."""
    faces = scene.mesh.surface()
    speeds = rollout.velocities.norm(dim=-1)
    png = render_png(
        out / f"{name}.png",
        rollout.positions[-1],
        faces,
        scalars=speeds[-1],
        scalar_name="speed (m/s)",
        title=f"{name}, t = {float(rollout.times[-1]):.2f} s",
    )
    shown, fps = gif_frames(rollout.frame_steps, rollout.dt)
    positions = list(rollout.positions[shown])
    gif = render_gif(out / f"{name}.gif", positions, faces, scalars=speeds[shown], fps=fps)
    return png, gif


def gif_frames(frame_steps: Tensor, dt: float) -> tuple[list[int], float]:
    """Which saved frames (steps `frame_steps` `[F]`, evenly spaced, of `dt` s) a real-time GIF shows,
    and its frame rate in 1/s: every frame up to `MAX_GIF_FPS`, else every k-th one; always the last,
    so the animation ends where the PNG does."""
    frames = len(frame_steps)
    spacing = int(frame_steps[1] - frame_steps[0]) if frames > 1 else 1
    frame_rate = 1.0 / (dt * spacing)
    stride = max(1, math.ceil(frame_rate / MAX_GIF_FPS))
    return sorted({*range(0, frames, stride), frames - 1}), frame_rate / stride


def summary(name: str, scene: es.Scene, rollout: Rollout, figures: dict[str, float]) -> str:
    """A few lines: size, speed, solver effort, and the check's figures."""
    iterations = [s.iterations for s in rollout.stats]
    unconverged = sum(not s.converged for s in rollout.stats)
    solver = rollout.stats[0]
    lines = [
        f"{name}: {len(rollout.stats)} steps of h = {rollout.dt:.4g} s, {scene.num_vertices} vertices, "
        f"{scene.mesh.num_elements} {'tets' if scene.dim == 3 else 'triangles'}, "
        f"{solver.solver} (tol {solver.tol:.0e} m/s), {scene.integrator}",
        f"  median {1e3 * statistics.median(rollout.step_seconds.tolist()):.1f} ms per step; "
        f"iterations per step mean {statistics.fmean(iterations):.2f}, max {max(iterations)}; "
        f"final residual {rollout.stats[-1].residual:.2e} m/s; "
        f"{unconverged} steps not converged",
    ]
    lines += [f"  {key}: {value:.6g}" for key, value in figures.items()]
    return "\n".join(lines)


def script_main(argv: list[str] | None, script: ModuleType, *, seconds: float, resolution: int) -> int:
    """The command line every scene script shares: build, run, write, render, summarise, check.

    `script` is the scene script's module: its docstring, ``NAME``, ``build_scene(resolution, dt, solver,
    tol)``, ``run(scene, seconds, out, frames_every=...)``, ``measure(rollout)`` and ``check(rollout)``.
    Returns 0 when the run passes `check`, 1 otherwise (the failed predicate is printed).
    """
    name = script.NAME
    args = make_parser(script.__doc__, name, seconds=seconds, resolution=resolution).parse_args(argv)
    scene = script.build_scene(args.resolution, args.dt, args.solver, args.tol)
    rollout = script.run(scene, args.seconds, args.out, frames_every=args.frames_every)
    outputs = [rollout.vtk]
    if not args.no_render:
        outputs += render(rollout, scene, args.out, name)
    print(summary(name, scene, rollout, script.measure(rollout)))
    print("  wrote " + ", ".join(str(p) for p in outputs))
    try:
        script.check(rollout)
    except AssertionError as err:
        print(f"CHECK FAILED: {err}", file=sys.stderr)
        return 1
    print("  check passed")
    return 0
