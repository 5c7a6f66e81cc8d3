"""``lidarcal correct``: every cloud of a mission bag corrected into a bag or a LAS/LAZ file.

:func:`correct_bag` does it and returns a :class:`CorrectionReport`; how it reads the bag once
and what it writes: docs/correction.md, "``lidarcal correct`` on a bag".
"""

from __future__ import annotations

import contextlib
import functools
import heapq
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.core.georeferencing.heading import check_orientation
from lidarcal_ros.core.georeferencing.rigorous import check_model_setting
from lidarcal_ros.core.jit import start_without_blas
from lidarcal_ros.core.mission import MAX_COORDINATE_M, Trajectory
from lidarcal_ros.core.radiometry import describe_alpha
from lidarcal_ros.core.trajectory.strip_errors import (
    POSE_BEYOND_STRIPS,
    TrajectoryCorrection,
    trajectory_corrections,
)
from lidarcal_ros.errors import BagError, InputError, LidarcalError, one_line
from lidarcal_ros.io.bag.prefetch import WriteBehind, prefetched
from lidarcal_ros.io.calibration_file import CalibrationRecord, read_calibration
from lidarcal_ros.io.cloud.columns import resolve_time_field
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array, make_point_dtype
from lidarcal_ros.io.url_cache import source_of
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.corrected_cloud import CorrectionStats
from lidarcal_ros.pipeline.correction.stream import DEFAULT_BATCH_POINTS, StreamCorrector
from lidarcal_ros.pipeline.correction.trajectory_gate import RereadBag, TrajectoryGate

__all__ = [
    "FOREIGN_OUTPUT_SUFFIXES", "LAS_RUN_POINTS", "CorrectOptions", "CorrectionReport",
    "correct_bag", "is_sbet_output", "output_kind",
    "warm_up_compiled_loops",
]

if TYPE_CHECKING:
    from lidarcal_ros.io.survey.las_writer import LasStats
    from lidarcal_ros.pipeline.executor import Executor

logger = logging.getLogger(__name__)

#: Points per LAS write (corrected clouds are gathered into runs of this size).
LAS_RUN_POINTS = 100_000
#: Fewest points held waiting for the trajectory before a bag is read again, trajectory first
#: (:attr:`CorrectOptions.max_held_points`; some 40 MB of clouds).
MIN_HELD_POINTS = 1_000_000

@dataclass
class CorrectionReport:
    """What :func:`correct_bag` did."""

    output: Path
    kind: str
    stats: CorrectionStats
    passthrough_messages: int = 0
    las_skipped_non_finite: int = 0
    seconds: float = 0.0
    frame_id: str = ""
    atmosphere: str = ""
    reflectance: str = ""
    #: What was written of the corrected trajectory ('' where nothing).
    trajectory: str = ""
    warnings: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        """A short human-readable summary."""
        s = self.stats
        rate = s.points / self.seconds if self.seconds > 0 else math.nan
        out = [f"corrected {s.points} points in {s.clouds} clouds -> {self.output} "
               f"({self.kind}, {self.seconds:.1f} s, {rate / 1e6:.2f} M points/s)"]
        if self.kind == "bag":
            out.append(f"passed through {self.passthrough_messages} other messages")
        out.append(self.atmosphere)
        out.append("model: " + s.describe_models())
        if self.reflectance:
            out.append(f"reflectance: {self.reflectance}")
        out.append("incidence: " + s.describe_incidence())
        out.append(f"grazing incidence (clamped): {s.grazing}; rough surface: {s.rough}; "
                   f"volume (canopy) returns: {s.volume}; "
                   f"no normal: {s.no_normal}; not corrected (trajectory): {s.not_corrected}; "
                   f"without intensity: {s.no_intensity}")
        if self.trajectory:
            out.append(f"corrected trajectory: {self.trajectory}")
        out.extend(f"warning: {w}" for w in self.warnings)
        return out


#: Suffixes of point, text and archive formats that ``lidarcal correct`` does not write: an
#: output named so is refused rather than written as a rosbag2 directory of that name.
FOREIGN_OUTPUT_SUFFIXES = frozenset({
    ".asc", ".bag", ".csv", ".db3", ".e57", ".gz", ".h5", ".json", ".npy", ".npz", ".pcd",
    ".ply", ".pts", ".tif", ".tiff", ".txt", ".xyz", ".yaml", ".yml", ".zip",
})


def output_kind(path: str | Path) -> str:
    """``las`` for ``.las``/``.laz``, else ``bag`` (``.mcap`` file or rosbag2 directory).

    Raises
    ------
    InputError
        A suffix of :data:`FOREIGN_OUTPUT_SUFFIXES` (``out.txt``, ``out.ply``, ...): a format
        lidarcal does not write.
    """
    suffix = Path(path).suffix.lower()
    if suffix in FOREIGN_OUTPUT_SUFFIXES:
        raise InputError(f"{path}: lidarcal correct does not write {suffix} files; name the "
                         "output .las or .laz (LAS 1.4), .mcap, or a directory for a rosbag2 "
                         "bag")
    return "las" if suffix in (".las", ".laz") else "bag"


def _pose_reader(bag: Any, topic: str, samples: Any) -> Callable[[str, Any], None]:
    """``add(msgtype, raw)``: a trajectory message's CDR bytes into ``samples``
    (:class:`~lidarcal_ros.io.cloud.trajectory_messages.TrajectorySamples`), refusing another
    type."""
    from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES

    decode = functools.partial(bag.deserialize, topic=topic)

    def add(msgtype: str, raw: Any) -> None:
        if msgtype not in TRAJECTORY_TYPES:
            raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
        samples.add_raw(msgtype, raw, decode)

    return add


