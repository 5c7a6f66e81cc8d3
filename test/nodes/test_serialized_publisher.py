"""``nodes.serialized_publisher.SerializedPublisher`` over loopback DDS: a serialized cloud
published from ``bytes``, a ``bytearray``, a ``memoryview`` or a shared-memory ring arrives
byte for byte as rclpy's own ``publish(bytes)`` sends it, rcl taking the buffer in place."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from lidarcal_ros.io.cloud.messages import cloud_cdr
from lidarcal_ros.io.cloud.pointcloud import make_point_dtype
from lidarcal_ros.io.cloud.shared_ring import SharedRing
from lidarcal_ros.nodes.serialized_publisher import SerializedPublisher, rcl_serialized_publish

TOPIC = "/serialized_publisher_test/points"


@pytest.fixture()
def link(probe: tuple[Any, Any]) -> tuple[Any, Any, list[bytes]]:
    """A publisher and a raw subscriber of PointCloud2 on the probe node, its executor, and
    what the subscriber received."""
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.topics import stream_qos

    node, executor = probe
    received: list[bytes] = []
    publisher = node.create_publisher(PointCloud2, TOPIC, stream_qos(100))
    node.create_subscription(PointCloud2, TOPIC, received.append, stream_qos(100), raw=True)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return publisher, executor, received


def _receive(executor: Any, received: list[bytes], count: int) -> list[bytes]:
    deadline = time.monotonic() + 10.0
    while len(received) < count and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    assert len(received) == count, f"{len(received)} of {count} messages arrived"
    return list(received)


def _clouds(count: int, points: int = 50_000) -> list[bytes]:
    rng = np.random.default_rng(7)
    out = []
    for k in range(count):
        pts = np.zeros(points, dtype=make_point_dtype())
        pts["x"] = 500_000.0 + rng.uniform(0, 100, points)
        pts["t"] = 1000.0 + k + np.arange(points) * 1e-6
        out.append(cloud_cdr(k, "map", pts))
    return out


def test_rcl_function_is_found_once_rclpy_is_loaded(ros_context: Any) -> None:
    assert rcl_serialized_publish() is not None


def test_every_kind_of_buffer_arrives_as_rclpy_sends_bytes(
        link: tuple[Any, Any, list[bytes]]) -> None:
    publisher, executor, received = link
    direct = SerializedPublisher(publisher)
    assert direct.direct
    clouds = _clouds(4)
    ring = SharedRing.create(8 << 20)
    try:
        offset = ring.allocate(len(clouds[3]))
        assert offset is not None
        ring.write(offset, [clouds[3]])
        publisher.publish(clouds[0])  # rclpy's own
        direct.publish(clouds[0])
        direct.publish(bytearray(clouds[1]))
        direct.publish(memoryview(clouds[2])[:])
        with ring.view(offset, len(clouds[3])) as view:
            direct.publish(view)
    finally:
        ring.unlink()
        ring.close()
    got = _receive(executor, received, 5)
    assert got == [clouds[0], clouds[0], clouds[1], clouds[2], clouds[3]]


def test_without_rcl_function_it_publishes_a_bytes_copy(
        link: tuple[Any, Any, list[bytes]]) -> None:
    publisher, executor, received = link
    fallback = SerializedPublisher(publisher, direct=False)
    assert not fallback.direct
    clouds = _clouds(2, points=1000)
    fallback.publish(memoryview(clouds[0]))
    fallback.publish(clouds[1])
    assert _receive(executor, received, 2) == clouds
