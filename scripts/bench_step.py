"""Benchmark one implicit-Euler step: wall time *and* error, per optimizer and mesh size.

The scene: a cantilever 1 × 0.2 × 0.2 m clamped at x = 0, swinging under gravity (E = 1e5 Pa,
ν = 0.3, ρ = 1000 kg/m³, h = 1/60 s, float64). A reference trajectory is computed with
Newton–CG at tol 1e-10 m/s; every optimizer then takes the same steps from the reference
states, and each step's x_{n+1} is compared with the reference's.

The contact scene (`--scenes landing`): a 0.2 m cube of the same material (E = 1e5 Pa by
default, ν = 0.3, ρ = 1000 kg/m³, h = 1/60 s) falls at 1 m/s onto `es.Ground(0.0, friction=0.5)`.
After `--landing-warmup` reference steps of free fall it lands in the second timed step; the
timed steps go on through the rebound to rest. Every optimizer takes those steps from the
reference states, as above, and the table adds the lowest vertex height it produced (> 0: no
penetration). More tables: iterations per step through the impact; the cost of the contact
terms (barrier, lagged friction, CCD) against the elastic term's; and the same steps without an
obstacle, with the ground out of reach and in contact.

Run:  python scripts/bench_step.py                       # cantilever, ~1k, 10k and 50k tets
      python scripts/bench_step.py --sizes 1k --steps 3  # quick
      python scripts/bench_step.py --scenes landing --sizes 1k 10k 50k --threads 1
      python scripts/bench_step.py --scenes landing --sizes 1k --solvers newton-cg  # quick
Writes: <out>/bench_step.csv, <out>/bench_step.md (the table) and <out>/bench_step.png for the
cantilever; <out>/bench_step_landing.{csv,md,png}, bench_step_landing_terms.csv,
bench_step_landing_obstacles.csv and bench_step_landing_trace.csv for the landing.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from _bench import (
    configure_threads,
    fixed,
    make_parser,
    median_ms,
    pyplot,
    save_figure,
    table,
    write_csv,
    write_outputs,
)

import energysim as es
from energysim.contact import LaggedFriction
from energysim.integrators.adjoint import step_terms
from energysim.objective.derivatives import element_hessian
from energysim.objective.objective import Objective

# cells along (x, y, z) for about 1k, 10k and 50k tets (6 tets per cell)
SIZES = {"tiny": (6, 1, 1), "1k": (15, 3, 3), "10k": (35, 7, 7), "50k": (60, 12, 12)}
REFERENCE_TOL = 1e-10


def timed_steps(
    scene: es.Scene,
    states: list[torch.Tensor],
    steps: int,
    solver: es.Solver,
    budget_s: float,
    probe: Callable[[torch.Tensor], float] | None = None,
) -> tuple[list[float], list[es.SolverResult], list[float], list[float]]:
    """Step `solver` from each reference state in turn: wall times (s), solver reports, max |x − x_ref|
    against the next reference state (m), and `probe(x)` of each result; stops early past `budget_s`."""
    times, stats, errors, probed = [], [], [], []
    for k in range(steps):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", es.ConvergenceWarning)  # reported in the table instead
            start = time.perf_counter()
            result = es.step(scene, states[k], solver=solver)
            times.append(time.perf_counter() - start)
        stats.append(result.stats)
        x, _ = scene.split_state(result.state)
        x_ref, _ = scene.split_state(states[k + 1])
        errors.append(float((x - x_ref).abs().max()))
        if probe is not None:
            probed.append(probe(x))
        if sum(times) > budget_s:  # a slow optimizer on a big mesh: fewer samples
            break
    return times, stats, errors, probed


def solvers(tol: float, first_order_iterations: int) -> dict[str, es.Solver]:
    """The optimizers compared, all stopping at the same velocity residual `tol` (m/s)."""
    return {
        "newton-cg": es.NewtonCG(tol=tol),
        "newton-cg-autograd": es.NewtonCG(tol=tol, hessian="autograd", preconditioner="none"),
        "lbfgs": es.LBFGS(tol=tol, max_iter=first_order_iterations),
        "adam": es.Adam(tol=tol, max_iter=first_order_iterations, lr=1e-4),
    }


def build_scene(cells: tuple[int, int, int]) -> es.Scene:
    """The swinging cantilever on a box mesh with `cells` cells."""
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=cells)
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


@dataclass(frozen=True)
class Row:
    """One (mesh, optimizer) line of the table."""

    tets: int
    solver: str
    steps: int
    ms_per_step: float
    iterations: float
    grad_evals: float
    hvps: float
    residual: float
    converged: str
    error_m: float


def effort(stats: list[es.SolverResult]) -> dict[str, object]:
    """What the solver's reports of the timed steps add up to: the columns `Row` and `LandingRow` share."""
    return {
        "iterations": statistics.mean(s.iterations for s in stats),
        "grad_evals": statistics.mean(s.grad_evals for s in stats),
        "hvps": statistics.mean(s.hvp_evals for s in stats),
        "residual": max(s.residual for s in stats),
        "converged": f"{sum(s.converged for s in stats)}/{len(stats)}",
    }