def _whole_trajectory(bag: Any, topic: str, samples: Any) -> Trajectory:
    if not samples:
        raise BagError(f"{bag.path}: topic {topic} has no messages")
    return samples.trajectory(f"{bag.path}: trajectory {topic}")


def _checked_trajectory(bag: Any, topic: str, samples: Any,
                        settings: CorrectionSettings) -> tuple[Trajectory, str]:
    """The whole trajectory of ``samples`` and its frame, refused as :func:`correct_bag`
    refuses it (several frames, no orientation where the settings need one)."""
    trajectory = _whole_trajectory(bag, topic, samples)
    if len(samples.frames) > 1:
        raise InputError(f"{bag.path}: poses on {topic} are in several frames: "
                         f"{sorted(samples.frames)}")
    check_orientation(settings.heading_source, trajectory, f"{bag.path}: {topic}")
    check_model_setting(settings.model, trajectory, f"{bag.path}: {topic}")
    return trajectory, next(iter(samples.frames))


@dataclass(frozen=True)
class CorrectOptions:
    """How :func:`correct_bag` writes and works.

    Attributes
    ----------
    crs : pyproj.CRS or None
        CRS of the map frame, written into LAS output (ignored, with a warning, for bags).
    overwrite : bool
        Replace an existing output.
    batch_points : int
        Points corrected together (memory is about 1 kB per point of batch).
    workers : int
        Batches corrected in parallel (reading and writing stay in the calling thread:
        they are mostly Python code, and threads of their own only contend for the
        interpreter lock).
    max_held_points : int or None
        Most points of clouds held while the trajectory read so far does not cover them
        (the bag read once); beyond, the bag is read again with its trajectory first (its
        trajectory comes after its clouds). None: ``4 * batch_points``, at least
        :data:`MIN_HELD_POINTS`; 0: always the trajectory first (two passes). The output
        is the same.
    trajectory_out : Path or None
        Also write the corrected trajectory here (``overwrite`` applies to it too): an
        Applanix SBET where it ends in ``.out`` or ``.sbet`` (needs ``crs``:
        :func:`~lidarcal_ros.io.survey.trajectory_crs.write_sbet_trajectory`), else ASCII
        ``time,x,y,z[,roll,pitch,heading]``
        (:func:`~lidarcal_ros.io.survey.trajectory_files.write_ascii_trajectory`); the
        delivered one, with a warning, where the calibration holds no trajectory errors.
    """

    crs: Any = None
    overwrite: bool = False
    batch_points: int = DEFAULT_BATCH_POINTS
    workers: int = 1
    max_held_points: int | None = None
    trajectory_out: Path | None = None

    @property
    def held_points_bound(self) -> int:
        """:attr:`max_held_points`, None resolved."""
        if self.max_held_points is not None:
            return max(int(self.max_held_points), 0)
        return max(4 * self.batch_points, MIN_HELD_POINTS)


def _sensor_frame(bag: str | Path, record: CalibrationRecord, points_topic: str,
                  trajectory_topic: str, map_frame: str) -> str | None:
    """The sensor's frame of clouds in it (docs/method.md section 12), None for map-frame
    clouds; refused in one line where the calibration holds no mounting of it."""
    from lidarcal_ros.io.bag.sensor_bag import sensor_frame_of
    from lidarcal_ros.pipeline.correction.sensor_frame import sensor_extrinsic

    frame = sensor_frame_of(bag, points_topic=points_topic, trajectory_topic=trajectory_topic,
                            map_frame=map_frame)
    if frame is not None:
        sensor_extrinsic(record, frame, where=f"{bag}: {points_topic}")
    return frame


