"""Trajectory messages (poses, odometry, points) as samples of a mission's ``Trajectory``.

Positions metres in ``header.frame_id``, times float seconds, orientations ``(x, y, z, w)``
(NaN where the type has none); a PoseWithCovarianceStamped's position sigmas (m) from its
covariance's diagonal.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.io.bag.format import (
    ODOMETRY,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    stamp_seconds,
)

#: Trajectory message types accepted (in a bag and on a topic), with how to get the position and the
#: orientation (None: the type has none).
TRAJECTORY_TYPES: dict[str, Callable[[Any], tuple[Any, Any]]] = {
    POSE_STAMPED: lambda m: (m.pose.position, m.pose.orientation),
    ODOMETRY: lambda m: (m.pose.pose.position, m.pose.pose.orientation),
    POSE_WITH_COVARIANCE_STAMPED: lambda m: (m.pose.pose.position, m.pose.pose.orientation),
    "geometry_msgs/msg/PointStamped": lambda m: (m.point, None),
}


def trajectory_sample(msgtype: str, msg: Any
                      ) -> tuple[float, tuple[float, float, float], tuple[float, ...]]:
    """A trajectory message of one of :data:`TRAJECTORY_TYPES` as ``(t, (x, y, z), q)``:
    header stamp (s), position (m) and its orientation quaternion ``(x, y, z, w)`` (NaN
    where the type has none; the identity is kept, and read as none by
    :class:`~lidarcal_ros.core.mission.Trajectory`)."""
    pos, q = TRAJECTORY_TYPES[msgtype](msg)
    quat = _NO_ORIENTATION if q is None else (float(q.x), float(q.y), float(q.z), float(q.w))
    return (stamp_seconds(msg.header.stamp), (float(pos.x), float(pos.y), float(pos.z)),
            quat)


def position_sigma(msgtype: str, msg: Any) -> tuple[float, float, float]:
    """The position sigmas (m) along x, y, z of a trajectory message: the square roots of a
    PoseWithCovarianceStamped's covariance diagonal (the navigation solution's accuracy, as
    ``lidarcal import`` writes it from an ``smrmsg``); NaN where not above zero, and for
    every other type (an Odometry's covariance is the odometry's, often a placeholder)."""
    if msgtype != POSE_WITH_COVARIANCE_STAMPED:
        return _NO_SIGMA
    cov = msg.pose.covariance
    return tuple(math.sqrt(v) if v > 0.0 and math.isfinite(v) else math.nan  # type: ignore[return-value]
                 for v in (float(cov[0]), float(cov[7]), float(cov[14])))


_NO_ORIENTATION = (math.nan, math.nan, math.nan, math.nan)
_NO_SIGMA = (math.nan, math.nan, math.nan)
#: A PoseStamped in CDR after its encapsulation: stamp (sec, nanosec), the frame id's length;
#: then, 8-byte aligned, position and orientation.
_POSE_HEADER = struct.Struct("<iII")
_POSE_BODY = struct.Struct("<7d")


class TrajectorySamples:
    """Trajectory messages gathered into a :class:`~lidarcal_ros.core.mission.Trajectory`
    (in any order), with the frames they are in."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.xyz: list[tuple[float, float, float]] = []
        self.orientation: list[tuple[float, ...]] = []
        self.frames: set[str] = set()
        #: Position sigmas (m) of the samples, NaN where a message carries none; None while
        #: no message carried one (the rows before the first are filled in then).
        self.sigma: list[tuple[float, float, float]] | None = None

    def add(self, msgtype: str, msg: Any) -> None:
        """Add a decoded message of type ``msgtype`` (one of :data:`TRAJECTORY_TYPES`)."""
        t, xyz, q = trajectory_sample(msgtype, msg)
        sigma = position_sigma(msgtype, msg)
        if self.sigma is None and not all(math.isnan(v) for v in sigma):
            self.sigma = [_NO_SIGMA] * len(self.t)
        if self.sigma is not None:
            self.sigma.append(sigma)
        self.t.append(t)
        self.xyz.append(xyz)
        self.orientation.append(q)
        self.frames.add(str(msg.header.frame_id))

    def add_raw(self, msgtype: str, raw: bytes | memoryview,
                decode: Callable[[memoryview, str], Any]) -> None:
        """Add a message from its CDR bytes: a little-endian ``PoseStamped`` read straight
        from them (the same numbers as its decoded message gives, a tenth of the time: the
        poses of a long mission number tens of thousands), any other through
        ``decode(bytes, msgtype)``."""
        body = _pose_body_offset(raw) if msgtype == POSE_STAMPED else None
        if body is not None:  # CDR, little-endian
            sec, nanosec, size = _POSE_HEADER.unpack_from(raw, 4)
            end = 16 + size  # of the frame id, its NUL included
            x, y, z, qx, qy, qz, qw = _POSE_BODY.unpack_from(raw, body)
            if self.sigma is not None:
                self.sigma.append(_NO_SIGMA)
            self.t.append(float(sec) + int(nanosec) * 1e-9)  # (stamp_seconds)
            self.xyz.append((x, y, z))
            self.orientation.append((qx, qy, qz, qw))
            self.frames.add(bytes(raw[16:end - 1]).decode())
            return
        self.add(msgtype, decode(memoryview(raw), msgtype))

    def __len__(self) -> int:
        return len(self.t)

    def trajectory(self, source: str) -> Trajectory:
        """The samples as a trajectory, in time order, screened as a whole
        (:func:`~lidarcal_ros.core.mission.screen_samples`: poses with a non-finite stamp or
        position, and stamps repeated at conflicting positions, left out with a warning line
        counting them).

        Raises
        ------
        TrajectoryError
            Every pose at one stamp (the header stamps were not set), or fewer than two usable
            poses: one line naming ``source`` (file and topic).
        """
        return Trajectory.from_samples(np.asarray(self.t, dtype=np.float64),
                                       np.asarray(self.xyz, dtype=np.float64),
                                       np.asarray(self.orientation).reshape(-1, 4),
                                       source=source,
                                       position_sigma=None if self.sigma is None
                                       else np.asarray(self.sigma).reshape(-1, 3))


