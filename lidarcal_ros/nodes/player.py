"""``lidarcal replay``: publish a bag's messages on live topics with their original timing.

The timing is :mod:`lidarcal_ros.pipeline.replay`'s; this module makes the publishers, one per
topic with the bag's type and QoS, and waits for the subscribers (docs/nodes.md, "The helper
nodes of the CLI").
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable, Iterable
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from lidarcal_ros.core.config import SCHEMA
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.bag.reader import BagReader
from lidarcal_ros.nodes.serialized_publisher import SerializedPublisher
from lidarcal_ros.nodes.suite import SUITE_TOPIC, read_suite_state
from lidarcal_ros.nodes.topics import latched_qos, stream_qos
from lidarcal_ros.pipeline.replay import SubscriberWait, wait_for_subscribers

__all__ = ["PLAYER_NODE", "PUBLISH_STALL_S", "SUITE_INPUTS", "PlayerNode", "message_class",
           "publish_patiently", "topic_qos"]

PLAYER_NODE = "lidarcal_replay"
#: How long a message may wait for a slow subscriber before the replay fails, s.
PUBLISH_STALL_S = 30.0
#: The streams the suite's nodes subscribe to (their default topics).
SUITE_INPUTS = (SCHEMA["topics.points"].default, SCHEMA["topics.trajectory"].default)


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Type`` (None if not importable here)."""
    try:
        pkg, kind, name = msgtype.split("/")
        module = importlib.import_module(f"{pkg}.{kind}")
        return getattr(module, name)
    except (ValueError, ImportError, AttributeError):
        return None


#: Seconds of a topic's messages, at the replay's pace, its publisher keeps for a subscriber
#: that falls behind (the default ``--queue``): a 100 Hz Odometry at ``--rate 10`` keeps
#: 2000, a 10 Hz cloud 200 (1 MB each: 200 MB at most, and only while a reader lags).
QUEUE_SECONDS = 2.0
#: The depth of every topic at least, and of every topic at most (the default ``--queue``).
MIN_QUEUE, MAX_QUEUE = 100, 10_000


def topic_depth(info: Any, *, span_s: float, rate: float) -> int:
    """The keep-last depth of a topic of ``info.count`` messages over ``span_s`` s of bag
    time replayed at ``rate`` times real time: :data:`QUEUE_SECONDS` of its messages, within
    :data:`MIN_QUEUE` and :data:`MAX_QUEUE`."""
    per_s = info.count / span_s if span_s > 0 else 0.0
    return int(min(MAX_QUEUE, max(MIN_QUEUE, math.ceil(per_s * rate * QUEUE_SECONDS))))


def topic_qos(info: Any, queue: int) -> QoSProfile:
    """QoS to publish a bag topic with (docs/nodes.md)."""
    from rosbags.interfaces import QosReliability

    best_effort = bool(info.qos) and all(
        q.reliability == QosReliability.BEST_EFFORT for q in info.qos)
    if info.transient_local:
        return latched_qos(max(1, min(info.count, 100)))
    return stream_qos(queue, best_effort=best_effort)


def publish_patiently(publish: Callable[[], None], *, stall_s: float) -> bool:
    """Call ``publish`` until it succeeds, for up to ``stall_s`` seconds; return whether it
    had to wait. A reliable writer whose history is full waits Fast DDS's max_blocking_time
    (100 ms) for the slowest reader to acknowledge, then fails: back-pressure from a busy
    subscriber, not a broken topic.

    Raises
    ------
    LidarcalError
        Still refused after ``stall_s`` (the last refusal).
    """
    deadline = None
    while True:
        try:
            publish()
            return deadline is not None
        except LidarcalError:
            now = time.monotonic()
            if deadline is None:
                deadline = now + stall_s
            elif now >= deadline:
                raise
            time.sleep(0.01)