def kernel_timings(scene: es.Scene, state: torch.Tensor) -> dict[str, float]:
    """ms per energy, energy + gradient, Hessian assembly and Hessian-vector product at `state`."""
    x, _ = scene.split_state(state)
    objective = Objective(list(scene.terms), scene.free, scene.dt / scene.vertex_mass)
    operator = objective.hessian(x)
    operator.matrix(x)
    vector = torch.randn_like(x)
    autograd_operator = objective.hessian(x, use_element_blocks=False)
    return {
        "energy": median_ms(lambda: objective.energy(x)),
        "energy+gradient": median_ms(lambda: objective.energy_and_gradient(x)),
        "element Hessians + CSR assembly": median_ms(lambda: objective.hessian(x).matrix(x)),
        "HVP (assembled CSR)": median_ms(lambda: operator.matvec(vector)),
        "HVP (autograd double backward)": median_ms(lambda: autograd_operator.matvec(vector)),
    }


def run(
    size: str,
    steps: int,
    warmup: int,
    tol: float,
    names: list[str],
    first_order_iterations: int,
    budget_s: float,
) -> tuple[list[Row], dict[str, float]]:
    """Reference trajectory, then every optimizer on the same steps; rows and kernel timings."""
    scene = build_scene(SIZES[size])
    reference = es.NewtonCG(tol=REFERENCE_TOL, max_iter=100, strict=True)
    state = scene.initial_state()
    for _ in range(warmup):  # start from a swinging, bent beam, not from rest
        state = es.step(scene, state, solver=reference).state
    states = [state]
    for _ in range(steps):
        states.append(es.step(scene, states[-1], solver=reference).state)
    rows = []
    for name, solver in solvers(tol, first_order_iterations).items():
        if name not in names:
            continue
        times, stats, errors, _ = timed_steps(scene, states, steps, solver, budget_s)
        rows.append(
            Row(
                tets=scene.mesh.num_elements,
                solver=name,
                steps=len(times),
                ms_per_step=1e3 * statistics.median(times),
                **effort(stats),
                error_m=max(errors),
            )
        )
    return rows, kernel_timings(scene, states[-1])


def markdown(rows: list[Row], kernels: dict[int, dict[str, float]], tol: float) -> str:
    """The results as markdown tables."""
    lines = [
        f"Cantilever step, h = 1/60 s, float64, {torch.get_num_threads()} threads; tol = {tol:g} m/s "
        f"(velocity residual); error = max |x_(n+1) − x_ref| against Newton–CG at {REFERENCE_TOL:g} m/s.",
        "",
    ]
    header = ["tets", "optimizer", "median ms/step", "iterations", "grad evals", "HVPs", "max residual (m/s)",
              "converged", "max error (m)"]
    lines += table(header, [
        [r.tets, r.solver, f"{r.ms_per_step:.1f}", f"{r.iterations:.1f}", f"{r.grad_evals:.1f}",
            f"{r.hvps:.1f}",
         f"{r.residual:.1e}", r.converged, f"{r.error_m:.1e}"]
        for r in rows
    ], align="rl" + "r" * 7)
    kernel_names = [f"{k} (ms)" for k in next(iter(kernels.values()))]
    lines += ["", *table(["tets", *kernel_names], [
        [tets, *(f"{v:.2f}" for v in timing.values())] for tets, timing in kernels.items()
    ], align="r" * (1 + len(kernel_names)))]
    return "\n".join(lines) + "\n"


