"""A step objective's evaluations as `torch.compile`d functions (opt-in: `Solver(compile=True)`).

A small body's Newton iteration is hundreds of tiny tensor operations, and in eager PyTorch on a
CPU their dispatch costs more than their arithmetic: the 360-tet worm's energy and gradient take
2,000 operations a call. Compiled, the element kernels of all terms fuse into a few loops. Seven
functions are compiled, each over the objective's list of terms (or the part of it that it reads):
the energy, the energy with its gradient, a run of explicit leapfrog substeps
(`energysim.integrators.explicit`), every term's energy apart (TR-BDF2's energy check), a line
search's first trial (the CCD step limit, then the energy, gradient, slopes and residual where it
lands), the warm start's candidates cut back to admissible steps with their energies (a large
CPU batch: the cuts, then each energy by the energy's function), and the Hessian of a small system,
its element blocks scattered straight into the storage a direct solve factorises, no CSR in between
(`energysim.objective.compiled_hessian` says where each entry goes: dense, band or level blocks; a
batch's band storage is filled batch-last, `energysim.objective.batch_last`).
The compiled functions are the eager ones, compiled: the evaluations of
`energysim.objective.evaluation`, the leapfrog of `energysim.integrators.explicit` and the batch-last
kicks and Hessian of `energysim.objective.batch_last`; only the element-major Hessian's scatter into
its storage is written here. The tests compare them to the eager paths to 1e-9 relative, and a 0.2 s
worm walk to 1e-10 m with the same iterations.

The first call per scene pays the compilation; a new scene, step size or batch size compiles again,
and a batch that drops its converged entries meets several sizes. It pays off for long runs of one
scene, walking and training (docs/solvers.md has the timings). Where compiling fails (no C++
compiler, an unsupported operation), a warning says so once and the eager paths take over.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.compile_settings import package_compile_settings
from energysim.contact.projection import project_contacts
from energysim.energies.base import (
    ElementEnergy,
    EnergyTerm,
    has_vertex_diagonal,
    is_dissipative,
    limits_steps,
)
from energysim.objective import batch_last, evaluation
from energysim.objective.batch_last import BatchLastPlan, batch_last_plan, takes_batch_last
from energysim.objective.evaluation import step_limit

__all__ = [
    "CUT_BACK_SPLIT_MIN_ROWS",
    "HOST_CODE_MIN_BATCH",
    "LEAPFROG_CHUNK",
    "batch_last_plan",
    "call",
    "cut_back",
    "energy",
    "energy_and_gradient",
    "has_closed_forms",
    "leapfrog",
    "step_limit",
    "term_energies",
    "trial",
]


def has_closed_forms(terms: Sequence[EnergyTerm], *, hessian: bool) -> bool:
    """Whether every term declares a closed-form gradient (`has_gradient_kernel`) and, with `hessian`,
    closed-form Hessian entries (linear, a `VertexDiagonalEnergy`, or element blocks from
    `has_hessian_kernel`), which is what the compiled functions call."""
    for term in terms:
        if not term.has_gradient_kernel:
            return False
        blocks = term.is_linear or has_vertex_diagonal(term) or (
            isinstance(term, ElementEnergy) and term.has_hessian_kernel
        )
        if hessian and not blocks:
            return False
    return True


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
    # `energysim.integrators.explicit.leapfrog` itself, with the closed-form gradients and the contact
    # projections; the energies computed along the way are dead code that the compiler drops
    dissipative = [term for term in terms if is_dissipative(term)]

    def acceleration(y: Tensor) -> Tensor:
        return -evaluation.energy_and_gradient(terms, None, action, free, y)[1] * inverse_mass[:, None]

    def damping(y: Tensor, u: Tensor) -> Tensor:
        return -sum(term.dissipation_gradient(y, u) for term in dissipative) * inverse_mass[:, None]

    def contact(y: Tensor, u: Tensor, horizon: Tensor) -> Tensor:
        return project_contacts(obstacles, free, y, u, horizon)

    return _EXPLICIT["leapfrog"](
        x, v, h, substeps, acceleration, contact if obstacles else None, damping if dissipative else None
    )


# `energysim.integrators.explicit.leapfrog`, looked up by `leapfrog` before its first compiled call:
# `energysim.integrators` imports the objective, which imports this module, so not at import time
_EXPLICIT: dict[str, Callable] = {}


def _hessian_entries(
    terms: tuple[EnergyTerm, ...],
    action: Tensor | None,
    x: Tensor,
    groups: tuple[tuple[tuple[int, ...], Tensor, bool], ...],
    diagonal_positions: Tensor,
    length: int,
    start: Tensor | None = None,
    single: bool = False,
) -> Tensor:
    # every term's Hessian entries summed into one flat storage per batch entry (a dense matrix, or
    # band storage), `[B, length + 1]`, float32 with `single`, added to a copy of `start` (same
    # shape) where given: per-vertex diagonals at `diagonal_positions`; element blocks by group
    # (terms sharing their elements, summed before one scatter) at the group's positions, where the
    # last slot takes the entries the storage drops; a `relative` group in float32 at positions
    # relative to each element's first corner (`compiled_hessian.band_hessian`)
    batch = x.shape[0]
    dtype = torch.float32 if single else x.dtype
    flat = x.new_zeros(batch, length + 1, dtype=dtype) if start is None else start.clone()
    diagonal = batch_last.vertex_diagonal(terms, x)
    if diagonal is not None:
        flat[:, diagonal_positions] += diagonal.to(dtype)
    for members, positions, relative in groups:
        element_positions = x[:, terms[members[0]].element_vertices]
        read = action
        if relative:
            element_positions = (element_positions - element_positions[:, :, :1]).to(dtype)
            read = None if action is None else action.to(dtype)
        blocks = terms[members[0]].element_hessian(element_positions, read)
        for member in members[1:]:
            blocks = blocks + terms[member].element_hessian(element_positions, read)
        flat.index_add_(1, positions, blocks.reshape(batch, -1).to(dtype))
    return flat


# The Hessian of the terms whose Hessian is constant (`has_constant_hessian`), once per objective:
# functions of their own, so that their graphs do not count against the per-function graph limit
# of the functions called every Newton iteration
def _constant_hessian_entries(*args: object) -> Tensor:
    return _hessian_entries(*args)


def _constant_hessian_entries_batch_last(*args: object) -> Tensor:
    return batch_last.hessian_entries_batch_last(*args)


_SOURCES: dict[str, Callable] = {
    "energy": evaluation.total_energy,
    "energy_and_gradient": evaluation.energy_and_gradient,
    "term_energies": evaluation.term_energies,
    "hessian_entries": _hessian_entries,
    "hessian_entries_batch_last": batch_last.hessian_entries_batch_last,
    "constant_hessian_entries": _constant_hessian_entries,
    "constant_hessian_entries_batch_last": _constant_hessian_entries_batch_last,
    "trial": evaluation.trial,
    "cut_back": evaluation.cut_back,
    "cut_targets": evaluation.cut_targets,
    "leapfrog": _leapfrog,
    "kick_batch_last": batch_last.kick_batch_last,
    "viscous_kick_batch_last": batch_last.viscous_kick_batch_last,
}
# Inductor inlines an intermediate with a single consumer into that consumer's loop, so a
# per-element quantity broadcast over a 12×12 block (the muscle's 3×3 fibre stiffness, the
# neo-Hookean invariants) is recomputed for every entry of the block, square roots and divisions
# included. Realizing every intermediate of more than a few operations into its own buffer first
# took the worm's compiled band Hessian on the CPU from 0.85 to 0.53 ms (360 tets, one thread; the
# fibre muscles' blocks alone from 0.31 to 0.07 ms); there the energy and gradient gain nothing from
# it (their intermediates are read once, and their 3×3 products stay `@`). The neo-Hookean blocks'
# two strain-map products are written so that Inductor fuses them too
# (`energysim.linalg.small_matmul`): 0.53 → 0.46 ms for one worm, 31 → 25 ms for 64, 1.14 → 0.97
# ms for the 810-tet cantilever (the fastest of 30–200 calls each way, alternating in one process).
# On a GPU every small product is fused, so every evaluation of the implicit step recomputes: there
# all of them realize. For 4,096 worms on one H100 the level Hessian took 27.5 instead of 35.8 ms a
# call, and a step with a budget of 4 Newton iterations 270 instead of 309 ms (docs/envs.md). On
# the CPU, with every evaluation realized, a 64-worm env had not finished its first compiled steps
# after 20 minutes.
_REALIZE: dict[str, object] = {"realize_opcount_threshold": 4}
# The batch-last Hessian's element kernels are hundreds of scalar expressions over one loop; Inductor
# fuses at most 64 nodes into a kernel by default, so the entries of the worm's element terms
# were split over several loops that wrote their intermediates to memory and read them back. With
# the cap raised, they share one loop: the band Hessian of 64 worms took 6.8 instead of 9.8 ms a
# call (one thread, caches evicted; docs/benchmarks.md).
_FUSE_ALL: dict[str, object] = {"max_fusion_size": 1024}
_OPTIONS: dict[str, dict[str, dict[str, object]]] = {
    "cpu": {
        "hessian_entries": _REALIZE,
        "constant_hessian_entries": _REALIZE,
        "hessian_entries_batch_last": _FUSE_ALL,
        "constant_hessian_entries_batch_last": _FUSE_ALL,
    },
    "cuda": {
        name: _REALIZE
        for name in (
            "energy",
            "energy_and_gradient",
            "term_energies",
            "hessian_entries",
            "constant_hessian_entries",
            "trial",
            "cut_back",
        )
    },
}
# On the CPU a batch of `HOST_CODE_MIN_BATCH` or more bodies (an RL env's, whose calls repeat for
# hours) gets C++ host code (Inductor's `cpp_wrapper`): the default Python wrapper allocates, aliases
# and checks each of a call's intermediate buffers in Python, some 150 lines a call for the worm's band
# Hessian (what it saves is in docs/envs.md). It compiles more slowly, so smaller batches (a script's
# single body, most tests) keep the Python wrapper.
_HOST_CODE: dict[str, dict[str, object]] = {"cpu": {"cpp_wrapper": True}}
HOST_CODE_MIN_BATCH = 8
_COMPILED: dict[tuple[str, str, bool], Callable] = {}
_FAILED: set[str] = set()


def _compiled(name: str, device_type: str, host_code: bool = False) -> Callable | None:
    if name in _FAILED:
        return None
    key = (name, device_type, host_code)
    if key not in _COMPILED:
        options = dict(_HOST_CODE.get(device_type, {})) if host_code else {}
        options.update(_OPTIONS.get(device_type, {}).get(name, {}))
        _COMPILED[key] = torch.compile(_SOURCES[name], options=options or None)
    return _COMPILED[key]


def call(name: str, *args: object, batch: int = 1) -> object | None:
    """The compiled function `name` applied to `args`, for a batch of `batch` bodies, or None where it
    could not be compiled (a warning says why, once per function); the caller then evaluates eagerly."""
    device = next((arg.device.type for arg in args if isinstance(arg, Tensor)), "cpu")
    function = _compiled(name, device, batch >= HOST_CODE_MIN_BATCH and device in _HOST_CODE)
    if function is None:
        return None
    try:
        with torch.no_grad(), package_compile_settings():
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
    return call("energy", tuple(terms), anchor, action, x, batch=x.shape[0])


def term_energies(terms: Sequence[EnergyTerm], action: Tensor | None, x: Tensor) -> Tensor | None:
    """Every term's E_i(x) at `x` itself (no anchor), `[len(terms), B]`, by the compiled function, or
    None (evaluate eagerly)."""
    return call("term_energies", tuple(terms), action, x, batch=x.shape[0])


def energy_and_gradient(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, free: Tensor, x: Tensor
) -> tuple[Tensor, Tensor] | None:
    """E(x) `[B]` and ∇E(x) `[B, n, d]` (zero on fixed vertices) by the compiled function, or None."""
    return call("energy_and_gradient", tuple(terms), anchor, action, free, x, batch=x.shape[0])


def trial(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    free: Tensor,
    residual_scale: Tensor,
    x: Tensor,
    direction: Tensor,
    gradient: Tensor,
    judge: Callable[..., tuple[Tensor, ...]],
    judged_with: tuple,
) -> tuple[object, ...] | None:
    """`Objective.trial`'s results (`evaluation.trial`) by one compiled function, or None."""
    arguments = (tuple(terms), anchor, action, free, residual_scale, x, direction, gradient)
    return call("trial", *arguments, judge, judged_with, batch=x.shape[0])


