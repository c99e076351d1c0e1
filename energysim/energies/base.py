"""The contract every energy term keeps, and the capabilities a term declares in its type.

A term is a small, pure function of positions: `term(x, action) -> energy`, with `x` of shape
`[B, n, d]` (a batch of B configurations of n vertices in d = 2 or 3 dimensions) and the energy
of shape `[B]`, in J. Rest data and material constants are buffers, so `.to(device, dtype)`
moves them; a constant may require grad. Gradients, Hessian-vector products and Hessian blocks
come from autograd in `energysim.objective.derivatives`, unless the term declares a kernel.

What else a term offers is declared once, by its class, never probed at run time:

- its kind, by base class: `ElementEnergy` (a sum over small elements, with per-element Hessian
  blocks), `VertexDiagonalEnergy` (a constant per-vertex Hessian diagonal: the inertia),
  `StepLimitingEnergy` (a barrier that bounds how far a step may go: obstacles),
  `DissipativeEnergy` (no stored energy, a velocity-dependent force: viscosity);
- its kernels and hooks, by class flags: `is_linear`, `has_constant_hessian`, `has_gradient_kernel`,
  `has_hessian_kernel`, `has_batch_last_kernel`, `has_lagged_terms`, `has_curvature_hint`,
  `is_actuated`, `is_translation_invariant`.

The solvers, the compiled evaluations and the integrators ask only these (`isinstance` or the
flag), so a term that declares a kernel must implement it, and one that does not is never asked.
"""

from __future__ import annotations

import copy
import weakref

import torch
from torch import Tensor, nn

from energysim.fem.hessian_entries import upper_entries
from energysim.mesh import SimplexMesh


