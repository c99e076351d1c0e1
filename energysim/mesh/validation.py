"""The checks a simplex mesh passes once, at construction, and the signed volumes they judge by.

`validated` returns the rest positions as float64 and the elements as int64, every element
positively oriented (a negatively oriented one has its last two vertices swapped), or raises
ValueError naming the offending indices: non-finite coordinates, indices out of range, flat or
repeated-vertex elements (judged relative to each element's size), elements listed twice, vertices no
element uses, and elements overlapping across a shared facet.
"""

from __future__ import annotations

import itertools
import logging
import math

import torch

# the meshes' own logger: reorientation is news about the mesh being built
logger = logging.getLogger("energysim.mesh.simplex")

# Relative threshold below which an element counts as flat: |volume| <= tol * (mean edge length)**d.
DEGENERACY_TOLERANCE = 1e-12

# Faces of a positively oriented tet (v0..v3), each ordered so its right-hand normal points outwards.
TET_FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
# Edges of a positively oriented (counter-clockwise) triangle; traversed CCW, the outside is on the right.
TRI_EDGES = ((0, 1), (1, 2), (2, 0))


def format_indices(indices: torch.Tensor, limit: int = 10) -> str:
    """Format the indices `indices` (shape `[k]`) as `"[a, b, ...]"`, listing at most `limit` of them."""
    values = indices.flatten().tolist()
    text = "[" + ", ".join(str(int(v)) for v in values[:limit]) + "]"
    if len(values) > limit:
        text += f" and {len(values) - limit} more"
    return text


def _edge_determinant(edges: torch.Tensor) -> torch.Tensor:
    """det of the d edge vectors `edges[..., k, :]` (shape `[..., d, d]`), shape `[...]`."""
    if edges.shape[-1] == 3:
        # Explicit triple product: exactly zero for repeated vertices, unlike an LU-based determinant.
        return (edges[..., 0, :] * torch.linalg.cross(edges[..., 1, :], edges[..., 2, :])).sum(-1)
    return edges[..., 0, 0] * edges[..., 1, 1] - edges[..., 0, 1] * edges[..., 1, 0]


def signed_volumes(vertices: torch.Tensor, elements: torch.Tensor) -> torch.Tensor:
    """Signed simplex volumes, differentiable in `vertices`.

    `vertices`: positions, shape `[n, d]` with d = 2 or 3, in m. `elements`: vertex indices, shape
    `[m, d + 1]`. Returns shape `[m]`, in m^d: `det[x1-x0, x2-x0, x3-x0] / 6` in 3D, `det[x1-x0, x2-x0] / 2`
    in 2D (area, i.e. volume per metre of depth). Positive for positively oriented elements.
    """
    x = vertices[elements]
    edges = x[:, 1:] - x[:, :1]
    return _edge_determinant(edges) / (6.0 if vertices.shape[1] == 3 else 2.0)


def check_finite(vertices: torch.Tensor) -> None:
    """Refuse vertices `[n, d]` with a NaN or infinite coordinate, naming them."""
    bad = torch.nonzero(~torch.isfinite(vertices).all(dim=1)).flatten()
    if bad.numel():
        raise ValueError(f"vertices {format_indices(bad)} have NaN or infinite coordinates")


def _row_keys(rows: torch.Tensor) -> torch.Tensor:
    """For non-negative integer rows, shape `[r, k]`, an int64 key per row, shape `[r]`, equal exactly
    for equal rows."""
    # Fold the columns into one scalar key, replacing the partial key by its dense rank before each
    # step so it stays below r * n (no int64 overflow); 1-D unique is far faster than unique(dim=0).
    key = rows[:, 0]
    for column in range(1, rows.shape[1]):
        rank = torch.unique(key, return_inverse=True)[1]
        key = rank * (int(rows[:, column].max()) + 1) + rows[:, column]
    return key


def _key_counts(key: torch.Tensor) -> torch.Tensor:
    """How many entries of `key` (shape `[r]`) equal each one, shape `[r]`."""
    _, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse]


def row_counts(rows: torch.Tensor) -> torch.Tensor:
    """For non-negative integer rows, shape `[r, k]`, how many rows equal each one, shape `[r]`."""
    return _key_counts(_row_keys(rows))


