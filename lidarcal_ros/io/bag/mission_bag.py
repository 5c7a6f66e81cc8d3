"""A mission (strips of points, trajectory, control points) read from and written to a bag.

Coordinates in metres in the map frame (``header.frame_id``); times float seconds on the
bag's clock.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from lidarcal_ros.core.mission import (
    MAX_COORDINATE_M,
    ControlPoints,
    Mission,
    Strip,
    Trajectory,
)
from lidarcal_ros.errors import BagError, ConfigError, InputError
from lidarcal_ros.io.bag.format import POINTCLOUD2, seconds_to_ns
from lidarcal_ros.io.bag.reader import BagReader, open_bag
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.columns import (
    DEFAULT_COORDINATE_TOLERANCE_M,
    extract_xyz,
    float32_warning,
)
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array, make_point_dtype
from lidarcal_ros.io.cloud.strip_accumulator import StripAccumulator, is_nondecreasing
from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES, TrajectorySamples

logger = logging.getLogger(__name__)

#: The point fields a written strip always has (an extra field may not take their names).
_WRITTEN_CORE = frozenset({"x", "y", "z", "t", "intensity", "strip_id"})


def _present(bag: BagReader) -> str:
    return ", ".join(bag.topics) or "none"


def read_mission(
    path: str | os.PathLike[str],
    *,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    control_topic: str | None = "/lidar/control_points",
    time_field: str = "t",
    thinning_cell_m: float = 0.0,
    box: tuple[float, float, float, float] | None = None,
    coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M,
) -> Mission:
    """Read a mission bag into memory.

    Parameters
    ----------
    path : path-like
        rosbag2 directory or bare ``.mcap`` file.
    points_topic : str, keyword-only
        ``sensor_msgs/PointCloud2`` chunks with ``x, y, z`` (map frame, m), a FLOAT64 time
        field (absolute s) and ``strip_id``/``point_source_id``.
    trajectory_topic : str, keyword-only
        ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry`` (also
        ``PoseWithCovarianceStamped``, ``PointStamped``): IMU origin in the map frame.
    control_topic : str or None, keyword-only
        ``PointCloud2`` with ``x, y, z`` control points; the last message is used. Ignored
        when absent from the bag or None.
    time_field : str, keyword-only
        Time field of the clouds (see :func:`~lidarcal_ros.io.cloud.columns.extract_columns`).
    thinning_cell_m : float, keyword-only
        Keep only the first point of each square cell of this size (m) per strip in each
        cloud (:mod:`lidarcal_ros.core.calibration.thinning`; counted in ``thinned_points``); 0
        keeps every point.
    box : (xmin, ymin, xmax, ymax), keyword-only, optional
        Keep only the points inside this box of the map frame (m): a part of a mission
        read without holding the rest.
    coordinate_tolerance_m : float, keyword-only
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (m; the range noise):
        coarser is refused, a step above a tenth of it is warned about
        (:func:`~lidarcal_ros.io.cloud.columns.extract_columns`).

    Returns
    -------
    Mission
        Strips sorted by ``strip_id``, points within a strip sorted by time; fields other
        than x, y, z, time, intensity and strip id go to ``Strip.extra`` in their own dtype
        (a strip keeps a field only if all its points have it). Points with a non-finite
        x, y, z or t are dropped and counted in ``dropped_non_finite``.

    Raises
    ------
    BagError
        Bag unreadable, a required topic missing or of the wrong type.
    CloudFormatError
        A cloud lacks a required field.
    InputError
        Clouds and trajectory are in different frames.
    """
    with open_bag(path) as bag:
        for topic in (points_topic, trajectory_topic):
            if topic not in bag.topics:
                raise BagError(
                    f"{bag.path}: topic {topic} not found; topics present: {_present(bag)}"
                )
        expect_topic_type(bag, points_topic, (POINTCLOUD2,))
        expect_topic_type(bag, trajectory_topic, tuple(TRAJECTORY_TYPES))
        use_control = control_topic is not None and control_topic in bag.topics
        if use_control:
            assert control_topic is not None
            expect_topic_type(bag, control_topic, (POINTCLOUD2,))
        wanted = [points_topic, trajectory_topic] + ([control_topic] if use_control else [])

        acc = StripAccumulator(points_topic, time_field, thinning_cell_m, box,
                                coordinate_tolerance_m)
        samples = TrajectorySamples()
        decode_pose = functools.partial(bag.deserialize, topic=trajectory_topic)
        control_msg: Any = None
        for topic, msgtype, _log_ns, raw in bag.messages([t for t in wanted if t]):
            is_pose = topic == trajectory_topic
            ok_type = msgtype in TRAJECTORY_TYPES if is_pose else msgtype == POINTCLOUD2
            if not ok_type:
                raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
            if is_pose:
                samples.add_raw(msgtype, raw, decode_pose)
                continue
            msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
            if topic == points_topic:
                acc.add(msg)
            else:
                control_msg = msg
        if not acc.n_messages:
            raise BagError(f"{bag.path}: topic {points_topic} has no messages")
        if not samples:
            raise BagError(f"{bag.path}: topic {trajectory_topic} has no messages")
        frame = _check_frames(bag.path, points_topic, acc.frames, trajectory_topic,
                              samples.frames)
        control = None
        if control_msg is not None:
            assert control_topic is not None
            control = _control_from_cloud(bag.path, control_topic, control_msg, frame,
                                          coordinate_tolerance_m)
        strips, dropped = acc.strips()
        if not strips and not acc.outside_box:  # (a box may hold nothing: its reader says)
            raise InputError(
                f"{bag.path}: all {dropped} points on {points_topic} have a non-finite x, y, z "
                "or t" if dropped else
                f"{bag.path}: all {acc.n_messages} clouds on {points_topic} are empty")
        trajectory = samples.trajectory(f"{bag.path}: trajectory {trajectory_topic}")
    note = float32_warning(acc.coordinate_step_m, coordinate_tolerance_m)
    if note:
        logger.warning("%s: %s: %s", path, points_topic, note)
    if dropped:
        logger.warning("%s: dropped %d points with non-finite x, y, z or t (or a coordinate "
                       "beyond %g m)", path, dropped, MAX_COORDINATE_M)
    return Mission(trajectory, strips, control, frame, dropped, acc.thinned)


def expect_topic_type(bag: BagReader, topic: str, types: Sequence[str]) -> None:
    """Refuse (BagError, one line) a ``topic`` of the bag whose type is not one of
    ``types``."""
    got = bag.topics[topic].msgtype
    if got not in types:
        raise BagError(
            f"{bag.path}: topic {topic} has type {got}; expected {' or '.join(types)}"
        )


def _check_frames(
    path: Path, points_topic: str, cloud_frames: set[str], traj_topic: str, traj_frames: set[str]
) -> str:
    if len(cloud_frames) > 1:
        raise InputError(
            f"{path}: clouds on {points_topic} are in several frames: {sorted(cloud_frames)}"
        )
    if len(traj_frames) > 1:
        raise InputError(
            f"{path}: poses on {traj_topic} are in several frames: {sorted(traj_frames)}"
        )
    cloud_frame = next(iter(cloud_frames))
    traj_frame = next(iter(traj_frames))
    if cloud_frame != traj_frame:
        raise InputError(
            f"{path}: clouds on {points_topic} are in frame '{cloud_frame}' but the "
            f"trajectory on {traj_topic} is in frame '{traj_frame}'"
        )
    return cloud_frame


def _control_from_cloud(path: Path, topic: str, msg: Any, frame: str,
                        coordinate_tolerance_m: float) -> ControlPoints | None:
    if msg.header.frame_id != frame:
        raise InputError(
            f"{path}: control points on {topic} are in frame '{msg.header.frame_id}' but "
            f"the clouds are in '{frame}'"
        )
    xyz = extract_xyz(cloud_to_array(msg, source=topic), source=topic,
                      coordinate_tolerance_m=coordinate_tolerance_m)
    ok = np.isfinite(xyz).all(axis=1)
    if not ok.all():
        logger.warning("%s: dropped %d non-finite control points", topic, int((~ok).sum()))
        xyz = xyz[ok]
    if not len(xyz):
        logger.warning("%s: control point cloud is empty", topic)
        return None
    return ControlPoints([f"C{i + 1}" for i in range(len(xyz))], xyz)


def strip_point_array(
    strip: Strip, floats: dict[str, np.ndarray], where: str
) -> np.ndarray:
    """The strip as one structured array of the lidarcal output layout.

    Parameters
    ----------
    strip : Strip
    floats : dict of str to (n,) array
        Further FLOAT32 fields of the strip's points.
    where : str
        Named in error lines (file and strip).

    Returns
    -------
    numpy.ndarray
        ``x, y, z, t`` FLOAT64 (map frame, m; s), ``intensity`` FLOAT32 (if the strip has
        it), ``strip_id`` UINT16, then ``floats`` and the strip's extra fields in their own
        dtype (:func:`~lidarcal_ros.io.cloud.pointcloud.make_point_dtype`), in the strip's order.

    Raises
    ------
    InputError
        A column of the wrong shape, a strip id beyond UINT16, an extra field that is not
        numbers or clashes with another field.
    """
    n = len(strip)
    if strip.xyz.shape != (n, 3):
        raise InputError(f"{where}: xyz has shape {strip.xyz.shape}, expected ({n}, 3)")
    if not 0 <= strip.strip_id <= np.iinfo(np.uint16).max:
        raise InputError(f"{where}: strip_id {strip.strip_id} does not fit UINT16")
    base = make_point_dtype(tuple(floats), intensity=strip.intensity is not None)
    spec: list[tuple[Any, ...]] = [(name, base.fields[name][0]) for name in base.names or ()]  # type: ignore[index]
    natives: dict[str, np.ndarray] = {}
    for name, values in strip.extra.items():
        if name in _WRITTEN_CORE or name in floats:
            raise InputError(f"{where}: extra field '{name}' clashes with another field")
        arr = np.asarray(values)
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        if arr.shape[:1] != (n,) or arr.ndim > 2 or arr.dtype.kind not in "iuf":
            raise InputError(
                f"{where}: extra field '{name}' has shape {arr.shape} and dtype {arr.dtype}; "
                f"expected ({n},) or ({n}, k) numbers"
            )
        natives[name] = arr
        spec.append((name, arr.dtype.newbyteorder("<"), arr.shape[1:]))
    dtype = np.dtype(spec, align=True) if natives else base
    out = np.zeros(n, dtype=dtype)  # zeroed padding: the same points, the same bytes
    out["x"], out["y"], out["z"] = strip.xyz[:, 0], strip.xyz[:, 1], strip.xyz[:, 2]
    out["t"] = strip.t
    if strip.intensity is not None:
        out["intensity"] = strip.intensity
    out["strip_id"] = strip.strip_id
    for name, values in {**floats, **natives}.items():
        if np.shape(values)[:1] != (n,):
            raise InputError(f"{where}: extra field '{name}' has {len(values)} values, not {n}")
        out[name] = values
    return out


def time_chunk_bounds(t: np.ndarray, chunk_seconds: float) -> list[int]:
    """Boundaries of consecutive ``chunk_seconds`` windows over sorted times (NaN last)."""
    n_finite = int(np.count_nonzero(np.isfinite(t)))
    if n_finite == 0:
        return [0, int(t.size)]
    tf = t[:n_finite]
    edges = tf[0] + chunk_seconds * np.arange(1, np.floor((tf[-1] - tf[0]) / chunk_seconds) + 1)
    cuts = np.unique(np.searchsorted(tf, edges, side="left"))
    cuts = cuts[(cuts > 0) & (cuts < n_finite)]
    return [0, *cuts.tolist(), int(t.size)]


def write_mission_bag(
    path: str | os.PathLike[str],
    mission: Mission,
    *,
    chunk_seconds: float = 0.1,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    control_topic: str = "/lidar/control_points",
    overwrite: bool = False,
    extra_point_fields: dict[str, list[np.ndarray]] | None = None,
) -> Path:
    """Write a mission as a bag of the lidarcal contract.

    Parameters
    ----------
    path : path-like
        Output rosbag2 directory (or bare ``.mcap`` file).
    mission : Mission
    chunk_seconds : float, keyword-only
        Duration of scanning per PointCloud2 chunk, seconds.
    points_topic, trajectory_topic, control_topic : str, keyword-only
    overwrite : bool, keyword-only
        Replace an existing output.
    extra_point_fields : dict of str to list of arrays, keyword-only
        Further FLOAT32 point fields, one array per strip (in ``mission.strips`` order).
        ``Strip.extra`` arrays are written too, in their own dtype.

    Returns
    -------
    pathlib.Path
        The written bag.

    Notes
    -----
    Each strip becomes time-ordered chunks with fields ``x, y, z, t`` FLOAT64,
    ``intensity`` FLOAT32 (if present), ``strip_id`` UINT16 and the extras, stamped with the
    chunk's first point time, in ``mission.frame_id``. The trajectory is written as
    PoseStamped, with its orientation where it has one, else the identity; the
    control points as one transient-local
    PointCloud2 (x, y, z) at the start. All messages are in log-time order.
    """
    if not chunk_seconds > 0:
        raise ConfigError(f"chunk_seconds must be positive, got {chunk_seconds}")
    extras = extra_point_fields or {}
    for name, per_strip in extras.items():
        if len(per_strip) != len(mission.strips):
            raise InputError(
                f"{path}: extra field '{name}' has {len(per_strip)} arrays for "
                f"{len(mission.strips)} strips"
            )
    frame = mission.frame_id
    # (stamp_ns, kind: 0 pose / 1 cloud, index) events, sorted once.
    events: list[tuple[int, int, int]] = []
    clouds: list[np.ndarray] = []
    for k, strip in enumerate(mission.strips):
        where = f"{path}: strip {strip.strip_id}"
        t = np.asarray(strip.t, dtype=np.float64)
        sorted_ = bool(np.isfinite(t).all()) and is_nondecreasing(t)
        order = None if sorted_ else np.argsort(t, kind="stable")  # NaN times go last
        floats = {name: np.asarray(v[k], dtype=np.float32) for name, v in extras.items()}
        points = strip_point_array(strip, floats, where)
        if order is not None:
            points = points[order]
        if len(points) and not np.isfinite(points["t"][0]):
            raise InputError(f"{where}: no finite point time")
        if len(points) and points["t"][0] < 0:
            raise InputError(f"{where}: negative point time {points['t'][0]}")
        bounds = time_chunk_bounds(points["t"], chunk_seconds)
        for a, b in itertools.pairwise(bounds):
            if b > a:
                clouds.append(points[a:b])
                events.append((seconds_to_ns(points["t"][a]), 1, len(clouds) - 1))
    traj = mission.trajectory
    for i in range(len(traj)):
        if not traj.t[i] >= 0:
            raise InputError(f"{path}: trajectory time {traj.t[i]} is negative or not finite")
        events.append((seconds_to_ns(traj.t[i]), 0, i))
    events.sort()
    start_ns = events[0][0] if events else 0

    latched = [control_topic] if mission.control is not None else []
    with BagWriter(path, overwrite=overwrite, latched_topics=latched) as writer:
        _write_control(writer, control_topic, start_ns, frame, mission.control)
        for stamp, kind, key in events:
            if kind == 1:
                writer.write_cloud(points_topic, stamp, frame, clouds[key])
            else:
                writer.write_trajectory_pose(trajectory_topic, stamp, frame, traj, key)
    logger.info(
        "%s: wrote %d strips (%d chunks), %d poses", path, len(mission.strips),
        len(clouds), len(traj),
    )
    return Path(path)


def _write_control(writer: BagWriter, topic: str, stamp_ns: int, frame: str,
                   control: ControlPoints | None) -> None:
    """The control points as one PointCloud2 (x, y, z FLOAT64), if there are any."""
    if control is None or not len(control):
        return
    xyz = np.asarray(control.xyz, dtype=np.float64).reshape(-1, 3)
    cp = np.empty(len(xyz), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    cp["x"], cp["y"], cp["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    writer.write_cloud(topic, stamp_ns, frame, cp)


class StreamedStrip(Protocol):
    """A strip given a block of points at a time (``write_mission_stream``): its id, the
    trajectory samples flown with it (map frame), the times of its first and last points (s)
    and ``blocks()``: ``(t, xyz, intensity)`` in time order (s; map frame, m)."""

    strip_id: int
    trajectory: Trajectory
    t_first: float
    t_last: float

    def blocks(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The strip's points, a block at a time."""
        ...


