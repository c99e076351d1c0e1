"""Active fibre muscles on linear simplices: elements that contract along a rest fibre direction.

Each actuated element carries a unit fibre m in its rest shape. Its current fibre vector is F m
and its fibre stretch λ = ‖F m‖; the action shortens the stretch the fibre wants to λ* = 1 − c·a.
The energy only sees λ, so the term has no stiffness across the fibre (nor in shear): a scene
pairs it with an elastic term (`NeoHookean`) that holds the body together.
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import ElementEnergy, as_parameter, check_per_element, check_positive
from energysim.energies.muscles import contraction
from energysim.fem.hessian_entries import fibre_hessian_entries
from energysim.fem.kernels import (
    fibre_energy_and_forces_entries,
    fibre_energy_and_gradient,
    fibre_forces_entries,
    fibre_hessian_blocks,
)
from energysim.fem.kinematics import shape_gradients, simplex_rest_frame
from energysim.mesh import SimplexMesh, format_indices

# Fibres shorter than this (before normalisation) count as missing: their direction is noise.
MIN_FIBRE_LENGTH = 1e-12


def fibre_muscle_density(fibre_stretch: Tensor, stiffness: Tensor, target_stretch: Tensor) -> Tensor:
    """Active fibre energy per unit rest volume, k/2 (λ − λ*)², in J/m³.

    Args:
        fibre_stretch: λ = ‖F m‖, dimensionless, shape `[...]`.
        stiffness: k in Pa, broadcastable to `[...]`.
        target_stretch: λ* = 1 − c·a, dimensionless, broadcastable to `[...]`.
    """
    return 0.5 * stiffness * (fibre_stretch - target_stretch) ** 2


def fibre_vector(element_positions: Tensor, fibre_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Current fibre vectors F m, shape `[..., m, d]`, and fibre stretches ‖F m‖, shape `[..., m]`.

    With F = Σ_b x_b ⊗ ∇N_b, F m = Σ_b (∇N_b · m) x_b: one weight per vertex, precomputed. A tiny
    floor under the squared norm keeps the gradient and its derivative finite at F m = 0.

    Args:
        element_positions: shape `[..., m, d+1, d]`, in m.
        fibre_weights: ∇N_b · m, shape `[m, d+1]`, in 1/m.
    """
    vector = (fibre_weights[..., None] * element_positions).sum(dim=-2)
    return vector, torch.sqrt((vector * vector).sum(dim=-1) + 1e-30)