def _pose_body_offset(raw: bytes | memoryview) -> int | None:
    """Where a little-endian CDR ``PoseStamped``'s position starts in ``raw`` (None where
    ``raw`` is not one as :meth:`TrajectorySamples.add_raw` reads it)."""
    if len(raw) < 16 or raw[1] != 1:
        return None
    _sec, _nanosec, size = _POSE_HEADER.unpack_from(raw, 4)
    end = 16 + size
    body = 4 + (end - 4 + 7) // 8 * 8
    if size and body + _POSE_BODY.size == len(raw) and raw[end - 1] == 0:
        return body
    return None


def moved_message(msgtype: str, raw: bytes | memoryview, xyz: tuple[float, float, float],
                  decode: Callable[[memoryview, str], Any],
                  encode: Callable[[Any, str], Any]) -> bytes:
    """The CDR bytes of trajectory message ``raw`` (one of :data:`TRAJECTORY_TYPES`) with its
    position set to ``xyz`` (m), everything else (stamp, frame, orientation, twist,
    covariances) as it was: a little-endian ``PoseStamped`` patched in its bytes, any other
    through ``decode(bytes, msgtype)`` and ``encode(message, msgtype)``."""
    if msgtype == POSE_STAMPED:
        body = _pose_body_offset(raw)
        if body is not None:
            out = bytearray(raw)
            struct.pack_into("<3d", out, body, *xyz)
            return bytes(out)
    msg = decode(memoryview(raw), msgtype)
    pos, _q = TRAJECTORY_TYPES[msgtype](msg)
    pos.x, pos.y, pos.z = (float(v) for v in xyz)
    return bytes(encode(msg, msgtype))


__all__ = ["TRAJECTORY_TYPES", "TrajectorySamples", "moved_message", "position_sigma",
           "trajectory_sample"]
