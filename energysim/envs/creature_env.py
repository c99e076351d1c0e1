"""`CreatureEnv`: one shipped soft creature on level ground as a Gymnasium environment.

The agent sets the muscle activations (or, with `activation_time_constant`, the command they
follow with first-order dynamics); the reward is the forward (+x) speed of the centre of mass
minus a control cost, as in Gymnasium's MuJoCo locomotion tasks. See docs/envs.md.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from energysim.envs.actions import as_action_array
from energysim.envs.config import FRICTION_SMOOTHING, CreatureEnvConfig
from energysim.envs.core import CreatureSimulation
from energysim.envs.env_rendering import (
    EnvRenderer,
    RenderOptions,
    available_render_modes,
    check_render_mode,
)
from energysim.envs.transition import Transition


def observation_space(simulation: CreatureSimulation) -> spaces.Box:
    """The float32 Box of one observation (unbounded: positions and velocities have no natural limit)."""
    return spaces.Box(-np.inf, np.inf, (simulation.layout.size,), dtype=np.float32)


def action_space(simulation: CreatureSimulation) -> spaces.Box:
    """One activation per actuator in [−1, 1], float32."""
    return spaces.Box(-1.0, 1.0, (simulation.num_actuators,), dtype=np.float32)


def step_info(transition: Transition, index: int) -> dict[str, Any]:
    """The info dict of batch entry `index`: every reward term, the activation the muscles hold
    (float64 `[a]`) and what the solver did."""
    return {
        "x_position": float(transition.x_position[index]),
        "x_velocity": float(transition.x_velocity[index]),
        "reward_forward": float(transition.reward_forward[index]),
        "reward_ctrl": float(transition.reward_ctrl[index]),
        "activation": transition.activation[index].detach().cpu().numpy().astype(np.float64),
        "solver_iterations": int(transition.solver_iterations[index]),
        "solver_residual": float(transition.solver_residual[index]),
        "numerical_failure": bool(transition.numerical_failure[index]),
    }


class CreatureEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """A shipped creature (`energysim.creatures`) learning to move forward on frictional ground.

    Observation (float32, see `ObservationLayout`): centre-of-mass height and velocity, positions and
    velocities of `num_markers` surface markers relative to the centre of mass, the 6D (3D) or
    (cos θ, sin θ) (2D) orientation of the body's best-fit rigid frame, and the muscles' activations.
    Action: one activation per actuator in [−1, 1] (clipped), or with `activation_time_constant` τ
    the command u that the activation a follows, ȧ = (u − a)/τ, from a = 0 at reset. Reward:
    `forward_reward_weight` × centre-of-mass x velocity over the step − `ctrl_cost_weight` × ‖u‖².
    A failed solve or a leapfrog step that blew up ends the episode (`terminated`,
    `info["numerical_failure"]`) with the last good state and observation and a finite reward.

    Args:
        creature: a name in `energysim.creatures.CREATURES`.
        frame_skip: physics steps per env step.
        dt: physics time step in s.
        forward_reward_weight, ctrl_cost_weight: reward weights (per m/s, per unit ‖u‖²).
        reset_noise_scale: uniform reset noise half-width, m for positions and m/s for velocities.
        friction: Coulomb coefficient of the ground.
        friction_smoothing: ε_v in m/s of the implicit ground's smoothed friction (default
            `envs.config.FRICTION_SMOOTHING`, 0.005 m/s); the explicit integrator's friction is exact.
        barrier_distance: d̂ in m, the range of the implicit ground's barrier; None (default):
            `envs.config.GROUND_BARRIER_DISTANCE_FRACTION` (3e-3) × the creature's rest bounding-box
            diagonal. The explicit integrator's contact is at the surface.
        solver_tol: Newton–CG velocity-residual tolerance in m/s.
        solver_max_iter: most Newton iterations per physics step; more is a numerical failure.
        solver_budget: a fixed budget of Newton iterations per physics step whose last iterate is
            kept, converged or not (its residual is in `info["solver_residual"]`); None: solve to
            `solver_tol`. See `CreatureEnvConfig`.
        solver_compile: compiled objective evaluations (see `CreatureEnvConfig`).
        max_episode_steps: truncate after this many env steps; None: never (`gymnasium.make`
            truncates through the registration's `TimeLimit` instead).
        num_markers: marker vertices in the observation.
        activation_time_constant: τ in s of the activation dynamics; 0: none, the action is the
            activation; None: the body model's 0.05 s, with every integrator (`CreatureEnvConfig`).
        integrator: "implicit_euler" (default), "tr_bdf2" or "leapfrog" (explicit substeps, fast in
            batches with `solver_compile`; see `CreatureEnvConfig`).
        substeps: leapfrog substeps per physics step; None: from the Courant limit at rest.
        viscosity: the body's Kelvin–Voigt viscosity η in Pa·s; 0: none; None: the body model's 30,
            with every integrator (`CreatureEnvConfig`).
        render_mode: None, "rgb_array" (a side view, see `SideViewRenderer`) or "human" (shown in a
            window at every reset and step; needs a display, else a RuntimeError here).
        render_width, render_height: frame size in pixels.
        camera: "follow" (centred on the centre of mass; the tiled ground scrolls past) or "fixed".
        camera_window: `(x_min, x_max)` in m a fixed camera shows; None: taken from the episode's start.
        device, dtype: where and in which precision the simulation runs.

    Attributes:
        simulation: the `CreatureSimulation` stepped with a batch of one (scene, markers, layout).
        state: the current state, shape `[1, 2·n·d]`, in m and m/s; None before the first reset.
        activation: the activations the muscles hold, shape `[1, a]` (the last action, clipped, or
            its filtered value with τ; zeros after a reset); None before the first reset.
        elapsed_steps: env steps since the last reset.
    """

    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array"], "render_fps": 60}

    def __init__(
        self,
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
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        config = CreatureEnvConfig(
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
        check_render_mode(render_mode)
        render_options = RenderOptions(render_width, render_height, camera, camera_window)
        self.simulation = CreatureSimulation(config, device=device, dtype=dtype)
        self.config = config
        self.render_mode = render_mode
        self.metadata = {
            **type(self).metadata,
            "render_modes": available_render_modes(),
            "render_fps": max(1, round(1 / self.simulation.frame_seconds)),
        }
        self.observation_space = observation_space(self.simulation)
        self.action_space = action_space(self.simulation)
        self.state: torch.Tensor | None = None  # [1, 2·n·d]
        self.activation: torch.Tensor | None = None  # [1, a]
        self.elapsed_steps = 0
        self._observation = np.zeros(self.observation_space.shape, dtype=np.float32)
        self._rendering = EnvRenderer(self.simulation, render_mode, render_options, f"energysim {creature}")

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Rest shape and zero velocity with uniform noise (`reset_noise_scale`), just touching the ground."""
        super().reset(seed=seed, options=options)
        self.state = self.simulation.reset([self.np_random])
        self.activation = self.simulation.rest_activation(1)
        self.elapsed_steps = 0
        self._observation = self._to_numpy(self.simulation.observe(self.state, self.activation))
        self._rendering.reset()
        if self.render_mode == "human":
            self.render()
        return self._observation.copy(), {"x_position": float(self.simulation.x_position(self.state)[0])}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance `frame_skip` physics steps with `action` (shape `[a]`, clipped to [−1, 1]): the
        activation, or with τ the command the activation follows."""
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        action = as_action_array(action)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"action must have shape {self.action_space.shape} (one activation per actuator of the "
                f"{self.config.creature}), got {action.shape}"
            )
        transition = self.simulation.step(self.state, torch.from_numpy(action)[None], self.activation)
        self.state = transition.state
        self.activation = transition.activation
        self.elapsed_steps += 1
        info = step_info(transition, 0)
        # a failed entry's observation is that of its last good state, finite by construction
        self._observation = self._to_numpy(transition.observation)
        terminated = info["numerical_failure"]
        limit = self.config.max_episode_steps
        truncated = limit is not None and self.elapsed_steps >= limit
        if self.render_mode == "human":
            self.render()
        return self._observation.copy(), float(transition.reward[0]), terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """An RGB side view `[render_height, render_width, 3]` uint8 of the current state in
        "rgb_array" mode; "human" shows it in the window. None otherwise and before the first reset."""
        return self._rendering.render(self.state)

    def close(self) -> None:
        self._rendering.close()
        super().close()

    @staticmethod
    def _to_numpy(observation: torch.Tensor) -> np.ndarray:
        return observation[0].detach().cpu().numpy().astype(np.float32)


__all__ = ["CreatureEnv", "action_space", "observation_space", "step_info"]
