"""energysim: differentiable soft-body simulation in PyTorch, where every force is an energy's gradient.

One implicit-Euler step is the minimisation
x_{n+1} = argmin_x ½h⁻²‖x − (x_n + h v_n)‖²_M + Σ_i E_i(x) by a pluggable optimizer.

Installed as the distribution ``torch-energysim``; imported as ``energysim``.
"""

# The one place the version is written: pyproject.toml reads it from here (setuptools' `attr`).
__version__ = "0.2.0"

from energysim.contact import BoxObstacle, Ground, HalfSpace, Obstacle, SphereObstacle
from energysim.creatures import CREATURES, Creature, load_creature, resting_state
from energysim.energies import (
    ActuatedSprings,
    DensityEnergy,
    ElementEnergy,
    EnergyTerm,
    FibreMuscles,
    Gravity,
    Inertia,
    NeoHookean,
    Springs,
    Viscosity,
)
from energysim.integrators.adjoint import GradientError
from energysim.integrators.explicit import InstabilityError
from energysim.integrators.rollout import rollout
from energysim.integrators.step import StepResult, solve_static, stable_substeps, step, timestep
from energysim.mesh import MeshFileError, MeshFileNotFoundError, SimplexMesh, TetMesh, TriMesh, load_mesh
from energysim.model.scene import EXPLICIT_INTEGRATORS, IMPLICIT_INTEGRATORS, INTEGRATORS, Scene
from energysim.objective.objective import Objective
from energysim.solvers import (
    LBFGS,
    Adam,
    ConvergenceError,
    ConvergenceWarning,
    NewtonCG,
    Solver,
    SolverResult,
)
from energysim.viewer import Viewer

# Sub-packages that pull in optional or heavier dependencies load on first use: `es.export`
# (meshio, pyvista on render) and `es.envs` (Gymnasium), so that `import energysim` stays light.
_LAZY_SUBPACKAGES = ("envs", "export")


def __getattr__(name: str) -> object:
    if name in _LAZY_SUBPACKAGES:
        import importlib

        return importlib.import_module(f"energysim.{name}")
    raise AttributeError(f"module 'energysim' has no attribute {name!r}")


__all__ = [
    "ActuatedSprings",
    "BoxObstacle",
    "Ground",
    "HalfSpace",
    "Obstacle",
    "SphereObstacle",
    "GradientError",
    "rollout",
    "LBFGS",
    "Adam",
    "ConvergenceError",
    "ConvergenceWarning",
    "CREATURES",
    "DensityEnergy",
    "Creature",
    "ElementEnergy",
    "FibreMuscles",
    "EnergyTerm",
    "Gravity",
    "EXPLICIT_INTEGRATORS",
    "IMPLICIT_INTEGRATORS",
    "INTEGRATORS",
    "InstabilityError",
    "MeshFileError",
    "MeshFileNotFoundError",
    "Inertia",
    "NeoHookean",
    "NewtonCG",
    "Objective",
    "Scene",
    "SimplexMesh",
    "Solver",
    "SolverResult",
    "Springs",
    "StepResult",
    "TetMesh",
    "TriMesh",
    "Viscosity",
    "Viewer",
    "load_creature",
    "load_mesh",
    "resting_state",
    "solve_static",
    "stable_substeps",
    "step",
    "timestep",
]