def plot(rows: list[Row], path: Path) -> None:
    """ms per step against tet count, one line per optimizer, log–log."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r.solver for r in rows):
        mine = [r for r in rows if r.solver == name]
        axes[0].loglog([r.tets for r in mine], [r.ms_per_step for r in mine], "o-", label=name)
        axes[1].loglog([r.ms_per_step for r in mine], [max(r.error_m, 1e-16) for r in mine], "o-", label=name)
    axes[0].set(xlabel="tets", ylabel="median ms per step", title="Wall time per step")
    axes[1].set(xlabel="median ms per step", ylabel="max position error (m)", title="Error against time")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    figure.tight_layout()
    save_figure(figure, path)


# --- the landing: contact and friction ------------------------------------------------------

# cells along (x, y, z) of the cube for about 1k, 10k and 50k tets (6 tets per cell)
LANDING_SIZES = {"tiny": (2, 2, 2), "1k": (6, 5, 6), "10k": (12, 12, 12), "50k": (20, 20, 20)}
LANDING_SIDE = 0.2  # m
LANDING_SPEED = 1.0  # m/s, downward, at the start of the warm-up
LANDING_FRICTION = 0.5
GRAVITY = 9.81
FAR_BELOW = 1.0  # m: where the out-of-reach ground lies, below y = 0


class CountingGround(es.Ground):
    """`es.Ground` that counts its CCD calls (`step_limit`: once per line search and warm-start
    candidate; `max_step` is it plus the check of the start)."""

    ccd_calls = 0

    def step_limit(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        self.ccd_calls += 1
        return super().step_limit(x, dx)


def build_landing_scene(
    cells: tuple[int, int, int],
    youngs_modulus: float,
    ground_height: float | None = 0.0,
    ground: type[es.Ground] = es.Ground,
) -> es.Scene:
    """The cube with `cells` cells, and the ground at y = `ground_height` (None: no obstacle at all)."""
    mesh = es.TetMesh.box(size=(LANDING_SIDE,) * 3, cells=cells)
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -GRAVITY, 0.0))
    scene.add(es.NeoHookean(youngs_modulus=youngs_modulus, poissons_ratio=0.3))
    if ground_height is not None:
        scene.add(ground(ground_height, friction=LANDING_FRICTION))
    return scene


def landing_start(scene: es.Scene, warmup: int) -> torch.Tensor:
    """The undeformed cube falling at `LANDING_SPEED`, placed so that it reaches the ground in the
    second step after `warmup` steps (implicit Euler falls h·Σ_j (v₀ + j g h) in k steps)."""
    h = scene.dt

    def fallen(k: int) -> float:
        return h * sum(LANDING_SPEED + j * GRAVITY * h for j in range(1, k + 1))

    lift = 0.5 * (fallen(warmup + 1) + fallen(warmup + 2))
    x0 = scene.mesh.vertices + torch.tensor([0.0, lift, 0.0], dtype=scene.mesh.vertices.dtype)
    v0 = torch.tensor([0.0, -LANDING_SPEED, 0.0], dtype=x0.dtype).expand_as(x0)
    return scene.initial_state(x0, v0)


def ground_of(scene: es.Scene) -> es.Obstacle:
    """The scene's (single) obstacle."""
    (ground,) = [term for term in scene.terms if isinstance(term, es.Obstacle)]
    return ground