def correct_bag(
    bag_path: str | Path,
    calibration: str | Path | CalibrationRecord,
    output: str | Path,
    config: FlightConfig | None = None,
    options: CorrectOptions = CorrectOptions(),  # (frozen: shared safely)
    *,
    progress: Callable[[str, float], None] | None = None,
    executor: Executor | None = None,
) -> CorrectionReport:
    """Correct every cloud of a mission bag; write a bag or a LAS/LAZ file.

    Parameters
    ----------
    bag_path : path
        rosbag2 directory or ``.mcap`` with the topics of ``config``.
    calibration : path or CalibrationRecord
        Calibration file of docs/interface.md.
    output : path
        ``.las``/``.laz``: LAS 1.4 point format 6 (:mod:`lidarcal_ros.io.survey.las_writer`);
        otherwise a rosbag2 bag (bare MCAP for ``.mcap``) with the corrected clouds on
        ``topics.corrected`` and every input message passed through unchanged.
    config : FlightConfig, optional
        Defaults when None.
    options : CorrectOptions
    progress : callable(stage, fraction), optional
    executor : Executor, optional
        Correct the clouds in parts there (``--dask``: :mod:`lidarcal_ros.pipeline.correction.
        parts`; the same output); None: in this process, the bag read once where it can be.

    Returns
    -------
    CorrectionReport

    Raises
    ------
    BagError, CloudFormatError, InputError, ConfigError, TrajectoryError
        One line naming the file, topic or field at fault.
    """
    from lidarcal_ros.io.bag.reader import open_bag

    started = time.perf_counter()
    # The compiled loops load while the bag is read (their first call in a process costs
    # some 0.5 s; reading is mostly decompression, which leaves the interpreter free).
    warm_up = threading.Thread(target=warm_up_compiled_loops, name="lidarcal-warm-up",
                               daemon=True)
    warm_up.start()
    config = config or FlightConfig()
    record = (calibration if isinstance(calibration, CalibrationRecord)
              else read_calibration(calibration))
    settings = CorrectionSettings.from_config(config, record)
    out_path = Path(output)
    kind = output_kind(out_path)
    points_topic = config["topics.points"]
    traj_topic = config["topics.trajectory"]
    corrected_topic = config["topics.corrected"]
    # (written where there is something to correct it by)
    moved_topic = (str(config["topics.trajectory_corrected"])
                   if kind == "bag" and record.trajectory is not None else None)
    bag_path = source_of(bag_path)  # (a URL as given: each process reading it fetches it)
    inputs = [bag_path.resolve()] if isinstance(bag_path, Path) else []
    if out_path.resolve() in inputs:
        raise InputError(f"{out_path}: output would overwrite the input bag")
    sensor = _sensor_frame(bag_path, record, points_topic, traj_topic, config["frame_id"])
    if sensor is not None and options.trajectory_out is not None:
        raise InputError(f"--trajectory-out {options.trajectory_out}: not written for clouds "
                         f"in the sensor's frame '{sensor}' (the bag's trajectory is already "
                         "the INS's)")
    if options.trajectory_out is not None and Path(options.trajectory_out).resolve() in (
            *inputs, out_path.resolve()):
        raise InputError(f"{options.trajectory_out}: the trajectory output would overwrite "
                         "the input bag or the corrected output")
    warnings: list[str] = []
    sbet_out = options.trajectory_out is not None and is_sbet_output(options.trajectory_out)
    if sbet_out and options.crs is None:
        raise InputError(f"--trajectory-out {options.trajectory_out}: an SBET needs the map's "
                         "CRS; give --crs EPSG:...")
    if sbet_out:
        from lidarcal_ros.io.survey.trajectory_crs import check_map_crs

        check_map_crs(options.crs, where="--crs")
    if options.crs is not None and kind == "bag" and not sbet_out:
        warnings.append("--crs applies to LAS/LAZ output and an SBET --trajectory-out only; "
                        "ignored for a bag")
        logger.warning("%s", warnings[-1])

    with open_bag(bag_path) as bag:
        _check_topics(bag, points_topic, traj_topic,
                      corrected_topic if kind == "bag" else None, moved_topic)
        request = _Request(settings, config, options, out_path,
                           (points_topic, traj_topic, corrected_topic), moved_topic, progress,
                           warnings, warm_up, None if sensor is None else record)
        run = functools.partial(_correct_once, bag, request)
        report = None
        if sensor is not None:
            # (the trajectory first: the sensor's origin needs the poses around each cloud)
            if executor is not None:
                warnings.append("clouds in the sensor's frame are corrected in this process "
                                "(not in parts)")
                logger.warning("%s", warnings[-1])
        elif executor is not None:
            from lidarcal_ros.pipeline.correction.parts import correct_in_parts

            report = correct_in_parts(bag, request, executor)
        elif options.held_points_bound:
            try:
                report = run(single_pass=True)
            except (RereadBag, LidarcalError) as exc:
                # An error is raised again by the second pass, after what reading the
                # trajectory first finds wrong: the same error as always.
                logger.info("%s: reading the bag again, trajectory first (%s)", bag_path,
                            one_line(exc))
        if report is None:
            report = run(single_pass=False)
    _warn_of_what_was_left(report, bag_path, options.crs)
    report.seconds = time.perf_counter() - started
    return report


@dataclass(frozen=True)
class _Request:
    """What :func:`correct_bag` was asked, checked: the settings, the output, the topics
    (clouds, trajectory, corrected clouds; the corrected trajectory's, None where it is not
    written), the warnings so far and the warm-up thread."""

    settings: CorrectionSettings
    config: FlightConfig
    options: CorrectOptions
    out_path: Path
    topics: tuple[str, str, str]
    moved_topic: str | None
    progress: Callable[[str, float], None] | None
    warnings: list[str]
    warm_up: threading.Thread
    #: The calibration of clouds in the sensor's frame (None: map-frame clouds).
    sensor: CalibrationRecord | None = None


def _correct_once(bag: Any, request: _Request, *, single_pass: bool) -> CorrectionReport:
    """:func:`correct_bag` after its checks: the trajectory read first, or (``single_pass``)
    with the clouds; RereadBag where one pass cannot give the result of two."""
    from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples

    settings, options, out_path, progress = (request.settings, request.options,
                                             request.out_path, request.progress)
    points_topic, traj_topic, corrected_topic = request.topics
    kind = output_kind(out_path)
    trajectory, frame = Trajectory(np.zeros(0), np.zeros((0, 3))), ""
    samples = TrajectorySamples()
    if progress:
        progress("correcting" if single_pass else "reading trajectory", 0.0)
    poses = _PoseMessages() if request.moved_topic is not None else None
    if not single_pass:
        add = _pose_reader(bag, traj_topic, samples)
        for _topic, msgtype, ns, raw in prefetched(lambda: bag.messages([traj_topic])):
            add(msgtype, raw)
            if poses is not None:
                poses.add(ns, msgtype, raw)
        trajectory, frame = _checked_trajectory(bag, traj_topic, samples, settings)
    decode: _CloudDecoder = _cloud_points
    if request.sensor is not None:
        trajectory, settings, decode = _sensor_clouds(bag, request, trajectory, frame, settings)
    settings, meaning = radiometry_of(bag, request, settings)
    messages = _CorrectedMessages() if kind == "bag" else None
    corrector = StreamCorrector(trajectory, settings, batch_points=options.batch_points,
                                workers=options.workers, source=points_topic,
                                keep_tallies=kind == "bag",
                                place=None if messages is None else messages.place)
    source = str(bag.path)
    gate = (TrajectoryGate(corrector, samples, _pose_reader(bag, traj_topic, samples),
                           functools.partial(_checked_trajectory, bag, traj_topic, samples,
                                             settings),
                           source=source, topic=points_topic,
                           max_held_points=options.held_points_bound)
            if single_pass else
            TrajectoryGate.known(corrector, frame, source=source, topic=points_topic))
    n_clouds = max(bag.topics[points_topic].count, 1)
    report = CorrectionReport(out_path, kind, corrector.stats, frame_id=frame,
                              atmosphere=describe_alpha(settings.radiometry),
                              reflectance=meaning, warnings=list(request.warnings))
    job = _Job(bag, corrector, gate, out_path, points_topic, traj_topic, corrected_topic,
               options.overwrite, n_clouds, progress, report, request.moved_topic, poses,
               messages, decode)
    try:
        corrector.start()  # the workers start while the clouds are read
        if kind == "las":
            _correct_to_las(job, options.crs)
        else:
            _correct_to_bag(job)
    finally:
        corrector.close()
    report.frame_id = gate.frame or ""
    if options.trajectory_out is not None:
        _write_trajectory_file(job, Path(options.trajectory_out), options)
    return report


