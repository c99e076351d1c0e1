"""A step objective's evaluations as `torch.compile`d functions (opt-in: `Solver(compile=True)`).

A small body's Newton iteration is hundreds of tiny tensor operations, and in eager PyTorch on a
CPU their dispatch costs more than their arithmetic: the 360-tet worm's energy and gradient take
2,000 operations a call. Compiled, the element kernels of all terms fuse into a few loops. Seven
functions are compiled, each over the objective's whole list of terms: the energy, the energy with
its gradient, a run of explicit leapfrog substeps (`energysim.integrators.explicit`), every term's energy
apart (TR-BDF2's energy check), a line search's first trial (the CCD step limit, then the energy,
gradient, slopes and residual where it lands), the warm start's candidates cut back to
admissible steps with their energies, and the Hessian of a small system, its element blocks
scattered straight into a dense `[B, N, N]` matrix or into LAPACK's band storage
(`energysim.linalg.banded`), no CSR in between.
They compute what the eager paths compute, up to the order of floating-point operations (the
tests compare them to 1e-9 relative, and a 0.2 s worm walk to 1e-10 m with the same iterations).

Measured with `python scripts/bench_creatures.py` without and with `--compile` (mean ms per step
over a 5 s walk): the worm 42.5 → 11.8, the 2D crawler 22.1 → 8.5 and the 2D walker 25.6 → 10.2
(all three faster than real time). Bodies over 600 DOFs take the band direct solve only compiled
(`NewtonCG.direct_limit`): the quadruped (888 tets) 150.6 → 46.0 against the eager CG path. The
first call per scene pays the compilation (about 15 s for the worm, a few seconds when torch's
on-disk cache already holds it); a new scene, step size or batch size
compiles again, and a batch that drops its converged entries meets several sizes (six worms: about
a minute the first time). It pays off for long runs of one scene: walking, training. Where compiling
fails (no C++ compiler, an unsupported operation), a warning says so once and the eager paths take
over.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from energysim.contact.obstacles import project_contacts
from energysim.energies.base import ElementEnergy, EnergyTerm, has_element_blocks, is_dissipative
from energysim.linalg.assembly import dof_indices
from energysim.linalg.banded import (
    band_diagonal_positions,
    band_length,
    band_positions,
    eliminate_fixed_in_bands,
)
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.linalg.caching import IdentityCache


def has_closed_forms(terms: Sequence[EnergyTerm], *, hessian: bool) -> bool:
    """Whether every term has a closed-form gradient (and, with `hessian`, a closed-form Hessian:
    a per-vertex diagonal or element blocks), which is what the compiled functions call."""
    for term in terms:
        if isinstance(term, ElementEnergy):
            gradient = hasattr(term, "element_energy_and_gradient") or hasattr(term, "element_gradient")
            blocks = term.is_linear or hasattr(term, "element_hessian")
        else:
            gradient = type(term).value_and_gradient is not EnergyTerm.value_and_gradient
            blocks = term.is_linear or hasattr(term, "hessian_diagonal")
        if not gradient or (hessian and not blocks):
            return False
    return True


def _at(term: EnergyTerm, x: Tensor, anchor: Tensor | None) -> Tensor:
    # as `Objective`: linear terms (gravity) see x − anchor, which keeps their rounding small
    return x - anchor if term.is_linear and anchor is not None else x


def _energy(terms: tuple[EnergyTerm, ...], anchor: Tensor | None, action: Tensor | None, x: Tensor) -> Tensor:
    total = x.new_zeros(x.shape[0])
    for term in terms:
        total = total + term(_at(term, x, anchor), action)
    return total


def _term_energies(terms: tuple[EnergyTerm, ...], action: Tensor | None, x: Tensor) -> Tensor:
    return torch.stack([term(x, action) for term in terms])


def _energy_and_gradient(
    terms: tuple[EnergyTerm, ...], anchor: Tensor | None, action: Tensor | None, free: Tensor, x: Tensor
) -> tuple[Tensor, Tensor]:
    total = x.new_zeros(x.shape[0])
    gradient = torch.zeros_like(x)
    for term in terms:
        value, term_gradient = term.value_and_gradient(_at(term, x, anchor), action)
        total = total + value
        gradient = gradient + term_gradient
    return total, gradient * free[:, None].to(gradient.dtype)


def step_limit(terms: Sequence[EnergyTerm], x: Tensor, direction: Tensor) -> Tensor:
    """The largest fraction of `direction` every term allows from `x`, `[B]`, at most 1, unchecked
    (`EnergyTerm.step_limit`): NaN where `x` is not admissible. Traced inside the compiled functions,
    and `Objective.max_step`'s eager evaluation."""
    limit = x.new_ones(x.shape[0])
    for term in terms:
        term_limit = term.step_limit(x, direction)
        if term_limit is not None:
            limit = torch.minimum(limit, term_limit)
    return limit


