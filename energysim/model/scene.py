"""A scene: one mesh, its masses, the energy terms it needs, pinned vertices, a time step and a solver."""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from energysim.energies.base import EnergyTerm, check_positive
from energysim.energies.gravity import Gravity
from energysim.mesh import SimplexMesh
from energysim.mesh.indices import as_indices
from energysim.model.converted import ConvertedMirror, check_dtype
from energysim.solvers import NewtonCG, Solver

IMPLICIT_INTEGRATORS = ("implicit_euler", "tr_bdf2")
EXPLICIT_INTEGRATORS = ("leapfrog",)
INTEGRATORS = IMPLICIT_INTEGRATORS + EXPLICIT_INTEGRATORS


class Scene(nn.Module):
    """The static model of a simulation; states are plain tensors kept outside it.

    Args:
        mesh: rest mesh (`TetMesh` in 3D, `TriMesh` in 2D).
        density: ρ in kg/m³ (kg/m² per metre of depth in 2D: 2D quantities are per unit depth).
        dt: time step h in s, > 0.
        gravity: acceleration of gravity, d components, in m/s²; None: no gravity term at all.
        vertex_mass: optional lumped masses, shape `[n]`, in kg, instead of density × rest volume.
        solver: the optimizer for each step; default `NewtonCG(tol=1e-5)`.
        integrator: "implicit_euler" (one solve per step, first order, damps oscillations),
            "tr_bdf2" (two solves per step, second order, keeps slow oscillations) or "leapfrog"
            (explicit position Verlet, second order, no solve, no contact, stable only below the
            Courant limit: `energysim.integrators.explicit`); see `step`.
        substeps: the leapfrog substeps of dt / substeps one step takes (implicit steps take dt
            whole and need 1).

    Example:
        >>> scene = Scene(TetMesh.box(size=(1, .2, .2), cells=(10, 2, 2)), dt=1/60)
        >>> scene.add(NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    """

    def __init__(
        self,
        mesh: SimplexMesh,
        density: float = 1000.0,
        dt: float = 1.0 / 60.0,
        gravity: Sequence[float] | Tensor | None = (0.0, -9.81, 0.0),
        vertex_mass: Tensor | None = None,
        solver: Solver | None = None,
        integrator: str = "implicit_euler",
        substeps: int = 1,
    ) -> None:
        super().__init__()
        if not isinstance(mesh, SimplexMesh):
            raise TypeError(f"mesh must be a TetMesh or TriMesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.dt = dt
        self.integrator = integrator
        self.substeps = substeps
        if vertex_mass is None:
            # density may be a tensor that requires grad (material identification): check its value,
            # in float64 (a Python float read as float32 would turn 1e-300 into 0)
            if not isinstance(density, Tensor):
                if isinstance(density, bool) or not isinstance(density, (int, float)):
                    raise TypeError(f"density must be a number in kg/m^3, got {density!r}")
                density = torch.tensor(float(density), dtype=torch.float64)
            checked = density.detach()
            if not bool(torch.isfinite(checked).all() & (checked > 0).all()):
                raise ValueError(f"density must be finite and > 0 kg/m^3, got {checked.tolist()}")
            vertex_mass = density * mesh.vertex_rest_volume().to(torch.float64)
            underflow = torch.nonzero(vertex_mass.detach() == 0).reshape(-1)
            if underflow.numel():
                raise ValueError(
                    f"density {checked.tolist()} kg/m^3 gives vertex masses (density × rest volume) that "
                    f"underflow to 0 kg in float64 at vertices {underflow[:10].tolist()}: the density is "
                    "too small to represent; give a larger one"
                )
        vertex_mass = torch.as_tensor(vertex_mass, dtype=torch.float64)
        if tuple(vertex_mass.shape) != (mesh.num_vertices,):
            raise ValueError(
                f"vertex_mass must have shape [{mesh.num_vertices}], got {tuple(vertex_mass.shape)}"
            )
        check_positive(vertex_mass, "vertex_mass", "kg")
        self.register_buffer("vertex_mass", vertex_mass)
        self.register_buffer("rest_positions", mesh.vertices.clone())
        self.register_buffer("fixed", torch.zeros(mesh.num_vertices, dtype=torch.bool))
        self.terms = nn.ModuleList()
        # copies in the dtypes and on the devices of the states stepped so far (`matching`)
        self._converted: dict[tuple[torch.dtype, torch.device], ConvertedMirror] = {}
        self.solver: Solver = solver if solver is not None else NewtonCG(tol=1e-5)
        if gravity is not None:
            self.add(Gravity(gravity))

    @property
    def dt(self) -> float:
        """Time step h in s."""
        return self._dt

    @dt.setter
    def dt(self, value: float) -> None:
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"dt must be a finite number > 0 s, got {value!r}")
        self._dt = float(value)

    @property
    def integrator(self) -> str:
        """How a step advances the state: one of `INTEGRATORS`."""
        return self._integrator

    @integrator.setter
    def integrator(self, value: str) -> None:
        if value not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {value!r}")
        self._integrator = value

    @property
    def substeps(self) -> int:
        """Explicit substeps per step (`integrator="leapfrog"`), each of dt / substeps."""
        return self._substeps

    @substeps.setter
    def substeps(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"substeps must be an integer >= 1, got {value!r}")
        self._substeps = value

    @property
    def dim(self) -> int:
        """Spatial dimension d (2 or 3)."""
        return self.mesh.dim

    @property
    def num_vertices(self) -> int:
        return self.mesh.num_vertices

    @property
    def num_dofs(self) -> int:
        """n·d: positions take `num_dofs` entries of a state, velocities the next `num_dofs`."""
        return self.mesh.num_vertices * self.mesh.dim

    @property
    def free(self) -> Tensor:
        """Which vertices move, shape `[n]`, bool."""
        return ~self.fixed

    def add(self, term: EnergyTerm) -> EnergyTerm:
        """Bind `term` to this scene's mesh and add it to the step objective; returns it."""
        if not isinstance(term, EnergyTerm):
            raise TypeError(f"expected an EnergyTerm, got {type(term).__name__}")
        owner = term.scene
        if owner is self:
            raise ValueError(
                f"this {type(term).__name__} is already in this scene: a term is added once (to count "
                "it twice, scale its constants)"
            )
        if owner is not None:
            raise ValueError(
                f"this {type(term).__name__} already belongs to another scene, and its rest data is "
                "bound to that scene's mesh: construct a new term for this scene"
            )
        term.bind(self.mesh, self.vertex_mass)
        term.to(dtype=self.vertex_mass.dtype, device=self.vertex_mass.device)
        term.mark_added(self)
        self.terms.append(term)
        return term

    def matching(self, like: Tensor, what: str = "the state") -> Scene:
        """This scene in the dtype and on the device of `like` (a state or positions): the scene
        itself where they are its own, else a converted copy, kept and brought up to date with this
        scene on every call (`energysim.model.converted`). This scene is never changed, and gradients
        through the copy reach this scene's tensors that require grad.

        Args:
            like: a state `[2·num_dofs]` / `[B, 2·num_dofs]` or positions `[..., n, d]`.
            what: how errors name `like`.

        Raises:
            TypeError: `like` or the scene is not float32 or float64 (half precision cannot hold
                the physics).
            ValueError: a constant of the scene overflows or underflows in `like`'s dtype.
        """
        check_dtype(like.dtype, what)
        own = self.vertex_mass
        check_dtype(own.dtype, "the scene")
        if own.dtype == like.dtype and own.device == like.device:
            return self
        key = (like.dtype, like.device)
        mirror = self._converted.get(key)
        if mirror is None:
            mirror = self._converted[key] = ConvertedMirror(like.dtype, like.device)
        copy = mirror.of(self)
        copy.__dict__["_converted"] = {}
        return copy

    def fix(self, vertex_indices: Sequence[int] | Tensor) -> None:
        """Pin vertices where the state puts them: they are eliminated from every solve.

        Args:
            vertex_indices: integer indices in [0, n) (a list, NumPy array or tensor), or a boolean
                mask of shape `[n]` that is True at the vertices to pin.
        """
        index = as_indices(vertex_indices, "vertex_indices", self.num_vertices, allow_mask=True)
        index = index.reshape(-1).to(self.fixed.device)
        fixed = self.fixed.clone()
        fixed[index] = True
        self.fixed = fixed

    def fix_set(self, name: str) -> None:
        """Pin the vertices of the mesh's vertex set `name` (a gmsh physical group, an Abaqus NSET, ...).

        Raises:
            KeyError: the mesh has no vertex set `name` (the message lists those it has).
            ValueError: the set is empty (it named only points that no element uses).
        """
        sets = self.mesh.vertex_sets
        if name not in sets:
            raise KeyError(f"the mesh has no vertex set {name!r}; it has {sorted(sets)}")
        if sets[name].numel() == 0:
            raise ValueError(f"vertex set {name!r} is empty: none of its points is a vertex of an element")
        self.fix(sets[name])

    def initial_state(
        self, positions: Tensor | None = None, velocities: Tensor | None = None, batch_size: int | None = None
    ) -> Tensor:
        """A state `[x.flatten(), v.flatten()]`, shape `[2·num_dofs]` (or `[B, 2·num_dofs]`).

        Args:
            positions: shape `[n, d]` in m; default the rest positions.
            velocities: shape `[n, d]` in m/s; default zero.
            batch_size: stack B ≥ 1 copies; None: one unbatched state.
        """
        if batch_size is not None:
            try:
                count = None if isinstance(batch_size, bool) else operator.index(batch_size)
            except TypeError:
                count = None
            if count is None or count < 1:
                raise ValueError(f"batch_size must be an integer >= 1 or None, got {batch_size!r}")
            batch_size = count
        x = self.rest_positions if positions is None else torch.as_tensor(positions).to(self.rest_positions)
        v = torch.zeros_like(x) if velocities is None else torch.as_tensor(velocities).to(x)
        for name, value in (("positions", x), ("velocities", v)):
            if tuple(value.shape) != (self.num_vertices, self.dim):
                raise ValueError(
                    f"{name} must have shape [{self.num_vertices}, {self.dim}], got {tuple(value.shape)}"
                )
        state = torch.cat([x.reshape(-1), v.reshape(-1)])
        return state if batch_size is None else state.expand(batch_size, -1).clone()

    def split_state(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """Positions and velocities `[B, n, d]` from a state `[2·num_dofs]` or `[B, 2·num_dofs]`."""
        if not isinstance(state, Tensor):
            raise TypeError(f"state must be a torch.Tensor, got {type(state).__name__}")
        if state.ndim not in (1, 2) or state.shape[-1] != 2 * self.num_dofs:
            raise ValueError(
                f"state must have shape [{2 * self.num_dofs}] or [B, {2 * self.num_dofs}] "
                f"(positions then velocities of {self.num_vertices} vertices in {self.dim}D), "
                f"got {tuple(state.shape)}"
            )
        if not state.is_floating_point():
            raise TypeError(f"state must be a floating-point tensor, got {state.dtype}")
        batched = state.reshape(-1, 2, self.num_vertices, self.dim)
        return batched[:, 0], batched[:, 1]