#: ``decode(bag, msgtype, raw, topic)``: a cloud message's bytes as ``(message, points)``,
#: the points map-frame ones (and the message's header their frame and stamp).
_CloudDecoder = Callable[[Any, str, bytes, str], tuple[Any, np.ndarray]]


def _sensor_clouds(bag: Any, request: _Request, base: Trajectory, map_frame: str,
                   settings: CorrectionSettings
                   ) -> tuple[Trajectory, CorrectionSettings, _CloudDecoder]:
    """For clouds in the sensor's frame (:mod:`lidarcal_ros.pipeline.correction.sensor_frame`):
    the corrector's trajectory (the sensor's origin), its settings and the decoder of the
    clouds into the map frame."""
    from types import SimpleNamespace

    from lidarcal_ros.io.bag.format import stamp_seconds
    from lidarcal_ros.pipeline.correction.sensor_frame import SensorFrameGeoreference

    assert request.sensor is not None
    points_topic = request.topics[0]
    where = f"{bag.path}: {points_topic}"
    frame = request.sensor.extrinsic.child if request.sensor.extrinsic else ""
    geo = SensorFrameGeoreference.from_config(request.sensor, request.config, frame,
                                              map_frame, where=where)
    origin = geo.set_trajectory(base)

    def decode(bag: Any, msgtype: str, raw: bytes, topic: str) -> tuple[Any, np.ndarray]:
        msg, points = _cloud_points(bag, msgtype, raw, topic)
        if msg.header.frame_id != frame:
            raise InputError(f"{where}: clouds in frame '{msg.header.frame_id}' and in the "
                             f"sensor's frame '{frame}'")
        cloud = geo.cloud(points, stamp_seconds(msg.header.stamp), source=where)
        if geo.decoder.reading is not None and not said:
            said.append(True)  # (said once, as lidarcal calibrate says it)
            logger.warning("%s: %s", where, geo.decoder.reading.describe())
        return SimpleNamespace(header=SimpleNamespace(stamp=msg.header.stamp,
                                                      frame_id=map_frame)), cloud

    said: list[bool] = []
    logger.info("%s: clouds in the sensor's frame '%s' georeferenced with the calibrated "
                "mounting %s -> %s and dr %+.1f mm", where, frame, geo.extrinsic.parent, frame,
                geo.range_offset_m * 1e3)
    return origin, geo.settings(settings), decode


def radiometry_of(bag: Any, request: _Request, settings: CorrectionSettings
                  ) -> tuple[CorrectionSettings, str]:
    """``settings`` with the calibration constant a reference target in ``bag`` gives (where
    the configuration names one; not in clouds in the sensor's frame), and what the
    reflectance then means."""
    meaning = settings.radiometry.meaning
    if not settings.radiometry.absolute and request.sensor is None:
        from lidarcal_ros.pipeline.correction.reflectance import (
            measure_target_in_bag,
            target_of,
            with_constant,
        )

        if target_of(request.config) is not None:
            request.warm_up.join()  # (it hides scipy.linalg a moment; the target may need it)
        target = measure_target_in_bag(bag.path, settings, request.config)
        if target is not None:
            settings = with_constant(settings, target.constant)
            meaning = f"{settings.radiometry.meaning} The {target.describe()}."
    return settings, meaning


class _PoseMessages:
    """The trajectory messages of the input as read (log time ns, type, CDR bytes), kept
    for the corrected trajectory topic (some 100 bytes a PoseStamped)."""

    def __init__(self) -> None:
        self.messages: list[tuple[int, str, bytes]] = []

    def add(self, ns: int, msgtype: str, raw: Any) -> None:
        self.messages.append((int(ns), msgtype, bytes(raw)))


def _trajectory_correction(corrector: StreamCorrector, t: np.ndarray) -> TrajectoryCorrection:
    """The error to remove from trajectory samples at ``t`` (s): the calibration's
    ``e_hat_s`` over the strips' times seen by ``corrector`` (zero without an estimate)."""
    estimate = corrector.settings.trajectory_errors
    if estimate is None:
        return TrajectoryCorrection(np.zeros((len(t), 3)),
                                    np.full(len(t), POSE_BEYOND_STRIPS, np.int8))
    return trajectory_corrections(estimate, corrector.strip_spans, t)


