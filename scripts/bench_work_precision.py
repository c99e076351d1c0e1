"""Work-precision: wall time per simulated second against trajectory error, per optimizer, h and tolerance.

Three scenes, each simulated from the same initial state by every optimizer (Adam, L-BFGS, Newton–CG and
projected Newton, `NewtonCG(project_hessian=True)`) with every implicit integrator
(`es.IMPLICIT_INTEGRATORS`: implicit Euler, first order, one solve per step; TR-BDF2, second order,
two solves per step; Adam with implicit Euler only, as it is too slow to run twice) at every time
step h and velocity-residual tolerance of a grid, float64:
- cantilever: `cantilever.build_scene` (1 × 0.2 × 0.2 m, E = 100 kPa, ν = 0.3, 240 tets), released
  from rest, swings down under gravity;
- drop: `bench_step.build_landing_scene` (a 0.2 m cube, 384 tets) on `es.Ground(0.0, friction=0.5)`,
  falling at 1 m/s (`bench_step.landing_start`, placed for h = 1/60 s: it lands at t ≈ 0.06 s) and
  thrown sideways at `SLIDE_SPEED`, so that it lands, slides and is stopped by friction;
- quadruped: the shipped quadruped (888 tets) walking its open-loop gait from rest
  (`_locomotion.build_scene`, `default_gait`, `initial_state`; `walk.SPECS["quadruped"]`).

Errors compare vertex positions at the times every run shares (multiples of the least common multiple
of the time steps, 1/12 s for the default grid; nothing is interpolated):
- error = RMS over those times (t > 0) and all vertices of |x − x_ref|, divided by the body size (the
  rest mesh's bounding-box diagonal); final error = the same at the last time only. x_ref: Newton–CG at
  tol `--reference-tol` and h = `--reference-dt` with TR-BDF2 (`--reference-integrator`). Its
  convergence is checked by a second run at half that step: their difference estimates the
  reference's own error (3/4 of it for a second-order step, 1/2 for a first-order one), and it should
  lie well (~10×) below the smallest error reported. TR-BDF2 rather than implicit Euler: on the
  cantilever (0.5 s) TR-BDF2's time-discretisation error is 1.5e-4 of the body size at h = 1/120 s
  and 9.8e-6 at 1/480 s, while implicit Euler at h = 1/3840 s is itself off by 2.2e-4 (its distance
  from TR-BDF2 at that h, and twice its own h-halving difference, 1.1e-4): an implicit-Euler x_ref
  could not measure TR-BDF2's runs at all. TR-BDF2's h-halving difference there is 1.2e-7, for about
  twice the cost (two solves per step). On the drop and the quadruped, TR-BDF2 takes an implicit-Euler
  step wherever the body touches the ground (the quadruped: every step, so the two references are the
  same trajectory), and x_ref is about as accurate as implicit Euler's there, at about the same cost.
- solver error: the same measures against Newton–CG at the reference tolerance with the run's own h
  and integrator (the "tight" run), so only the optimizer's early stop is measured, not the time
  discretisation. The tight runs' own error against x_ref is the time-discretisation error; its slope
  in log h is the observed order of convergence (implicit Euler: 1; TR-BDF2: 2 away from contact).

Adam and L-BFGS stop after `--max-iter` iterations per solve (Newton: 100); a run whose CPU time
would exceed `--budget` seconds is stopped and reported "over budget" with its projected cost. After a
run that went over budget or left half its steps unconverged, the tighter tolerances of the same
optimizer and h are "skipped": they only add iterations. Every run is one sample, timed in wall and in
CPU time (the same with one thread on an idle machine; CPU time is the steadier on a shared one).
Failed runs (not converged, diverged, over budget, skipped) stay in every table.

Run:  python scripts/bench_work_precision.py                  # full: about 70 min of CPU, one thread
      python scripts/bench_work_precision.py --quick --out /tmp/wp_quick
      python scripts/bench_work_precision.py --from-csv docs/benchmarks/work_precision.csv  # tables only
      python scripts/bench_work_precision.py --scenes cantilever --optimizers newton-cg lbfgs \\
          --integrators tr_bdf2 --dts 1/60 1/120 --tols 1e-3 1e-6 --seconds 0.25
Writes: <out>/work_precision.csv (every run), work_precision.md (tables), work_precision.png (error
against wall time per simulated second, one panel per scene) and work_precision_errors.png (the two
error sources: time discretisation against h per integrator, solver error against tolerance).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields, replace
from fractions import Fraction
from functools import lru_cache
from pathlib import Path

import _locomotion
import bench_step
import cantilever
import torch
from _bench import (
    INTEGRATOR_ORDER,
    configure_threads,
    finite,
    loglog_slope,
    pyplot,
    save_figure,
    step_through,
    walk_spec,
    write_csv,
)
from _bench import fixed as _f
from _bench import sci as _e
from _bench import write_outputs as write_files
from torch import Tensor
from tqdm import tqdm

import energysim as es
from energysim.creatures import Creature, load_creature
from energysim.objective.objective import Objective

DEFAULT_DTS = ("1/24", "1/60", "1/120", "1/240", "1/480")
DEFAULT_TOLS = (1e-2, 1e-3, 1e-4, 1e-6)  # m/s
QUICK_DTS = ("1/60", "1/120")
QUICK_TOLS = (1e-2, 1e-4)
# the headline tables: the fastest run with error at most this fraction of the body size (1e-2: about what
# the eye sees; 1e-3: what a quantitative comparison asks for)
ACCURACIES = (1e-3, 1e-2)
SLIDE_SPEED = 0.5  # m/s along +x: the dropped cube slides on landing, so friction does work
LANDING_CELLS = {"full": (4, 4, 4), "quick": (2, 2, 2)}
CANTILEVER_RESOLUTION = {"full": 2, "quick": 1}  # cells across the beam, 5× as many along it
SECONDS = {
    "full": {"cantilever": 0.5, "drop": 0.5, "quadruped": 0.5},
    "quick": {"cantilever": 0.25, "drop": 0.25, "quadruped": 1 / 12},
}


@dataclass(frozen=True)
class Setup:
    """A scene ready to run: the model, its initial state, and the action at time t (None: unactuated)."""

    scene: es.Scene
    state: Tensor
    action: Callable[[float], Tensor] | None


def build_cantilever(size: str) -> Setup:
    """The cantilever released from rest in its rest shape."""
    scene = cantilever.build_scene(resolution=CANTILEVER_RESOLUTION[size])
    return Setup(scene, scene.initial_state(), None)


def build_drop(size: str) -> Setup:
    """The cube above the frictional ground, falling at 1 m/s and moving sideways at `SLIDE_SPEED`."""
    scene = bench_step.build_landing_scene(LANDING_CELLS[size], youngs_modulus=1e5)
    scene.dt = 1 / 60  # the start is placed for this step: the same state for every run
    x0, v0 = scene.split_state(bench_step.landing_start(scene, warmup=2))
    v0 = v0 + torch.tensor([SLIDE_SPEED, 0.0, 0.0], dtype=v0.dtype)
    return Setup(scene, scene.initial_state(x0[0], v0[0]), None)


@lru_cache(maxsize=1)
def _quadruped() -> Creature:
    return load_creature(walk_spec("quadruped").creature)


def build_quadruped(size: str) -> Setup:
    """The shipped quadruped at rest on the ground, driven by its default gait (one size only)."""
    creature = _quadruped()
    spec = walk_spec("quadruped")
    scene = _locomotion.build_scene(creature, friction=spec.friction)
    gait = _locomotion.default_gait(spec, creature)
    return Setup(scene, _locomotion.initial_state(scene), gait.action)


SCENE_NOTES = {
    "cantilever": "neo-Hookean beam (E = 100 kPa) clamped at x = 0, released from rest under gravity",
    "drop": f"cube (E = 100 kPa) landing at 1 m/s and sliding at {SLIDE_SPEED:g} m/s on ground with μ = 0.5",
    "quadruped": "shipped quadruped, open-loop gait from rest (eased in over 0.25 s), ground μ = 0.8",
}
SCENES: dict[str, Callable[[str], Setup]] = {
    "cantilever": build_cantilever,
    "drop": build_drop,
    "quadruped": build_quadruped,
}


OPTIMIZERS = ("adam", "lbfgs", "newton-cg", "projected-newton")
# Adam needs hundreds of iterations per solve: TR-BDF2's two solves per step would double the slowest
# part of the benchmark for a curve that only repeats implicit Euler's verdict on Adam
SINGLE_INTEGRATOR = {"adam": "implicit_euler"}


def integrators_for(optimizer: str, integrators: Iterable[str]) -> list[str]:
    """The integrators of `integrators` that `optimizer` runs with (Adam: implicit Euler only)."""
    only = SINGLE_INTEGRATOR.get(optimizer)
    return [i for i in integrators if only is None or i == only]


def make_optimizer(name: str, tol: float, max_iter: int) -> es.Solver:
    """Optimizer `name` stopping at velocity residual `tol` (m/s); Adam and L-BFGS after `max_iter`
    iterations per step (Newton's default cap, 100, is far above what it needs)."""
    if name == "adam":
        return es.Adam(tol=tol, max_iter=max_iter, lr=1e-4)
    if name == "lbfgs":
        return es.LBFGS(tol=tol, max_iter=max_iter)
    if name == "newton-cg":
        return es.NewtonCG(tol=tol)
    if name == "projected-newton":
        return es.NewtonCG(tol=tol, project_hessian=True)
    raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {name!r}")


class OverBudgetError(Exception):
    """A run stopped because its CPU time would exceed its budget."""


class BudgetedSolver:
    """Delegates every step's solves to `solver`, keeps each report, and stops the run (`OverBudgetError`)
    once its CPU time exceeds `budget_s`, or, after three steps, once the projection to all `steps`
    exceeds three times `budget_s` (so that a hopeless run costs a few steps, not the whole budget).

    A TR-BDF2 step solves twice (three times when it touched an obstacle and is redone by implicit
    Euler), so steps are counted by `observe`, which the stepping loop calls after every step, not
    by solves. CPU time, not wall time: on a shared machine the same run must meet the same fate."""

    def __init__(self, solver: es.Solver, budget_s: float, steps: int) -> None:
        self.solver = solver
        self.tol, self.max_iter, self.strict, self.compile, self.name = (
            solver.tol,
            solver.max_iter,
            solver.strict,
            solver.compile,
            solver.name,
        )
        self.budget_s, self.steps = budget_s, steps
        self.results: list[es.SolverResult] = []
        self.boundaries: list[int] = []  # len(results) after each observed state, the initial one first
        self.started = time.process_time()

    def observe(self) -> None:
        """Mark the end of a step (the first call: the initial state)."""
        self.boundaries.append(len(self.results))

    def step_reports(self) -> list[list[es.SolverResult]]:
        """The solves of each completed step (a stopped step's partial solves are left out)."""
        edges = self.boundaries
        return [self.results[a:b] for a, b in zip(edges, edges[1:], strict=False)]

    def prepare(self, objective: Objective) -> Objective:
        """The wrapped solver's `prepare`."""
        return self.solver.prepare(objective)

    def minimize(self, objective: Objective, x0: Tensor) -> es.SolverResult:
        """The wrapped solver's `minimize`, after the budget check."""
        elapsed = time.process_time() - self.started
        done = max(len(self.boundaries) - 1, 0)
        projected = elapsed / done * self.steps if done else 0.0
        if elapsed > self.budget_s or (done >= 3 and projected > 3 * self.budget_s):
            raise OverBudgetError(
                f"stopped after {done} steps, {elapsed:.1f} s CPU; projected {projected:.1f} s"
            )
        result = self.solver.minimize(objective, x0)
        self.results.append(result)
        return result


@dataclass(frozen=True)
class Run:
    """One simulated trajectory: its setting, its cost and its errors.

    Attributes:
        scene: scene name.
        role: "reference" (x_ref), "reference-check" (x_ref's h halved), "tight" (Newton–CG at the
            reference tolerance with a sweep h and integrator: the exact discrete trajectory of that
            h and integrator) or "sweep".
        optimizer: optimizer name.
        integrator: one of `es.IMPLICIT_INTEGRATORS`: how the scene steps in time.
        dt: time step h as a fraction of a second, e.g. "1/60"; dt_s: the same in s.
        tol: velocity-residual tolerance, m/s.
        status: "ok", "unconverged" (some steps stopped at max_iter), "diverged" (a non-finite
            iterate), "over budget" (stopped, costs projected) or "skipped" (see `hopeless`).
        steps: steps of the whole run; steps_done: steps taken.
        unconverged_steps: steps with a solve that ended above `tol`.
        iterations_per_step: mean outer iterations per step taken (all its solves).
        solves_per_step: mean solves per step taken: 1 for implicit Euler; for TR-BDF2 2 on a step
            away from contact, 1 on a step that starts touching an obstacle (implicit Euler instead),
            3 on one whose TR-BDF2 stages touched (redone by implicit Euler).
        max_residual: largest final velocity residual of a solve, m/s.
        wall_s: wall time of the steps taken (the `es.step` calls), s; of the whole attempt if it failed.
        wall_per_sim_s: wall s per simulated s; for an over-budget run, projected to the whole run.
        cpu_s, cpu_per_sim_s: the same in CPU time of the process (the whole run): steadier than wall
            time on a shared machine, and equal to it with one thread on an idle one.
        error: RMS over shared times and vertices of |x − x_ref| / body size.
        final_error: RMS over vertices at the last time of |x − x_ref| / body size.
        solver_error, solver_final_error: the same against the tight run with this h.
        body_size_m: the rest mesh's bounding-box diagonal, m.
        elements: tets in the mesh.
    """

    scene: str
    role: str
    optimizer: str
    integrator: str
    dt: str
    dt_s: float
    tol: float
    status: str
    steps: int
    steps_done: int
    unconverged_steps: int
    iterations_per_step: float
    solves_per_step: float
    max_residual: float
    wall_s: float
    wall_per_sim_s: float
    cpu_s: float
    cpu_per_sim_s: float
    error: float
    final_error: float
    solver_error: float
    solver_final_error: float
    body_size_m: float
    elements: int


@dataclass(frozen=True)
class Trajectory:
    """What a run produced: its report and the positions at the shared times (None if it failed)."""

    run: Run
    samples: Tensor | None  # [J + 1, n, d], m, at t = j · spacing, j = 0..J


def parse_dt(text: str) -> Fraction:
    """A time step from the command line, as a fraction of a second ("1/60" or "0.01")."""
    value = Fraction(text).limit_denominator(10**6)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"time steps must be > 0 s, got {text}")
    return value


