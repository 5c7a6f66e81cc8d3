"""Bags of clouds in the sensor's frame, as ROS lidar drivers and an INS record them.

The clouds (``header.frame_id`` the sensor's, a driver's per-point time), the trajectory of
``base_link`` with its orientation (Odometry or PoseStamped) and the nominal mounting
``base_link -> sensor`` from ``/tf_static`` (docs/interface.md, docs/method.md section 12).
Points metres in the sensor's frame, times absolute float seconds on the stamps' clock.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import IDENTITY_XYZW
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting, TimeConvention
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.uav_payload import NANOSECONDS_UINT32, SensorClouds
from lidarcal_ros.errors import BagError, ConfigError, InputError, TrajectoryError
from lidarcal_ros.io.bag.format import (
    NS_PER_SECOND,
    ODOMETRY,
    POINTCLOUD2,
    seconds_to_ns,
    stamp_seconds,
)
from lidarcal_ros.io.bag.mission_bag import expect_topic_type
from lidarcal_ros.io.bag.reader import BagReader, open_bag
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array
from lidarcal_ros.io.cloud.sensor_time import SensorCloudDecoder, TimeReading
from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES, TrajectorySamples

logger = logging.getLogger(__name__)

TF_MESSAGE = "tf2_msgs/msg/TFMessage"


@dataclass
class SensorBag:
    """A bag's clouds in the sensor's frame with what georeferencing them needs
    (:func:`read_sensor_bag`).

    Attributes
    ----------
    path : Path
    points_topic, trajectory_topic : str
    frame_id : str
        The clouds' ``header.frame_id`` (the sensor's frame).
    map_frame : str
        The trajectory's ``header.frame_id``.
    base_frame : str
        The frame whose poses the trajectory gives.
    stamps : (k,) float64
        Each cloud's ``header.stamp``, s.
    offsets : (k + 1,) int64
        Cloud ``i`` holds points ``offsets[i]:offsets[i + 1]``.
    xyz : (n, 3) float64
        The points in the sensor's frame, m.
    t : (n,) float64
        Their absolute times, s.
    intensity : (n,) float32 or None
    trajectory : Trajectory
        Poses of ``base_frame`` in ``map_frame``, with orientation.
    mounting : Mounting
        The nominal ``base_frame -> frame_id``.
    mounting_source : str
        Where it came from (``/tf_static`` or the configuration), in words.
    time : TimeReading
        How the per-point time was read.
    """

    path: Path
    points_topic: str
    trajectory_topic: str
    frame_id: str
    map_frame: str
    base_frame: str
    stamps: np.ndarray
    offsets: np.ndarray
    xyz: np.ndarray
    t: np.ndarray
    intensity: np.ndarray | None
    trajectory: Trajectory
    mounting: Mounting
    mounting_source: str
    time: TimeReading

    @property
    def n_points(self) -> int:
        """How many points the clouds hold."""
        return int(self.t.shape[0])


def _first_header_frame(bag: BagReader, topic: str) -> str | None:
    for _topic, msgtype, _log, raw in bag.messages([topic]):
        return str(bag.deserialize(memoryview(raw), msgtype, topic=topic).header.frame_id)
    return None


def sensor_frame_of(path: str | os.PathLike[str], *, points_topic: str,
                    trajectory_topic: str, map_frame: str = "map") -> str | None:
    """The clouds' frame where the bag's clouds are in another frame than its trajectory
    and than ``map_frame`` (the sensor's: docs/method.md section 12); None where they are
    in either (a mission bag of map-frame clouds, whose reader refuses frames that
    disagree) or a topic is missing or empty (the mission reader says so)."""
    with open_bag(path) as bag:
        if points_topic not in bag.topics or trajectory_topic not in bag.topics:
            return None
        if bag.topics[points_topic].msgtype != POINTCLOUD2:
            return None
        cloud = _first_header_frame(bag, points_topic)
        pose = _first_header_frame(bag, trajectory_topic)
    sensor = cloud is not None and pose is not None and cloud not in (pose, map_frame)
    return cloud if sensor else None


def _compose(first: Mounting, second: Mounting) -> Mounting:
    """``first`` then ``second``: a -> b and b -> c as a -> c."""
    return Mounting(first.rotation @ second.rotation,
                    first.translation + first.rotation @ second.translation)


def static_mounting(transforms: dict[str, tuple[str, Mounting]], base: str,
                    sensor: str) -> Mounting | None:
    """The transform ``base -> sensor`` from static transforms (``child: (parent, transform
    parent -> child)``), composed along the chain from ``sensor`` up to ``base`` (a robot
    description's ``base_link -> velodyne_base_link -> velodyne``); None where ``sensor``
    does not hang below ``base``."""
    chain: list[Mounting] = []
    frame, seen = sensor, set()
    while frame != base:
        if frame not in transforms or frame in seen:
            return None
        seen.add(frame)
        parent, transform = transforms[frame]
        chain.append(transform)
        frame = parent
    out = Mounting(np.eye(3), np.zeros(3))
    for transform in reversed(chain):
        out = _compose(out, transform)
    return out


def _add_transforms(msg: Any, transforms: dict[str, tuple[str, Mounting]], source: str) -> None:
    for tf in msg.transforms:
        tr, q = tf.transform.translation, tf.transform.rotation
        try:
            mounting = Mounting.from_quaternion([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w])
        except ConfigError as exc:
            raise BagError(f"{source}: {tf.header.frame_id} -> {tf.child_frame_id}: "
                           f"{exc}") from None
        transforms[str(tf.child_frame_id)] = (str(tf.header.frame_id), mounting)


def read_sensor_bag(
    path: str | os.PathLike[str],
    *,
    points_topic: str,
    trajectory_topic: str,
    tf_topic: str = "/tf_static",
    base_frame: str = "base_link",
    time_field: str | None = None,
    time_convention: TimeConvention | str = TimeConvention.AUTO,
    mounting: Mounting | None = None,
) -> SensorBag:
    """Read a bag of clouds in the sensor's frame (module docstring).

    Parameters
    ----------
    path : path-like
    points_topic, trajectory_topic, tf_topic : str, keyword-only
    base_frame : str, keyword-only
        The trajectory's body frame; an Odometry's ``child_frame_id`` where it has one.
    time_field : str or None, keyword-only
        The per-point time field (None: the first of ``time, t, timestamp, offset_time``).
    time_convention : TimeConvention, keyword-only
        Relative, absolute, or auto: decided on the first cloud, said in one log line.
    mounting : Mounting or None, keyword-only
        The nominal mounting ``base_frame -> sensor`` of the configuration: used instead of
        ``tf_topic``'s.

    Raises
    ------
    BagError
        A topic missing, empty or of the wrong type; no mounting anywhere.
    CloudFormatError
        No usable time field or coordinates.
    InputError
        Clouds in several frames.
    TrajectoryError
        Poses with no orientation.
    """
    with open_bag(path) as bag:
        where = str(bag.path)
        for topic in (points_topic, trajectory_topic):
            if topic not in bag.topics:
                raise BagError(f"{where}: topic {topic} not found; topics present: "
                               f"{', '.join(bag.topics) or 'none'}")
        expect_topic_type(bag, points_topic, (POINTCLOUD2,))
        expect_topic_type(bag, trajectory_topic, tuple(TRAJECTORY_TYPES))
        use_tf = tf_topic in bag.topics and bag.topics[tf_topic].msgtype == TF_MESSAGE
        samples = TrajectorySamples()
        transforms: dict[str, tuple[str, Mounting]] = {}
        frames: set[str] = set()
        stamps: list[float] = []
        xyz_parts: list[np.ndarray] = []
        t_parts: list[np.ndarray] = []
        intensity_parts: list[np.ndarray] | None = []
        decoder = SensorCloudDecoder(field=time_field, convention=time_convention)
        child_frame = ""
        decode_pose = functools.partial(bag.deserialize, topic=trajectory_topic)
        topics = [points_topic, trajectory_topic] + ([tf_topic] if use_tf else [])
        for topic, msgtype, _log, raw in bag.messages(topics):
            if topic == trajectory_topic:
                if msgtype == ODOMETRY and not child_frame:
                    msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
                    child_frame = str(msg.child_frame_id)
                    samples.add(msgtype, msg)
                else:
                    samples.add_raw(msgtype, raw, decode_pose)
                continue
            msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
            if topic == tf_topic:
                _add_transforms(msg, transforms, f"{where}: {tf_topic}")
                continue
            source = f"{where}: {points_topic}"
            points = cloud_to_array(msg, source=source)
            frames.add(str(msg.header.frame_id))
            stamp = stamp_seconds(msg.header.stamp)
            xyz, t, intensity = decoder.decode(points, stamp, source=source)
            stamps.append(stamp)
            xyz_parts.append(xyz)
            t_parts.append(t)
            if intensity_parts is not None:
                if intensity is not None:
                    intensity_parts.append(intensity)
                else:
                    intensity_parts = None
        if not stamps:
            raise BagError(f"{where}: topic {points_topic} has no messages")
        if not samples:
            raise BagError(f"{where}: topic {trajectory_topic} has no messages")
        reading = decoder.reading
        if reading is None:
            raise InputError(f"{where}: all {len(stamps)} clouds on {points_topic} are empty")
        if len(frames) > 1:
            raise InputError(f"{where}: clouds on {points_topic} are in several frames: "
                             f"{sorted(frames)}")
        if len(samples.frames) > 1:
            raise InputError(f"{where}: poses on {trajectory_topic} are in several frames: "
                             f"{sorted(samples.frames)}")
        trajectory = samples.trajectory(f"{where}: trajectory {trajectory_topic}")
    frame_id = next(iter(frames))
    base = child_frame or base_frame
    if trajectory.orientation is None:
        raise TrajectoryError(
            f"{where}: trajectory {trajectory_topic} carries no orientation (identity or zero "
            f"quaternions throughout); clouds in the sensor's frame '{frame_id}' need the "
            f"attitude of {base}")
    if mounting is not None:
        source_words = "the configuration (sensor_frame.mounting)"
    else:
        found = static_mounting(transforms, base, frame_id)
        if found is None:
            have = ", ".join(f"{p} -> {c}" for c, (p, _) in sorted(transforms.items()))
            raise BagError(
                f"{where}: no mounting {base} -> {frame_id}: "
                + (f"{tf_topic} holds {have or 'no transform'}" if use_tf
                   else f"no {tf_topic} in the bag")
                + " and sensor_frame.mounting is not set")
        mounting, source_words = found, tf_topic
    # said once the bag is accepted (a refusal stays one line)
    logger.warning("%s: %s: %s", where, points_topic, reading.describe())
    counts = [len(p) for p in t_parts]
    return SensorBag(
        path=Path(path), points_topic=points_topic, trajectory_topic=trajectory_topic,
        frame_id=frame_id, map_frame=next(iter(samples.frames)), base_frame=base,
        stamps=np.asarray(stamps), offsets=np.concatenate([[0], np.cumsum(counts)]).astype(
            np.int64),
        xyz=np.concatenate(xyz_parts), t=np.concatenate(t_parts),
        intensity=None if intensity_parts is None else np.concatenate(intensity_parts),
        trajectory=trajectory, mounting=mounting, mounting_source=source_words, time=reading)


# ------------------------------------------------------------------ writing


class SensorTimeFormat(StrEnum):
    """The per-point time a written bag carries: the layout's driver field (``driver``:
    Velodyne ``time`` FLOAT32 s, Ouster ``t`` UINT32 ns, after the stamp), or Hesai's and
    Livox's ``timestamp`` FLOAT64 s, absolute or after the stamp."""

    DRIVER = "driver"
    TIMESTAMP_ABSOLUTE = "timestamp-absolute"
    TIMESTAMP_RELATIVE = "timestamp-relative"


def _cloud_points(clouds: SensorClouds, i: int, time_format: SensorTimeFormat) -> np.ndarray:
    """Cloud ``i`` as its driver lays it out: ``x, y, z, intensity`` FLOAT32, the time
    field, ``ring`` UINT16."""
    part = clouds.cloud(i)
    if time_format == SensorTimeFormat.DRIVER:
        name = clouds.time_field
        kind = "<u4" if clouds.time_units == NANOSECONDS_UINT32 else "<f4"
    else:
        name, kind = "timestamp", "<f8"
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                      (name, kind), ("ring", "<u2")])
    out = np.zeros(part.stop - part.start, dtype=dtype)
    xyz = clouds.xyz[part]
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    # an intensity falling with range, as a return's does (no radiometry is simulated here)
    out["intensity"] = 255.0 / (1.0 + 0.02 * np.linalg.norm(xyz, axis=1))
    out["ring"] = clouds.ring[part]
    if time_format == SensorTimeFormat.DRIVER:
        out[name] = clouds.time[part]
    else:
        scale = 1e-9 if clouds.time_units == NANOSECONDS_UINT32 else 1.0
        relative = clouds.time[part].astype(np.float64) * scale
        out[name] = relative if time_format == SensorTimeFormat.TIMESTAMP_RELATIVE \
            else relative + clouds.stamps[i]
    return out


