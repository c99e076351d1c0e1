"""RLlib PPO on a local two-runner Ray cluster, against uniform random actions on the same episodes.

Two env runners (Ray actors) each step one batched `CreatureVectorEnv` of B worms on the explicit env;
after the training iterations the trained policy's mean action (the greedy policy) and uniform random
actions run the same seeded episodes, and their returns and forward distances are compared.

Run:  python scripts/ray_ppo.py                          # 25 iterations of 2 × 16 worms × 60 steps
      python scripts/ray_ppo.py --iterations 3 --episodes 32
Prints: per iteration its wall time and env steps; then, for each policy, the mean return and mean
forward distance over the evaluation episodes with their standard errors.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


@dataclasses.dataclass(frozen=True)
class Outcome:
    """Mean and standard error of a policy's episode returns and forward distances (m)."""

    return_mean: float
    return_stderr: float
    distance_mean: float
    distance_stderr: float

    @staticmethod
    def of(returns: np.ndarray, distances: np.ndarray) -> Outcome:
        root = np.sqrt(len(returns))
        return Outcome(
            float(returns.mean()),
            float(returns.std(ddof=1) / root),
            float(distances.mean()),
            float(distances.std(ddof=1) / root),
        )


@dataclasses.dataclass(frozen=True)
class Result:
    iterations: int
    env_steps: int
    train_seconds: float
    exploring_returns: tuple[float, ...]  # each iteration's mean return of the sampled episodes
    initial: Outcome  # the untrained greedy policy
    trained: Outcome
    random: Outcome


def run(
    *,
    iterations: int = 25,
    num_envs: int = 16,
    env_runners: int = 2,
    episode_steps: int = 60,
    episodes: int = 64,
    lr: float = 3e-4,
    num_cpus: int = 2,
) -> Result:
    """Train PPO for `iterations` and evaluate on `episodes` seeded episodes (a multiple of `num_envs`)."""
    import ray

    from energysim.envs.rllib import (
        episode_outcomes,
        greedy_policy,
        make_vector_env,
        ppo_config,
        random_policy,
    )

    if episodes % num_envs or episodes < 2 * num_envs:
        raise ValueError(
            f"episodes must be a multiple of num_envs = {num_envs}, at least two, got {episodes}"
        )
    # the runners' own env
    env = make_vector_env(
        {
            "num_envs": num_envs,
            "creature": "worm",
            "integrator": "leapfrog",
            "solver_compile": True,
            "max_episode_steps": episode_steps,
        }
    )
    seeds = [10_000 + num_envs * k for k in range(episodes // num_envs)]

    def evaluate(policy) -> Outcome:
        pairs = [episode_outcomes(env, policy, seed) for seed in seeds]
        return Outcome.of(np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs]))

    started_here = not ray.is_initialized()
    if started_here:
        ray.init(num_cpus=num_cpus, include_dashboard=False)
    try:
        algorithm = ppo_config(
            "worm",
            num_envs_per_runner=num_envs,
            num_env_runners=env_runners,
            max_episode_steps=episode_steps,
            rollout_steps=episode_steps,
            lr=lr,
        ).build_algo()
        try:
            initial = evaluate(greedy_policy(algorithm))
            start = time.perf_counter()
            exploring_returns = []
            for iteration in range(iterations):
                tick = time.perf_counter()
                result = algorithm.train()
                steps = int(result["num_env_steps_sampled_lifetime"])
                exploring_returns.append(float(result["env_runners"]["episode_return_mean"]))
                print(f"iteration {iteration + 1}: {time.perf_counter() - tick:.1f} s, {steps} env steps")
            train_seconds = time.perf_counter() - start
            trained = evaluate(greedy_policy(algorithm))
        finally:
            algorithm.stop()
    finally:
        if started_here:
            ray.shutdown()
    random = evaluate(random_policy(env.action_space, seed=7))
    return Result(iterations, steps, train_seconds, tuple(exploring_returns), initial, trained, random)


def improvement(result: Result) -> tuple[float, float]:
    """The trained policy's mean forward distance over the random policy's, in m, and its standard error."""
    gain = result.trained.distance_mean - result.random.distance_mean
    return gain, float(np.hypot(result.trained.distance_stderr, result.random.distance_stderr))


def check(result: Result, margin: float = 3.0) -> None:
    """The trained greedy policy goes forward, and farther than random actions by `margin` standard
    errors; its return beats theirs by as much."""
    gain, stderr = improvement(result)
    assert result.trained.distance_mean > margin * result.trained.distance_stderr > 0, result.trained
    assert gain > margin * stderr, (gain, stderr)
    return_gain = result.trained.return_mean - result.random.return_mean
    assert return_gain > margin * np.hypot(result.trained.return_stderr, result.random.return_stderr), result


def main(argv: list[str] | None = None) -> Result:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=25)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--env-runners", type=int, default=2)
    parser.add_argument("--episode-steps", type=int, default=60)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--lr", type=float, default=3e-4)
    args = parser.parse_args(argv)
    result = run(
        iterations=args.iterations,
        num_envs=args.num_envs,
        env_runners=args.env_runners,
        episode_steps=args.episode_steps,
        episodes=args.episodes,
        lr=args.lr,
    )
    print(
        f"{result.iterations} iterations, {result.env_steps} env steps, {result.train_seconds:.0f} s training"
    )
    for name in ("initial", "trained", "random"):
        outcome: Outcome = getattr(result, name)
        print(
            f"{name:8s} return {outcome.return_mean:+.3f} ± {outcome.return_stderr:.3f}, "
            f"distance {100 * outcome.distance_mean:+.2f} ± {100 * outcome.distance_stderr:.2f} cm"
        )
    check(result)
    return result


if __name__ == "__main__":
    main()