def _check_degenerate(vertices: torch.Tensor, elements: torch.Tensor, dim: int) -> None:
    """Refuse elements with a repeated vertex or (near) zero volume, and volumes float64 cannot hold.

    Flatness is judged on each element scaled to unit size (its edges divided by its largest coordinate
    extent), so the test is the same for a mesh in micrometres or in kilometres and cannot overflow.
    """
    sorted_ids = elements.sort(dim=1).values
    repeated = (sorted_ids[:, 1:] == sorted_ids[:, :-1]).any(dim=1)
    x = vertices[elements]
    extent = (x.amax(dim=1) - x.amin(dim=1)).amax(dim=1)
    unit = (x[:, 1:] - x[:, :1]) / torch.where(extent > 0, extent, torch.ones_like(extent))[:, None, None]
    unit_volume = _edge_determinant(unit) / math.factorial(dim)
    pairs = torch.tensor(list(itertools.combinations(range(dim), 2)))
    # Edges between vertices 1..d, plus the d edges from vertex 0 (the rows of `unit`).
    other_edges = unit[:, pairs[:, 1]] - unit[:, pairs[:, 0]]
    lengths = torch.cat([unit.norm(dim=-1), other_edges.norm(dim=-1)], dim=1)
    mean_edge = lengths.mean(dim=1)
    # Written as "not above" so that a NaN from coincident vertices counts as flat.
    flat = ~(unit_volume.abs() > DEGENERACY_TOLERANCE * mean_edge**dim)
    bad = torch.nonzero(repeated | flat | (extent == 0)).flatten()
    if bad.numel():
        raise ValueError(
            f"{bad.numel()} degenerate (repeated-vertex or near-zero-volume) elements {format_indices(bad)}"
        )
    volume = signed_volumes(vertices, elements)
    bad = torch.nonzero(~torch.isfinite(volume) | (volume == 0)).flatten()
    if bad.numel():
        raise ValueError(
            f"elements {format_indices(bad)} are well shaped but their volumes overflow or underflow "
            f"float64 (element sizes {float(extent.min()):.3g} to {float(extent.max()):.3g} m); "
            "rescale the mesh to metres"
        )


def _check_distinct(elements: torch.Tensor) -> None:
    """Refuse two elements on the same vertex set (an element listed twice, in any vertex order)."""
    key_counts = row_counts(elements.sort(dim=1).values)
    bad = torch.nonzero(key_counts > 1).flatten()
    if bad.numel():
        raise ValueError(
            f"elements {format_indices(bad)} repeat another element's vertices (an element listed twice, "
            "possibly with its vertices permuted); each element must appear once"
        )


def _permutation_parity(order: torch.Tensor) -> torch.Tensor:
    """Parity (0 even, 1 odd) of each row of `order`, a permutation of 0..k-1, shape `[r, k]`."""
    k = order.shape[1]
    inversions = sum((order[:, i] > order[:, j]).long() for i in range(k) for j in range(i + 1, k))
    return inversions % 2


def _check_no_overlap(elements: torch.Tensor, dim: int) -> None:
    """Refuse positively oriented elements that overlap in volume across a shared facet.

    In a valid mesh a facet bounds at most two elements, one on each side, so the two traverse it in
    opposite orientations. A facet of three or more elements, or of two that traverse it the same way
    (both on the same side), means the elements overlap.
    """
    local = TET_FACES if dim == 3 else TRI_EDGES
    facets = elements[:, local].reshape(-1, dim)
    ordered = facets.sort(dim=1)
    parity = _permutation_parity(ordered.indices)
    owner = torch.arange(elements.shape[0]).repeat_interleave(len(local))
    key = _row_keys(ordered.values)
    shared = _key_counts(key)
    same_way = _key_counts(2 * torch.unique(key, return_inverse=True)[1] + parity)
    crowded = shared > 2
    if bool(crowded.any()):
        first = facets[crowded][0].sort().values
        raise ValueError(
            f"elements {format_indices(torch.unique(owner[crowded]))} overlap: facets shared by more than "
            f"two elements (e.g. vertices {format_indices(first)})"
        )
    same_side = (shared == 2) & (same_way == 2)
    if bool(same_side.any()):
        first = facets[same_side][0].sort().values
        raise ValueError(
            f"elements {format_indices(torch.unique(owner[same_side]))} overlap: they lie on the same side "
            f"of a shared facet (e.g. vertices {format_indices(first)})"
        )


def validated(vertices: torch.Tensor, elements: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Copies of `vertices` `[n, dim]` (as float64) and `elements` `[m, dim + 1]` (as int64) that pass
    every check, with negatively oriented elements reoriented; ValueError naming the offending
    indices where a check fails. The shapes and dtypes are the caller's to check first."""
    vertices = vertices.to(torch.float64).clone().contiguous()
    elements = elements.to(torch.int64).clone().contiguous()
    n = vertices.shape[0]
    check_finite(vertices)

    bad = torch.nonzero(((elements < 0) | (elements >= n)).any(dim=1)).flatten()
    if bad.numel():
        raise ValueError(
            f"elements {format_indices(bad)} reference vertex indices outside [0, {n}) ({n} vertices)"
        )

    _check_degenerate(vertices, elements, dim)
    volume = signed_volumes(vertices, elements)
    _check_distinct(elements)

    used = torch.bincount(elements.flatten(), minlength=n) > 0
    bad = torch.nonzero(~used).flatten()
    if bad.numel():
        raise ValueError(f"vertices {format_indices(bad)} are used by no element")

    negative = volume < 0
    count = int(negative.sum())
    if count:
        # Swapping two vertices flips the sign of the determinant and leaves the element unchanged.
        elements[negative] = elements[negative][:, [*range(dim - 1), dim, dim - 1]]
        logger.info("reoriented %d of %d negatively oriented elements", count, elements.shape[0])
    _check_no_overlap(elements, dim)
    return vertices, elements.contiguous()
