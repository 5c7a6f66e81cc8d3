"""``lidarcal record`` (and ``lidarcal run --record``): write live topics to an MCAP bag.

What it subscribes to and how latched topics are kept: docs/nodes.md, "The helper nodes of the
CLI".
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lidarcal_ros.io.bag.format import normalize_msgtype
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.nodes.player import message_class

__all__ = ["DEFAULT_TOPICS", "RECORDER_NODE", "RecorderNode"]

RECORDER_NODE = "lidarcal_record"

#: What ``lidarcal record`` records by default: the outputs of the node suite.
DEFAULT_TOPICS = ("/lidar/points_corrected", "/lidar/calibration/estimate",
                  "/lidar/calibration/yaml", "/diagnostics")


class RecorderNode(Node):
    """Records ``topics`` into the bag at ``output`` (docs/nodes.md)."""

    def __init__(self, output: str | Path, topics: Sequence[str] = DEFAULT_TOPICS, *,
                 overwrite: bool = False, queue: int = 1000, context: Any = None,
                 node_name: str = RECORDER_NODE) -> None:
        super().__init__(node_name, context=context)
        self.topics = list(dict.fromkeys(topics))
        self.queue = queue
        self.writer = BagWriter(output, overwrite=overwrite, staged=False).open()
        self.counts: dict[str, int] = {t: 0 for t in self.topics}
        self._recording: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._closed = False
        self.create_timer(0.2, self._discover)
        self._discover()
        self.get_logger().info(f"recording {', '.join(self.topics)} -> {output}")

    def _discover(self) -> None:
        if len(self._recording) == len(self.topics):
            return
        graph = dict(self.get_topic_names_and_types())
        for topic in self.topics:
            if topic in self._recording or topic not in graph:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            msgtype = normalize_msgtype(graph[topic][0])
            cls = message_class(msgtype)
            if cls is None:
                self.get_logger().warning(f"{topic}: type {msgtype} not available; skipped",
                                          once=True)
                continue
            latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                          for i in infos)
            best_effort = all(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                              for i in infos)
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=1 if latched else self.queue,
                reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                             else ReliabilityPolicy.RELIABLE),
                durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                            else DurabilityPolicy.VOLATILE))
            with self._lock:
                self.writer.add_topic(topic, msgtype, latched=latched)
            self._recording[topic] = self.create_subscription(
                cls, topic, lambda raw, t=topic, m=msgtype: self._write(t, m, raw), qos,
                raw=True)

    def _write(self, topic: str, msgtype: str, raw: bytes) -> None:
        now = self.get_clock().now().nanoseconds
        with self._lock:
            if self._closed:
                return
            self.writer.write_raw(topic, msgtype, now, raw)
            self.counts[topic] += 1

    def close(self) -> None:
        """Finish the bag."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.writer.close()
        total = sum(self.counts.values())
        self.get_logger().info(f"recorded {total} messages -> {self.writer.path}")
