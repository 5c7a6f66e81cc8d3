"""Publishing serialized (CDR) messages straight from the memory that holds them.

rcl's ``rcl_publish_serialized_message`` through :mod:`ctypes`, else rclpy's copy; why:
docs/internals.md, "ROS messages without copies".
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
    (docs/internals.md).

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
