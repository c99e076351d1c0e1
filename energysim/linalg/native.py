"""The package's C kernels, compiled on first use by the system C compiler and loaded with ctypes.

Only what neither torch nor LAPACK offers lives here: a band Cholesky of many small systems at once
(`band_tiles.c`; LAPACK's `?pbtrf` takes one matrix per call). Every kernel has a torch/scipy path
beside it that gives the same result to rounding, so a machine without a compiler loses speed, not
function: `library()` returns None there, and callers take the other path.

The shared object is built once per source, compiler and flags into a cache folder
(`$ENERGYSIM_CACHE_DIR`, else `$XDG_CACHE_HOME/energysim`, else `~/.cache/energysim`), written under
a temporary name and renamed into place, so processes that build it at once never load half a file.
`ENERGYSIM_NATIVE=0` turns the kernels off (the tests use it to check both paths agree).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import torch

SOURCE = "band_tiles.c"
# the builds of `SOURCE` in one library, by the kernel each exports: its preprocessor definitions
# (double precision is the file's default; single: eight systems a 32-byte vector), the name's
# suffix (`-DSUFFIX`) added by `builds`
BUILDS: dict[str, tuple[str, ...]] = {"band_solve_tiles": (), "band_solve_tiles_single": ("-DREAL=float",)}
# where the CPU has AVX-512, every build factorises two columns at once: its 32 vector registers
# (AVX-512VL lends them to 32-byte vectors too) hold both columns' sums
PAIRED: tuple[str, ...] = ("-mavx512f", "-mavx512vl", "-DCOLUMN_PAIRS")
# and each is built again with 64-byte vectors (twice the systems a tile), exported with the
# suffix `_wide`
WIDE: tuple[str, ...] = ("-DVECTOR_BYTES=64",)
# bytes of a SIMD vector in the builds of `BUILDS` and in the wide ones
VECTOR_BYTES = 32
WIDE_VECTOR_BYTES = 64
# a build that takes longer is abandoned and the fallback path taken (it takes ~0.3 s)
BUILD_TIMEOUT_S = 120.0


def enabled() -> bool:
    """Whether the kernels may be used: `ENERGYSIM_NATIVE` is not "0"."""
    return os.environ.get("ENERGYSIM_NATIVE", "1") != "0"


def library() -> ctypes.CDLL | None:
    """The loaded kernels, built first where the cache lacks them; None where they are turned off or
    could not be built or loaded (a warning names why, once)."""
    return _load() if enabled() else None


def cache_dir() -> Path:
    """Where built kernels are kept."""
    chosen = os.environ.get("ENERGYSIM_CACHE_DIR")
    if chosen:
        return Path(chosen)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "energysim"


def compiler() -> str | None:
    """The C compiler: `$CC`, else `cc`, `gcc` or `clang` on the PATH; None without one."""
    named = os.environ.get("CC")
    if named:
        return shutil.which(named)
    return next((path for name in ("cc", "gcc", "clang") if (path := shutil.which(name))), None)


def architecture_flags() -> list[str]:
    """Instruction-set flags for this CPU: AVX2 and FMA where torch found them (4 doubles per
    vector), otherwise the compiler's baseline (SSE2 on x86-64, NEON on arm64), which stays correct
    on any machine the cache is shared with."""
    capability = torch.backends.cpu.get_cpu_capability()
    return ["-mavx2", "-mfma"] if capability in ("AVX2", "AVX512") else []


def has_wide_vectors() -> bool:
    """Whether the kernels are built for 64-byte vectors too: torch found AVX-512 on this CPU."""
    return torch.backends.cpu.get_cpu_capability() == "AVX512"


def builds() -> dict[str, tuple[str, ...]]:
    """The kernels built for this CPU and the definitions and flags each is built with: `BUILDS`,
    and where the CPU has AVX-512, those with column pairs (`PAIRED`) and their wide forms."""
    table = {}
    for name, defines in BUILDS.items():
        suffix = name.removeprefix("band_solve_tiles")
        if not has_wide_vectors():
            table[name] = (*defines, f"-DSUFFIX={suffix}")
            continue
        table[name] = (*defines, *PAIRED, f"-DSUFFIX={suffix}")
        table[f"{name}_wide"] = (*defines, *PAIRED, *WIDE, f"-DSUFFIX={suffix}_wide")
    return table


def tile_kernel(kernels: ctypes.CDLL, *, single: bool, batch: int) -> tuple[Callable, int]:
    """The band kernel (`band_tiles.c`) that solves `batch` systems, and the systems it takes a tile:
    the wide build where the library has it and the batch fills more than one 32-byte tile (for
    fewer, its wider tile would factorise more identity padding than it saves), else the 32-byte one.
    `single`: the float32 build."""
    size = 4 if single else 8
    name = "band_solve_tiles_single" if single else "band_solve_tiles"
    if batch > VECTOR_BYTES // size:
        wide = getattr(kernels, f"{name}_wide", None)
        if wide is not None:
            return wide, WIDE_VECTOR_BYTES // size
    return getattr(kernels, name), VECTOR_BYTES // size


@functools.cache
def _load() -> ctypes.CDLL | None:
    try:
        return _declare(ctypes.CDLL(str(_build())))
    except (OSError, AttributeError, subprocess.SubprocessError, RuntimeError) as error:
        warnings.warn(
            f"energysim: the C band kernels could not be built or loaded ({error}); the band solves take "
            "LAPACK's one-matrix routines instead (slower for batches, same results)",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


def _build() -> Path:
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler (cc, gcc or clang) on the PATH; set CC to name one")
    source = resources.files("energysim.linalg").joinpath(SOURCE).read_text(encoding="utf-8")
    flags = ["-O3", "-std=c99", "-fPIC", *architecture_flags()]
    kernels = builds()
    defines = [define for variant in kernels.values() for define in variant]
    identity = "\0".join([source, cc, *flags, *defines, platform.machine()])
    key = hashlib.sha256(identity.encode()).hexdigest()[:16]
    target = cache_dir() / f"band_tiles-{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as scratch:
        source_path = Path(scratch) / SOURCE
        source_path.write_text(source, encoding="utf-8")
        built = Path(scratch) / target.name
        # the source once per kernel (`builds`), linked into one library
        objects = [str(Path(scratch) / f"{name}.o") for name in kernels]
        commands = [
            [cc, *flags, *variant, "-c", str(source_path), "-o", obj]
            for variant, obj in zip(kernels.values(), objects, strict=True)
        ]
        commands.append([cc, *flags, "-shared", *objects, "-o", str(built), "-lm"])
        for command in commands:
            result = subprocess.run(command, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
            if result.returncode != 0:
                raise RuntimeError(f"{' '.join(command)} failed: {result.stderr.strip()[-500:]}")
        os.replace(built, target)
    return target


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    pointer, size = ctypes.c_void_p, ctypes.c_long
    for name in builds():
        # bands, entry and batch strides, batch, N, w; rhs, order, solution, ok, work
        getattr(lib, name).argtypes = [pointer, size, size, size, size, size, *[pointer] * 5]
        getattr(lib, name).restype = None
    return lib
