"""Which point-positioning model a strip gets, the rigorous model's geometry, the laser-vector QA.

``matching.model`` and what makes an attitude usable: docs/method.md section 10.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import body_rotations, interpolated_frames
from lidarcal_ros.core.georeferencing.heading import MAX_CRAB_DEG, HeadingSource, wrap_angle
from lidarcal_ros.core.georeferencing.laser_geometry import (
    LaserGeometry,
    PositioningModel,
    ScannerKind,
)
from lidarcal_ros.core.georeferencing.local_trajectory import (
    DEFAULT_WINDOW,
    TrajectoryWindow,
    covered_by_trajectory,
    laser_geometry,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import ConfigError, TrajectoryError

logger = logging.getLogger(__name__)

#: Slowest trajectory (samples per second) whose attitude the rigorous model interpolates:
#: an aircraft in turbulence changes its attitude by degrees within a second.
MIN_ATTITUDE_RATE_HZ = 10.0
#: Largest tilt of the body's up axis from the vertical (deg) taken for REP-103's body frame:
#: survey flights bank by up to about 30 degrees in turns; a z-down frame is 180 off.
MAX_TILT_DEG = 60.0
#: Trajectory kept around a strip's time span when judging its attitude, s (the model of a
#: point reads the samples this far from it).
MODEL_SPAN_PAD_S = 1.0

#: What a general scanner's strips are not checked for, said in their model choice: its laser
#: vectors point anywhere (docs/method.md section 12) and a multirotor may fly sideways.
GENERAL_SKIPS = ("general scanner: the heading is not compared with the track, nor the "
                 "points required below the trajectory")

#: Messages already logged (a stream asks once per chunk; one line is enough).
_LOGGED: set[str] = set()


@dataclass(frozen=True)
class ModelChoice:
    """The model a strip gets and why.

    Attributes
    ----------
    model : PositioningModel
        ``LEVEL`` or ``RIGOROUS``.
    reason : str
        In words, e.g. ``"INS attitude at 50 Hz"`` or ``"the poses carry no orientation"``.
    rate_hz : float
        Median trajectory sample rate over the strip, Hz (NaN: too few samples).
    interpolation_error_rad : float
        95th percentile of the attitude's interpolation error between samples, estimated
        from the samples themselves (NaN without attitude).
    """

    model: PositioningModel
    reason: str
    rate_hz: float = math.nan
    interpolation_error_rad: float = math.nan


def check_model_setting(mode: PositioningModel, trajectory: Trajectory, where: str) -> None:
    """Refuse at once what ``rigorous`` would refuse strip by strip: a trajectory without
    orientation (ConfigError naming ``where``)."""
    if mode == PositioningModel.RIGOROUS and trajectory.orientation is None:
        raise ConfigError(f"{where}: matching.model is 'rigorous' but the trajectory's poses "
                          "carry no orientation (identity); use 'level' or 'auto'")


def choose_model(trajectory: Trajectory, t_lo: float, t_hi: float, *,
                 mode: PositioningModel = PositioningModel.AUTO,
                 heading_source: HeadingSource = HeadingSource.AUTO,
                 source: str = "points",
                 scanner: ScannerKind = ScannerKind.LINEAR) -> ModelChoice:
    """The model the points fired between ``t_lo`` and ``t_hi`` (s) get (docs/method.md section 10).

    A ``GENERAL`` scanner's (section 12) needs ``mode`` ``rigorous``; its heading is not
    compared with the track (:data:`GENERAL_SKIPS`, said in the choice's reason).

    Raises
    ------
    TrajectoryError
        ``rigorous`` asked for where the attitude is missing, levelled or too sparse.
    """
    level, rigorous = PositioningModel.LEVEL, PositioningModel.RIGOROUS
    general = scanner is ScannerKind.GENERAL
    if general and mode != rigorous:
        raise ConfigError(f"{source}: a general scanner's laser vectors need matching.model "
                          f"'rigorous', not '{mode}'")
    if mode == level:
        return ModelChoice(level, "matching.model level")
    span = _span(trajectory, t_lo, t_hi)
    rate = _rate_hz(span.t)
    refusal = _missing_attitude(span, rate, levelled_ok=mode == rigorous)
    if refusal is not None:
        if mode == rigorous:
            raise TrajectoryError(f"{source}: matching.model is 'rigorous' but {refusal}")
        if "Hz" in refusal:
            _log_once(f"{source}: {refusal}: level model")
        return ModelChoice(level, refusal, rate)
    if mode == PositioningModel.AUTO and heading_source == HeadingSource.TRACK:
        return ModelChoice(level, "matching.heading_source track", rate)
    assert span.orientation is not None
    odd = _other_convention(span, compare_track=not general)
    if odd is not None:
        if mode == rigorous:
            _log_once(f"{source}: {odd}; rigorous model as asked (matching.model rigorous)")
        else:
            _log_once(f"{source}: {odd}: level model with the track's heading; set "
                      "matching.model to 'rigorous' to use the attitude anyway")
            return ModelChoice(level, odd, rate)
    error = _interpolation_error(span)
    reason = f"INS attitude at {rate:.0f} Hz" + (f"; {GENERAL_SKIPS}" if general else "")
    return ModelChoice(rigorous, reason, rate, error)


def _span(trajectory: Trajectory, t_lo: float, t_hi: float) -> Trajectory:
    i0 = int(np.searchsorted(trajectory.t, t_lo - MODEL_SPAN_PAD_S))
    i1 = int(np.searchsorted(trajectory.t, t_hi + MODEL_SPAN_PAD_S, side="right"))
    return trajectory.take(slice(i0, i1))


def _rate_hz(t: np.ndarray) -> float:
    if t.shape[0] < 2:
        return math.nan
    return float(1.0 / np.median(np.diff(t)))


def _missing_attitude(span: Trajectory, rate: float, *, levelled_ok: bool) -> str | None:
    """Why the poses of ``span`` give no usable attitude, or None; ``levelled_ok``: level
    poses (a heading only) are an attitude (the rigorous model asked for: it then equals the
    level one with the poses' heading, interpolated)."""
    if span.orientation is None:
        return "the poses carry no orientation"
    if not span.full_attitude and not levelled_ok:
        return "the poses carry a heading only (no roll or pitch)"
    missing = int(np.isnan(span.orientation[:, 0]).sum())
    if missing:
        return (f"{missing} of {len(span)} poses around the strip carry no orientation "
                "(identity)")
    if not rate >= MIN_ATTITUDE_RATE_HZ:
        return (f"the trajectory comes at {rate:.1f} Hz, too sparse for the attitude's "
                f"motion (the rigorous model needs {MIN_ATTITUDE_RATE_HZ:g} Hz or more)")
    return None


def _other_convention(span: Trajectory, *, compare_track: bool = True) -> str | None:
    """Words on an orientation that is not REP-103's body frame, or None; ``compare_track``:
    a heading off the track by more than a crab is one (not for a platform that may fly
    sideways)."""
    assert span.orientation is not None
    q = span.orientation
    x, y = q[:, 0], q[:, 1]
    up_z = 1.0 - 2.0 * (x * x + y * y)  # R(q)[2, 2]: the body's up axis, vertical component
    tilt = float(np.degrees(np.arccos(np.clip(np.min(up_z), -1.0, 1.0))))
    if tilt > MAX_TILT_DEG:
        return (f"the poses' orientation tilts the body's up axis by up to {tilt:.0f} deg "
                f"(more than the {MAX_TILT_DEG:g} a survey flight banks): its body frame is "
                "not REP-103's (x forward, y left, z up)?")
    if not compare_track:
        return None
    track = _track_heading(span)
    heading = span.heading
    assert heading is not None
    ok = np.isfinite(track)
    if ok.any():
        crab = abs(float(np.degrees(np.median(wrap_angle(heading[ok] - track[ok])))))
        if crab > MAX_CRAB_DEG:
            return (f"the poses' orientation disagrees with the track by {crab:.0f} degrees "
                    f"(median; more than the {MAX_CRAB_DEG:g} a crab reaches): its body frame "
                    "is not REP-103's (x forward, y left, z up)?")
    return None


def _track_heading(trajectory: Trajectory) -> np.ndarray:
    """The track's heading ``kappa`` at each sample (rad; NaN where the platform does not
    move horizontally), from central differences of the positions."""
    xyz = trajectory.xyz
    if len(trajectory) < 2:
        return np.full(len(trajectory), np.nan)
    v = np.gradient(xyz[:, :2], trajectory.t, axis=0)
    moving = np.hypot(v[:, 0], v[:, 1]) > 1e-3
    return np.where(moving, np.arctan2(-v[:, 0], v[:, 1]), np.nan)


def _interpolation_error(span: Trajectory) -> float:
    """95th percentile (rad) of the error of the attitude's interpolation between samples
    (:func:`~lidarcal_ros.core.georeferencing.attitude.interpolated_frames`), estimated from the
    samples themselves: every other sample is predicted from the others, an interval twice the
    sampling; the cubic's error (tangents from central differences) grows with the cube of
    the interval, so an eighth of the miss is the error between neighbours."""
    q = span.orientation
    if q is None or len(span) < 5:
        return math.nan
    half = span.take(slice(None, None, 2))
    t_odd = span.t[1:-1:2]
    if half.orientation is None or not t_odd.size:
        return math.nan
    segment = np.clip(np.searchsorted(half.t, t_odd, side="right") - 1, 0, len(half) - 2)
    _, predicted, _ = interpolated_frames(t_odd, np.zeros((t_odd.size, 3)),
                                          segment.astype(np.int64), half.t, half.xyz,
                                          half.orientation)
    actual = body_rotations(q[1:-1:2])
    # the angle of R_pred^T R_actual: acos((trace - 1) / 2)
    trace = np.einsum("nij,nij->n", predicted, actual)
    miss = np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))
    ok = np.isfinite(miss)
    return float(np.percentile(miss[ok], 95) / 8.0) if ok.any() else math.nan


