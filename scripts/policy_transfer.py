"""Policy transfer between the implicit and the explicit creature env: a PPO policy trained by
`train_ppo.py` on one integrator's env, evaluated on its own env and on the other's.

The two envs are two discretisations of one body model (`energysim.envs.config`): the implicit env
(Newton solves, IPC barrier ground, smoothed lagged friction) and the explicit env (leapfrog
substeps, inelastic ground projection, Coulomb friction), with the same viscosity, friction and
creature. The deterministic policy (the mean action, `train_ppo.controller`, behind the run's own
clock features and activation filter) runs the fixed evaluation episodes (`_training.evaluate`) in
- its own env and the other env at the defaults it was trained with (h = 1/60 s, frame_skip 1, the
  run's solver tolerance and Newton budget, `--solver-budget`; leapfrog: the stable substep count at
  rest);
- both envs at finer settings, labelled "converged" (`CONVERGED`): implicit with h = 1/240 s ×
  frame_skip 4 at a solver tolerance of 1e-6 m/s with no Newton budget, explicit with 128
  substeps. These resolve a slow crawl. A fast gait needs a much smaller implicit step
  (docs/training.md): `--implicit-frame-skip k` sets it to 1/(60·k) s. The env step stays 1/60 s,
  so the policy's clock, filter and reward are the same.

The retention ratio is the return on the other env over the return on its own env at the same
settings (default with default, converged with converged); it is undefined (NaN) where the own
return is not positive. The first episode's centre-of-mass trace (height above the ground, forward
position and velocity per env step) of every case goes to ``trace.csv``: where a policy loses its
return on the other env, the traces show how its gait differs there.

Run:  python scripts/policy_transfer.py --model out/train_ppo_leapfrog/model.zip --out out/policy_transfer
      python scripts/policy_transfer.py --model MODEL --skip-converged      # the default settings only
      python scripts/policy_transfer.py --model MODEL --implicit-frame-skip 64   # implicit h = 1/3840 s
      python scripts/policy_transfer.py --model MODEL --quick --out /tmp/t   # 4-step episodes
Writes to --out: policy_transfer.csv (one row per evaluation), policy_transfer.md (the table and the
retention ratios), policy_transfer.png (returns and distances), trace.csv.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from _bench import configure_threads, fixed, make_parser, pyplot, save_figure, write_csv, write_outputs
from _bench import table as markdown_table
from _training import CreatureVecEnv, Evaluation, check_integer, evaluate
from _transfer_cases import CONVERGED, INTEGRATORS, EnvSettings, Policy, cases, default_settings, load_policy

# the evaluation cases live in `_transfer_cases`; they are named here too, as this script's interface
__all__ = [
    "CONVERGED", "INTEGRATORS", "EnvSettings", "Policy", "TracePoint", "TransferRow", "cases", "check",
    "default_settings", "evaluate_transfer", "load_policy", "main", "markdown", "retention_ratio", "run",
    "transfer_env", "with_retention",
]

NAME = "policy_transfer"
# env steps per episode of `--quick`
QUICK_EPISODE_STEPS = 4


@dataclass(frozen=True)
class TransferRow:
    """One evaluation: a row of ``policy_transfer.csv``.

    Attributes:
        trained_on: the integrator of the policy's training env.
        env: the integrator of the evaluation env.
        settings: "default" or "converged".
        dt: physics step in s; frame_skip: physics steps per env step; substeps: leapfrog substeps
            per physics step (0 for the implicit env); solver_tol: Newton–CG tolerance in m/s.
        episodes: evaluation episodes; episode_steps: env steps each.
        mean_return, return_stderr: mean undiscounted return and its standard error.
        distance: mean forward distance of the centre of mass per episode, in m.
        failures: episodes ended by a numerical failure.
        newton_per_env_step: mean Newton iterations per env step (0 for the explicit env).
        retention: mean_return over the own env's at the same settings (1 on the own env; NaN where
            the own return is not positive).
        seconds: wall time of the evaluation, in s.
        solver_budget: most Newton iterations per physics step of the implicit env (0: none, every
            step solved to solver_tol; 0 for the explicit env).
    """

    trained_on: str
    env: str
    settings: str
    dt: float
    frame_skip: int
    substeps: int
    solver_tol: float
    episodes: int
    episode_steps: int
    mean_return: float
    return_stderr: float
    distance: float
    failures: int
    newton_per_env_step: float
    retention: float
    seconds: float
    solver_budget: int = 0


@dataclass(frozen=True)
class TracePoint:
    """The centre of mass of the first evaluation episode after `step` env steps: a row of ``trace.csv``
    (`height` above the ground, forward position `x` in m, `x_velocity` and `height_velocity` in m/s),
    and the height of the body's lowest vertex above the ground, `lowest`, in m: the body is off the
    ground where it exceeds the implicit env's barrier distance d̂, or 0 in the explicit env."""

    env: str
    settings: str
    step: int
    height: float
    x: float
    x_velocity: float
    height_velocity: float
    lowest: float


