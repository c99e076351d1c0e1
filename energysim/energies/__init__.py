"""Energy terms: each a small, pure function of positions (and the action) returning joules."""

from energysim.energies.base import ElementEnergy, EnergyTerm
from energysim.energies.derived import DensityEnergy
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.energies.gravity import Gravity
from energysim.energies.inertia import Inertia
from energysim.energies.muscles import ActuatedSprings
from energysim.energies.neo_hookean import NeoHookean
from energysim.energies.springs import Springs
from energysim.energies.viscosity import LaggedViscosity, Viscosity

__all__ = [
    "ActuatedSprings",
    "DensityEnergy",
    "ElementEnergy",
    "EnergyTerm",
    "FibreMuscles",
    "Gravity",
    "Inertia",
    "LaggedViscosity",
    "NeoHookean",
    "Springs",
    "Viscosity",
]