# From this many element rows (bodies × elements of the largest element term) a CPU batch's
# cut-back runs as the cuts' call and one energy call per point: the four energies fused in one
# function outgrow the caches there and are the faster form below it (timings in docs/envs.md).
# A GPU keeps the one call (fewer launches; not measured there).
CUT_BACK_SPLIT_MIN_ROWS = 16_384


def cut_back(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    origin: Tensor,
    targets: Sequence[Tensor],
) -> tuple[Tensor, Tensor, Tensor] | None:
    """`Objective.cut_back`'s cuts and energies, and the step limits (NaN where `origin` is not
    admissible), by compiled calls, or None: `evaluation.cut_back` in one, or for a large CPU batch
    (`CUT_BACK_SPLIT_MIN_ROWS`) the two functions it composes apart, the cuts in one call
    (`evaluation.cut_targets`) and each energy by the energy's function."""
    batch = origin.shape[0]
    sizes = [term.element_vertices.shape[0] for term in terms if isinstance(term, ElementEnergy)]
    elements = max(sizes, default=0)
    if origin.device.type != "cpu" or batch * elements < CUT_BACK_SPLIT_MIN_ROWS:
        return call("cut_back", tuple(terms), anchor, action, origin, tuple(targets), batch=batch)
    # only the terms that limit steps: every term passed adds guards to the call
    limiting = tuple(term for term in terms if limits_steps(term))
    cut = call("cut_targets", limiting, origin, tuple(targets), batch=batch)
    if cut is None:
        return None
    cuts, limits = cut
    energies = [energy(terms, anchor, action, point) for point in (origin, *cuts.unbind(0))]
    if any(value is None for value in energies):
        return None
    return cuts, torch.stack(energies), limits