class EnergyTerm(nn.Module):
    """Base class of energy terms. Subclasses implement `forward(x, action) -> [B]` in J.

    Class flags (capabilities, declared by the subclass):
        is_linear: the energy is linear in `x`, so its Hessian is zero.
        has_constant_hessian: the energy is quadratic in `x`: its Hessian depends on neither `x` nor
            the action, and a compiled objective assembles it once and adds it to every later
            Hessian (`energysim.objective.compiled_hessian`).
        has_gradient_kernel: `value_and_gradient` gives E and ∇E in closed form (never None); the
            compiled evaluations call only terms that declare it.
        has_lagged_terms: `lagged_terms` may add terms to a step (friction, viscosity).
        has_curvature_hint: Newton–CG shows each iteration's start and end to `curvature_hint`
            and records what it returns, which may change the term's next Hessian blocks (friction).
        is_actuated: the term reads the action; `num_actuators` says how many entries.
        is_translation_invariant: E(x + c) = E(x) for every shift c common to all vertices: the
            energy reads differences of positions only (elastic terms, muscles, viscosity). Float32
            Hessian blocks are then taken at positions relative to each element's first corner,
            which float32 resolves wherever the body is (`energysim.objective.compiled_hessian`).
    """

    is_linear: bool = False
    has_constant_hessian: bool = False
    has_gradient_kernel: bool = False
    has_lagged_terms: bool = False
    has_curvature_hint: bool = False
    is_actuated: bool = False
    is_translation_invariant: bool = False

    @property
    def scene(self) -> nn.Module | None:
        """The scene this term was added to (its rest data is bound to that scene's mesh), or None."""
        owner = self.__dict__.get("_owner")
        return None if owner is None else owner()

    def mark_added(self, scene: nn.Module) -> None:
        """Record that `scene` holds this term; called by `Scene.add`, which refuses a term that
        another scene holds. A weak reference: a term keeps no scene alive."""
        # stored past nn.Module.__setattr__, which would register the scene as a submodule
        self.__dict__["_owner"] = weakref.ref(scene)

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        """Build rest-state buffers from the scene's mesh; called once by `Scene.add`.

        Args:
            mesh: the scene's rest mesh.
            vertex_mass: lumped vertex masses, shape `[n]`, in kg.
        """

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def max_step(self, x: Tensor, dx: Tensor) -> Tensor | None:
        """Largest α ≤ 1 such that `x + α dx` is admissible for this term, shape `[B]`; None: no limit
        (only a `StepLimitingEnergy` has one)."""
        return self.step_limit(x, dx)

    def step_limit(self, x: Tensor, dx: Tensor) -> Tensor | None:
        """`max_step` without the check of `x`: NaN for batch entries where `x` is not admissible, and
        no data-dependent branch, so that compiled code can call it (`Objective.trial`); None here."""
        return None

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        """E(x) `[B]` and ∇E(x) `[B, n, d]` from closed-form kernels, without autograd, where the class
        declares `has_gradient_kernel`; else None (the solvers then differentiate `forward`). Kernels
        are checked against autograd in the tests; they exist because a small scene's step is
        dominated by per-operation overhead, and a backward pass doubles the operations."""
        return None

    def warm_start(self, x_prev: Tensor, candidate: Tensor) -> Tensor:
        """Where a step's solve may start instead of `candidate` (`[B, n, d]`, a prediction from the
        step's start `x_prev`), in this term's view; default `candidate`. A step term overrides it
        where a prediction is known to land where Newton's quadratic model of the term is poor."""
        return candidate

    def curvature_hint(self, previous: Tensor, current: Tensor) -> Tensor:
        """What one Newton iteration, from `previous` to `current` (`[B, n, d]`), tells this term about
        its next Hessian blocks, where the class declares `has_curvature_hint`: a term whose exact
        Hessian misleads Newton in a way the last step shows marks where to give a safer block
        (`set_curvature_hint` records it); asking changes nothing.
        The blocks stay a positive semidefinite model of the term, so the solve still stops on the
        residual alone; the adjoint builds the step's terms anew, with exact blocks."""
        raise NotImplementedError(f"{type(self).__name__} declares no curvature hint")

    def batch_last_curvature_hint(
        self, start_corners: list[list[Tensor]], corners: list[list[Tensor]]
    ) -> Tensor | None:
        """`curvature_hint` with the batch innermost, `[m, B]`, from the corners `[i][b]` `[m, B]` at an
        iteration's start and end, for a compiled line-search trial; None where the class has none."""
        return None

    def set_curvature_hint(self, hint: Tensor) -> None:
        """Record a `curvature_hint` for the next Hessian blocks."""
        raise NotImplementedError(f"{type(self).__name__} declares no curvature hint")

    def lagged_terms(self, x_prev: Tensor, dt: float) -> list[EnergyTerm]:
        """Terms this one adds to a single step's objective, built from the positions at the step's
        start, `[B, n, d]` (friction, whose normal forces are taken there); none unless the class
        declares `has_lagged_terms`."""
        return []

    def rows(self, entries: Tensor) -> EnergyTerm | None:
        """This step term for the batch entries `entries` (indices `[k]`) alone, sliced from its own
        per-entry data, or None where the term cannot slice itself (the step then builds the term
        again from the entries' state). Terms that hold per-entry data (the inertia, lagged
        friction and viscosity) implement it: a solver restricts the step to the entries still
        iterating several times a step, and slicing costs a few index operations where building
        computes the lagged data anew."""
        return None

    def _with(self, **attributes: Tensor) -> EnergyTerm:
        # a shallow copy of this term with `attributes` replaced; only plain tensor attributes (not
        # registered buffers or parameters, which the copy would share with this term)
        part = copy.copy(self)
        for name, value in attributes.items():
            if name in self._buffers or name in self._parameters:
                raise ValueError(f"{type(self).__name__}.{name} is registered: a copy would share it")
            part.__dict__[name] = value
        return part

    def in_precision(self, dtype: torch.dtype) -> EnergyTerm:
        """A shallow copy of this term whose floating-point tensors (buffers, parameters detached,
        plain tensor attributes) are cast to `dtype`, for evaluations in another precision (the
        float32 Hessian of `energysim.objective.compiled_hessian`); this term is left as it is."""
        part = copy.copy(self)
        cast = {}
        for name, value in [*self._buffers.items(), *self._parameters.items()]:
            floating = value is not None and value.is_floating_point()
            cast[name] = value.detach().to(dtype) if floating else value
        # parameters become plain buffers of the copy: it is evaluated, never trained
        part.__dict__["_buffers"], part.__dict__["_parameters"] = cast, {}
        for name, value in vars(self).items():
            if isinstance(value, Tensor) and value.is_floating_point():
                part.__dict__[name] = value.to(dtype)
        return part

    @property
    def num_actuators(self) -> int:
        """How many action entries the term reads (0 unless `is_actuated`)."""
        return 0


class VertexDiagonalEnergy(EnergyTerm):
    """A term whose Hessian is a constant diagonal, the same for the d coordinates of a vertex
    (the implicit-Euler inertia): solvers add it to the assembled diagonal, L-BFGS starts from its
    inverse. Subclasses implement `hessian_diagonal`."""

    has_constant_hessian = True

    def hessian_diagonal(self) -> Tensor:  # pragma: no cover - abstract
        """The Hessian's diagonal per vertex, shape `[n]`, in N/m."""
        raise NotImplementedError


