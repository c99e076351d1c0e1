"""`CreatureVectorEnv`: B creatures stepped as one batched solve, as a Gymnasium `VectorEnv`.

The B states are one `[B, 2·n·d]` tensor on one device, and each env step is `frame_skip` batched
`es.step` calls, not B Python copies of `CreatureEnv`. Entry i behaves exactly like a `CreatureEnv`
reset with seed `seed + i` and given the same actions (to rounding; tests/test_envs.py checks 1e-8).

Autoreset: `AutoresetMode.NEXT_STEP`, Gymnasium's default, which every vector wrapper accepts. An
entry that terminates or truncates at step t is reset by the call at step t + 1: that call ignores
its action and returns its reset observation, reward 0 and terminated = truncated = False, with its
reset info ("x_position" only) in the info arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from torch import Tensor

from energysim.envs.actions import as_action_array
from energysim.envs.config import FRICTION_SMOOTHING, CreatureEnvConfig
from energysim.envs.core import CreatureSimulation
from energysim.envs.creature_env import action_space, observation_space
from energysim.envs.env_rendering import (
    EnvRenderer,
    RenderOptions,
    available_render_modes,
    check_render_mode,
)
from energysim.envs.transition import Transition

STEP_INFO_KEYS = (
    "x_velocity",
    "reward_forward",
    "reward_ctrl",
    "activation",
    "solver_iterations",
    "solver_residual",
    "numerical_failure",
)


class CreatureVectorEnv(gymnasium.vector.VectorEnv):
    """`num_envs` copies of a `CreatureEnv` task, simulated as one batch.

    Args:
        num_envs: B ≥ 1.
        creature and the other keywords: as `CreatureEnv`.
        render_entries: how many entries `render()` draws, the first ones: one frame, or a grid of
            ⌈√k⌉ columns (`tile_frames`); at most `num_envs`.
            `max_episode_steps` truncates each entry after that many env steps (`gymnasium.make_vec`
            passes the registration's value).

    Info: arrays of length B with a `_key` mask each, as Gymnasium's vector envs give them:
    "x_position" for every entry; "x_velocity", "reward_forward", "reward_ctrl", "activation"
    (`[B, a]`), "solver_iterations", "solver_residual" and "numerical_failure" for the entries
    stepped (not those reset).

    Attributes:
        simulation: the batched `CreatureSimulation` (scene, markers, observation layout).
        states: the B states, shape `[B, 2·n·d]`, in m and m/s, on the simulation's device.
        activations: the activations the muscles hold, shape `[B, a]` (last actions, clipped, or their
            filtered values with `activation_time_constant`; zeros after a reset).
        elapsed_steps: env steps since each entry's reset, shape `[B]`.
    """

    metadata: dict[str, Any] = {
        "render_modes": ["human", "rgb_array"],
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int,
        creature: str = "worm",
        *,
        frame_skip: int = 1,
        dt: float = 1 / 60,
        forward_reward_weight: float = 1.0,
        ctrl_cost_weight: float = 1e-3,
        reset_noise_scale: float = 1e-3,
        friction: float = 0.8,
        friction_smoothing: float = FRICTION_SMOOTHING,
        barrier_distance: float | None = None,
        solver_tol: float = 1e-4,
        solver_max_iter: int = 100,
        solver_budget: int | None = None,
        solver_compile: bool = False,
        max_episode_steps: int | None = None,
        num_markers: int = 12,
        activation_time_constant: float | None = None,
        integrator: str = "implicit_euler",
        substeps: int | None = None,
        viscosity: float | None = None,
        render_mode: str | None = None,
        render_width: int = 480,
        render_height: int = 270,
        camera: str = "follow",
        camera_window: tuple[float, float] | None = None,
        render_entries: int = 1,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        check_render_mode(render_mode)
        render_options = RenderOptions(render_width, render_height, camera, camera_window, render_entries)
        if render_options.entries > num_envs:
            raise ValueError(f"render_entries must be at most num_envs = {num_envs}, got {render_entries}")
        self.config = CreatureEnvConfig(
            creature=creature,
            frame_skip=frame_skip,
            dt=dt,
            forward_reward_weight=forward_reward_weight,
            ctrl_cost_weight=ctrl_cost_weight,
            reset_noise_scale=reset_noise_scale,
            friction=friction,
            friction_smoothing=friction_smoothing,
            barrier_distance=barrier_distance,
            solver_tol=solver_tol,
            solver_max_iter=solver_max_iter,
            solver_budget=solver_budget,
            solver_compile=solver_compile,
            max_episode_steps=max_episode_steps,
            num_markers=num_markers,
            activation_time_constant=activation_time_constant,
            integrator=integrator,
            substeps=substeps,
            viscosity=viscosity,
        )
        self.simulation = CreatureSimulation(self.config, device=device, dtype=dtype)
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.metadata = {
            **type(self).metadata,
            "render_modes": available_render_modes(),
            "render_fps": max(1, round(1 / self.simulation.frame_seconds)),
        }
        self.single_observation_space = observation_space(self.simulation)
        self.single_action_space = action_space(self.simulation)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.states = self.simulation.rest_state.expand(self.num_envs, -1).clone()
        # the activations each entry's muscles hold now: the state of the activation dynamics, or
        # the last action, clipped, without them (zeros after a reset)
        self.activations = self.simulation.rest_activation(self.num_envs)
        self.elapsed_steps = np.zeros(self.num_envs, dtype=np.int64)
        self.observations = np.zeros((self.num_envs, self.simulation.layout.size), dtype=np.float32)
        self._generators: list[np.random.Generator | None] = [None] * self.num_envs
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._was_reset = False
        self._rendering = EnvRenderer(self.simulation, render_mode, render_options, f"energysim {creature}")

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every entry, or those in `options["reset_mask"]` (bool array `[B]`).

        Args:
            seed: None (keep each entry's generator, or a random one), an int s (entry i is seeded
                s + i), or one int-or-None per entry.
        """
        seeds = self._seeds(seed)
        if isinstance(seed, int):
            super().reset(seed=seed)
        mask = np.ones(self.num_envs, dtype=bool)
        if options is not None and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(
                    f"options['reset_mask'] must be a bool array of shape ({self.num_envs},) with a True "
                    "entry"
                )
        for i in np.flatnonzero(mask):
            if seeds[i] is not None or self._generators[i] is None:
                self._generators[i] = seeding.np_random(seeds[i])[0]
        self._reset_entries(np.flatnonzero(mask))
        self._autoreset[mask] = False
        self._was_reset = True
        if self.render_mode == "human":
            self.render()
        x_position = self.simulation.x_position(self.states).cpu().numpy()
        return self.observations.copy(), {"x_position": x_position, "_x_position": mask.copy()}

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every entry with its action `[B, a]`; reset those that ended at the previous step."""
        if not self._was_reset:
            raise RuntimeError("call reset() before step()")
        actions = as_action_array(actions, "actions")
        if actions.shape != self.action_space.shape:
            raise ValueError(
                f"actions must have shape {self.action_space.shape} (num_envs x actuators of the "
                f"{self.config.creature}), got {actions.shape}"
            )
        if not np.isfinite(actions).all():
            raise ValueError(
                f"actions have non-finite entries in rows {np.flatnonzero(~np.isfinite(actions).all(1))}"
            )
        resetting = self._autoreset.copy()
        stepping = np.flatnonzero(~resetting)
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        info: dict[str, Any] = {}
        if resetting.any():
            self._reset_entries(np.flatnonzero(resetting))
        if stepping.size:
            # the whole batch is stepped, the entries just reset from their fresh state with relaxed
            # muscles, and their results dropped: a step of B − k entries would have another shape,
            # and a compiled step would be compiled again for every k (entries never mix)
            index = torch.from_numpy(stepping).to(self.simulation.device)
            action = actions.copy()
            action[resetting] = 0.0
            full = self.simulation.step(self.states, torch.from_numpy(action), self.activations)
            transition = _entries(full, index) if resetting.any() else full
            self.states = self.states.index_copy(0, index, transition.state)
            self.activations = self.activations.index_copy(0, index, transition.activation)
            self.observations[stepping] = transition.observation.cpu().numpy()
            self.elapsed_steps[stepping] += 1
            rewards[stepping] = transition.reward.cpu().numpy()
            failed = transition.numerical_failure.cpu().numpy()
            terminated[stepping] = failed
            if self.config.max_episode_steps is not None:
                truncated[stepping] = self.elapsed_steps[stepping] >= self.config.max_episode_steps
            stepped = ~resetting
            for key in STEP_INFO_KEYS:
                values = getattr(transition, key).cpu().numpy()
                array = np.zeros((self.num_envs, *values.shape[1:]), dtype=values.dtype)
                array[stepping] = values
                info[key], info[f"_{key}"] = array, stepped.copy()
        info["x_position"] = self.simulation.x_position(self.states).cpu().numpy()
        info["_x_position"] = np.ones(self.num_envs, dtype=bool)
        self._autoreset = terminated | truncated
        if self.render_mode == "human":
            self.render()
        return self.observations.copy(), rewards, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The first entry's side view `[render_height, render_width, 3]` uint8, or a grid of the first
        `render_entries` (see `CreatureEnv.render`); "human" shows it. None before the first reset."""
        return self._rendering.render(self.states if self._was_reset else None)

    def close_extras(self, **kwargs: Any) -> None:
        self._rendering.close()

    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(
                f"seed must be None, an int or a list of {self.num_envs} seeds, got {len(seeds)}"
            )
        return seeds

    def _reset_entries(self, entries: np.ndarray) -> None:
        """Fresh start states for `entries` from their own generators; zero activations and step counts."""
        generators = [self._generators[i] for i in entries]
        index = torch.from_numpy(entries).to(self.simulation.device)
        states = self.simulation.reset(generators)
        self.states = self.states.index_copy(0, index, states)
        self.activations = self.activations.index_fill(0, index, 0.0)
        self.observations[entries] = self.simulation.observe(states, self.activations[index]).cpu().numpy()
        self.elapsed_steps[entries] = 0
        self._rendering.reset(entries.tolist())


def _entries(transition: Transition, index: Tensor) -> Transition:
    """The rows `index` of every field of `transition`."""
    return Transition(**{field.name: getattr(transition, field.name)[index] for field in fields(Transition)})


__all__ = ["CreatureVectorEnv", "STEP_INFO_KEYS"]
