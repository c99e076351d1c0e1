"""A Ray Tune sweep of PPO on a creature env: one trial per learning rate, the trials in parallel.

Each trial is an RLlib PPO run (`energysim.envs.rllib.ppo_config`) that samples one batched
`CreatureVectorEnv` of B creatures in its own process (`--env-runners 0`) or in that many runner
actors. Ray schedules as many trials at once as the cluster has CPUs for, here or on a multi-node
cluster (`--address auto` after `ray start`; see docs/scale-out.md).

Run:  python scripts/ray_tune_sweep.py                                  # 2 learning rates, local Ray
      python scripts/ray_tune_sweep.py --lrs 1e-4 3e-4 1e-3 --iterations 20 --address auto
Writes: <out>/sweep.csv and <out>/sweep.md, one row per trial: its learning rate, final mean episode
return, env steps, and the wall-clock interval it trained in (so that overlaps show parallel trials).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import tempfile
from pathlib import Path


@dataclasses.dataclass(frozen=True)
class TrialRow:
    lr: float
    episode_return_mean: float
    env_steps: int
    iterations: int
    start: float  # Unix time, s, when the trial's first training iteration began
    end: float  # Unix time, s, when its last one ended


def run(
    lrs: list[float],
    *,
    creature: str = "worm",
    iterations: int = 2,
    num_envs: int = 16,
    env_runners: int = 0,
    episode_steps: int = 20,
    address: str | None = None,
    num_cpus: int | None = 2,
) -> list[TrialRow]:
    """Run one PPO trial per learning rate through Ray Tune and return one row per trial."""
    import ray
    from ray import tune

    from energysim.envs.rllib import ppo_config

    if address is None:
        ray.init(num_cpus=num_cpus, include_dashboard=False, ignore_reinit_error=True)
    else:
        ray.init(address=address, ignore_reinit_error=True)
    try:
        config = ppo_config(
            creature,
            num_envs_per_runner=num_envs,
            num_env_runners=env_runners,
            max_episode_steps=episode_steps,
            rollout_steps=episode_steps,
            num_epochs=2,
        ).training(lr=tune.grid_search(lrs))
        with tempfile.TemporaryDirectory() as storage:
            tuner = tune.Tuner(
                "PPO",
                param_space=config,
                run_config=tune.RunConfig(
                    storage_path=storage,
                    stop={"training_iteration": iterations},
                    verbose=0,
                ),
                tune_config=tune.TuneConfig(max_concurrent_trials=len(lrs)),
            )
            results = tuner.fit()
            rows = []
            for result in results:
                if result.error is not None:
                    raise RuntimeError(f"trial with lr={result.config['lr']} failed: {result.error}")
                history = result.metrics_dataframe
                first, last = history.iloc[0], history.iloc[-1]
                rows.append(
                    TrialRow(
                        lr=float(result.config["lr"]),
                        episode_return_mean=float(last["env_runners/episode_return_mean"]),
                        env_steps=int(last["num_env_steps_sampled_lifetime"]),
                        iterations=int(last["training_iteration"]),
                        start=float(first["timestamp"] - first["time_this_iter_s"]),
                        end=float(last["timestamp"]),
                    )
                )
    finally:
        ray.shutdown()
    return sorted(rows, key=lambda row: row.lr)


def check(rows: list[TrialRow], lrs: list[float], iterations: int) -> None:
    assert sorted(row.lr for row in rows) == sorted(lrs), "a learning rate has no trial"
    assert all(row.iterations == iterations for row in rows), "a trial stopped early"
    assert all(row.env_steps > 0 for row in rows), "a trial sampled nothing"
    assert max(row.start for row in rows) < min(row.end for row in rows), "the trials did not overlap"


def write(rows: list[TrialRow], out: Path) -> None:
    """<out>/sweep.csv and <out>/sweep.md, each written whole (temporary file, then rename)."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = min(row.start for row in rows)
    fields = [field.name for field in dataclasses.fields(TrialRow)]
    lines = [
        "| lr | final mean episode return | env steps | iterations | trained from (s) | to (s) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {row.lr:g} | {row.episode_return_mean:+.3f} | {row.env_steps} | {row.iterations} | "
        f"{row.start - t0:.1f} | {row.end - t0:.1f} |"
        for row in rows
    ]
    for name, text in (("sweep.md", "\n".join(lines) + "\n"), ("sweep.csv", None)):
        path = out / name
        temporary = path.with_suffix(path.suffix + ".tmp")
        with temporary.open("w", newline="") as file:
            if text is not None:
                file.write(text)
            else:
                writer = csv.writer(file)
                writer.writerow(fields)
                writer.writerows(dataclasses.astuple(row) for row in rows)
        os.replace(temporary, path)


def main(argv: list[str] | None = None) -> list[TrialRow]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lrs", type=float, nargs="+", default=[1e-4, 1e-3])
    parser.add_argument("--creature", default="worm")
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--env-runners", type=int, default=0)
    parser.add_argument("--episode-steps", type=int, default=20)
    parser.add_argument("--address", default=None, help="a running cluster, e.g. auto; default: local Ray")
    parser.add_argument("--num-cpus", type=int, default=2, help="CPUs of the local Ray instance")
    parser.add_argument("--out", type=Path, default=Path("out/ray_tune_sweep"))
    args = parser.parse_args(argv)
    rows = run(
        args.lrs,
        creature=args.creature,
        iterations=args.iterations,
        num_envs=args.num_envs,
        env_runners=args.env_runners,
        episode_steps=args.episode_steps,
        address=args.address,
        num_cpus=args.num_cpus,
    )
    check(rows, args.lrs, args.iterations)
    write(rows, args.out)
    print((args.out / "sweep.md").read_text())
    return rows


if __name__ == "__main__":
    main()