class FibreMuscles(ElementEnergy):
    """Σ_e V_e k_e/2 (‖F_e m_e‖ − (1 − c·a_e))² over the actuated elements.

    `actuators` and `fibres` give one entry per element of the scene's mesh; elements whose
    actuator is −1 are passive and left out of this term. `action[:, j]` drives actuator j and is
    clamped to [−1, 1]: a = 1 asks for a fibre stretch 1 − c (contraction), a = −1 for 1 + c, and
    without an action (a = 0) the rest shape has zero energy and zero force.

    Args:
        fibres: rest fibre direction of every mesh element, shape `[m, d]`; normalised here, and
            those of actuated elements must be finite and non-zero.
        actuators: the actuator of every mesh element, shape `[m]`, integers in [−1, a); −1: passive.
        stiffness: active stiffness k in Pa, a scalar or one per mesh element (shape `[m]`); may
            require grad.
        max_contraction: c, the fibre strain an action of 1 asks for, in (0, 1).
    """

    has_gradient_kernel = True
    has_hessian_kernel = True
    has_batch_last_kernel = True
    is_actuated = True
    is_translation_invariant = True

    def __init__(
        self,
        fibres: Tensor,
        actuators: Tensor,
        stiffness: float | Tensor = 1e5,
        max_contraction: float = 0.3,
    ) -> None:
        super().__init__()
        fibres = torch.as_tensor(fibres, dtype=torch.float64)
        actuators = torch.as_tensor(actuators)
        if fibres.ndim != 2 or fibres.shape[1] not in (2, 3):
            raise ValueError(f"fibres must have shape [m, 2] or [m, 3], got {tuple(fibres.shape)}")
        if actuators.is_floating_point() or actuators.is_complex() or actuators.dtype == torch.bool:
            raise ValueError(f"actuators must hold integers, got dtype {actuators.dtype}")
        if tuple(actuators.shape) != (fibres.shape[0],):
            raise ValueError(
                f"actuators must have shape [{fibres.shape[0]}] (one per fibre), got {tuple(actuators.shape)}"
            )
        actuators = actuators.to(torch.int64)
        bad = torch.nonzero(actuators < -1).reshape(-1)
        if bad.numel():
            raise ValueError(
                f"actuator indices must be >= -1 (-1: passive); offending elements {format_indices(bad)}"
            )
        if not (actuators >= 0).any():
            raise ValueError("no element has an actuator (all are -1): the term would be empty")
        length = fibres.norm(dim=-1)
        missing = (actuators >= 0) & ~(torch.isfinite(length) & (length > MIN_FIBRE_LENGTH))
        bad = torch.nonzero(missing).reshape(-1)
        if bad.numel():
            raise ValueError(f"actuated elements {format_indices(bad)} have zero-length or non-finite fibres")
        # Passive elements' fibres are never read; keep them finite so buffers stay clean.
        unit = torch.where(
            (actuators >= 0)[:, None], fibres / length.clamp_min(MIN_FIBRE_LENGTH)[:, None], 0.0
        )
        if not 0 < max_contraction < 1:
            raise ValueError(f"max_contraction must lie in (0, 1), got {max_contraction}")
        stiffness = as_parameter(stiffness, "stiffness")
        check_positive(stiffness, "stiffness", "Pa")
        self.register_buffer("fibres", unit)
        self.register_buffer("actuators", actuators)
        # a Python int, read on every energy evaluation: no device sync there
        self._num_actuators = int(actuators.max()) + 1
        self.register_buffer("stiffness", stiffness)
        self.max_contraction = float(max_contraction)

    @property
    def num_actuators(self) -> int:
        """How many entries of the action this term reads."""
        return self._num_actuators

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        count = self.actuators.shape[0]
        if mesh.num_elements != count or mesh.dim != self.fibres.shape[1]:
            raise ValueError(
                f"fibres and actuators describe {count} elements in {self.fibres.shape[1]}D; "
                f"the mesh has {mesh.num_elements} elements in {mesh.dim}D"
            )
        check_per_element(self.stiffness, count, "stiffness", "mesh element")
        element_index = torch.nonzero(self.actuators >= 0).reshape(-1)
        # every element actuated: the mesh's own tensor, which the elastic terms hold too, so that
        # the compiled batch evaluations gather and scatter them together (they group terms by the
        # identity of `element_vertices`): one gather and one scatter fewer per evaluation
        whole = element_index.shape[0] == mesh.num_elements
        elements = mesh.elements if whole else mesh.elements[element_index].contiguous()
        rest_edge_inverse, rest_volume = simplex_rest_frame(mesh.vertices, elements)
        fibre = self.fibres[element_index].to(rest_edge_inverse.dtype)
        self.register_buffer("element_index", element_index)
        self.register_buffer("element_vertices", elements)
        self.register_buffer("element_actuator", self.actuators[element_index])
        self.register_buffer("rest_volume", rest_volume)
        self.register_buffer("fibre_weights", (shape_gradients(rest_edge_inverse) @ fibre[..., None])[..., 0])

    def element_stiffness(self) -> Tensor:
        """k of the actuated elements in Pa, a scalar or shape `[m_active]`."""
        return self.stiffness if self.stiffness.ndim == 0 else self.stiffness[self.element_index]

    def target_stretch(self, action: Tensor | None) -> Tensor:
        """λ* = 1 − c·clamp(a, −1, 1) per actuated element, shape `[B, m_active]` (a 0-d 1 without action)."""
        if action is None:
            return self.rest_volume.new_ones(())
        return contraction(action, self.element_actuator, self.max_contraction, self.num_actuators, "muscles")

    def batch_last_forces(self, corners: list[list[Tensor]], action: Tensor | None) -> list[list[Tensor]]:
        """∂E/∂x entry by entry with the batch innermost (see `ElementEnergy.batch_last_forces`): a
        spring's force along the fibre vector (`energysim.fem.kernels.fibre_forces_entries`)."""
        return fibre_forces_entries(corners, self.fibre_weights, *self._batch_last_spring(action))

    def _batch_last_spring(self, action: Tensor | None) -> tuple[Tensor, Tensor]:
        # V k `[m, 1]` (or a scalar) and λ* `[m, B]` (or a 0-d 1) of the batch-last kernels, from the
        # transposed action `[a, B]`
        if action is None:
            target = self.rest_volume.new_ones(())
        else:
            target = 1.0 - self.max_contraction * action[self.element_actuator].clamp(-1.0, 1.0)
        stiffness = self.element_stiffness() * self.rest_volume
        return (stiffness[:, None] if stiffness.ndim else stiffness), target

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """V k/2 (λ − λ*)² `[m_active, B]` and ∂E/∂x entry by entry, batch innermost (see
        `ElementEnergy.batch_last_energy_and_forces`;
        `energysim.fem.kernels.fibre_energy_and_forces_entries`)."""
        return fibre_energy_and_forces_entries(corners, self.fibre_weights, *self._batch_last_spring(action))

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """The upper entries of every actuated element's Hessian block, batch innermost (see
        `ElementEnergy.batch_last_hessian_entries`; `energysim.fem.hessian_entries.fibre_hessian_entries`)."""
        return fibre_hessian_entries(corners, self.fibre_weights, *self._batch_last_spring(action))

    def fibre_stretch(self, x: Tensor) -> Tensor:
        """‖F m‖ of every actuated element at positions `x` `[B, n, d]`, shape `[B, m_active]`."""
        _, stretch = fibre_vector(x[:, self.element_vertices], self.fibre_weights)
        return stretch

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        _, stretch = fibre_vector(element_positions, self.fibre_weights)
        density = fibre_muscle_density(stretch, self.element_stiffness(), self.target_stretch(action))
        return self.rest_volume * density

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """`element_energy` `[B, m_active]` in J and its corner gradients `[B, m_active, d+1, d]` in N
        (`energysim.fem.kernels.fibre_energy_and_gradient`)."""
        vector, stretch = fibre_vector(element_positions, self.fibre_weights)
        return fibre_energy_and_gradient(
            vector,
            stretch,
            self.rest_volume * self.element_stiffness(),
            self.target_stretch(action),
            self.fibre_weights,
        )

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact Hessian blocks `[B, m_active, (d+1)d, (d+1)d]`, N/m (see `fibre_hessian_blocks`)."""
        vector, stretch = fibre_vector(element_positions, self.fibre_weights)
        return fibre_hessian_blocks(
            vector,
            stretch,
            self.rest_volume * self.element_stiffness(),
            self.target_stretch(action),
            self.fibre_weights,
        )
