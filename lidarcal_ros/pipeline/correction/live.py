"""The live corrector's work without ROS: clouds wait for the trajectory, are corrected, go out.

:class:`LiveCorrector` is what ``lidarcal_corrector`` runs (docs/correction.md, "The live
corrector").
"""

from __future__ import annotations

import copy
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.heading import HeadingSource, describe_heading_policy
from lidarcal_ros.core.georeferencing.rigorous import describe_model_policy
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryEstimate
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.bag.format import ns_to_seconds
from lidarcal_ros.io.calibration_file import read_calibration
from lidarcal_ros.io.cloud.columns import resolve_time_field, time_span
from lidarcal_ros.io.cloud.messages import OK, WARN, StatusSpec, parse_cloud
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.backlog import Region, WaitingCloud, WaitingClouds, take_ready
from lidarcal_ros.pipeline.correction.process import CorrectionProcess, InboundRegion
from lidarcal_ros.pipeline.correction.sensor_frame import SensorFrameGeoreference
from lidarcal_ros.pipeline.correction.service import LocalCorrection, ServiceOptions
from lidarcal_ros.pipeline.throttled_log import ThrottledLog

__all__ = ["POSES_PER_HANDOVER", "CorrectorOptions", "CorrectorStats", "LiveCorrector"]

logger = logging.getLogger(__name__)

#: Trajectory samples held for the correction at most: they go with the next cloud, or on
#: their own beyond this (a trajectory without clouds, e.g. on transit to the site, is not
#: kept as Python objects for hours).
POSES_PER_HANDOVER = 2000
#: Least wall time between two log lines of one kind of skipped or dropped cloud, s.
_LOG_EVERY_S = 2.0


@dataclass(frozen=True)
class CorrectorOptions:
    """The corrector's own settings: the node parameters of the same names
    (:data:`lidarcal_ros.core.config.NODE_PARAMETERS`, where they are described; from the
    node's values with :func:`~lidarcal_ros.core.config.node_options`).

    Attributes
    ----------
    trajectory_buffer_s : float
        Seconds of trajectory kept.
    max_trajectory_wait_s : float
        Longest wall time a cloud waits for the trajectory to cover it, s.
    flush_timeout_s : float
        Wall time without a new cloud after which held clouds are corrected without
        look-ahead, s.
    lookahead : bool
        Wait for the next clouds of a strip before fitting a cloud's normals.
    workers : int
        Threads correcting batches.
    batch_points : int
        Clouds of one strip corrected together up to this many points (0: one at a time).
    separate_process : bool
        Correct in a child process (else in a thread of this one).
    max_backlog_mib : int
        Most received clouds waiting for the correction, MiB (0: no limit).
    shared_memory_mib : int
        Size of each shared-memory ring of the child process, MiB (0: pipes only).
    """

    trajectory_buffer_s: float
    max_trajectory_wait_s: float
    flush_timeout_s: float
    lookahead: bool
    workers: int
    batch_points: int
    separate_process: bool
    max_backlog_mib: int
    shared_memory_mib: int


@dataclass
class CorrectorStats:
    """Counts since start (or the last reset)."""

    clouds_in: int = 0
    points_in: int = 0
    clouds_out: int = 0
    points_out: int = 0
    skipped: int = 0
    dropped: int = 0  # clouds dropped from a backlog above max_backlog_mib
    dropped_bytes: int = 0
    last_error: str = ""
    not_corrected: int = 0
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=10000))
    busy_s: float = 0.0