@dataclass(frozen=True)
class LandingRow:
    """One (mesh, optimizer) line of the landing table."""

    tets: int
    solver: str
    steps: int
    ms_per_step: float
    iterations: float
    max_iterations: int
    grad_evals: float
    hvps: float
    residual: float
    converged: str
    min_height_m: float
    error_m: float


@dataclass(frozen=True)
class ObstacleRow:
    """The same steps in a scene without obstacles, with the ground out of reach, and in contact."""

    tets: int
    scene: str
    terms: str
    ccd_terms: int
    ccd_calls_per_step: float
    samples: int
    ms_per_step: float
    iterations: float
    vs_no_obstacle_pct: float


def interleaved_median_ms(
    functions: dict[object, Callable[[], object]], rounds: int = 21
) -> dict[object, float]:
    """Median wall time of each function in ms, after one warm-up call each; the calls are
    interleaved round by round, so a stretch of load from other processes hits all of them alike."""
    for function in functions.values():
        function()
    samples: dict[object, list[float]] = {key: [] for key in functions}
    for _ in range(rounds):
        for key, function in functions.items():
            start = time.perf_counter()
            function()
            samples[key].append(time.perf_counter() - start)
    return {key: 1e3 * statistics.median(times) for key, times in samples.items()}


def assembled_hessian(objective: Objective, x: torch.Tensor) -> torch.Tensor | None:
    """The objective's element Hessians at `x`, assembled into its CSR matrix."""
    return objective.hessian(x).matrix(x)


def term_costs(scene: es.Scene, previous: torch.Tensor, state: torch.Tensor) -> list[dict[str, object]]:
    """ms per evaluation of each term alone at `state`, friction lagged from `previous` (in contact).

    Rows: the elastic term, the ground barrier, the lagged friction term (energy + gradient through
    `Objective`, element Hessian blocks through `element_hessian`), the CCD of one line search and
    the friction term's construction once per step; then the whole step objective without and
    with its contact terms (energy + gradient, element Hessians + CSR assembly).
    """
    x_prev, v_prev = scene.split_state(previous)
    x, _ = scene.split_state(state)
    ground = ground_of(scene)
    elastic = next(term for term in scene.terms if isinstance(term, es.NeoHookean))
    lagged = ground.lagged_terms(x_prev, scene.dt)
    if not lagged:
        raise RuntimeError("the cost breakdown needs a state in contact: take more --landing-steps")
    (friction,) = lagged
    scale = scene.dt / scene.vertex_mass
    motion = x - x_prev
    with_contact = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x_prev, v_prev, scene.free)
    without = [term for term in with_contact if not isinstance(term, (es.Obstacle, LaggedFriction))]
    kernels: dict[tuple[str, str], Callable[[], object]] = {}
    for label, term in (
        (f"elastic (NeoHookean, {elastic.element_vertices.shape[0]} tets)", elastic),
        (f"ground barrier ({ground.element_vertices.shape[0]} vertices)", ground),
        (f"lagged friction ({friction.element_vertices.shape[0]} vertices)", friction),
    ):
        objective = Objective([term], scene.free, scale)
        kernels[label, "evaluation"] = partial(objective.energy_and_gradient, x)
        kernels[label, "hessian"] = partial(element_hessian, term, x, None)
    kernels["ground CCD (max_step), once per line search", "evaluation"] = partial(
        ground.max_step, x_prev, motion
    )
    kernels["friction term built (lagged_terms), once per step", "evaluation"] = partial(
        ground.lagged_terms, x_prev, scene.dt
    )
    for label, terms in (
        ("step objective without contact terms", without),
        ("step objective with contact terms", with_contact),
    ):
        objective = Objective(terms, scene.free, scale, anchor=x)
        kernels[label, "evaluation"] = partial(objective.energy_and_gradient, x)
        kernels[label, "hessian"] = partial(assembled_hessian, objective, x)
    timings = interleaved_median_ms(kernels)
    labels = list(dict.fromkeys(label for label, _ in kernels))
    measured = [(label, timings[label, "evaluation"], timings.get((label, "hessian"))) for label in labels]
    elastic_gradient, elastic_hessian = measured[0][1], measured[0][2]
    return [
        {
            "tets": scene.mesh.num_elements,
            "term": label,
            "energy_gradient_ms": gradient_ms,
            "energy_gradient_pct": 100 * gradient_ms / elastic_gradient,
            "hessian_ms": math.nan if hessian_ms is None else hessian_ms,
            "hessian_pct": math.nan if hessian_ms is None else 100 * hessian_ms / elastic_hessian,
        }
        for label, gradient_ms, hessian_ms in measured
    ]


