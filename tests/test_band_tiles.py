"""The C kernel that factorises band systems four at a time (`energysim/linalg/band_tiles.c`),
checked against dense float64 algebra on the worm's own Newton matrices, and its build: cached,
replaced whole, and a clear fallback where no compiler builds it."""

from __future__ import annotations

from collections.abc import Iterator
from types import SimpleNamespace

import pytest
import torch
from test_block_tridiagonal import _objective, _worm_batch

from energysim.linalg import banded, native
from energysim.linalg.linear_solve import BandCholesky, solve_with_shifts
from energysim.solvers.newton_cg import INDEFINITE_SHIFTS

needs_compiler = pytest.mark.skipif(native.compiler() is None, reason="no C compiler on this machine")
RTOL = 1e-10


@pytest.fixture
def fresh_build(monkeypatch: pytest.MonkeyPatch, tmp_path) -> Iterator[None]:
    """Kernels built anew into `tmp_path`; the process's loaded kernels restored afterwards."""
    monkeypatch.setenv("ENERGYSIM_CACHE_DIR", str(tmp_path))
    native._load.cache_clear()
    yield
    native._load.cache_clear()


def _worm_systems(noise: list[float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The worm's step Hessians at perturbed states (dense `[B, N, N]`), their band storage
    `[B, N, u + 1]`, and the layout."""
    scene, state, action = _worm_batch(noise, fix=True)
    objective, x = _objective(scene, state, action)
    operator = objective.hessian(x)
    dense = operator.dense(x)
    _, _, layout = operator.level_blocks(x)
    bands = dense.reshape(dense.shape[0], -1)[:, layout.band_entries]
    return dense, bands, layout


def _batch_last_view(bands: torch.Tensor, spare: int) -> torch.Tensor:
    """`bands` `[B, N, w]` as a view of batch-last memory whose rows hold `spare` more columns than B,
    as the compiled band Hessian hands them over (there one: the storage's dropped slot)."""
    batch = bands.shape[0]
    wide = torch.zeros(bands.shape[1] * bands.shape[2], batch + spare, dtype=bands.dtype)
    wide[:, :batch] = bands.reshape(batch, -1).T
    return wide[:, :batch].T.reshape(bands.shape)


def _assert_dense_solutions(
    solution: torch.Tensor, solved: torch.Tensor, dense: torch.Tensor, rhs: torch.Tensor, rtol: float
) -> None:
    """The band solve solved exactly the positive definite systems of `dense`, each as float64 dense
    algebra does to `rtol`, and left the others zero."""
    definite = (torch.linalg.cholesky_ex(dense).info == 0).tolist()
    assert solved.tolist() == definite
    for entry, positive in enumerate(definite):
        if not positive:
            assert bool((solution[entry] == 0).all())
            continue
        expected = torch.linalg.solve(dense[entry], rhs[entry])
        assert float((solution[entry] - expected).norm() / expected.norm()) < rtol


@needs_compiler
@pytest.mark.parametrize("storage", ["batch-major", "batch-last", "padded columns"])
@pytest.mark.parametrize("batch", [2, 5, 8])
def test_the_tiles_solve_the_worms_newton_systems_as_dense_algebra(batch: int, storage: str) -> None:
    # 5 fills two tiles, the second with three identity lanes; noise of 3e-3 makes a Hessian indefinite.
    # batch-major and batch-last storage (a row stride of B + 3) are read where they lie; columns
    # padded to w + 2 entries, which no pair of strides describes, are copied first
    noise = [1e-4 * entry for entry in range(batch)]
    noise[1] = 3e-3
    dense, bands, layout = _worm_systems(noise)
    if storage == "batch-last":
        bands = _batch_last_view(bands, spare=3)
    if storage == "padded columns":
        padded = torch.zeros(*bands.shape[:2], bands.shape[2] + 2, dtype=bands.dtype)
        padded[..., : bands.shape[2]] = bands
        bands = padded[..., : bands.shape[2]]
    assert (banded._band_strides(bands)[0] is bands) == (storage != "padded columns")
    definite = (torch.linalg.cholesky_ex(dense).info == 0).tolist()
    assert not definite[1]
    rhs = torch.randn(batch, dense.shape[-1], generator=torch.Generator().manual_seed(5), dtype=dense.dtype)
    kept = bands.clone()
    solution, solved = banded.solve_bands_in_tiles(bands, rhs, layout, native.library())
    assert torch.equal(bands, kept)  # the kernel only reads the caller's storage
    _assert_dense_solutions(solution, solved, dense, rhs, RTOL)


# float32 solves of the worm's systems (condition numbers near 5e4) land within about 1e-5 of float64's
SINGLE_RTOL = 1e-3


@needs_compiler
@pytest.mark.parametrize("given", ["float64, single", "float32"])
@pytest.mark.parametrize("batch", [3, 9])
def test_single_precision_tiles_solve_the_worms_systems_to_float32_accuracy(batch: int, given: str) -> None:
    # eight systems a tile: 9 fills two, the second with seven identity lanes; entry 1 is indefinite.
    # float64 bands with `single`, or float32 bands (the compiled float32 Hessian's), which imply it
    noise = [1e-4 * entry for entry in range(batch)]
    noise[1] = 3e-3
    dense, bands, layout = _worm_systems(noise)
    bands = _batch_last_view(bands if given != "float32" else bands.float(), spare=3)
    definite = (torch.linalg.cholesky_ex(dense).info == 0).tolist()
    assert not definite[1]
    rhs = torch.randn(batch, dense.shape[-1], generator=torch.Generator().manual_seed(11), dtype=dense.dtype)
    kept = bands.clone()
    assert banded.solve_keeps_bands(bands)
    solution, solved = banded.solve_bands(bands, rhs, layout, single=given != "float32")
    assert torch.equal(bands, kept) and solution.dtype == torch.float64
    _assert_dense_solutions(solution, solved, dense, rhs, SINGLE_RTOL)


@needs_compiler
def test_a_system_singular_in_float32_is_solved_again_in_float64() -> None:
    # [[1, 1], [1, 1 + 1e-9]] in two neighbouring DOFs: positive definite, but 1 + 1e-9 rounds to 1
    # in float32, which leaves a zero pivot; the verdict and the solution must be float64's
    _, bands, layout = _worm_systems([0.0, 1e-4, 2e-4])
    size = bands.shape[1]
    nearly = torch.zeros_like(bands)
    nearly[..., 0] = 1.0
    nearly[1, 10, 1] = 1.0  # A[p(11), p(10)]
    nearly[1, 11, 0] = 1.0 + 1e-9
    matrix = torch.eye(size, dtype=bands.dtype)  # entry 1 in band order
    matrix[10, 11] = matrix[11, 10] = 1.0
    matrix[11, 11] = 1.0 + 1e-9
    rhs = torch.randn(3, size, generator=torch.Generator().manual_seed(12), dtype=bands.dtype)
    solution, solved = banded.solve_bands_in_tiles(nearly, rhs, layout, native.library(), single=True)
    assert solved.tolist() == [True, True, True]
    expected = torch.linalg.solve(matrix, rhs[1, layout.band_order])
    assert float((solution[1, layout.band_order] - expected).norm() / expected.norm()) < 1e-4
    torch.testing.assert_close(solution[[0, 2]], rhs[[0, 2]], rtol=1e-6, atol=0.0)


@needs_compiler
def test_a_nan_system_fails_alone_and_leaves_its_tile_mates_exact() -> None:
    dense, bands, layout = _worm_systems([0.0, 1e-4, 2e-4, 3e-4])
    bands[2, 7, 3] = float("nan")
    rhs = torch.randn(4, dense.shape[-1], generator=torch.Generator().manual_seed(6), dtype=dense.dtype)
    solution, solved = banded.solve_bands_in_tiles(bands, rhs, layout, native.library())
    assert solved.tolist() == [True, True, False, True]
    assert bool(torch.isfinite(solution).all()) and bool((solution[2] == 0).all())
    for entry in (0, 1, 3):
        expected = torch.linalg.solve(dense[entry], rhs[entry])
        assert float((solution[entry] - expected).norm() / expected.norm()) < RTOL


@needs_compiler
def test_both_band_paths_give_one_solution(monkeypatch: pytest.MonkeyPatch) -> None:
    dense, bands, layout = _worm_systems([0.0, 2e-4, 3e-3])
    rhs = torch.randn(3, dense.shape[-1], generator=torch.Generator().manual_seed(8), dtype=dense.dtype)
    tiles, tiles_solved = banded.solve_bands(bands.clone(), rhs, layout)
    monkeypatch.setenv("ENERGYSIM_NATIVE", "0")
    assert native.library() is None
    lapack, lapack_solved = banded.solve_bands(bands.clone(), rhs, layout)
    assert torch.equal(tiles_solved, lapack_solved)
    assert float((tiles - lapack).norm() / lapack.norm()) < RTOL


@needs_compiler
@pytest.mark.parametrize("kernels", ["tiles", "lapack"])
def test_a_kept_band_system_shifts_from_the_unfactorised_hessian(
    kernels: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # `keep` needs H after the first solve, for the shifted retries: the tiles only read the bands, so
    # they are kept as they are; LAPACK factorises in place, so they are copied first. Either way
    # the indefinite entry's retry solves H + τ|diag H| of the first τ that factorises
    if kernels == "lapack":
        monkeypatch.setenv("ENERGYSIM_NATIVE", "0")
    dense, bands, layout = _worm_systems([0.0, 3e-3, 2e-4])
    assert int(torch.linalg.cholesky_ex(dense[1]).info) != 0
    system = BandCholesky.of(bands, layout, keep=True)
    assert (system.pristine is bands) == (kernels == "tiles")
    gradient = torch.randn(3, dense.shape[-1], generator=torch.Generator().manual_seed(10), dtype=dense.dtype)
    rhs = -gradient.reshape(3, -1, 3)
    wanted = torch.ones(3, dtype=torch.bool)
    direction, solved = solve_with_shifts(system, rhs, wanted, INDEFINITE_SHIFTS)
    assert solved.tolist() == [True, True, True]
    for shift in INDEFINITE_SHIFTS:
        shifted = dense[1] + shift * torch.diag(dense[1].diagonal().abs())
        if int(torch.linalg.cholesky_ex(shifted).info) == 0:
            break
    expected = torch.linalg.solve(shifted, -gradient[1])
    assert float((direction[1].reshape(-1) - expected).norm() / expected.norm()) < RTOL


@needs_compiler
def test_the_kernels_are_built_once_and_kept(fresh_build: None, tmp_path) -> None:
    assert native.library() is not None
    built = sorted(tmp_path.iterdir())
    # one shared object, no build folder left behind
    assert len(built) == 1 and built[0].suffix == ".so"
    stamp = built[0].stat().st_mtime_ns
    native._load.cache_clear()
    assert native.library() is not None
    assert sorted(tmp_path.iterdir()) == built and built[0].stat().st_mtime_ns == stamp


def test_without_a_compiler_the_band_solve_warns_and_stays_exact(
    fresh_build: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CC", "no-such-compiler-energysim")
    with pytest.warns(RuntimeWarning, match="no C compiler"):
        assert native.library() is None
    dense, bands, layout = _worm_systems([0.0, 1e-4])
    rhs = torch.randn(2, dense.shape[-1], generator=torch.Generator().manual_seed(9), dtype=dense.dtype)
    solution, solved = banded.solve_bands(bands, rhs, layout)
    assert bool(solved.all())
    # one system at a time: after torch.set_num_threads(n > 1), which other tests call, batched LU
    # solves of large systems fail in some torch builds (MKL rejects the pivots; torch 2.13's CPU wheel)
    expected = torch.stack([torch.linalg.solve(dense[entry], rhs[entry]) for entry in range(len(dense))])
    assert float((solution - expected).norm() / expected.norm()) < RTOL


def test_an_unloadable_cached_kernel_warns_and_leaves_lapack(
    fresh_build: None, monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    # a file in the cache that is no shared object (a foreign or truncated copy): a clear fallback
    spoiled = tmp_path / "band_tiles-spoiled.so"
    spoiled.write_bytes(b"not a shared object")
    monkeypatch.setattr(native, "_build", lambda: spoiled)
    with pytest.warns(RuntimeWarning, match="could not be built"):
        assert native.library() is None


def _random_band_systems(batch: int, size: int, half_bandwidth: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random symmetric, strictly diagonally dominant (so positive definite) band matrices, dense
    `[B, N, N]`, and their band storage in the natural order `[B, N, u + 1]`."""
    generator = torch.Generator().manual_seed(size * 100 + half_bandwidth)
    rows, columns = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    in_band = (rows - columns).abs() <= half_bandwidth
    lower = torch.randn(batch, size, size, generator=generator, dtype=torch.float64).tril(-1) * in_band
    dense = lower + lower.transpose(1, 2)
    dense = dense + torch.diag_embed(dense.abs().sum(-1) + 1.0)
    bands = torch.zeros(batch, size, half_bandwidth + 1, dtype=torch.float64)
    for offset in range(half_bandwidth + 1):
        bands[:, : size - offset, offset] = dense.diagonal(-offset, dim1=1, dim2=2)
    return dense, bands


@needs_compiler
@pytest.mark.parametrize("single", [False, True])
@pytest.mark.parametrize(("size", "half_bandwidth"), [(51, 7), (50, 7), (12, 11), (7, 2), (9, 0)])
def test_band_systems_of_any_order_and_width_solve_as_dense_algebra(
    size: int, half_bandwidth: int, single: bool
) -> None:
    # odd and even orders, a band as wide as the matrix, a diagonal matrix: the edges of the column
    # pairs the wide build factorises; 19 systems fill wide tiles with a short last one where built
    dense, bands = _random_band_systems(19, size, half_bandwidth)
    layout = SimpleNamespace(band_order=torch.arange(size))
    rhs = torch.randn(19, size, generator=torch.Generator().manual_seed(13), dtype=torch.float64)
    solution, solved = banded.solve_bands_in_tiles(bands, rhs, layout, native.library(), single=single)
    # float32 solves of these well-conditioned systems land within a few float32 ulps of float64's
    _assert_dense_solutions(solution, solved, dense, rhs, SINGLE_RTOL if single else RTOL)


@needs_compiler
@pytest.mark.skipif(not native.has_wide_vectors(), reason="no AVX-512 on this machine: no wide kernels")
@pytest.mark.parametrize("single", [False, True])
def test_the_wide_tiles_give_the_narrow_tiles_solutions_to_the_last_bit(
    single: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the same operations on every entry in the same order (`band_tiles.c`): the tile's width
    # changes the speed, not one bit of a direction
    kernels = native.library()
    dense, bands, layout = _worm_systems([1e-4 * entry for entry in range(17)])
    rhs = torch.randn(17, dense.shape[-1], generator=torch.Generator().manual_seed(14), dtype=dense.dtype)
    name = "band_solve_tiles_single" if single else "band_solve_tiles"
    assert native.tile_kernel(kernels, single=single, batch=17)[0] is getattr(kernels, f"{name}_wide")
    wide = banded.solve_bands_in_tiles(bands, rhs, layout, kernels, single=single)
    narrow_lanes = native.VECTOR_BYTES // (4 if single else 8)
    monkeypatch.setattr(native, "tile_kernel", lambda *_, **__: (getattr(kernels, name), narrow_lanes))
    narrow = banded.solve_bands_in_tiles(bands, rhs, layout, kernels, single=single)
    assert torch.equal(wide[1], narrow[1]) and torch.equal(wide[0], narrow[0])
