"""Process-wide CPU settings that make small simulations faster: threads and the memory allocator."""

from __future__ import annotations

import ctypes
import ctypes.util

import torch

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


# Some glibc versions refuse mmap thresholds above 32 MB on 64-bit systems (half their largest heap);
# `retain_freed_memory` then falls back to this.
_OLD_GLIBC_MAX_THRESHOLD = 32 << 20
# The default threshold. A Newton iteration of 64 worms allocates blocks above 32 MB: with a 32 MB
# threshold they still faulted in afresh at every iteration, with 128 MB (and 512 MB) they did not.
RETAINED_BLOCK_BYTES = 256 << 20


def retain_freed_memory(threshold_bytes: int = RETAINED_BLOCK_BYTES) -> bool:
    """Let glibc's malloc keep freed blocks of up to `threshold_bytes` for reuse.

    A Newton step allocates buffers of a few MB to a hundred MB every iteration (the dense Hessian and
    its Cholesky factor for small bodies, element blocks for large ones or large batches). By default
    glibc hands blocks that large straight back to the kernel when they are freed, so the next
    iteration pays a page fault for every 4 kB it touches again: on the shipped creatures about a
    fifth of the step time, and for the env's batch of 64 worms a third (one step solved to 1e-4 m/s:
    0.99 s with a 32 MB threshold, 0.66 s with 128 MB or 512 MB). Blocks below `threshold_bytes` then
    come from the heap, and up to twice that of free memory stays mapped. Where glibc refuses a
    threshold that large (older versions cap it at 32 MB), 32 MB is set. Process-wide, so it is for
    scripts and applications to call, not something `import energysim` does.

    Returns:
        whether the setting was applied (False where the C library is not glibc).
    """
    if threshold_bytes < 0:
        raise ValueError(f"threshold_bytes must be >= 0, got {threshold_bytes}")
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    value = min(threshold_bytes, 1 << 30)  # an int for mallopt; its trim threshold is twice this
    if not mallopt(_M_MMAP_THRESHOLD, value):
        value = min(value, _OLD_GLIBC_MAX_THRESHOLD)
        if not mallopt(_M_MMAP_THRESHOLD, value):
            return False
    return bool(mallopt(_M_TRIM_THRESHOLD, 2 * value))


def configure(threads: int | None = None, *, retain_memory: bool = True) -> None:
    """Set torch's intra-op threads (None: leave as is) and, optionally, `retain_freed_memory()`.

    Meshes of a few thousand elements run fastest on one thread: their tensor operations are too
    small to split, and on a busy machine a second thread mostly waits.

    Blocks above the threshold (`RETAINED_BLOCK_BYTES`) still come fresh from the kernel, 4 kB page by
    page. For meshes of tens of thousands of elements start the process with THP_MEM_ALLOC_ENABLE=1,
    which makes torch allocate buffers of 2 MB and more in huge pages (one Newton–CG step at 101k
    tets: 1.7 → 1.3 s). It cannot be set from here: torch reads it once, at its first allocation.
    """
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    if retain_memory:
        retain_freed_memory()