def obstacle_overhead(
    cells: tuple[int, int, int], youngs_modulus: float, states: list[torch.Tensor], tol: float, repeats: int
) -> list[ObstacleRow]:
    """Newton–CG steps from the same `states` in three scenes, interleaved: no obstacle at all, the
    ground `FAR_BELOW` m below (no vertex within its barrier distance), and the ground at y = 0."""
    far_label = f"ground {FAR_BELOW:g} m below (out of reach)"
    variants = {
        "no obstacle": build_landing_scene(cells, youngs_modulus, None),
        far_label: build_landing_scene(cells, youngs_modulus, -FAR_BELOW, CountingGround),
        "ground at y = 0 (landing)": build_landing_scene(cells, youngs_modulus, 0.0, CountingGround),
    }
    far = ground_of(variants[far_label])
    for state in states:
        x, _ = variants[far_label].split_state(state)
        if float(far.signed_distance(x).min()) <= far.barrier_distance:
            raise RuntimeError("the far ground is within reach of the barrier")
    solver = es.NewtonCG(tol=tol)
    labels = list(variants)
    times: dict[str, list[float]] = {label: [] for label in labels}
    iterations: dict[str, list[int]] = {label: [] for label in labels}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", es.ConvergenceWarning)
        for scene in variants.values():  # one untimed step each: sparsity patterns, caches
            es.step(scene, states[0], solver=solver)
            for term in scene.terms:
                if isinstance(term, CountingGround):
                    term.ccd_calls = 0
        turn = 0
        for state in states:
            for _ in range(repeats):
                turn += 1
                for label in labels[turn % 3 :] + labels[: turn % 3]:  # rotated order: drifts even out
                    start = time.perf_counter()
                    result = es.step(variants[label], state, solver=solver)
                    times[label].append(time.perf_counter() - start)
                    iterations[label].append(result.stats.iterations)
    baseline = 1e3 * statistics.median(times["no obstacle"])
    rows = []
    for label, scene in variants.items():
        x, v = scene.split_state(states[-1])
        terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
        calls = sum(term.ccd_calls for term in scene.terms if isinstance(term, CountingGround))
        ms = 1e3 * statistics.median(times[label])
        rows.append(
            ObstacleRow(
                tets=scene.mesh.num_elements,
                scene=label,
                terms=" + ".join(type(term).__name__.replace("CountingGround", "Ground") for term in terms),
                ccd_terms=sum(type(term).step_limit is not es.EnergyTerm.step_limit for term in terms),
                ccd_calls_per_step=calls / len(times[label]),
                samples=len(times[label]),
                ms_per_step=ms,
                iterations=statistics.mean(iterations[label]),
                vs_no_obstacle_pct=100 * (ms / baseline - 1),
            )
        )
    return rows


