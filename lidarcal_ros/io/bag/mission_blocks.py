"""A mission bag read a cloud at a time, as often as asked (memory that does not grow with it).

Coordinates in metres in the map frame; times float seconds on the bag's clock. The points of
each cloud come as :class:`~lidarcal_ros.core.mission.Strip` pieces, as
:func:`~lidarcal_ros.io.bag.mission_bag.read_mission` reads them (the same columns, the same
non-finite points dropped, the same box), without the strips' extra fields.
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Iterator
from typing import Any

from lidarcal_ros.core.mission import ControlPoints, Strip, Trajectory
from lidarcal_ros.errors import BagError, ConfigError
from lidarcal_ros.io.bag.format import POINTCLOUD2
from lidarcal_ros.io.bag.mission_bag import _check_frames, _control_from_cloud, expect_topic_type
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.cloud.columns import DEFAULT_COORDINATE_TOLERANCE_M
from lidarcal_ros.io.cloud.strip_accumulator import StripAccumulator
from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES, TrajectorySamples
from lidarcal_ros.io.url_cache import source_of

logger = logging.getLogger(__name__)


class MissionBlocks:
    """A mission bag's clouds, one pass over the bag per call of :meth:`clouds`.

    The first pass also reads the trajectory and the control points (:attr:`trajectory`,
    :attr:`control`, :attr:`frame`, :attr:`dropped_non_finite`, set once it has ended).
    Parameters as :func:`~lidarcal_ros.io.bag.mission_bag.read_mission`'s; thinning is
    refused (ConfigError): a thinned mission is small enough to read whole.
    """

    def __init__(
        self, path: str | os.PathLike[str], *, points_topic: str = "/lidar/points",
        trajectory_topic: str = "/lidar/trajectory",
        control_topic: str | None = "/lidar/control_points", time_field: str = "t",
        thinning_cell_m: float = 0.0, box: tuple[float, float, float, float] | None = None,
        coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M,
    ) -> None:
        if thinning_cell_m > 0:
            raise ConfigError("calibration.memory bounded reads every point: leave "
                              "calibration.thinning_cell_m at 0 (a thinned mission is read "
                              "whole)")
        self.path = source_of(path)
        self.points_topic = points_topic
        self.trajectory_topic = trajectory_topic
        self.control_topic = control_topic
        self.time_field = time_field
        self.box = box
        self.coordinate_tolerance_m = coordinate_tolerance_m
        self.trajectory: Trajectory | None = None
        self.control: ControlPoints | None = None
        self.frame = "map"
        self.dropped_non_finite = 0
        self.n_messages = 0

    def clouds(self) -> Iterator[list[Strip]]:
        """Each cloud's points by strip id (in time order within the cloud), in the bag's
        order; one pass over the bag.

        Raises
        ------
        BagError
            Bag unreadable, a required topic missing, empty or of the wrong type.
        """
        first = self.trajectory is None
        with open_bag(self.path) as bag:
            for topic in (self.points_topic, self.trajectory_topic):
                if topic not in bag.topics:
                    raise BagError(f"{bag.path}: topic {topic} not found; topics present: "
                                   f"{', '.join(bag.topics) or 'none'}")
            expect_topic_type(bag, self.points_topic, (POINTCLOUD2,))
            expect_topic_type(bag, self.trajectory_topic, tuple(TRAJECTORY_TYPES))
            control_topic = self.control_topic if self.control_topic in bag.topics else None
            wanted = [self.points_topic]
            if first:
                wanted += [self.trajectory_topic] + ([control_topic] if control_topic else [])
            samples = TrajectorySamples()
            decode_pose = functools.partial(bag.deserialize, topic=self.trajectory_topic)
            frames: set[str] = set()
            control_msg: Any = None
            n_messages = dropped = 0
            for topic, msgtype, _log_ns, raw in bag.messages(wanted):
                if topic == self.trajectory_topic:
                    if msgtype not in TRAJECTORY_TYPES:
                        raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
                    samples.add_raw(msgtype, raw, decode_pose)
                    continue
                if msgtype != POINTCLOUD2:
                    raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
                msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
                if topic != self.points_topic:
                    control_msg = msg
                    continue
                n_messages += 1
                acc = StripAccumulator(self.points_topic, self.time_field, 0.0, self.box,
                                       self.coordinate_tolerance_m)
                acc.add(msg)
                frames |= acc.frames
                strips, n_dropped = acc.strips()
                dropped += n_dropped
                yield [Strip(s.strip_id, s.xyz, s.t) for s in strips]
            if not n_messages:
                raise BagError(f"{bag.path}: topic {self.points_topic} has no messages")
            if first:
                if not samples:
                    raise BagError(f"{bag.path}: topic {self.trajectory_topic} has no messages")
                self.frame = _check_frames(bag.path, self.points_topic, frames,
                                           self.trajectory_topic, samples.frames)
                if control_msg is not None:
                    self.control = _control_from_cloud(bag.path, str(control_topic),
                                                       control_msg, self.frame,
                                                       self.coordinate_tolerance_m)
                self.trajectory = samples.trajectory(
                    f"{bag.path}: trajectory {self.trajectory_topic}")
                self.dropped_non_finite, self.n_messages = dropped, n_messages
                if dropped:
                    logger.warning("%s: dropped %d points with non-finite x, y, z or t",
                                   self.path, dropped)


__all__ = ["MissionBlocks"]
