"""Process-wide tuning of glibc's allocator for streams of large, short-lived buffers.

Why, with figures: docs/internals.md, "Memory allocator".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import mmap
import sys
import threading
from typing import Any

__all__ = [
    "MMAP_THRESHOLD_BYTES", "NODE_TRIM_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES",
    "populate_in_background", "single_malloc_arena", "tune_allocator",
]

_log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: madvise(2) advice: fault in the pages of a range, writable, leaving their contents
#: (Linux 5.14 and later).
_MADV_POPULATE_WRITE = 23

#: Allocations up to this size come from the heap, not a fresh mapping (bytes).
MMAP_THRESHOLD_BYTES = 256 << 20
#: Free memory at the top of the heap is returned to the system above this (bytes).
TRIM_THRESHOLD_BYTES = 512 << 20
#: The same for the processes of the nodes (bytes): a few clouds' worth.
NODE_TRIM_THRESHOLD_BYTES = 64 << 20


def tune_allocator(*, single_arena: bool = True,
                   trim_threshold_bytes: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Keep freed memory in the process: no ``mmap``/``munmap`` and page faults per buffer.

    Memory stays bounded by the largest batch in flight either way; it is just not returned
    to the system between batches.

    Parameters
    ----------
    single_arena : bool
        One malloc arena for all threads (``M_ARENA_MAX`` = 1). Worker threads then do not
        each keep a high-water mark of their own (without it the peak of a threaded
        correction creeps up with the mission's length). The nodes keep glibc's default:
        DDS's own threads allocate there too.
    trim_threshold_bytes : int
        Free memory at the top of the heap beyond this goes back to the system. The nodes
        use less than the default: they run for hours, and a burst (a backlog of clouds)
        should not stay resident.

    Returns
    -------
    bool
        Whether the settings were applied (Linux with glibc only).
    """
    name = ctypes.util.find_library("c")
    if not name or sys.platform != "linux":
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
        ok &= libc.mallopt(_M_TRIM_THRESHOLD, int(trim_threshold_bytes)) == 1
    except (OSError, AttributeError):
        return False
    if single_arena:
        ok &= single_malloc_arena()
    if not ok:
        _log.debug("mallopt refused a setting; glibc's defaults stay")
    return bool(ok)


def single_malloc_arena() -> bool:
    """One glibc malloc arena for every thread of this process from now on (``M_ARENA_MAX``
    = 1); whether it was set (glibc only). Each thread would get its own, and memory one
    thread frees is then not reused by another: ``calibrate --memory bounded`` of 16M points
    peaked at 3437 MiB with the default arenas, 3175 MiB with one, in the same time."""
    try:
        return bool(ctypes.CDLL(None).mallopt(_M_ARENA_MAX, 1) == 1)
    except (OSError, AttributeError):  # (not glibc)
        return False


_madvise: Any = None


def populate_in_background(array: Any) -> threading.Thread | None:
    """Fault in the pages of a large new array in a background thread, without changing
    its contents (``madvise(MADV_POPULATE_WRITE)``, Linux 5.14 or later; elsewhere nothing
    is done).

    A fresh array is otherwise faulted in page by page as it is first written, by the
    thread that writes it: for the 60 MB grid of a wide swath that is 40-180 ms of the
    correction's time here, in the first chunks of a strip. Populating the range in one
    call costs a third of that, runs without the interpreter lock and on the other core,
    and, as the contents are left alone, may overlap the owner's own writes.

    Parameters
    ----------
    array : numpy.ndarray
        Contiguous; only the pages wholly inside it are populated.

    Returns
    -------
    threading.Thread or None
        The thread (daemon), or None when there is nothing to do here.
    """
    global _madvise
    if sys.platform != "linux" or array.nbytes < (1 << 20):
        return None
    if _madvise is None:
        try:
            func = ctypes.CDLL(None, use_errno=True).madvise
        except (OSError, AttributeError):
            _madvise = False
            return None
        func.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        func.restype = ctypes.c_int
        _madvise = func
    if _madvise is False:
        return None
    page = mmap.PAGESIZE
    address = int(array.ctypes.data)
    start = -(-address // page) * page
    stop = (address + int(array.nbytes)) // page * page
    if stop <= start:
        return None
    madvise = _madvise

    def populate(_owner: Any) -> None:  # (the argument keeps the array alive meanwhile)
        if madvise(start, stop - start, _MADV_POPULATE_WRITE) != 0:
            _log.debug("madvise(MADV_POPULATE_WRITE): errno %d", ctypes.get_errno())

    thread = threading.Thread(target=populate, args=(array,), name="lidarcal-populate",
                              daemon=True)
    thread.start()
    return thread