def fraction_label(value: Fraction) -> str:
    """A time as written on the command line: "1/60", "1/2", "1"."""
    return str(value)


def common_multiple(steps: Iterable[Fraction]) -> Fraction:
    """The least common multiple of time steps: the spacing of the times every run reaches."""
    numerator, denominator = 1, 0
    for step in steps:
        numerator = math.lcm(numerator, step.numerator)
        denominator = math.gcd(denominator, step.denominator)
    return Fraction(numerator, denominator)


def body_size(scene: es.Scene) -> float:
    """The rest mesh's bounding-box diagonal, m."""
    low, high = scene.mesh.bounding_box()
    return float((high - low).norm())


def rms_error(samples: Tensor, reference: Tensor) -> tuple[float, float]:
    """RMS over times j ≥ 1 and vertices of the distance between `samples` and `reference` `[J + 1, n, d]`,
    and the same at the last time only; both in m."""
    distance_squared = (samples[1:] - reference[1:]).square().sum(dim=-1)
    return float(distance_squared.mean().sqrt()), float(distance_squared[-1].mean().sqrt())


def simulate_run(
    name: str,
    setup: Setup,
    role: str,
    optimizer: str,
    dt: Fraction,
    solver: es.Solver,
    seconds: Fraction,
    spacing: Fraction,
    budget_s: float,
    integrator: str = "implicit_euler",
) -> Trajectory:
    """Simulate `seconds` of scene `name` at time step `dt` with `integrator` and `solver`, within
    `budget_s` CPU seconds."""
    scene = setup.scene
    scene.dt = float(dt)
    scene.integrator = integrator
    steps = int(seconds / dt)
    every = int(spacing / dt)
    budgeted = BudgetedSolver(solver, budget_s, steps)
    scene.solver = budgeted
    status, samples = "ok", None
    wall_started, cpu_started = time.perf_counter(), time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", es.ConvergenceWarning)  # counted from the reports instead
            rollout = step_through(
                scene, setup.state, steps, every=every, action=setup.action, after_step=budgeted.observe
            )
        samples = rollout.positions[rollout.frame_steps % every == 0]
        if not torch.isfinite(samples).all():
            status, samples = "diverged", None
    except OverBudgetError:
        status = "over budget"
    except es.ConvergenceError:
        status = "diverged"
    wall = time.perf_counter() - wall_started
    cpu = time.process_time() - cpu_started
    if samples is not None:
        wall = float(rollout.step_seconds.sum())  # the steps alone
    reports = budgeted.step_reports()
    done = len(reports)
    unconverged = sum(not all(r.converged for r in solves) for solves in reports)
    if status == "ok" and unconverged:
        status = "unconverged"
    # an over-budget run's cost projected to all its steps; a diverged run has no cost to compare
    scale = math.nan if status == "diverged" or not done else steps / done
    run = Run(
        scene=name,
        role=role,
        optimizer=optimizer,
        integrator=integrator,
        dt=fraction_label(dt),
        dt_s=float(dt),
        tol=solver.tol,
        status=status,
        steps=steps,
        steps_done=done,
        unconverged_steps=unconverged,
        iterations_per_step=sum(r.iterations for solves in reports for r in solves) / done
        if done
        else math.nan,
        solves_per_step=sum(len(solves) for solves in reports) / done if done else math.nan,
        max_residual=max((r.residual for solves in reports for r in solves), default=math.nan),
        wall_s=wall,
        wall_per_sim_s=wall * scale / float(seconds),
        cpu_s=cpu,
        cpu_per_sim_s=cpu * scale / float(seconds),
        error=math.nan,
        final_error=math.nan,
        solver_error=math.nan,
        solver_final_error=math.nan,
        body_size_m=body_size(scene),
        elements=scene.mesh.num_elements,
    )
    return Trajectory(run, samples)


