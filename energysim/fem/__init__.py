"""Finite-element building blocks: kinematics of linear simplices, pure material densities, and the
hand-written kernels that are kept beside their derived forms."""

from energysim.fem.kernels import stable_neo_hookean_stress_hessian
from energysim.fem.kinematics import deformation_gradient, shape_gradients, simplex_rest_frame
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density

__all__ = [
    "deformation_gradient",
    "lame_parameters",
    "shape_gradients",
    "simplex_rest_frame",
    "stable_neo_hookean_density",
    "stable_neo_hookean_stress_hessian",
]
