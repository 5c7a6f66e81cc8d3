"""Taking serialized (CDR) messages straight into memory the caller provides.

rcl's ``rcl_take_serialized_message`` through :mod:`ctypes`, else a plain raw subscription; why:
docs/internals.md, "ROS messages without copies".
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.waitable import NumberOfEntities, Waitable

from lidarcal_ros.nodes.rcl_functions import (
    ALLOCATE,
    DEALLOCATE,
    RCL_RET_OK,
    REALLOCATE,
    ZERO_ALLOCATE,
    SerializedMessage,
    c_function,
    take_rcl_error,
)

__all__ = ["SerializedSubscription", "rcl_serialized_take"]

logger = logging.getLogger(__name__)

#: rcl's return value when there was no message to take (``rcl/types.h``).
_RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401


@functools.cache
def rcl_serialized_take() -> Any:
    """The rcl function ``rcl_take_serialized_message`` through ctypes, or None
    (:func:`~lidarcal_ros.nodes.rcl_functions.c_function`; looked up once)."""
    return c_function("librcl.so", "rcl_take_serialized_message",
                      [ctypes.c_void_p, ctypes.POINTER(SerializedMessage), ctypes.c_void_p,
                       ctypes.c_void_p], ctypes.c_int)


#: ``allocate(size) -> (view, token)``: a writable view of ``size`` bytes to receive a
#: message into, and what the callback gets with it.
Allocate = Callable[[int], tuple[memoryview, Any]]
#: ``callback(message, token)``: the message (a view of the allocated memory, or ``bytes``)
#: and the allocation's token (None for ``bytes``).
Callback = Callable[[memoryview | bytes, Any], None]


class _NotTheSubscription(MutuallyExclusiveCallbackGroup):
    """The group of a subscription taken by a :class:`SerializedSubscription`: rclpy's
    executor runs its QoS event handlers, never the subscription itself (so it never takes
    its messages)."""

    def can_execute(self, entity: Any) -> bool:
        return not isinstance(entity, Subscription) and super().can_execute(entity)

    def beginning_execution(self, entity: Any) -> bool:
        return not isinstance(entity, Subscription) and super().beginning_execution(entity)


class SerializedSubscription(Waitable[Any]):
    """A raw subscription whose messages are taken into the caller's memory (module
    docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    msg_type : type
        The message class (the topic's type).
    topic : str
    qos : rclpy.qos.QoSProfile
    allocate : callable(int) -> (memoryview, token)
        Where to receive a message of so many bytes (called from the executor's thread,
        during the take). It must not fail; a view shorter than asked is refused.
    callback : callable(memoryview or bytes, token)
        Each message, once taken, in order.
    discard : callable(token), optional
        Memory allocated for a message that rcl then failed to deliver (not otherwise
        called).
    callback_group : rclpy.callback_groups.CallbackGroup, optional
        Where the taking and the callback run (the node's default group otherwise).
    direct : bool
        Take into ``allocate``'s memory where rcl allows (else always rclpy's ``bytes``).
    """

    def __init__(self, node: Node, msg_type: Any, topic: str, qos: Any, *,
                 allocate: Allocate, callback: Callback,
                 discard: Callable[[Any], None] | None = None,
                 callback_group: CallbackGroup | None = None, direct: bool = True) -> None:
        group = callback_group if callback_group is not None else node.default_callback_group
        super().__init__(group)
        self._allocate = allocate
        self._callback = callback
        self._discard = discard
        function = rcl_serialized_take() if direct else None
        if function is not None:
            self.subscription = node.create_subscription(
                msg_type, topic, _never_called, qos, raw=True,
                callback_group=_NotTheSubscription())
            if not hasattr(self.subscription.handle, "pointer"):  # (an rclpy without it)
                node.destroy_subscription(self.subscription)
                function = None
        self._function = function
        if function is None:  # a plain raw subscription, taken by rclpy's executor
            self.subscription = node.create_subscription(
                msg_type, topic, lambda raw: callback(raw, None), qos, raw=True,
                callback_group=group)
            return
        self._index = -1
        self._received: tuple[memoryview, Any] | None = None
        # The allocator rmw calls during a take: reallocate (from no buffer) is the one it
        # uses; the others are there because rcutils checks that all four are set.
        self._functions = (ALLOCATE(lambda size, state: None),
                           DEALLOCATE(lambda pointer, state: None),
                           REALLOCATE(self._reallocate),
                           ZERO_ALLOCATE(lambda count, size, state: None))
        node.add_waitable(self)

    @property
    def direct(self) -> bool:
        """Whether messages are taken into ``allocate``'s memory (else ``bytes``)."""
        return self._function is not None

    # -- rclpy's Waitable ----------------------------------------------------------------
    def __enter__(self) -> None:
        # (a destroyed subscription raises here; the executor then leaves it out of the wait
        # set's count, but still calls add_to_wait_set: it must add nothing)
        self._index = -1
        self.subscription.handle.__enter__()
        self._index = 0

    def __exit__(self, *exc: Any) -> None:
        self.subscription.handle.__exit__(*exc)

    def get_num_entities(self) -> NumberOfEntities:
        """One subscription for the wait set."""
        return NumberOfEntities(num_subs=1)

    def add_to_wait_set(self, wait_set: Any) -> None:
        """Add the subscription to ``wait_set`` (nothing if it was destroyed)."""
        if self._index >= 0:
            self._index = wait_set.add_subscription(self.subscription.handle)

    def is_ready(self, wait_set: Any) -> bool:
        """Whether ``wait_set`` says a message is waiting on the subscription."""
        return self._index >= 0 and bool(wait_set.is_ready("subscription", self._index))

    def take_data(self) -> tuple[memoryview, Any] | None:
        """Take one message into memory from ``allocate`` (None: there was none)."""
        function = self._function
        assert function is not None  # (rclpy's executor takes the messages otherwise)
        message = SerializedMessage(None, 0, 0, *self._functions, None)
        self._received = None
        handle = self.subscription.handle
        try:
            with handle:
                ret = function(handle.pointer, ctypes.byref(message), None, None)
        except InvalidHandle:  # destroyed since the wait (as rclpy's own take, skipped)
            return None
        received, self._received = self._received, None
        if ret == RCL_RET_OK and received is not None:
            view, token = received
            return view[:message.buffer_length], token
        if ret not in (RCL_RET_OK, _RCL_RET_SUBSCRIPTION_TAKE_FAILED):
            logger.error("%s: a message could not be taken (%s)",
                         self.subscription.topic_name, take_rcl_error(ret))
        if received is not None and self._discard is not None:  # allocated, not filled
            self._discard(received[1])
        return None

    async def execute(self, taken_data: tuple[memoryview, Any] | None) -> None:
        """Hand a taken message (its bytes and ``allocate``'s token) to the callback."""
        if taken_data is not None:
            self._callback(*taken_data)

    # -- the allocator rmw calls -------------------------------------------------------------
    def _reallocate(self, pointer: int | None, size: int, _state: int | None) -> int | None:
        """The request of rmw for the message's buffer (from none): the caller's memory. Never
        raises (the exception would be lost inside the C call): None refuses."""
        try:
            if pointer or self._received is not None:
                return None  # (a second resize: not how rmw takes a message)
            view, token = self._allocate(int(size))
            if len(view) < size or view.readonly:
                return None
            self._received = (view, token)
            return ctypes.addressof(ctypes.c_char.from_buffer(view))
        except Exception:  # (see the docstring)
            logger.exception("allocating a message of %d bytes", size)
            return None


def _never_called(_raw: bytes) -> None:  # pragma: no cover - the executor never takes it
    raise AssertionError("taken by SerializedSubscription")
