"""Clouds in the sensor's frame fed live to a streaming calibration (docs/method.md section 12).

:class:`SensorFrameFeed` holds the poses of ``base_link`` and the driver's points as they
arrive; once the trajectory has settled which line a point is on (:data:`CLOSE_AFTER_S` past
it) it hands the calibration the point georeferenced as ``lidarcal calibrate`` georeferences
it (:func:`~lidarcal_ros.core.calibration.extrinsic.line_strips`), in blocks, one strip per
line, with the trajectory of the sensor's origin; the points of the turns it lets go.
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
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.trajectory.lines import MIN_LINE_S, WINDOW_S, line_of, straight_lines
from lidarcal_ros.errors import InputError, TrajectoryError
from lidarcal_ros.io.bag.sensor_bag import static_mounting
from lidarcal_ros.io.calibration_file import Extrinsic
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.calibration.checkpoint import SensorFrameState
from lidarcal_ros.pipeline.calibration.stream_inputs import TrajectorySamples
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration

__all__ = ["CLOSE_AFTER_S", "HELD_S", "SensorFrameFeed"]

logger = logging.getLogger(__name__)

#: A line is closed once the trajectory reaches this far past its end, s: whether a pose is
#: on a line depends on the poses ``2 WINDOW_S`` either side of it and a line's end is
#: trimmed by one ``WINDOW_S`` (:func:`~lidarcal_ros.core.trajectory.lines.straight_lines`),
#: so from then on the line is the one the whole flight's trajectory gives.
CLOSE_AFTER_S = 4.0 * WINDOW_S
#: Seconds of points the feed holds behind the trajectory's newest pose at most: a point on
#: no line is let go only once a line through it would be :data:`~lidarcal_ros.core.
#: trajectory.lines.MIN_LINE_S` long (the first seconds of a line are on none yet).
HELD_S = CLOSE_AFTER_S + MIN_LINE_S


class SensorFrameFeed:
    """The poses of ``base_link`` and a driver's points, handed to a
    :class:`StreamingCalibration` line by line in blocks (module docstring).

    It holds the points of the last :data:`HELD_S` seconds behind the trajectory's newest
    pose and those ahead of it, never more than ``max_points`` (beyond, the oldest are let go
    and counted in :attr:`overflow_points`); the calibration's memory budget bounds the rest.

    Parameters
    ----------
    base_frame : str, keyword-only
        ``sensor_frame.base_frame``: the trajectory's body frame where its messages name
        none (an Odometry's ``child_frame_id`` names it: :meth:`set_base_frame`).
    mounting : Mounting or None, keyword-only
        The nominal ``base_frame -> sensor`` of the configuration (``sensor_frame.mounting``);
        None: from the static transforms (:meth:`add_transforms`).
    max_points : int, keyword-only
        Points held at most.
    """

    def __init__(self, *, base_frame: str, mounting: Mounting | None,
                 max_points: int = 50_000_000) -> None:
        self.configured_base = base_frame
        self.base_frame = base_frame
        self.max_points = int(max_points)
        self._configured = mounting
        self._transforms: dict[str, tuple[str, Mounting]] = {}
        self._tf_source = ""
        self.reset()

    def reset(self) -> None:
        """Forget the poses, points and lines (keep the mounting, the transforms and the base
        frame)."""
        #: The clouds' frame (the sensor's), None until the first cloud.
        self.frame_id: str | None = None
        #: The trajectory's frame.
        self.map_frame: str | None = None
        #: The lines closed (first and last time, s), strip ids their indices.
        self.lines = np.empty((0, 2))
        #: Points left out: in no line (turns, hover), of a part already handed on, or let go
        #: over ``max_points``.
        self.turn_points = 0
        self.late_points = 0
        self.overflow_points = 0
        #: Why no line goes on to the calibration ('' while they do), one line.
        self.refusal = ""
        self._poses = TrajectorySamples()
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._fed_t = -math.inf  # the newest pose of the sensor's origin handed on, s
        self._handed_t = -math.inf  # points up to this time handed on where on a line, s
        self._newest_point = -math.inf  # s
        self._used: Mounting | None = None  # the nominal the poses handed on were made with

    # -- inputs ---------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """Whether clouds in the sensor's frame have arrived."""
        return self.frame_id is not None

    def add_transforms(self, transforms: dict[str, tuple[str, Mounting]], source: str) -> None:
        """Static transforms (``child: (parent, parent -> child)``), e.g. of ``/tf_static``."""
        self._transforms.update(transforms)
        self._tf_source = source

    def set_base_frame(self, frame: str) -> None:
        """The trajectory's body frame as its messages name it (an Odometry's
        ``child_frame_id``): it takes the place of ``sensor_frame.base_frame``, as in
        ``lidarcal calibrate`` (kept once poses went on with a mounting)."""
        if frame and self._used is None:
            self.base_frame = frame

    @property
    def base_note(self) -> str:
        """One line where the trajectory's body frame is not the configured mounting's parent
        ('' where they agree or the mounting is the static transforms')."""
        if self._configured is None or self.base_frame == self.configured_base:
            return ""
        return (f"the trajectory's child_frame_id '{self.base_frame}' is not "
                f"sensor_frame.base_frame '{self.configured_base}', the parent of "
                f"sensor_frame.mounting: the mounting is taken as {self.base_frame} -> "
                f"{self.frame_id}")

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
        if float(np.max(t)) <= self._handed_t:
            self.late_points += len(t)  # its part of the flight was handed on already
            return
        self._pending.append((xyz, t))
        self._newest_point = max(self._newest_point, float(np.max(t)))
        excess = self.pending_points - self.max_points
        while excess > 0 and self._pending:
            _, oldest = self._pending.pop(0)
            self.overflow_points += len(oldest)
            excess -= len(oldest)
            logger.warning("clouds in the sensor's frame: more than %d points ahead of the "
                           "trajectory; the oldest cloud (%d points) let go", self.max_points,
                           len(oldest))

    # -- state ----------------------------------------------------------------------------
    @property
    def mounting(self) -> Mounting | None:
        """The nominal mounting: the one the poses handed on were made with, else the
        configuration's, else the static transforms' chain ``base_frame -> sensor`` (None:
        none yet)."""
        if self._used is not None:
            return self._used
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
        """Points held until the trajectory settles their line."""
        return sum(len(t) for _, t in self._pending)

    @property
    def ended(self) -> bool:
        """Every point was handed on, the flight taken as ended (a final :meth:`step`)."""
        return self._handed_t == math.inf

    @property
    def base_trajectory(self) -> Trajectory:
        """The poses of ``base_frame`` received (InputError before the first)."""
        return self._poses.trajectory

    @property
    def horizon(self) -> float:
        """Points up to this time (s) were handed on where on a line (-inf: none yet); later
        points of it are late."""
        return self._handed_t

    def extrinsic(self, cal: MountingCalibration) -> Extrinsic:
        """The calibration file's ``extrinsic`` block of a calibration of these clouds."""
        return Extrinsic(self.base_frame, self.frame_id or "", cal.mounting, cal.nominal)

    def calibration(self, result: CalibrationResult) -> MountingCalibration | None:
        """The calibrated mounting of an estimate of the lines handed on (None: no
        mounting)."""
        nominal = self.mounting
        return None if nominal is None else mounting_calibration(result, nominal, self.lines)

    # -- checkpoints ----------------------------------------------------------------------
    def state(self) -> SensorFrameState | None:
        """What a checkpoint must carry to resume (None: no cloud in the sensor's frame)."""
        if self.frame_id is None:
            return None
        held = self._pending
        return SensorFrameState(
            frame_id=self.frame_id, base_frame=self.base_frame, map_frame=self.map_frame or "",
            nominal=self._used, lines=self.lines.copy(), poses=self._poses.arrays(),
            pending_xyz=np.concatenate([p for p, _ in held]) if held else np.empty((0, 3)),
            pending_t=np.concatenate([q for _, q in held]) if held else np.empty(0),
            fed_t=self._fed_t, handed_t=self._handed_t,
            counters=(self.turn_points, self.late_points, self.overflow_points))

    def restore(self, state: SensorFrameState) -> None:
        """Resume from :meth:`state` (the calibration from the same checkpoint)."""
        self.reset()
        self.frame_id, self.base_frame = state.frame_id, state.base_frame
        self.map_frame = state.map_frame or None
        self._used = state.nominal
        self.lines = np.asarray(state.lines, dtype=np.float64).reshape(-1, 2)
        t, xyz, q = state.poses
        if t.size:
            self._poses.add(t, xyz, q)
        if state.pending_t.size:
            self._pending = [(state.pending_xyz, state.pending_t)]
        self._fed_t, self._handed_t = state.fed_t, state.handed_t
        self._newest_point = float(np.max(state.pending_t)) if state.pending_t.size else \
            state.handed_t
        self.turn_points, self.late_points, self.overflow_points = state.counters

    # -- the work -------------------------------------------------------------------------
    def _refuse(self, reason: str) -> int:
        if reason != self.refusal:
            logger.error("clouds in the sensor's frame refused: %s", reason)
        self.refusal = reason
        return 0

    def _no_mounting(self) -> str:
        held = ", ".join(f"{p} -> {c}" for c, (p, _) in sorted(self._transforms.items()))
        return (f"no mounting {self.base_frame} -> {self.frame_id}: "
                + (f"{self._tf_source} holds {held or 'none'}" if self._tf_source else
                   "nothing received on /tf_static")
                + " and sensor_frame.mounting is not set")

    def step(self, stream: StreamingCalibration, *, final: bool = False,
             covered: bool = False) -> int:
        """Hand ``stream`` the new poses of the sensor's origin and the points whose line
        the trajectory has settled (with ``final``: all, the flight taken as ended; with
        ``covered`` too, only once the poses reach a ``WINDOW_S`` past the newest point, so
        that the last line takes every point the whole trajectory would give it); returns
        the points handed on. What stops it is said in :attr:`refusal`."""
        if self.frame_id is None or not self._poses:
            return 0
        nominal = self.mounting
        if nominal is None:
            return self._refuse(self._no_mounting())
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
            self._used = nominal  # the calibration's trajectory is made with it now
        lines = straight_lines(base)
        if final and covered and float(base.t[-1]) < self._newest_point + WINDOW_S:
            final = False  # poses of the last points' time still to come (queued behind)
        # (no later than the newest point: a cloud may come after the poses of its time)
        horizon = math.inf if final else min(float(base.t[-1]) - CLOSE_AFTER_S,
                                             self._newest_point)
        if horizon <= self._handed_t:  # (after a final step: everything was)
            return 0
        closed = lines[lines[:, 1] <= horizon]
        if len(closed) > len(self.lines):
            self.lines = closed
        if not self._pending:
            self._handed_t = horizon
            return 0
        xyz = np.concatenate([p for p, _ in self._pending])
        t = np.concatenate([q for _, q in self._pending])
        label = line_of(t, lines)
        settled = t <= horizon
        hand = settled & (label >= 0)
        # on no line: let go once a line through it would be long enough to be one
        gone = hand | (settled & (t <= horizon - MIN_LINE_S))
        handed = 0
        for strip in line_strips(xyz[hand], t[hand], origin, nominal, lines):
            ids = np.full(len(strip), strip.strip_id, dtype=np.uint32)
            stream.add_cloud(CloudColumns(strip.xyz, strip.t, strip_id=ids), self.map_frame
                             or "map")
            handed += len(strip)
        self.turn_points += int(np.count_nonzero(gone)) - handed
        keep = ~gone
        self._pending = [(xyz[keep], t[keep])] if keep.any() else []
        self._handed_t = horizon
        return handed
