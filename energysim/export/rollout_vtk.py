"""Any rollout of a scene as a VTK time series: positions, velocities, strain energy, stress, contact
force, activations, and the obstacles beside it.

    pvd = export_rollout(scene, states, "out/run", actions=actions)   # open the .pvd in ParaView

The arrays come from the scene's own terms: strain energy density and stress from its `NeoHookean`
terms, contact force from its obstacles, activation from its `FibreMuscles` (per element) and
`ActuatedSprings` (per vertex). Nothing here steps the scene: it reads states that a rollout already
produced.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from energysim.energies import ActuatedSprings, NeoHookean
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.viewer.scalars import strain_energy_density

from .fields import STRESS_FIELD_NAMES, STRESS_MEASURES, element_stress, vertex_contact_force
from .obstacle_geometry import obstacle_surfaces
from .series import SINGLE_FILE_FORMATS, VTKSeries

if TYPE_CHECKING:
    from energysim.model.scene import Scene


def _stack(values: Tensor | Sequence[Tensor], name: str) -> Tensor:
    if isinstance(values, Tensor):
        return values.detach()
    values = [torch.as_tensor(v).detach() for v in values]
    if not values:
        raise ValueError(f"{name} is empty")
    for k, value in enumerate(values):
        if value.shape != values[0].shape:
            raise ValueError(
                f"{name}[{k}] has shape {tuple(value.shape)}, {name}[0] has {tuple(values[0].shape)}: "
                "all must match"
            )
    return torch.stack(values)


def _per_state_actions(actions: Tensor, num_states: int) -> Tensor:
    """One action per state, `[F, a]`: a row per state is kept; a row per step shifts by one.

    With one action per step (as `energysim.integrators.rollout` takes them) state k > 0 was solved with the
    action of step k − 1, so that is the activation it shows; the initial state had none (zero).
    """
    if actions.ndim != 2 or actions.shape[0] not in (num_states, num_states - 1):
        raise ValueError(
            f"actions must have shape [{num_states - 1}, a] (one per step) or [{num_states}, a] "
            f"(one per state), got {tuple(actions.shape)}"
        )
    if actions.shape[0] == num_states:
        return actions
    return torch.cat([torch.zeros_like(actions[:1]), actions])


def element_activation(scene: Scene, actions: Tensor) -> Tensor | None:
    """Activation of every element in each frame, shape `[F, m]`, dimensionless in [−1, 1].

    From the scene's `FibreMuscles` terms: the action of each element's actuator, clamped to [−1, 1]
    as the muscle applies it (1: full contraction); averaged where several terms drive one element,
    and 0 for passive elements. None when the scene has no `FibreMuscles` term.

    Args:
        scene: the model.
        actions: one action per frame, shape `[F, a]`.
    """
    terms = [term for term in scene.terms if isinstance(term, FibreMuscles)]
    if not terms:
        return None
    frames, count = actions.shape[0], scene.mesh.num_elements
    total = actions.new_zeros(frames, count)
    drivers = actions.new_zeros(count)
    for term in terms:
        _check_width(actions, term.num_actuators, type(term).__name__)
        activation = actions[:, term.element_actuator].clamp(-1.0, 1.0)
        total = total.index_add(1, term.element_index, activation)
        drivers = drivers.index_add(0, term.element_index, torch.ones_like(activation[0]))
    return total / drivers.clamp_min(1.0)


def vertex_spring_activation(scene: Scene, actions: Tensor) -> Tensor | None:
    """Mean activation of the actuated springs at each vertex per frame, shape `[F, n]`, in [−1, 1].

    From the scene's `ActuatedSprings` terms (clamped as they apply it); 0 at vertices without an
    actuated spring. None when the scene has none.

    Args:
        scene: the model.
        actions: one action per frame, shape `[F, a]`.
    """
    terms = [term for term in scene.terms if isinstance(term, ActuatedSprings)]
    if not terms:
        return None
    frames, count = actions.shape[0], scene.num_vertices
    total = actions.new_zeros(frames, count)
    springs = actions.new_zeros(count)
    for term in terms:
        _check_width(actions, term.num_actuators, type(term).__name__)
        activation = actions[:, term.actuators].clamp(-1.0, 1.0)
        ends = term.element_vertices.reshape(-1)
        total = total.index_add(1, ends, activation.repeat_interleave(2, dim=1))
        springs = springs.index_add(0, ends, torch.ones_like(ends, dtype=actions.dtype))
    return total / springs.clamp_min(1.0)


def _check_width(actions: Tensor, needed: int, what: str) -> None:
    if actions.shape[1] < needed:
        raise ValueError(f"actions have {actions.shape[1]} entries; the scene's {what} need {needed}")


def export_rollout(
    scene: Scene,
    states: Tensor | Sequence[Tensor],
    folder: str | os.PathLike[str],
    *,
    actions: Tensor | Sequence[Tensor] | None = None,
    times: Tensor | Sequence[float] | None = None,
    every: int = 1,
    name: str = "frame",
    stress: str | None = "cauchy",
    surface_only: bool = False,
    single_file: str | None = None,
) -> Path:
    """Write states of `scene` as ``{name}_00000.vtu``, … and ``{name}.pvd`` in `folder`; return the ``.pvd``.

    Each ``.vtu`` holds the positions (the points, in m) with point data ``velocity`` (m/s) and
    ``displacement`` from the rest shape (m), field data ``TimeValue`` (the frame's time in s, which
    ParaView shows), and when the scene has the terms for them cell data ``strain_energy_density``
    (J/m³, J/m² per metre of depth in 2D; `NeoHookean`), ``cauchy_stress`` or ``first_piola_stress``
    (Pa, 9 components, row-major 3×3; `NeoHookean`, see `energysim.export.fields.element_stress`),
    ``actuator`` and ``activation`` (`FibreMuscles`; actuator −1: passive), and point data
    ``contact_force`` (N, the obstacles' barrier force) and ``spring_activation`` (`ActuatedSprings`).
    Activations need `actions`; without them they are left out.

    When the scene has obstacles (ground, half-spaces, spheres, boxes) they are written once, as static
    triangles with cell data ``obstacle`` (their order among the scene's obstacle terms), into a second
    series ``{name}_obstacles.pvd`` of one frame at the first time: open both ``.pvd`` files in ParaView
    (a static part shows at every time and keeps the body's colour map free of it). A half-space is a
    rectangle around the range the body covers over the frames (see
    `energysim.export.obstacle_geometry`).

    The frames go into a new folder ``{name}.<random>/`` beside the ``.pvd`` (see
    `energysim.export.series`); the ``.pvd`` is switched to them in one atomic rename once all are on
    disk, and only then are the frames of an older series of the same name removed. So `folder` holds,
    at every instant, either the complete older series or the complete new one, even if the export
    fails or the process is killed; files the library did not write are never removed. Every input is
    checked before anything is written.

    Args:
        scene: the model the states belong to.
        states: F states, a stack `[F, 2·num_dofs]` or a list of `[2·num_dofs]` (one batch entry:
            index a batched rollout first).
        folder: output folder (created with its parents).
        actions: `[F − 1, a]` (one per step, as `es.rollout` takes them: frame k shows the action
            of the step that ended there, frame 0 zero) or `[F, a]` (one per state).
        times: time of each state in s, shape `[F]`, strictly increasing; default k · `scene.dt`.
        every: write every `every`-th state, and always the last.
        name: file stem.
        stress: "cauchy" (σ, ``cauchy_stress``), "first_piola" (P, ``first_piola_stress``) or None (no
            stress field).
        surface_only: write only the boundary triangles (`mesh.surface()`) and their vertices, with the
            point fields restricted to them and each triangle carrying the cell fields of its element
            (3D meshes only): smaller files, the same picture.
        single_file: "xdmf": also write the series as ``{name}.xdmf`` beside the ``.pvd`` (one XDMF file,
            its arrays in one HDF5 file; needs h5py), published with the ``.pvd``; None: no such file.

    Raises:
        ValueError: no states, states, actions or times of the wrong shape, non-finite states, actions
            or times, `every` < 1, an unknown `stress` or `single_file`, `surface_only` not a bool or
            for a 2D mesh.
        ImportError: `single_file="xdmf"` without h5py.
        NotADirectoryError: `folder` (or a folder above it) is a file.
        PermissionError: `folder` cannot be written.
    """
    states = _stack(states, "states")
    if states.ndim != 2 or states.shape[-1] != 2 * scene.num_dofs:
        raise ValueError(
            f"states must have shape [F, {2 * scene.num_dofs}] or be a list of [{2 * scene.num_dofs}] "
            f"(positions then velocities of {scene.num_vertices} vertices in {scene.dim}D), "
            f"got {tuple(states.shape)}; for a batched rollout index one batch entry first"
        )
    if states.shape[0] == 0:
        raise ValueError("states is empty: nothing to export")
    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"every must be an integer >= 1, got {every!r}")
    if stress is not None and stress not in STRESS_MEASURES:
        raise ValueError(f"stress must be one of {STRESS_MEASURES} or None, got {stress!r}")
    if not isinstance(surface_only, bool):
        raise ValueError(f"surface_only must be True or False, got {surface_only!r}")
    if surface_only and scene.dim != 3:
        raise ValueError(
            "surface_only needs a 3D mesh (its boundary is triangles); a 2D mesh is drawn whole already"
        )
    if single_file not in SINGLE_FILE_FORMATS:
        raise ValueError(f"single_file must be one of {SINGLE_FILE_FORMATS}, got {single_file!r}")
    if not (states.is_floating_point() or states.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"states must be real numbers, got dtype {states.dtype}")
    states = states.to(scene.vertex_mass)
    x, v = scene.split_state(states)
    frames = x.shape[0]
    if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
        bad = torch.nonzero(~(torch.isfinite(x).all(dim=(1, 2)) & torch.isfinite(v).all(dim=(1, 2))))
        raise ValueError(f"states {bad.reshape(-1)[:10].tolist()} hold NaN or inf")
    if times is None:
        time_values = [k * scene.dt for k in range(frames)]
    else:
        # kept as Python floats: a list through torch would be rounded to float32
        values = times.detach().reshape(-1).tolist() if isinstance(times, Tensor) else list(times)
        time_values = [float(t) for t in values]
        if len(time_values) != frames:
            raise ValueError(f"times must have {frames} entries (one per state), got {len(time_values)}")
        if not all(math.isfinite(t) for t in time_values):
            raise ValueError("times must be finite")
        if any(later <= earlier for earlier, later in zip(time_values[:-1], time_values[1:], strict=True)):
            raise ValueError("times must be strictly increasing")

    cell_data: dict[str, Tensor] = {}
    point_data: dict[str, Tensor] = {}
    if any(isinstance(term, NeoHookean) for term in scene.terms):
        cell_data["strain_energy_density"] = strain_energy_density(scene, states)
    if stress is not None:
        element_stresses = element_stress(scene, x, stress)
        if element_stresses is not None:
            cell_data[STRESS_FIELD_NAMES[stress]] = element_stresses.reshape(frames, -1, 9)
    contact_force = vertex_contact_force(scene, x)
    if contact_force is not None:
        point_data["contact_force"] = contact_force
    if actions is not None:
        per_state = _per_state_actions(_stack(actions, "actions").to(x), frames)
        if not torch.isfinite(per_state).all():
            bad = torch.nonzero(~torch.isfinite(per_state).all(dim=1)).reshape(-1)
            bad = bad - (per_state.shape[0] - len(actions))  # rows of `actions` as given
            raise ValueError(f"actions {bad[:10].tolist()} hold NaN or inf")
        fibre_activation = element_activation(scene, per_state)
        if fibre_activation is not None:
            cell_data["activation"] = fibre_activation
        spring_activation = vertex_spring_activation(scene, per_state)
        if spring_activation is not None:
            point_data["spring_activation"] = spring_activation
    actuator = _element_actuators(scene)

    written = sorted({*range(0, frames, every), frames - 1})
    rest = scene.rest_positions
    cells, keep_vertices, keep_cells = scene.mesh.elements, slice(None), slice(None)
    if surface_only:
        facets, owners = scene.mesh.surface_with_elements()
        keep_vertices, cells = torch.unique(facets, return_inverse=True)
        keep_cells = owners
    obstacles = obstacle_surfaces(scene, x[written])
    series = VTKSeries(folder, cells, name=name, single_file=single_file)
    with series:  # committed when every frame is on disk, discarded if anything goes wrong
        for k in written:
            frame_cells = {key: value[k][keep_cells] for key, value in cell_data.items()}
            if actuator is not None:
                frame_cells["actuator"] = actuator[keep_cells]
            frame_points = {
                "velocity": v[k],
                "displacement": x[k] - rest,
                **{key: value[k] for key, value in point_data.items()},
            }
            series.write(
                time_values[k],
                x[k][keep_vertices],
                point_data={key: value[keep_vertices] for key, value in frame_points.items()},
                cell_data=frame_cells,
                field_data={"TimeValue": time_values[k]},
            )
        if obstacles is not None:
            points, triangles, owner = obstacles
            # committed just before the body's series: a failure before then leaves both as they were
            with VTKSeries(folder, triangles, name=f"{name}_obstacles") as static:
                static.write(time_values[written[0]], points, cell_data={"obstacle": owner})
    return series.pvd_path


def _element_actuators(scene: Scene) -> Tensor | None:
    """The actuator of every element from the scene's `FibreMuscles`, shape `[m]`, −1 passive."""
    actuator = None
    for term in scene.terms:
        if isinstance(term, FibreMuscles):
            mine = term.actuators
            actuator = mine if actuator is None else torch.where(mine >= 0, mine, actuator)
    return actuator


__all__ = ["element_activation", "export_rollout", "vertex_spring_activation"]
