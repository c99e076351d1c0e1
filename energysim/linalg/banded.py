"""Band Cholesky solves of small Hessians on the CPU: LAPACK's `?pbtrf` / `?pbtrs` (scipy), or for
a batch the C kernel of `energysim.linalg.native` that factorises four systems at once (eight with
AVX-512, twice as many in float32).

A long body couples each vertex only to near neighbours. With the DOFs numbered level by level
(`LevelLayout.band_order`, Cuthill–McKee levels and order) its Hessian is a band matrix of
half-bandwidth u, and a band Cholesky factorisation costs about N·u² flops against a dense one's
N³/3 (the worm: N = 432, u = 32). For N = 432, u = 44 a factorisation and solve in lower band
storage takes 0.25 ms in the solver against 1.26 ms for the dense Cholesky and solve it replaced
(profiled on one core); the compiled Hessian is assembled straight into band storage
(`band_positions`). Unlike
the block-tridiagonal solve, it is one LAPACK call per system, with no Python loop over levels, so it
pays for a single body too. LAPACK has no batched band routine, so on its path a batch is a loop
over entries; the C kernel interleaves four systems per SIMD vector instead (`solve_bands_in_tiles`:
4.6–4.8 against 12.1–12.8 ms for 64 random systems of the worm's size, read where they lie). There
is no CUDA form: this path is for the CPU (`prefer_band`).
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from energysim.fem.hessian_entries import upper_entries
from energysim.linalg import native
from energysim.linalg.assembly import dof_indices
from energysim.linalg.block_tridiagonal import LevelLayout
from energysim.linalg.caching import IdentityCache

# LAPACK's band Cholesky factor of one matrix, in lower band storage (Fortran order, `[u + 1, N]`)
BandFactor = np.ndarray

# Band storage wins when N·(u+1)² is well below N³/3; LAPACK's band kernels run at a fraction of the
# dense kernel's flop rate at these sizes, so ask for a clear margin.
BAND_MARGIN = 6
# Entries of a batch are factorised one LAPACK call each; past a few, the batched level solve wins.
BAND_MAX_BATCH = 4
# Band systems of N = 432, u = 44 took 0.33 ms in one tile against LAPACK's 0.59 ms
# for three, 0.35 against 0.41 for two and 0.37 against 0.19 for one (`solve_bands_in_tiles`)
TILE_MIN_BATCH = 3


def prefer_band(
    layout: LevelLayout, batch: int, num_dofs: int, device: torch.device, *, compiled: bool = False
) -> bool:
    """Whether a band factorisation is estimated cheaper than a dense one (N = `num_dofs`).

    With `compiled` the Hessian is assembled straight into band storage by a compiled function, and
    the band path wins for any batch: on 16 worms with random actions it took 608 ms per env step
    against 1,004 ms for the level solve (whose Hessian is assembled eagerly), on 64 worms 3.3 s
    against 4.4 s, and a single 810-tet cantilever (TR-BDF2, h = 1/48 s) 0.53 against 0.69–0.76 s per
    simulated second, all compiled."""
    narrow = BAND_MARGIN * (layout.half_bandwidth + 1) ** 2 < num_dofs**2
    return device.type == "cpu" and (compiled or batch <= BAND_MAX_BATCH) and narrow


def band_cholesky_solve(dense: Tensor, rhs: Tensor, layout: LevelLayout) -> tuple[Tensor, Tensor]:
    """Solve symmetric `dense` `[B, N, N]` systems for `rhs` `[B, N]` by band Cholesky in the layout's
    ordering; returns the solutions `[B, N]` (zero where a system is not positive definite) and which
    systems were positive definite `[B]`. CPU tensors, float32 or float64."""
    batch, size = rhs.shape
    bands = dense.reshape(batch, size * size)[:, layout.band_entries]
    return solve_bands(bands, rhs, layout)


def tiles_solve(batch: int, device: torch.device) -> bool:
    """Whether `solve_bands` takes the C kernel for a batch of `batch` systems on `device`: CPU
    batches of `TILE_MIN_BATCH` or more, where the kernel is built."""
    return device.type == "cpu" and batch >= TILE_MIN_BATCH and native.library() is not None


def solve_keeps_bands(bands: Tensor) -> bool:
    """Whether `solve_bands` leaves `bands` as they are: the C kernel reads them and factorises in its
    own work buffer, where LAPACK's path overwrites them with the factors."""
    return bands.dtype in (torch.float32, torch.float64) and tiles_solve(bands.shape[0], bands.device)


def solve_bands(
    bands: Tensor, rhs: Tensor, layout: LevelLayout, *, single: bool = False
) -> tuple[Tensor, Tensor]:
    """`band_cholesky_solve` from the matrices already in the layout's band storage, `bands`
    `[B, N, u + 1]` with `[b, j, r]` = A[p(j + r), p(j)] (`LevelLayout.band_entries`). `bands` may
    be overwritten by the factors.

    Batches take the C kernel that factorises four float64 systems at once (`solve_bands_in_tiles`)
    where it is built, eight at once in float32 for float32 `bands` or with `single` (twice as many
    with AVX-512); the rest, LAPACK one matrix at a time in the bands' own precision."""
    if solve_keeps_bands(bands):
        return solve_bands_in_tiles(bands, rhs, layout, native.library(), single=single)
    return substitute_bands(factorise_bands(bands), rhs, layout)


