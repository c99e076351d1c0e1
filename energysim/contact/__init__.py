"""Contact and friction as energies: static obstacles with an IPC barrier, CCD and lagged friction,
and the contact projection of explicit steps."""

from energysim.contact.barrier import barrier, barrier_derivatives, default_barrier_stiffness
from energysim.contact.friction import LaggedFriction, mollified_slip
from energysim.contact.obstacle_term import Obstacle, contact_areas
from energysim.contact.obstacles import BoxObstacle, Ground, HalfSpace, SphereObstacle

__all__ = [
    "BoxObstacle",
    "Ground",
    "HalfSpace",
    "LaggedFriction",
    "Obstacle",
    "SphereObstacle",
    "barrier",
    "barrier_derivatives",
    "contact_areas",
    "default_barrier_stiffness",
    "mollified_slip",
]
