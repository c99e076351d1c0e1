"""The batched core of the creature environments: reset, step and reward on `[B, 2·n·d]` states.

No Gymnasium here: the environments (`creature_env`, `vector_env`) are thin wrappers that convert to
numpy, count episode steps and reset finished entries. Everything is vectorised over the batch, so
one env step of B creatures is `frame_skip` batched `es.step` calls.

A step whose solve fails is a numerical failure of that batch entry: the solver here is strict, so a
solve that does not reach `solver_tol` within `solver_max_iter` Newton iterations raises
`ConvergenceError`, as does a non-finite iterate. The batch is then split in halves, recursively,
until the failing entries stand alone: they keep their last good state and are flagged, the others
are stepped as if nothing had happened (entries of a batched solve never mix, see `NewtonCG`). The
explicit step fails the same way, by `InstabilityError`, where an entry's energy grew past its
allowance, went non-finite, or a vertex ended inside the ground (`explicit.blown_up`); so no
failed entry returns a non-finite state, observation or reward.

With `activation_time_constant` τ set, the action is a command u that the muscles' activation a
follows with first-order dynamics ȧ = (u − a)/τ, integrated exactly over each physics step; without
it the action is the activation, as before.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from energysim.creatures import CREATURES, load_creature, resting_state, scene_ground
from energysim.energies import Viscosity
from energysim.envs.observation import ObservationLayout, centre_of_mass, farthest_point_markers, observe
from energysim.integrators.step import stable_substeps, step
from energysim.model.scene import INTEGRATORS
from energysim.solvers import ConvergenceError, NewtonCG

# τ of the activation dynamics the explicit integrator gets by default: an elastic body takes in
# energy at every jump of its muscles' rest lengths. With instant random activations and no
# viscosity the leapfrog worm gained about 3 J a step (its weight is 0.48 kg) until it blew up
# within 90 steps even at 64 substeps; with η = 30 Pa·s a jump of every muscle from rest still
# blew up some of 64 worms in the first step at 32 substeps (the elements it squashes stiffen past
# the step's limits). Through τ = 0.05 s, with that η, 64 worms ran 300 random-action steps at 32
# substeps without a failure, their kinetic energy levelling off near 0.2 J.
LEAPFROG_ACTIVATION_TIME_CONSTANT = 0.05
# η in Pa·s of the Kelvin–Voigt viscosity (`energysim.energies.Viscosity`) the explicit integrator
# gets by default: leapfrog keeps every elastic wave, so without it the worm rings and its gait is
# chaotic (2 s of gait: 9.2, 11.3, 12.3 and 14.0 cm at 32, 64, 128 and 256 substeps). With 30 Pa·s
# the same runs converge, 12.40, 12.18, 12.21 and 12.22 cm; 100 Pa·s is past the viscous kick's
# stable step at 32 substeps (`explicit.stable_damping_step`).
LEAPFROG_VISCOSITY = 30.0

logger = logging.getLogger(__name__)


def _check_integer(value: object, name: str, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")


def _check_number(
    value: object, name: str, unit: str, low: float | None = None, strict: bool = False
) -> None:
    ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict else value >= low
    if not ok:
        bound = "" if low is None else f" and {'>' if strict else '>='} {low}"
        raise ValueError(f"{name} must be a finite number{bound}{unit}, got {value!r}")


def as_action_array(action: object, name: str = "action") -> np.ndarray:
    """`action` as a float64 numpy array, refusing what is not real numbers: a bool, complex, string
    or object array would otherwise be converted without a word (complex losing its imaginary part).

    Raises:
        ValueError: naming `name` and the dtype it has.
    """
    array = np.asarray(action.detach().cpu() if isinstance(action, Tensor) else action)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers (activations in [-1, 1]), got dtype {array.dtype}")
    return array.astype(np.float64)


def _representable(observation: Tensor, reward: Tensor) -> Tensor:
    """Which entries' observation `[B, k]` stays finite as float32 (what the envs return) and reward
    `[B]` finite, `[B]` bool."""
    finite = torch.isfinite(observation.to(torch.float32)).all(dim=1)
    return finite & torch.isfinite(reward)


@dataclass(frozen=True)
class CreatureEnvConfig:
    """What defines a creature environment (Gymnasium MuJoCo names where they exist).

    Attributes:
        creature: a name in `energysim.creatures.CREATURES`.
        frame_skip: physics steps per env step, each with the env step's action.
        dt: physics time step h in s; an env step lasts `frame_skip`·h.
        forward_reward_weight: reward per m/s of forward (+x) centre-of-mass velocity.
        ctrl_cost_weight: cost per unit of ‖u‖² (u the clipped action).
        reset_noise_scale: half-width of the uniform noise added at reset to every rest position
            component (m) and velocity component (m/s).
        friction: Coulomb coefficient μ of the ground.
        solver_tol: Newton–CG velocity-residual tolerance in m/s.
        solver_max_iter: most Newton iterations per physics step; a step that needs more fails.
        solver_compile: evaluate the step objective by `torch.compile`d functions (`Solver(compile=
            True)`): about 3× more env steps/s for one worm on a CPU, after a compilation of 15 s to
            a minute (each new batch size that the solve's compaction meets compiles again).
        max_episode_steps: env steps before truncation, or None for none.
        num_markers: marker vertices in the observation.
        activation_time_constant: τ in s of first-order activation dynamics: the activation a
            follows the action u as ȧ = (u − a)/τ, starting from rest (a = 0) at a reset. 0: none,
            the action is the activation. None: none with an implicit integrator,
            `LEAPFROG_ACTIVATION_TIME_CONSTANT` with "leapfrog".
        integrator: the scene's integrator (`Scene.integrator`): "implicit_euler" (Newton–CG solves
            with the IPC ground), "tr_bdf2", or "leapfrog" (explicit substeps, the ground as an
            inelastic contact with Coulomb friction; with `solver_compile`, the fast one for batches).
        substeps: leapfrog substeps per physics step; None: `stable_substeps` at the rest shape
            (32 for the worm at h = 1/60 s). Only with "leapfrog".
        viscosity: η in Pa·s of the body's Kelvin–Voigt viscosity (`Viscosity`); 0: none. None:
            none with an implicit integrator (implicit Euler damps by itself), `LEAPFROG_VISCOSITY`
            with "leapfrog".
    """

    creature: str = "worm"
    frame_skip: int = 1
    dt: float = 1 / 60
    forward_reward_weight: float = 1.0
    ctrl_cost_weight: float = 1e-3
    reset_noise_scale: float = 1e-3
    friction: float = 0.8
    solver_tol: float = 1e-4
    solver_max_iter: int = 100
    solver_compile: bool = False
    max_episode_steps: int | None = None
    num_markers: int = 12
    activation_time_constant: float | None = None
    integrator: str = "implicit_euler"
    substeps: int | None = None
    viscosity: float | None = None

    def __post_init__(self) -> None:
        if self.creature not in CREATURES:
            raise ValueError(f"unknown creature {self.creature!r}; choose one of {CREATURES}")
        _check_integer(self.frame_skip, "frame_skip", 1)
        _check_number(self.dt, "dt", " s", 0.0, strict=True)
        _check_number(self.forward_reward_weight, "forward_reward_weight", "")
        _check_number(self.ctrl_cost_weight, "ctrl_cost_weight", "", 0.0)
        _check_number(self.reset_noise_scale, "reset_noise_scale", " m (m/s)", 0.0)
        _check_number(self.friction, "friction", "", 0.0)
        _check_number(self.solver_tol, "solver_tol", " m/s", 0.0, strict=True)
        _check_integer(self.solver_max_iter, "solver_max_iter", 1)
        if not isinstance(self.solver_compile, bool):
            raise ValueError(f"solver_compile must be True or False, got {self.solver_compile!r}")
        if self.max_episode_steps is not None:
            _check_integer(self.max_episode_steps, "max_episode_steps", 1)
        _check_integer(self.num_markers, "num_markers", 1)
        if self.activation_time_constant is not None:
            _check_number(self.activation_time_constant, "activation_time_constant", " s", 0.0)
        if self.viscosity is not None:
            _check_number(self.viscosity, "viscosity", " Pa·s", 0.0)
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        if self.substeps is not None:
            _check_integer(self.substeps, "substeps", 1)
            if self.integrator != "leapfrog":
                raise ValueError(
                    f"substeps = {self.substeps} is for integrator='leapfrog'; an implicit step takes "
                    "dt whole"
                )

    @property
    def time_constant(self) -> float:
        """τ in s of the activation dynamics in effect (0: none); see `activation_time_constant`."""
        if self.activation_time_constant is not None:
            return float(self.activation_time_constant)
        return LEAPFROG_ACTIVATION_TIME_CONSTANT if self.integrator == "leapfrog" else 0.0

    @property
    def body_viscosity(self) -> float:
        """η in Pa·s of the body's viscosity in effect (0: none); see `viscosity`."""
        if self.viscosity is not None:
            return float(self.viscosity)
        return LEAPFROG_VISCOSITY if self.integrator == "leapfrog" else 0.0

    @property
    def filters_activation(self) -> bool:
        """Whether the activation follows the action with a time constant (`time_constant` > 0)."""
        return self.time_constant > 0

    def activation_decay(self) -> float:
        """exp(−h/τ): the fraction of a − u left after one physics step (0 without a time constant)."""
        tau = self.time_constant
        return math.exp(-self.dt / tau) if tau > 0 else 0.0