def _odometry(writer: BagWriter, stamp_ns: int, map_frame: str, base_frame: str,
              xyz: np.ndarray, q: np.ndarray) -> Any:
    types = writer.message_classes
    sec, nsec = divmod(stamp_ns, NS_PER_SECOND)
    point, quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    vector = types["geometry_msgs/msg/Vector3"]
    return types[ODOMETRY](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
            frame_id=map_frame),
        child_frame_id=base_frame,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                orientation=quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                       w=float(q[3]))),
            covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vector(x=0.0, y=0.0, z=0.0),
                                                   angular=vector(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)))


def _tf_message(writer: BagWriter, stamp_ns: int, parent: str, child: str,
                mounting: Mounting) -> Any:
    types = writer.message_classes
    sec, nsec = divmod(stamp_ns, NS_PER_SECOND)
    tr, q = mounting.translation, mounting.quaternion
    transform = types["geometry_msgs/msg/TransformStamped"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=float(tr[0]), y=float(tr[1]),
                                                           z=float(tr[2])),
            rotation=types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]),
                                                           z=float(q[2]), w=float(q[3]))))
    return types[TF_MESSAGE](transforms=[transform])


def write_sensor_bag(
    path: str | os.PathLike[str],
    clouds: SensorClouds,
    trajectory: Trajectory,
    mounting: Mounting,
    *,
    points_topic: str = "/velodyne_points",
    trajectory_topic: str = "/ins/odometry",
    tf_topic: str = "/tf_static",
    map_frame: str = "map",
    base_frame: str = "base_link",
    time_format: SensorTimeFormat = SensorTimeFormat.DRIVER,
    overwrite: bool = False,
) -> Path:
    """Write a payload's recording as ``ros2 bag record -s mcap`` writes those topics: the
    clouds in ``clouds.frame_id``, ``nav_msgs/Odometry`` of ``base_frame`` in ``map_frame``
    at each pose (each logged at its stamp), and ``mounting`` (``base_frame ->
    clouds.frame_id``) once on ``tf_topic`` at the start, offered transient-local as
    ``robot_state_publisher`` does.

    A pose without orientation is written as the identity (as an odometry without attitude
    publishes it).

    Raises
    ------
    OutputError
        The output exists (without ``overwrite``) or cannot be written.
    """
    q = np.tile(IDENTITY_XYZW, (len(trajectory), 1)) if trajectory.orientation is None \
        else np.where(np.isnan(trajectory.orientation), IDENTITY_XYZW, trajectory.orientation)
    first = min(float(trajectory.t[0]), float(clouds.stamps[0]) if len(clouds) else np.inf)
    start_ns = seconds_to_ns(first)
    events = [(seconds_to_ns(float(s)), 1, i) for i, s in enumerate(clouds.stamps)]
    events += [(seconds_to_ns(float(t)), 0, i) for i, t in enumerate(trajectory.t)]
    events.sort()
    with BagWriter(path, overwrite=overwrite, latched_topics=[tf_topic]) as writer:
        writer.write_message(tf_topic, TF_MESSAGE, start_ns,
                             _tf_message(writer, start_ns, base_frame, clouds.frame_id,
                                         mounting))
        for log_ns, kind, i in events:
            if kind == 1:
                writer.write_cloud(points_topic, log_ns, clouds.frame_id,
                                   _cloud_points(clouds, i, time_format))
            else:
                writer.write_message(trajectory_topic, ODOMETRY, log_ns,
                                     _odometry(writer, log_ns, map_frame, base_frame,
                                               trajectory.xyz[i], q[i]))
    logger.info("%s: wrote %d clouds, %d poses", path, len(clouds), len(trajectory))
    return Path(path)


__all__ = ["TF_MESSAGE", "SensorBag", "SensorTimeFormat", "read_sensor_bag", "sensor_frame_of",
           "static_mounting", "write_sensor_bag"]