def transfer_env(
    policy: Policy, env: EnvSettings, episodes: int, episode_steps: int, compile: bool = False
) -> CreatureVecEnv:
    """The SB3 view of `episodes` creatures of the policy's run in the env `env`, with the run's clock
    and activation filter on the controller's side (`train_ppo.vec_env`'s, the env's own filter off).

    Raises:
        ValueError: `env`'s env step differs from 1/60 s (the policy's clock and filter assume it).
    """
    from energysim.creatures import load_creature
    from energysim.envs import CreatureVectorEnv

    run = policy.settings
    if not math.isclose(env.dt * env.frame_skip, 1 / 60, rel_tol=1e-12):
        raise ValueError(
            f"the env step frame_skip × dt must be 1/60 s as in training, got {env.frame_skip} × {env.dt} s"
        )
    vector = CreatureVectorEnv(
        check_integer(episodes, "episodes", 1),
        creature=run["creature"],
        frame_skip=env.frame_skip,
        dt=env.dt,
        solver_tol=env.solver_tol,
        solver_budget=env.solver_budget if env.integrator == "implicit_euler" else None,
        solver_compile=compile,
        max_episode_steps=check_integer(episode_steps, "episode_steps", 1),
        integrator=env.integrator,
        substeps=env.substeps if env.integrator == "leapfrog" else None,
        activation_time_constant=0.0,
    )
    frequency = load_creature(run["creature"]).gait_frequency if run["clock"] else None
    return CreatureVecEnv(vector, frequency, float(run["action_tau"]))


def centre_of_mass_trace(venv: CreatureVecEnv, result: Evaluation, env: EnvSettings) -> list[TracePoint]:
    """The recorded episode's centre of mass per env step (`TracePoint`)."""
    from energysim.envs.observation import centre_of_mass

    simulation = venv.env.simulation
    scene, ground = simulation.scene, simulation.ground
    x, v = scene.split_state(result.states)
    com = centre_of_mass(x, scene.vertex_mass)
    com_velocity = centre_of_mass(v, scene.vertex_mass)
    up = ground.normal.to(com)
    height = com @ up - float(ground.offset)
    height_velocity = com_velocity @ up
    lowest = ground.signed_distance(x).amin(dim=-1)
    return [
        TracePoint(env.integrator, env.label, k, float(height[k]), float(com[k, 0]),
                   float(com_velocity[k, 0]), float(height_velocity[k]), float(lowest[k]))
        for k in range(com.shape[0])
    ]