def skipped(
    name: str, setup: Setup, optimizer: str, integrator: str, dt: Fraction, tol: float, seconds: Fraction
) -> Run:
    """The report of a run not taken, because a looser tolerance of it was `hopeless`."""
    measured = {f.name: math.nan for f in fields(Run) if f.type == "float"}
    return Run(
        **measured,
        scene=name,
        role="sweep",
        optimizer=optimizer,
        integrator=integrator,
        dt=fraction_label(dt),
        dt_s=float(dt),
        tol=tol,
        status="skipped",
        steps=int(seconds / dt),
        steps_done=0,
        unconverged_steps=0,
        body_size_m=body_size(setup.scene),
        elements=setup.scene.mesh.num_elements,
    )


def with_errors(trajectory: Trajectory, reference: Tensor | None, tight: Tensor | None) -> Run:
    """`trajectory`'s report with its errors against x_ref and against the tight run of its h."""
    run, samples = trajectory.run, trajectory.samples
    if samples is None:
        return run
    errors: dict[str, float] = {}
    if reference is not None:
        error, final = rms_error(samples, reference)
        errors.update(error=error / run.body_size_m, final_error=final / run.body_size_m)
    if tight is not None:
        error, final = rms_error(samples, tight)
        errors.update(solver_error=error / run.body_size_m, solver_final_error=final / run.body_size_m)
    return replace(run, **errors)


def scene_plan(args: argparse.Namespace, seconds: Fraction) -> list[tuple[str, str, str, Fraction, float]]:
    """(role, optimizer, integrator, h, tol) of every run of one scene, in order: the references first,
    then the tight run of each integrator and h, then the sweep, each optimizer, integrator and h from
    the loosest tolerance to the tightest."""
    reference = args.reference_integrator
    plan = [
        ("reference", "newton-cg", reference, args.reference_dt, args.reference_tol),
        ("reference-check", "newton-cg", reference, args.reference_dt / 2, args.reference_tol),
    ]
    plan += [
        ("tight", "newton-cg", integrator, dt, args.reference_tol)
        for integrator in args.integrators
        for dt in args.dts
    ]
    for optimizer in args.optimizers:
        for integrator in integrators_for(optimizer, args.integrators):
            for dt in args.dts:
                plan += [("sweep", optimizer, integrator, dt, tol) for tol in sorted(args.tols, reverse=True)]
    return plan


def hopeless(run: Run) -> bool:
    """Whether a tighter tolerance of `run`'s optimizer and h can only fail too: `run` went over budget,
    or at least half its steps stopped at max_iter (a tighter tolerance only adds iterations; Adam's and
    L-BFGS's iterates do not depend on it)."""
    return run.status == "over budget" or (run.steps_done > 0 and 2 * run.unconverged_steps >= run.steps_done)


