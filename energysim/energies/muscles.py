"""Actuation as energy: springs whose rest length the action shortens."""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.energies.springs import Springs
from energysim.mesh import SimplexMesh
from energysim.mesh.indices import as_indices


def actuator_counts(terms: Iterable[EnergyTerm]) -> dict[str, int]:
    """The actuated terms among `terms` (those that declare `is_actuated`, as `ActuatedSprings`
    and `FibreMuscles` do), by class name, with the most action entries any of that class reads."""
    counts: dict[str, int] = {}
    for term in terms:
        if term.is_actuated:
            name = type(term).__name__
            counts[name] = max(counts.get(name, 0), term.num_actuators)
    return counts


def check_action_width(terms: Iterable[object], action: Tensor | None) -> None:
    """Refuse an action that is not one entry per actuator of the scene's `terms`.

    A term reads the action when it declares `num_actuators` (the entries it reads). The action of a
    step, `[a]` or `[B, a]`, must have a equal to the largest of them: fewer would leave actuators
    without a command, more would be entries that nothing reads, ignored without a word. A scene
    without an actuated term takes no action (a = 0 is accepted). A real-valued action is required:
    a complex one would lose its imaginary part and a bool one is no activation. Other shapes than
    `[a]` and `[B, a]` are left to the caller's shape check.

    Raises:
        ValueError: naming the action's entries per body and the actuators of the scene's terms.
    """
    if action is None:
        return
    if action.dtype == torch.bool or action.is_complex():
        raise ValueError(f"action must hold real numbers (activations in [-1, 1]), got dtype {action.dtype}")
    if action.ndim not in (1, 2):
        return
    width = action.shape[-1]
    counts = actuator_counts(terms)
    if not counts:
        if width:
            raise ValueError(
                f"action has {width} entries per body, but the scene has no actuated term (none "
                "declares num_actuators, as FibreMuscles and ActuatedSprings do): nothing would read "
                "it; pass action=None"
            )
        return
    needed = max(counts.values())
    if width != needed:
        if len(counts) == 1:
            (name,) = counts
            terms_text = f"the scene's {name} have {needed} actuators"
        else:
            listed = ", ".join(f"{name}: {count}" for name, count in counts.items())
            terms_text = f"the scene's actuated terms read {needed} ({listed})"
        raise ValueError(f"action has {width} entries per body, {terms_text}")


def contraction(
    action: Tensor, actuator_of: Tensor, max_contraction: float, needed: int, what: str
) -> Tensor:
    """1 − c·clamp(a_j, −1, 1) for each actuated thing, j = `actuator_of` of it; shape `[B, len]`.

    Raises:
        ValueError: `action` has fewer than `needed` entries.
    """
    if action.shape[-1] < needed:
        raise ValueError(f"action has {action.shape[-1]} entries; these {what} need {needed}")
    return 1.0 - max_contraction * action[..., actuator_of].clamp(-1.0, 1.0)


class ActuatedSprings(Springs):
    """Springs whose rest length is ℓ₀ (1 − c·a), a = the action of the spring's actuator.

    Each spring belongs to one actuator; `action[:, j]` drives actuator j and is clamped to
    [−1, 1], so the rest length stays within ℓ₀ (1 ± c): a contraction c < 1 keeps it positive.
    Without an action they are plain springs.

    Args:
        edges: vertex pairs, shape `[s, 2]`.
        actuators: the actuator of each spring, shape `[s]`, integers in [0, a).
        stiffness: k in N/m, a scalar or shape `[s]`.
        max_contraction: c, the fraction of the rest length an action of 1 takes off, in (0, 1).
        rest_length: ℓ₀ in m, a scalar or shape `[s]`; None measures it on the rest mesh.
    """

    is_actuated = True

    def __init__(
        self,
        edges: Tensor,
        actuators: Tensor,
        stiffness: float | Tensor = 1.0,
        max_contraction: float = 0.3,
        rest_length: float | Tensor | None = None,
    ) -> None:
        if edges is None:
            raise ValueError("actuated springs need explicit edges")
        super().__init__(edges, stiffness, rest_length)
        if not 0 < max_contraction < 1:
            raise ValueError(f"max_contraction must lie in (0, 1), got {max_contraction}")
        self.register_buffer("actuators", as_indices(actuators, "actuators", what="actuator"))
        self.max_contraction = max_contraction
        # a Python int, read on every energy evaluation: no device sync there
        self._num_actuators = int(self.actuators.max()) + 1 if self.actuators.numel() else 0

    @property
    def num_actuators(self) -> int:
        """How many entries of the action this term reads."""
        return self._num_actuators

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        super().bind(mesh, vertex_mass)
        count = self.element_vertices.shape[0]
        if tuple(self.actuators.shape) != (count,) or bool((self.actuators < 0).any()):
            raise ValueError(f"actuators must be non-negative integers of shape [{count}]")

    def target_length(self, action: Tensor | None) -> Tensor:
        """ℓ₀ (1 − c·clamp(a, −1, 1)) per spring, shape `[B, s]` (or `[s]` without an action), in m."""
        if action is None:
            return self.rest_length
        factor = contraction(action, self.actuators, self.max_contraction, self.num_actuators, "springs")
        return self.rest_length * factor