class LiveCorrector:
    """The live correction of clouds as they arrive (docs/correction.md).

    Parameters
    ----------
    config : FlightConfig
    options : CorrectorOptions
    publish : callable(bytes or memoryview)
        Called with each corrected cloud's CDR bytes, in the order the clouds arrived (from
        the correction's reader thread, or the worker thread). A ``memoryview`` is a view of
        shared memory, valid during the call only: published from there, never kept.
    calibration : str
        Calibration file used until an estimate arrives ('' = the configuration's
        ``calibration.fixed.*`` values).

    Raises
    ------
    ConfigError
        The calibration file cannot be read.
    """

    def __init__(self, config: FlightConfig, options: CorrectorOptions, *,
                 publish: Callable[[bytes | memoryview], None], calibration: str = "") -> None:
        self.config = config
        self.options = options
        self._publish = publish
        self.stats = CorrectorStats()
        self._lock = threading.Condition()
        self._waiting = WaitingClouds()
        self._closing = False
        self.estimate_source = "configuration"
        #: Each strip's trajectory error removed with the biases (the calibration file's,
        #: docs/method.md section 11), or None.
        self._trajectory_errors: TrajectoryEstimate | None = None
        #: Georeferences clouds in the sensor's frame with the calibration file's mounting
        #: (None: map-frame clouds; docs/nodes.md).
        self.sensor: SensorFrameGeoreference | None = None
        if calibration:
            record = read_calibration(calibration)  # one line at start-up
            self._delta, self._trajectory_errors = record.delta, record.trajectory
            self.estimate_source = str(calibration)
            if record.extrinsic is not None:
                self.sensor = SensorFrameGeoreference.from_config(
                    record, config, record.extrinsic.child, config["frame_id"],
                    where=calibration)
                self._times = copy.deepcopy(self.sensor.decoder)  # (the clouds' last times)
                logger.info("clouds in the sensor's frame '%s' georeferenced with the "
                            "calibrated mounting %s -> %s of %s into '%s'",
                            record.extrinsic.child, record.extrinsic.parent,
                            record.extrinsic.child, calibration, config["frame_id"])
        else:
            self._delta = _fixed_biases(config)
        self.settings = self._settings_of(config)
        if config["radiometry.reference_target"] and not self.settings.radiometry.absolute:
            logger.warning(
                "radiometry.reference_target is not used live (it needs the whole mission: "
                "lidarcal report or correct derive radiometry.calibration_constant from it); "
                "reflectance stays relative, in intensity units")
        self._settings_changed = False
        self._lookahead_changed = False
        self._keep_changed = False
        #: The trajectory received (``trajectory_buffer_s`` kept).
        self.trajectory = TrajectoryBuffer(options.trajectory_buffer_s)
        self._poses_t: list[float] = []  # samples not yet given to the correction
        self._poses_xyz: list[tuple[float, float, float]] = []
        self._poses_q: list[tuple[float, ...]] = []
        self._held: dict[int, WaitingCloud] = {}  # pushed, not yet reported back
        self._next_tag = 0
        self._last_push = time.monotonic()
        self._released_tag = -1  # the newest tag at the last time-out release
        self._throttled = ThrottledLog(logger)
        #: What corrects the clouds: a :class:`CorrectionProcess` or a
        #: :class:`LocalCorrection` (replaced if the process dies).
        self.runner = self._start_runner()
        self._worker = threading.Thread(target=self._work, name="lidarcal-corrector",
                                        daemon=True)
        self._worker.start()

    # -- input (from the node's callbacks) ---------------------------------------------
    def receive_buffer(self, size: int) -> tuple[memoryview, InboundRegion | None]:
        """Memory to receive a cloud of ``size`` bytes into (from the node's subscription,
        during the take): a region of the correction process's inbound ring, so that the
        cloud reaches the numerics without another copy, or (no ring, or a full one) a
        buffer of its own. Give both to :meth:`add_cloud` once the cloud is in it, or the
        region back (:meth:`InboundRegion.release`) if it never came."""
        runner = self.runner
        if isinstance(runner, CorrectionProcess):
            region = runner.inbound_region(size)
            if region is not None:
                return region.view, region
        return memoryview(bytearray(size)), None

    def add_cloud(self, raw: bytes | memoryview, region: Region | None = None) -> None:
        """A cloud received (CDR bytes; in ``region`` of :meth:`receive_buffer`, if it was
        received there): corrected once the trajectory covers it."""
        cloud = WaitingCloud(raw, time.monotonic(), memoryview(raw).nbytes, region=region)
        with self._lock:
            self._waiting.append(cloud)
            self._lock.notify()

    def add_pose(self, t: float, xyz: tuple[float, float, float], frame_id: str,
                 orientation: tuple[float, ...]) -> None:
        """A trajectory sample: time (s), IMU position (map frame, m), quaternion xyzw
        (NaN: none)."""
        steps = self.trajectory.steps_back
        self.trajectory.add(t, xyz, frame_id, orientation)
        if self.trajectory.steps_back > steps:
            self._throttled.log(logging.ERROR, _LOG_EVERY_S,
                                f"{self.config['topics.trajectory']}: pose "
                                f"{self.trajectory.last_step_back}; the poses of the old "
                                "clock from there on are dropped")
        with self._lock:
            self._poses_t.append(t)
            self._poses_xyz.append(xyz)
            self._poses_q.append(orientation)
            if self._waiting:  # a cloud may be waiting for the trajectory to cover it
                # (not otherwise: hundreds of samples a second would each wake the worker)
                self._lock.notify()

    def set_config(self, config: FlightConfig) -> None:
        """A new flight configuration: applies from the next cloud on (its
        ``calibration.fixed.*`` too while no estimate or file gave the biases)."""
        if self.estimate_source == "configuration":
            self._delta = _fixed_biases(config)
        with self._lock:
            self.config = config
            self.settings = self._settings_of(config)
            self._settings_changed = True

    def _settings_of(self, config: FlightConfig) -> CorrectionSettings:
        """The correction's settings: ``config``'s, the biases and trajectory errors held
        (for clouds in the sensor's frame, none: the mounting holds them)."""
        settings = replace(CorrectionSettings.from_config(config, self._delta),
                           trajectory_errors=self._trajectory_errors)
        return settings if self.sensor is None else self.sensor.settings(settings)

    def set_estimate(self, delta: np.ndarray, source: str,
                     trajectory_errors: TrajectoryEstimate | None = None) -> None:
        """New biases (docs/method.md order, SI) and each strip's trajectory error (none:
        the trajectory as exact) from ``source``: applied from the next cloud on (not to
        clouds in the sensor's frame, which the calibration file's mounting corrects)."""
        if self.sensor is not None:
            self._throttled.log(logging.WARNING, 3600.0,
                                f"estimate from {source} not applied: clouds in the sensor's "
                                "frame are corrected with the calibration file's mounting")
            return
        with self._lock:
            self._delta = delta
            self._trajectory_errors = trajectory_errors
            self.estimate_source = source
            self.settings = self._settings_of(self.config)
            self._settings_changed = True

    def set_options(self, options: CorrectorOptions) -> None:
        """New options (those not read-only apply at once)."""
        old, self.options = self.options, options
        if options.trajectory_buffer_s != old.trajectory_buffer_s:
            self.trajectory.keep_s = float(options.trajectory_buffer_s)
            with self._lock:
                self._keep_changed = True
        if options.lookahead != old.lookahead:
            with self._lock:
                self._lookahead_changed = True

    # -- what the node and the tests read ------------------------------------------------
    @property
    def waiting_clouds(self) -> int:
        """Clouds received and not yet handed to the correction."""
        return len(self._waiting)

    @property
    def waiting_bytes(self) -> int:
        """Bytes of those clouds."""
        return self._waiting.bytes

    @property
    def held_clouds(self) -> int:
        """Clouds handed to the correction and not yet reported back."""
        return len(self._held)

    @property
    def poses_waiting(self) -> int:
        """Trajectory samples not yet handed to the correction."""
        return len(self._poses_t)

    @property
    def transport(self) -> str:
        """How clouds reach the numerics: ``thread``, ``shared memory`` or ``pipes``."""
        runner = self.runner
        if not isinstance(runner, CorrectionProcess):
            return "thread"
        return "shared memory" if runner.shared_memory else "pipes"

    def status(self) -> StatusSpec:
        """The diagnostics ``lidarcal: corrector``."""
        s = self.stats
        lat = np.asarray(s.latencies, dtype=np.float64)
        p50 = float(np.percentile(lat, 50)) if lat.size else math.nan
        p99 = float(np.percentile(lat, 99)) if lat.size else math.nan
        steps = self.trajectory.steps_back
        level = WARN if s.skipped or s.not_corrected or s.dropped or steps else OK
        msg = (f"{s.clouds_out} clouds ({s.points_out} points) corrected, "
               f"latency p99 {p99 * 1000:.0f} ms")
        if steps:
            msg += (f"; pose {self.trajectory.last_step_back} ({steps} step(s) back; the old "
                    "clock's poses dropped)")
        if s.dropped:
            msg += (f"; {s.dropped} clouds dropped ({s.dropped_bytes / 2**20:.0f} MiB): "
                    "backlog above max_backlog_mib")
        if s.skipped:
            msg += f"; {s.skipped} malformed clouds skipped (last: {s.last_error})"
        if s.not_corrected:
            msg += f"; {s.not_corrected} points not covered by the trajectory"
        heading_source = HeadingSource(self.config["matching.heading_source"])
        return StatusSpec(level, "lidarcal: corrector", msg, {
            "clouds_in": str(s.clouds_in), "points_in": str(s.points_in),
            "clouds_out": str(s.clouds_out), "points_out": str(s.points_out),
            "skipped_clouds": str(s.skipped), "not_corrected_points": str(s.not_corrected),
            "dropped_clouds": str(s.dropped),
            "queued_mib": f"{self._waiting.bytes / 2**20:.1f}",
            "latency_p50_s": f"{p50:.4f}", "latency_p99_s": f"{p99:.4f}",
            "queued_clouds": str(len(self._waiting)), "held_clouds": str(len(self._held)),
            "estimate_source": self.estimate_source, "transport": self.transport,
            "incidence": self.settings.radiometry.incidence_rule,
            "poses_left_out": str(self.trajectory.left_out),
            "clock_steps_back": str(steps),
            "heading": describe_heading_policy(heading_source,
                                               self.trajectory.oriented_samples > 0),
            "model": describe_model_policy(self.settings.model, self.trajectory.trajectory(),
                                           heading_source=heading_source)})

    def close(self) -> None:
        """Stop the worker; held clouds are corrected and published first."""
        with self._lock:
            self._closing = True
            self._lock.notify_all()
        self._worker.join(timeout=5.0)
        try:
            self._sync()
            self.runner.close()
        except Exception as exc:  # shutting down
            logger.error("flushing held clouds failed: %s", exc)

    # -- the worker ------------------------------------------------------------------------
    def _start_runner(self) -> CorrectionProcess | LocalCorrection:
        o = self.options
        options = ServiceOptions(batch_points=o.batch_points, workers=o.workers,
                                 lookahead=o.lookahead, source=self.config["topics.points"],
                                 trajectory_keep_s=o.trajectory_buffer_s,
                                 ring_bytes=o.shared_memory_mib << 20, sensor=self.sensor)
        if o.separate_process:
            try:
                return CorrectionProcess(self.settings, options, on_result=self._on_result,
                                         on_error=self._on_error, on_failure=self._on_failure)
            except OSError as exc:  # no process can be started here: correct in a thread
                logger.warning("correction process not started (%s); correcting in a thread "
                               "of this node", exc)
        return LocalCorrection(self.settings, options, on_result=self._on_result,
                               on_error=self._on_error, warm=True)

    def _on_failure(self, reason: str) -> None:
        logger.error("corrector: %s; restarting it", reason)

    def _work(self) -> None:
        while True:
            with self._lock:
                if self._closing:
                    return
                self._drop_over_backlog()
                clouds = list(self._waiting)
                poses_waiting = len(self._poses_t)
            try:
                self.runner.poll()
                if poses_waiting > POSES_PER_HANDOVER:  # (no clouds for a while)
                    self._sync()
                progressed = self._step(clouds)
            except Exception as exc:  # never let the worker die
                logger.error("corrector: unexpected error: %s", exc)
                progressed = False
            if not progressed:
                with self._lock:
                    if not self._closing:
                        self._lock.wait(timeout=self._idle_timeout())

    def _drop_over_backlog(self) -> None:
        """Drop the oldest waiting clouds while more than ``max_backlog_mib`` wait (the
        worker is the only one to take from the queue; called with the lock held)."""
        limit = int(self.options.max_backlog_mib) << 20
        dropped, dropped_bytes = self._waiting.drop_oldest(limit)
        if not dropped:
            return
        self.stats.dropped += dropped
        self.stats.dropped_bytes += dropped_bytes
        self._throttled.log(
            logging.WARNING, _LOG_EVERY_S,
            f"backlog above max_backlog_mib ({limit >> 20} MiB): dropped the {dropped} oldest "
            f"waiting clouds ({dropped_bytes / 2**20:.0f} MiB; {self.stats.dropped} so far)")

    def _idle_timeout(self) -> float:
        """How long the worker may wait for a notification (a cloud, or a trajectory sample
        while a cloud waits for the trajectory) before it must look again itself: to
        collect the batches of worker threads in this process, to release held clouds after
        ``flush_timeout_s`` without a new one, to give up on a trajectory that stopped, or to
        hand on samples piling up without clouds. Called with the lock held."""
        if isinstance(self.runner, LocalCorrection) and self.runner.in_flight:
            return 0.005
        timeout = 0.25
        if self._waiting:
            timeout = 0.05  # (max_trajectory_wait_s is seconds)
        if self._held and self._released_tag != self._next_tag:
            due = self._last_push + self.options.flush_timeout_s - time.monotonic()
            timeout = min(timeout, max(due, 0.001))
        return timeout

    def _parse(self, cloud: WaitingCloud) -> bool:
        source = self.config["topics.points"]
        try:
            parsed = parse_cloud(cloud.raw, source=source)
            traj_frame = self.trajectory.frame_id
            if self.sensor is not None:
                if traj_frame is not None and traj_frame != self.sensor.map_frame:
                    raise LidarcalError(f"{source}: the trajectory is in '{traj_frame}', not "
                                        f"in frame_id '{self.sensor.map_frame}'")
                if parsed.frame_id != self.sensor.extrinsic.child:
                    raise LidarcalError(f"{source}: cloud in frame '{parsed.frame_id}'; the "
                                        "calibration's extrinsic block is the mounting of "
                                        f"'{self.sensor.extrinsic.child}'")
                _, t, _ = self._times.decode(parsed.points, ns_to_seconds(parsed.stamp_ns),
                                             source=source)
                _, t_max = time_span(t)
                # the poses are looked up at the true times (a timing bias below 0: later)
                t_max -= self.sensor.extrinsic.time_offset_s
            else:
                if traj_frame is not None and parsed.frame_id != traj_frame:
                    raise LidarcalError(f"{source}: cloud in frame '{parsed.frame_id}' but "
                                        f"the trajectory is in '{traj_frame}'")
                tname = resolve_time_field(parsed.points, self.settings.time_field,
                                           source=source)
                _, t_max = time_span(parsed.points[tname])
            cloud.t_max = t_max if math.isfinite(t_max) else -math.inf
        except LidarcalError as exc:
            cloud.release()
            self._skip(str(exc))
            return False
        cloud.parsed, cloud.n_points = True, len(parsed.points)
        return True

    def _skip(self, reason: str) -> None:
        self.stats.skipped += 1
        self.stats.last_error = reason
        self._throttled.log(logging.ERROR, _LOG_EVERY_S, f"malformed cloud skipped: {reason}")

    def _step(self, clouds: list[WaitingCloud]) -> bool:
        """Hand the clouds that the trajectory covers to the correction, in order; returns
        whether anything was done.

        All the clouds ready at once go together: under a backlog their normals are
        evaluated in one pass (fewer, larger numpy calls catch up faster); with one cloud
        ready this is the one-cloud-at-a-time path.
        """
        ready, done = take_ready(clouds, self.trajectory.end, self.trajectory.last_arrival,
                                 time.monotonic(), self.options.max_trajectory_wait_s,
                                 self._parse)
        if ready:
            self._push(ready)
        with self._lock:
            self._waiting.pop_oldest(done)
            empty = not self._waiting
        if (empty and self._held and self._released_tag != self._next_tag
                and time.monotonic() - self._last_push >= self.options.flush_timeout_s):
            # No new cloud for a while (a pause, the end of a strip): correct what is held
            # without waiting for look-ahead, with the trajectory received up to now.
            self._released_tag = self._next_tag
            self._sync()
            self.runner.release()
            return True
        return done > 0

    def _sync(self) -> None:
        """Give the correction the new trajectory samples, settings and switches, in the
        order they came (a new estimate applies from the next cloud on)."""
        with self._lock:
            t, xyz, orientation = self._poses_t, self._poses_xyz, self._poses_q
            self._poses_t, self._poses_xyz, self._poses_q = [], [], []
            settings = self.settings if self._settings_changed else None
            lookahead_changed, keep_changed = self._lookahead_changed, self._keep_changed
            self._settings_changed = self._lookahead_changed = self._keep_changed = False
        if isinstance(self.runner, CorrectionProcess) and not self.runner.alive:
            # it died (reported by _on_failure): a new one, with the whole trajectory kept
            self.runner = self._start_runner()
            whole = self.trajectory.trajectory()
            self.runner.poses(whole.t, whole.xyz, whole.orientation)
        elif t:
            self.runner.poses(np.asarray(t, dtype=np.float64),
                              np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
                              np.asarray(orientation, dtype=np.float64).reshape(-1, 4))
        if settings is not None:
            self.runner.set_settings(settings)
        if lookahead_changed:
            self.runner.set_lookahead(self.options.lookahead)
        if keep_changed:
            self.runner.set_trajectory_keep(self.options.trajectory_buffer_s)

    def _push(self, clouds: list[WaitingCloud]) -> None:
        started = time.perf_counter()
        self._sync()
        tagged: list[tuple[int, bytes | memoryview, Region | None]] = []
        with self._lock:
            for cloud in clouds:
                tag = self._next_tag
                self._next_tag += 1
                self._held[tag] = cloud
                tagged.append((tag, cloud.raw, cloud.region))
                cloud.raw, cloud.region = b"", None  # the correction has it now
                self.stats.clouds_in += 1
                self.stats.points_in += cloud.n_points
        runner = self.runner
        if isinstance(runner, CorrectionProcess):  # (a region of its ring: not copied)
            runner.push([(tag, region if isinstance(region, InboundRegion) else raw)
                         for tag, raw, region in tagged])
        else:
            runner.push([(tag, raw) for tag, raw, _ in tagged])
        self._last_push = time.monotonic()
        self.stats.busy_s += time.perf_counter() - started

    def _on_result(self, tag: int, cdr: bytes | memoryview, points: int, not_corrected: int,
                   _seconds: float) -> None:
        """A corrected cloud (from the correction's reader thread, or inline): published."""
        with self._lock:
            cloud = self._held.pop(tag, None)
        if cloud is None:
            return
        started = time.perf_counter()
        self._publish(cdr)
        self.stats.busy_s += time.perf_counter() - started
        self.stats.clouds_out += 1
        self.stats.points_out += points
        self.stats.not_corrected += not_corrected
        self.stats.latencies.append(time.monotonic() - cloud.received)

    def _on_error(self, tag: int, reason: str) -> None:
        """A cloud the correction refused (malformed) or lost: logged and skipped."""
        with self._lock:
            cloud = self._held.pop(tag, None)
        if cloud is None:
            return
        self.stats.clouds_in -= 1
        self.stats.points_in -= cloud.n_points
        self._skip(reason)


def _fixed_biases(config: FlightConfig) -> np.ndarray:
    """The configuration's ``calibration.fixed.*`` biases (docs/method.md order, SI)."""
    return np.array([config[f"calibration.fixed.{n}"] for n in PARAMETER_NAMES])
