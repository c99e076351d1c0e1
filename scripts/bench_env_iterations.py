"""Where the implicit env's Newton iterations come from: one random-action batch, the solver and the
contact model varied one at a time.

Each variant is a `CreatureVectorEnv` of B creatures (compiled unless `--eager`, frame_skip 1,
h = 1/60 s, the env's body model), reset with seed 0 and driven by the same uniformly random
actions. After `--warmup` untimed steps, the variants' `--steps` timed step calls are interleaved,
so a slow moment of a shared machine falls on all of them alike. The variants:

- `default`: the env as shipped (tol 1e-4 m/s, ε_v = 5e-3 m/s, d̂ = 3e-3 × the body's
  bounding-box diagonal, κ by the ground's rule);
- `d_hat 1e-3 diag`: the barrier's range d̂ of the `Ground` default, 1e-3 × the diagonal (the env's
  before it took 3e-3);
- `tol 1e-2`: the solver's tolerance loosened 100×;
- `eps_v 1e-2`: the friction smoothing doubled;
- `kappa x10`, `kappa x100`: a stiffer barrier, so that the bodies rest closer to d̂;
- `no contact`: the ground moved 5 m down after the reset, so the bodies fall freely through every
  timed step (the muscles and the body's own nonlinearity alone).

Per variant: the Newton iterations per step (each entry's own count, averaged), the median wall time
of a step call, the largest velocity residual left and, except without contact, the suggested gait's
forward distance in 2 s by one creature of that variant (how much the variant changes the physics).
For the default it also reports how far the contact gaps move in one step: quantiles of
log10(d_{n+1} / d_n) over the vertices within the barrier's range d̂ at either end.

Every variant compiles its own graphs in this one process, so Dynamo's limit on graphs per
function is raised here; past it a function would fall back to eager evaluation silently.

Run:  python scripts/bench_env_iterations.py --out docs/benchmarks/bench_env_iterations
      python scripts/bench_env_iterations.py --variants default "d_hat 1e-3 diag"   (a subset)
Writes: <out>/bench_env_iterations.csv, .md (the table) and .png.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from _bench import configure_threads, make_parser, pyplot, save_figure, table, write_outputs
from bench_env import GAIT_SECONDS, gait_distance

from energysim.contact.obstacle_term import BARRIER_DISTANCE_FRACTION
from energysim.creatures import CREATURES, load_creature
from energysim.envs import CreatureVectorEnv
from energysim.envs.core import CreatureSimulation

# a change to a built simulation (applied before its first step, so no compiled graph holds the old value)
Adjust = Callable[[CreatureSimulation], None]


def _scale_barrier(factor: float) -> Adjust:
    def adjust(simulation: CreatureSimulation) -> None:
        with torch.no_grad():
            simulation.ground.barrier_stiffness.mul_(factor)

    return adjust


def _lower_ground(simulation: CreatureSimulation) -> None:
    with torch.no_grad():
        simulation.ground.offset.sub_(5.0)


def _ground_default_range(creature: str) -> dict:
    # the `Ground` default d̂ (a fraction of the rest bounding-box diagonal)
    low, high = load_creature(creature).mesh.bounding_box()
    return {"barrier_distance": BARRIER_DISTANCE_FRACTION * float((high - low).norm())}


@dataclass(frozen=True)
class Variant:
    """One configuration: env options (or a function of the creature that gives them), a change to
    the built simulation, a change after the reset."""

    name: str
    options: dict | Callable[[str], dict] = field(default_factory=dict)
    built: Adjust | None = None
    after_reset: Adjust | None = None
    walks: bool = True

    def options_for(self, creature: str) -> dict:
        """The env options of this variant for `creature`."""
        return self.options(creature) if callable(self.options) else dict(self.options)


VARIANTS = (
    Variant("default"),
    Variant("d_hat 1e-3 diag", _ground_default_range),
    Variant("tol 1e-2", {"solver_tol": 1e-2}),
    Variant("eps_v 1e-2", {"friction_smoothing": 1e-2}),
    Variant("kappa x10", built=_scale_barrier(10.0)),
    Variant("kappa x100", built=_scale_barrier(100.0)),
    Variant("no contact", after_reset=_lower_ground, walks=False),
)


@dataclass(frozen=True)
class Row:
    """One variant's line of the table."""

    variant: str
    creature: str
    batch: int
    steps: int
    newton_iterations: float
    ms_per_call: float
    solver_residual: float
    gait_distance: float


def contact_distances(env: CreatureVectorEnv) -> np.ndarray:
    """The ground's signed distance of every vertex of every entry, `[B, n]`, in m."""
    simulation = env.simulation
    positions = simulation.scene.split_state(env.states)[0]
    return simulation.ground.signed_distance(simulation.ground.vertex_positions(positions)).numpy()


