"""The rcl and rcutils C functions the nodes call through :mod:`ctypes`.

Looked up in the libraries rclpy has loaded into this process, never in others found on a path,
so that they are the very rcl rclpy runs on; rclpy must be imported first.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from typing import Any

__all__ = [
    "ALLOCATE", "DEALLOCATE", "RCL_RET_OK", "REALLOCATE", "ZERO_ALLOCATE", "SerializedMessage",
    "c_function", "take_rcl_error",
]

logger = logging.getLogger(__name__)

#: rcl's return value for success (``rcl/types.h``).
RCL_RET_OK = 0

#: The four functions of an ``rcutils_allocator_t`` (``rcutils/allocator.h``), each with
#: the allocator's state last: allocate(size), deallocate(pointer), reallocate(pointer, size),
#: zero_allocate(count, size).
ALLOCATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p)
DEALLOCATE = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p)
REALLOCATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t,
                              ctypes.c_void_p)
ZERO_ALLOCATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t,
                                 ctypes.c_void_p)


class SerializedMessage(ctypes.Structure):
    """``rcl_serialized_message_t`` (= ``rcutils_uint8_array_t``,
    ``rcutils/types/uint8_array.h``): the buffer, its length and capacity, and its
    ``rcutils_allocator_t`` spelt out (the four functions, NULL unless given, and the
    state). Publishing reads the buffer only; a take asks the allocator for it."""

    _fields_ = [
        ("buffer", ctypes.c_void_p),
        ("buffer_length", ctypes.c_size_t),
        ("buffer_capacity", ctypes.c_size_t),
        ("allocate", ALLOCATE),
        ("deallocate", DEALLOCATE),
        ("reallocate", REALLOCATE),
        ("zero_allocate", ZERO_ALLOCATE),
        ("state", ctypes.c_void_p),
    ]


@functools.cache
def _loaded(library: str) -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL(library, mode=getattr(os, "RTLD_NOLOAD", 0))
    except OSError as exc:
        logger.debug("%s is not loaded (%s)", library, exc)
        return None


def c_function(library: str, name: str, argtypes: list[Any], restype: Any) -> Any:
    """Function ``name`` of the loaded ``library`` (``librcl.so``, ``librcutils.so``) with
    these argument and result types, or None where the library is not loaded or lacks it."""
    loaded = _loaded(library)
    function = getattr(loaded, name, None) if loaded is not None else None
    if function is None:
        logger.debug("%s: no %s", library, name)
        return None
    function.argtypes = argtypes
    function.restype = restype
    return function


class _ErrorString(ctypes.Structure):
    """``rcutils_error_string_t``."""

    _fields_ = [("text", ctypes.c_char * 1024)]


def take_rcl_error(ret: int) -> str:
    """The rcl message for the call that just failed with ``ret`` (``rcl error N`` where it
    cannot be read), its error state cleared as rclpy clears it after a failure."""
    get = c_function("librcutils.so", "rcutils_get_error_string", [], _ErrorString)
    reset = c_function("librcutils.so", "rcutils_reset_error", [], None)
    text = get().text.decode(errors="replace") if get is not None else ""
    if reset is not None:
        reset()
    return " ".join(text.split()) or f"rcl error {ret}"
