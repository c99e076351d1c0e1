"""Energy terms written once, as a density ψ(F); their gradients and Hessian blocks are derived.

A user's elastic term subclasses `DensityEnergy` and writes only `density(F)`, the energy per unit
rest volume of a linear simplex as a pure function of its deformation gradient. Everything the
solvers use comes from that one definition:

    E_e = V_e ψ(F_e),   F_e = Σ_b x_b ⊗ ∇N_b   (linear in the corner positions x_b),
    ∂E_e/∂x_b = V_e P ∇N_b,                      P = ∂ψ/∂F,
    K_e = V_e Sᵀ (∂²ψ/∂F²) S,                    S = ∂vec(F)/∂x_e, constant per element.

P and ∂²ψ/∂F² are taken by `torch.func` on the small `[B, m, d, d]` tensor F alone, never through
the gather of corner positions and F = Ds Dm⁻¹, which makes the derived blocks several times
cheaper than differentiating the whole element energy twice (`autograd_element_hessian`). The
term then has the kernels solvers look for (`element_energy_and_gradient`, `element_hessian`), so
it takes every fast path a built-in term takes: Newton–CG's assembled blocks, the direct solves,
and `torch.compile` (`energysim.objective.compiled`), where `torch.func` traces into the compiled graph.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch
from torch import Tensor
from torch.func import grad, jvp, vjp, vmap

from energysim.compile_settings import package_compile_settings
from energysim.energies.base import ElementEnergy
from energysim.fem.kinematics import deformation_gradient, shape_gradients, simplex_rest_frame
from energysim.linalg.small_matmul import small_matmul
from energysim.mesh import SimplexMesh

DensityFn = Callable[[Tensor], Tensor]
# The derived ∂²ψ/∂F² is hundreds of small operations per call, mostly the zero-filled gradients of
# the entries ψ reads (F[..., i, j]); compiled, they fuse into one loop: the volume term's blocks on
# 1,920 tets take 2 instead of 12 ms. The compilation takes seconds once per term class and device
# (less from torch's on-disk cache), so an eager solver compiles only a term that keeps being called
# on many elements.
COMPILE_AFTER_CALLS = 20
COMPILE_MIN_ELEMENTS = 1000


class DensityEnergy(ElementEnergy):
    """Σ_e V_e ψ(F_e) over the mesh's simplices, with ψ given by the subclass's `density`.

    Subclasses implement `density(F) -> ψ` (J/m³) as a pure function of F, shape `[..., d, d]`,
    returning shape `[...]`, and of the term's own parameters (tensors set in `__init__`, registered
    as buffers so that `.to(device, dtype)` moves them; they may require grad, and may have one
    entry per element, shape `[m]`, which broadcasts against `[..., m]`). Nothing else: the energy,
    its gradient and its per-element Hessian blocks are derived from `density`.

    Example, a volume-preservation term ψ = k/2 (det F − 1)²::

        class VolumePreservation(es.DensityEnergy):
            def __init__(self, stiffness: float) -> None:
                super().__init__()
                self.register_buffer("stiffness", torch.tensor(stiffness, dtype=torch.float64))

            def density(self, F: torch.Tensor) -> torch.Tensor:
                return 0.5 * self.stiffness * (torch.linalg.det(F) - 1.0) ** 2
    """

    has_gradient_kernel = True
    has_hessian_kernel = True
    is_translation_invariant = True
    rest_edge_inverse: Tensor
    rest_volume: Tensor
    # Whether the derived kernels run `torch.compile`d on an eager solver's calls: True always, False
    # never, None (default) once the term has been evaluated `COMPILE_AFTER_CALLS` times on at least
    # `COMPILE_MIN_ELEMENTS` elements (counting the batch), where the compilation pays for itself.
    compile_derivatives: bool | None = None

    def _compiles_derivatives(self, elements: int) -> bool:
        if self.compile_derivatives is not None:
            return self.compile_derivatives
        if elements < COMPILE_MIN_ELEMENTS:
            return False
        calls = self.__dict__.get("_large_calls", 0) + 1
        self.__dict__["_large_calls"] = calls
        return calls > COMPILE_AFTER_CALLS

    def density(self, F: Tensor) -> Tensor:
        """Energy per unit rest volume ψ(F), in J/m³.

        Args:
            F: deformation gradients, shape `[..., d, d]`, dimensionless.

        Returns:
            shape `[...]`.
        """
        raise NotImplementedError(f"{type(self).__name__} must implement density(F), energy per unit volume")

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        """Build the rest frame, volumes and strain maps of the mesh's simplices, and check `density`
        once at the rest state (its shape and finiteness), so a mistake surfaces here, not in a solve."""
        rest_edge_inverse, rest_volume = simplex_rest_frame(mesh.vertices, mesh.elements)
        self.register_buffer("element_vertices", mesh.elements)
        self.register_buffer("rest_edge_inverse", rest_edge_inverse)
        self.register_buffer("rest_volume", rest_volume)
        dim = mesh.dim
        grad_n = shape_gradients(rest_edge_inverse)
        self.register_buffer("shape_gradient", grad_n, persistent=False)
        # S = ∂vec(F)/∂x_e, `[m, d·d, (d+1)·d]`: F_kj = Σ_b x_bk ∇N_bj gives ∇N_bj δ_kl. With √V
        # folded in, K_e = (√V S)ᵀ ∂²ψ/∂F² (√V S) takes two small products per element.
        eye = torch.eye(dim, dtype=grad_n.dtype, device=grad_n.device)
        strain_map = (eye[None, :, None, None, :] * grad_n.transpose(1, 2)[:, None, :, :, None]).flatten(3)
        weighted = strain_map.flatten(1, 2) * rest_volume.sqrt()[:, None, None]
        self.register_buffer("weighted_strain_map", weighted.contiguous(), persistent=False)
        self.register_buffer("weighted_strain_map_t", weighted.transpose(1, 2).contiguous(), persistent=False)
        self._check_density(mesh.num_elements, dim, rest_edge_inverse)

    def _check_density(self, count: int, dim: int, like: Tensor) -> None:
        name = type(self).__name__
        F = torch.eye(dim, dtype=like.dtype, device=like.device).expand(1, count, dim, dim)
        with torch.no_grad():
            value = self.density(F)
        if not isinstance(value, Tensor) or tuple(value.shape) != (1, count):
            shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(
                f"{name}.density(F) must return one energy density per deformation gradient, shape "
                f"F.shape[:-2]; for F of shape {tuple(F.shape)} it returned {shape}"
            )
        bad = ~torch.isfinite(value.reshape(-1))
        if bad.any():
            index = torch.nonzero(bad).reshape(-1)[:10].tolist()
            raise ValueError(f"{name}.density(F) is not finite at F = I for elements {index}")

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """V_e ψ(F_e), shape `[B, m]`, in J, from corner positions `[B, m, d+1, d]` in m."""
        F = deformation_gradient(element_positions, self.rest_edge_inverse)
        return self.rest_volume * self.density(F)

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """V_e ψ(F_e) `[B, m]` in J and its gradient V_e P ∇N_b `[B, m, d+1, d]` in N, with P = ∂ψ/∂F
        derived from `density` on F alone. Detached: parameters' gradients flow through `forward`."""
        energy, gradient = derived_kernel("energy_and_gradient", self, element_positions.detach())
        return energy.detach(), gradient.detach()

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-element Hessian blocks V_e Sᵀ (∂²ψ/∂F²) S, shape `[B, m, (d+1)d, (d+1)d]`, in N/m,
        with ∂²ψ/∂F² derived from `density` (`density_stiffness`)."""
        return derived_kernel("hessian", self, element_positions.detach()).detach()


def density_stress(density: DensityFn, F: Tensor) -> tuple[Tensor, Tensor]:
    """P = ∂ψ/∂F and ψ(F) of a pure density, by one reverse pass on F alone.

    Every entry of F belongs to one element, so the gradient of Σψ is every element's P at once.

    Args:
        density: ψ, maps `[..., d, d]` to `[...]`, in J/m³.
        F: deformation gradients, shape `[..., d, d]`.

    Returns:
        P, shape `[..., d, d]` in Pa, and ψ(F), shape `[...]` in J/m³.
    """

    def total(F: Tensor) -> tuple[Tensor, Tensor]:
        value = density(F)
        return value.sum(), value

    return grad(total, has_aux=True)(F)


def density_stiffness(density: DensityFn, F: Tensor) -> Tensor:
    """∂²ψ/∂F² of a pure density, shape `[..., d·d, d·d]` in Pa (row-major vec(F)), by `torch.func`.

    Column (ij) is the derivative of P along the unit tangent E_ij, the same for every element, so
    all d·d columns of every element come from one vectorised pass over the d·d tangents. Eagerly
    that pass is reverse-over-reverse (a `vjp` of P, fewer operations); while `torch.compile` traces
    it is forward-over-reverse (`jvp` of P), whose tangents fuse into the generated loops.
    """
    dim = F.shape[-1]
    stress = grad(lambda F: density(F).sum())
    basis = torch.eye(dim * dim, dtype=F.dtype, device=F.device)
    tangents = basis.reshape(dim * dim, *([1] * (F.ndim - 2)), dim, dim).expand(dim * dim, *F.shape)
    if torch.compiler.is_compiling():
        columns = vmap(lambda tangent: jvp(stress, (F,), (tangent,))[1])(tangents)
    else:
        _, pullback = vjp(stress, F)
        (columns,) = vmap(pullback)(tangents)
    # columns[c, ..., i, j] = ∂²ψ/∂F_c∂F_ij for tangent c, symmetric in (c, ij)
    return columns.flatten(-2).movedim(0, -1)


def _energy_and_gradient_kernel(term: DensityEnergy, element_positions: Tensor) -> tuple[Tensor, Tensor]:
    F = deformation_gradient(element_positions, term.rest_edge_inverse)
    stress, density = density_stress(term.density, F)
    stress = stress * term.rest_volume[:, None, None]
    return term.rest_volume * density, small_matmul(term.shape_gradient, stress.transpose(-1, -2))


def _hessian_kernel(term: DensityEnergy, element_positions: Tensor) -> Tensor:
    F = deformation_gradient(element_positions, term.rest_edge_inverse)
    stiffness = density_stiffness(term.density, F)
    return small_matmul(
        term.weighted_strain_map_t,
        small_matmul(stiffness, term.weighted_strain_map, fuse_on_cpu=True),
        fuse_on_cpu=True,
    )


_KERNELS: dict[str, Callable] = {
    "energy_and_gradient": _energy_and_gradient_kernel,
    "hessian": _hessian_kernel,
}
_CPU_OPTIONS: dict[str, dict[str, object]] = {"hessian": {"realize_opcount_threshold": 4}}
_COMPILED: dict[tuple[str, str, type], Callable] = {}
_FAILED: set[tuple[str, str, type]] = set()


def _run_kernel(name: str, term: DensityEnergy, element_positions: Tensor, always: bool = False) -> object:
    # one compiled kernel per (kernel, device type, term class), built on the first call that wants it
    key = (name, element_positions.device.type, type(term))
    elements = element_positions.shape[0] * element_positions.shape[1]
    if key not in _FAILED and (always or term._compiles_derivatives(elements)):
        if key not in _COMPILED:
            options = _CPU_OPTIONS.get(name) if key[1] == "cpu" else None
            # static shapes: forward-mode derivatives do not trace with symbolic sizes
            _COMPILED[key] = torch.compile(_KERNELS[name], options=options, dynamic=False)
        try:
            with torch.no_grad(), package_compile_settings():
                return _COMPILED[key](term, element_positions)
        except Exception as error:  # noqa: BLE001 - any compiler failure means: evaluate eagerly
            _FAILED.add(key)
            warnings.warn(
                f"torch.compile could not compile the derived {name} kernel of {type(term).__name__} "
                f"({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
                "deriving it eagerly instead",
                RuntimeWarning,
                stacklevel=4,
            )
    with torch.no_grad():
        return _KERNELS[name](term, element_positions)


_opaque_kernel = torch.compiler.disable(_run_kernel, recursive=True)


def derived_kernel(name: str, term: DensityEnergy, element_positions: Tensor) -> object:
    """The derived kernel `name` ("energy_and_gradient" or "hessian") of `term` at corner positions
    `[B, m, d+1, d]` (see `DensityEnergy.element_energy_and_gradient` and `element_hessian`)."""
    if torch.compiler.is_compiling():
        # Inside a compiled objective the Hessian kernel runs as a compiled graph of its own: fused
        # with another term's blocks, Inductor makes one kernel slower than the two apart
        if name == "hessian":
            return _opaque_kernel(name, term, element_positions, True)
        return _KERNELS[name](term, element_positions)
    return _run_kernel(name, term, element_positions)
