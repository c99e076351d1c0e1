"""Process-wide CPU settings that make small simulations faster: threads and the memory allocator."""

from __future__ import annotations

import ctypes
import ctypes.util

import torch

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(threshold_bytes: int = 32 << 20) -> bool:
    """Let glibc's malloc keep freed blocks of up to `threshold_bytes` for reuse.

    A Newton step allocates buffers of a few MB every iteration (the dense Hessian and its Cholesky
    factor for small bodies, element blocks for large ones). By default glibc hands blocks that large
    straight back to the kernel when they are freed, so the next iteration pays a page fault for every
    4 kB it touches again; on the shipped creatures that is about a fifth of the step time. Blocks
    below `threshold_bytes` (at most 32 MB, glibc's limit) then come from the heap, and up to twice
    that of free memory stays mapped. Process-wide, so it is for scripts
    and applications to call, not something `import energysim` does.

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
    # glibc refuses mmap thresholds above 32 MB (half its largest heap) on 64-bit systems
    value = min(threshold_bytes, 32 << 20)
    return bool(mallopt(_M_MMAP_THRESHOLD, value)) and bool(mallopt(_M_TRIM_THRESHOLD, 2 * value))


def configure(threads: int | None = None, *, retain_memory: bool = True) -> None:
    """Set torch's intra-op threads (None: leave as is) and, optionally, `retain_freed_memory()`.

    Meshes of a few thousand elements run fastest on one thread: their tensor operations are too
    small to split, and on a busy machine a second thread mostly waits.

    Blocks above 32 MB still come fresh from the kernel, 4 kB page by page. For meshes of tens of
    thousands of elements start the process with THP_MEM_ALLOC_ENABLE=1, which makes torch allocate
    buffers of 2 MB and more in huge pages (one Newton–CG step at 101k tets: 1.7 → 1.3 s). It cannot
    be set from here: torch reads it once, at its first allocation.
    """
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    if retain_memory:
        retain_freed_memory()
