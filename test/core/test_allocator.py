"""Process memory helpers (lidarcal_ros.core.allocator) against what the kernel reports."""

from __future__ import annotations

import ctypes
import mmap
import sys

import numpy as np
import pytest

from lidarcal_ros.core.allocator import populate_in_background

linux_only = pytest.mark.skipif(sys.platform != "linux", reason="madvise/mincore of Linux")


def _resident_pages(array: np.ndarray) -> int:
    """Pages of ``array`` in memory, from mincore(2)."""
    page = mmap.PAGESIZE
    start = -(-array.ctypes.data // page) * page
    stop = (array.ctypes.data + array.nbytes) // page * page
    count = (stop - start) // page
    vec = (ctypes.c_ubyte * count)()
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    assert libc.mincore(start, stop - start, vec) == 0, ctypes.get_errno()
    return sum(v & 1 for v in vec)


@linux_only
def test_populate_faults_in_a_fresh_array_in_the_background() -> None:
    # A fresh anonymous mapping: no page is in memory until it is touched.
    area = mmap.mmap(-1, 64 << 20)
    fresh = np.frombuffer(area, dtype=np.float64)
    assert _resident_pages(fresh) < 16
    thread = populate_in_background(fresh)
    if thread is None:
        pytest.skip("madvise is not available here")
    thread.join(timeout=30)
    assert _resident_pages(fresh) > 0.99 * (64 << 20) // mmap.PAGESIZE
    del fresh
    area.close()


@linux_only
def test_populate_leaves_the_contents_alone_while_they_are_written() -> None:
    values = np.arange(8 << 20, dtype=np.float64)  # 64 MB, written: resident
    expected = values.copy()
    thread = populate_in_background(values)
    values[::1000] += 1.0  # the owner writes meanwhile
    expected[::1000] += 1.0
    if thread is not None:
        thread.join(timeout=30)
    np.testing.assert_array_equal(values, expected)


def test_nothing_is_done_for_a_small_array() -> None:
    assert populate_in_background(np.empty(1000)) is None