def _describe_correction(correction: TrajectoryCorrection, where: str) -> str:
    inside, between, beyond = correction.counts()
    moved = np.linalg.norm(correction.errors, axis=1)
    largest = float(moved.max()) * 100 if moved.size else 0.0
    return (f"{len(moved)} poses -> {where} ({inside} in a strip: its e_s(t) removed, "
            f"{between} between strips: interpolated, {beyond} before the first or after the "
            f"last strip: the nearest strip's end held; largest move {largest:.1f} cm)")


def _write_trajectory_file(job: _Job, path: Path, options: CorrectOptions) -> None:
    """The corrected trajectory of ``job`` (its whole trajectory, screened) as ASCII, or as
    an SBET (:func:`is_sbet_output`) in the geographic coordinates of ``options.crs``."""
    from lidarcal_ros.io.survey.trajectory_crs import write_sbet_trajectory
    from lidarcal_ros.io.survey.trajectory_files import write_ascii_trajectory

    trajectory = job.corrector.trajectory
    correction = _trajectory_correction(job.corrector, trajectory.t)
    moved = Trajectory(trajectory.t, trajectory.xyz - correction.errors,
                       trajectory.orientation, full_attitude=trajectory.full_attitude)
    report = job.report
    comments = [f"lidarcal corrected trajectory of {job.bag.path} ({job.trajectory_topic}), "
                f"frame '{report.frame_id}'",
                "time: the bag's clock (UNIX seconds); x, y, z: metres; roll, pitch, heading: "
                "degrees (heading clockwise from grid north)",
                "x, y, z = delivered - e_hat_s(t) (docs/method.md section 11); between strips "
                "interpolated linearly, before the first and after the last strip held"]
    if job.corrector.settings.trajectory_errors is None:
        report.warnings.append(f"{path}: the calibration holds no trajectory errors: the "
                               "trajectory is written as delivered")
        logger.warning("%s", report.warnings[-1])
        comments[-1] = "x, y, z as delivered: the calibration holds no trajectory errors"
    where = str(path)
    if is_sbet_output(path):
        _, week = write_sbet_trajectory(path, moved, options.crs, overwrite=options.overwrite)
        where = (f"{path} (SBET, {options.crs.name} to WGS 84"
                 + (f", GPS week {week}" if week is not None else "") + ")")
    else:
        write_ascii_trajectory(path, moved, comments=comments, overwrite=options.overwrite)
    text = _describe_correction(correction, where)
    report.trajectory = f"{report.trajectory}; {text}" if report.trajectory else text


def is_sbet_output(path: str | Path) -> bool:
    """``--trajectory-out`` names an SBET (``.out``, ``.sbet``), not an ASCII file."""
    return Path(path).suffix.lower() in (".out", ".sbet")


def _write_moved_poses(job: _Job, writer: Any) -> None:
    """Every trajectory message of the input again on the corrected trajectory's topic,
    its position less the error of its time, at its input's log time."""
    from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples, moved_message

    assert job.moved_topic is not None and job.poses is not None
    bag, topic = job.bag, job.trajectory_topic
    decode = functools.partial(bag.deserialize, topic=topic)
    parsed = TrajectorySamples()
    for _ns, msgtype, raw in job.poses.messages:
        parsed.add_raw(msgtype, raw, decode)
    t = np.asarray(parsed.t, dtype=np.float64)
    xyz = np.asarray(parsed.xyz, dtype=np.float64).reshape(-1, 3)
    correction = _trajectory_correction(job.corrector, t)
    moved = xyz - correction.errors
    msgdef = bag.topics[topic].msgdef or None
    encode = bag.typestore.serialize_cdr
    for k, (ns, msgtype, raw) in enumerate(job.poses.messages):
        if not np.isfinite(moved[k]).all():  # (a pose the trajectory left out: as it came)
            out = raw
        else:
            out = moved_message(msgtype, raw, (float(moved[k, 0]), float(moved[k, 1]),
                                               float(moved[k, 2])), decode, encode)
        writer.write_raw(job.moved_topic, msgtype, ns, out, msgdef=msgdef)
    job.report.trajectory = _describe_correction(correction, job.moved_topic)


def _check_topics(bag: Any, points_topic: str, trajectory_topic: str,
                  corrected_topic: str | None, moved_topic: str | None = None) -> None:
    """Refuse a bag without the clouds or the trajectory (or with them of the wrong type or
    empty), or one that already holds ``corrected_topic`` or ``moved_topic``."""
    from lidarcal_ros.io.bag.format import POINTCLOUD2
    from lidarcal_ros.io.cloud.trajectory_messages import TRAJECTORY_TYPES

    for topic, types in ((points_topic, (POINTCLOUD2,)),
                         (trajectory_topic, tuple(TRAJECTORY_TYPES))):
        if topic not in bag.topics:
            raise BagError(f"{bag.path}: topic {topic} not found; topics present: "
                           f"{', '.join(bag.topics) or 'none'}")
        got = bag.topics[topic].msgtype
        if got not in types:
            raise BagError(f"{bag.path}: topic {topic} has type {got}; expected "
                           f"{' or '.join(types)}")
        if bag.topics[topic].count == 0:
            raise BagError(f"{bag.path}: topic {topic} has no messages")
    for new in (corrected_topic, moved_topic):
        if new is not None and new in bag.topics:
            raise BagError(f"{bag.path}: already has topic {new}; a corrected bag cannot "
                           "be corrected again into the same topic")
    if moved_topic is not None and moved_topic in (points_topic, trajectory_topic,
                                                   corrected_topic):
        raise BagError(f"{bag.path}: the corrected trajectory's topic {moved_topic} is "
                       "another input or output topic")