def write_mission_stream(
    path: str | os.PathLike[str],
    strips: Iterable[StreamedStrip],
    *,
    control: ControlPoints | None = None,
    frame_id: str = "map",
    chunk_seconds: float = 0.1,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    control_topic: str = "/lidar/control_points",
    overwrite: bool = False,
) -> tuple[Path, int]:
    """Write a mission given strip by strip and block by block as :func:`write_mission_bag`
    writes it whole (the same messages in the same order, for strips flown one after the other),
    holding one block and one chunk of points at a time.

    Parameters
    ----------
    strips : iterable of StreamedStrip
        In time order: a strip's points and samples all after the previous strip's; within
        a strip, finite non-decreasing point times.
    control, frame_id, chunk_seconds, points_topic, trajectory_topic, control_topic, overwrite
        As :func:`write_mission_bag` (``control`` and ``frame_id`` its mission's).

    Returns
    -------
    (pathlib.Path, int)
        The written bag and the number of points in it.

    Raises
    ------
    InputError
        Strips out of time order, point times not finite and non-decreasing, or a negative
        time.
    """
    if not chunk_seconds > 0:
        raise ConfigError(f"chunk_seconds must be positive, got {chunk_seconds}")
    latched = [control_topic] if control is not None else []
    n_points = n_chunks = n_poses = 0
    last_ns = -1
    with BagWriter(path, overwrite=overwrite, latched_topics=latched) as writer:
        for strip in strips:
            out = _StripOut(writer, strip, f"{path}: strip {strip.strip_id}", frame_id,
                            points_topic, trajectory_topic)
            if out.first_ns < last_ns:
                raise InputError(f"{out.where}: begins before the previous strip ends")
            if last_ns < 0:
                _write_control(writer, control_topic, out.first_ns, frame_id, control)
            last_ns = out.write(chunk_seconds)
            n_points, n_chunks, n_poses = (n_points + out.n_points, n_chunks + out.n_chunks,
                                           n_poses + out.n_poses)
    logger.info("%s: wrote %d chunks, %d poses", path, n_chunks, n_poses)
    return Path(path), n_points