class StepLimitingEnergy(EnergyTerm):
    """A barrier, infinite where a state is not admissible, that bounds how far a step may go.

    Subclasses implement `step_limit` (without a data-dependent branch) and `max_step`, which raises
    ValueError, saying why, where `x` itself is not admissible. The line searches start from it.
    """

    def step_limit(self, x: Tensor, dx: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def max_step(self, x: Tensor, dx: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


class DissipativeEnergy(EnergyTerm):
    """A velocity-dependent force from a Rayleigh dissipation D(x, v), with no stored energy.

    Its energy is zero (so implicit solvers and energy checks see nothing of it); explicit kicks
    take the force from `dissipation_gradient`, implicit steps from `lagged_terms`. A class with
    `has_batch_last_kernel` also has `batch_last_dissipation_gradient` (compiled batches).
    """

    is_linear = True  # a zero energy: nothing for Hessians, nothing for the energy check
    has_gradient_kernel = True
    has_lagged_terms = True
    has_batch_last_kernel: bool = False

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        return x.new_zeros(x.shape[0])

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Zero energy and zero gradient: the term stores nothing."""
        return x.new_zeros(x.shape[0]), torch.zeros_like(x)

    def dissipation(self, x: Tensor, v: Tensor) -> Tensor:  # pragma: no cover - abstract
        """D(x, v) `[B]` in W at positions and velocities `[B, n, d]`."""
        raise NotImplementedError

    def dissipation_gradient(self, x: Tensor, v: Tensor) -> Tensor:  # pragma: no cover - abstract
        """∂D/∂v `[B, n, d]` in N: minus the viscous forces."""
        raise NotImplementedError

    def batch_last_dissipation_gradient(
        self, corners: list[list[Tensor]], velocities: list[list[Tensor]]
    ) -> list[list[Tensor]]:  # pragma: no cover - abstract
        """∂D/∂v entry by entry with the batch innermost (see `ElementEnergy.batch_last_forces`)."""
        raise NotImplementedError


class ElementEnergy(EnergyTerm):
    """A sum of energies of small elements, each depending on the positions of its k vertices.

    Subclasses set the buffer `element_vertices` (shape `[m, k]`) in `bind` and implement
    `element_energy`; that structure lets solvers build per-element Hessian blocks (by autograd,
    or by the term's `element_hessian` where it declares `has_hessian_kernel`). With
    `has_gradient_kernel` it implements `element_energy_and_gradient`; with `has_batch_last_kernel`,
    `batch_last_forces`.
    """

    element_vertices: Tensor
    has_hessian_kernel: bool = False
    has_batch_last_kernel: bool = False

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Energies of every element, shape `[B, m]`, in J.

        Args:
            element_positions: shape `[B, m, k, d]`, in m.
            action: the step's action, shape `[B, a]`, or None.
        """
        raise NotImplementedError  # pragma: no cover - abstract

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:  # pragma: no cover - abstract
        """`element_energy` `[B, m]` in J and its gradient per corner `[B, m, k, d]` in N, in one pass."""
        raise NotImplementedError

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:  # pragma: no cover
        """Exact per-element Hessian blocks, shape `[B, m, k·d, k·d]`, in N/m."""
        raise NotImplementedError

    def batch_last_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> list[list[Tensor]]:  # pragma: no cover - abstract
        """∂E/∂x entry by entry with the batch innermost, for compiled explicit steps of many bodies
        (`energysim.objective.batch_last`): `corners[i][b]` is coordinate i of every element's corner
        b, shape `[m, B]` in m, `action` transposed `[a, B]` or None, and the result's `[i][b]` is
        ∂E/∂x_bi, `[m, B]` in N."""
        raise NotImplementedError

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """Every element's energy `[m, B]` in J and ∂E/∂x_bi `[i][b]` `[m, B]` in N, the batch
        innermost, for compiled evaluations of a batch (`energysim.objective.batch_last`); `corners`
        and `action` as for `batch_last_forces`. This default transposes
        `element_energy_and_gradient`'s (a term with `has_gradient_kernel`); terms on the hot path
        write theirs as scalar arithmetic."""
        positions = torch.stack([torch.stack(coordinate) for coordinate in corners]).permute(3, 2, 1, 0)
        energy, gradient = self.element_energy_and_gradient(positions, None if action is None else action.T)
        corner_count, dim = positions.shape[2], positions.shape[3]
        return energy.T, [[gradient[:, :, b, i].T for b in range(corner_count)] for i in range(dim)]

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """The upper entries of every element's Hessian block (in the order of
        `energysim.fem.hessian_entries.upper_entries`) with the batch innermost, `[m, B]` each, in
        N/m, for the compiled Hessian of a batch (`energysim.objective.batch_last`); `corners` and
        `action` as for `batch_last_forces`. This default transposes `element_hessian`'s blocks;
        terms on the hot path write theirs as scalar arithmetic (`energysim.fem.hessian_entries`)."""
        positions = torch.stack([torch.stack(coordinate) for coordinate in corners]).permute(3, 2, 1, 0)
        blocks = self.element_hessian(positions, None if action is None else action.T)
        pairs = upper_entries(len(corners[0]), len(corners))
        return [blocks[:, :, row, column].T for row, column in pairs]

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        return self.element_energy(gather_vertices(x, self.element_vertices), action).sum(dim=-1)

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        """From `element_energy_and_gradient` where the class declares `has_gradient_kernel`, else None."""
        if not self.has_gradient_kernel:
            return None
        with torch.no_grad():
            energies, gradients = self.element_energy_and_gradient(x[:, self.element_vertices], action)
            gradient = scatter_vertices(gradients, self.element_vertices, x.shape[1])
        return energies.sum(dim=-1), gradient


class _GatherVertices(torch.autograd.Function):
    # x[:, index] backpropagates through an accumulating index_put, several times slower than
    # a scatter-add on flat DOF numbers; this backward is that scatter-add, itself differentiable
    # (its derivative is the gather again), so double backward keeps working.

    @staticmethod
    def forward(ctx, x: Tensor, dofs: Tensor) -> Tensor:  # noqa: ANN001 - autograd's signature
        ctx.save_for_backward(dofs)
        ctx.size = x.shape[1] * x.shape[2]
        return x.reshape(x.shape[0], -1).index_select(1, dofs.reshape(-1)).reshape(x.shape[0], *dofs.shape)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # noqa: ANN001
        (dofs,) = ctx.saved_tensors
        return _scatter_dofs(grad, dofs, ctx.size), None


def _scatter_dofs(values: Tensor, dofs: Tensor, size: int) -> Tensor:
    batch = values.shape[0]
    flat = values.new_zeros(batch, size).index_add(1, dofs.reshape(-1), values.reshape(batch, -1))
    return flat.reshape(batch, -1, dofs.shape[-1])


def _element_dofs(element_vertices: Tensor, dim: int) -> Tensor:
    return element_vertices[..., None] * dim + torch.arange(dim, device=element_vertices.device)


def scatter_vertices(values: Tensor, element_vertices: Tensor, num_vertices: int) -> Tensor:
    """Sum per-element vertex values `[B, m, k, d]` onto the vertices: `[B, n, d]` (gather's adjoint)."""
    dim = values.shape[-1]
    return _scatter_dofs(values, _element_dofs(element_vertices, dim), num_vertices * dim)


def gather_vertices(x: Tensor, element_vertices: Tensor) -> Tensor:
    """`x[:, element_vertices]` with a fast backward.

    Args:
        x: positions, shape `[B, n, d]`.
        element_vertices: shape `[m, k]`.

    Returns:
        shape `[B, m, k, d]`.
    """
    return _GatherVertices.apply(x, _element_dofs(element_vertices, x.shape[-1]))


def as_parameter(value: float | Tensor, name: str) -> Tensor:
    """A float64 tensor from a scalar or a tensor, keeping the tensor (and its grad) when given one."""
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            value = value.to(torch.float64)
        return value
    return torch.tensor(float(value), dtype=torch.float64)


def check_per_element(value: Tensor, count: int, name: str, what: str) -> None:
    """Raise unless `value` is a scalar or has shape `[count]`."""
    if value.ndim != 0 and tuple(value.shape) != (count,):
        raise ValueError(
            f"{name} must be a scalar or have shape [{count}] (one per {what}), got {tuple(value.shape)}"
        )


def check_positive(value: Tensor, name: str, unit: str) -> None:
    """Raise unless every entry of `value` is finite and > 0, naming the first offending entries."""
    bad = ~(torch.isfinite(value) & (value > 0))
    if bad.any():
        index = torch.nonzero(bad.reshape(-1)).reshape(-1)[:10].tolist()
        raise ValueError(f"{name} must be finite and > 0 {unit}; offending entries {index}")


def limits_steps(term: EnergyTerm) -> bool:
    """Whether `term` bounds how far a step may go: a `StepLimitingEnergy` (a contact barrier)."""
    return isinstance(term, StepLimitingEnergy)


def is_dissipative(term: EnergyTerm) -> bool:
    """Whether `term` dissipates through a velocity-dependent force: a `DissipativeEnergy`."""
    return isinstance(term, DissipativeEnergy)


def has_element_blocks(term: EnergyTerm) -> bool:
    """Whether `term` enters Hessians as element blocks: a nonlinear `ElementEnergy`. The eager
    assembly, the sparsity pattern and the compiled scatter all ask this, so they agree on which
    blocks there are."""
    return isinstance(term, ElementEnergy) and not term.is_linear


def has_vertex_diagonal(term: EnergyTerm) -> bool:
    """Whether `term` enters Hessians as a per-vertex diagonal: a nonlinear `VertexDiagonalEnergy`."""
    return isinstance(term, VertexDiagonalEnergy) and not term.is_linear
