"""Stress and contact force of a rollout's states, from the scene's own terms, for export.

Stress comes from the scene's elastic terms written as a density ψ(F) (`DensityEnergy`: `NeoHookean`
and any user term), as P = ∂ψ/∂F of the very density the solver minimises (`density_stress`); contact
force from its obstacles (`Obstacle.contact_force`, −∇ of the barrier). Nothing
here repeats the physics.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from energysim.contact.obstacles import Obstacle
from energysim.energies.derived import DensityEnergy, density_stress
from energysim.fem.kinematics import deformation_gradient

if TYPE_CHECKING:
    from energysim.model.scene import Scene

logger = logging.getLogger(__name__)

STRESS_MEASURES = ("cauchy", "first_piola")
# the name of each measure's field in the exported files (the unit is Pa for both)
STRESS_FIELD_NAMES = {"cauchy": "cauchy_stress", "first_piola": "first_piola_stress"}


def _as_3x3(tensor: Tensor) -> Tensor:
    """`[..., d, d]` -> `[..., 3, 3]`: the in-plane block of a 2D tensor, zeros out of plane."""
    if tensor.shape[-1] == 3:
        return tensor
    out = tensor.new_zeros(*tensor.shape[:-2], 3, 3)
    out[..., :2, :2] = tensor
    return out


def element_stress(scene: Scene, positions: Tensor, measure: str = "cauchy") -> Tensor | None:
    """Stress of every element in each frame, shape `[F, m, 3, 3]`, in Pa; None without a density term.

    The sum over the scene's `DensityEnergy` terms on the mesh's elements (`NeoHookean`, users' terms)
    of their first Piola–Kirchhoff stress P = ∂ψ/∂F
    (force per reference area), or the Cauchy stress σ = J⁻¹ P Fᵀ (force per current area). Other
    terms (muscles, viscosity) add no stress here. In 2D (plane strain) the in-plane components are
    given and the out-of-plane row and column are 0. σ is undefined in an inverted element (J ≤ 0):
    there it is NaN, and a warning names the frames and elements.

    Args:
        scene: the model.
        positions: `[F, n, d]`, in m.
        measure: "cauchy" or "first_piola".
    """
    if measure not in STRESS_MEASURES:
        raise ValueError(f"stress must be one of {STRESS_MEASURES} or None, got {measure!r}")
    terms = [term for term in scene.terms if isinstance(term, DensityEnergy)]
    if not terms:
        return None
    with torch.no_grad():
        total = None
        for term in terms:
            F = deformation_gradient(positions[:, term.element_vertices], term.rest_edge_inverse)
            stress, _ = density_stress(term.density, F)
            total = stress if total is None else total + stress
        if measure == "first_piola":
            return _as_3x3(total)
        J = torch.linalg.det(F)
        inverted = J <= 0
        if inverted.any():
            frames, elements = torch.nonzero(inverted, as_tuple=True)
            logger.warning(
                "Cauchy stress is undefined in inverted elements (J <= 0), written as NaN: frames %s, "
                "elements %s; the first Piola-Kirchhoff stress is defined there",
                torch.unique(frames)[:10].tolist(),
                torch.unique(elements)[:10].tolist(),
            )
        safe = torch.where(inverted, torch.nan, J)
        return _as_3x3(total @ F.transpose(-1, -2) / safe[..., None, None])


def vertex_contact_force(scene: Scene, positions: Tensor) -> Tensor | None:
    """Force of the scene's obstacles on every vertex in each frame, shape `[F, n, d]`, in N.

    The sum of `Obstacle.contact_force` (the barrier's normal force, −∇ of its energy) over the
    scene's obstacle terms (ground, half-spaces, spheres, boxes); friction, a lagged term of each
    step, is not included. None when the scene has no obstacle.

    Args:
        scene: the model.
        positions: `[F, n, d]`, in m.
    """
    terms = [term for term in scene.terms if isinstance(term, Obstacle)]
    if not terms:
        return None
    with torch.no_grad():
        return sum(term.contact_force(positions) for term in terms)


__all__ = ["STRESS_FIELD_NAMES", "STRESS_MEASURES", "element_stress", "vertex_contact_force"]