def evaluate_transfer(
    policy: Policy,
    envs: Sequence[EnvSettings],
    episodes: int,
    episode_steps: int,
    compile: bool = False,
    log: Any = None,
) -> tuple[list[TransferRow], list[TracePoint]]:
    """Evaluate `policy`'s deterministic action on each env of `envs` (the same evaluation episodes in
    each), with the retention ratios against the own env at the same settings (`TransferRow`).

    `log(row)`, when given, is called after each evaluation. Returns the rows and the traces.
    """
    from train_ppo import controller

    act = controller(policy.model)
    rows, traces = [], []
    for env in envs:
        venv = transfer_env(policy, env, episodes, episode_steps, compile)
        result, seconds = timed_evaluation_recorded(venv, act)
        row = TransferRow(
            trained_on=policy.integrator,
            env=env.integrator,
            settings=env.label,
            dt=env.dt,
            frame_skip=env.frame_skip,
            substeps=int(venv.env.simulation.scene.substeps) if env.integrator == "leapfrog" else 0,
            solver_tol=env.solver_tol,
            solver_budget=(env.solver_budget or 0) if env.integrator == "implicit_euler" else 0,
            episodes=episodes,
            episode_steps=episode_steps,
            mean_return=result.mean_return,
            return_stderr=result.stderr_return,
            distance=result.mean_distance,
            failures=result.failures,
            newton_per_env_step=result.solver_iterations,
            retention=math.nan,
            seconds=seconds,
        )
        rows.append(row)
        traces += centre_of_mass_trace(venv, result, env)
        if log is not None:
            log(row)
    return with_retention(rows), traces


def timed_evaluation_recorded(venv: CreatureVecEnv, act: Any) -> tuple[Evaluation, float]:
    """`_training.evaluate(venv, act, record=True)` and its wall time in s."""
    start = time.perf_counter()
    result = evaluate(venv, act, record=True)
    return result, time.perf_counter() - start


def retention_ratio(other_return: float, own_return: float) -> float:
    """`other_return` / `own_return`: the fraction of its own env's return a policy keeps on the
    other env; NaN where `own_return` is not positive (a ratio to a non-gain means nothing)."""
    return other_return / own_return if own_return > 0 else math.nan


def with_retention(rows: Sequence[TransferRow]) -> list[TransferRow]:
    """`rows` with `retention` set against the own env's row of the same settings (NaN without one)."""
    own = {row.settings: row.mean_return for row in rows if row.env == row.trained_on}
    return [
        replace(
            row,
            retention=(
                retention_ratio(row.mean_return, own[row.settings]) if row.settings in own else math.nan
            ),
        )
        for row in rows
    ]


def markdown(policy: Policy, rows: Sequence[TransferRow]) -> str:
    """The rows as a markdown table and the retention ratios in a sentence."""
    header = [
        "evaluated on", "settings", "h (s) × frame_skip", "substeps", "tol (m/s)", "Newton budget",
        "return ± s.e.",
        "distance in 2 s (cm)" if rows and rows[0].episode_steps == 120 else "distance (cm)",
        "failures", "Newton it./env step", "retention", "eval time (s)",
    ]
    body = [
        [
            row.env,
            row.settings,
            f"1/{round(1 / row.dt)} × {row.frame_skip}",
            row.substeps or "–",
            f"{row.solver_tol:.0e}" if row.env == "implicit_euler" else "–",
            row.solver_budget or "–",
            f"{row.mean_return:+.4f} ± {row.return_stderr:.4f}",
            f"{100 * row.distance:+.2f}",
            f"{row.failures}/{row.episodes}",
            fixed(row.newton_per_env_step, 1) if row.env == "implicit_euler" else "–",
            fixed(row.retention, 3),
            f"{row.seconds:.0f}",
        ]
        for row in rows
    ]
    lines = [
        f"Policy trained on `{policy.integrator}` ({policy.settings['creature']}, {policy.path.name}), "
        f"deterministic, {rows[0].episodes} evaluation episodes of {rows[0].episode_steps} env steps of "
        "1/60 s. Retention: return on the env over the return on the own env at the same settings.",
        "",
        *markdown_table(header, body, "ll" + "r" * (len(header) - 2)),
        "",
    ]
    return "\n".join(lines)