def attitude_segments(t: np.ndarray, trajectory: Trajectory, *, source: str = "points"
                      ) -> np.ndarray:
    """The trajectory segment of each firing time: the sample ``j`` with ``t_j <= t <
    t_j+1`` (int64; held within the samples), for
    :func:`~lidarcal_ros.core.georeferencing.attitude.interpolated_frames`.

    Raises
    ------
    TrajectoryError
        A segment whose end samples lack an orientation.
    """
    q = trajectory.orientation
    m = len(trajectory)
    if q is None or m < 2:
        raise TrajectoryError(f"{source}: the trajectory has no orientation")
    segment = np.clip(np.searchsorted(trajectory.t, t, side="right") - 1, 0, m - 2)
    lacking = np.isnan(q[segment, 0]) | np.isnan(q[segment + 1, 0])
    if lacking.any():
        k = int(np.argmax(lacking))
        raise TrajectoryError(f"{source}: the poses around t={t[k]:.3f} s carry no orientation "
                              f"({int(lacking.sum())} of {t.shape[0]} points)")
    return segment.astype(np.int64)


def rigorous_geometry(t: np.ndarray, xyz: np.ndarray, trajectory: Trajectory, *,
                      window: TrajectoryWindow = DEFAULT_WINDOW,
                      source: str = "points",
                      scanner: ScannerKind = ScannerKind.LINEAR) -> LaserGeometry:
    """docs/method.md section 10: the firing position and ``R_ins`` interpolated to each firing
    time (:func:`~lidarcal_ros.core.georeferencing.attitude.interpolated_frames`), and the laser
    vector ``rho_hat = R_ins^T (X - X_o)``; for a ``GENERAL`` scanner (section 12: the
    trajectory that of the sensor's origin) that is the laser vector itself, and a point may
    lie above the sensor.

    The points must be covered as the level model would need them
    (:func:`~lidarcal_ros.core.georeferencing.local_trajectory.covered_by_trajectory`), so that both
    models serve the same points.

    Raises
    ------
    TrajectoryError
        A point not covered, between samples without orientation, or (a linear scanner's)
        not below its firing position.
    """
    t = np.asarray(t, dtype=np.float64)
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    n = t.shape[0]
    if n == 0:
        return LaserGeometry.empty(PositioningModel.RIGOROUS, scanner)
    q = trajectory.orientation
    if q is None:
        raise TrajectoryError(f"{source}: the trajectory has no orientation")
    covered = covered_by_trajectory(t, trajectory, window=window)
    if not covered.all():
        k = int(np.argmin(covered))
        raise TrajectoryError(
            f"{source}: trajectory gap at t={t[k]:.3f} s ({int((~covered).sum())} of {n} "
            f"points not covered by >= {window.min_samples} samples within "
            f"+-{window.window_s:g} s)")
    segment = attitude_segments(t, trajectory, source=source)
    origin, rotation, rho = interpolated_frames(t, xyz, segment, trajectory.t, trajectory.xyz,
                                                q)
    x, y, z = rho[:, 0], rho[:, 1], rho[:, 2]
    above = z >= 0
    if above.any() and scanner is ScannerKind.LINEAR:
        k = int(np.argmax(above))
        raise TrajectoryError(
            f"{source}: point at t={t[k]:.3f} s is not below the trajectory "
            f"(z={z[k]:.6g} m); wrong trajectory or time base?")
    beta = np.arctan2(-x, -z)
    # The heading of the body's forward axis (R_ins's second column) on the horizontal.
    kappa = np.arctan2(-rotation[:, 0, 1], rotation[:, 1, 1])
    v = trajectory.xyz[segment + 1] - trajectory.xyz[segment]
    track = np.arctan2(-v[:, 0], v[:, 1])
    crab = float(np.degrees(np.median(wrap_angle(kappa - track))))
    return LaserGeometry(x=x, z=z, kappa=kappa, beta=beta, origin=origin,
                         heading_from=HeadingSource.ATTITUDE, crab_deg=crab,
                         rotation=rotation, y=y, model=PositioningModel.RIGOROUS,
                         scanner=scanner)


