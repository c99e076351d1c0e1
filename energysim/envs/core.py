"""The batched core of the creature environments: reset, step and reward on `[B, 2·n·d]` states.

No Gymnasium here: the environments (`creature_env`, `vector_env`) are thin wrappers that convert to
numpy, count episode steps and reset finished entries. Everything is vectorised over the batch, so
one env step of B creatures is `frame_skip` batched `es.step` calls.

A step whose solve fails is a numerical failure of that batch entry: the solver here is strict, so a
solve that does not reach `solver_tol` within `solver_max_iter` Newton iterations raises
`ConvergenceError`, as does a non-finite iterate. With a fixed budget (`solver_budget`) only a
non-finite iterate fails; an unconverged one is kept, and its residual reported. The failing
entries are then found by bisection: solves of the whole batch in which the entries not under test
stand at rest with relaxed muscles, so that every solve has the batch's shape and a compiled step is
never recompiled for a smaller one. The failing entries keep their last good state and are flagged,
the others are stepped as if nothing had happened (entries of a batched solve never mix, see
`NewtonCG`). The explicit step fails the same way, by `InstabilityError`, where an entry's energy
grew past its allowance, went non-finite, or a vertex ended inside the ground
(`explicit.blown_up`); so no failed entry returns a non-finite state, observation or reward.

The configuration and its checks are in `config`, the actions' in `actions`, the `Transition` and
its reward in `transition`; their names are importable from here too.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from energysim.creatures import load_creature, resting_state, scene_ground
from energysim.energies import Viscosity
from energysim.envs.actions import as_action_array, checked_action
from energysim.envs.config import LEAPFROG_ACTIVATION_TIME_CONSTANT, LEAPFROG_VISCOSITY, CreatureEnvConfig
from energysim.envs.observation import ObservationLayout, centre_of_mass, farthest_point_markers, observe
from energysim.envs.transition import Transition, control_reward, forward_reward, representable
from energysim.integrators.step import stable_substeps, step
from energysim.solvers import ConvergenceError, ConvergenceWarning, NewtonCG

logger = logging.getLogger(__name__)


class CreatureSimulation:
    """A shipped creature on level ground, stepped in batches, with its observation and reward.

    Args:
        config: the environment's settings.
        device: where states live (default CPU).
        dtype: floating-point type of the simulation (float64 recommended; see the README).
    """

    def __init__(
        self,
        config: CreatureEnvConfig,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if not isinstance(config, CreatureEnvConfig):
            raise TypeError(f"config must be a CreatureEnvConfig, got {type(config).__name__}")
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
        self.config = config
        self.creature = load_creature(config.creature)
        # random actions make H indefinite in about half the Newton iterations: the shifted
        # factorisation keeps them on the direct (compiled) path, at the same iteration count.
        # Directions from float32 band factors took the iterations of float64 ones (64 worms,
        # 32 quadrupeds) in less time (docs/envs.md)
        budgeted = config.solver_budget is not None
        solver = NewtonCG(
            tol=config.solver_tol,
            max_iter=config.solver_budget if budgeted else config.solver_max_iter,
            strict=not budgeted,
            indefinite="shift",
            compile=config.solver_compile,
            factor_precision="single",
        )
        low, high = self.creature.mesh.bounding_box()
        # the leapfrog's contact is at the surface: its ground keeps the `Ground` default d̂, which
        # only sets how high a reset lifts the body (d̂/2)
        explicit = config.integrator == "leapfrog"
        self.scene = self.creature.scene(
            config.dt,
            config.friction,
            solver,
            friction_smoothing=config.friction_smoothing,
            barrier_distance=None if explicit else config.barrier_distance_for(float((high - low).norm())),
        )
        if config.body_viscosity > 0:
            self.scene.add(Viscosity(config.body_viscosity))
        self.scene.to(device=torch.device(device) if device is not None else None, dtype=dtype)
        self.scene.integrator = config.integrator
        if config.integrator == "leapfrog":
            self.scene.substeps = config.substeps or stable_substeps(self.scene)
        self.ground = scene_ground(self.scene)
        mesh = self.creature.mesh
        surface = mesh.surface_vertices()
        if config.num_markers > surface.numel():
            raise ValueError(
                f"num_markers must be at most {surface.numel()} (the {config.creature}'s surface vertices), "
                f"got {config.num_markers}"
            )
        self.markers = farthest_point_markers(mesh.vertices, surface, config.num_markers).to(self.device)
        self.layout = ObservationLayout.build(mesh.dim, config.num_markers, self.num_actuators)
        self.rest_state = resting_state(self.scene)

    @property
    def device(self) -> torch.device:
        return self.scene.vertex_mass.device

    @property
    def dtype(self) -> torch.dtype:
        return self.scene.vertex_mass.dtype

    @property
    def num_actuators(self) -> int:
        return self.creature.num_actuators

    @property
    def frame_seconds(self) -> float:
        """Duration of one env step, frame_skip·h, in s."""
        return self.config.frame_skip * self.config.dt

    def reset(self, generators: Sequence[np.random.Generator]) -> Tensor:
        """Start states `[B, 2·n·d]`, one per generator: rest positions and zero velocities, each with
        uniform noise of half-width `reset_noise_scale`, then moved along the ground's normal so the
        lowest vertex is d̂/2 above the ground (`resting_state`). Entry i draws its n·d position
        then n·d velocity components from `generators[i]`, so it depends on that generator alone.
        """
        scale = self.config.reset_noise_scale
        shape = (self.scene.num_vertices, self.scene.dim)
        noise = np.stack([np.stack([g.uniform(-scale, scale, shape) for _ in range(2)]) for g in generators])
        noise = torch.from_numpy(noise).to(device=self.device, dtype=self.dtype)
        return resting_state(self.scene, self.scene.rest_positions + noise[:, 0], noise[:, 1])

    def observe(self, state: Tensor, activation: Tensor) -> Tensor:
        """Observations `[B, layout.size]` (see `ObservationLayout`) at `state` `[B, 2·n·d]`."""
        x, v = self.scene.split_state(state)
        return observe(
            x,
            v,
            activation,
            self.scene.rest_positions,
            self.scene.vertex_mass,
            self.markers,
            self.ground.normal,
            float(self.ground.offset),
        )

    def x_position(self, state: Tensor) -> Tensor:
        """Centre-of-mass x of each state, `[B]`, in m."""
        return centre_of_mass(self.scene.split_state(state)[0], self.scene.vertex_mass)[:, 0]

    def check_action(self, action: Tensor) -> Tensor:
        """`action` `[B, a]` as a finite tensor on the simulation's device, clipped to [−1, 1]
        (`actions.checked_action`)."""
        return checked_action(action, self.num_actuators, self.config.creature, self.device, self.dtype)

    def rest_activation(self, batch: int) -> Tensor:
        """The activations of relaxed muscles, zeros `[batch, a]` (what a reset starts from)."""
        return torch.zeros(batch, self.num_actuators, device=self.device, dtype=self.dtype)

    def step(self, state: Tensor, action: Tensor, activation: Tensor | None = None) -> Transition:
        """`frame_skip` physics steps of every entry with its action `[B, a]` (clipped to [−1, 1]).

        Without `activation_time_constant` the clipped action u is the activation of every physics
        step. With τ, the activation starts from `activation` `[B, a]` (None: at rest, zeros) and
        before each physics step of length h becomes u + (a − u)·exp(−h/τ): the exact solution of
        ȧ = (u − a)/τ for u held constant over the step. An entry whose solve fails stops at its last
        good state for the rest of the frame, and its activation at the one it failed with. An entry
        whose frame ends finite in the simulation's precision but with an observation past float32's
        range or a non-finite reward fails too, and goes back to the state it started the frame with.
        """
        command = self.check_action(action)
        if state.ndim != 2 or state.shape[0] != command.shape[0]:
            raise ValueError(f"state must have shape [{command.shape[0]}, 2·n·d], got {list(state.shape)}")
        batch = state.shape[0]
        filtering = self.config.filters_activation
        decay = self.config.activation_decay()
        if not filtering:
            # the action itself, untouched: without τ the activation is exactly the clipped action
            current = command
        elif activation is None:
            current = self.rest_activation(batch)
        else:
            current = torch.as_tensor(activation, device=self.device).to(self.dtype)
            if current.shape != command.shape:
                expected, got = list(command.shape), list(current.shape)
                raise ValueError(f"activation must have the action's shape {expected}, got {got}")
        start = state
        x_before = self.x_position(state)
        alive = torch.ones(batch, dtype=torch.bool, device=self.device)
        iterations = torch.zeros(batch, dtype=torch.int64, device=self.device)
        residual = torch.zeros(batch, dtype=self.dtype, device=self.device)
        with torch.no_grad():
            for _ in range(self.config.frame_skip):
                if bool(alive.all()):
                    if filtering:
                        current = command + (current - command) * decay
                    state, ok, taken, left = self._solve(state, current)
                    alive, iterations, residual = ok, iterations + taken, torch.maximum(residual, left)
                    continue
                index = torch.nonzero(alive).flatten()
                if index.numel() == 0:
                    break
                if filtering:
                    # failed entries keep the activation they failed with, as they keep their state
                    advanced = command[index] + (current[index] - command[index]) * decay
                    current = current.index_copy(0, index, advanced)
                new, ok, taken, left = self._solve(state[index], current[index])
                state = state.index_copy(0, index, new)
                alive = alive.index_copy(0, index, ok)
                iterations = iterations.index_add(0, index, taken)
                residual = residual.index_copy(0, index, torch.maximum(residual[index], left))
            reward_ctrl = control_reward(command, self.config.ctrl_cost_weight)
            x_after, x_velocity, reward_forward, observation = self._outcome(state, current, x_before)
            unrepresentable = ~representable(observation, reward_forward)
            if bool(unrepresentable.any()):
                # finite in the simulation's precision, but not as the float32 observation or the
                # reward: the entry failed, and goes back to the frame's start
                logger.info(
                    "numerical failure of a %s step: entries %s left the float32 range",
                    self.config.creature,
                    torch.nonzero(unrepresentable).flatten().tolist(),
                )
                state = torch.where(unrepresentable[:, None], start, state)
                alive = alive & ~unrepresentable
                iterations = iterations.masked_fill(unrepresentable, 0)
                residual = residual.masked_fill(unrepresentable, 0.0)
                x_after, x_velocity, reward_forward, observation = self._outcome(state, current, x_before)
        return Transition(
            state=state,
            action=command,
            activation=current,
            observation=observation,
            reward=reward_forward + reward_ctrl,
            reward_forward=reward_forward,
            reward_ctrl=reward_ctrl,
            x_position=x_after,
            x_velocity=x_velocity,
            numerical_failure=~alive,
            solver_iterations=iterations,
            solver_residual=residual.masked_fill(~alive, 0.0),
        )

    def _outcome(
        self, state: Tensor, activation: Tensor, x_before: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """At the end of a frame: centre-of-mass x `[B]` (m), its velocity over the frame `[B]` (m/s),
        the forward reward `[B]` and the observation `[B, layout.size]`."""
        x_after = self.x_position(state)
        x_velocity, reward_forward = forward_reward(
            x_before, x_after, self.frame_seconds, self.config.forward_reward_weight
        )
        return x_after, x_velocity, reward_forward, self.observe(state, activation)

    def _solve(self, state: Tensor, activation: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """One physics step of every entry: new states (the old one where it failed), which entries
        succeeded `[B]`, their Newton iterations `[B]` (0 where failed) and the velocity residual in
        m/s their solve left `[B]` (0 where failed)."""
        everyone = torch.arange(state.shape[0], device=self.device)
        return self._solve_entries(state, activation, everyone)

    def _solve_entries(
        self, state: Tensor, activation: Tensor, tested: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`_solve` of the entries `tested` (indices into the batch); the others come back unchanged,
        not succeeded, with 0 iterations and 0 residual.

        The solve is of the full batch `[B, ...]`, the entries outside `tested` replaced by the rest
        state with relaxed muscles (a solve that cannot fail), so that every solve has the batch's
        shape: solving fewer entries would compile a new step for every batch size.
        """
        batch = state.shape[0]
        keep = torch.zeros(batch, dtype=torch.bool, device=self.device)
        keep[tested] = True
        if bool(keep.all()):
            trial_state, trial_activation = state, activation
        else:
            placeholder = self.rest_state.to(state).expand(batch, -1)
            trial_state = torch.where(keep[:, None], state, placeholder)
            trial_activation = torch.where(keep[:, None], activation, self.rest_activation(batch))
        try:
            with warnings.catch_warnings():
                if self.config.solver_budget is not None:
                    # a budget's unconverged solves are its design: their residual is reported
                    warnings.simplefilter("ignore", ConvergenceWarning)
                result = step(self.scene, trial_state, trial_activation)
        except ConvergenceError as error:
            if tested.numel() == 1:
                logger.info("numerical failure of a %s step: %s", self.config.creature, error)
                failed = torch.zeros(batch, dtype=torch.bool, device=self.device)
                none = torch.zeros(batch, dtype=torch.int64, device=self.device)
                return state, failed, none, torch.zeros(batch, dtype=self.dtype, device=self.device)
            # bisect to find the failing entries; the others' results do not depend on the split
            half = tested.numel() // 2
            first = self._solve_entries(state, activation, tested[:half])
            second = self._solve_entries(state, activation, tested[half:])
            in_first = torch.zeros(batch, dtype=torch.bool, device=self.device)
            in_first[tested[:half]] = True
            return (
                torch.where(in_first[:, None], first[0], second[0]),
                torch.where(in_first, first[1], second[1]),
                torch.where(in_first, first[2], second[2]),
                torch.where(in_first, first[3], second[3]),
            )
        ok = keep & torch.isfinite(result.state).all(dim=1)
        new_state = torch.where(ok[:, None], result.state, state)
        residuals = result.stats.residuals
        if residuals is None or residuals.shape != (batch,):
            residuals = torch.full((batch,), float(result.stats.residual), device=self.device)
        left = residuals.to(dtype=self.dtype, device=self.device)
        taken = result.stats.entry_iterations
        if taken is None or taken.shape != (batch,):
            taken = torch.full((batch,), result.stats.iterations, dtype=torch.int64, device=self.device)
        taken = taken.to(self.device)
        return new_state, ok, taken.masked_fill(~ok, 0), left.masked_fill(~ok, 0.0)


__all__ = [
    "LEAPFROG_ACTIVATION_TIME_CONSTANT",
    "LEAPFROG_VISCOSITY",
    "CreatureEnvConfig",
    "CreatureSimulation",
    "Transition",
    "as_action_array",
]
