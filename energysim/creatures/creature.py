"""The `Creature` record: a soft creature's rest mesh, muscles and suggested numbers, with its
muscle term, its open-loop gait and its scene on level ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.contact import Ground
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.energies.neo_hookean import NeoHookean
from energysim.mesh import SimplexMesh
from energysim.model.scene import Scene
from energysim.solvers import Solver

STANDARD_GRAVITY = 9.81  # m/s², the creatures' scenes pull along −y


@dataclass(frozen=True, eq=False)
class Creature:
    """A soft creature at rest, with its muscles and suggested numbers.

    Attributes:
        name: one of `CREATURES`.
        mesh: rest mesh (`TetMesh` in 3D, `TriMesh` in 2D), in m; x forward, y up, lowest vertex at y = 0.
        actuators: actuator of each element, int64, shape `[m]`; −1: passive.
        fibres: unit rest fibre direction of each element, float64, shape `[m, d]`.
        num_actuators: a, the length of the action the creature's muscles read.
        body_length: extent of the rest mesh along x, in m.
        description: what the creature is and how its actuators are laid out.
        actuator_names: a name per actuator, a of them.
        youngs_modulus: suggested E of the body in Pa.
        poissons_ratio: suggested ν.
        density: suggested ρ in kg/m³ (kg/m² per metre of depth in 2D).
        muscle_stiffness: suggested active fibre stiffness k in Pa.
        max_contraction: suggested c in (0, 1): full activation asks for fibre stretch 1 − c.
        gait_frequency: suggested open-loop gait frequency f in Hz.
        gait_amplitude: suggested activation amplitude, in [0, 1].
        gait_phases: suggested phase φ_j of each actuator, in rad.
    """

    name: str
    mesh: SimplexMesh
    actuators: Tensor
    fibres: Tensor
    num_actuators: int
    body_length: float
    description: str
    actuator_names: tuple[str, ...]
    youngs_modulus: float
    poissons_ratio: float
    density: float
    muscle_stiffness: float
    max_contraction: float
    gait_frequency: float
    gait_amplitude: float
    gait_phases: tuple[float, ...]

    @property
    def dim(self) -> int:
        """Spatial dimension d (2 or 3)."""
        return self.mesh.dim

    def muscles(
        self, stiffness: float | Tensor | None = None, max_contraction: float | None = None
    ) -> FibreMuscles:
        """The creature's `FibreMuscles` term; stiffness (Pa) and c default to the suggested ones."""
        return FibreMuscles(
            self.fibres,
            self.actuators,
            stiffness=self.muscle_stiffness if stiffness is None else stiffness,
            max_contraction=self.max_contraction if max_contraction is None else max_contraction,
        )

    def gait_action(self, time: float | Tensor) -> Tensor:
        """The suggested open-loop action A sin(2π f t + φ_j), shape `[a]` (or `[T, a]` for times `[T]`).

        Args:
            time: t in s, a number or shape `[T]`.
        """
        t = torch.as_tensor(time, dtype=torch.float64)
        phases = torch.tensor(self.gait_phases, dtype=torch.float64)
        return self.gait_amplitude * torch.sin(2 * math.pi * self.gait_frequency * t[..., None] + phases)

    def scene(
        self,
        dt: float = 1 / 60,
        friction: float = 0.8,
        solver: Solver | None = None,
        *,
        friction_smoothing: float | None = None,
        barrier_distance: float | None = None,
    ) -> Scene:
        """The creature on level ground: its suggested material and muscles, gravity along −y and an
        IPC ground at y = 0 with lagged Coulomb friction μ.

        Terms, in order: gravity (9.81 m/s² along −y), `NeoHookean` (E, ν), `muscles()`, `Ground`.

        Args:
            dt: time step h in s, > 0.
            friction: Coulomb coefficient μ of the ground, ≥ 0.
            solver: the scene's optimizer; default the `Scene` default.
            friction_smoothing: ε_v in m/s of the ground's smoothed friction (`Obstacle`); None: the
                `Ground` default.
            barrier_distance: d̂ in m, the range of the ground's barrier (`Obstacle`); None: the
                `Ground` default (1e-3 × the body's bounding-box diagonal).
        """
        up = (0.0, 1.0, 0.0) if self.dim == 3 else (0.0, 1.0)
        scene = Scene(
            self.mesh,
            density=self.density,
            dt=dt,
            gravity=tuple(-STANDARD_GRAVITY * u for u in up),
            solver=solver,
        )
        scene.add(NeoHookean(self.youngs_modulus, self.poissons_ratio))
        scene.add(self.muscles())
        options = {"friction_smoothing": friction_smoothing, "barrier_distance": barrier_distance}
        chosen = {name: value for name, value in options.items() if value is not None}
        scene.add(Ground(0.0, normal=up, friction=friction, **chosen))
        return scene


__all__ = ["STANDARD_GRAVITY", "Creature"]