def run_landing(
    size: str,
    steps: int,
    warmup: int,
    tol: float,
    names: list[str],
    first_order_iterations: int,
    budget_s: float,
    youngs_modulus: float,
    repeats: int,
) -> tuple[list[LandingRow], list[dict[str, object]], list[dict[str, object]], list[ObstacleRow]]:
    """Reference landing, every optimizer on the same steps; rows, per-step trace, term costs and
    the comparison with and without an obstacle."""
    cells = LANDING_SIZES[size]
    scene = build_landing_scene(cells, youngs_modulus)
    ground = ground_of(scene)
    reference = es.NewtonCG(tol=REFERENCE_TOL, max_iter=100, strict=True)
    state = landing_start(scene, warmup)
    for _ in range(warmup):  # free fall, not timed
        state = es.step(scene, state, solver=reference).state
    states, reference_stats = [state], []
    for _ in range(steps):
        result = es.step(scene, states[-1], solver=reference)
        states.append(result.state)
        reference_stats.append(result.stats)
    rows, iterations = [], {}
    for name, solver in solvers(tol, first_order_iterations).items():
        if name not in names:
            continue
        times, stats, errors, heights = timed_steps(
            scene, states, steps, solver, budget_s, probe=lambda x: float(ground.signed_distance(x).min())
        )
        iterations[name] = [s.iterations for s in stats]
        rows.append(
            LandingRow(
                tets=scene.mesh.num_elements,
                solver=name,
                steps=len(times),
                ms_per_step=1e3 * statistics.median(times),
                max_iterations=max(iterations[name]),
                **effort(stats),
                min_height_m=min(heights),
                error_m=max(errors),
            )
        )
    trace = []
    for k in range(steps):
        x, _ = scene.split_state(states[k + 1])
        distance = ground.signed_distance(x)
        line = {
            "tets": scene.mesh.num_elements,
            "step": k + 1,
            "time_s": (warmup + k + 1) * scene.dt,
            "min_height_m": float(distance.min()),
            "vertices_in_contact": int((distance < ground.barrier_distance).sum()),
            "reference_iterations": reference_stats[k].iterations,
        }
        for name, counts in iterations.items():
            line[f"{name}_iterations"] = counts[k] if k < len(counts) else ""
        trace.append(line)
    # the last pair of states whose first one is in contact (friction is lagged from it)
    touching = [k for k in range(steps) if ground.lagged_terms(scene.split_state(states[k])[0], scene.dt)]
    if not touching:
        raise RuntimeError("the cube never touched the ground: take more --landing-steps")
    costs = term_costs(scene, states[touching[-1]], states[touching[-1] + 1])
    overhead = obstacle_overhead(cells, youngs_modulus, states[:-1], tol, repeats)
    return rows, trace, costs, overhead


