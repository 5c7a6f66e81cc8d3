"""``nodes.serialized_subscription.SerializedSubscription`` over loopback DDS: each message
is taken straight into the memory its ``allocate`` gives (a shared-memory ring here),
arrives byte for byte as published, in order, with the token of its memory; rclpy's
executor never takes the messages itself; without rcl's function it is a plain raw
subscription."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from lidarcal_ros.io.cloud.messages import cloud_cdr
from lidarcal_ros.io.cloud.pointcloud import make_point_dtype
from lidarcal_ros.io.cloud.shared_ring import SharedRing
from lidarcal_ros.nodes.serialized_subscription import (
    SerializedSubscription,
    rcl_serialized_take,
)

TOPIC = "/serialized_subscription_test/points"


def _clouds(count: int, points: int) -> list[bytes]:
    out = []
    for k in range(count):
        pts = np.zeros(points + k, dtype=make_point_dtype())
        pts["x"] = 700_000.0 + np.arange(points + k)
        pts["t"] = 2000.0 + k
        out.append(cloud_cdr(k, "map", pts))
    return out


class _Receiver:
    """Allocates in a ring (or in a bytearray once the ring is full) and keeps what came."""

    def __init__(self, ring: SharedRing) -> None:
        self.ring = ring
        self.asked: list[int] = []
        self.got: list[tuple[bytes, Any]] = []

    def allocate(self, size: int) -> tuple[memoryview, Any]:
        self.asked.append(size)
        offset = self.ring.allocate(size)
        if offset is None:
            return memoryview(bytearray(size)), None
        return self.ring.view(offset, size), offset

    def callback(self, message: memoryview | bytes, token: Any) -> None:
        self.got.append((bytes(message), token))
        if token is not None:
            self.ring.free(token)


def _exchange(node: Any, executor: Any, receiver: _Receiver, clouds: list[bytes], *,
              direct: bool = True) -> SerializedSubscription:
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.topics import stream_qos

    subscription = SerializedSubscription(
        node, PointCloud2, TOPIC, stream_qos(100), allocate=receiver.allocate,
        callback=receiver.callback, direct=direct)
    publisher = node.create_publisher(PointCloud2, TOPIC, stream_qos(100))
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    for raw in clouds:
        publisher.publish(raw)
    deadline = time.monotonic() + 10.0
    while len(receiver.got) < len(clouds) and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    node.destroy_publisher(publisher)
    return subscription


def test_messages_are_taken_into_the_given_memory(probe: tuple[Any, Any]) -> None:
    assert rcl_serialized_take() is not None
    clouds = _clouds(5, 20_000)
    ring = SharedRing.create(3 * len(clouds[-1]) + 4096)
    try:
        receiver = _Receiver(ring)
        subscription = _exchange(*probe, receiver, clouds)
        assert subscription.direct
        assert [raw for raw, _ in receiver.got] == clouds  # whole, in order
        assert receiver.asked == [len(raw) for raw in clouds]  # exactly each size, once
        assert all(token is not None for _, token in receiver.got)  # all in the ring
        assert ring.regions_in_use == 0
    finally:
        ring.unlink()
        ring.close()


def test_a_message_larger_than_the_ring_goes_to_memory_of_its_own(
        probe: tuple[Any, Any]) -> None:
    clouds = _clouds(2, 1000) + _clouds(1, 50_000)
    ring = SharedRing.create(len(clouds[0]) * 3)
    try:
        receiver = _Receiver(ring)
        _exchange(*probe, receiver, clouds)
        assert [raw for raw, _ in receiver.got] == clouds
        assert [token is None for _, token in receiver.got] == [False, False, True]
    finally:
        ring.unlink()
        ring.close()


def test_without_rcl_function_messages_arrive_as_bytes(probe: tuple[Any, Any]) -> None:
    clouds = _clouds(3, 1000)
    ring = SharedRing.create(1 << 20)
    try:
        receiver = _Receiver(ring)
        subscription = _exchange(*probe, receiver, clouds, direct=False)
        assert not subscription.direct
        assert receiver.got == [(raw, None) for raw in clouds]
        assert receiver.asked == []
    finally:
        ring.unlink()
        ring.close()


def test_the_executor_spins_on_once_the_subscription_is_destroyed(
        probe: tuple[Any, Any]) -> None:
    node, executor = probe
    clouds = _clouds(1, 100)
    ring = SharedRing.create(1 << 20)
    try:
        receiver = _Receiver(ring)
        subscription = _exchange(node, executor, receiver, clouds)
        node.destroy_subscription(subscription.subscription)
        executor.spin_once(timeout_sec=0.05)  # the waitable adds nothing, raises nothing
        assert not subscription.is_ready(None) and len(receiver.got) == 1
        assert subscription.take_data() is None  # (a take after the wait: skipped)
    finally:
        ring.unlink()
        ring.close()