def solve_bands_in_tiles(
    bands: Tensor, rhs: Tensor, layout: LevelLayout, kernels: ctypes.CDLL, *, single: bool = False
) -> tuple[Tensor, Tensor]:
    """`solve_bands` by the C kernel of `energysim.linalg.native` (CPU), four float64 systems to a
    tile (`band_tiles.c`), each SIMD operation serving four of them; eight where the CPU has
    AVX-512 and the batch fills more than one tile of four (`native.tile_kernel`). The kernel reads
    the bands where they lie (`_band_strides`); batch-last storage, the compiled band Hessian's
    transposed view, it gathers a tile's systems at a time. `bands` is left unchanged.

    `single` (implied by float32 `bands`): factorise and solve in float32, twice the systems to a
    tile (float64 bands are rounded to a float32 copy first); the solutions are returned in `rhs`'s
    precision. Which systems are positive definite stays float64's verdict: those float32 finds not
    positive definite are solved again in float64 (rounding can tip a nearly singular matrix either
    way)."""
    given, single = bands, single or bands.dtype == torch.float32
    if single and bands.dtype != torch.float32:
        bands = bands.to(torch.float32)  # strides kept: batch-last stays batch-last
    batch, size, width = bands.shape
    kernel, lanes = native.tile_kernel(kernels, single=single, batch=batch)
    real = bands.dtype
    tiles = -(-batch // lanes)
    storage, entry_stride, batch_stride = _band_strides(bands)
    # the kernel reads the right-hand sides and writes the solutions as float64 rows in the DOFs'
    # own order, permuting them into the band order and back itself
    given_rhs = rhs.to(torch.float64).contiguous()
    solution = torch.empty_like(given_rhs)
    positive_definite = torch.empty(tiles * lanes, dtype=torch.uint8)
    work = torch.empty(size * (width + 1) * lanes, dtype=real)
    kernel(
        storage.data_ptr(), entry_stride, batch_stride, batch, size, width, given_rhs.data_ptr(),
        _band_order(layout).data_ptr(), solution.data_ptr(), positive_definite.data_ptr(), work.data_ptr(),
    )
    solved = positive_definite[:batch].bool()
    solution = solution.to(rhs.dtype)
    if single and not bool(solved.all()):
        rows = torch.nonzero(~solved).reshape(-1)
        again, again_solved = solve_bands_in_tiles(given[rows].double(), rhs[rows], layout, kernels)
        solution = solution.index_copy(0, rows, again)
        solved = solved.index_copy(0, rows, again_solved)
    return solution, solved


def _band_order(layout: LevelLayout) -> Tensor:
    # the layout's band order as the kernel reads it: int64, contiguous, on the CPU
    return layout.band_order.to(torch.int64).contiguous()


def _band_strides(bands: Tensor) -> tuple[Tensor, int, int]:
    # `bands` `[B, N, w]` as the kernel reads them, entry (b, i, r) at (i·w + r)·entry_stride +
    # b·batch_stride: the tensor itself where its strides allow that (batch-last or batch-major), else
    # a contiguous copy; and the two strides
    _, _, width = bands.shape
    if bands.stride(1) != width * bands.stride(2):
        bands = bands.contiguous()
    return bands, bands.stride(2), bands.stride(0)


def factorise_bands(bands: Tensor) -> list[BandFactor | None]:
    """The band Cholesky factor of each matrix in `bands` `[B, N, u + 1]` (layout band storage, CPU),
    None where one is not positive definite. `bands` is overwritten by the factors, which share its
    memory: keep `bands` unchanged while they are in use."""
    # [N, u+1] C-contiguous: its transpose is the Fortran-ordered `ab` LAPACK reads, with no copy.
    # Lower storage: OpenBLAS factorises it 2.5× faster than upper storage of the same matrix
    # (135 against 330 µs for N = 432, u = 44).
    bands = bands.contiguous()
    factorise, _ = _band_routines(bands.dtype)
    factors: list[BandFactor | None] = []
    for entry in range(bands.shape[0]):
        factor, info = factorise(bands[entry].numpy().T, lower=1, overwrite_ab=1)
        factors.append(factor if info == 0 else None)
    return factors


def substitute_bands(
    factors: Sequence[BandFactor | None], rhs: Tensor, layout: LevelLayout
) -> tuple[Tensor, Tensor]:
    """Solve with band Cholesky factors (`factorise_bands`, one per row of `rhs` `[B, N]`, or None):
    the solutions `[B, N]` (zero where the factor is None) and which rows were solved `[B]`."""
    batch, _ = rhs.shape
    order = layout.band_order
    permuted = rhs[:, order].contiguous()
    solution = torch.zeros_like(rhs)
    solved = torch.zeros(batch, dtype=torch.bool, device=rhs.device)
    _, substitute = _band_routines(rhs.dtype)
    for entry, factor in enumerate(factors):
        if factor is None:
            continue
        values, info = substitute(factor, permuted[entry].numpy(), lower=1)
        if info == 0:
            solution[entry, order] = torch.from_numpy(values)
            solved[entry] = True
    return solution, solved


@functools.cache
def _band_routines(dtype: torch.dtype) -> tuple[Callable, Callable]:
    # LAPACK's ?pbtrf and ?pbtrs for `dtype`, looked up once (the lookup cost 10 µs a solve)
    from scipy.linalg import lapack

    return lapack.get_lapack_funcs(("pbtrf", "pbtrs"), (torch.zeros(1, dtype=dtype).numpy(),))


def band_length(layout: LevelLayout) -> int:
    """Entries of one matrix in band storage, N·(u + 1)."""
    return layout.band_position.numel() * (layout.half_bandwidth + 1)


_POSITIONS: IdentityCache[Tensor] = IdentityCache(capacity=32)


def band_positions(layout: LevelLayout, element_vertices: Tensor, dim: int) -> Tensor:
    """Where each entry of element Hessian blocks `[m, k·d, k·d]` (flattened) lands in one matrix's
    band storage, flattened, shape `[m·(k·d)²]`. Band storage holds the lower triangle: entries
    above it, which enter through their transposes, go to the extra slot `band_length(layout)`
    (scattering them there measured faster than gathering the kept half first).

    Assembling straight into band storage skips the dense `[N, N]` matrix (1.5 MB for the worm,
    zeroed every Newton iteration) and the gather out of it. Cached per layout and vertex tensor.
    """

    def build() -> Tensor:
        position = layout.band_position[dof_indices(element_vertices, dim)]
        row, column = position[:, :, None], position[:, None, :]
        width = layout.half_bandwidth + 1
        return torch.where(row >= column, column * width + (row - column), band_length(layout)).reshape(-1)

    return _POSITIONS.get((layout, element_vertices), dim, build)


def band_upper_positions(layout: LevelLayout, element_vertices: Tensor, dim: int) -> Tensor:
    """Where the upper entries of element Hessian blocks (`energysim.fem.hessian_entries.upper_entries`,
    element-major: entry p of element e at e·P + p, as the batch-last Hessian stacks them) land in
    one matrix's band storage, shape `[m·P]`: each at its own place or its transpose's, whichever
    lies in the stored lower triangle. Cached per layout and vertex tensor."""

    def build() -> Tensor:
        pairs = upper_entries(element_vertices.shape[1], dim)
        device = element_vertices.device
        rows, columns = (torch.tensor(index, device=device) for index in zip(*pairs, strict=True))
        position = layout.band_position[dof_indices(element_vertices, dim)]
        first, second = position[:, rows], position[:, columns]
        low, high = torch.minimum(first, second), torch.maximum(first, second)
        return (low * (layout.half_bandwidth + 1) + (high - low)).reshape(-1)

    return _UPPER_POSITIONS.get((layout, element_vertices), dim, build)


_UPPER_POSITIONS: IdentityCache[Tensor] = IdentityCache(capacity=32)


def band_diagonal_positions(layout: LevelLayout) -> Tensor:
    """Where each DOF's diagonal entry lies in band storage, shape `[N]` (DOF order)."""
    return layout.band_position * (layout.half_bandwidth + 1)


def eliminate_fixed_in_bands(bands: Tensor, layout: LevelLayout, fixed_dofs: Tensor) -> Tensor:
    """`bands` `[B, N, u + 1]` with the rows and columns of `fixed_dofs` (`[N]` bool, DOF order)
    replaced by the identity's, as `energysim.linalg.assembly.assemble` eliminates them."""
    mask, identity = _elimination(layout, fixed_dofs, bands.dtype)
    bands = bands * mask
    bands[..., 0] += identity
    return bands


_ELIMINATIONS: IdentityCache[tuple[Tensor, Tensor]] = IdentityCache(capacity=32)


def _elimination(layout: LevelLayout, fixed_dofs: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The 0/1 mask `[N, u + 1]` that clears the band entries in a fixed row or column, and the
    fixed DOFs' diagonal `[N]`, both in band order. Built once per layout and set of fixed DOFs:
    building them every call made the elimination take 0.39 ms instead of 0.04 (the compiled
    810-tet cantilever, where the profile put it at 8 % of a Newton iteration). The set is keyed by
    its bytes (a scene hands out a new `free` tensor at every access)."""

    def build() -> tuple[Tensor, Tensor]:
        fixed = fixed_dofs[layout.band_order]
        size, width = fixed.numel(), layout.half_bandwidth + 1
        kept = (~fixed).to(dtype)
        rows = torch.arange(size, device=fixed.device)[:, None] + torch.arange(width, device=fixed.device)
        return kept[:, None] * kept[rows.clamp(max=size - 1)], fixed.to(dtype)

    key = (fixed_dofs.cpu().numpy().tobytes(), dtype, fixed_dofs.device)
    return _ELIMINATIONS.get((layout,), key, build)
