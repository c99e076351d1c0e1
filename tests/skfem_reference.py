"""Linear-elastic P1 reference solutions from scikit-fem, on the vertices and elements of an energysim mesh.

Nothing here calls energysim: stiffness, loads and Lamé parameters all come from scikit-fem, so a
comparison with energysim checks its kinematics, material model, assembly and solver against an
independent finite-element code that discretises the same problem with the same elements.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse
from skfem import (
    Basis,
    BilinearForm,
    ElementTetP0,
    ElementTetP1,
    ElementTriP0,
    ElementTriP1,
    ElementVector,
    LinearForm,
    MeshTet,
    MeshTri,
    asm,
    condense,
    solve,
)
from skfem.helpers import ddot, sym_grad
from skfem.models.elasticity import lame_parameters, linear_elasticity, linear_stress

_ELEMENTS = {2: (MeshTri, ElementTriP1, ElementTriP0), 3: (MeshTet, ElementTetP1, ElementTetP0)}


def vector_basis(vertices: np.ndarray, elements: np.ndarray) -> Basis:
    """P1 vector basis on the given simplices (triangles: plane strain; tetrahedra: 3D).

    Args:
        vertices: shape `[n, d]`, in m.
        elements: shape `[m, d+1]`, vertex indices.
    """
    dim = vertices.shape[1]
    mesh_type, element, _ = _ELEMENTS[dim]
    # sort_t=False: MeshTri would otherwise reorder each triangle's vertices; P1 does not need it
    # (it integrates with |det|), and element e must stay element e for per-element moduli
    mesh = mesh_type(
        np.ascontiguousarray(vertices.T, dtype=np.float64), np.ascontiguousarray(elements.T), sort_t=False
    )
    assert np.array_equal(mesh.p, vertices.T) and np.array_equal(mesh.t, elements.T)
    return Basis(mesh, ElementVector(element()))


def stiffness(
    basis: Basis, youngs_modulus: float | np.ndarray, poissons_ratio: float
) -> scipy.sparse.csr_matrix:
    """Linear-elastic stiffness matrix; `youngs_modulus` a scalar or one value per element, in Pa.

    A scalar uses scikit-fem's stock `linear_elasticity` form; per-element values go through a
    DG0 (piecewise constant) field evaluated at the same quadrature points.
    """
    if np.ndim(youngs_modulus) == 0:
        return asm(linear_elasticity(*lame_parameters(float(youngs_modulus), poissons_ratio)), basis)
    youngs_modulus = np.asarray(youngs_modulus, dtype=np.float64)
    assert youngs_modulus.shape == (basis.mesh.nelements,)
    dim = basis.mesh.dim()
    dg0 = basis.with_element(_ELEMENTS[dim][2]())

    @BilinearForm
    def heterogeneous(u, v, w):
        stress = linear_stress(*lame_parameters(w.E, poissons_ratio))
        return ddot(stress(sym_grad(u)), sym_grad(v))

    return asm(heterogeneous, basis, E=dg0.interpolate(youngs_modulus))


def body_force_load(basis: Basis, density: float, gravity: Sequence[float]) -> np.ndarray:
    """Consistent load vector of the body force ρ g, in N, shape `[N]` (scikit-fem DOF order)."""
    acceleration = np.asarray(gravity, dtype=np.float64)

    @LinearForm
    def weight(v, w):
        return density * sum(acceleration[k] * v[k] for k in range(len(acceleration)))

    return asm(weight, basis)


def nodal(basis: Basis, values: np.ndarray) -> np.ndarray:
    """A scikit-fem DOF vector as one row per vertex, shape `[n, d]`."""
    return values[basis.nodal_dofs].T


def clamped_displacement(
    basis: Basis, stiffness_matrix: scipy.sparse.spmatrix, load: np.ndarray, clamped: np.ndarray
) -> np.ndarray:
    """Displacements `[n, d]`, in m, of the linear problem K u = f with u = 0 at the `clamped` vertices."""
    fixed_dofs = basis.nodal_dofs[:, clamped].reshape(-1)
    return nodal(basis, solve(*condense(stiffness_matrix, load, D=fixed_dofs)))