def plot(rows: Sequence[TransferRow], path: Path) -> None:
    """Bars of the mean return and the distance of every evaluation."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    labels = [f"{row.env}\n{row.settings}" for row in rows]
    colours = ["tab:blue" if row.env == row.trained_on else "tab:orange" for row in rows]
    axes[0].bar(labels, [row.mean_return for row in rows], yerr=[row.return_stderr for row in rows],
                color=colours)
    axes[0].set_ylabel("mean evaluation return")
    axes[1].bar(labels, [100 * row.distance for row in rows], color=colours)
    axes[1].set_ylabel("forward distance per episode (cm)")
    for axis in axes:
        axis.tick_params(axis="x", labelsize=8)
        axis.grid(alpha=0.3, axis="y")
        axis.axhline(0.0, color="black", lw=0.8)
    figure.suptitle(f"policy trained on {rows[0].trained_on} (blue: own env, orange: the other env)")
    figure.tight_layout()
    save_figure(figure, path)


def run(
    model: Path, out: Path, *, quick: bool = False, converged: bool = True, compile: bool = False,
    episodes: int | None = None, draw: bool = True, implicit_frame_skip: int | None = None,
) -> list[TransferRow]:
    """Evaluate the policy at `model` on every case (`cases`), write the outputs to `out` and print the
    table; returns the rows. `episodes`: None for the run's own evaluation episodes;
    `implicit_frame_skip`: the implicit env's converged physics steps per env step (None: 4)."""
    policy = load_policy(model)
    if episodes is None:
        episodes = int(policy.settings["eval_episodes"])
    episodes = check_integer(episodes, "episodes", 1)
    steps = QUICK_EPISODE_STEPS if quick else int(policy.settings["episode_steps"])

    def log(row: TransferRow) -> None:
        print(f"{row.env} ({row.settings}): return {row.mean_return:+.4f}, distance "
              f"{100 * row.distance:+.2f} cm, {row.seconds:.0f} s", flush=True)

    envs = cases(policy, converged, implicit_frame_skip)
    rows, traces = evaluate_transfer(policy, envs, episodes, steps, compile, log)
    text = markdown(policy, rows)
    write_outputs(Path(out), NAME, rows, text, (lambda path: plot(rows, path)) if draw else None)
    write_csv(Path(out) / "trace.csv", traces)
    print(text)
    return rows


def check(rows: Sequence[TransferRow]) -> None:
    """What every transfer evaluation satisfies: the own env's retention is 1, every other row's is
    its return over the own env's at its settings, and every figure is finite."""
    own = {row.settings: row for row in rows if row.env == row.trained_on}
    for row in rows:
        if not (math.isfinite(row.mean_return) and math.isfinite(row.distance)):
            raise AssertionError(f"non-finite evaluation: {row}")
        expected = retention_ratio(row.mean_return, own[row.settings].mean_return)
        if not (row.retention == expected or (math.isnan(row.retention) and math.isnan(expected))):
            raise AssertionError(f"retention {row.retention} of {row.env}/{row.settings} is not {expected}")


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (module docstring); returns 0."""
    parser = make_parser(__doc__, NAME)
    add = parser.add_argument
    add("--model", type=Path, required=True, help="model.zip written by train_ppo.py")
    add("--quick", action="store_true", help=f"episodes of {QUICK_EPISODE_STEPS} env steps")
    add("--skip-converged", action="store_true", help="evaluate at the default settings only")
    add("--compile", action="store_true", help="compiled physics evaluations (solver_compile) in every env")
    add("--episodes", type=int, default=None, help="evaluation episodes (default: the run's)")
    add("--implicit-frame-skip", type=int, default=None,
        help="the implicit env's converged physics steps per env step, h = 1/(60·k) s (default 4)")
    args = parser.parse_args(argv)
    if args.implicit_frame_skip is not None:
        check_integer(args.implicit_frame_skip, "implicit-frame-skip", 1)
    configure_threads(check_integer(args.threads, "threads", 1))
    torch.set_num_threads(args.threads)
    rows = run(args.model, args.out, quick=args.quick, converged=not args.skip_converged,
               compile=args.compile, episodes=args.episodes, draw=not args.no_plot,
               implicit_frame_skip=args.implicit_frame_skip)
    check(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())

