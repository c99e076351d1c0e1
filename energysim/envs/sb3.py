"""`SB3VecEnv`: the batched `CreatureVectorEnv` as a stable-baselines3 `VecEnv`.

SB3's algorithms take their own `VecEnv`, not a Gymnasium `VectorEnv`:

    import gymnasium
    from stable_baselines3 import PPO
    from energysim.envs import SB3VecEnv

    worms = gymnasium.make_vec("energysim/Worm-v0", num_envs=4, vectorization_mode="vector_entry_point")
    envs = SB3VecEnv(worms)
    model = PPO("MlpPolicy", envs).learn(total_timesteps=10_000)

The B creatures stay one batched solve per step. What the adapter translates:
- **Autoreset.** The env resets an ended entry at the *next* step (Gymnasium's default); SB3 expects
  it reset at once. An entry that ends is reset in the same `step_wait`, its reset observation is
  returned, and the episode's last observation goes into ``info["terminal_observation"]``.
  ``info["TimeLimit.truncated"]`` is True when the time limit, not a numerical failure, ended it, so
  SB3 bootstraps the value of truncated episodes.
- **Infos.** One dict per entry with the env's step info as Python scalars ("x_position",
  "x_velocity", "reward_forward", "reward_ctrl", "solver_iterations", "solver_residual",
  "numerical_failure") and "activation" (float `[a]`), plus "episode" ({"r": return, "l": length},
  as SB3's `Monitor` writes it) when the episode ends, which SB3's logger reads for ``rollout/ep_rew_mean``.
- **Rewards** are float32 (SB3's buffers); the env's float64 rewards of the last step are in
  `rewards`.

stable-baselines3 belongs to the `rl` extra; ``import energysim.envs`` imports it only when
`SB3VecEnv` is first used.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

try:
    from stable_baselines3.common.vec_env import VecEnv
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError(
        "energysim.envs.SB3VecEnv needs stable-baselines3; install the rl extra: "
        "pip install 'torch-energysim[rl]'"
    ) from error

from energysim.envs.rendering import SideViewRenderer
from energysim.envs.vector_env import STEP_INFO_KEYS, CreatureVectorEnv

# attributes of the batched env that hold one row per entry: `get_attr` hands each entry its own row
PER_ENTRY_ATTRIBUTES = ("states", "activations", "elapsed_steps", "observations")
RENDER_MODES = ("rgb_array",)


class SB3VecEnv(VecEnv):
    """A `CreatureVectorEnv` seen by stable-baselines3 as a `VecEnv` of `env.num_envs` entries.

    Args:
        env: the batched env, as `gymnasium.make_vec(id, num_envs, vectorization_mode=
            "vector_entry_point")` or `CreatureVectorEnv(num_envs, creature, ...)` return it
            (no Gymnasium vector wrappers around it: the adapter drives its resets itself). Its
            `max_episode_steps` ends the episodes.
        render_mode: None, or "rgb_array": `render()` tiles one side view per entry (SB3's
            ``render("human")`` shows that with OpenCV).

    Attributes:
        env: the wrapped `CreatureVectorEnv` (its `simulation`, `states`, `activations`).
        rewards: the env's float64 rewards of the last step, `[B]`.
        episode_returns, episode_lengths: the running episode of each entry, `[B]`.

    Seeding follows SB3: `seed(s)` seeds the next `reset()` with s + i for entry i; without it, each
    entry keeps drawing from its own generator. Entries reset by the autoreset draw from theirs too.
    """

    def __init__(self, env: CreatureVectorEnv, render_mode: str | None = None) -> None:
        if not isinstance(env, CreatureVectorEnv):
            raise TypeError(
                "SB3VecEnv wraps a CreatureVectorEnv (gymnasium.make_vec(id, num_envs, "
                f"vectorization_mode='vector_entry_point') with no vector wrappers), got {type(env).__name__}"
            )
        if render_mode not in (None, *RENDER_MODES):
            raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")
        self.env = env
        self._render_mode = render_mode
        self.rewards = np.zeros(env.num_envs)
        self.episode_returns = np.zeros(env.num_envs)
        self.episode_lengths = np.zeros(env.num_envs, dtype=np.int64)
        self._actions: np.ndarray | None = None
        self._renderer: SideViewRenderer | None = None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)

    def reset(self) -> np.ndarray:
        """Reset every entry (seeded by `seed`, if called since the last reset); observations `[B, o]`."""
        options = [option for option in self._options if option]
        if options:
            raise ValueError(f"CreatureVectorEnv's reset takes no per-entry options, got {options[0]!r}")
        seeds = list(self._seeds)
        observations, info = self.env.reset(seed=None if all(s is None for s in seeds) else seeds)
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{"x_position": float(x)} for x in info["x_position"]]
        self.episode_returns[:] = 0.0
        self.episode_lengths[:] = 0
        self._actions = None
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        """Store the actions `[B, a]` (activations in [−1, 1], clipped) for `step_wait`."""
        self._actions = np.asarray(actions)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """Step every entry; reset the entries that ended at once (module docstring).

        Returns:
            observations `[B, o]` float32, rewards `[B]` float32, dones `[B]` bool, one info per entry.
        """
        if self._actions is None:
            raise RuntimeError("step_async(actions) must come before step_wait()")
        actions, self._actions = self._actions, None
        observations, rewards, terminated, truncated, info = self.env.step(actions)
        self.rewards = rewards
        self.episode_returns += rewards
        self.episode_lengths += 1
        done = terminated | truncated
        infos = [self._entry_info(info, i) for i in range(self.num_envs)]
        for i in np.flatnonzero(done):
            infos[i]["terminal_observation"] = observations[i].copy()
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            infos[i]["episode"] = {"r": float(self.episode_returns[i]), "l": int(self.episode_lengths[i])}
        if done.any():
            self._reset_ended(done, observations)
        return observations, rewards.astype(np.float32), done, infos

    def _reset_ended(self, done: np.ndarray, observations: np.ndarray) -> None:
        """Reset the entries `done` (bool `[B]`) now, writing their reset observations into `observations`."""
        fresh, info = self.env.reset(options={"reset_mask": done})
        observations[done] = fresh[done]
        for i in np.flatnonzero(done):
            self.reset_infos[i] = {"x_position": float(info["x_position"][i])}
        self.episode_returns[done] = 0.0
        self.episode_lengths[done] = 0

    @staticmethod
    def _entry_info(info: dict[str, Any], i: int) -> dict[str, Any]:
        entry: dict[str, Any] = {"x_position": float(info["x_position"][i])}
        for key in STEP_INFO_KEYS:
            if key in info:
                value = info[key][i]
                entry[key] = value.copy() if isinstance(value, np.ndarray) else value.item()
        return entry

    def close(self) -> None:
        self._renderer = None
        self.env.close()

    def get_images(self) -> Sequence[np.ndarray]:
        """One RGB side view `[H, W, 3]` uint8 per entry of its current state (render_mode "rgb_array")."""
        if self.render_mode != "rgb_array":
            raise ValueError(
                f"get_images needs render_mode 'rgb_array', this SB3VecEnv has {self.render_mode!r}"
            )
        if self._renderer is None:
            self._renderer = SideViewRenderer(self.env.simulation.creature.mesh)
        positions = self.env.simulation.scene.split_state(self.env.states)[0].detach().cpu().numpy()
        return [self._renderer.render(x) for x in positions]

    def get_attr(self, attr_name: str, indices: int | Iterable[int] | None = None) -> list[Any]:
        """The batched env's attribute `attr_name` once per selected entry: its own row for
        `PER_ENTRY_ATTRIBUTES`, the shared value otherwise ("render_mode" is the adapter's)."""
        selected = self._indices(indices)
        if attr_name == "render_mode":
            return [self._render_mode for _ in selected]
        value = getattr(self.env, attr_name)
        if attr_name in PER_ENTRY_ATTRIBUTES:
            return [value[i] for i in selected]
        return [value for _ in selected]

    def set_attr(self, attr_name: str, value: Any, indices: int | Iterable[int] | None = None) -> None:
        """Set an attribute of the batched env; the entries share it, so `indices` must select all."""
        self._all_entries(indices, "set_attr")
        setattr(self.env, attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: int | Iterable[int] | None = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        """Call a method of the batched env once (the entries share it, so `indices` must select all);
        its result is repeated once per entry."""
        self._all_entries(indices, "env_method")
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result for _ in range(self.num_envs)]

    def env_is_wrapped(self, wrapper_class: type, indices: int | Iterable[int] | None = None) -> list[bool]:
        """No Gymnasium wrapper is around any entry."""
        return [False for _ in self._indices(indices)]

    def _indices(self, indices: int | Iterable[int] | None) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        selected = [indices] if isinstance(indices, (int, np.integer)) else list(indices)
        bad = [i for i in selected if not 0 <= int(i) < self.num_envs]
        if bad:
            raise IndexError(f"indices {bad} out of range for {self.num_envs} entries")
        return [int(i) for i in selected]

    def _all_entries(self, indices: int | Iterable[int] | None, method: str) -> None:
        if sorted(set(self._indices(indices))) != list(range(self.num_envs)):
            raise ValueError(
                f"{method}: the {self.num_envs} entries share one batched env, so indices must select "
                f"all of them (None), got {indices!r}"
            )


__all__ = ["PER_ENTRY_ATTRIBUTES", "SB3VecEnv"]