def landing_markdown(
    rows: list[LandingRow],
    trace: list[dict[str, object]],
    costs: list[dict[str, object]],
    overhead: list[ObstacleRow],
    args: argparse.Namespace,
) -> str:
    """The landing's results as markdown tables."""
    scene = build_landing_scene(LANDING_SIZES["tiny"], args.landing_youngs)
    ground = ground_of(scene)
    threads = torch.get_num_threads()
    lines = [
        f"Landing step: a {LANDING_SIDE:g} m cube (E = {args.landing_youngs:g} Pa, ν = 0.3, ρ = 1000 kg/m³) "
        f"falling at {LANDING_SPEED:g} m/s onto `es.Ground(0.0, friction={LANDING_FRICTION:g})` "
        f"(barrier distance d̂ = {ground.barrier_distance:.2e} m), h = 1/60 s, float64, "
        f"{threads} thread{'s' * (threads != 1)}. {args.landing_warmup} reference steps of free fall, then "
        f"{args.landing_steps} timed steps: it lands in the second; the rest cover the rebound and settling. "
        f"tol = {args.tol:g} m/s (velocity residual); error = max |x_(n+1) − x_ref| against Newton–CG at "
        f"{REFERENCE_TOL:g} m/s from the same states; lowest vertex = min over all timed steps of the "
        "height above the ground (> 0: no penetration). Wall times are medians, on a shared machine "
        "(noisy).",
        "",
    ]
    header = ["tets", "optimizer", "median ms/step", "iterations", "max iterations", "grad evals", "HVPs",
              "max residual (m/s)", "converged", "lowest vertex (m)", "max error (m)"]
    lines += table(header, [
        [r.tets, r.solver, f"{r.ms_per_step:.1f}", f"{r.iterations:.1f}", r.max_iterations,
            f"{r.grad_evals:.1f}",
         f"{r.hvps:.1f}", f"{r.residual:.1e}", r.converged, f"{r.min_height_m:.2e}", f"{r.error_m:.1e}"]
        for r in rows
    ], align="rl" + "r" * 9)
    solver_columns = [k for k in trace[0] if k.endswith("_iterations") and k != "reference_iterations"]
    lines += [
        "",
        "Iterations per timed step (the reference's states; vertices in contact: within d̂ of the ground).",
        "",
    ]
    header = ["tets", "step", "t (s)", "lowest vertex (m)", "vertices in contact", "reference iterations",
              *(key.removesuffix("_iterations") + " iterations" for key in solver_columns)]
    lines += table(header, [
        [t["tets"], t["step"], f"{t['time_s']:.3f}", f"{t['min_height_m']:.2e}", t["vertices_in_contact"],
         t["reference_iterations"], *(t[key] for key in solver_columns)]
        for t in trace
    ], align="r" * len(header))
    lines += [
        "",
        "Cost per evaluation of each term alone at a resting state in contact (friction lagged from the "
        "step before); % of the elastic term's cost. CCD and the friction term's construction have no "
        "Hessian; the last two lines are the whole step objective (inertia, gravity, elasticity, and the "
        "contact terms or not), Hessian column = element Hessians + CSR assembly.",
        "",
    ]
    header = ["tets", "term", "energy+gradient (ms)", "% of elastic", "element Hessian blocks (ms)",
        "% of elastic"]
    lines += table(header, [
        [c["tets"], c["term"], f"{c['energy_gradient_ms']:.3f}", f"{c['energy_gradient_pct']:.1f}",
         fixed(c["hessian_ms"], 3), fixed(c["hessian_pct"], 1)]
        for c in costs
    ], align="rlrrrr")
    lines += [
        "",
        f"The same Newton–CG steps (tol {args.tol:g} m/s, from every timed reference state, "
        f"{args.landing_repeats}× each, the three scenes interleaved) without an obstacle, with the ground "
        f"{FAR_BELOW:g} m below (no vertex within d̂) and with the ground at y = 0. Without obstacles "
        "the step objective (`energysim.integrators.adjoint.step_terms`) holds no contact term, and "
        "`Objective.max_step` finds no term that limits a step, so no CCD runs: the scene pays nothing "
        "for contact. An out-of-reach ground adds its (all-zero) barrier to every evaluation, one CCD "
        "per line search and per warm-start candidate, and lets the warm start also try x_n (iteration "
        "counts can differ slightly); friction is built only where a vertex is within d̂.",
        "",
    ]
    header = ["tets", "scene", "step objective terms (at rest)", "terms with CCD", "CCD calls/step",
        "steps timed",
              "median ms/step", "Newton iterations", "vs no obstacle"]
    lines += table(header, [
        [o.tets, o.scene, o.terms, o.ccd_terms, f"{o.ccd_calls_per_step:.1f}", o.samples,
            f"{o.ms_per_step:.1f}",
         f"{o.iterations:.2f}", f"{o.vs_no_obstacle_pct:+.0f}%"]
        for o in overhead
    ], align="rll" + "r" * 6)
    return "\n".join(lines) + "\n"