def strip_geometry(t: np.ndarray, xyz: np.ndarray, trajectory: Trajectory, *,
                   window: TrajectoryWindow = DEFAULT_WINDOW, source: str = "points",
                   heading_source: HeadingSource = HeadingSource.AUTO,
                   model: PositioningModel = PositioningModel.AUTO,
                   scanner: ScannerKind = ScannerKind.LINEAR
                   ) -> tuple[LaserGeometry, ModelChoice]:
    """The laser geometry of a strip's points by the model ``matching.model`` chooses for
    it (:func:`choose_model`), and that choice.

    Parameters are those of
    :func:`~lidarcal_ros.core.georeferencing.local_trajectory.laser_geometry`, plus ``model``
    (``matching.model``) and ``scanner`` (:class:`ScannerKind`; ``GENERAL`` needs
    ``rigorous``).
    """
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        return LaserGeometry.empty(), ModelChoice(PositioningModel.LEVEL, "no points")
    choice = choose_model(trajectory, float(np.min(t)), float(np.max(t)), mode=model,
                          heading_source=heading_source, source=source, scanner=scanner)
    if choice.model == PositioningModel.RIGOROUS:
        geometry = rigorous_geometry(t, xyz, trajectory, window=window, source=source,
                                     scanner=scanner)
    else:
        geometry = laser_geometry(t, xyz, trajectory, window=window, source=source,
                                  heading_source=heading_source)
    return geometry, choice