def _cut_back(
    terms: tuple[EnergyTerm, ...],
    anchor: Tensor | None,
    action: Tensor | None,
    origin: Tensor,
    targets: tuple[Tensor, ...],
) -> tuple[Tensor, Tensor, Tensor]:
    energies, cuts, limits = [_energy(terms, anchor, action, origin)], [], []
    for target in targets:
        motion = target - origin
        limit = step_limit(terms, origin, motion)
        cuts.append(origin + limit[:, None, None] * motion)
        energies.append(_energy(terms, anchor, action, cuts[-1]))
        limits.append(limit)
    return torch.stack(cuts), torch.stack(energies), torch.stack(limits)


def _trial(
    terms: tuple[EnergyTerm, ...],
    anchor: Tensor | None,
    action: Tensor | None,
    free: Tensor,
    residual_scale: Tensor,
    x: Tensor,
    direction: Tensor,
    gradient: Tensor,
) -> tuple[Tensor, ...]:
    limit = step_limit(terms, x, direction)
    trial_x = x + limit[:, None, None] * direction
    energy, trial_gradient = _energy_and_gradient(terms, anchor, action, free, trial_x)
    slope = (gradient * direction).sum(dim=(-1, -2))
    trial_slope = (trial_gradient * direction).sum(dim=(-1, -2))
    residual = (trial_gradient * residual_scale[:, None]).abs().amax(dim=(-1, -2))
    return limit, trial_x, energy, trial_gradient, slope, trial_slope, residual


def _leapfrog(
    terms: tuple[EnergyTerm, ...],
    obstacles: tuple[EnergyTerm, ...],
    action: Tensor | None,
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: Tensor,
    substeps: int,
) -> tuple[Tensor, Tensor]:
    # `energysim.integrators.explicit.leapfrog` with the closed-form gradients and the contact projections,
    # unrolled; the energies it computes along the way are dead code that the compiler drops
    if obstacles:
        v = project_contacts(obstacles, free, x, v, 0.5 * h)
    for _ in range(substeps):
        x = x + (0.5 * h) * v
        _, gradient = _energy_and_gradient(terms, None, action, free, x)
        v = v - h * gradient * inverse_mass[:, None]
        for term in terms:
            if is_dissipative(term):
                v = v - h * term.dissipation_gradient(x, v) * inverse_mass[:, None]
        if obstacles:
            v = project_contacts(obstacles, free, x, v, h)
        x = x + (0.5 * h) * v
    return x, v


def _corner_dofs(term: EnergyTerm, dim: int, device: torch.device) -> Tensor:
    # the DOF rows `[d, k, m]` of the corners of `term`'s elements in a `[n·d, B]` state
    return term.element_vertices.T[None] * dim + torch.arange(dim, device=device)[:, None, None]


def _corners(values: Tensor, corner_dofs: Tensor) -> list[list[Tensor]]:
    # rows `corner_dofs` of `values` `[n·d, B]` as corners[i][b] `[m, B]`
    gathered = values[corner_dofs]
    return [[gathered[i, b] for b in range(gathered.shape[1])] for i in range(gathered.shape[0])]


def _scatter_corners(
    gradient: Tensor, corner_dofs: Tensor, forces: Sequence[list[list[Tensor]]], dim: int
) -> Tensor:
    # Σ over `forces` (each [i][b] `[m, B]`) added onto the DOF rows of `gradient` `[n·d, B]`
    total = torch.stack(
        [torch.stack([sum(f[i][b] for f in forces) for b in range(dim + 1)]) for i in range(dim)]
    )
    return gradient.index_add(0, corner_dofs.reshape(-1), total.reshape(-1, gradient.shape[1]))