def landing_plot(rows: list[LandingRow], trace: list[dict[str, object]], path: Path) -> None:
    """ms per step against tet count per optimizer; Newton iterations per timed step per mesh."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r.solver for r in rows):
        mine = [r for r in rows if r.solver == name]
        axes[0].loglog([r.tets for r in mine], [r.ms_per_step for r in mine], "o-", label=name)
    for tets in dict.fromkeys(t["tets"] for t in trace):
        mine = [t for t in trace if t["tets"] == tets]
        steps = [t["step"] for t in mine]
        line = axes[1].plot(steps, [t["reference_iterations"] for t in mine], "--", label=f"{tets} reference")
        if "newton-cg_iterations" in mine[0]:
            counts = [t["newton-cg_iterations"] for t in mine]
            shown = [(s, c) for s, c in zip(steps, counts, strict=True) if c != ""]
            axes[1].plot(
                [s for s, _ in shown],
                [c for _, c in shown],
                "o-",
                color=line[0].get_color(),
                label=f"{tets} newton-cg",
            )
    axes[0].set(xlabel="tets", ylabel="median ms per step", title="Landing: wall time per step")
    axes[1].set(
        xlabel="timed step (lands in step 2)", ylabel="iterations", title="Newton iterations per step"
    )
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    figure.tight_layout()
    save_figure(figure, path)


def cantilever_main(args: argparse.Namespace) -> list[Row]:
    """The cantilever benchmark; writes bench_step.{csv,md,png}."""
    rows, kernels = [], {}
    for size in args.sizes:
        size_rows, timing = run(
            size, args.steps, args.warmup, args.tol, args.solvers, args.first_order_iterations, args.budget
        )
        rows += size_rows
        kernels[size_rows[0].tets] = timing
        for row in size_rows:
            print(row)
    text = markdown(rows, kernels, args.tol)
    print(text)
    write_outputs(args.out, "bench_step", rows, text, None if args.no_plot else lambda path: plot(rows, path))
    return rows


def landing_main(args: argparse.Namespace) -> list[LandingRow]:
    """The landing benchmark; writes bench_step_landing.{csv,md,png} and _{trace,terms,obstacles}.csv."""
    rows, trace, costs, overhead = [], [], [], []
    for size in args.sizes:
        size_rows, size_trace, size_costs, size_overhead = run_landing(
            size,
            args.landing_steps,
            args.landing_warmup,
            args.tol,
            args.solvers,
            args.first_order_iterations,
            args.budget,
            args.landing_youngs,
            args.landing_repeats,
        )
        rows += size_rows
        trace += size_trace
        costs += size_costs
        overhead += size_overhead
        for row in size_rows + size_overhead:
            print(row)
    text = landing_markdown(rows, trace, costs, overhead, args)
    print(text)
    plotter = None if args.no_plot else lambda path: landing_plot(rows, trace, path)
    write_outputs(args.out, "bench_step_landing", rows, text, plotter)
    write_csv(args.out / "bench_step_landing_trace.csv", trace)
    write_csv(args.out / "bench_step_landing_terms.csv", costs)
    write_csv(args.out / "bench_step_landing_obstacles.csv", overhead)
    return rows


def main(argv: list[str] | None = None) -> list[Row | LandingRow]:
    parser = make_parser(__doc__, "bench_step", threads=None)
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=["cantilever"],
        choices=["cantilever", "landing"],
        help="which benchmarks",
    )
    parser.add_argument("--sizes", nargs="+", default=["1k", "10k", "50k"], choices=list(SIZES))
    parser.add_argument("--solvers", nargs="+", default=list(solvers(1.0, 1)), choices=list(solvers(1.0, 1)))
    parser.add_argument("--steps", type=int, default=5, help="timed steps per optimizer")
    parser.add_argument("--warmup", type=int, default=10, help="reference steps before the timed ones")
    parser.add_argument("--tol", type=float, default=1e-5, help="velocity residual, m/s")
    parser.add_argument(
        "--first-order-iterations", type=int, default=1000, help="max_iter of Adam and L-BFGS"
    )
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per optimizer and size, at most")
    parser.add_argument("--landing-steps", type=int, default=12, help="timed steps of the landing")
    parser.add_argument("--landing-warmup", type=int, default=2, help="free-fall steps before them")
    parser.add_argument("--landing-youngs", type=float, default=1e5, help="the cube's Young's modulus, Pa")
    parser.add_argument(
        "--landing-repeats", type=int, default=3, help="repeats per state of the with/without-obstacle steps"
    )
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    args = parser.parse_args(argv)
    configure_threads(args.threads, retain_memory=False)
    rows: list[Row | LandingRow] = []
    if "cantilever" in args.scenes:
        rows += cantilever_main(args)
    if "landing" in args.scenes:
        rows += landing_main(args)
    return rows


if __name__ == "__main__":
    main()