# ------------------------------------------------------------------ laser-vector QA
#: Median along-track component of the laser vectors (m) beyond which the QA warns: a
#: linear scanner's is 0; boresight biases of a few arcminutes move it by decimetres, a
#: timing offset by the distance flown in that time.
MAX_MEDIAN_ALONG_M = 0.5
#: Half the 5-95 % spread of the along-track component (m) beyond which the QA warns.
MAX_SPREAD_ALONG_M = 1.0
#: Share of laser vectors beyond the field of view (plus a degree) beyond which it warns.
MAX_OUTSIDE_FOV = 0.01


@dataclass
class LaserVectorQA:
    """What the recovered laser vectors ``rho_hat`` of a strip say about the data
    (docs/method.md section 10).

    Attributes
    ----------
    along_median_m, along_spread_m : float
        Median and half the 5-95 % spread of the along-track component ``rho_hat[1]``, m
        (NaN for the level model, which recovers none).
    scan_min_deg, scan_max_deg : float
        0.5th and 99.5th percentiles of the implied scan angle ``beta``, deg.
    outside_fov : float
        Share of the points whose ``|beta|`` exceeds half the field of view by over a
        degree.
    warnings : list of str
        One line each: a timing offset, a lever arm, a wrong body convention, a wrong field
        of view.
    skipped : str
        What was not checked and why, in words ("" where all was).
    """

    along_median_m: float
    along_spread_m: float
    scan_min_deg: float
    scan_max_deg: float
    outside_fov: float
    warnings: list[str] = field(default_factory=list)
    skipped: str = ""