def run_scene(name: str, seconds: Fraction, args: argparse.Namespace, progress: tqdm) -> list[Run]:
    """Every run of scene `name`, with errors; rows in the order of `scene_plan`."""
    setup = SCENES[name](args.size)
    trajectories: list[Trajectory] = []
    given_up: set[tuple[str, str, Fraction]] = set()
    for role, optimizer, integrator, dt, tol in scene_plan(args, seconds):
        steps = int(seconds / dt)
        progress.set_postfix_str(f"{name} {role} {optimizer} {integrator} h={fraction_label(dt)} tol={tol:g}")
        if role == "sweep" and (optimizer, integrator, dt) in given_up:
            run = skipped(name, setup, optimizer, integrator, dt, tol, seconds)
            trajectories.append(Trajectory(run, None))
        else:
            budget = args.budget if role == "sweep" else math.inf
            solver = make_optimizer(optimizer, tol, args.max_iter)
            trajectory = simulate_run(
                name, setup, role, optimizer, dt, solver, seconds, args.spacing, budget, integrator
            )
            trajectories.append(trajectory)
            if role == "sweep" and hopeless(trajectory.run):
                given_up.add((optimizer, integrator, dt))
            if role == "reference" and trajectory.samples is None:
                raise RuntimeError(f"{name}: the reference run failed ({trajectory.run.status})")
        progress.update(steps)
        last = trajectories[-1].run
        progress.write(
            f"{name:10s} {role:15s} {optimizer:16s} {integrator:14s} h={last.dt:7s} tol={tol:7.0e} "
            f"{last.status:12s} "
            f"wall {last.wall_per_sim_s:8.2f} s/s  CPU {last.cpu_per_sim_s:8.2f} s/s  "
            f"iterations/step {last.iterations_per_step:7.1f}"
        )
    reference = trajectories[0].samples
    tight = {(t.run.integrator, t.run.dt_s): t.samples for t in trajectories if t.run.role == "tight"}
    return [
        with_errors(
            t,
            reference,
            tight.get((t.run.integrator, t.run.dt_s)) if t.run.role in ("sweep", "tight") else None,
        )
        for t in trajectories
    ]


# --- analysis ---------------------------------------------------------------------------------------


def observed_order(runs: list[Run]) -> float:
    """Least-squares slope of log(error) against log(h) over `runs` with a positive finite error."""
    return loglog_slope([r.dt_s for r in runs], [r.error for r in runs])


def time_series(rows: list[Run], scene: str, integrator: str = "implicit_euler") -> list[Run]:
    """The tight runs of `scene` with `integrator`, largest h first: their error is the
    time-discretisation error."""
    return sorted(
        (r for r in rows if r.scene == scene and r.role == "tight" and r.integrator == integrator),
        key=lambda r: -r.dt_s,
    )


def integrators_in(rows: list[Run]) -> list[str]:
    """The integrators of the tight runs, in the order they ran."""
    return list(dict.fromkeys(r.integrator for r in rows if r.role == "tight"))


def sweep_pairs(rows: list[Run]) -> list[tuple[str, str]]:
    """The (optimizer, integrator) pairs of the sweep, in the order they ran."""
    return list(dict.fromkeys((r.optimizer, r.integrator) for r in rows if r.role == "sweep"))


def sweep_runs(rows: list[Run], scene: str, optimizer: str, integrator: str) -> list[Run]:
    """The sweep's runs of `optimizer` with `integrator` on `scene`, in the order they ran."""
    return [
        r
        for r in rows
        if r.scene == scene and r.role == "sweep" and r.optimizer == optimizer and r.integrator == integrator
    ]


def reference_check(rows: list[Run], scene: str) -> dict[str, float]:
    """|x_ref − x_ref(h/2)| (RMS over shared times, / body size), the smallest sweep or tight error, and
    their ratio."""
    check = next(r for r in rows if r.scene == scene and r.role == "reference-check")
    reported = [
        r.error for r in rows if r.scene == scene and r.role in ("sweep", "tight") and finite(r.error)
    ]
    smallest = min(reported, default=math.nan)
    return {"difference": check.error, "smallest": smallest, "ratio": smallest / check.error}


def reference_verdict(ratio: float) -> str:
    """How far the reference can be trusted, from the ratio of the smallest error it judges to its
    h-halving difference (half its own error where it is first order, 3/4 where second: the verdict
    takes the first-order factor, the larger)."""
    if not finite(ratio):
        return "–"
    if ratio >= 10:
        return "converged"
    return f"too coarse: its own error (~2× the difference) is ~{2 / ratio:.0%} of the smallest error"


def euler_at_reference_h(rows: list[Run], scene: str) -> float:
    """Implicit Euler's error at the reference's h, extrapolated at first order from its tight run at the
    smallest h (error ∝ h): what an implicit-Euler reference would be off by. NaN without such a run."""
    series = [r for r in time_series(rows, scene, "implicit_euler") if finite(r.error) and r.error > 0]
    reference = next(r for r in rows if r.scene == scene and r.role == "reference")
    return series[-1].error * reference.dt_s / series[-1].dt_s if series else math.nan


def order_verdict(order: float, integrator: str, series: list[Run]) -> str:
    """Whether `order` is the order `integrator` has away from contact, and why not where a TR-BDF2
    run took implicit-Euler steps on contact (fewer or more than 2 solves per step)."""
    expected = INTEGRATOR_ORDER[integrator]
    name = {1: "first", 2: "second"}[expected]
    verdict = f"{name} order" if abs(order - expected) <= 0.3 else f"not yet in the {name}-order regime"
    solves = [r.solves_per_step for r in series if finite(r.solves_per_step)]
    if integrator != "tr_bdf2" or not solves or all(abs(s - 2.0) < 1e-9 for s in solves):
        return verdict
    if all(abs(s - 1.0) < 1e-9 for s in solves):
        return verdict + "; every step started in contact and took implicit Euler (1 solve per step)"
    low, high = f"{min(solves):.2f}", f"{max(solves):.2f}"
    spread = low if low == high else f"{low}–{high}"
    return verdict + f"; contact steps took implicit Euler ({spread} solves per step, 2 without contact)"


def headline(
    rows: list[Run],
    scene: str,
    optimizer: str,
    accuracy: float,
    by: str = "wall",
    integrator: str = "implicit_euler",
) -> Run | None:
    """The sweep run of `optimizer` with `integrator` on `scene` with error ≤ `accuracy` and the least
    wall time per simulated second (`by="error"`: the least error); a run with unconverged steps
    counts, since its trajectory is what was measured."""
    fitting = [
        r
        for r in sweep_runs(rows, scene, optimizer, integrator)
        if r.status in ("ok", "unconverged") and finite(r.error) and r.error <= accuracy
    ]
    if by == "error":
        return min(fitting, key=lambda r: (r.error, r.wall_per_sim_s), default=None)
    return min(fitting, key=lambda r: r.wall_per_sim_s, default=None)


# --- output -----------------------------------------------------------------------------------------


