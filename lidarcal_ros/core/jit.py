"""How the core's per-point loops are compiled (numba).

``nopython`` and ``nogil`` (threads of the correction run them in parallel), ``error_model
"numpy"`` (a division by zero gives inf or NaN as numpy's would, not an exception), cached on
disk next to the module that defines them (or in numba's user cache where that is
read-only).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import Any, TypeVar, cast

from numba import njit

_log = logging.getLogger(__name__)

#: Options of every compiled function of the core.
JIT_OPTIONS: dict[str, Any] = {"nogil": True, "error_model": "numpy"}
_F = TypeVar("_F", bound=Callable[..., Any])


def compiled(func: _F) -> _F:
    """Compile ``func`` (:data:`JIT_OPTIONS`), cached on disk; where no cache directory is
    writable (a read-only install and home), compiled afresh in each process instead of
    failing the import."""
    try:
        return cast(_F, njit(cache=True, **JIT_OPTIONS)(func))
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        _log.debug("no cache for the compiled loops (%s): compiling in this process", exc)
        return cast(_F, njit(cache=False, **JIT_OPTIONS)(func))


def inlined(func: _F) -> _F:
    """A compiled helper inlined into the compiled functions that call it (no call of its
    own: tuples of floats in and out cost nothing)."""
    return cast(_F, njit(inline="always", **JIT_OPTIONS)(func))


def start_without_blas() -> None:
    """Start numba's compiler now, telling it that no BLAS is at hand.

    numba's first compilation (or cache load) in a process loads its implementations of
    numpy, and one of them imports ``scipy.linalg`` only to learn whether ``np.dot`` and
    ``np.linalg`` can be compiled: some 0.2-0.3 s, a third of numba's start. The compiled
    loops of this package call no BLAS or LAPACK function (``test_jit`` checks their source),
    so a process that only corrects points (``lidarcal correct``, the corrector node's
    numerics) starts numba with scipy.linalg hidden from that one check; scipy.linalg is
    importable as usual afterwards. Where it is imported already, or numba has compiled
    before, numba's check costs nothing and this does nothing more than start it.

    Call it before anything else compiles, from the thread that starts the process's
    compiled loops, while no other thread imports scipy.linalg (for those few hundred
    milliseconds that import would fail).
    """
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.registry import cpu_target

    # Under numba's compiler lock, as its own compilations set the compiler up: a function
    # compiled in another thread meanwhile would otherwise be typed against registries
    # half loaded ("Unknown attribute 'shape' of type array").
    with global_compiler_lock:
        if "scipy.linalg" in sys.modules:
            cpu_target.target_context.refresh()
            return
        sys.modules["scipy.linalg"] = None  # type: ignore[assignment]  # import -> ImportError
        try:
            cpu_target.target_context.refresh()
        finally:
            if sys.modules.get("scipy.linalg", 0) is None:
                del sys.modules["scipy.linalg"]


__all__ = ["JIT_OPTIONS", "compiled", "inlined", "start_without_blas"]
