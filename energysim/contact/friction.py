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
from energysim.linalg.small_matmul import small_matmul


def _norm_and_square(u: Tensor) -> tuple[Tensor, Tensor]:
    """‖u‖ and ‖u‖² over the last axis; ‖u‖ has a zero (not NaN) derivative at u = 0.

    f0 below ε is written as s/ε − y·s/(3ε²) with s = ‖u‖² smooth, so the kink of y = ‖u‖ at 0
    enters only multiplied by s, whose value and slope vanish there: derivatives stay exact.
    """
    square = (u * u).sum(dim=-1)
    positive = square > 0
    safe = torch.where(positive, square, torch.ones_like(square))
    return torch.where(positive, torch.sqrt(safe), torch.zeros_like(square)), square


def mollified_slip(u: Tensor, smoothing: float | Tensor) -> Tensor:
    """f0(‖u‖) in m, over the last axis of `u` (tangential displacements in m); ε = `smoothing` in m."""
    length, square = _norm_and_square(u)
    ramp = square / smoothing - length * square / (3.0 * smoothing**2) + smoothing / 3.0
    return torch.where(length < smoothing, ramp, length)


def mollified_slip_gradient(u: Tensor, smoothing: float | Tensor) -> Tensor:
    """∇ₓ f0(‖P(x − x_n)‖) = f1(y)/y · u, shape `[..., d]` (dimensionless); f1/y = (2 − y/ε)/ε below ε."""
    length, _ = _norm_and_square(u)
    below = length < smoothing
    safe_length = torch.where(below, smoothing, length)
    over_length = torch.where(below, (2.0 - length / smoothing) / smoothing, 1.0 / safe_length)
    return over_length[..., None] * u


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
    below = length < smoothing
    safe_length = torch.where(below, smoothing, length)
    over_length = torch.where(below, (2.0 - length / smoothing) / smoothing, 1.0 / safe_length)
    along = torch.where(below, -length / smoothing**2, -1.0 / safe_length)
    if majorized is not None:
        along = torch.where(majorized & ~below, torch.zeros_like(along), along)
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
        self._index_contacts()

    def _index_contacts(self) -> None:
        # the vertices in contact (λ > 0), the only ones `curvature_hint` can mark: their (entry,
        # vertex) pairs, x_n and projectors, gathered once a step rather than at every iteration
        entry, vertex = torch.nonzero(self.weight.detach() > 0, as_tuple=True)
        self._contact_entry, self._contact_vertex = entry, self.element_vertices[vertex, 0]
        self._contact_slot = entry * self.weight.shape[-1] + vertex  # in a flattened `[B, m]`
        self._contact_start = self.previous_positions.detach()[entry, vertex]
        self._contact_projector = self.projector.detach()[entry, vertex]

    def rows(self, entries: Tensor) -> LaggedFriction:
        """This step's friction for the batch entries `entries` alone (see `EnergyTerm.rows`)."""
        part = self._with(
            previous_positions=self.previous_positions[entries],
            projector=self.projector[entries],
            weight=self.weight[entries],
            majorized=self.majorized[entries],
        )
        part._index_contacts()
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
        rows = self._contact_entry * current.shape[1] + self._contact_vertex
        after = self._contact_projector @ (current.reshape(-1, dim)[rows] - self._contact_start)[..., None]
        # the projector is symmetric and idempotent: P(x₀ − x_n)·u = (x₀ − x_n)·u
        before = (previous.reshape(-1, dim)[rows] - self._contact_start)[..., None, :]
        before_along = (before @ after)[..., 0, 0]
        sliding = torch.linalg.vector_norm(after[..., 0], dim=-1) > self.smoothing
        hint = torch.zeros(batch * count, dtype=torch.bool, device=current.device)
        hint[self._contact_slot] = sliding & (before_along < 0)
        return hint.reshape(batch, count)

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