def _kick_batch_last(
    terms: tuple[EnergyTerm, ...],
    groups: tuple[tuple[int, ...], ...],
    obstacles: tuple[EnergyTerm, ...],
    action: Tensor | None,
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: Tensor,
    drift: Tensor | None,
) -> tuple[Tensor, Tensor]:
    # One leapfrog kick at the midpoint x, on states laid out `[n·d, B]`, batch innermost: gathers
    # and scatters move rows of B contiguous numbers, and every element kernel (`batch_last_forces`)
    # is one loop vectorised over the batch, the terms of a group sharing one gather and one
    # scatter. Terms outside `groups` (gravity) give their gradient in the usual layout. With a
    # `drift`, the contact projection and the drift follow (`_finish_batch_last`); without one, the
    # caller's viscous kick does them (`_viscous_kick_batch_last`).
    dofs, batch = x.shape
    n, dim = inverse_mass.shape[0], dofs // inverse_mass.shape[0]
    action_t = None if action is None else action.T
    grouped = {index for group in groups for index in group}
    gradient = x.new_zeros(dofs, batch)
    for group in groups:
        corner_dofs = _corner_dofs(terms[group[0]], dim, x.device)
        corners = _corners(x, corner_dofs)
        forces = [terms[index].batch_last_forces(corners, action_t) for index in group]
        gradient = _scatter_corners(gradient, corner_dofs, forces, dim)
    for index, term in enumerate(terms):
        if index not in grouped:
            natural = x.T.reshape(batch, n, dim)
            gradient = gradient + term.value_and_gradient(natural, action)[1].reshape(batch, dofs).T
    v = v - h * gradient * inverse_mass.repeat_interleave(dim)[:, None]
    if drift is None:
        return x, v
    return _finish_batch_last(obstacles, free, x, v, h, drift)


def _viscous_kick_batch_last(
    terms: tuple[EnergyTerm, ...],
    obstacles: tuple[EnergyTerm, ...],
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: Tensor,
    drift: Tensor,
) -> tuple[Tensor, Tensor]:
    # The viscous kick of the dissipative `terms` at the velocity the elastic kick left
    # (`explicit.leapfrog`), then contact and drift. A compiled function of its own: in one with the
    # elastic kernels, which the compiler fuses with these over the same elements, the kick took
    # 2.1 ms where apart the two take 0.4 and 0.5 (64 worms, one thread).
    dofs, batch = x.shape
    dim = dofs // inverse_mass.shape[0]
    gradient = x.new_zeros(dofs, batch)
    for term in terms:
        corner_dofs = _corner_dofs(term, dim, x.device)
        forces = term.batch_last_dissipation_gradient(_corners(x, corner_dofs), _corners(v, corner_dofs))
        gradient = _scatter_corners(gradient, corner_dofs, [forces], dim)
    v = v - h * gradient * inverse_mass.repeat_interleave(dim)[:, None]
    return _finish_batch_last(obstacles, free, x, v, h, drift)


def _finish_batch_last(
    obstacles: tuple[EnergyTerm, ...], free: Tensor, x: Tensor, v: Tensor, h: Tensor, drift: Tensor
) -> tuple[Tensor, Tensor]:
    # a kick's contact projection and the drift after it, on `[n·d, B]` states
    dofs, batch = x.shape
    n = free.shape[0]
    if obstacles:
        natural = (x.T.reshape(batch, n, -1), v.T.reshape(batch, n, -1))
        v = project_contacts(obstacles, free, *natural, h).reshape(batch, dofs).T
    return x + drift * v, v


def _hessian_entries(
    terms: tuple[EnergyTerm, ...],
    action: Tensor | None,
    x: Tensor,
    groups: tuple[tuple[tuple[int, ...], Tensor], ...],
    diagonal_positions: Tensor,
    length: int,
) -> Tensor:
    # every term's Hessian entries summed into one flat storage per batch entry (a dense matrix, or
    # band storage): per-vertex diagonals at `diagonal_positions`; element blocks by group (terms
    # sharing their elements, summed before one scatter) at the group's positions, where the last
    # slot takes the entries the storage drops
    batch, n, dim = x.shape
    flat = x.new_zeros(batch, length + 1)
    for term in terms:
        if hasattr(term, "hessian_diagonal") and not term.is_linear:
            diagonal = term.hessian_diagonal().reshape(-1, n, 1).expand(batch, n, dim).reshape(batch, n * dim)
            flat[:, diagonal_positions] += diagonal
    for members, positions in groups:
        element_positions = x[:, terms[members[0]].element_vertices]
        blocks = terms[members[0]].element_hessian(element_positions, action)
        for member in members[1:]:
            blocks = blocks + terms[member].element_hessian(element_positions, action)
        flat.index_add_(1, positions, blocks.reshape(batch, -1))
    return flat[:, :length]