def run(
    creature: str,
    batch: int,
    steps: int,
    warmup: int,
    gait: bool,
    compiled: bool = True,
    variants: tuple[Variant, ...] = VARIANTS,
) -> tuple[list[Row], np.ndarray]:
    """Every variant's row, and the first variant's per-step log10 gap ratios of the vertices in
    contact."""
    envs = []
    for variant in variants:
        env = CreatureVectorEnv(batch, creature, solver_compile=compiled, **variant.options_for(creature))
        if variant.built is not None:
            variant.built(env.simulation)
        env.reset(seed=0)
        env.action_space.seed(0)
        if variant.after_reset is not None:
            variant.after_reset(env.simulation)
        for _ in range(warmup):
            env.step(env.action_space.sample())
        envs.append(env)
    walls = [[] for _ in variants]
    iterations = [[] for _ in variants]
    residuals = [[0.0] for _ in variants]
    ratios = []
    reach = envs[0].simulation.ground.barrier_distance
    for _ in range(steps):
        for index, env in enumerate(envs):
            before = contact_distances(env) if index == 0 else None
            actions = env.action_space.sample()
            start = time.perf_counter()
            _, _, _, _, info = env.step(actions)
            walls[index].append(time.perf_counter() - start)
            stepped = info["_solver_iterations"]
            iterations[index].append(float(info["solver_iterations"][stepped].mean()))
            residuals[index].append(float(info["solver_residual"][stepped].max()))
            if before is not None:
                after = contact_distances(env)
                near = (before < reach) | (after < reach)
                ratios.append(np.log10(after[near] / before[near]))
    rows = []
    for index, variant in enumerate(variants):
        distance = float("nan")
        if gait and variant.walks:
            options = {"solver_compile": compiled, **variant.options_for(creature)}
            distance = gait_distance(creature, options, "cpu", GAIT_SECONDS, prepare=variant.built)
        rows.append(
            Row(
                variant=variant.name,
                creature=creature,
                batch=batch,
                steps=steps,
                newton_iterations=statistics.fmean(iterations[index]),
                ms_per_call=1e3 * statistics.median(walls[index]),
                solver_residual=max(residuals[index]),
                gait_distance=distance,
            )
        )
        print(f"{variant.name}: {rows[-1].newton_iterations:.2f} Newton its, {rows[-1].ms_per_call:.0f} ms")
    return rows, np.concatenate(ratios)


QUANTILES = (0.01, 0.1, 0.5, 0.9, 0.99)


def markdown(rows: list[Row], ratios: np.ndarray, threads: int, compiled: bool = True) -> str:
    """The table, and the default's gap ratios."""
    first = rows[0]
    evaluations = "compiled" if compiled else "eager"
    lines = [
        f"{first.creature}, B = {first.batch}, {evaluations}, random actions (seed 0) through the env's "
        f"activation dynamics, h = 1/60 s, {threads} thread(s); {first.steps} interleaved step calls per "
        "variant. Newton its: each entry's own count per step, averaged. Gait: the suggested gait's forward "
        "distance in 2 s, one creature of the variant.",
        "",
    ]
    lines += table(
        ["variant", "Newton its/step", "median ms/call", "largest residual (m/s)", "gait distance (m)"],
        [
            [r.variant, f"{r.newton_iterations:.2f}", f"{r.ms_per_call:.0f}", f"{r.solver_residual:.1e}",
             "–" if np.isnan(r.gait_distance) else f"{r.gait_distance:.5f}"]
            for r in rows
        ],
    )
    values = np.quantile(ratios, QUANTILES)
    spread = ", ".join(f"{q:g}: {v:+.2f}" for q, v in zip(QUANTILES, values, strict=True))
    lines += [
        "",
        f"{first.variant}: how far the contact gaps move in one step, log10(d_n+1 / d_n) over {ratios.size} "
        f"vertex-steps within d̂ at either end; quantiles {spread}.",
    ]
    return "\n".join(lines) + "\n"


def plot(rows: list[Row], path: Path) -> None:
    """Newton iterations and wall time per step, one bar pair per variant."""
    plt = pyplot()
    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    names = [r.variant for r in rows]
    left.barh(names, [r.newton_iterations for r in rows])
    left.set(xlabel="Newton iterations per step (entries' mean)")
    right.barh(names, [r.ms_per_call for r in rows])
    right.set(xlabel="median ms per step call")
    right.set_yticklabels([])
    figure.suptitle(f"{rows[0].creature}, B = {rows[0].batch}: what the Newton iterations depend on")
    figure.tight_layout()
    save_figure(figure, path)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = make_parser(__doc__, "bench_env_iterations", out=Path("docs/benchmarks"))
    parser.add_argument("--creature", default="worm", choices=CREATURES)
    parser.add_argument("--batch-size", type=int, default=64, help="B")
    parser.add_argument("--steps", type=int, default=8, help="timed step calls per variant")
    parser.add_argument("--warmup", type=int, default=8, help="untimed step calls first (compiles)")
    parser.add_argument("--no-gait", action="store_true", help="skip the gait distances")
    parser.add_argument("--eager", action="store_true", help="eager evaluations instead of compiled ones")
    names = [variant.name for variant in VARIANTS]
    parser.add_argument(
        "--variants", nargs="+", default=names, choices=names, metavar="NAME",
        help=f"the variants to run, in this order (default all: {', '.join(names)})",
    )
    args = parser.parse_args(argv)
    if args.batch_size < 1 or args.steps < 1 or args.warmup < 0 or args.threads < 1:
        parser.error("--batch-size, --steps and --threads must be >= 1 and --warmup >= 0")
    configure_threads(args.threads)
    compiled = not args.eager
    variants = tuple(VARIANTS[names.index(name)] for name in args.variants)
    # each variant's envs compile their own graphs (one per batch size their compaction meets)
    dynamo = torch._dynamo.config
    limit = "recompile_limit" if hasattr(dynamo, "recompile_limit") else "cache_size_limit"  # torch < 2.6
    setattr(dynamo, limit, max(getattr(dynamo, limit), 16 * len(variants)))
    rows, ratios = run(
        args.creature, args.batch_size, args.steps, args.warmup, not args.no_gait, compiled, variants
    )
    text = markdown(rows, ratios, args.threads, compiled)
    print(text)
    write_outputs(
        args.out,
        "bench_env_iterations",
        rows,
        text,
        None if args.no_plot else lambda path: plot(rows, path),
    )
    return rows


if __name__ == "__main__":
    main()
