"""``lidarcal replay``: publish a bag's messages on live topics with their original timing.

The timing (rate, loop, start, duration, ``/clock``) is :mod:`lidarcal_ros.pipeline.replay`;
this module only creates the publishers: one per topic, of the bag's message type, publishing
the CDR bytes of the bag as they are (no deserialisation). QoS follows what the bag recorded:
transient-local topics (control points) are published transient-local with the depth of their
message count (up to 100), other topics reliable (best effort if every recorded publisher was),
keep-last ``queue`` deep.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Iterable
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from lidarcal_ros.io.bag_reader import BagReader
from lidarcal_ros.nodes.serialized_publisher import SerializedPublisher
from lidarcal_ros.nodes.topics import latched_qos, stream_qos

__all__ = ["PLAYER_NODE", "PlayerNode", "message_class", "topic_qos"]

PLAYER_NODE = "lidarcal_replay"


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Type`` (None if not importable here)."""
    try:
        pkg, kind, name = msgtype.split("/")
        module = importlib.import_module(f"{pkg}.{kind}")
        return getattr(module, name)
    except (ValueError, ImportError, AttributeError):
        return None


def topic_qos(info: Any, queue: int) -> QoSProfile:
    """QoS to publish a bag topic with (module docstring)."""
    from rosbags.interfaces import QosReliability

    best_effort = bool(info.qos) and all(
        q.reliability == QosReliability.BEST_EFFORT for q in info.qos)
    if info.transient_local:
        return latched_qos(max(1, min(info.count, 100)))
    return stream_qos(queue, best_effort=best_effort)


class PlayerNode(Node):
    """Publishers for the topics of an open bag (raw CDR)."""

    def __init__(self, bag: BagReader, *, topics: Iterable[str] | None = None, queue: int = 100,
                 clock: bool = False, context: Any = None, node_name: str = PLAYER_NODE) -> None:
        super().__init__(node_name, context=context)
        wanted = set(topics) if topics is not None else None
        self.publishers_by_topic: dict[str, Any] = {}
        self._serialized: dict[str, SerializedPublisher] = {}
        self.latched: set[str] = set()
        self.skipped: dict[str, str] = {}
        for topic, info in bag.topics.items():
            if wanted is not None and topic not in wanted:
                continue
            cls = message_class(info.msgtype)
            if cls is None:
                self.skipped[topic] = f"message type {info.msgtype} not available here"
                self.get_logger().warning(f"{topic}: {self.skipped[topic]}; not replayed")
                continue
            self.publishers_by_topic[topic] = self.create_publisher(cls, topic,
                                                                    topic_qos(info, queue))
            # (a message is published from where the bag reader holds it: no bytes copy)
            self._serialized[topic] = SerializedPublisher(self.publishers_by_topic[topic])
            if info.transient_local:
                self.latched.add(topic)
        self.clock_publisher = None
        if clock:
            from rosgraph_msgs.msg import Clock

            self._clock_cls = Clock
            self.clock_publisher = self.create_publisher(
                Clock, "/clock", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    @property
    def topics(self) -> list[str]:
        return sorted(self.publishers_by_topic)

    def publish(self, topic: str, _msgtype: str, _ns: int, raw: bytes | memoryview) -> None:
        pub = self._serialized.get(topic)
        if pub is not None:
            pub.publish(raw)

    def publish_clock(self, ns: int) -> None:
        if self.clock_publisher is None:
            return
        msg = self._clock_cls()
        msg.clock.sec, msg.clock.nanosec = divmod(int(ns), 1_000_000_000)
        self.clock_publisher.publish(msg)

    def wait_for_all_acked(self, timeout_s: float) -> bool:
        """Wait until the subscribers acknowledged everything published (reliable topics)."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout_s
        ok = True
        for pub in self.publishers_by_topic.values():
            left = max(deadline - time.monotonic(), 0.0)
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        return ok

    def wait_for_subscribers(self, timeout_s: float, *, minimum: int = 1,
                             settle_s: float = 1.0, stop: Any = None) -> list[str]:
        """Wait until each non-latched topic has ``minimum`` subscribers and the counts have
        not changed for ``settle_s`` (the nodes of a suite are matched one by one: the first
        match alone would start the replay while the others' subscriptions are still being
        matched, and their first messages would be lost); returns the topics still short of
        ``minimum`` when ``timeout_s`` runs out."""
        deadline = time.monotonic() + timeout_s
        counts: dict[str, int] = {}
        steady_since = time.monotonic()
        while True:
            now = time.monotonic()
            seen = {t: p.get_subscription_count() for t, p in self.publishers_by_topic.items()
                    if t not in self.latched}
            if seen != counts:
                counts, steady_since = seen, now
            missing = [t for t, n in counts.items() if n < minimum]
            settled = not missing and now - steady_since >= settle_s
            if settled or now >= deadline or (stop is not None and stop()):
                return missing
            time.sleep(0.05)