#: What the QA of a general scanner's laser vectors leaves out (:attr:`LaserVectorQA.skipped`).
GENERAL_QA_SKIPS = ("along-track lean and spread and the field of view not checked: a "
                    "general scanner's laser vectors point anywhere (docs/method.md section 12)")


def laser_vector_qa(geometry: LaserGeometry, *, fov_deg: float, speed_mps: float
                    ) -> LaserVectorQA:
    """The QA of a strip's laser vectors (:class:`LaserVectorQA`).

    Boresight and lever-arm biases lean the laser vectors by decimetres (``-z domega + x
    dkappa + dY`` along track), so the warnings mean most for the points corrected by the
    calibration's estimate: what the biases do not explain.

    Parameters
    ----------
    geometry : LaserGeometry
        The strip's points (as delivered, or corrected by the estimate).
    fov_deg : float
        The scanner's full field of view, deg (``sensor.fov_deg``).
    speed_mps : float
        Ground speed over the strip, m/s: turns an along-track offset into a time.
    """
    return scan_qa(geometry.beta, geometry.y, scanner=geometry.scanner, model=geometry.model,
                   fov_deg=fov_deg, speed_mps=speed_mps)


def scan_qa(beta: np.ndarray, along: np.ndarray | None, *, scanner: ScannerKind,
            model: PositioningModel, fov_deg: float, speed_mps: float) -> LaserVectorQA:
    """:func:`laser_vector_qa` of a strip's scan angles ``beta`` (rad) and the along-track
    parts ``along`` of its laser vectors (m; None: the level model's, not known), as the
    ``scanner`` and point ``model`` give them."""
    beta = np.degrees(beta[np.isfinite(beta)])
    if scanner is ScannerKind.GENERAL:  # no along-track part, no scan angle to judge
        return LaserVectorQA(math.nan, math.nan, math.nan, math.nan, math.nan,
                             skipped=GENERAL_QA_SKIPS)
    if not beta.size:
        return LaserVectorQA(math.nan, math.nan, math.nan, math.nan, math.nan)
    lo, hi = (float(v) for v in np.percentile(beta, [0.5, 99.5]))
    half = 0.5 * fov_deg
    outside = float(np.mean(np.abs(beta) > half + 1.0))
    warnings = []
    median = spread = math.nan
    if along is not None and along.size:
        p5, p50, p95 = (float(v) for v in np.percentile(along, [5, 50, 95]))
        median, spread = p50, 0.5 * (p95 - p5)
        if abs(median) > MAX_MEDIAN_ALONG_M:
            ms = 1000.0 * median / speed_mps if speed_mps > 0 else math.nan
            warnings.append(
                f"laser vectors lean {median:+.2f} m along track (median; a linear scanner's "
                f"is 0): a timing offset of {ms:+.0f} ms between points and trajectory, or "
                "a lever arm along track?")
        if spread > MAX_SPREAD_ALONG_M:
            warnings.append(
                f"laser vectors spread +-{spread:.2f} m along track (5-95 %): the poses' "
                "orientation is not the scanner's (body convention, time base)?")
    if outside > MAX_OUTSIDE_FOV:
        reach = (f"{100.0 * outside:.1f}% of the scan angles lie beyond the field of view "
                 f"(+-{half:g} deg; {lo:+.1f} to {hi:+.1f} deg)")
        if model == PositioningModel.RIGOROUS:
            warnings.append(f"{reach}: sensor.fov_deg, or the body convention?")
        else:
            warnings.append(f"{reach}: the platform rolls, and the level model reads its roll "
                            "as scan angle (sensor.fov_deg?)")
    return LaserVectorQA(median, spread, lo, hi, outside, warnings)


