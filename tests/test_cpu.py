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
    assert retain_freed_memory() is True


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="threads"):
        configure(0)
    with pytest.raises(ValueError, match="threshold_bytes"):
        retain_freed_memory(-1)
