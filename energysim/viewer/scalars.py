"""Per-element quantities worth colouring a trajectory by, computed from a scene's energy terms.

Kept apart from the server: the server takes plain arrays and knows nothing of energies.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.energies import NeoHookean
from energysim.model.scene import Scene


def strain_energy_density(scene: Scene, states: Tensor | Sequence[Tensor]) -> Tensor:
    """Elastic energy per unit rest volume of each element in each frame, shape `[F, m]`, in J/m³.

    The sum over the scene's `NeoHookean` terms of element energy / element rest volume (J/m² per metre
    of depth in 2D). Zero in the rest shape, so it shows where a body is strained.

    Args:
        scene: a scene with at least one `NeoHookean` term.
        states: flat states, a list of `[2·num_dofs]` or a stack `[F, 2·num_dofs]`.
    """
    terms = [term for term in scene.terms if isinstance(term, NeoHookean)]
    if not terms:
        raise ValueError("the scene has no NeoHookean term, so no strain energy density to show")
    if not isinstance(states, Tensor):
        states = torch.stack(list(states))
    with torch.no_grad():
        x, _ = scene.split_state(states.detach().to(scene.vertex_mass))
        density = torch.zeros(x.shape[0], scene.mesh.num_elements, dtype=x.dtype, device=x.device)
        for term in terms:
            density = density + term.element_energy(x[:, term.element_vertices], None) / term.rest_volume
    return density