_SOURCES: dict[str, Callable] = {
    "energy": _energy,
    "energy_and_gradient": _energy_and_gradient,
    "term_energies": _term_energies,
    "hessian_entries": _hessian_entries,
    "trial": _trial,
    "cut_back": _cut_back,
    "leapfrog": _leapfrog,
    "kick_batch_last": _kick_batch_last,
    "viscous_kick_batch_last": _viscous_kick_batch_last,
}
# Inductor's C++ backend inlines an intermediate with a single consumer into that consumer's loop,
# so a per-element quantity broadcast over a 12×12 block (the muscle's 3×3 fibre stiffness, the
# neo-Hookean invariants) is recomputed for every entry of the block, square roots and divisions
# included. Realizing every intermediate of more than a few operations into its own buffer first
# took the worm's compiled band Hessian from 0.85 to 0.53 ms (360 tets, one thread; the fibre
# muscles' blocks alone from 0.31 to 0.07 ms). The energy and gradient gain nothing from it (their
# intermediates are read once), and GPU code keeps Inductor's defaults. The neo-Hookean blocks' two
# strain-map products are written so that Inductor fuses them too (`energysim.linalg.small_matmul`):
# 0.53 → 0.46 ms for one worm, 31 → 25 ms for 64, 1.14 → 0.97 ms for the 810-tet cantilever
# (the fastest of 30–200 calls each way, alternating in one process).
_CPU_OPTIONS: dict[str, dict[str, object]] = {"hessian_entries": {"realize_opcount_threshold": 4}}
_COMPILED: dict[tuple[str, str], Callable] = {}
_FAILED: set[str] = set()


def _compiled(name: str, device_type: str) -> Callable | None:
    if name in _FAILED:
        return None
    key = (name, device_type)
    if key not in _COMPILED:
        options = _CPU_OPTIONS.get(name) if device_type == "cpu" else None
        _COMPILED[key] = torch.compile(_SOURCES[name], options=options)
    return _COMPILED[key]


