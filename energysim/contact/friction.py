"""IPC's smoothed, lagged friction: a dissipative potential built at the start of each step.

For a vertex in contact at the start of the step (positions x_n), with normal force λ and unit
normal n taken there and held fixed through the step ("lagged"), the friction potential is

    D(x) = μ λ f0(‖u‖),   u = (I − n nᵀ)(x − x_n),  the tangential displacement over the step,

with the mollifier f0 (ipc-toolkit's `smooth_friction_mollifier`): f0(y) = y²(1 − y/(3ε))/ε + ε/3
for y < ε and y beyond, ε = ε_v h. Its force −μλ f1(‖u‖) u/‖u‖ has magnitude μλ once the vertex
slides faster than ε_v (kinetic friction) and ramps linearly to zero below (static friction as
a stiff spring, up to a creep velocity of order ε_v). D is convex in x.

Along a sliding vertex's slip D is linear, so Newton's model has no friction curvature there: a
vertex that sticks at the solution is sent through the static zone to slide the other way, and
the next model sends it back (in one dimension, a two-cycle). Where an iteration reversed a
vertex's slip, its next Hessian block takes the curvature f1(y)/y along the slip as well as across
it: the Hessian of the quadratic that touches f0(‖u‖) at u and lies above it everywhere, whose
minimiser cannot overshoot (`curvature_hint`; what it saves is in docs/contact.md).
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import ElementEnergy
from energysim.linalg.batch_innermost import batch_innermost
from energysim.linalg.small_matmul import small_matmul


def slip_length(square: Tensor) -> Tensor:
    """‖u‖ from ‖u‖², with a zero (not NaN) derivative at u = 0.

    f0 below ε is written as s/ε − y·s/(3ε²) with s = ‖u‖² smooth, so the kink of y = ‖u‖ at 0
    enters only multiplied by s, whose value and slope vanish there: derivatives stay exact.
    """
    positive = square > 0
    safe = torch.where(positive, square, torch.ones_like(square))
    return torch.where(positive, torch.sqrt(safe), torch.zeros_like(square))


def _norm_and_square(u: Tensor) -> tuple[Tensor, Tensor]:
    """‖u‖ and ‖u‖² over the last axis (`slip_length`)."""
    square = (u * u).sum(dim=-1)
    return slip_length(square), square


# The mollifier's scalars, functions of y = ‖u‖ (and s = ‖u‖²) alone: the friction term's kernels in
# either layout (`LaggedFriction`: slips `[..., d]`, or their components batch-last) are built on them


def slip_value(length: Tensor, square: Tensor, smoothing: float | Tensor) -> Tensor:
    """f0(y) in m: s/ε − y s/(3ε²) + ε/3 below ε, y beyond."""
    ramp = square / smoothing - length * square / (3.0 * smoothing**2) + smoothing / 3.0
    return torch.where(length < smoothing, ramp, length)


def slip_gradient_scale(length: Tensor, smoothing: float | Tensor) -> Tensor:
    """f1(y)/y in 1/m: (2 − y/ε)/ε below ε, 1/y beyond (∇ f0 = (f1/y) u)."""
    below = length < smoothing
    safe_length = torch.where(below, smoothing, length)
    return torch.where(below, (2.0 - length / smoothing) / smoothing, 1.0 / safe_length)


def slip_curvature_along(
    length: Tensor, smoothing: float | Tensor, majorized: Tensor | None = None
) -> Tensor:
    """f1′(y) − f1(y)/y in 1/m, the Hessian's extra curvature along û: −y/ε² below ε, −1/y beyond;
    0 beyond ε where `majorized` is set (see `mollified_slip_hessian`)."""
    below = length < smoothing
    safe_length = torch.where(below, smoothing, length)
    along = torch.where(below, -length / smoothing**2, -1.0 / safe_length)
    if majorized is not None:
        along = torch.where(majorized & ~below, torch.zeros_like(along), along)
    return along


def mollified_slip(u: Tensor, smoothing: float | Tensor) -> Tensor:
    """f0(‖u‖) in m, over the last axis of `u` (tangential displacements in m); ε = `smoothing` in m."""
    return slip_value(*_norm_and_square(u), smoothing)


def mollified_slip_gradient(u: Tensor, smoothing: float | Tensor) -> Tensor:
    """∇ₓ f0(‖P(x − x_n)‖) = f1(y)/y · u, shape `[..., d]` (dimensionless); f1/y = (2 − y/ε)/ε below ε."""
    length, _ = _norm_and_square(u)
    return slip_gradient_scale(length, smoothing)[..., None] * u


def mollified_slip_hessian(
    u: Tensor, smoothing: float | Tensor, projector: Tensor, majorized: Tensor | None = None
) -> Tensor:
    """∇²ₓ f0(‖P(x − x_n)‖) = (f1/y) P + (f1′ − f1/y) ûûᵀ, shape `[..., d, d]` (1/m).

    Below ε: f1/y = (2 − y/ε)/ε and f1′ − f1/y = −y/ε², both finite at y = 0; beyond: 1/y and −1/y.
    `majorized` (bool, `u`'s shape without its last axis): where set and y ≥ ε, (f1/y) P alone, the
    Hessian of the majorizing quadratic q(v) = f0(y) + (f1(y)/2y)(‖v‖² − y²) of f0(‖v‖) (f1(y)/y
    falls as y grows, so q ≥ f0 everywhere, with equal value and slope at u).
    """
    length, _ = _norm_and_square(u)
    over_length = slip_gradient_scale(length, smoothing)
    along = slip_curvature_along(length, smoothing, majorized)
    unit = u / torch.where(length > 0, length, torch.ones_like(length))[..., None]
    outer = unit[..., :, None] * unit[..., None, :]
    return over_length[..., None, None] * projector + along[..., None, None] * outer


class LaggedFriction(ElementEnergy):
    """Σ_i μ λ_i f0(‖(I − n_i n_iᵀ)(x_i − x_n,i)‖) over contact vertices: one step's friction.

    Built by an obstacle for one step from the state at its start; not added to scenes. Every
    element is one vertex. Its lagged data may carry autograd history (from x_n or μ), which
    makes the step's gradient include how friction depends on them.

    Args:
        element_vertices: the vertices, shape `[m, 1]`.
        previous_positions: x_n of those vertices, shape `[B, m, d]`, in m.
        normals: unit contact normals at x_n, shape `[B, m, d]`.
        normal_force: λ, shape `[B, m]`, in N (0 where not in contact).
        friction: μ, a scalar tensor.
        smoothing: ε = ε_v h, in m.
    """

    has_gradient_kernel = True
    has_hessian_kernel = True
    has_curvature_hint = True

    def __init__(
        self,
        element_vertices: Tensor,
        previous_positions: Tensor,
        normals: Tensor,
        normal_force: Tensor,
        friction: Tensor,
        smoothing: float,
    ) -> None:
        super().__init__()
        self.element_vertices = element_vertices
        self.previous_positions = previous_positions
        eye = torch.eye(normals.shape[-1], dtype=normals.dtype, device=normals.device)
        self.projector = eye - normals[..., :, None] * normals[..., None, :]
        self.weight = friction * normal_force
        # a tensor, like the inertia's M/h²: compiled evaluations then need no new graph for a new h
        self.smoothing = torch.as_tensor(smoothing, dtype=normals.dtype, device=normals.device)
        # the vertices whose Hessian block is the majorizer's (`curvature_hint`), `[B, m]`
        self.majorized = torch.zeros(normal_force.shape, dtype=torch.bool, device=normals.device)
        self._contacts: tuple[Tensor, ...] | None = None  # `_contact_index`, built on first use
        self._lay_out_batch_last()

    def _lay_out_batch_last(self) -> None:
        # x_n `[d, m, B]`, P `[d, d, m, B]` and μλ `[m, B]`, batch innermost, for the batch-last
        # kernels: read strided from the `[B, m, ...]` originals, each entry would be a gather of its own
        self.previous_positions_t = batch_innermost(self.previous_positions, 2, 1, 0)
        self.projector_t = batch_innermost(self.projector, 2, 3, 1, 0)
        self.weight_t = batch_innermost(self.weight, 1, 0)

    def _contact_index(self) -> tuple[Tensor, ...]:
        # the vertices in contact (λ > 0), the only ones `curvature_hint` can mark: their entries,
        # state vertices, slots in a flattened `[B, m]`, x_n and projectors, gathered once per term
        # (a step's, or its rows') rather than at every iteration, and only where the eager hint is
        # asked for: a compiled batch's line search mostly gives it (`batch_last_curvature_hint`)
        if self._contacts is None:
            entry, vertex = torch.nonzero(self.weight.detach() > 0, as_tuple=True)
            self._contacts = (
                entry,
                self.element_vertices[vertex, 0],
                entry * self.weight.shape[-1] + vertex,
                self.previous_positions.detach()[entry, vertex],
                self.projector.detach()[entry, vertex],
            )
        return self._contacts

    def rows(self, entries: Tensor) -> LaggedFriction:
        """This step's friction for the batch entries `entries` alone (see `EnergyTerm.rows`)."""
        part = self._with(
            previous_positions=self.previous_positions[entries],
            projector=self.projector[entries],
            weight=self.weight[entries],
            majorized=self.majorized[entries],
        )
        part._contacts = None
        part._lay_out_batch_last()
        return part

    def _slip(self, element_positions: Tensor) -> Tensor:
        displacement = element_positions[..., 0, :] - self.previous_positions
        return small_matmul(self.projector, displacement[..., None])[..., 0]

    def warm_start(self, x_prev: Tensor, candidate: Tensor) -> Tensor:
        """`candidate` with every vertex in contact held at x_n (zero slip).

        Along its slip a sliding vertex's friction is linear, so Newton's quadratic model there has
        no curvature and a step that brings a vertex to rest overshoots through zero slip; the line
        search then backtracks. A prediction that moves contact vertices by h·v starts most of them
        sliding, while most stick at the solution. Held, they start in the static zone, whose
        model over-estimates the friction and so errs on the short side. On the worm's 5 s walk
        this took 8.1 → 7.5 Newton iterations per step.
        """
        vertices = self.element_vertices[:, 0]
        touching = (self.weight > 0)[..., None]
        held = candidate.clone()
        held[:, vertices] = torch.where(touching, x_prev[:, vertices], candidate[:, vertices])
        return held

    def curvature_hint(self, previous: Tensor, current: Tensor) -> Tensor:
        """The sliding vertices whose slip points against its direction at `previous` (`[B, n, d]`,
        an iteration's start; `current` its end), `[B, m]` bool: their next Hessian blocks are the
        majorizer's.

        Only the last iteration's reversals count: marking every vertex that ever reversed within
        a step, or every sliding vertex, would keep the majorizer where a vertex slides at the
        solution, and Newton's convergence there would be linear, not quadratic.
        """
        # eager, on the contact vertices alone (the others have no friction to mark), by matrix
        # products, not sums over a last axis of 3, which are slow in eager code
        batch, count, dim = *self.majorized.shape, current.shape[-1]
        entry, vertex, slot, start, projector = self._contact_index()
        rows = entry * current.shape[1] + vertex
        after = projector @ (current.reshape(-1, dim)[rows] - start)[..., None]
        # the projector is symmetric and idempotent: P(x₀ − x_n)·u = (x₀ − x_n)·u
        before = (previous.reshape(-1, dim)[rows] - start)[..., None, :]
        before_along = (before @ after)[..., 0, 0]
        sliding = torch.linalg.vector_norm(after[..., 0], dim=-1) > self.smoothing
        hint = torch.zeros(batch * count, dtype=torch.bool, device=current.device)
        hint[slot] = sliding & (before_along < 0)
        return hint.reshape(batch, count)

    def batch_last_curvature_hint(
        self, start_corners: list[list[Tensor]], corners: list[list[Tensor]]
    ) -> Tensor:
        """`curvature_hint` with the batch innermost, `[m, B]` bool, from the vertices' positions at
        the iteration's start and end as `[i][0]` `[m, B]` (`energysim.objective.batch_last`): fixed
        shapes, so that the compiled line-search trial gives it with its other results and the
        solver needs no eager call where the search takes that trial. Checked against
        `curvature_hint` (tests/test_friction_curvature.py)."""
        slip, length, _ = self._slip_entries(corners)
        dim = len(corners)
        before_along = sum((start_corners[i][0] - self.previous_positions_t[i]) * slip[i] for i in range(dim))
        return (self.weight_t > 0) & (length > self.smoothing) & (before_along < 0)

    def set_curvature_hint(self, hint: Tensor) -> None:
        """Record `curvature_hint`'s marks for the next Hessian blocks."""
        self.majorized.copy_(hint)

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        return self.weight * mollified_slip(self._slip(element_positions), self.smoothing)

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """`element_energy` `[B, m]` in J and μλ f1(y)/y · u per vertex `[B, m, 1, d]` in N."""
        slip = self._slip(element_positions)
        energy = self.weight * mollified_slip(slip, self.smoothing)
        return energy, (self.weight[..., None] * mollified_slip_gradient(slip, self.smoothing))[..., None, :]

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Per-vertex Hessian blocks `[B, m, d, d]`, in N/m, positive semidefinite: exact, or the
        majorizer's where the solver marked the vertex (`curvature_hint`)."""
        slip = self._slip(element_positions)
        hessian = mollified_slip_hessian(slip, self.smoothing, self.projector, self.majorized)
        return self.weight[..., None, None] * hessian

    def _slip_entries(self, corners: list[list[Tensor]]) -> tuple[list[Tensor], Tensor, Tensor]:
        # u = P (x − x_n) by components `[m, B]`, with ‖u‖ and ‖u‖², batch innermost
        dim = len(corners)
        displacement = [corners[j][0] - self.previous_positions_t[j] for j in range(dim)]
        slip = [sum(self.projector_t[i, j] * displacement[j] for j in range(dim)) for i in range(dim)]
        square = sum(component * component for component in slip)
        return slip, slip_length(square), square

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """`element_energy` `[m, B]` and μλ f1(y)/y · u per vertex, entry by entry with the batch
        innermost (see `ElementEnergy.batch_last_energy_and_forces`)."""
        slip, length, square = self._slip_entries(corners)
        weight = self.weight_t
        scale = weight * slip_gradient_scale(length, self.smoothing)
        return weight * slip_value(length, square, self.smoothing), [[scale * u] for u in slip]

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """`element_hessian`'s upper entries `[m, B]`, batch innermost (see
        `ElementEnergy.batch_last_hessian_entries`): μλ[(f1/y) P + (f1′ − f1/y) ûûᵀ]."""
        slip, length, _ = self._slip_entries(corners)
        weight = self.weight_t
        across = weight * slip_gradient_scale(length, self.smoothing)
        along = weight * slip_curvature_along(length, self.smoothing, self.majorized.T)
        divisor = torch.where(length > 0, length, torch.ones_like(length))
        unit = [u / divisor for u in slip]
        dim = len(corners)
        return [
            across * self.projector_t[i, k] + along * unit[i] * unit[k]
            for i in range(dim)
            for k in range(i, dim)
        ]
