"""`CreatureEnvConfig`: what defines a creature environment, checked when it is made, and the
settings that follow from it (the activation dynamics and the body viscosity in effect): one body
model, the same for the implicit and the explicit integrator.

With `activation_time_constant` τ set, the action is a command u that the muscles' activation a
follows with first-order dynamics ȧ = (u − a)/τ, integrated exactly over each physics step; without
it the action is the activation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from energysim.creatures import CREATURES
from energysim.model.scene import INTEGRATORS

# The body model both integrators share: one creature, two discretisations. Its activation dynamics
# and viscosity are properties of the body, not of a scheme, so that the implicit step as h → 0 and
# the leapfrog as its substeps grow converge to one gait (scripts/bench_env_models.py).
#
# τ in s of the activation dynamics: an elastic body takes in energy at every jump of its muscles'
# rest lengths. With instant random activations and no viscosity the leapfrog worm gained about 3 J
# a step (its weight is 0.48 kg) until it blew up within 90 steps even at 64 substeps; with
# η = 30 Pa·s a jump of every muscle from rest still blew up some of 64 worms in the first step at
# 32 substeps (the elements it squashes stiffen past the step's limits). Through τ = 0.05 s, with
# that η, 64 worms ran 300 random-action steps at 32 substeps without a failure, their kinetic
# energy levelling off near 0.2 J. For the implicit step the same τ takes the jumps out of the
# Newton solves' starting points.
ACTIVATION_TIME_CONSTANT = 0.05
# η in Pa·s of the Kelvin–Voigt viscosity (`energysim.energies.Viscosity`): leapfrog keeps every
# elastic wave, so without it the worm rings and its gait is chaotic (2 s of gait: 9.2, 11.3, 12.3
# and 14.0 cm at 32, 64, 128 and 256 substeps). With 30 Pa·s the same runs converge, 12.40, 12.18,
# 12.21 and 12.22 cm; 100 Pa·s is past the viscous kick's stable step at 32 substeps
# (`explicit.stable_damping_step`). The implicit step takes the same term as a lagged incremental
# potential.
BODY_VISCOSITY = 30.0
# the names these values had when only the explicit integrator used them
LEAPFROG_ACTIVATION_TIME_CONSTANT = ACTIVATION_TIME_CONSTANT
LEAPFROG_VISCOSITY = BODY_VISCOSITY
# ε_v in m/s of the implicit env's smoothed friction: below this slip velocity the friction force
# ramps down (static friction creeps at a fraction of it). The friction's curvature is μλ/(ε_v h),
# so a small ε_v makes Newton's quadratic model of a sticking vertex valid only over a slip of
# ε_v·h. With 16 randomly driven worms, 1e-3 m/s (the `Ground` default) took 15.4 Newton
# iterations per entry and step, 5e-3 m/s 10.9 and 1e-2 m/s 10.0; the suggested gait's 2 s
# distance moved by 0.14 % at 5e-3 (0.13896 → 0.13916 m at h = 1/60 s), far below the time step's
# own error (scripts/bench_env_models.py). Slow motions creep more with a larger ε_v: a 240-step
# PPO run's gain fell from 11 to 4 evaluation standard errors at 1e-2 m/s, and stayed at 11 at 5e-3.
# The explicit env's projected Coulomb friction has no smoothing.
FRICTION_SMOOTHING = 5e-3
# d̂ of the implicit env's ground as a fraction of the creature's rest bounding-box diagonal: three
# times the `Ground` default (IPC's 1e-3). Contact costs a randomly driven body several Newton
# iterations a step, and a wider barrier (κ by the same rule, so a third as stiff) costs fewer: 64
# worms took 6.96 instead of 7.76 per step, the quadruped and the starfish 16 % fewer, and the
# suggested gaits' 2 s distances moved by 0.08 %, 0.02 % and 3 % at h = 1/60 s, below implicit
# Euler's own time error there (docs/envs.md, "The ground's barrier range").
GROUND_BARRIER_DISTANCE_FRACTION = 3e-3


def check_integer(value: object, name: str, low: int) -> int:
    """`value` as an int >= `low`, or ValueError naming `name` (a bool is not an integer here)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def check_number(
    value: object, name: str, low: float | None = None, *, strict: bool = False, unit: str = ""
) -> float:
    """`value` as a finite float (> `low` with `strict`, else >= `low`), or ValueError naming `name`
    and the `unit` it is read in (e.g. " m/s")."""
    ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict else value >= low
    if not ok:
        bound = "" if low is None else f" {'>' if strict else '>='} {low}"
        raise ValueError(f"{name} must be a finite number{bound}{unit}, got {value!r}")
    return float(value)


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
        friction_smoothing: ε_v in m/s of the implicit ground's smoothed friction (`FRICTION_SMOOTHING`);
            the explicit integrator's projected friction is exact Coulomb and ignores it.
        barrier_distance: d̂ in m, the range of the implicit ground's barrier; None:
            `GROUND_BARRIER_DISTANCE_FRACTION` × the creature's rest bounding-box diagonal
            (`barrier_distance_for`). The barrier's stiffness κ follows the `Ground` rule (the body's
            weight rests at d̂/2). The explicit integrator's contact is at the surface and ignores it.
        solver_tol: Newton–CG velocity-residual tolerance in m/s.
        solver_max_iter: most Newton iterations per physics step; a step that needs more fails.
        solver_budget: None (default): every physics step is solved to `solver_tol`. An integer k:
            a fixed budget, every step takes at most k Newton iterations (fewer where it reaches
            `solver_tol`) and keeps the iterate it ends at, whatever velocity residual that leaves
            (reported per step as `solver_residual`); `solver_max_iter` is then unused. The iterate
            is still a descent step of the step's energy, inside every obstacle's CCD limit.
        solver_compile: evaluate the step objective by `torch.compile`d functions (`Solver(compile=
            True)`): about 3× more env steps/s for one worm on a CPU, after a compilation of 15 s to
            a minute (each new batch size that the solve's compaction meets compiles again).
        max_episode_steps: env steps before truncation, or None for none.
        num_markers: marker vertices in the observation.
        activation_time_constant: τ in s of first-order activation dynamics: the activation a
            follows the action u as ȧ = (u − a)/τ, starting from rest (a = 0) at a reset. 0: none,
            the action is the activation. None: the body model's `ACTIVATION_TIME_CONSTANT`, with
            every integrator.
        integrator: the scene's integrator (`Scene.integrator`): "implicit_euler" (Newton–CG solves
            with the IPC ground), "tr_bdf2", or "leapfrog" (explicit substeps, the ground as an
            inelastic contact with Coulomb friction; with `solver_compile`, the fast one for batches).
        substeps: leapfrog substeps per physics step; None: `stable_substeps` at the rest shape
            (32 for the worm at h = 1/60 s). Only with "leapfrog".
        viscosity: η in Pa·s of the body's Kelvin–Voigt viscosity (`Viscosity`); 0: none. None: the
            body model's `BODY_VISCOSITY`, with every integrator.
    """

    creature: str = "worm"
    frame_skip: int = 1
    dt: float = 1 / 60
    forward_reward_weight: float = 1.0
    ctrl_cost_weight: float = 1e-3
    reset_noise_scale: float = 1e-3
    friction: float = 0.8
    friction_smoothing: float = FRICTION_SMOOTHING
    barrier_distance: float | None = None
    solver_tol: float = 1e-4
    solver_max_iter: int = 100
    solver_budget: int | None = None
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
        check_integer(self.frame_skip, "frame_skip", 1)
        check_number(self.dt, "dt", 0.0, strict=True, unit=" s")
        check_number(self.forward_reward_weight, "forward_reward_weight")
        check_number(self.ctrl_cost_weight, "ctrl_cost_weight", 0.0)
        check_number(self.reset_noise_scale, "reset_noise_scale", 0.0, unit=" m (m/s)")
        check_number(self.friction, "friction", 0.0)
        check_number(self.friction_smoothing, "friction_smoothing", 0.0, strict=True, unit=" m/s")
        if self.barrier_distance is not None:
            check_number(self.barrier_distance, "barrier_distance", 0.0, strict=True, unit=" m")
        check_number(self.solver_tol, "solver_tol", 0.0, strict=True, unit=" m/s")
        check_integer(self.solver_max_iter, "solver_max_iter", 1)
        if self.solver_budget is not None:
            check_integer(self.solver_budget, "solver_budget", 1)
            if self.integrator == "leapfrog":
                raise ValueError(
                    f"solver_budget = {self.solver_budget} is for the implicit integrators; the leapfrog "
                    "solves nothing"
                )
        if not isinstance(self.solver_compile, bool):
            raise ValueError(f"solver_compile must be True or False, got {self.solver_compile!r}")
        if self.max_episode_steps is not None:
            check_integer(self.max_episode_steps, "max_episode_steps", 1)
        check_integer(self.num_markers, "num_markers", 1)
        if self.activation_time_constant is not None:
            check_number(self.activation_time_constant, "activation_time_constant", 0.0, unit=" s")
        if self.viscosity is not None:
            check_number(self.viscosity, "viscosity", 0.0, unit=" Pa·s")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        if self.substeps is not None:
            check_integer(self.substeps, "substeps", 1)
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
        return ACTIVATION_TIME_CONSTANT

    @property
    def body_viscosity(self) -> float:
        """η in Pa·s of the body's viscosity in effect (0: none); see `viscosity`."""
        if self.viscosity is not None:
            return float(self.viscosity)
        return BODY_VISCOSITY

    @property
    def filters_activation(self) -> bool:
        """Whether the activation follows the action with a time constant (`time_constant` > 0)."""
        return self.time_constant > 0

    def barrier_distance_for(self, diagonal: float) -> float:
        """d̂ in m of the implicit ground for a creature whose rest bounding box has this `diagonal`
        (m): `barrier_distance`, or `GROUND_BARRIER_DISTANCE_FRACTION` × `diagonal` where that is None."""
        if self.barrier_distance is not None:
            return float(self.barrier_distance)
        return GROUND_BARRIER_DISTANCE_FRACTION * diagonal

    def activation_decay(self) -> float:
        """exp(−h/τ): the fraction of a − u left after one physics step (0 without a time constant)."""
        tau = self.time_constant
        return math.exp(-self.dt / tau) if tau > 0 else 0.0


__all__ = [
    "ACTIVATION_TIME_CONSTANT",
    "BODY_VISCOSITY",
    "FRICTION_SMOOTHING",
    "GROUND_BARRIER_DISTANCE_FRACTION",
    "LEAPFROG_ACTIVATION_TIME_CONSTANT",
    "LEAPFROG_VISCOSITY",
    "CreatureEnvConfig",
]
