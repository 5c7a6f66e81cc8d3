"""The nodes' trajectory subscription (``nodes.trajectory_input.TrajectoryInput``) over
loopback DDS.

With ``trajectory_type`` ``auto`` the node must already listen when a stream starts: a
subscription made only once a publisher has been seen on the graph loses the first samples of
every replay started after the node (at 10x, the whole trajectory of the first strip, which
the calibrator then cannot use). It follows another accepted type when the publishers use one.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from lidarcal_ros.core.georeferencing.attitude import headings_from_quaternions
from lidarcal_ros.io.bag.format import ODOMETRY, POSE_STAMPED


@pytest.fixture()
def publisher_node(ros_context: Any) -> Iterator[Any]:
    """A node of another DDS participant (as a driver or a replay in a process of its own:
    one participant cannot hold one topic with two types)."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context, domain_id=ros_context.get_domain_id())
    node = rclpy.create_node("trajectory_input_source", context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        context.try_shutdown()


def _spin_until(executor: Any, cond: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        executor.spin_once(timeout_sec=0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _pose(k: int) -> Any:
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = "map"
    msg.header.stamp.sec = 1000 + k
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = 1.0, 60.0 * k, 1000.0
    return msg


def _odometry(k: int) -> Any:
    from nav_msgs.msg import Odometry

    msg = Odometry()
    msg.header.frame_id = "map"
    msg.header.stamp.sec = 2000 + k
    msg.pose.pose.position.x, msg.pose.pose.position.y = 2.0, -5.0 * k
    msg.pose.pose.position.z = 800.0
    # Flying south (-y), crabbed 4 degrees: yaw -94 degrees (REP-103: from east, x forward).
    yaw = math.radians(-94.0)
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def test_auto_listens_before_any_publisher_and_misses_no_sample(probe: tuple[Any, Any]
                                                                 ) -> None:
    from geometry_msgs.msg import PoseStamped

    from lidarcal_ros.nodes.trajectory_input import TrajectoryInput

    node, executor = probe
    samples: list[tuple[float, tuple[float, float, float], str]] = []
    orientations: list[tuple[float, ...]] = []

    def on_sample(t: float, xyz: tuple[float, float, float], frame: str,
                  q: tuple[float, ...]) -> None:
        samples.append((t, xyz, frame))
        orientations.append(q)

    traj = TrajectoryInput(node, "/trajectory_input/poses", "auto", on_sample)
    # subscribed at once, with the contract's type, though nobody publishes yet
    assert traj.subscription is not None and traj.msgtype == POSE_STAMPED
    pub = node.create_publisher(PoseStamped, "/trajectory_input/poses", 100)
    try:
        # A stream that starts as soon as it is matched (as a replay does): every sample
        # arrives, the first included.
        _spin_until(executor, lambda: pub.get_subscription_count() >= 1, 10, "the match")
        for k in range(40):
            pub.publish(_pose(k))
        _spin_until(executor, lambda: len(samples) == 40, 10, "40 samples")
        assert samples[0] == (1000.0, (1.0, 0.0, 1000.0), "map")
        assert [t for t, _, _ in samples] == [1000.0 + k for k in range(40)]
        # the orientation as published (the identity: none, for the Trajectory)
        assert all(q == (0.0, 0.0, 0.0, 1.0) for q in orientations)
        # the publishers' type is the one subscribed: looking stops
        _spin_until(executor, lambda: traj.confirmed, 5, "the type to be confirmed")
        assert traj.msgtype == POSE_STAMPED and traj.errors == 0
    finally:
        node.destroy_publisher(pub)


def test_auto_switches_to_the_publishers_type(probe: tuple[Any, Any],
                                              publisher_node: Any) -> None:
    from nav_msgs.msg import Odometry

    from lidarcal_ros.nodes.trajectory_input import TrajectoryInput

    node, executor = probe
    samples: list[tuple[float, tuple[float, float, float], str, tuple[float, ...]]] = []
    traj = TrajectoryInput(node, "/trajectory_input/odometry", "auto",
                           lambda t, xyz, frame, q: samples.append((t, xyz, frame, q)))
    first = traj.subscription
    pub = publisher_node.create_publisher(Odometry, "/trajectory_input/odometry", 100)
    try:
        _spin_until(executor, lambda: traj.msgtype == ODOMETRY, 10, "the switch to Odometry")
        assert traj.subscription is not first and traj.confirmed
        _spin_until(executor, lambda: pub.get_subscription_count() >= 1, 10, "the match")
        for k in range(5):
            pub.publish(_odometry(k))
        _spin_until(executor, lambda: len(samples) == 5, 10, "5 samples")
        assert samples[-1][:3] == (2004.0, (2.0, -20.0, 800.0), "map")
        # the orientation as published (its heading: docs/method.md's kappa = yaw - 90 degrees)
        kappa = headings_from_quaternions(np.array(samples[-1][3]))[0]
        assert math.degrees(kappa) == pytest.approx(-184.0 + 360.0)
        assert traj.errors == 0
    finally:
        publisher_node.destroy_publisher(pub)


def test_a_given_type_is_subscribed_at_once_without_looking(probe: tuple[Any, Any]) -> None:
    from lidarcal_ros.errors import ConfigError
    from lidarcal_ros.nodes.trajectory_input import TrajectoryInput

    node, _executor = probe
    traj = TrajectoryInput(node, "/trajectory_input/given", "nav_msgs/Odometry",
                           lambda t, xyz, frame, kappa: None)
    assert traj.msgtype == ODOMETRY and traj.subscription is not None and traj.confirmed
    with pytest.raises(ConfigError, match="sensor_msgs/msg/Imu"):
        TrajectoryInput(node, "/trajectory_input/bad", "sensor_msgs/msg/Imu",
                        lambda t, xyz, frame, kappa: None)
