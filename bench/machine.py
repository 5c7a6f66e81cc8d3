"""What machine a benchmark ran on, in one line, with a memory-speed probe.

The correction and the node benchmarks are bound by memory traffic more than by arithmetic:
on two machines that both report "2 cores", the same commit measured 161-199 and 614-754 ns a
point through the corrector (bench/README.md). A figure quoted without the machine's speed
cannot be compared with another run's, so every benchmark prints this line first:

    .venv/bin/python bench/machine.py
    machine: AMD EPYC, 2 cores, load average 0.4; copy 64 MiB 5.9 GB/s, sin 1M 14.1 ns each;
    Python 3.11.7, numpy 2.4.6, scipy 1.17.1
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def memory_speed() -> dict[str, float]:
    """A quick probe (about 0.3 s) of what the benchmarks' inner work depends on.

    Returns
    -------
    dict
        ``copy_gb_s``: bandwidth of copying a 64 MiB array into another (GB/s, best of 5,
        pages already faulted in: far beyond any cache); ``sin_ns``: numpy's sine of 1M
        float64, ns per element (best of 5: the speed of a vectorised numpy pass).
    """
    import numpy as np

    n = (64 << 20) // 8
    src = np.arange(n, dtype=np.float64)
    dst = np.empty_like(src)
    np.copyto(dst, src)  # fault the destination in outside the timing
    best_copy = min(_timed(lambda: np.copyto(dst, src)) for _ in range(5))
    x = src[: 1 << 20] * 1e-6
    out = np.empty_like(x)
    best_sin = min(_timed(lambda: np.sin(x, out=out)) for _ in range(5))
    return {"copy_gb_s": src.nbytes / best_copy / 1e9, "sin_ns": best_sin / x.size * 1e9}


def _timed(work: Callable[[], object]) -> float:
    start = time.perf_counter()
    work()
    return time.perf_counter() - start


def describe(speed: dict[str, float] | None = None) -> str:
    """One line: CPU model, cores, load average, the memory probe (``speed``, as
    :func:`memory_speed` returns it; probed now if not given), library versions."""
    import numpy
    import scipy

    speed = memory_speed() if speed is None else speed
    return (f"{cpu_model()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; "
            f"copy 64 MiB {speed['copy_gb_s']:.1f} GB/s, sin 1M {speed['sin_ns']:.1f} ns "
            f"each; Python {platform.python_version()}, numpy {numpy.__version__}, scipy "
            f"{scipy.__version__}")


if __name__ == "__main__":
    print(f"machine: {describe()}")