def describe_models(choices: dict[int, ModelChoice]) -> str:
    """One line on the models the strips got (strip id -> choice), e.g. ``"rigorous (INS
    attitude at 50 Hz) for every strip"``."""
    if not choices:
        return "no strip"
    groups: dict[tuple[PositioningModel, str], list[int]] = {}
    for sid, c in sorted(choices.items()):
        groups.setdefault((c.model, c.reason), []).append(sid)
    if len(groups) == 1:
        (model, reason), _ = next(iter(groups.items()))
        return f"{model} ({reason}) for every strip"
    return "; ".join(f"{model} ({reason}) for strip{'s' if len(ids) > 1 else ''} "
                     f"{', '.join(map(str, ids))}" for (model, reason), ids in groups.items())


def describe_model_policy(mode: PositioningModel, trajectory: Trajectory, *,
                          heading_source: HeadingSource = HeadingSource.AUTO) -> str:
    """What ``matching.model`` makes of the newest second of ``trajectory`` (a live node's
    status), e.g. ``"rigorous (INS attitude at 50 Hz)"``."""
    if len(trajectory) < 2:
        return f"{mode} (no trajectory yet)"
    end = float(trajectory.t[-1])
    try:
        c = choose_model(trajectory, end - 1.0, end, mode=mode, heading_source=heading_source,
                         source="trajectory")
    except (TrajectoryError, ConfigError) as exc:
        return f"refused: {exc}"
    return f"{c.model} ({c.reason})"


#: The model of a calibration whose strips got both.
MIXED = "mixed"


def models_summary(choices: dict[int, ModelChoice]) -> str:
    """``level``, ``rigorous`` or :data:`MIXED`: the model of a calibration as a whole (a
    plain string, as the calibration file writes it)."""
    models = {c.model for c in choices.values()}
    if len(models) == 1:
        return models.pop().value
    return MIXED if models else PositioningModel.LEVEL.value


def _log_once(message: str) -> None:
    if message not in _LOGGED:
        _LOGGED.add(message)
        logger.warning("%s", message)


__all__ = [
    "GENERAL_QA_SKIPS", "GENERAL_SKIPS", "MAX_TILT_DEG", "MIN_ATTITUDE_RATE_HZ", "MIXED",
    "MODEL_SPAN_PAD_S", "LaserVectorQA", "ModelChoice",
    "attitude_segments", "check_model_setting", "choose_model", "describe_model_policy",
    "describe_models",
    "laser_vector_qa", "models_summary", "rigorous_geometry", "scan_qa", "strip_geometry",
]
