"""A step objective's evaluations as `torch.compile`d functions (opt-in: `Solver(compile=True)`).

A small body's Newton iteration is hundreds of tiny tensor operations, and in eager PyTorch on a
CPU their dispatch costs more than their arithmetic: the 360-tet worm's energy and gradient take
2,000 operations a call. Compiled, the element kernels of all terms fuse into a few loops. Three
functions are compiled, each over the objective's whole list of terms: the energy, the energy with
its gradient, and the dense Hessian of a small system (element blocks scattered straight into a
`[B, N, N]` matrix, no CSR in between). They compute what the eager paths compute, up to the
order of floating-point operations (the tests compare them to 1e-9 relative, and a 0.2 s worm walk
to 1e-10 m with the same iterations).

Measured with `python scripts/bench_creatures.py --compile`: the worm 38.5 → 25.9 ms per step, the
2D crawler 22.8 → 12.5 ms (faster than real time); the quadruped (888 tets, over the dense solve's
size, so CG) 124 → 118 ms. The first call per scene pays the compilation (about 15 s for the worm,
a few seconds when torch's on-disk cache already holds it); a new scene, step size or batch size
compiles again, and a batch that drops its converged entries meets several sizes (six worms: about
a minute the first time). It pays off for long runs of one scene: walking, training. Where compiling
fails (no C++ compiler, an unsupported operation), a warning says so once and the eager paths take
over.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.assembly import dof_indices
from energysim.energies.base import ElementEnergy, EnergyTerm


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


def _dense_hessian(
    terms: tuple[EnergyTerm, ...], action: Tensor | None, free: Tensor, x: Tensor, eliminate: bool
) -> Tensor:
    batch, n, dim = x.shape
    size = n * dim
    flat = x.new_zeros(batch, size * size)
    for term in terms:
        if term.is_linear:
            continue
        if hasattr(term, "hessian_diagonal"):
            diagonal = term.hessian_diagonal().reshape(-1, n, 1).expand(batch, n, dim).reshape(batch, size)
            flat[:, torch.arange(size, device=x.device) * (size + 1)] += diagonal
            continue
        vertices = term.element_vertices
        blocks = term.element_hessian(x[:, vertices], action)
        dofs = dof_indices(vertices, dim)
        positions = (dofs[:, :, None] * size + dofs[:, None, :]).reshape(-1)
        flat.index_add_(1, positions, blocks.reshape(batch, -1))
    dense = flat.reshape(batch, size, size)
    if eliminate:
        # fixed DOFs get the rows and columns of the identity, as in `energysim.assembly.assemble`
        fixed = (~free)[:, None].expand(n, dim).reshape(-1)
        kept = (~fixed).to(x.dtype)
        dense = dense * kept[:, None] * kept[None, :] + torch.diag(fixed.to(x.dtype))
    return dense


_SOURCES: dict[str, Callable] = {
    "energy": _energy,
    "energy_and_gradient": _energy_and_gradient,
    "dense_hessian": _dense_hessian,
}
_COMPILED: dict[str, Callable] = {}
_FAILED: set[str] = set()


def _compiled(name: str) -> Callable | None:
    if name in _FAILED:
        return None
    if name not in _COMPILED:
        _COMPILED[name] = torch.compile(_SOURCES[name])
    return _COMPILED[name]


def call(name: str, *args: object) -> object | None:
    """The compiled function `name` applied to `args`, or None where it could not be compiled (a
    warning says why, once per function); the caller then evaluates eagerly."""
    function = _compiled(name)
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


def energy_and_gradient(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, free: Tensor, x: Tensor
) -> tuple[Tensor, Tensor] | None:
    """E(x) `[B]` and ∇E(x) `[B, n, d]` (zero on fixed vertices) by the compiled function, or None."""
    return call("energy_and_gradient", tuple(terms), anchor, action, free, x)


def dense_hessian(
    terms: Sequence[EnergyTerm], action: Tensor | None, free: Tensor, x: Tensor
) -> Tensor | None:
    """∇²E(x) as dense `[B, n·d, n·d]` matrices, fixed DOFs eliminated (identity rows and columns),
    by the compiled function, or None."""
    return call("dense_hessian", tuple(terms), action, free, x, not bool(free.all()))
