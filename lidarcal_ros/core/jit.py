"""How the core's per-point loops are compiled (numba).

``nopython`` and ``nogil`` (threads of the correction run them in parallel), ``error_model
"numpy"`` (a division by zero gives inf or NaN as numpy's would, not an exception), cached on
disk next to the module that defines them (or in numba's user cache where that is
read-only).
"""

from __future__ import annotations

import logging
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


__all__ = ["JIT_OPTIONS", "compiled", "inlined"]
