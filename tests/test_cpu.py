"""Process-wide CPU settings: threads and glibc's allocator."""

from __future__ import annotations

import platform

import pytest
import torch

from energysim.cpu import configure, retain_freed_memory


def test_configure_sets_the_thread_count_and_restores():
    before = torch.get_num_threads()
    try:
        configure(1)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_glibc_accepts_the_allocator_setting():
    import ctypes
    import ctypes.util

    assert retain_freed_memory() is True
    # the setting is glibc's own: a block of the default threshold's size comes from the heap now, so
    # freeing it keeps it mapped (glibc reports its mmapped bytes in mallinfo2's `hblkhd`)
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    if not hasattr(libc, "mallinfo2"):
        pytest.skip("no mallinfo2 in this glibc")

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
            "keepcost",
        )]

    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    mapped = libc.mallinfo2().hblkhd
    block = libc.malloc(64 << 20)  # 64 MB: above the 32 MB older defaults allowed
    try:
        assert libc.mallinfo2().hblkhd == mapped  # not a fresh mmap of its own
    finally:
        libc.free(block)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="threads"):
        configure(0)
    with pytest.raises(ValueError, match="threshold_bytes"):
        retain_freed_memory(-1)
