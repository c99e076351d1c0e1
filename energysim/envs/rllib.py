"""The batched creature env on Ray RLlib: one `CreatureVectorEnv` of B bodies per env runner.

Needs the optional `ray` extra (``pip install 'torch-energysim[rl,ray]'``); nothing else in the package
imports this module, so ``import energysim`` and ``import energysim.envs`` never import ray.

RLlib's env runners step a Gymnasium `VectorEnv` each. With ``gym_env_vectorize_mode=
VECTOR_ENTRY_POINT`` a runner calls the registered creator once with ``num_envs`` and gets back one
batched env, so every runner simulates its B creatures as one batched solve, and a cluster of N runners
simulates N batches at once, each on its own CPU (or node). See docs/scale-out.md.

    import ray
    from energysim.envs.rllib import ppo_config
    ray.init()                                   # or ray.init(address="auto") on a cluster
    algo = ppo_config("worm", num_envs_per_runner=16, num_env_runners=2).build_algo()
    for _ in range(10):
        result = algo.train()
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
import torch

try:
    from ray.rllib.algorithms.ppo import PPO, PPOConfig
    from ray.rllib.core import DEFAULT_MODULE_ID
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.tune.registry import register_env
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError(
        "energysim.envs.rllib needs ray[rllib]; install the ray extra: pip install 'torch-energysim[rl,ray]'"
    ) from error

from energysim.creatures import CREATURES
from energysim.envs import MAX_EPISODE_STEPS
from energysim.envs.vector_env import CreatureVectorEnv

# the name RLlib's registry knows the creator by, on the driver and on every worker
RLLIB_ENV = "energysim-creature-vector"

Policy = Callable[[np.ndarray], np.ndarray]


class RunnerSeeds(gymnasium.vector.VectorWrapper):
    """Seeds B entries from one runner seed so that no two runners share an entry's seed.

    RLlib seeds runner w with ``seed + w``; `CreatureVectorEnv` seeds entry i with ``s + i``, so two
    runners would share B − 1 entry seeds. Here entry i of the runner seeded s gets ``s·B + i``.
    """

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seed = int(seed) * self.num_envs
        return self.env.reset(seed=seed, options=options)


def make_vector_env(env_config: Mapping[str, Any]) -> gymnasium.vector.VectorEnv:
    """RLlib's env creator: one `CreatureVectorEnv`, its entries seeded apart from other runners'.

    Args:
        env_config: ``num_envs`` (B, set by RLlib from ``num_envs_per_env_runner``) and any keyword of
            `CreatureVectorEnv` (``creature``, ``integrator``, ``max_episode_steps``, ...); RLlib's
            runner context keys (``worker_index`` and the like) are not part of it.
    """
    kwargs = dict(env_config)
    if "num_envs" not in kwargs:
        raise ValueError(
            "env_config must hold num_envs (RLlib sets it from num_envs_per_env_runner with "
            "gym_env_vectorize_mode=VECTOR_ENTRY_POINT)"
        )
    num_envs = kwargs.pop("num_envs")
    kwargs.setdefault("max_episode_steps", MAX_EPISODE_STEPS)
    return RunnerSeeds(CreatureVectorEnv(num_envs, **kwargs))


def register_rllib_env() -> str:
    """Register `make_vector_env` with Ray's registry (idempotent) and return its name, `RLLIB_ENV`.

    Ray ships the registration to every worker of the cluster; the workers import this module by
    name, so energysim must be installed on every node (or shipped with ``runtime_env``).
    """
    register_env(RLLIB_ENV, make_vector_env)
    return RLLIB_ENV


def _check_count(value: object, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def ppo_config(
    creature: str = "worm",
    *,
    num_envs_per_runner: int = 16,
    num_env_runners: int = 2,
    integrator: str = "leapfrog",
    solver_compile: bool = True,
    max_episode_steps: int = MAX_EPISODE_STEPS,
    rollout_steps: int = 64,
    lr: float = 3e-4,
    num_epochs: int = 10,
    num_minibatches: int = 4,
    hidden_sizes: Sequence[int] = (64, 64),
    gamma: float = 0.98,
    gae_lambda: float = 0.95,
    initial_log_std: float = -1.0,
    entropy_coeff: float = 0.0,
    seed: int | None = 0,
    env_kwargs: Mapping[str, Any] | None = None,
) -> PPOConfig:
    """A PPO config whose every env runner steps one `CreatureVectorEnv` of B creatures.

    The explicit env (``integrator="leapfrog"``, compiled) is the default because PPO needs 10⁴–10⁶
    env steps, which it delivers in minutes (docs/training.md); ``"implicit_euler"`` works the same way.

    Args:
        creature: one of `energysim.creatures.CREATURES`.
        num_envs_per_runner: B, the creatures one runner simulates as one batch.
        num_env_runners: remote runners (Ray actors, one CPU each); 0 samples in the algorithm's process.
        integrator, solver_compile, max_episode_steps: as `CreatureVectorEnv`.
        rollout_steps: env steps each runner collects per entry for one training batch, so a batch
            holds ``max(1, num_env_runners)·B·rollout_steps`` transitions.
        lr: Adam learning rate.
        num_epochs, num_minibatches: passes over each batch and minibatches per pass.
        hidden_sizes: the policy's and value function's hidden layer widths (two separate networks).
        gamma, gae_lambda: the discount per env step and the GAE λ.
        initial_log_std: the Gaussian's log σ at the start, one free parameter per actuator. RLlib's
            default (σ = 1, state dependent) saturates most actions at ±1, so the exploring policy
            moves by its noise while its mean, the greedy policy, learns to stand still; σ = e⁻¹ lets
            the mean carry the gait (as SB3's log σ₀ = −1 in docs/training.md).
        entropy_coeff: the entropy bonus's weight in the loss.
        seed: runner w's entries are seeded ``(seed + w)·B + i``; None leaves them unseeded.
        env_kwargs: further `CreatureVectorEnv` keywords (``frame_skip``, ``friction``, ...).

    Raises:
        ValueError: naming the argument that is out of range.
    """
    if creature not in CREATURES:
        raise ValueError(f"creature must be one of {CREATURES}, got {creature!r}")
    num_envs_per_runner = _check_count(num_envs_per_runner, "num_envs_per_runner", 1)
    num_env_runners = _check_count(num_env_runners, "num_env_runners", 0)
    max_episode_steps = _check_count(max_episode_steps, "max_episode_steps", 1)
    rollout_steps = _check_count(rollout_steps, "rollout_steps", 1)
    num_epochs = _check_count(num_epochs, "num_epochs", 1)
    num_minibatches = _check_count(num_minibatches, "num_minibatches", 1)
    if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a finite number > 0, got {lr!r}")
    for name, value, low, high in (
        ("gamma", gamma, 0.0, 1.0),
        ("gae_lambda", gae_lambda, 0.0, 1.0),
        ("initial_log_std", initial_log_std, -10.0, 2.0),
        ("entropy_coeff", entropy_coeff, 0.0, math.inf),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
            raise ValueError(f"{name} must be a number in [{low}, {high}], got {value!r}")
    hidden = [_check_count(width, f"hidden_sizes[{i}]", 1) for i, width in enumerate(hidden_sizes)]
    env_config = {
        **dict(env_kwargs or {}),
        "creature": creature,
        "integrator": integrator,
        "solver_compile": solver_compile,
        "max_episode_steps": max_episode_steps,
    }
    batch = max(1, num_env_runners) * num_envs_per_runner * rollout_steps
    return (
        PPOConfig()
        .environment(env=register_rllib_env(), env_config=env_config)
        .env_runners(
            num_env_runners=num_env_runners,
            num_envs_per_env_runner=num_envs_per_runner,
            gym_env_vectorize_mode=gymnasium.VectorizeMode.VECTOR_ENTRY_POINT,
            rollout_fragment_length=rollout_steps,
            num_cpus_per_env_runner=1,
        )
        .training(
            lr=float(lr),
            train_batch_size_per_learner=batch,
            minibatch_size=max(1, batch // num_minibatches),
            num_epochs=num_epochs,
            gamma=float(gamma),
            lambda_=float(gae_lambda),
            entropy_coeff=float(entropy_coeff),
        )
        .rl_module(
            model_config=DefaultModelConfig(fcnet_hiddens=hidden, free_log_std=True, vf_share_layers=False)
        )
        .callbacks(on_algorithm_init=_InitialLogStd(float(initial_log_std)))
        .debugging(seed=seed)
    )


class _InitialLogStd:
    """`on_algorithm_init`: set the policy's free log σ in every copy of the module, the learners' and
    the env runners' (RLlib starts the free log σ at 0)."""

    def __init__(self, log_std: float) -> None:
        self.log_std = log_std

    def __call__(self, algorithm: PPO, **kwargs: Any) -> None:
        log_std = self.log_std

        def set_log_std(module: torch.nn.Module) -> None:
            with torch.no_grad():
                for name, parameter in module.named_parameters():
                    if name.endswith("log_std"):
                        parameter.fill_(log_std)

        algorithm.learner_group.foreach_learner(
            lambda learner: set_log_std(learner.module[DEFAULT_MODULE_ID])
        )
        algorithm.env_runner_group.foreach_env_runner(
            lambda runner: set_log_std(runner.module), local_env_runner=True
        )


def greedy_policy(algorithm: PPO) -> Policy:
    """The trained policy's deterministic action (the Gaussian's mean): observations `[B, o]` → `[B, a]`."""
    module = algorithm.get_module()
    distribution = module.get_inference_action_dist_cls()

    def act(observations: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = module.forward_inference({"obs": torch.as_tensor(observations, dtype=torch.float32)})
            action = distribution.from_logits(out["action_dist_inputs"]).to_deterministic().sample()
        return np.clip(action.numpy().astype(np.float64), -1.0, 1.0)

    return act


def random_policy(action_space: gymnasium.spaces.Box, seed: int) -> Policy:
    """Uniform random actions in `action_space` (the batched `[B, a]` box), from a seeded generator."""
    generator = np.random.default_rng(seed)
    return lambda observations: generator.uniform(action_space.low, action_space.high)


def episode_outcomes(
    env: gymnasium.vector.VectorEnv, policy: Policy, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Each entry's return and forward distance over its first episode from ``env.reset(seed=seed)``.

    Returns:
        returns `[B]`, and distances `[B]` in m: the centre of mass's x at the episode's end minus at
        its start.

    `env` is a `CreatureVectorEnv`, or one wrapped (as `make_vector_env` gives it); it needs
    ``max_episode_steps``, so that every episode ends.
    """
    if env.unwrapped.config.max_episode_steps is None:
        raise ValueError("episode_outcomes needs an env with max_episode_steps set, got None")
    observations, info = env.reset(seed=seed)
    start = np.asarray(info["x_position"], dtype=np.float64).copy()
    end = start.copy()
    returns = np.zeros(env.num_envs)
    running = np.ones(env.num_envs, dtype=bool)
    while running.any():
        observations, rewards, terminated, truncated, info = env.step(policy(observations))
        returns[running] += rewards[running]
        end[running] = info["x_position"][running]
        running &= ~(terminated | truncated)
    return returns, end - start


def episode_returns(env: gymnasium.vector.VectorEnv, policy: Policy, seed: int) -> np.ndarray:
    """Each entry's return over its first episode from ``env.reset(seed=seed)``, shape `[B]`
    (`episode_outcomes`' first half)."""
    return episode_outcomes(env, policy, seed)[0]


__all__ = [
    "RLLIB_ENV",
    "RunnerSeeds",
    "episode_outcomes",
    "episode_returns",
    "greedy_policy",
    "make_vector_env",
    "ppo_config",
    "random_policy",
    "register_rllib_env",
]
