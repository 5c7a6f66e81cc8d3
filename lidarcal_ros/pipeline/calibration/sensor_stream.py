"""Clouds in the sensor's frame fed live to a streaming calibration (docs/method.md section 12).

:class:`SensorFrameFeed` holds the poses of ``base_link`` and the driver's points as they
arrive; as each flight line closes (the turn after it has begun) it hands the calibration the
line's points georeferenced as ``lidarcal calibrate`` georeferences them
(:func:`~lidarcal_ros.core.calibration.extrinsic.line_strips`), one strip per line, and the
trajectory of the sensor's origin.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from lidarcal_ros.core.calibration.extrinsic import (
    MountingCalibration,
    line_strips,
    mounting_calibration,
    sensor_trajectory,
)
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.trajectory.lines import WINDOW_S, straight_lines
from lidarcal_ros.errors import InputError, TrajectoryError
from lidarcal_ros.io.bag.sensor_bag import static_mounting
from lidarcal_ros.io.calibration_file import Extrinsic
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.calibration.stream_inputs import TrajectorySamples
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration

__all__ = ["CLOSE_AFTER_S", "SensorFrameFeed"]

logger = logging.getLogger(__name__)

#: A line is closed once the trajectory reaches this far past its end, s: whether a pose is
#: on a line depends on the poses ``2 WINDOW_S`` either side of it and a line's end is
#: trimmed by one ``WINDOW_S`` (:func:`~lidarcal_ros.core.trajectory.lines.straight_lines`),
#: so from then on the line is the one the whole flight's trajectory gives.
CLOSE_AFTER_S = 4.0 * WINDOW_S


class SensorFrameFeed:
    """The poses of ``base_link`` and a driver's points, handed to a
    :class:`StreamingCalibration` line by line (module docstring).

    Parameters
    ----------
    base_frame : str, keyword-only
        The trajectory's body frame (``sensor_frame.base_frame``).
    mounting : Mounting or None, keyword-only
        The nominal ``base_frame -> sensor`` of the configuration (``sensor_frame.mounting``);
        None: from the static transforms (:meth:`add_transforms`).
    """

    def __init__(self, *, base_frame: str, mounting: Mounting | None) -> None:
        self.base_frame = base_frame
        self._configured = mounting
        self._transforms: dict[str, tuple[str, Mounting]] = {}
        self._tf_source = ""
        self.reset()

    def reset(self) -> None:
        """Forget the poses, points and lines (keep the mounting and the transforms)."""
        #: The clouds' frame (the sensor's), None until the first cloud.
        self.frame_id: str | None = None
        #: The trajectory's frame.
        self.map_frame: str | None = None
        #: The lines closed (first and last time, s), strip ids their indices.
        self.lines = np.empty((0, 2))
        #: Points left out: in no line (turns, hover), or of a line already closed.
        self.turn_points = 0
        self.late_points = 0
        #: Why no line goes on to the calibration ('' while they do), one line.
        self.refusal = ""
        self._poses = TrajectorySamples()
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._fed_t = -math.inf  # the newest pose of the sensor's origin handed on, s
        self._newest_point_t = -math.inf  # the newest point's time received, s

    # -- inputs ---------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """Whether clouds in the sensor's frame have arrived."""
        return self.frame_id is not None

    def add_transforms(self, transforms: dict[str, tuple[str, Mounting]], source: str) -> None:
        """Static transforms (``child: (parent, parent -> child)``), e.g. of ``/tf_static``."""
        self._transforms.update(transforms)
        self._tf_source = source

    def add_poses(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray,
                  frame_id: str) -> None:
        """Poses of ``base_frame``: times (n,) s, positions (n, 3) m, quaternions (n, 4)
        xyzw (NaN: none), in ``frame_id``."""
        if self.map_frame is None:
            self.map_frame = frame_id
        elif frame_id != self.map_frame:
            raise InputError(f"trajectory in frame '{frame_id}' but earlier poses in "
                             f"'{self.map_frame}'")
        self._poses.add(t, xyz, orientation)

    def add_cloud(self, xyz: np.ndarray, t: np.ndarray, frame_id: str) -> None:
        """A driver's cloud: (n, 3) m in ``frame_id`` (the sensor's), (n,) absolute s
        (:class:`~lidarcal_ros.io.cloud.sensor_time.SensorCloudDecoder`)."""
        if self.frame_id is None:
            self.frame_id = frame_id
        elif frame_id != self.frame_id:
            raise InputError(f"cloud in frame '{frame_id}' but earlier clouds in "
                             f"'{self.frame_id}'")
        if not len(t):
            return
        newest = float(np.max(t))
        if self.lines.size and newest <= self.lines[-1, 1]:
            self.late_points += len(t)  # its line was handed on already
            return
        self._newest_point_t = max(self._newest_point_t, newest)
        self._pending.append((xyz, t))

    # -- state ----------------------------------------------------------------------------
    @property
    def mounting(self) -> Mounting | None:
        """The nominal mounting: the configuration's, else the static transforms' chain
        ``base_frame -> sensor`` (None: neither yet)."""
        if self._configured is not None:
            return self._configured
        if self.frame_id is None:
            return None
        return static_mounting(self._transforms, self.base_frame, self.frame_id)

    @property
    def mounting_source(self) -> str:
        """Where the nominal mounting comes from, in words."""
        return ("the configuration (sensor_frame.mounting)" if self._configured is not None
                else self._tf_source or "/tf_static")

    @property
    def pending_points(self) -> int:
        """Points held until their line closes."""
        return sum(len(t) for _, t in self._pending)

    def extrinsic(self, cal: MountingCalibration) -> Extrinsic:
        """The calibration file's ``extrinsic`` block of a calibration of these clouds."""
        return Extrinsic(self.base_frame, self.frame_id or "", cal.mounting, cal.nominal)

    def calibration(self, result: CalibrationResult) -> MountingCalibration | None:
        """The calibrated mounting of an estimate of the lines handed on (None: no
        mounting)."""
        nominal = self.mounting
        return None if nominal is None else mounting_calibration(result, nominal, self.lines)

    # -- the work -------------------------------------------------------------------------
    def _refuse(self, reason: str) -> int:
        if reason != self.refusal:
            logger.error("clouds in the sensor's frame refused: %s", reason)
        self.refusal = reason
        return 0

    def step(self, stream: StreamingCalibration, *, final: bool = False,
             covered: bool = False) -> int:
        """Hand ``stream`` the new poses of the sensor's origin and the points of the lines
        closed since the last step (with ``final``: every line, the flight taken as ended;
        with ``covered`` too, only once the poses reach a ``WINDOW_S`` past the newest point,
        so that the last line takes every point the whole trajectory would give it); returns
        the points handed on. What stops it is said in :attr:`refusal`."""
        if self.frame_id is None or not self._poses:
            return 0
        nominal = self.mounting
        if nominal is None:
            return self._refuse(
                f"no mounting {self.base_frame} -> {self.frame_id}: "
                + (f"{self._tf_source} holds none" if self._tf_source else
                   "nothing received on /tf_static")
                + " and sensor_frame.mounting is not set")
        base = self._poses.trajectory
        if base.orientation is None:
            return self._refuse(f"the trajectory carries no orientation of {self.base_frame} "
                                "(identity or none throughout); clouds in the sensor's frame "
                                f"'{self.frame_id}' need its attitude")
        try:
            origin = sensor_trajectory(base, nominal)
        except TrajectoryError as exc:
            return self._refuse(str(exc))
        self.refusal = ""
        new = origin.t > self._fed_t
        if new.any():
            assert origin.orientation is not None and self.map_frame is not None
            stream.add_trajectory(origin.t[new], origin.xyz[new], self.map_frame,
                                  origin.orientation[new])
            self._fed_t = float(origin.t[-1])
        lines = straight_lines(base)
        if final and covered and float(base.t[-1]) < self._newest_point_t + WINDOW_S:
            final = False  # poses of the last line's end still to come (queued behind)
        # Both streams past the line's end: the clouds, larger, often arrive behind the
        # poses, and points of a line handed on already are lost to it.
        horizon = math.inf if final else \
            min(float(base.t[-1]), self._newest_point_t) - CLOSE_AFTER_S
        closed = lines[lines[:, 1] <= horizon]
        if len(closed) <= len(self.lines) or not self._pending:
            return 0
        xyz = np.concatenate([p for p, _ in self._pending])
        t = np.concatenate([q for _, q in self._pending])
        handed = 0
        for strip in line_strips(xyz, t, origin, nominal, closed):
            if strip.strip_id < len(self.lines):
                continue
            ids = np.full(len(strip), strip.strip_id, dtype=np.uint32)
            stream.add_cloud(CloudColumns(strip.xyz, strip.t, strip_id=ids), self.map_frame
                             or "map")
            handed += len(strip)
            logger.info("line %d closed (%.1f-%.1f s): %d points", strip.strip_id,
                        *closed[strip.strip_id], len(strip))
        later = t > closed[-1, 1]
        self.turn_points += int(t.size - np.count_nonzero(later)) - handed
        self._pending = [(xyz[later], t[later])] if later.any() else []
        self.lines = closed
        return handed