def call(name: str, *args: object) -> object | None:
    """The compiled function `name` applied to `args`, or None where it could not be compiled (a
    warning says why, once per function); the caller then evaluates eagerly."""
    device = next((arg.device.type for arg in args if isinstance(arg, Tensor)), "cpu")
    function = _compiled(name, device)
    if function is None:
        return None
    try:
        with torch.no_grad():
            return function(*args)
    except Exception as error:  # noqa: BLE001 - any compiler failure means: evaluate eagerly
        _FAILED.add(name)
        warnings.warn(
            f"torch.compile could not compile the objective's {name} ({type(error).__name__}: "
            f"{str(error).splitlines()[0] if str(error) else ''}); evaluating it eagerly instead",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


def energy(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, x: Tensor
) -> Tensor | None:
    """E(x) `[B]` by the compiled function, or None (evaluate eagerly)."""
    return call("energy", tuple(terms), anchor, action, x)


def term_energies(terms: Sequence[EnergyTerm], action: Tensor | None, x: Tensor) -> Tensor | None:
    """Every term's E_i(x) at `x` itself (no anchor), `[len(terms), B]`, by the compiled function, or
    None (evaluate eagerly)."""
    return call("term_energies", tuple(terms), action, x)


def energy_and_gradient(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, free: Tensor, x: Tensor
) -> tuple[Tensor, Tensor] | None:
    """E(x) `[B]` and ∇E(x) `[B, n, d]` (zero on fixed vertices) by the compiled function, or None."""
    return call("energy_and_gradient", tuple(terms), anchor, action, free, x)


def trial(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    free: Tensor,
    residual_scale: Tensor,
    x: Tensor,
    direction: Tensor,
    gradient: Tensor,
) -> tuple[Tensor, ...] | None:
    """`Objective.trial`'s seven results by one compiled function, or None."""
    return call("trial", tuple(terms), anchor, action, free, residual_scale, x, direction, gradient)


def cut_back(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    origin: Tensor,
    targets: Sequence[Tensor],
) -> tuple[Tensor, Tensor, Tensor] | None:
    """`Objective.cut_back`'s cuts and energies, and the step limits (NaN where `origin` is not
    admissible), by one compiled function, or None."""
    return call("cut_back", tuple(terms), anchor, action, origin, tuple(targets))


# Leapfrog substeps per compiled call: unrolled into one generated loop nest, so the call's
# overhead (about 30 µs) is paid once per eight substeps. The batch-last kernels are long scalar
# expressions, one kick per call: eight of them unrolled take minutes to compile, one takes
# seconds, and its call's overhead is small beside the millisecond a batch of bodies takes.
LEAPFROG_CHUNK = 8
# Batches from this size on take the batch-last layout where every element term has
# `batch_last_forces`: with fewer entries its vectors would run mostly empty.
BATCH_LAST_MIN_BATCH = 8


class BatchLastPlan(NamedTuple):
    """How `leapfrog` kicks batch-last: the `elastic` terms, their `groups` (indices into
    `elastic`) and the `dissipative` terms, each kicked by a compiled function of its own."""

    elastic: tuple[EnergyTerm, ...]
    groups: tuple[tuple[int, ...], ...]
    dissipative: tuple[EnergyTerm, ...]


def batch_last_plan(terms: Sequence[EnergyTerm]) -> BatchLastPlan | None:
    """For batch-last kicks: the terms with `batch_last_forces` grouped by equal `element_vertices`
    (`_element_groups`), and the dissipative terms (`batch_last_dissipation_gradient`); None where
    another term is neither linear with a closed-form gradient (gravity) nor one of those."""
    dissipative = tuple(term for term in terms if is_dissipative(term))
    elastic = tuple(term for term in terms if not is_dissipative(term))
    groups = tuple(
        tuple(group) for group in _element_groups(elastic, lambda term: hasattr(term, "batch_last_forces"))
    )
    grouped = {index for group in groups for index in group}
    for index, term in enumerate(elastic):
        closed_form = type(term).value_and_gradient is not EnergyTerm.value_and_gradient
        if index not in grouped and not (term.is_linear and closed_form):
            return None
    if not all(hasattr(term, "batch_last_dissipation_gradient") for term in dissipative):
        return None
    return BatchLastPlan(elastic, groups, dissipative)


def leapfrog(
    terms: Sequence[EnergyTerm],
    obstacles: Sequence[EnergyTerm],
    action: Tensor | None,
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    h: float,
    substeps: int,
) -> tuple[Tensor, Tensor] | None:
    """`energysim.integrators.explicit.leapfrog` over the force `terms`, with `obstacles` projecting the
    velocities (`project_contacts`), by compiled calls of unrolled substeps (`inverse_mass` `[n]`
    zero on pinned vertices), or None. Batches of `BATCH_LAST_MIN_BATCH` or more run batch-last
    (`batch_last_plan`) where the terms allow it."""
    step = torch.tensor(h, dtype=x.dtype, device=x.device)  # a tensor: a new h is no new graph
    batch = x.shape[0]
    plan = batch_last_plan(terms) if batch >= BATCH_LAST_MIN_BATCH else None
    if plan is not None:
        return _leapfrog_batch_last(plan, obstacles, action, free, inverse_mass, x, v, step, substeps)
    done = 0
    while done < substeps:
        chunk = min(LEAPFROG_CHUNK, substeps - done)
        arguments = (tuple(terms), tuple(obstacles), action, free, inverse_mass, x, v, step, chunk)
        result = call("leapfrog", *arguments)
        if result is None:
            return None
        x, v = result
        done += chunk
    return x, v


def _leapfrog_batch_last(
    plan: BatchLastPlan,
    obstacles: Sequence[EnergyTerm],
    action: Tensor | None,
    free: Tensor,
    inverse_mass: Tensor,
    x: Tensor,
    v: Tensor,
    step: Tensor,
    substeps: int,
) -> tuple[Tensor, Tensor] | None:
    # `leapfrog` laid out `[n·d, B]`: the first half drift here, then per substep the compiled
    # elastic kick and, with dissipative terms, the viscous one, then the drift (a whole step, a
    # half for the last)
    batch, n, dim = x.shape
    if obstacles:
        v = project_contacts(obstacles, free, x, v, 0.5 * step)
    x, v = (tensor.reshape(batch, -1).T.contiguous() for tensor in (x, v))
    x = x + (0.5 * step) * v
    # only the terms each function reads: every module argument adds guards to every call
    elastic = (plan.elastic, plan.groups, tuple(obstacles), action, free, inverse_mass)
    viscous = (plan.dissipative, tuple(obstacles), free, inverse_mass)
    for substep in range(substeps):
        drift = step if substep < substeps - 1 else 0.5 * step
        result = call("kick_batch_last", *elastic, x, v, step, None if plan.dissipative else drift)
        if result is not None and plan.dissipative:
            result = call("viscous_kick_batch_last", *viscous, *result, step, drift)
        if result is None:
            return None
        x, v = result
    return x.T.reshape(batch, n, dim), v.T.reshape(batch, n, dim)


_GROUPS: IdentityCache[list[list[int]]] = IdentityCache(capacity=16)


def _element_groups(
    terms: Sequence[EnergyTerm], member: Callable[[EnergyTerm], bool] = has_element_blocks
) -> list[tuple[int, ...]]:
    """The indices of the terms that are `member`s (default: those with element blocks), grouped by
    equal `element_vertices` (a muscle term on every element of the mesh shares the elastic term's
    elements): one gather and one scatter per group. Cached per tuple of vertex tensors."""
    members = [index for index, term in enumerate(terms) if member(term)]
    vertices = [terms[index].element_vertices for index in members]

    def build() -> list[list[int]]:
        groups: list[list[int]] = []
        for position, tensor in enumerate(vertices):
            for group in groups:
                first = vertices[group[0]]
                if first is tensor or (first.shape == tensor.shape and torch.equal(first, tensor)):
                    group.append(position)
                    break
            else:
                groups.append([position])
        return groups

    return [tuple(members[position] for position in group) for group in _GROUPS.get(vertices, None, build)]


def dense_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor
) -> Tensor | None:
    """∇²E(x) as dense `[B, n·d, n·d]` matrices, fixed DOFs eliminated (identity rows and columns),
    by the compiled function, or None."""
    batch, n, dim = x.shape
    size = n * dim
    groups = []
    for members in _element_groups(terms):
        dofs = dof_indices(terms[members[0]].element_vertices, dim)
        groups.append((members, (dofs[:, :, None] * size + dofs[:, None, :]).reshape(-1)))
    diagonal = torch.arange(size, device=x.device) * (size + 1)
    flat = call("hessian_entries", tuple(terms), action, x, tuple(groups), diagonal, size * size)
    if flat is None:
        return None
    dense = flat.reshape(batch, size, size)
    if not bool(free.all()):
        # fixed DOFs get the rows and columns of the identity, as in `energysim.linalg.assembly.assemble`
        fixed = (~free)[:, None].expand(n, dim).reshape(-1)
        kept = (~fixed).to(x.dtype)
        dense = dense * kept[:, None] * kept[None, :] + torch.diag(fixed.to(x.dtype))
    return dense


def band_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor, layout: LevelLayout
) -> Tensor | None:
    """∇²E(x) in `layout`'s band storage, `[B, N, u + 1]` (`energysim.linalg.banded`), fixed DOFs
    eliminated, by the compiled function, or None."""
    batch, n, dim = x.shape
    groups = tuple(
        (members, band_positions(layout, terms[members[0]].element_vertices, dim))
        for members in _element_groups(terms)
    )
    diagonal = band_diagonal_positions(layout)
    flat = call("hessian_entries", tuple(terms), action, x, groups, diagonal, band_length(layout))
    if flat is None:
        return None
    bands = flat.reshape(batch, n * dim, layout.half_bandwidth + 1)
    if not bool(free.all()):
        bands = eliminate_fixed_in_bands(bands, layout, (~free)[:, None].expand(n, dim).reshape(-1))
    return bands
