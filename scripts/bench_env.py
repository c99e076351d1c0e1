"""Benchmark the batched creature environments: env steps per second against the batch size B.

For each creature and B, a `CreatureVectorEnv` (frame_skip 1, h = 1/60 s, the registered defaults
otherwise) is reset with seed 0 and stepped with uniformly random actions (the action space seeded
with 0): `--warmup` steps untimed, then `--steps` timed `step` calls. Env steps per second are
B / (median wall time of one call); the spread beside it is the interquartile range of the calls.
Random activations switch every muscle at every step, which is harder for the solver than a
gait: the Newton iterations per step are in the table. `--activation-time-constant` τ (s) turns on
the env's first-order activation dynamics, which low-pass the random commands before the muscles see
them. `--compile` evaluates the step objective by compiled functions (`solver_compile=True`); its
compilation happens in the untimed warm-up steps, so give it a few (`--warmup 10`). Runs use
`--threads` intra-op threads (default 1, best for meshes this small on a shared
machine). `--integrator leapfrog` steps the env's explicit physics (`CreatureEnvConfig`: substeps
from the Courant limit, the ground as an inelastic contact with Coulomb friction), `--integrator
both` the implicit and the explicit env of the same body model side by side, with their ratio;
their timed calls are taken in `--turns` turns (a slow moment of a shared machine then falls on both
alike), each turn after one untimed call (whose caches the other env's data had filled). The ratio
of their rates comes with its range over the turns (each turn's ratio of median step times), the
error of the ratio that the machine's drift leaves.
Beside each implicit run: the largest velocity residual a solve left (m/s).

Every speed comes with an error: the suggested open-loop gait (the creature's sine, through the
same activation dynamics) is walked for 2 s by one env of the benchmarked configuration and by a
reference of the same model four times finer in time (the implicit step at h/4 with frame_skip 4;
the leapfrog at 4× the substeps). The table gives the reference's forward distance of the centre of
mass and the configuration's error against it (the reference in float64 also for `--dtype float32`).

Run:  python scripts/bench_env.py                                    # worm and quadruped, B = 1, 16, 64
      python scripts/bench_env.py --creatures worm --batch-sizes 1 4 --steps 3 --no-plot   # quick
      python scripts/bench_env.py --profile                          # also where the time goes
      python scripts/bench_env.py --activation-time-constant 0.05    # muscles with τ = 50 ms
      python scripts/bench_env.py --compile --warmup 10 --out docs/benchmarks/bench_env_compiled
      python scripts/bench_env.py --integrator leapfrog --compile --warmup 3 --steps 40 \
          --out docs/benchmarks/bench_env_leapfrog                   # the explicit env
      python scripts/bench_env.py --creatures worm --batch-sizes 64 --integrator both --compile \
          --warmup 10 --steps 20 --out docs/benchmarks/bench_env_both    # both envs side by side
      python scripts/bench_env.py --creatures worm --batch-sizes 64 --integrator both --compile \
          --warmup 10 --steps 256 --turns 16 --out docs/benchmarks/bench_env_both_256_steps   # longer
      python scripts/bench_env.py --creatures worm --batch-sizes 64 --compile --warmup 10 \
          --steps 20 --solver-tol 1e-2 --out docs/benchmarks/bench_env_tol1e-2   # a looser tolerance
      python scripts/bench_env.py --integrator leapfrog --compile --warmup 3 --steps 40 \
          --dtype float32 --out docs/benchmarks/bench_env_leapfrog_float32
Writes: <out>/bench_env.csv, <out>/bench_env.md (the table) and <out>/bench_env.png.
"""

from __future__ import annotations

import cProfile
import dataclasses
import io
import math
import pstats
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from _bench import configure_threads, make_parser, pyplot, quartiles, save_figure, table, write_outputs

from energysim.creatures import CREATURES
from energysim.envs import CreatureEnv, CreatureVectorEnv
from energysim.envs.config import CreatureEnvConfig
from energysim.envs.core import CreatureSimulation

# the rate the project aims at: the batched worm at B = 64 on 2 CPU cores
TARGET_STEPS_PER_SECOND = 1000.0
# the implicit env's documented tolerance, m/s
SOLVER_TOL = CreatureEnvConfig.solver_tol
# turns the envs of one creature and B take at their timed calls (`bench`), by default
TURNS = 4


