"""The nodes' trajectory subscription: of a given message type, or the one its publishers use."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.node import Node

from lidarcal_ros.errors import ConfigError
from lidarcal_ros.nodes.topics import stream_qos

__all__ = ["TrajectoryInput", "trajectory_message_classes"]


def trajectory_message_classes() -> dict[str, Any]:
    """Message classes of the trajectory types the nodes accept, by ``pkg/msg/Type``."""
    from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry

    return {
        "geometry_msgs/msg/PoseStamped": PoseStamped,
        "nav_msgs/msg/Odometry": Odometry,
        "geometry_msgs/msg/PoseWithCovarianceStamped": PoseWithCovarianceStamped,
        "geometry_msgs/msg/PointStamped": PointStamped,
    }


class TrajectoryInput:
    """Subscribes to the trajectory topic, of a given type or the one its publishers use.

    Calls ``on_sample(t_seconds, (x, y, z), frame_id, orientation)`` for each sample (raw CDR
    decoded with rosbags; ``orientation`` its quaternion ``(x, y, z, w)``, NaN where the type
    has none: :func:`~lidarcal_ros.io.cloud.trajectory_messages.trajectory_sample`). With
    ``msgtype`` ``auto`` the subscription is made at once for the contract's
    type (``geometry_msgs/msg/PoseStamped``), and the publishers on the topic are looked up
    every 0.5 s until one appears: if they use another accepted type, the subscription
    switches to it. Waiting for a publisher before subscribing at all would lose the first
    samples of every stream that starts after the node (up to a second of them, and at a
    replay's 10x rate the trajectory of a whole strip).
    """

    def __init__(self, node: Node, topic: str, msgtype: str,
                 on_sample: Callable[[float, tuple[float, float, float], str,
                                      tuple[float, ...]], None],
                 *, depth: int = 10000, callback_group: Any = None,
                 on_child_frame: Callable[[str], None] | None = None) -> None:
        self.node = node
        self.topic = topic
        self.on_sample = on_sample
        #: Told the body frame the first message naming one names (an Odometry's
        #: ``child_frame_id``), once.
        self.on_child_frame = on_child_frame
        self.child_frame_id = ""
        self.depth = depth
        self.group = callback_group
        self.msgtype: str | None = None
        self.subscription: Any = None
        self.errors = 0
        self._timer: Any = None
        from lidarcal_ros.io.bag.format import POSE_STAMPED, normalize_msgtype
        from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES

        self._getters = TRAJECTORY_TYPES
        if msgtype and msgtype != "auto":
            self._subscribe(normalize_msgtype(msgtype))
            return
        self._subscribe(POSE_STAMPED, confirmed=False)
        self._timer = node.create_timer(0.5, self._discover, callback_group=callback_group)
        self._discover()

    @property
    def confirmed(self) -> bool:
        """Whether the message type is settled (given, or that of the topic's publishers): the
        subscription stays, the publishers are no longer looked up."""
        return self._timer is None

    def _discover(self) -> None:
        """Follow the type of the topic's publishers (``auto``), once they appear."""
        resolved = self.node.resolve_topic_name(self.topic)  # remappings applied
        types = sorted({info.topic_type
                        for info in self.node.get_publishers_info_by_topic(resolved)})
        if not types:
            return  # no publisher yet: keep the subscription of the contract's type
        if self.msgtype in types:
            self._subscribe(self.msgtype)  # confirmed: the subscription stays
            return
        accepted = [t for t in types if t in self._getters]
        if accepted:
            self._subscribe(accepted[0])
            return
        self.node.get_logger().error(
            f"{self.topic} has type(s) {', '.join(types)}; expected one of "
            f"{', '.join(self._getters)}", throttle_duration_sec=30.0)

    def _subscribe(self, msgtype: str, *, confirmed: bool = True) -> None:
        """Subscribe for ``msgtype`` (replacing a subscription of another type); once
        ``confirmed`` (a given type, or the publishers' own), stop looking."""
        classes = trajectory_message_classes()
        if msgtype not in classes:
            raise ConfigError(f"trajectory type {msgtype} is not one of {', '.join(classes)}")
        if confirmed and self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if msgtype == self.msgtype:
            if confirmed:
                self.node.get_logger().info(f"trajectory: {self.topic} ({msgtype})")
            return
        if self.subscription is not None:
            self.node.destroy_subscription(self.subscription)
        self.msgtype = msgtype
        # Each subscription decodes its own type (a message of the one replaced may still be
        # in a callback when the type changes).
        self.subscription = self.node.create_subscription(
            classes[msgtype], self.topic, lambda raw: self._on_raw(raw, msgtype),
            stream_qos(self.depth), raw=True, callback_group=self.group)
        if confirmed:
            self.node.get_logger().info(f"trajectory: {self.topic} ({msgtype})")

    def _on_raw(self, raw: bytes, msgtype: str) -> None:
        from lidarcal_ros.io.cloud.messages import deserialize
        from lidarcal_ros.io.cloud.trajectory_messages import trajectory_sample

        try:
            msg = deserialize(raw, msgtype)
            t, xyz, orientation = trajectory_sample(msgtype, msg)
        except Exception as exc:  # malformed message: log, skip, keep running
            self.errors += 1
            self.node.get_logger().error(f"{self.topic}: malformed {msgtype} skipped "
                                         f"({exc})", throttle_duration_sec=5.0)
            return
        child = str(getattr(msg, "child_frame_id", "") or "")
        if child and not self.child_frame_id:
            self.child_frame_id = child
            if self.on_child_frame is not None:
                self.on_child_frame(child)
        self.on_sample(t, xyz, str(msg.header.frame_id), orientation)
