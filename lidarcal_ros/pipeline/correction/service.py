"""The correction behind the live corrector node: clouds in and out as CDR bytes.

:class:`CorrectionEngine` is the numerics; :class:`LocalCorrection` runs it in the calling
thread, :class:`~lidarcal_ros.pipeline.correction.process.CorrectionProcess` in a child process.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.bag.format import ns_to_seconds
from lidarcal_ros.io.cloud.messages import cloud_cdr, cloud_cdr_parts, parse_cloud
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.sensor_frame import SensorFrameGeoreference
from lidarcal_ros.pipeline.correction.stream import StreamCorrector

__all__ = [
    "RING_BYTES", "CorrectedMessage", "CorrectionEngine", "ErrorHandler", "LocalCorrection",
    "MessagePlacer", "ResultHandler", "ServiceOptions", "warm_up_engine",
]

logger = logging.getLogger(__name__)

#: ``on_result(tag, cdr, points, not_corrected, seconds)``: a corrected cloud, serialised
#: (``bytes``, or a view of a shared-memory ring that is valid during the call only).
ResultHandler = Callable[[Any, bytes | memoryview, int, int, float], None]
#: ``on_error(tag, reason)``: a cloud that could not be corrected (malformed), skipped.
ErrorHandler = Callable[[Any, str], None]


#: Default bytes of each shared-memory ring (:mod:`~lidarcal_ros.io.cloud.shared_ring`) that
#: carries the clouds to the correction process and back: about nine 50 ms chunks of a 4 MHz
#: sensor in (10 MB each), six out (15 MB), room for a start-up queue. A cloud that does not
#: fit goes through the pipe.
RING_BYTES = 96 << 20


@dataclass(frozen=True)
class ServiceOptions:
    """How the correction runs (the node's parameters).

    Attributes
    ----------
    batch_points : int
        :class:`StreamCorrector` ``batch_points`` (0: each cloud as soon as it can be).
    workers : int
        Threads correcting batches.
    lookahead : bool
        Wait for the points after a cloud before fitting its normals.
    source : str
        Topic named in messages.
    trajectory_keep_s : float
        Seconds of trajectory kept.
    ring_bytes : int
        Bytes of each of the two shared-memory rings of
        :class:`~lidarcal_ros.pipeline.correction.process.CorrectionProcess` (0: pipes only).
    sensor : SensorFrameGeoreference or None
        Clouds in the sensor's frame, georeferenced with this calibrated mounting (each
        engine its own copy; the trajectory then the poses of ``base_link``); None: map-frame
        clouds.
    """

    batch_points: int = 0
    workers: int = 1
    lookahead: bool = True
    source: str = "cloud"
    trajectory_keep_s: float = 600.0
    ring_bytes: int = RING_BYTES
    sensor: SensorFrameGeoreference | None = None


@dataclass(frozen=True)
class CorrectedMessage:
    """A corrected cloud, not yet serialised (each runner serialises it its own way).

    Attributes
    ----------
    tag : any
        The caller's name for the cloud.
    stamp_ns, frame_id : int, str
        The input message's header (ns since the epoch; the map frame).
    points : structured array
        The corrected points
        (:func:`~lidarcal_ros.pipeline.correction.corrected_cloud.corrected_dtype`).
    not_corrected : int
        Points flagged not corrected.
    dense : bool
        Every coordinate finite (the message's ``is_dense``).
    seconds : float
        Wall time from its push to its result, s.
    """

    tag: Any
    stamp_ns: int
    frame_id: str
    points: np.ndarray
    not_corrected: int
    dense: bool
    seconds: float

    def cdr_parts(self) -> tuple[bytes, memoryview, bytes]:
        """The message's CDR bytes in parts (:func:`~lidarcal_ros.io.cloud.messages.
        cloud_cdr_parts`)."""
        return cloud_cdr_parts(self.stamp_ns, self.frame_id, self.points,
                               is_dense=self.dense)


#: ``placer(tag, stamp_ns, frame_id, n, dtype)``: where to build a corrected cloud (the
#: points of its message, in the buffer it is sent from), or None.
MessagePlacer = Callable[[Any, int, str, int, "np.dtype[Any]"], "np.ndarray | None"]


class CorrectionEngine:
    """Trajectory buffer, stream corrector and CDR in: what both runners run.

    Parameters
    ----------
    settings : CorrectionSettings
    options : ServiceOptions
    placer : MessagePlacer, optional
        Where to build each corrected cloud (in the buffer it is sent from).
    on_failed : ErrorHandler, optional
        Called for each cloud of a batch whose correction raised (a bug); without it the
        exception propagates.

    Attributes
    ----------
    trajectory : TrajectoryBuffer
        The trajectory samples received (:meth:`poses`), ``options.trajectory_keep_s`` kept.
    corrector : StreamCorrector
    """

    def __init__(self, settings: CorrectionSettings, options: ServiceOptions, *,
                 placer: MessagePlacer | None = None, on_failed: ErrorHandler | None = None
                 ) -> None:
        self.options = options
        self.trajectory = TrajectoryBuffer(options.trajectory_keep_s)
        #: Georeferences clouds in the sensor's frame (None: map-frame clouds).
        self.sensor = copy.deepcopy(options.sensor)
        self._placer = placer
        self._on_failed = on_failed
        self.corrector = StreamCorrector(
            self.trajectory.trajectory(), settings, batch_points=options.batch_points,
            workers=options.workers, lookahead=options.lookahead, source=options.source,
            place=self._place if placer is not None else None,
            on_failed=self._failed if on_failed is not None else None, keep_tallies=True)
        self._headers: dict[Any, tuple[int, str, float]] = {}

    def _failed(self, tag: Any, exc: Exception) -> None:
        """A cloud whose batch raised in a worker (a bug): reported as an error, not lost."""
        assert self._on_failed is not None
        self._headers.pop(tag, None)
        self._on_failed(tag, f"internal error: {type(exc).__name__}: {exc}")

    def _place(self, tag: Any, n: int, dtype: np.dtype[Any]) -> np.ndarray | None:
        assert self._placer is not None
        stamp, frame, _started = self._headers[tag]
        return self._placer(tag, stamp, frame, n, dtype)

    def poses(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None = None
              ) -> None:
        """Add trajectory samples (as :meth:`LocalCorrection.poses`)."""
        self.trajectory.add_many(t, xyz, orientation)

    def push(self, clouds: Sequence[tuple[Any, bytes | memoryview]], on_error: ErrorHandler
             ) -> list[CorrectedMessage]:
        """Correct clouds (tag, CDR bytes, read in place); the corrected ones now ready.
        A malformed cloud goes to ``on_error`` and is skipped."""
        started = time.perf_counter()
        parsed: list[tuple[np.ndarray, Any]] = []
        failure = self._set_trajectory()
        for tag, raw in clouds:
            try:
                cloud = parse_cloud(raw, source=self.options.source)
                frame, points = cloud.frame_id, cloud.points
                if self.sensor is not None:
                    if failure:
                        raise LidarcalError(failure)
                    frame, points = self._georeferenced(cloud.frame_id, cloud.stamp_ns,
                                                        points)
            except LidarcalError as exc:
                on_error(tag, str(exc))
                continue
            self._headers[tag] = (cloud.stamp_ns, frame, started)
            parsed.append((points, tag))

        def malformed(tag: Any, exc: LidarcalError) -> None:
            self._headers.pop(tag, None)
            on_error(tag, str(exc))

        return self._finish(self.corrector.push_many(parsed, on_error=malformed))

    def _set_trajectory(self) -> str:
        """Give the corrector the trajectory received (of the sensor's origin, for clouds in
        the sensor's frame); why it cannot be ('' where it can)."""
        trajectory = self.trajectory.trajectory()
        if self.sensor is not None:
            try:
                trajectory = self.sensor.set_trajectory(trajectory)
            except LidarcalError as exc:
                return f"{self.options.source}: {exc}"
        self.corrector.set_trajectory(trajectory)
        return ""

    def _georeferenced(self, frame_id: str, stamp_ns: int, points: np.ndarray
                       ) -> tuple[str, np.ndarray]:
        """A cloud in the sensor's frame in the map frame (its frame, its points)."""
        sensor = self.sensor
        assert sensor is not None
        if frame_id != sensor.extrinsic.child:
            raise LidarcalError(f"{self.options.source}: cloud in frame '{frame_id}'; the "
                                "calibration's extrinsic block is the mounting of "
                                f"'{sensor.extrinsic.child}'")
        return sensor.map_frame, sensor.cloud(points, ns_to_seconds(stamp_ns),
                                              source=self.options.source)

    def release(self) -> list[CorrectedMessage]:
        """Correct what is held now, without waiting for look-ahead."""
        self._set_trajectory()
        return self._finish(self.corrector.release())

    def flush(self) -> list[CorrectedMessage]:
        """Correct everything held (the end of the stream)."""
        self._set_trajectory()
        return self._finish(self.corrector.flush())

    def collect(self, timeout: float = 0.0) -> list[CorrectedMessage]:
        """Clouds the worker threads have finished since the last call (waiting up to
        ``timeout`` s for the oldest batch in flight)."""
        return self._finish(self.corrector.collect_ready(timeout))

    def _finish(self, out: list[tuple[Any, np.ndarray]]) -> list[CorrectedMessage]:
        done = []
        tallies = self.corrector.tallies
        for tag, corrected in out:
            stamp, frame, started = self._headers.pop(tag)
            tally = tallies.pop(tag)
            done.append(CorrectedMessage(tag, stamp, frame, corrected,
                                   tally.flagged(FLAG_NOT_CORRECTED), tally.dense,
                                   time.perf_counter() - started))
        return done


class LocalCorrection:
    """The correction in the calling thread (same interface as
    :class:`~lidarcal_ros.pipeline.correction.process.CorrectionProcess`).

    ``warm``: run the engine once over a synthetic strip first (:func:`warm_up_engine`).
    """

    def __init__(self, settings: CorrectionSettings, options: ServiceOptions, *,
                 on_result: ResultHandler, on_error: ErrorHandler,
                 warm: bool = False) -> None:
        if warm:
            warm_up_engine(settings, options)
        #: The engine it runs (its trajectory and stream corrector).
        self.engine = CorrectionEngine(settings, options, on_failed=on_error)
        self._on_result = on_result
        self._on_error = on_error

    def poses(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None = None
              ) -> None:
        """Add trajectory samples (s; map frame, m; orientation quaternions (n, 4) xyzw, NaN
        rows or None: none)."""
        self.engine.poses(t, xyz, orientation)

    def push(self, clouds: list[tuple[Any, bytes | memoryview]]) -> None:
        """Correct clouds (tag, CDR bytes); results come through the handlers."""
        self._emit(self.engine.push(clouds, self._on_error))

    def release(self) -> None:
        """Correct what is held now, without waiting for look-ahead."""
        self._emit(self.engine.release())

    @property
    def in_flight(self) -> int:
        """Batches in worker threads whose clouds :meth:`poll` has not yet reported."""
        return self.engine.corrector.in_flight

    def poll(self) -> None:
        """Report the clouds worker threads have finished (``workers`` > 1)."""
        if self.engine.corrector.in_flight:
            self._emit(self.engine.collect())

    def set_settings(self, settings: CorrectionSettings) -> None:
        """Use new settings (calibration, radiometry) from the next batch on."""
        self.engine.corrector.set_settings(settings)

    def set_lookahead(self, lookahead: bool) -> None:
        """Wait for look-ahead (or not) from the next cloud on."""
        self.engine.corrector.set_lookahead(lookahead)

    def set_trajectory_keep(self, seconds: float) -> None:
        """Keep this many seconds of trajectory."""
        self.engine.trajectory.keep_s = float(seconds)

    def close(self) -> None:
        """Correct and report everything held."""
        self._emit(self.engine.flush())

    def _emit(self, results: list[CorrectedMessage]) -> None:
        for r in results:
            self._on_result(r.tag, b"".join(r.cdr_parts()), len(r.points), r.not_corrected,
                            r.seconds)


#: Points per cloud of the warm-up: a 50 ms chunk of a 4 MHz sensor, so that the heap has
#: grown to what such clouds need before the first real one comes.
_WARM_UP_CLOUD_POINTS = 200_000


def warm_up_engine(settings: CorrectionSettings, options: ServiceOptions) -> None:
    """Run the engine once over a synthetic strip (level flight at 1000 m over flat ground),
    so that the first real clouds do not pay for first calls (imports done lazily, compiled
    loops loaded) or first allocations (the heap grown page by page): without it the first
    chunks of a live stream come out late, and at a high point rate the backlog they leave
    takes seconds to work off."""
    from lidarcal_ros.io.cloud.pointcloud import make_point_dtype

    # (model auto: the synthetic poses carry no orientation that a rigorous one would need)
    engine = CorrectionEngine(dataclasses.replace(settings, time_field="t",
                                                  model=PositioningModel.AUTO),
                     dataclasses.replace(options, workers=1, source="warm-up", sensor=None))
    t_traj = np.arange(0.0, 2.0, 0.01)
    engine.poses(t_traj, np.column_stack([np.zeros_like(t_traj), 60.0 * t_traj,
                                          np.full_like(t_traj, 1000.0)]))
    rng = np.random.default_rng(0)
    clouds = []
    for k in range(3):
        n = _WARM_UP_CLOUD_POINTS
        pts = np.zeros(n, dtype=make_point_dtype())
        pts["t"] = 0.5 + k * 0.05 + np.sort(rng.random(n)) * 0.05
        t = pts["t"]
        pts["x"] = 300.0 * np.sin(2.0 * np.pi * 50.0 * t)
        pts["y"] = 60.0 * t
        pts["z"] = rng.normal(0.0, 0.05, n)
        pts["intensity"] = 100.0
        pts["strip_id"] = 1
        clouds.append((k, cloud_cdr(0, "map", pts)))
    for cloud in clouds:  # one at a time, as they come when the node keeps up
        engine.push([cloud], lambda _tag, _reason: None)
    engine.flush()