def _warn_of_what_was_left(report: CorrectionReport, bag_path: str | Path, crs: Any) -> None:
    """The report's (and the log's) warnings of points left uncorrected or without
    reflectance, and of a LAS/LAZ file without a CRS."""
    s, kind, out_path = report.stats, report.kind, report.output
    if s.not_corrected > s.non_finite:
        report.warnings.append(
            f"{s.not_corrected - s.non_finite} of {s.points} points not covered by the "
            "trajectory (or not below it): left uncorrected, flagged "
            f"{FLAG_NOT_CORRECTED} in correction_flags")
        logger.warning("%s: %s", bag_path, report.warnings[-1])
    if s.non_finite and kind == "bag":
        report.warnings.append(
            f"{s.non_finite} of {s.points} points with a non-finite x, y or z (or one beyond "
            f"{MAX_COORDINATE_M:g} m): passed on as "
            f"delivered, flagged {FLAG_NOT_CORRECTED} in correction_flags")
        logger.warning("%s: %s", bag_path, report.warnings[-1])
    if s.no_intensity:
        report.warnings.append(f"{s.no_intensity} points without intensity: reflectance NaN")
    if crs is None and kind == "las":
        report.warnings.append("written without a CRS: the LAS/LAZ file does not say where "
                               "its map frame is (give it with --crs, e.g. --crs EPSG:32633)")
        logger.warning("%s: %s", out_path, report.warnings[-1])


def _cloud_points(bag: Any, msgtype: str, raw: bytes, topic: str) -> tuple[Any, np.ndarray]:
    from lidarcal_ros.io.bag.format import POINTCLOUD2

    if msgtype != POINTCLOUD2:
        raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
    # (through a memoryview: rosbags would copy bytes to cut off their CDR header)
    msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
    return msg, cloud_to_array(msg, source=topic)


@dataclass(frozen=True)
class _Job:
    """One :func:`correct_bag`: what its LAS and its bag writer share.

    Attributes
    ----------
    bag : AnyReader-like
        The open input bag (:func:`lidarcal_ros.io.bag.reader.open_bag`).
    corrector : StreamCorrector
    gate : TrajectoryGate
        Hands each cloud to the corrector once the trajectory covers it (and checks its
        frame); reads the trajectory messages (:attr:`TrajectoryGate.reading`).
    out_path : Path
        The output file or directory.
    points_topic, trajectory_topic, corrected_topic : str
        The input clouds' topic, the trajectory's, and the corrected clouds' (bag output).
    overwrite : bool
        Replace an existing output.
    n_clouds : int
        Clouds on ``points_topic`` (for ``progress``).
    progress : callable(stage, fraction) or None
    report : CorrectionReport
        Filled in as the clouds are written.
    moved_topic : str or None
        The corrected trajectory's topic (bag output; None: not written).
    poses : _PoseMessages or None
        The trajectory messages read so far (where ``moved_topic`` is written).
    messages : _CorrectedMessages or None
        Where the corrected clouds are built (bag output; the corrector's placer).
    """

    bag: Any
    corrector: StreamCorrector
    gate: TrajectoryGate
    out_path: Path
    points_topic: str
    trajectory_topic: str
    corrected_topic: str
    overwrite: bool
    n_clouds: int
    progress: Callable[[str, float], None] | None
    report: CorrectionReport
    moved_topic: str | None = None
    poses: _PoseMessages | None = None
    messages: _CorrectedMessages | None = None
    decode: _CloudDecoder = _cloud_points

    @property
    def cloud_topics(self) -> list[str]:
        """The topics read for the correction: the clouds, and the trajectory where the gate
        reads it as it comes."""
        return ([self.points_topic, self.trajectory_topic] if self.gate.reading
                else [self.points_topic])


def _correct_to_las(job: _Job, crs: Any) -> None:
    """Correct the clouds of ``job`` into a LAS/LAZ file (``crs``: pyproj.CRS or None)."""
    from lidarcal_ros.io.survey.las_writer import LasChunkWriter

    bag, corrector, gate, out_path, points_topic = (job.bag, job.corrector, job.gate,
                                                    job.out_path, job.points_topic)
    progress, report = job.progress, job.report

    seen = 0
    time_field: str | None = None
    # The runs are compressed (lazrs, which releases the interpreter lock) in a thread of
    # their own while this one reads, decodes and corrects the next clouds.
    with LasChunkWriter(out_path, time_field=corrector.settings.time_field, crs=crs,
                        overwrite=job.overwrite,
                        reflectance_description=corrector.settings.radiometry.las_description,
                        ) as writer, WriteBehind(_write_parts(writer),
                                                 name="lidarcal-las") as write_run:
        runs = LasRuns(write_run)
        topics = job.cloud_topics
        for topic, msgtype, _ns, raw in prefetched(lambda: bag.messages(topics)):
            if topic != points_topic:
                gate.pose(msgtype, raw)
                continue
            msg, points = job.decode(bag, msgtype, raw, topic)
            if time_field is None and len(points):
                time_field = resolve_time_field(points, corrector.settings.time_field,
                                                source=topic)
                writer.time_field = time_field
            for _tag, ready in gate.cloud(None, msg, points):
                runs.add(corrector.push(ready, None))
            seen += 1
            if progress and seen % 50 == 0:
                progress("correcting", seen / job.n_clouds)
        for _tag, ready in gate.finish():
            runs.add(corrector.push(ready, None))
        runs.add(corrector.flush(), final=True)
        write_run.finish()
        _check_something_corrected(corrector.stats, bag.path, points_topic)
    las_warnings(report, writer.stats, out_path)


def _write_parts(writer: Any) -> Callable[[list[np.ndarray]], None]:
    """``write(parts)``: a run of corrected clouds into the LAS ``writer``, as one chunk."""

    def write_parts(parts: list[np.ndarray]) -> None:
        writer.write(np.concatenate(parts) if len(parts) > 1 else parts[0])

    return write_parts