# Leapfrog substeps per compiled call: unrolled into one generated loop nest, so the call's
# overhead (about 30 µs) is paid once per eight substeps. The batch-last kernels are long scalar
# expressions, one kick per call: eight of them unrolled take minutes to compile, one takes
# seconds, and its call's overhead is small beside the millisecond a batch of bodies takes.
LEAPFROG_CHUNK = 8
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
    zero on pinned vertices), or None. Batches laid out batch-last (`takes_batch_last`: every CPU
    batch, eight bodies or more elsewhere) run so (`batch_last_plan`) where the terms allow it."""
    if not _EXPLICIT:
        from energysim.integrators.explicit import leapfrog as explicit_leapfrog  # noqa: PLC0415

        _EXPLICIT["leapfrog"] = explicit_leapfrog
    step = torch.tensor(h, dtype=x.dtype, device=x.device)  # a tensor: a new h is no new graph
    batch = x.shape[0]
    plan = batch_last_plan(terms) if takes_batch_last(batch, x.device) else None
    if plan is not None:
        return _leapfrog_batch_last(plan, obstacles, action, free, inverse_mass, x, v, step, substeps)
    done = 0
    while done < substeps:
        chunk = min(LEAPFROG_CHUNK, substeps - done)
        arguments = (tuple(terms), tuple(obstacles), action, free, inverse_mass, x, v, step, chunk)
        result = call("leapfrog", *arguments, batch=batch)
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
        kick_drift = None if plan.dissipative else drift
        result = call("kick_batch_last", *elastic, x, v, step, kick_drift, batch=batch)
        if result is not None and plan.dissipative:
            result = call("viscous_kick_batch_last", *viscous, *result, step, drift, batch=batch)
        if result is None:
            return None
        x, v = result
    return x.T.reshape(batch, n, dim), v.T.reshape(batch, n, dim)
