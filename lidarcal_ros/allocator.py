"""Process-wide tuning of glibc's allocator for streams of large, short-lived buffers.

Every cloud that passes through lidarcal is a buffer of several MB: a ``bytes`` taken from
DDS, numpy temporaries of the correction, the corrected message. glibc serves allocations
above ``M_MMAP_THRESHOLD`` (128 KiB, raised dynamically only up to 32 MiB and only after a
free) with a fresh ``mmap`` and returns them with ``munmap``, so each buffer is faulted in
page by page and zeroed by the kernel. On this 2-core machine a raw DDS subscription that
takes 9.6 MB clouds spent 2.15 s of CPU per GB taken that way (1.1M page faults in 8 s),
against 0.50 s per GB with the settings below (bench/README.md, "Nodes").
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

_log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8

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
        if single_arena:
            ok &= libc.mallopt(_M_ARENA_MAX, 1) == 1
    except (OSError, AttributeError):
        return False
    if not ok:
        _log.debug("mallopt refused a setting; glibc's defaults stay")
    return bool(ok)