class LasRuns:
    """Corrected clouds gathered into runs for a LAS/LAZ writer: a run ends at the first
    cloud that brings it to :data:`LAS_RUN_POINTS` (or at a change of layout), whichever
    batches the clouds came back in, so that the file's chunks (and laspy's extra-bytes
    minima and maxima, which it takes per write) are the same on every run."""

    def __init__(self, write_run: Callable[[list[np.ndarray]], None]) -> None:
        self._write_run = write_run
        self._run: list[np.ndarray] = []
        self._points = 0

    def add(self, done: list[tuple[Any, np.ndarray]], *, final: bool = False) -> None:
        """Add the corrected clouds ``done`` (``(tag, array)``, in order); ``final``: write
        what is left too."""
        for _tag, corrected in done:
            if self._run and corrected.dtype != self._run[0].dtype:
                self._flush()
            self._run.append(corrected)
            self._points += len(corrected)
            if self._points >= LAS_RUN_POINTS:
                self._flush()
        if self._run and final:
            self._flush()

    def _flush(self) -> None:
        self._write_run(self._run)
        self._run, self._points = [], 0


def las_warnings(report: CorrectionReport, stats: LasStats, out_path: Path) -> None:
    """The report's warnings of points a LAS/LAZ writer could not store (``stats``: its
    counts)."""
    report.las_skipped_non_finite = stats.skipped_non_finite
    for count, why in ((stats.skipped_non_finite, "with non-finite coordinates (or one "
                        f"beyond {MAX_COORDINATE_M:g} m as delivered)"),
                       (stats.skipped_out_of_range, "more than 2147 km from the others "
                        "(beyond LAS's 32-bit coordinates)")):
        if count:
            report.warnings.append(f"{count} points {why} cannot be stored in LAS: skipped")
            logger.warning("%s: %s", out_path, report.warnings[-1])


def _check_something_corrected(stats: CorrectionStats, bag_path: Path, topic: str) -> None:
    """Refuse a correction without a single finite point (every cloud empty, or every point
    non-finite): there is no result, and the output is not kept."""
    if stats.points == 0:
        raise InputError(f"{bag_path}: all {stats.clouds} clouds on {topic} are empty; "
                         "nothing to correct")
    if stats.non_finite == stats.points:
        raise InputError(f"{bag_path}: all {stats.points} points on {topic} have a non-finite "
                         "x, y or z; nothing to correct")


class _CorrectedMessages:
    """The corrected clouds of a bag output, each built in the bytes of its message (the
    input's header, then the points, 8-byte aligned, then ``is_dense``), which the writer
    then copies once; keyed by the cloud's input sequence number."""

    def __init__(self) -> None:
        self._clouds: dict[int, tuple[int, Any]] = {}  # log time ns, input message
        self._messages: dict[int, np.ndarray] = {}

    def hold(self, k: int, ns: int, msg: Any) -> None:
        """Cloud ``k`` (log time ``ns``, the decoded input ``msg``) went to the correction."""
        self._clouds[k] = (ns, msg)

    def place(self, k: int, n: int, dtype: np.dtype[Any]) -> np.ndarray:
        """The points of cloud ``k`` (``n`` of ``dtype``), a view into the bytes of its
        corrected message, which this allocates (called from the corrector's threads)."""
        from lidarcal_ros.io.cloud.messages import cloud_header_cdr, stamp_ns
        from lidarcal_ros.io.cloud.pointcloud import point_fields

        _ns, msg = self._clouds[k]
        head = cloud_header_cdr(stamp_ns(msg.header.stamp), msg.header.frame_id,
                                point_fields(dtype), dtype.itemsize, n)
        pad = (-len(head)) % 8
        size = len(head) + n * dtype.itemsize + 1
        buf = np.empty(pad + size, dtype=np.uint8)
        buf[pad:pad + len(head)] = np.frombuffer(head, dtype=np.uint8)
        self._messages[k] = buf[pad:]
        return buf[pad + len(head):pad + size - 1].view(dtype)

    def release(self, k: int, dense: bool) -> tuple[int, np.ndarray]:
        """Cloud ``k``'s log time and finished message bytes (``is_dense`` set), let go."""
        ns, _msg = self._clouds.pop(k)
        message = self._messages.pop(k)
        message[-1] = dense
        return ns, message