class PlayerNode(Node):
    """Publishers for the topics of an open bag (raw CDR)."""

    def __init__(self, bag: BagReader, *, topics: Iterable[str] | None = None,
                 queue: int | None = None, rate: float = 1.0, clock: bool = False,
                 context: Any = None, node_name: str = PLAYER_NODE) -> None:
        super().__init__(node_name, context=context)
        wanted = set(topics) if topics is not None else None
        self.publishers_by_topic: dict[str, Any] = {}
        self._serialized: dict[str, SerializedPublisher] = {}
        self.latched: set[str] = set()
        self.skipped: dict[str, str] = {}
        #: The keep-last depth of each topic's publisher (``queue``, else
        #: :func:`topic_depth` at ``rate``).
        self.depths: dict[str, int] = {}
        #: Messages that had to wait for a slow subscriber (:meth:`publish`).
        self.stalls = 0
        for topic, info in bag.topics.items():
            if wanted is not None and topic not in wanted:
                continue
            cls = message_class(info.msgtype)
            if cls is None:
                self.skipped[topic] = f"message type {info.msgtype} not available here"
                self.get_logger().warning(f"{topic}: {self.skipped[topic]}; not replayed")
                continue
            depth = queue if queue is not None else topic_depth(
                info, span_s=(bag.end_ns - bag.start_ns) * 1e-9, rate=rate)
            self.depths[topic] = depth
            self.publishers_by_topic[topic] = self.create_publisher(cls, topic,
                                                                    topic_qos(info, depth))
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
        #: The last state of a ``lidarcal run`` seen ({} : none), and whether one was seen.
        self.suite_state: dict[str, Any] = {}
        self.suite_seen = False
        self.create_subscription(String, SUITE_TOPIC, self._on_suite, latched_qos())

    def _on_suite(self, msg: Any) -> None:
        self.suite_state = read_suite_state(msg.data)

    @property
    def topics(self) -> list[str]:
        """The topics replayed (those with a publisher), sorted."""
        return sorted(self.publishers_by_topic)

    def publish(self, topic: str, _msgtype: str, _ns: int, raw: bytes | memoryview) -> None:
        """Publish the CDR bytes ``raw`` of a bag message on ``topic`` as they are (topics not
        replayed: nothing)."""
        pub = self._serialized.get(topic)
        if pub is None:
            return
        if publish_patiently(lambda: pub.publish(raw), stall_s=PUBLISH_STALL_S):
            self.stalls += 1
            if self.stalls == 1:
                self.get_logger().warning(
                    f"{topic}: a subscriber is not keeping up; the replay waited for it")

    def publish_clock(self, ns: int) -> None:
        """Publish the bag time ``ns`` (nanoseconds) on /clock, where ``clock`` was asked for."""
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

    def wait_topics(self) -> list[str]:
        """The topics to wait for subscribers on: those played (not latched: a late joiner
        gets their messages anyway) that the suite listens to (:data:`SUITE_INPUTS`), or
        every one played when none of them is (a bag of other streams): a played topic no
        node listens to does not hold the replay up to the time-out."""
        streams = [t for t in self.topics if t not in self.latched]
        return [t for t in streams if t in SUITE_INPUTS] or streams

    def suite_starting(self) -> bool:
        """Whether a ``lidarcal run`` is seen (its monitor publishes the suite's state) that
        has not said its suite is up."""
        if self.count_publishers(SUITE_TOPIC) == 0:
            return False
        self.suite_seen = True
        return self.suite_state.get("state") != "up"

    def suite_waiting_for(self) -> str:
        """The nodes of a ``lidarcal run`` seen that are not up yet, as text."""
        state = self.suite_state
        missing = [n for n in state.get("nodes", []) if n not in state.get("up", [])]
        return ", ".join(missing) or "no state received"

    def wait_for_subscribers(self, timeout_s: float, *, minimum: int = 1,
                             topics: Iterable[str] | None = None, settle_s: float = 1.0,
                             stop: Callable[[], bool] = lambda: False) -> SubscriberWait:
        """Wait (spinning this node) until each of ``topics`` (default
        :meth:`wait_topics`) has ``minimum`` subscribers, the counts have not changed for
        ``settle_s`` and no ``lidarcal run`` seen is still starting
        (:func:`lidarcal_ros.pipeline.replay.wait_for_subscribers`), at most ``timeout_s``
        seconds; ``stop()`` ends the wait early."""
        from rclpy.executors import SingleThreadedExecutor

        waited = list(self.wait_topics() if topics is None else topics)
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(self)

        def pause(seconds: float) -> bool:
            executor.spin_once(timeout_sec=seconds)
            return stop()

        try:
            return wait_for_subscribers(
                lambda: {t: self.publishers_by_topic[t].get_subscription_count()
                         for t in waited},
                timeout_s=timeout_s, minimum=minimum, settle_s=settle_s,
                suite_starting=self.suite_starting, wait=pause)
        finally:
            executor.remove_node(self)
            executor.shutdown()