@dataclass(frozen=True)
class Transition:
    """One env step of B entries; tensors on the simulation's device.

    Attributes:
        state: the new states `[B, 2·n·d]`; a failed entry keeps its last good state.
        action: the actions u, clipped to [−1, 1], `[B, a]`.
        activation: the activations of the last physics step each entry attempted, `[B, a]`: `action`
            itself without a time constant, else its filtered value (`CreatureEnvConfig`).
        observation: `[B, layout.size]`, at `state` and `activation`.
        reward: `reward_forward + reward_ctrl`, `[B]`.
        reward_forward: `forward_reward_weight` × `x_velocity`, `[B]`.
        reward_ctrl: −`ctrl_cost_weight` × ‖action‖², `[B]` (on the command, as MuJoCo's control cost).
        x_position: centre-of-mass x at `state`, `[B]`, in m.
        x_velocity: centre-of-mass x displacement over the step / (frame_skip·h), `[B]`, in m/s.
        numerical_failure: which entries failed, `[B]`, bool.
        solver_iterations: Newton iterations of the solves that made `state` (summed over the
            frame; the count of the batched solve each entry took part in), `[B]`, int64.
    """

    state: Tensor
    action: Tensor
    activation: Tensor
    observation: Tensor
    reward: Tensor
    reward_forward: Tensor
    reward_ctrl: Tensor
    x_position: Tensor
    x_velocity: Tensor
    numerical_failure: Tensor
    solver_iterations: Tensor


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
        # factorisation keeps them on the direct (compiled) path, at the same iteration count
        solver = NewtonCG(
            tol=config.solver_tol,
            max_iter=config.solver_max_iter,
            strict=True,
            indefinite="shift",
            compile=config.solver_compile,
        )
        self.scene = self.creature.scene(config.dt, config.friction, solver)
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
        """`action` `[B, a]` as a finite tensor on the simulation's device, clipped to [−1, 1]."""
        if not isinstance(action, Tensor):
            action = as_action_array(action)
        elif action.dtype == torch.bool or action.is_complex():
            raise ValueError(
                f"action must hold real numbers (activations in [-1, 1]), got dtype {action.dtype}"
            )
        action = torch.as_tensor(action, device=self.device).to(self.dtype)
        if action.ndim != 2 or action.shape[1] != self.num_actuators:
            raise ValueError(
                f"action must have shape [B, {self.num_actuators}] (one activation per actuator of the "
                f"{self.config.creature}), got {list(action.shape)}"
            )
        if not torch.isfinite(action).all():
            bad = torch.nonzero(~torch.isfinite(action).all(dim=1)).flatten().tolist()
            raise ValueError(f"action has non-finite entries in batch entries {bad}")
        return action.clamp(-1.0, 1.0)

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
            # the action itself, untouched: the default stays exactly what it was before τ existed
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
        with torch.no_grad():
            for _ in range(self.config.frame_skip):
                if bool(alive.all()):
                    if filtering:
                        current = command + (current - command) * decay
                    state, ok, taken = self._solve(state, current)
                    alive, iterations = ok, iterations + taken
                    continue
                index = torch.nonzero(alive).flatten()
                if index.numel() == 0:
                    break
                if filtering:
                    # failed entries keep the activation they failed with, as they keep their state
                    advanced = command[index] + (current[index] - command[index]) * decay
                    current = current.index_copy(0, index, advanced)
                new, ok, taken = self._solve(state[index], current[index])
                state = state.index_copy(0, index, new)
                alive = alive.index_copy(0, index, ok)
                iterations = iterations.index_add(0, index, taken)
            reward_ctrl = -self.config.ctrl_cost_weight * command.square().sum(dim=1)
            x_after, x_velocity, reward_forward, observation = self._outcome(state, current, x_before)
            unrepresentable = ~_representable(observation, reward_forward)
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
        )

    def _outcome(
        self, state: Tensor, activation: Tensor, x_before: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """At the end of a frame: centre-of-mass x `[B]` (m), its velocity over the frame `[B]` (m/s),
        the forward reward `[B]` and the observation `[B, layout.size]`."""
        x_after = self.x_position(state)
        x_velocity = (x_after - x_before) / self.frame_seconds
        reward_forward = self.config.forward_reward_weight * x_velocity
        return x_after, x_velocity, reward_forward, self.observe(state, activation)

    def _solve(self, state: Tensor, activation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One physics step of every entry: new states (the old one where it failed), which entries
        succeeded `[B]`, and their Newton iterations `[B]` (0 where failed)."""
        batch = state.shape[0]
        try:
            result = step(self.scene, state, activation)
        except ConvergenceError as error:
            if batch == 1:
                logger.info("numerical failure of a %s step: %s", self.config.creature, error)
                failed = torch.zeros(1, dtype=torch.bool, device=self.device)
                return state, failed, torch.zeros(1, dtype=torch.int64, device=self.device)
            # split to find the failing entries; the others' results do not depend on the split
            half = batch // 2
            first = self._solve(state[:half], activation[:half])
            second = self._solve(state[half:], activation[half:])
            return tuple(torch.cat(pair) for pair in zip(first, second, strict=True))  # type: ignore[return-value]
        ok = torch.isfinite(result.state).all(dim=1)
        new_state = torch.where(ok[:, None], result.state, state)
        return new_state, ok, ok.to(torch.int64) * result.stats.iterations


__all__ = ["CreatureEnvConfig", "CreatureSimulation", "Transition", "as_action_array"]
