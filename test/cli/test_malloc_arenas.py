"""One glibc malloc arena for the command line's threads (cli/main.py's console_main,
core/allocator.py's single_malloc_arena)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

#: Four threads malloc (blocks over pymalloc's 512 bytes), all alive at once (a thread that
#: ended hands its heap to the next one: on a loaded machine they could run one after the
#: other), then glibc's malloc_stats prints one "Arena N:" line a heap to stderr.
_PROGRAM = """
import ctypes, sys, threading
if sys.argv[1] == "one":
    from lidarcal_ros.core.allocator import single_malloc_arena
    assert single_malloc_arena()
together = threading.Barrier(4)
def work():
    together.wait()
    held = [bytearray(4000) for _ in range(200)]
    together.wait()
threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads: t.start()
for t in threads: t.join()
ctypes.CDLL(None).malloc_stats()
"""


def _arenas(mode: str) -> int:
    # (without glibc's settings from the environment: a local Dask cluster's nannies set
    # MALLOC_ARENA_MAX in the environment of the process that started them, this one's)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    res = subprocess.run([sys.executable, "-c", _PROGRAM, mode], capture_output=True,
                         text=True, timeout=120, check=True, env=env)
    return sum(line.startswith("Arena ") for line in res.stderr.splitlines())


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_the_threads_share_one_arena() -> None:
    assert _arenas("default") > 1  # (each thread its own: what the limit is for)
    assert _arenas("one") == 1