class _StripOut:
    """One streamed strip into a bag: its chunks of points and its poses, in stamp order."""

    def __init__(self, writer: BagWriter, strip: StreamedStrip, where: str, frame_id: str,
                 points_topic: str, trajectory_topic: str) -> None:
        self.writer, self.strip, self.where, self.frame_id = writer, strip, where, frame_id
        self.points_topic, self.trajectory_topic = points_topic, trajectory_topic
        t = strip.trajectory.t
        if len(t) and not (np.isfinite(t).all() and t.min() >= 0):
            raise InputError(f"{where}: trajectory time {t.min()} is negative or not finite")
        if not (math.isfinite(strip.t_first) and strip.t_first >= 0):
            raise InputError(f"{where}: first point time {strip.t_first} is negative or not "
                             "finite")
        if not strip.t_last >= strip.t_first:
            raise InputError(f"{where}: point times not finite and non-decreasing (last "
                             f"{strip.t_last}, first {strip.t_first})")
        self.pose_ns = [seconds_to_ns(v) for v in t]
        self.first_ns = min([seconds_to_ns(strip.t_first), *self.pose_ns[:1]])
        self._poses = iter(sorted(range(len(t)), key=self.pose_ns.__getitem__))
        self._pending = next(self._poses, None)
        self._held: list[np.ndarray] = []
        self.n_points = self.n_chunks = self.n_poses = 0

    def write(self, chunk_seconds: float) -> int:
        """Write the strip; the stamp (ns) of its last message."""
        strip = self.strip
        # write_mission_bag's chunks: cut at t_first + k chunk_seconds (a point at an edge
        # opens the next chunk), empty ones left out
        n_edges = math.floor((strip.t_last - strip.t_first) / chunk_seconds)
        edges = strip.t_first + chunk_seconds * np.arange(1, n_edges + 1)
        held_chunk = -1
        previous = -math.inf
        for t, xyz, intensity in strip.blocks():
            if not len(t):
                continue
            if not (np.isfinite(t).all() and t[0] >= previous and is_nondecreasing(t)):
                raise InputError(f"{self.where}: point times not finite and non-decreasing")
            previous = float(t[-1])
            block = Strip(strip_id=strip.strip_id, xyz=xyz, t=t, intensity=intensity)
            points = strip_point_array(block, {}, self.where)
            chunk = np.searchsorted(edges, t, side="right")
            cuts = np.flatnonzero(np.diff(chunk)) + 1
            for a, b in itertools.pairwise([0, *cuts.tolist(), len(t)]):
                if chunk[a] != held_chunk and self._held:
                    self._write_chunk()
                self._held.append(points[a:b])
                held_chunk = int(chunk[a])
            self.n_points += len(t)
        if self._held:
            self._write_chunk()
        self._write_poses_until(None)
        return max([seconds_to_ns(previous) if previous > -math.inf else self.first_ns,
                    *self.pose_ns[-1:]])

    def _write_chunk(self) -> None:
        points = self._held[0]
        if len(self._held) > 1:  # copied field by field into zeros: padding as in one piece
            points = np.zeros(sum(map(len, self._held)), dtype=points.dtype)
            points[:] = np.concatenate(self._held)
        stamp = seconds_to_ns(points["t"][0])
        self._write_poses_until(stamp)  # a pose before a cloud of the same stamp
        self.writer.write_cloud(self.points_topic, stamp, self.frame_id, points)
        self._held.clear()
        self.n_chunks += 1

    def _write_poses_until(self, stamp_ns: int | None) -> None:
        while self._pending is not None and (stamp_ns is None
                                             or self.pose_ns[self._pending] <= stamp_ns):
            self.writer.write_trajectory_pose(self.trajectory_topic, self.pose_ns[self._pending],
                                              self.frame_id, self.strip.trajectory,
                                              self._pending)
            self._pending = next(self._poses, None)
            self.n_poses += 1


__all__ = ["StreamedStrip", "expect_topic_type", "read_mission", "strip_point_array",
           "time_chunk_bounds", "write_mission_bag", "write_mission_stream"]
