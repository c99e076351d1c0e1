"""Simplex meshes (tetrahedra in 3D, triangles in 2D): validation, generators and file I/O."""

from .io import MeshFileError, MeshFileNotFoundError, load_mesh
from .primitives import kuhn_pattern
from .simplex import SimplexMesh, TetMesh, TriMesh
from .validation import format_indices, signed_volumes

__all__ = [
    "SimplexMesh",
    "TetMesh",
    "TriMesh",
    "load_mesh",
    "MeshFileError",
    "MeshFileNotFoundError",
    "signed_volumes",
    "format_indices",
    "kuhn_pattern",
]