# the columns of the tables that give one chosen setting per scene, optimizer and integrator
SETTING_HEADER = (
    "| scene | optimizer | integrator | h (s) | tol (m/s) | wall s per simulated s "
    "| CPU s per simulated s | error | final error | status |",
    "|---|---|---|---:|---:|---:|---:|---:|---:|---|",
)


def _setting_row(scene: str, optimizer: str, integrator: str, best: Run | None, missing: str) -> str:
    """One row of a `SETTING_HEADER` table: the chosen run `best`, or `missing` where there is none."""
    if best is None:
        return f"| {scene} | {optimizer} | {integrator} | – | – | {missing} | – | – | – | – |"
    return (
        f"| {scene} | {optimizer} | {integrator} | {best.dt} | {best.tol:g} | {_cost(best)} | "
        f"{_e(best.error)} | {_e(best.final_error)} | {best.status} |"
    )


def _cost(r: Run) -> str:
    """Wall and CPU seconds per simulated second, as two table cells."""
    if not finite(r.wall_per_sim_s):
        return "– | –"
    mark = "≥" if r.status == "over budget" else ""  # projected from the steps taken
    return f"{mark}{r.wall_per_sim_s:.3g} | {mark}{r.cpu_per_sim_s:.3g}"


def scenes_in(rows: list[Run]) -> list[str]:
    """The scenes of `rows`, in the order they ran."""
    return list(dict.fromkeys(r.scene for r in rows))


def introduction(rows: list[Run], args: argparse.Namespace, seconds: dict[str, Fraction]) -> list[str]:
    """What was measured and how, and the scenes."""
    scenes = list(dict.fromkeys(r.scene for r in rows))
    reference = next(r for r in rows if r.role == "reference")
    threads = torch.get_num_threads()
    lines = [
        "Work precision: wall time per simulated second against the error of the trajectory, float64, "
        f"{threads} thread{'s' * (threads != 1)}, one run per setting on a shared machine (timings are "
        "noisy). Integrators: implicit_euler (one solve per step, first order) and tr_bdf2 (two solves "
        "per step, second order; on a step that touches an obstacle it takes an implicit-Euler step "
        "instead); Adam runs with implicit Euler only. Error = RMS over the times every run shares "
        f"(multiples of {fraction_label(args.spacing)} s, "
        "t > 0) and all vertices of |x − x_ref|, divided by the body size (the rest bounding-box diagonal); "
        f"x_ref: Newton–CG at {args.reference_tol:g} m/s with {reference.integrator} at "
        f"h = {fraction_label(args.reference_dt)} s. "
        "Solver error: the same against Newton–CG at that tolerance with the run's own h and integrator. "
        f"Tolerances are velocity residuals ‖h M⁻¹∇E‖∞ in m/s (each solve of a step; for tr_bdf2 h is "
        f"the stage's); Adam and L-BFGS stop after {args.max_iter} iterations per solve, Newton after "
        f"100; runs projected past {args.budget:g} s of CPU time are stopped "
        "(over budget). After a run that went over budget or left half its steps unconverged, the tighter "
        "tolerances of that optimizer, integrator and h are skipped: they only add iterations.",
        "",
        "| scene | what | elements | body size (m) | simulated (s) |",
        "|---|---|---:|---:|---:|",
    ]
    for scene in scenes:
        first = next(r for r in rows if r.scene == scene)
        lines.append(
            f"| {scene} | {SCENE_NOTES[scene]} | {first.elements} | {first.body_size_m:.3f} | "
            f"{float(seconds[scene]):.4g} |"
        )
    return lines


def fastest(rows: list[Run], accuracy: float) -> list[str]:
    """The fastest sweep run of each optimizer and integrator with error ≤ `accuracy` of the body size."""
    scenes, pairs = scenes_in(rows), sweep_pairs(rows)
    lines: list[str] = []
    lines += [
        "",
        f"## Fastest setting with error ≤ {accuracy:g} of the body size",
        "",
        *SETTING_HEADER,
    ]
    for scene in scenes:
        for optimizer, integrator in pairs:
            best = headline(rows, scene, optimizer, accuracy, integrator=integrator)
            missing = ""
            if best is None:
                series = time_series(rows, scene, integrator)
                floor = (
                    f"time-discretisation error at h = {series[-1].dt} s: {_e(series[-1].error)}"
                    if series
                    else "no tight run"
                )
                missing = f"none reached it ({floor})"
            lines.append(_setting_row(scene, optimizer, integrator, best, missing))
    return lines


