"""Publishing serialized (CDR) messages straight from the memory that holds them.

rclpy publishes a serialized message only from a Python :class:`bytes`, and copies that into
a C++ string before it hands it to rcl: a corrected cloud held in a shared-memory ring would
be copied twice (into the ``bytes``, then into the string) before DDS copies it once more
into its own segment, and rclpy holds the interpreter lock all the while. At 4M points/s
those two copies, 13 MB each, cost about a tenth of a core.

:class:`SerializedPublisher` gives rcl the buffer itself: rcl's public C function
``rcl_publish_serialized_message`` (``rcl/publisher.h``) called through :mod:`ctypes` with
the address of the publisher that rclpy documents (``Publisher.handle.pointer``, "the address
of the entity") and an ``rcutils_uint8_array_t`` (``rcutils/types/uint8_array.h``) that points
at the caller's bytes. DDS makes the one copy it always makes; ctypes lets the interpreter
lock go during the call. Where the library or the address is not to be had (another rclpy,
another platform), it publishes as rclpy does, from a ``bytes`` copy of the buffer.
"""

from __future__ import annotations

import ctypes
import functools
from typing import Any

import numpy as np

from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.nodes.rcl_functions import (
    RCL_RET_OK,
    SerializedMessage,
    c_function,
    take_rcl_error,
)

__all__ = ["SerializedPublisher", "rcl_serialized_publish"]


@functools.cache
def rcl_serialized_publish() -> Any:
    """The rcl function ``rcl_publish_serialized_message`` through ctypes, or None
    (:func:`~lidarcal_ros.nodes.rcl_functions.c_function`; looked up once)."""
    return c_function("librcl.so", "rcl_publish_serialized_message",
                      [ctypes.c_void_p, ctypes.POINTER(SerializedMessage), ctypes.c_void_p],
                      ctypes.c_int)


class SerializedPublisher:
    """Publishes serialized messages on an rclpy publisher from any contiguous buffer
    (module docstring).

    Parameters
    ----------
    publisher : rclpy.publisher.Publisher
        The publisher (of the messages' type) that rclpy made.
    direct : bool
        Hand rcl the buffer itself where rcl's function is to be had (else always a
        ``bytes`` copy through rclpy).
    """

    def __init__(self, publisher: Any, *, direct: bool = True) -> None:
        self.publisher = publisher
        function = rcl_serialized_publish() if direct else None
        if function is not None and not hasattr(publisher.handle, "pointer"):
            function = None
        self._function = function

    @property
    def direct(self) -> bool:
        """Whether messages go to rcl from the caller's buffer (no copy in Python)."""
        return self._function is not None

    def publish(self, data: bytes | bytearray | memoryview) -> None:
        """Publish one serialized message (its CDR bytes, encapsulation header first).
        ``data`` is read during the call only.

        Raises
        ------
        LidarcalError
            rcl refused the message (publisher destroyed, context shut down).
        """
        if self._function is None:
            self.publisher.publish(data if isinstance(data, bytes) else bytes(data))
            return
        array = np.frombuffer(data, dtype=np.uint8)  # its address; no copy
        message = SerializedMessage(array.ctypes.data, array.size, array.size)
        handle = self.publisher.handle
        with handle:  # (not destroyed while rcl reads it)
            ret = self._function(handle.pointer, ctypes.byref(message), None)
        if ret != RCL_RET_OK:
            raise LidarcalError(f"{self.publisher.topic_name}: publishing failed "
                                f"({take_rcl_error(ret)})")