class _OrderedOutput:
    """The output bag's messages in the input's (log-time) order.

    Messages are queued by (input sequence number, 0 passed through / 1 corrected): passed
    through ones are ready at once, corrected clouds when their batch comes back; whatever
    comes before the oldest cloud still held is written.
    """

    def __init__(self, writer: Any, bag: Any, corrected_topic: str,
                 report: CorrectionReport) -> None:
        self._writer, self._bag, self._report = writer, bag, report
        self._corrected_topic = corrected_topic
        self._ready: list[tuple[int, int, Any]] = []
        self._held: deque[int] = deque()
        self._skipped_topics: set[str] = set()

    def pass_through(self, k: int, topic: str, msgtype: str, ns: int, raw: bytes) -> None:
        """Input message ``k``, written as it is."""
        heapq.heappush(self._ready, (k, 0, (topic, msgtype, ns, raw)))

    def hold(self, k: int) -> None:
        """Input message ``k`` is a cloud being corrected: nothing after it is written yet."""
        self._held.append(k)

    def corrected(self, k: int, ns: int, message: np.ndarray) -> None:
        """Cloud ``k`` corrected: its message bytes (log time ``ns``)."""
        heapq.heappush(self._ready, (k, 1, (ns, message)))
        self._held.remove(k)

    def emit(self) -> None:
        """Write every message before the oldest cloud still held."""
        self._emit((self._held[0], 1) if self._held else (math.inf, 0))

    def emit_all(self) -> None:
        """Write every message queued."""
        self._emit((math.inf, 0))

    def _emit(self, limit: tuple[float, int]) -> None:
        from lidarcal_ros.io.bag.format import POINTCLOUD2

        ready = self._ready
        while ready and (ready[0][0], ready[0][1]) < limit:
            _, kind, payload = heapq.heappop(ready)
            if kind == 1:
                ns, message = payload
                self._writer.write_raw(self._corrected_topic, POINTCLOUD2, ns, message.data)
            else:
                self._write_raw(*payload)

    def _write_raw(self, topic: str, msgtype: str, ns: int, raw: bytes) -> None:
        if topic in self._skipped_topics:
            return
        try:
            self._writer.write_raw(topic, msgtype, ns, raw,
                                   msgdef=self._bag.topics[topic].msgdef or None)
        except BagError as exc:
            self._skipped_topics.add(topic)
            self._report.warnings.append(f"topic {topic} not passed through ({exc})")
            logger.warning("%s", self._report.warnings[-1])
            return
        self._report.passthrough_messages += 1


@contextlib.contextmanager
def bag_output(job: _Job) -> Iterator[tuple[Any, Any, _OrderedOutput]]:
    """The output bag of ``job`` open: its writer, the input's chunks copied into it (None
    where they are not: every message is then passed through one by one) and the
    :class:`_OrderedOutput` the messages go through."""
    from lidarcal_ros.io.bag.format import POINTCLOUD2
    from lidarcal_ros.io.bag.writer import BagWriter

    bag = job.bag
    latched = [t for t, info in bag.topics.items() if info.transient_local]
    with BagWriter(job.out_path, overwrite=job.overwrite, latched_topics=latched,
                   typestore=bag.typestore) as writer:
        # Where the input allows it, its chunks are copied as they are: every input message
        # is then in the output, and only the clouds are read.
        new_topics = {job.corrected_topic: POINTCLOUD2}
        if job.moved_topic is not None:
            new_topics[job.moved_topic] = bag.topics[job.trajectory_topic].msgtype
        copied = writer.copy_chunks_of(bag, new_topics)
        if copied is not None:
            job.report.passthrough_messages = copied.messages
        yield writer, copied, _OrderedOutput(writer, bag, job.corrected_topic, job.report)


def _correct_to_bag(job: _Job) -> None:
    """Correct the clouds of ``job`` into a bag, every other message passed through."""
    bag, corrector, gate, points_topic = job.bag, job.corrector, job.gate, job.points_topic
    messages = job.messages
    assert messages is not None  # (a bag output's corrector places into them)
    with bag_output(job) as (writer, copied, output):

        def collect(done: list[tuple[Any, np.ndarray]]) -> None:
            for k, _corrected in done:
                output.corrected(k, *messages.release(k, corrector.tallies.pop(k).dense))

        # (the chunks copied: the clouds, and the trajectory where the gate reads it)
        read_topics = None if copied is None else job.cloud_topics
        read = functools.partial(bag.messages, read_topics)
        seen = 0
        # (clouds alone: fewer of them read ahead hold as many bytes as the mixed messages)
        for k, (topic, msgtype, ns, raw) in enumerate(
                prefetched(read, batch=8 if read_topics == [points_topic] else 32)):
            if copied is None:  # (copied, the input's messages are in the output already)
                output.pass_through(k, topic, msgtype, ns, raw)
            if topic == points_topic:
                msg, points = job.decode(bag, msgtype, raw, topic)
                output.hold(k)
                messages.hold(k, ns, msg)
                for tag, covered in gate.cloud(k, msg, points):
                    collect(corrector.push(covered, tag))
                seen += 1
                if job.progress and seen % 50 == 0:
                    job.progress("correcting", seen / job.n_clouds)
            elif topic == job.trajectory_topic and gate.reading:
                gate.pose(msgtype, raw)
                if job.poses is not None:
                    job.poses.add(ns, msgtype, raw)
            output.emit()
        for tag, covered in gate.finish():
            collect(corrector.push(covered, tag))
        collect(corrector.flush())
        output.emit_all()
        _check_something_corrected(corrector.stats, bag.path, points_topic)
        if job.moved_topic is not None:
            _write_moved_poses(job, writer)


def warm_up_compiled_loops() -> None:
    """Correct a small synthetic cloud (of the lidarcal layout, read-only as a decoded one
    is), so that the compiled loops of the correction are loaded, and numba initialised, now
    rather than by the first cloud (numba started without its BLAS check:
    :func:`~lidarcal_ros.core.jit.start_without_blas`)."""
    start_without_blas()
    n = 64
    tt = np.linspace(0.0, 2.0, 41)
    trajectory = Trajectory(tt, np.column_stack([np.zeros_like(tt), 60.0 * tt,
                                                 np.full_like(tt, 1000.0)]))
    points = np.zeros(n, dtype=make_point_dtype())
    points["x"] = np.linspace(-300.0, 300.0, n)
    points["y"] = np.linspace(55.0, 65.0, n)
    points["t"] = np.linspace(0.9, 1.1, n)
    points["intensity"] = 100.0
    points["strip_id"] = 1
    cloud = np.frombuffer(points.tobytes(), dtype=points.dtype)
    corrector = StreamCorrector(trajectory, CorrectionSettings(delta=np.zeros(8)),
                                source="warm-up")
    corrector.push(cloud)
    corrector.flush()