@dataclass(frozen=True)
class Row:
    """One (creature, B) line of the table."""

    creature: str
    batch: int
    device: str
    steps: int
    ms_per_call: float
    ms_per_call_iqr: float
    env_steps_per_second: float
    env_steps_per_second_low: float
    env_steps_per_second_high: float
    newton_iterations: float
    failures: int
    activation_time_constant: float | None = None
    compiled: bool = False
    integrator: str = "implicit_euler"
    substeps: int = 1
    dtype: str = "float64"
    gait_seconds: float = float("nan")
    gait_distance_reference: float = float("nan")
    gait_distance_error: float = float("nan")
    solver_residual: float = float("nan")
    solver_budget: int | None = None
    solver_tol: float = SOLVER_TOL
    # the median ms per call in each turn the envs took, space-separated (`bench`)
    turn_ms_per_call: str = ""


@dataclass
class Timed:
    """One env under timing and what its step calls reported."""

    env: CreatureVectorEnv
    integrator: str
    walls: list[float] = field(default_factory=list)
    turn_walls: list[list[float]] = field(default_factory=list)
    iterations: list[float] = field(default_factory=list)
    residuals: list[float] = field(default_factory=lambda: [0.0])
    failures: int = 0


def bench(
    creature: str,
    batch: int,
    steps: int,
    warmup: int,
    device: str,
    profile: bool,
    activation_time_constant: float | None = None,
    compile_objective: bool = False,
    integrators: Sequence[str] = ("implicit_euler",),
    dtype: str = "float64",
    solver_budget: int | None = None,
    solver_tol: float = SOLVER_TOL,
    turns: int = TURNS,
) -> list[Row]:
    """Time `steps` calls of a batched env of `batch` creatures per integrator of `integrators`,
    the envs taking `turns` turns, so that a slow moment of a shared machine falls on every env alike
    (activation dynamics with time constant `activation_time_constant` in s, None: the env's
    default; compiled objective evaluations with `compile_objective`); one table row per env,
    without the gait's error (`gait_error`). `solver_budget`: the implicit env's fixed Newton budget
    per step; `solver_tol`: its velocity-residual tolerance, m/s."""
    timed = []
    for integrator in integrators:
        env = CreatureVectorEnv(
            batch,
            creature,
            frame_skip=1,
            dt=1 / 60,
            device=device,
            activation_time_constant=activation_time_constant,
            solver_compile=compile_objective,
            integrator=integrator,
            dtype=getattr(torch, dtype),
            solver_budget=solver_budget if integrator != "leapfrog" else None,
            solver_tol=solver_tol,
        )
        env.reset(seed=0)
        env.action_space.seed(0)
        for _ in range(warmup):
            env.step(env.action_space.sample())
        timed.append(Timed(env, integrator))
    profiler = cProfile.Profile() if profile else None
    # the envs take turns in blocks, each block after one untimed call: an env's first call after
    # another's finds the caches full of the other's data (the explicit env's step was 15-20 % slower
    # right after an implicit one's than in a run of its own)
    rounds = min(turns, steps) if len(timed) > 1 else 1
    for turn in range(rounds):
        for run in timed:
            if len(timed) > 1:
                run.env.step(run.env.action_space.sample())
            start = len(run.walls)
            for _ in range(steps // rounds + (turn < steps % rounds)):
                _time_step(run, device, profiler)
            run.turn_walls.append(run.walls[start:])
    if profiler is not None:
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(15)
        print(f"--- profile: {creature}, B = {batch}, {steps} calls per env ---\n{text.getvalue()}")
    return [_row(run, creature, batch, device, steps, compile_objective, dtype) for run in timed]


def _time_step(run: Timed, device: str, profiler: cProfile.Profile | None) -> None:
    # one timed step call of random actions, and what it reported
    actions = run.env.action_space.sample()
    if profiler is not None:
        profiler.enable()
    start = time.perf_counter()
    _, _, terminated, _, info = run.env.step(actions)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    run.walls.append(time.perf_counter() - start)
    if profiler is not None:
        profiler.disable()
    stepped = info.get("_solver_iterations", np.zeros(run.env.num_envs, dtype=bool))
    if stepped.any():
        run.iterations.append(float(info["solver_iterations"][stepped].mean()))
        run.residuals.append(float(info["solver_residual"][stepped].max()))
    run.failures += int(terminated.sum())


def _row(run: Timed, creature: str, batch: int, device: str, steps: int, compiled: bool, dtype: str) -> Row:
    # the table row of one timed env
    timing = quartiles(run.walls)
    low, median, high = timing.low, timing.median, timing.high
    print(
        f"{creature} B={batch} {run.integrator}: {steps} calls, median {1e3 * median:.1f} ms = "
        f"{batch / median:.1f} env steps/s"
    )
    env = run.env
    return Row(
        creature=creature,
        batch=batch,
        device=device,
        steps=steps,
        ms_per_call=1e3 * median,
        ms_per_call_iqr=1e3 * (high - low),
        env_steps_per_second=batch / median,
        env_steps_per_second_low=batch / high,
        env_steps_per_second_high=batch / low,
        newton_iterations=statistics.fmean(run.iterations) if run.iterations else float("nan"),
        failures=run.failures,
        activation_time_constant=env.config.time_constant,
        compiled=compiled,
        integrator=run.integrator,
        substeps=env.simulation.scene.substeps,
        dtype=dtype,
        solver_residual=max(run.residuals) if run.integrator != "leapfrog" else float("nan"),
        solver_budget=env.config.solver_budget,
        solver_tol=env.config.solver_tol,
        turn_ms_per_call=" ".join(f"{1e3 * statistics.median(walls):.3f}" for walls in run.turn_walls),
    )


GAIT_SECONDS = 2.0


def gait_distance(
    creature: str,
    options: dict,
    device: str,
    seconds: float,
    dt: float = 1 / 60,
    frame_skip: int = 1,
    prepare: Callable[[CreatureSimulation], None] | None = None,
) -> float:
    """Forward distance (m) of the centre of mass after `seconds` of the creature's suggested gait,
    sampled at every env step of frame_skip·dt, in one `CreatureEnv` with `options`; `prepare`
    changes its simulation before the reset."""
    env = CreatureEnv(creature, dt=dt, frame_skip=frame_skip, device=device, reset_noise_scale=0.0, **options)
    if prepare is not None:
        prepare(env.simulation)
    _, info = env.reset(seed=0)
    start = info["x_position"]
    creature_data = env.simulation.creature
    frame = dt * frame_skip
    for k in range(round(seconds / frame)):
        action = creature_data.gait_action(k * frame).numpy().astype(np.float32)
        _, _, terminated, _, info = env.step(action)
        if terminated:
            return float("nan")
    return info["x_position"] - start


def gait_error(row: Row, device: str, seconds: float = GAIT_SECONDS) -> Row:
    """`row` with its gait's reference distance and error: the same model four times finer in time,
    in float64 whatever the row's precision."""
    options = {
        "solver_budget": row.solver_budget,
        "solver_tol": row.solver_tol,
        "activation_time_constant": row.activation_time_constant,
        "integrator": row.integrator,
        "solver_compile": row.compiled,
        "dtype": getattr(torch, row.dtype),
    }
    # the reference solves every step to the env's tolerance (or the row's, if finer), whatever
    # budget the row had
    exact = {
        **options,
        "dtype": torch.float64,
        "solver_budget": None,
        "solver_tol": min(row.solver_tol, SOLVER_TOL),
    }
    if row.integrator == "leapfrog":
        measured = gait_distance(row.creature, {**options, "substeps": row.substeps}, device, seconds)
        reference = gait_distance(row.creature, {**exact, "substeps": 4 * row.substeps}, device, seconds)
    else:
        measured = gait_distance(row.creature, options, device, seconds)
        reference = gait_distance(row.creature, exact, device, seconds, dt=1 / 240, frame_skip=4)
    print(f"{row.creature} gait: {measured:.5f} m in {seconds:g} s, reference {reference:.5f} m")
    return dataclasses.replace(
        row,
        gait_seconds=seconds,
        gait_distance_reference=reference,
        gait_distance_error=abs(measured - reference),
    )


def activation_text(time_constant: float | None) -> str:
    """How the table's caption names the activation dynamics of a run."""
    if not time_constant:
        return "no activation dynamics (the action is the activation)"
    return f"activation dynamics with τ = {time_constant:g} s (random commands, filtered)"


PHYSICS = {
    "leapfrog": "explicit leapfrog substeps (the ground an inelastic contact with Coulomb friction)",
    "implicit_euler": (
        "implicit_euler, Newton–CG (tol {tol:g} m/s, indefinite Hessians shifted, the IPC ground)"
    ),
}


def gait_caption(seconds: float) -> str:
    """What the gait columns hold: the error against a finer reference, or that the gait was not walked
    (`--no-gait`)."""
    if math.isnan(seconds):
        return "The gait was not walked (`--no-gait`): no gait error."
    return (
        f"Gait error: the suggested gait's forward distance in {seconds:g} s against the same "
        "model four times finer in time, in float64 (the reference's distance beside it)."
    )


def _number(value: float, spec: str) -> str:
    # a table cell: blank where the value was not measured (NaN)
    return "" if math.isnan(value) else format(value, spec)


def markdown(rows: list[Row], threads: int) -> str:
    """The results as a markdown table, the envs side by side when both were run."""
    dynamics = activation_text(rows[0].activation_time_constant)
    evaluations = "compiled evaluations" if rows[0].compiled else "eager evaluations"
    budget = next((r.solver_budget for r in rows if r.solver_budget is not None), None)
    tol = next((r.solver_tol for r in rows if r.integrator != "leapfrog"), SOLVER_TOL)
    texts = {name: text.format(tol=tol) for name, text in PHYSICS.items()}
    if budget is not None:
        texts["implicit_euler"] += (
            f", a fixed budget of at most {budget} Newton iterations per step (the residual it leaves "
            "in the table; the gait's reference is solved to the tolerance)"
        )
    physics = "; ".join(texts[name] for name in dict.fromkeys(r.integrator for r in rows))
    lines = [
        f"Batched creature environments (`CreatureVectorEnv`), frame_skip 1, h = 1/60 s, {rows[0].dtype}, "
        f"one body model (η = 30 Pa·s, μ = 0.8), {physics}, {evaluations}, random actions (seed 0), "
        f"{dynamics}, {threads} thread(s), device {rows[0].device}. "
        "Env steps/s = B / median wall time of one `step` call; the range is from the calls' "
        f"interquartile range{_turns_text(rows)}. Work: leapfrog substeps per physics step, or Newton "
        "iterations per physics step (the mean over the entries of each one's own count; the batched "
        "solve runs as many as its slowest entry) with the largest velocity residual a solve left. "
        + gait_caption(rows[0].gait_seconds),
        "",
    ]
    header = ["creature", "B", "integrator", "calls", "median ms/call (IQR)", "env steps/s (IQR range)",
              "work/step", "residual (m/s)", "failures", "gait distance, reference (m)", "gait error (m)"]
    lines += table(header, [
        [r.creature, r.batch, r.integrator, r.steps, f"{r.ms_per_call:.1f} ({r.ms_per_call_iqr:.1f})",
         f"{r.env_steps_per_second:.1f} ({r.env_steps_per_second_low:.1f}–{r.env_steps_per_second_high:.1f})",
         f"{r.substeps} substeps" if r.integrator == "leapfrog" else f"{r.newton_iterations:.1f} Newton",
         "" if r.integrator == "leapfrog" else f"{r.solver_residual:.1e}", r.failures,
         _number(r.gait_distance_reference, ".4f"), _number(r.gait_distance_error, ".1e")]
        for r in rows
    ])
    implicit = {(r.creature, r.batch): r for r in rows if r.integrator != "leapfrog"}
    explicit = {(r.creature, r.batch): r for r in rows if r.integrator == "leapfrog"}
    for key in (key for key in implicit if key in explicit):  # in the table's order
        ratio = explicit[key].env_steps_per_second / implicit[key].env_steps_per_second
        low, high = turn_ratio_range(implicit[key], explicit[key])
        lines.append(
            f"\n{key[0]}, B = {key[1]}: the explicit env is {ratio:.2f}× the implicit env's rate "
            f"({low:.2f}–{high:.2f}× turn by turn)."
        )
    return "\n".join(lines) + "\n"


def _turns_text(rows: list[Row]) -> str:
    # how the envs of one creature and B shared the machine, where more than one ran
    if len({r.integrator for r in rows}) < 2:
        return ""
    return f"; the envs of one creature and B took turns, {len(rows[0].turn_ms_per_call.split())} each"


def turn_ratio_range(implicit: Row, explicit: Row) -> tuple[float, float]:
    """The smallest and largest ratio of the implicit env's median step time to the explicit env's
    over the turns they took (`bench`): how far the machine's drift moves the ratio of their rates."""
    slow, fast = implicit.turn_ms_per_call.split(), explicit.turn_ms_per_call.split()
    ratios = [float(one) / float(other) for one, other in zip(slow, fast, strict=True)]
    return min(ratios), max(ratios)


def plot(rows: list[Row], path: Path) -> None:
    """Env steps per second against B, one line per creature, with the target."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6, 4))
    for creature in dict.fromkeys(r.creature for r in rows):
        mine = [r for r in rows if r.creature == creature]
        batches = [r.batch for r in mine]
        rate = np.array([r.env_steps_per_second for r in mine])
        spread = np.array(
            [
                [r.env_steps_per_second - r.env_steps_per_second_low for r in mine],
                [r.env_steps_per_second_high - r.env_steps_per_second for r in mine],
            ]
        )
        axis.errorbar(batches, rate, yerr=spread, marker="o", capsize=3, label=creature)
    axis.axhline(
        TARGET_STEPS_PER_SECOND, color="black", linestyle="--", linewidth=1, label="target (worm, B = 64)"
    )
    axis.set(xscale="log", yscale="log", xlabel="batch size B", ylabel="env steps per second")
    axis.set_title(f"Batched env throughput, {rows[0].device}")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend()
    figure.tight_layout()
    save_figure(figure, path)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = make_parser(__doc__, "bench_env", out=Path("docs/benchmarks"))
    parser.add_argument("--creatures", nargs="+", default=["worm", "quadruped"], choices=CREATURES)
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[1, 16, 64], help="values of B")
    parser.add_argument("--steps", type=int, default=5, help="timed step calls per (creature, B)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed step calls first")
    default_device = "cuda" if torch.cuda.is_available() else "cpu"
    parser.add_argument("--device", default=default_device, help=f"torch device (default {default_device})")
    parser.add_argument("--profile", action="store_true", help="print cProfile's top functions per run")
    parser.add_argument(
        "--activation-time-constant",
        type=float,
        default=None,
        help="τ in s of the env's activation dynamics (default: the body model's, 0.05 s; 0: none)",
    )
    parser.add_argument(
        "--compile", action="store_true", help="compiled objective evaluations (compile in --warmup)"
    )
    parser.add_argument(
        "--integrator",
        default="implicit_euler",
        choices=["implicit_euler", "leapfrog", "both"],
        help="the env's integrator (leapfrog: explicit substeps, use with --compile; both: side by side)",
    )
    parser.add_argument(
        "--dtype", default="float64", choices=["float64", "float32"], help="the simulation's precision"
    )
    parser.add_argument(
        "--solver-budget",
        type=int,
        default=None,
        help="the implicit env's fixed Newton budget per physics step (default: solve to the tolerance)",
    )
    parser.add_argument(
        "--solver-tol",
        type=float,
        default=SOLVER_TOL,
        help=f"the implicit env's velocity-residual tolerance, m/s (default {SOLVER_TOL:g})",
    )
    parser.add_argument(
        "--turns", type=int, default=TURNS, help=f"turns the envs take with --integrator both ({TURNS})"
    )
    parser.add_argument("--no-gait", action="store_true", help="skip the gait's error (the slow part)")
    parser.add_argument(
        "--gait-seconds", type=float, default=GAIT_SECONDS, help="simulated time of the gait's error run, s"
    )
    args = parser.parse_args(argv)
    if min(args.batch_sizes) < 1 or args.steps < 1 or args.warmup < 0 or args.threads < 1 or args.turns < 1:
        parser.error("batch sizes, --steps, --turns and --threads must be >= 1 and --warmup >= 0")
    tau = args.activation_time_constant
    if tau is not None and not (np.isfinite(tau) and tau >= 0):
        parser.error(f"--activation-time-constant must be a finite number >= 0, got {tau}")
    if args.solver_budget is not None and args.solver_budget < 1:
        parser.error(f"--solver-budget must be an integer >= 1, got {args.solver_budget}")
    if not (np.isfinite(args.solver_tol) and args.solver_tol > 0):
        parser.error(f"--solver-tol must be a finite number > 0 m/s, got {args.solver_tol}")
    configure_threads(args.threads)
    integrators = ["implicit_euler", "leapfrog"] if args.integrator == "both" else [args.integrator]
    rows = [
        row
        for creature in args.creatures
        for batch in args.batch_sizes
        for row in bench(
            creature,
            batch,
            args.steps,
            args.warmup,
            args.device,
            args.profile,
            tau,
            args.compile,
            integrators,
            args.dtype,
            args.solver_budget,
            args.solver_tol,
            args.turns,
        )
    ]
    if not args.no_gait:
        # one gait per creature and integrator: the physics does not depend on B
        errors = {
            (creature, integrator): gait_error(
                next(r for r in rows if (r.creature, r.integrator) == (creature, integrator)),
                args.device,
                args.gait_seconds,
            )
            for creature in args.creatures
            for integrator in integrators
        }
        rows = [
            dataclasses.replace(
                r,
                gait_seconds=args.gait_seconds,
                gait_distance_reference=errors[r.creature, r.integrator].gait_distance_reference,
                gait_distance_error=errors[r.creature, r.integrator].gait_distance_error,
            )
            for r in rows
        ]
    text = markdown(rows, args.threads)
    print(text)
    write_outputs(args.out, "bench_env", rows, text, None if args.no_plot else lambda path: plot(rows, path))
    return rows


if __name__ == "__main__":
    main()