def smallest_errors(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """The cheapest run near the smallest error of each optimizer and integrator."""
    scenes, pairs = scenes_in(rows), sweep_pairs(rows)
    lines = [
        "",
        "## Smallest error each optimizer reached",
        "",
        "The cheapest run whose error is within 10% of the smallest error of any run of that optimizer "
        "and integrator.",
        "",
        *SETTING_HEADER,
    ]
    for scene in scenes:
        for optimizer, integrator in pairs:
            smallest = headline(rows, scene, optimizer, math.inf, by="error", integrator=integrator)
            best = (
                None
                if smallest is None
                else headline(rows, scene, optimizer, 1.1 * smallest.error, integrator=integrator)
            )
            lines.append(_setting_row(scene, optimizer, integrator, best, "no run finished"))
    return lines


def discretisation_errors(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """The tight runs' error against h, per integrator, with the observed order."""
    scenes, integrators = scenes_in(rows), integrators_in(rows)
    lines = [
        "",
        "## Time-discretisation error (Newton–CG at the reference tolerance) and observed order",
        "",
        "Per integrator. Order: slope of log(error) against log(h), least squares over all h, and "
        "between neighbours; implicit Euler should show 1, TR-BDF2 2. Measured against x_ref, whose own "
        "error adds a small bias at the finest h. On the drop and the quadruped the body touches the "
        "ground (the quadruped on every step, the cube from its landing at t ≈ 0.06 s on, for as long "
        "as it stays down), and TR-BDF2 takes an implicit-Euler step wherever it does (a second-order "
        "step would turn the kink an impact leaves into a bounce): its order there is that of implicit "
        "Euler at best, as is the order of any scheme through contact and friction. Solves per step "
        "show how often: 1 for implicit Euler; for TR-BDF2 2 on a step away from contact, 1 on one that "
        "starts in contact, 3 on one whose stages touched and that implicit Euler redid.",
        "",
        "| scene | integrator | h (s) | error | final error | order to next h | solves/step "
        "| wall s per simulated s | CPU s per simulated s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene in scenes:
        for integrator in integrators:
            series = time_series(rows, scene, integrator)
            for a, b in zip(series, series[1:] + [None], strict=True):
                pairwise = observed_order([a, b]) if b is not None else math.nan
                lines.append(
                    f"| {scene} | {integrator} | {a.dt} | {_e(a.error, 2)} | {_e(a.final_error, 2)} | "
                    f"{_f(pairwise, 2)} | {_f(a.solves_per_step, 2)} | {_cost(a)} |"
                )
            order = observed_order(series)
            lines.append(
                f"| {scene} | {integrator} | **fitted order** | **{_f(order, 2)}** | "
                f"{order_verdict(order, integrator, series)} | | | | |"
            )
    return lines


def reference_convergence(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """Whether x_ref is converged: its h-halving difference against the smallest error reported."""
    scenes, reference = scenes_in(rows), next(r for r in rows if r.role == "reference")
    lines = [
        "",
        "## Is the reference converged?",
        "",
        f"x_ref is {reference.integrator} at h_ref. |x_ref − x_ref(h_ref/2)| estimates its own error: "
        "half of it for a first-order step, 3/4 for a second-order one; the verdict takes the first-order "
        "factor (own error ≈ 2× the difference), which holds on the contact scenes, where TR-BDF2 steps "
        "by implicit Euler. It should lie at least ~10× below the smallest error reported. Why TR-BDF2: "
        "the last column is implicit Euler's error at h_ref, extrapolated at first order from its tight "
        "run at the smallest h. Where it is near or above the smallest error reported (the cantilever, "
        "whose TR-BDF2 runs are far more accurate), an implicit-Euler x_ref could not measure those "
        "runs; TR-BDF2 at the same h_ref is as accurate as the difference column says, at about twice the "
        "cost per step away from contact and the same cost on it.",
        "",
        "| scene | integrator | h_ref (s) | \\|x_ref − x_ref(h_ref/2)\\| | final | smallest error reported "
        "| ratio | unconverged reference steps | verdict | implicit Euler at h_ref |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for scene in scenes:
        check = reference_check(rows, scene)
        ref = next(r for r in rows if r.scene == scene and r.role == "reference")
        half = next(r for r in rows if r.scene == scene and r.role == "reference-check")
        lines.append(
            f"| {scene} | {ref.integrator} | {ref.dt} | {_e(check['difference'], 2)} | "
            f"{_e(half.final_error, 2)} | {_e(check['smallest'], 2)} | {_f(check['ratio'])} | "
            f"{ref.unconverged_steps + half.unconverged_steps}/{ref.steps + half.steps} | "
            f"{reference_verdict(check['ratio'])} | {_e(euler_at_reference_h(rows, scene), 2)} |"
        )
    return lines


def solver_errors(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """The sweep's solver error at `--solver-dt`, against the tight run of that h."""
    solver_dt = fraction_label(args.solver_dt)
    lines = [
        "",
        f"## Solver error at h = {solver_dt} s (against Newton–CG at {args.reference_tol:g} m/s, same h "
        "and integrator)",
        "",
        "| scene | optimizer | integrator | tol (m/s) | solver error | final | iterations/step "
        "| unconverged steps | wall s per simulated s | CPU s per simulated s | status |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        if r.role == "sweep" and r.dt == solver_dt:
            lines.append(
                f"| {r.scene} | {r.optimizer} | {r.integrator} | {r.tol:g} | {_e(r.solver_error)} | "
                f"{_e(r.solver_final_error)} | {_f(r.iterations_per_step)} | "
                f"{r.unconverged_steps}/{r.steps_done} | {_cost(r)} | {r.status} |"
            )
    return lines


def failures(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """How many runs of each optimizer and integrator failed, and how."""
    scenes, pairs = scenes_in(rows), sweep_pairs(rows)
    lines = [
        "",
        "## Failures per optimizer and integrator",
        "",
        "| scene | optimizer | integrator | runs | ok | unconverged | diverged | over budget | skipped "
        "| unconverged steps |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene in scenes:
        for optimizer, integrator in pairs:
            mine = sweep_runs(rows, scene, optimizer, integrator)
            count = {
                s: sum(r.status == s for r in mine)
                for s in ("ok", "unconverged", "diverged", "over budget", "skipped")
            }
            steps = sum(r.unconverged_steps for r in mine)
            taken = sum(r.steps_done for r in mine)
            lines.append(
                f"| {scene} | {optimizer} | {integrator} | {len(mine)} | "
                + " | ".join(str(v) for v in count.values())
                + f" | {steps}/{taken} |"
            )
    return lines


def every_run(rows: list[Run], args: argparse.Namespace) -> list[str]:
    """Every run's row."""
    lines = [
        "",
        "## Every run",
        "",
        "| scene | role | optimizer | integrator | h (s) | tol (m/s) | status | steps | unconverged "
        "| iterations/step | solves/step | wall s per simulated s | CPU s per simulated s | error "
        "| final error | solver error | solver final error |",
        "|---|---|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.scene} | {r.role} | {r.optimizer} | {r.integrator} | {r.dt} | {r.tol:g} | {r.status} | "
            f"{r.steps_done}/{r.steps} | {r.unconverged_steps} | {_f(r.iterations_per_step)} | "
            f"{_f(r.solves_per_step, 2)} | {_cost(r)} | {_e(r.error)} | {_e(r.final_error)} | "
            f"{_e(r.solver_error)} | {_e(r.solver_final_error)} |"
        )
    return lines


def markdown(rows: list[Run], args: argparse.Namespace, seconds: dict[str, Fraction]) -> str:
    """The results as markdown tables: what was run, then one section per question."""
    lines = introduction(rows, args, seconds)
    for accuracy in ACCURACIES:
        lines += fastest(rows, accuracy)
    sections = (smallest_errors, discretisation_errors, reference_convergence, solver_errors, failures,
        every_run)
    for section in sections:
        lines += section(rows, args)
    return "\n".join(lines) + "\n"


def _pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both wall time and error, by wall time."""
    front: list[tuple[float, float]] = []
    for wall, error in sorted(points):
        if not front or error < front[-1][1]:
            front.append((wall, error))
    return front


# line style of each integrator's curves in both figures
INTEGRATOR_STYLE = {"implicit_euler": "-", "tr_bdf2": "--"}


def plot_work_precision(rows: list[Run], tols: list[float], path: Path) -> None:
    """Error against wall time per simulated second, log–log, one panel per scene: a marker per run
    (colour: optimizer and integrator, shape: tolerance, hollow: some steps unconverged) and each
    (optimizer, integrator) pair's front (solid: implicit Euler, dashed: TR-BDF2)."""
    plt = pyplot()
    from matplotlib.lines import Line2D

    scenes = list(dict.fromkeys(r.scene for r in rows))
    pairs = sweep_pairs(rows)
    colours = {pair: f"C{i}" for i, pair in enumerate(pairs)}
    markers = dict(zip(sorted(tols, reverse=True), "osD^v<>ph*", strict=False))
    floors = {"implicit_euler": (":", 1.0, "right"), "tr_bdf2": ("-.", 0.0, "left")}
    width = max(5.4 * len(scenes), 8.0)
    figure, axes = plt.subplots(1, len(scenes), figsize=(width, 5.8), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        sweep = [r for r in rows if r.scene == scene and r.role == "sweep"]
        for pair in pairs:
            mine = [
                r
                for r in sweep
                if (r.optimizer, r.integrator) == pair
                and finite(r.error)
                and r.error > 0
                and r.status in ("ok", "unconverged")
            ]
            colour = colours[pair]
            for r in mine:
                hollow = r.status != "ok"
                ax.loglog(
                    r.wall_per_sim_s,
                    r.error,
                    markers.get(r.tol, "o"),
                    color=colour,
                    markerfacecolor="none" if hollow else colour,
                    alpha=0.8,
                )
            front = _pareto([(r.wall_per_sim_s, r.error) for r in mine])
            if front:
                style = INTEGRATOR_STYLE.get(pair[1], "-")
                ax.loglog(*zip(*front, strict=True), style, color=colour, alpha=0.6)
        for accuracy in ACCURACIES:
            ax.axhline(accuracy, color="grey", linestyle="--", linewidth=0.8)
        # each h's time-discretisation error: the floor no tolerance gets a run with that h and integrator
        # below (implicit Euler's labelled on the right, TR-BDF2's on the left)
        for integrator in integrators_in(rows):
            linestyle, x, align = floors.get(integrator, (":", 1.0, "right"))
            for r in time_series(rows, scene, integrator):
                if finite(r.error) and r.error > 0:
                    ax.axhline(r.error, color="black", linestyle=linestyle, linewidth=0.6, alpha=0.6)
                    ax.annotate(
                        f"h = {r.dt} s",
                        (x, r.error),
                        xycoords=("axes fraction", "data"),
                        fontsize=7,
                        ha=align,
                        va="bottom",
                        alpha=0.8,
                    )
        failed = sum(r.status in ("over budget", "skipped", "diverged") for r in sweep)
        ax.set(
            xlabel="wall s per simulated s",
            ylabel="RMS position error / body size",
            title=f"{scene} ({failed} of {len(sweep)} runs failed or skipped)",
        )
        ax.grid(True, which="both", alpha=0.3)
    handles = [
        Line2D(
            [],
            [],
            color=colours[pair],
            marker="o",
            linestyle=INTEGRATOR_STYLE.get(pair[1], "-"),
            label=f"{pair[0]} {pair[1]}",
        )
        for pair in pairs
    ]
    handles += [
        Line2D([], [], color="grey", marker=m, linestyle="", label=f"tol {t:g} m/s")
        for t, m in markers.items()
    ]
    handles.append(
        Line2D(
            [],
            [],
            color="grey",
            marker="o",
            markerfacecolor="none",
            linestyle="",
            label="some steps unconverged",
        )
    )
    accuracies = ", ".join(f"{a:g}" for a in ACCURACIES)
    handles.append(Line2D([], [], color="grey", linestyle="--", label=f"error {accuracies}"))
    for integrator in integrators_in(rows):
        label = f"time-discretisation error, {integrator}"
        linestyle = floors.get(integrator, (":",))[0]
        handles.append(Line2D([], [], color="black", linestyle=linestyle, label=label))
    # as many legend columns as fit the width (about 2.8 in per entry), and room below for its rows
    columns = min(len(handles), max(3, int(width // 2.8)))
    rows_needed = math.ceil(len(handles) / columns)
    figure.legend(handles=handles, fontsize=8, loc="lower center", ncol=columns)
    figure.suptitle(
        "Work precision; a line joins the runs of one optimizer and integrator that no faster run beats"
    )
    figure.tight_layout(rect=(0, 0.02 + 0.04 * rows_needed, 1, 1))
    save_figure(figure, path)


def plot_error_sources(rows: list[Run], args: argparse.Namespace, path: Path) -> None:
    """Top: time-discretisation error against h (tight Newton–CG) per integrator, with the observed
    orders and the reference check. Bottom: solver error against tolerance at h = `args.solver_dt`, per
    optimizer and integrator."""
    plt = pyplot()
    from matplotlib.ticker import NullFormatter

    scenes = list(dict.fromkeys(r.scene for r in rows))
    integrators = integrators_in(rows)
    optimizers = list(dict.fromkeys(optimizer for optimizer, _ in sweep_pairs(rows)))
    reference = next(r for r in rows if r.role == "reference")
    figure, axes = plt.subplots(2, len(scenes), figsize=(max(5.4 * len(scenes), 6.0), 8.4), squeeze=False)
    solver_dt = fraction_label(args.solver_dt)
    for column, scene in enumerate(scenes):
        top, bottom = axes[0][column], axes[1][column]
        orders = []
        for i, integrator in enumerate(integrators):
            series = [r for r in time_series(rows, scene, integrator) if finite(r.error) and r.error > 0]
            if not series:
                continue
            colour = f"C{i}"
            dts = [r.dt_s for r in series]
            top.loglog(dts, [r.error for r in series], "o-", color=colour, label=f"{integrator} RMS error")
            top.loglog(
                dts, [r.final_error for r in series], "s--", color=colour, alpha=0.6, label="final error"
            )
            order = INTEGRATOR_ORDER[integrator]
            scale = series[-1].error / series[-1].dt_s ** order
            top.loglog(dts, [scale * h**order for h in dts], ":", color=colour, label=f"order {order}")
            top.set_xticks(dts, [r.dt for r in series])
            top.xaxis.set_minor_formatter(NullFormatter())
            orders.append(f"{integrator} {_f(observed_order(series), 2)}")
        check = reference_check(rows, scene)
        if finite(check["difference"]) and check["difference"] > 0:
            top.axhline(
                check["difference"],
                color="C3",
                linewidth=0.8,
                label=f"|x_ref − x_ref(h_ref/2)|, {reference.integrator}, "
                f"h_ref = {fraction_label(args.reference_dt)} s",
            )
        top.set_title(f"{scene}: time discretisation, order " + ", ".join(orders), fontsize=9)
        top.set(xlabel="h (s)", ylabel="error / body size")
        top.grid(True, which="both", alpha=0.3)
        top.legend(fontsize=6)
        for optimizer, integrator in sweep_pairs(rows):
            colour = f"C{optimizers.index(optimizer)}"
            style = INTEGRATOR_STYLE.get(integrator, "-")
            mine = sorted(
                (
                    r
                    for r in sweep_runs(rows, scene, optimizer, integrator)
                    if r.dt == solver_dt and finite(r.solver_error) and r.solver_error > 0
                ),
                key=lambda r: -r.tol,
            )
            if not mine:
                continue
            bottom.loglog(
                [r.tol for r in mine],
                [r.solver_error for r in mine],
                style,
                color=colour,
                label=f"{optimizer} {integrator}",
            )
            for r in mine:
                bottom.loglog(
                    r.tol,
                    r.solver_error,
                    "o",
                    color=colour,
                    markerfacecolor="none" if r.status != "ok" else colour,
                )
        seconds = next(float(r.steps * r.dt_s) for r in rows if r.scene == scene)
        size = next(r.body_size_m for r in rows if r.scene == scene)
        tols = sorted(args.tols)
        bottom.loglog(
            tols, [seconds * t / size for t in tols], ":", color="grey", label="T · tol / body size"
        )
        bottom.plot(
            [], [], "o", color="grey", markerfacecolor="none", linestyle="", label="unconverged steps"
        )
        bottom.set(
            xlabel="tolerance (m/s)",
            ylabel="solver error / body size",
            title=f"{scene}: solver error, h = {solver_dt} s",
        )
        bottom.grid(True, which="both", alpha=0.3)
        bottom.legend(fontsize=6)
    figure.tight_layout()
    save_figure(figure, path)


# --- command line -----------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--scenes", nargs="+", choices=list(SCENES), default=list(SCENES))
    add("--optimizers", nargs="+", choices=OPTIMIZERS, default=list(OPTIMIZERS))
    add(
        "--integrators",
        nargs="+",
        choices=list(es.IMPLICIT_INTEGRATORS),
        default=list(es.IMPLICIT_INTEGRATORS),
        help="time integrators of the tight runs and the sweep (Adam: implicit_euler only)",
    )
    add(
        "--dts",
        nargs="+",
        type=parse_dt,
        default=None,
        help="time steps h, e.g. 1/60 (default: "
        + " ".join(DEFAULT_DTS)
        + "; --quick: "
        + " ".join(QUICK_DTS)
        + ")",
    )
    add(
        "--tols",
        nargs="+",
        type=float,
        default=None,
        help="velocity-residual tolerances, m/s (default: "
        + " ".join(f"{t:g}" for t in DEFAULT_TOLS)
        + "; --quick: "
        + " ".join(f"{t:g}" for t in QUICK_TOLS)
        + ")",
    )
    add(
        "--seconds",
        type=parse_dt,
        default=None,
        help="simulated time, s, a multiple of the shared sample spacing (default: 0.5 for each scene; "
        "--quick: 1/4, 1/4 and 1/12)",
    )
    add("--quick", action="store_true", help="tiny meshes, two h, two tolerances, short runs (CI size)")
    add("--reference-dt", type=parse_dt, default=None, help="h of x_ref (default 1/3840; --quick 1/960)")
    add(
        "--reference-integrator",
        choices=list(es.IMPLICIT_INTEGRATORS),
        default="tr_bdf2",
        help="integrator of x_ref and its check (tr_bdf2: second order away from contact)",
    )
    add("--reference-tol", type=float, default=1e-9, help="x_ref's and the tight runs' tolerance, m/s")
    add("--solver-dt", type=parse_dt, default=Fraction(1, 60), help="h of the solver-error table and plot")
    add("--max-iter", type=int, default=2000, help="iterations per step of Adam and L-BFGS, at most")
    add("--budget", type=float, default=None, help="CPU s per run, at most (default 30; --quick 10)")
    add("--threads", type=int, default=1, help="torch intra-op threads")
    add("--out", type=Path, default=Path("docs/benchmarks"))
    add("--no-plot", action="store_true")
    add("--from-csv", type=Path, default=None, help="run nothing: rewrite the table and plots from this CSV")
    args = parser.parse_args(argv)
    quick = args.quick
    args.size = "quick" if quick else "full"
    args.dts = sorted(
        set(args.dts or [parse_dt(t) for t in (QUICK_DTS if quick else DEFAULT_DTS)]), reverse=True
    )
    args.tols = sorted(set(args.tols or (QUICK_TOLS if quick else DEFAULT_TOLS)), reverse=True)
    args.reference_dt = args.reference_dt or Fraction(1, 960 if quick else 3840)
    args.budget = args.budget if args.budget is not None else (10.0 if quick else 30.0)
    args.spacing = common_multiple(args.dts)
    for dt in (args.reference_dt, args.reference_dt / 2):
        if (args.spacing / dt).denominator != 1:
            parser.error(
                f"--reference-dt {fraction_label(args.reference_dt)}: its steps must fall on the "
                f"shared times (multiples of {fraction_label(args.spacing)} s)"
            )
    if args.from_csv is None and args.solver_dt not in args.dts:
        parser.error(f"--solver-dt {fraction_label(args.solver_dt)} must be one of --dts")
    return args


# columns a CSV written before the integrator became a dimension lacks: all its runs were implicit Euler
LEGACY_COLUMNS = {"integrator": "implicit_euler", "solves_per_step": "1.0"}


def read_csv(path: Path) -> list[Run]:
    """The rows of a CSV this script wrote (an older one without the integrator columns too)."""
    convert = {"int": int, "float": float, "str": str}
    types = {field.name: convert[field.type] for field in fields(Run)}
    with open(path, newline="") as handle:
        return [
            Run(**{k: types[k](v) for k, v in {**LEGACY_COLUMNS, **line}.items()})
            for line in csv.DictReader(handle)
        ]


def settings_of(rows: list[Run], args: argparse.Namespace) -> dict[str, Fraction]:
    """Set the grid in `args` from the rows of an earlier run; returns the simulated seconds per scene."""
    sweep = [r for r in rows if r.role in ("sweep", "tight")]
    reference = next(r for r in rows if r.role == "reference")
    args.scenes = list(dict.fromkeys(r.scene for r in rows))
    args.optimizers = list(dict.fromkeys(r.optimizer for r in rows if r.role == "sweep"))
    args.integrators = integrators_in(rows)
    args.reference_integrator = reference.integrator
    args.dts = sorted({Fraction(r.dt) for r in sweep}, reverse=True)
    args.tols = sorted({r.tol for r in rows if r.role == "sweep"}, reverse=True)
    args.reference_dt, args.reference_tol = Fraction(reference.dt), reference.tol
    args.spacing = common_multiple(args.dts)
    return {r.scene: r.steps * Fraction(r.dt) for r in rows if r.role == "reference"}


def write_outputs(rows: list[Run], args: argparse.Namespace, seconds: dict[str, Fraction]) -> None:
    """CSV, markdown table and both figures in `args.out`; prints the table."""
    text = markdown(rows, args, seconds)
    print(text)
    plots = None if args.no_plot else lambda path: plot_work_precision(rows, args.tols, path)
    write_files(args.out, "work_precision", rows, text, plots)
    if not args.no_plot:
        plot_error_sources(rows, args, args.out / "work_precision_errors.png")


def main(argv: list[str] | None = None) -> list[Run]:
    """Run the benchmark; write CSV, markdown and plots to `--out`; return every run's row."""
    args = parse_args(argv)
    configure_threads(args.threads, retain_memory=False)
    if args.from_csv is not None:
        rows = read_csv(args.from_csv)
        write_outputs(rows, args, settings_of(rows, args))
        return rows
    seconds = {
        name: args.seconds or Fraction(SECONDS[args.size][name]).limit_denominator(1000)
        for name in args.scenes
    }
    for name, duration in seconds.items():
        if (duration / args.spacing).denominator != 1:
            raise SystemExit(
                f"{name}: --seconds {float(duration):g} is not a multiple of the shared sample "
                f"spacing {fraction_label(args.spacing)} s of the time steps"
            )
    total = sum(
        int(seconds[name] / dt) for name in args.scenes for *_, dt, _ in scene_plan(args, seconds[name])
    )
    rows: list[Run] = []
    with tqdm(total=total, unit="step", desc="work precision", smoothing=0.0) as progress:
        for name in args.scenes:
            rows += run_scene(name, seconds[name], args, progress)
            args.out.mkdir(parents=True, exist_ok=True)  # the rows so far, in case a later scene fails
            write_csv(args.out / "work_precision.csv", rows)
    write_outputs(rows, args, seconds)
    return rows


if __name__ == "__main__":
    main()
