"""The mounting of a scanner calibrated from clouds in its own frame (docs/method.md section 12).

:func:`calibrate_mounting` takes what a ROS payload records (points in the sensor's frame with
absolute times, the INS's poses of ``base_link``, the nominal mounting ``base_link ->
sensor``), splits the flight into lines, georeferences every point with the nominal
mounting, calibrates the strips with the rigorous model and a general scanner's columns, and
returns the calibrated mounting (:func:`~lidarcal_ros.core.georeferencing.sensor_frame.
mounting_from_biases`) with its sigmas.

The trajectory given to the calibration is that of the sensor's origin, ``X_mb + R_mb t_bs``
at each pose, and the points are georeferenced from it with the mounting's rotation alone:
the rigorous model's laser vector ``R_ins^T (X - X_o)`` is then the sensor's ``P R_bs p``
exactly (the same interpolation both ways), and the lever-arm biases ``dX, dY, dZ`` are the
error of ``P t_bs``.
"""

from __future__ import annotations

import copy
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from itertools import pairwise
from typing import Any

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import (
    ObservabilityLimits,
    ParameterState,
    ParameterStatus,
    Solution,
)
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Progress, calibrate
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.georeferencing.attitude import P_BODY, rotation_matrices
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel, ScannerKind
from lidarcal_ros.core.georeferencing.sensor_frame import (
    Mounting,
    biases_between,
    georeference,
    mounting_from_biases,
)
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.trajectory.lines import line_of, straight_lines
from lidarcal_ros.errors import ConfigError, TrajectoryError

logger = logging.getLogger(__name__)

#: The biases a mounting calibration estimates by default: the lever arm across and along
#: the track, the boresight and the range. ``dZ`` moves every strip alike (vertical lever
#: arm; observable with control only): held at the nominal; ``dS`` is no parameter of a
#: general scanner.
MOUNTING_SOLVE_FOR = ("dX", "dY", "domega", "dphi", "dkappa", "dr")

#: The default largest sigma of a usable timing bias ``dt``, s
#: (``sensor_frame.timing_max_sigma_s``): a flight that determines it less well (straight
#: lines at one speed: ``dt`` then moves every line along its track as ``dY`` does) holds it
#: at 0 and says so (:func:`mounting_settings` with ``timing``).
TIMING_MAX_SIGMA_S = 0.001
#: The default largest multiple correlation of a usable timing bias with the mounting's biases
#: (``sensor_frame.timing_max_correlation``, ``CalibrationSettings.timing_max_correlation``;
#: :func:`timing_unseen`); measured: 0.99 (with ``dY``) on straight lines at one speed and no
#: wobble, where ``dY``'s sigma grew seven-fold; 0.6 with a multirotor's wobble.
TIMING_MAX_CORRELATION = 0.95
#: Where a calibration with a timing bias says what ``dt`` is (docs/method.md section 12): a
#: general scanner has no mirror scale, and ``dS``'s place holds ``dt``.
TIMING_SLOT = "dS"

#: Passes of a mounting's calibration at most (:func:`calibrate_mounting`), the first (on the
#: boresight and range, the lever arm held) counted.
MAX_PASSES = 4
#: The lever-arm biases, held in a calibration's first pass (:func:`calibrate_mounting`).
LEVER_ARM = ("dX", "dY", "dZ")
#: How well a robot description's lever arm is known, 1 sigma per axis, m (a tape measure's
#: few centimetres): a lever-arm bias held at it (``dZ`` without control) moves the others
#: through the attitude's changes (measured: 2-4 mm of ``dX`` from 4-5 cm of ``dZ``, ten
#: formal sigmas), so their sigmas allow for it (``sensor_frame.lever_arm_sigma_m``).
NOMINAL_LEVER_ARM_SIGMA_M = 0.05
#: A pass whose estimate moves the points by more than this (m; :func:`points_moved`) is
#: followed by another, the clouds georeferenced anew with the mounting it gave: the strips'
#: TINs are built on the points as georeferenced, and where a boresight error of tenths of a
#: degree puts them tens of centimetres off, the patches and samples chosen there can hold
#: the iterations in a wrong minimum (measured: lever arm 0.44 m off at 34 sigma with a
#: tactical INS's errors; the second pass from that estimate, 12 mm).
REPASS_MOVE_M = 0.05


def mounting_settings(*, timing_max_sigma_s: float = TIMING_MAX_SIGMA_S,
                      lever_arm_sigma_m: float = NOMINAL_LEVER_ARM_SIGMA_M,
                      **options: object) -> CalibrationSettings:
    """The calibration settings of a mounting (:func:`calibrate_mounting`): ``options`` over
    :data:`MOUNTING_SOLVE_FOR` and no largest sigma of a usable bias (an airborne
    calibration holds a bias at 0 where its sigma says it is of no use; a mounting's bias
    held at 0 is the nominal's error, tenths of a degree: worse than any estimate). With
    ``timing`` the timing bias ``dt`` is estimated too (in :data:`TIMING_SLOT`'s place),
    held at 0 where its sigma exceeds ``timing_max_sigma_s`` (s) or its multiple correlation
    with the mounting's biases ``timing_max_correlation`` (:func:`timing_unseen`). A
    lever-arm bias held (``dZ`` without control) is taken as known to ``lever_arm_sigma_m``
    (m; :data:`NOMINAL_LEVER_ARM_SIGMA_M`), the others' sigmas allowing for it."""
    base: dict[str, object] = {"solve_for": MOUNTING_SOLVE_FOR,
                               "limits": ObservabilityLimits(max_sigma={}),
                               "timing_max_correlation": TIMING_MAX_CORRELATION,
                               "held_sigma": {n: lever_arm_sigma_m for n in LEVER_ARM}}
    merged = {**base, **options}
    if merged.get("timing"):
        merged["solve_for"] = (*tuple(merged["solve_for"]), TIMING_SLOT)  # type: ignore[arg-type]
        limits = merged["limits"]
        assert isinstance(limits, ObservabilityLimits)
        merged["limits"] = replace(limits, max_sigma={**limits.max_sigma,
                                                      TIMING_SLOT: timing_max_sigma_s})
        merged["scanner"], merged["model"] = ScannerKind.GENERAL, PositioningModel.RIGOROUS
    return CalibrationSettings(**merged)  # type: ignore[arg-type]


@dataclass
class MountingCalibration:
    """A calibrated mounting (:func:`calibrate_mounting`).

    Attributes
    ----------
    mounting : Mounting
        The calibrated ``base_link -> sensor`` transform (REP-103).
    nominal : Mounting
        The one the clouds were georeferenced with.
    range_offset_m : float
        ``dr``: subtract it from every range (no part of a transform), m.
    delta, sigma : (8,) float64
        The biases ``nominal - true`` (docs/method.md order, SI) and their sigmas (NaN: not
        estimated, held at ``settings.fixed``).
    translation_sigma_m : (3,) float64
        Sigmas of the calibrated ``t_bs`` along ``base_link``'s x, y, z, m (NaN: held).
    rotation_sigma_rad : (3,) float64
        Sigmas of the calibrated rotation about ``base_link``'s x, y, z, rad (NaN: held).
    lines : (k, 2) float64
        The lines flown (first and last time, s) whose points made the strips, strip ids
        their indices.
    result : CalibrationResult
        The calibration of the strips (QA, convergence, warnings); its biases are the
        eight of docs/method.md, ``dS`` held at 0 (the timing bias is taken out of its
        place into the fields below).
    time_offset_s : float
        The timing bias ``dt`` (delivered - true per-point time, s; docs/method.md section
        12): 0 where not estimated.
    time_offset_sigma_s : float
        Its sigma, s (NaN: not estimated).
    time_offset_correlation : dict
        Its correlation with each bias estimated with it.
    time_offset_note : str
        Where ``dt`` was asked for but the flight cannot see it: the statement (held at 0);
        else "".
    """

    mounting: Mounting
    nominal: Mounting
    range_offset_m: float
    delta: np.ndarray
    sigma: np.ndarray
    translation_sigma_m: np.ndarray
    rotation_sigma_rad: np.ndarray
    lines: np.ndarray
    result: CalibrationResult
    time_offset_s: float = 0.0
    time_offset_sigma_s: float = math.nan
    time_offset_correlation: dict[str, float] = field(default_factory=dict)
    time_offset_note: str = ""

    @property
    def timing_asked(self) -> bool:
        """The timing bias was asked for (estimated, or held at 0 with a note)."""
        return bool(np.isfinite(self.time_offset_sigma_s) or self.time_offset_note)


def sensor_trajectory(trajectory: Trajectory, mounting: Mounting) -> Trajectory:
    """The trajectory of the sensor's origin: ``X_mb + R_mb t_bs`` at each pose of
    ``base_link``, the orientation kept (map frame, m)."""
    q = trajectory.orientation
    if q is None:
        raise TrajectoryError("sensor-frame clouds need the orientation of base_link on the "
                              "trajectory; its poses carry none")
    if np.isnan(q[:, 0]).any():
        raise TrajectoryError(f"{int(np.isnan(q[:, 0]).sum())} of {len(trajectory)} poses "
                              "carry no orientation: the sensor's origin is unknown there")
    xyz = trajectory.xyz + rotation_matrices(q) @ mounting.translation
    return Trajectory(trajectory.t, xyz, q)


def calibrate_mounting(points: np.ndarray, t: np.ndarray, trajectory: Trajectory,
                       nominal: Mounting, *, settings: CalibrationSettings | None = None,
                       lines: np.ndarray | None = None,
                       control: ControlPoints | None = None,
                       progress: Progress | None = None,
                       passes: int = MAX_PASSES) -> MountingCalibration:
    """Calibrate the mounting ``base_link -> sensor`` from clouds in the sensor's frame
    (module docstring; docs/method.md section 12).

    Parameters
    ----------
    points : (n, 3) float32 or float64
        The points in the sensor's frame, m.
    t : (n,) float64
        Their absolute times on the trajectory's clock, s.
    trajectory : Trajectory
        The INS's poses of ``base_link`` (orientation required), map frame.
    nominal : Mounting
        The mounting the robot's description has.
    settings : CalibrationSettings, keyword-only, optional
        Options of the calibration (default: :func:`mounting_settings`); its ``scanner`` is
        taken as ``GENERAL`` and ``model`` as ``rigorous``.
    lines : (k, 2) float64, keyword-only, optional
        The lines' time spans, s (default:
        :func:`~lidarcal_ros.core.trajectory.lines.straight_lines` of ``trajectory``); the
        points outside them (turns) are left out.
    control : ControlPoints, keyword-only, optional
        Vertical control points (map frame), which make ``dZ`` observable.
    passes : int, keyword-only
        Calibrations at most. With more than one, the first estimates the boresight and
        ``dr`` with the lever arm held at the nominal (a nominal rotation tenths of a degree
        off puts the strips decimetres apart, where the first matches can trade a lever arm
        decimetres off against the rotation), the second everything from the mounting it
        gave; while a pass moves the points by more than :data:`REPASS_MOVE_M`, the next
        georeferences them anew with the mounting it gave (:func:`rebased` then expresses
        the last against ``nominal``).

    Raises
    ------
    ConfigError
        Points and times that disagree, ``dS`` asked for.
    TrajectoryError
        No orientation, points outside the trajectory's span.
    CalibrationError
        Fewer than two lines, nothing estimable (:func:`~lidarcal_ros.core.calibration.
        calibrate.calibrate`).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape[0] != p.shape[0]:
        raise ConfigError(f"mounting calibration: {p.shape[0]} points but {t.shape[0]} times")
    s = _general_rigorous(settings or mounting_settings())
    spans = straight_lines(trajectory) if lines is None else \
        np.asarray(lines, dtype=np.float64).reshape(-1, 2)
    held = _lever_arm_held(s) if passes > 1 else None
    if held is None:
        first = _one_pass(p, t, trajectory, nominal, s, spans, control, progress)
        return further_passes(p, t, trajectory, first, settings=s, control=control,
                              progress=progress, passes=passes)
    boresight = _one_pass(p, t, trajectory, nominal, held, spans, control, progress)
    logger.info("mounting pass 1 (the lever arm held) moved the points by %.3f m: "
                "georeferenced anew with its boresight",
                points_moved(boresight.delta, _typical_range(p)))
    second = _one_pass(p, t, trajectory, boresight.mounting, s, spans, control, progress)
    return further_passes(p, t, trajectory, second, settings=s, control=control,
                          progress=progress, passes=passes, origin=boresight, made=2)


def _lever_arm_held(settings: CalibrationSettings) -> CalibrationSettings | None:
    """The settings of a first pass on the boresight and ``dr`` alone, the lever arm (and a
    timing bias, which would take its along-track part) held; None where ``settings``
    solve for no lever arm or no rotation."""
    names = settings.solve_for
    if not any(n in names for n in LEVER_ARM) or \
            not any(n in names for n in ("domega", "dphi", "dkappa")):
        return None
    return replace(without_timing(settings),
                   solve_for=tuple(n for n in names if n not in LEVER_ARM and n != TIMING_SLOT))


def _general_rigorous(settings: CalibrationSettings) -> CalibrationSettings:
    """``settings`` for sensor-frame strips: their laser vectors are a general scanner's, the
    model the rigorous one (docs/method.md section 12)."""
    return replace(settings, scanner=ScannerKind.GENERAL, model=PositioningModel.RIGOROUS)


def _one_pass(points: np.ndarray, t: np.ndarray, trajectory: Trajectory, nominal: Mounting,
              settings: CalibrationSettings, spans: np.ndarray,
              control: ControlPoints | None, progress: Progress | None) -> MountingCalibration:
    """The clouds georeferenced with ``nominal`` and calibrated once."""
    origin = sensor_trajectory(trajectory, nominal)
    strips = line_strips(points, t, origin, nominal, spans)
    mission = Mission(origin, strips, control=control, frame_id="map")
    result = calibrate(mission, settings, progress=progress)
    unseen = timing_unseen(result.solution, settings)
    if unseen:
        # dt took (or blurred) biases the flight sees without it: again, dt held at 0
        logger.info("the timing bias cannot be told from the mounting (%s): calibrated "
                    "again without it", unseen)
        result = calibrate(mission, without_timing(settings), progress=progress)
        result.solution.status[TIMING_SLOT] = ParameterStatus(ParameterState.NOT_ESTIMABLE,
                                                              unseen)
    return mounting_calibration(result, nominal, spans)


def timing_unseen(sol: Solution, settings: CalibrationSettings) -> str:
    """Why a calibration with the timing bias (``settings.timing``) is to be made again
    without it, or "": ``dt`` was held (not estimable) and took another bias with it, or it
    was estimated but depends on the mounting's biases nearly (its multiple correlation with
    them above ``settings.timing_max_correlation``: straight lines at one speed and a steady
    attitude, where ``dt`` moves each line along its track as ``dY`` does)."""
    if not settings.timing:
        return ""
    said = sol.status[TIMING_SLOT]
    if said.state is not ParameterState.ESTIMATED:
        took = [n for n in settings.solve_for if n != TIMING_SLOT
                and sol.status[n].state is ParameterState.NOT_ESTIMABLE]
        return said.reason if took else ""
    j = sol.estimated.index(TIMING_SLOT)
    inverse = np.linalg.inv(sol.correlation)
    multiple = math.sqrt(max(0.0, 1.0 - 1.0 / float(inverse[j, j])))
    if multiple <= settings.timing_max_correlation:
        return ""
    r = sol.correlation[j].copy()
    r[j] = 0.0
    k = int(np.argmax(np.abs(r)))
    return (f"{TIMING_SLOT} depends on the other biases nearly (multiple correlation "
            f"{multiple:.3f} above {settings.timing_max_correlation:g}, {float(r[k]):+.2f} "
            f"with {sol.estimated[k]}): only their combination is determined")


def without_timing(settings: CalibrationSettings) -> CalibrationSettings:
    """``settings`` with no timing bias."""
    return replace(settings, timing=False,
                   solve_for=tuple(n for n in settings.solve_for if n != TIMING_SLOT),
                   limits=replace(settings.limits, max_sigma={
                       k: v for k, v in settings.limits.max_sigma.items() if k != TIMING_SLOT}))


def further_passes(points: np.ndarray, t: np.ndarray, trajectory: Trajectory,
                   first: MountingCalibration, *, settings: CalibrationSettings,
                   control: ControlPoints | None = None, progress: Progress | None = None,
                   passes: int = MAX_PASSES, origin: MountingCalibration | None = None,
                   made: int = 1) -> MountingCalibration:
    """After a calibration (``first``: a pass of :func:`calibrate_mounting`, the ``made``-th),
    the passes :func:`calibrate_mounting` goes on with: while a pass moved the points by
    more than :data:`REPASS_MOVE_M`, the clouds (``points`` in the sensor's frame, ``t``
    absolute s, on ``first.lines``) are georeferenced anew with its mounting and calibrated
    again, up to ``passes`` in all; the last expressed against the first pass's nominal
    (``origin``, default ``first``; :func:`rebased`)."""
    s = _general_rigorous(settings)
    origin = first if origin is None else origin
    typical_range = _typical_range(points)
    cal, number = first, made
    while number < passes and (moved := points_moved(cal.delta, typical_range)) > REPASS_MOVE_M:
        logger.info("mounting pass %d moved the points by %.3f m (at %.0f m): georeferenced "
                    "anew with its mounting", number, moved, typical_range)
        number += 1
        cal = _one_pass(points, t, trajectory, cal.mounting, s, first.lines, control, progress)
    return cal if number == 1 else rebased(cal, origin.nominal, origin, number)


def sensor_points(strips: Sequence[Strip], origin: Trajectory,
                  nominal: Mounting) -> tuple[np.ndarray, np.ndarray]:
    """The points of ``strips`` (as :func:`line_strips` made them from ``origin``, the
    sensor's, and ``nominal``'s rotation) back in the sensor's frame, (n, 3) m, with their
    times (n,) s, strip after strip: ``p = R_bs^T R_mb(t)^T (X - X_o(t))``."""
    xyz = np.concatenate([s.xyz for s in strips]) if strips else np.empty((0, 3))
    t = np.concatenate([s.t for s in strips]) if strips else np.empty(0)
    at = georeference(np.zeros_like(xyz), t, origin, Mounting(np.eye(3), np.zeros(3)),
                      source="strips")
    in_base = np.einsum("nji,nj->ni", at.base_rotation, xyz - at.origin)  # R_mb^T v
    return in_base @ nominal.rotation, t  # rows: (R_bs^T w)^T = w^T R_bs


def _typical_range(points: np.ndarray) -> float:
    """The median range of (up to 100,000 evenly taken of) ``points`` (n, 3), m."""
    step = max(points.shape[0] // 100_000, 1)
    r = np.sqrt(np.einsum("ij,ij->i", points[::step], points[::step]))
    r = r[np.isfinite(r) & (r > 0.0)]
    return float(np.median(r)) if r.size else 0.0


def points_moved(delta: np.ndarray, typical_range: float) -> float:
    """How far the biases ``delta`` (SI) move a point at ``typical_range`` m, m: the lever
    arm's shift and the boresight's rotation at that range (``dr`` moves every point along
    its own beam, whatever the geometry: not counted)."""
    d = np.nan_to_num(np.asarray(delta, dtype=np.float64))
    return float(np.linalg.norm(d[0:3]) + typical_range * np.linalg.norm(d[3:6]))


def rebased(cal: MountingCalibration, nominal: Mounting, first: MountingCalibration,
            passes: int) -> MountingCalibration:
    """The calibration of a later pass (``cal``, whose nominal was the mounting the pass
    before gave) expressed against the first ``nominal``: the same mounting and sigmas,
    the biases ``nominal - true``, the strips' discrepancies before calibration those of
    the ``first`` pass (as delivered), and a line saying so."""
    delta = biases_between(nominal, cal.mounting)
    delta[6:] = cal.delta[6:]  # dr (each pass's ranges are the delivered ones) and dS
    result = cal.result
    result.solution.delta = delta.copy()
    before = {(q.strip_a, q.strip_b): q for q in first.result.pairs}
    for q in result.pairs:
        was = before.get((q.strip_a, q.strip_b))
        if was is not None:
            q.rms_before, q.n_before = was.rms_before, was.n_before
    result.history = [h + (delta - cal.delta) for h in result.history]
    held = any(first.result.solution.status[n].state is ParameterState.FIXED and
               cal.result.solution.status[n].state is not ParameterState.FIXED
               for n in LEVER_ARM)
    result.solution.warnings.append(
        f"calibrated in {passes} passes: each pass after the first georeferenced the clouds "
        f"anew with the mounting the one before gave " + (
            "(the first estimated the boresight and dr with the lever arm held)" if held else
            f"(the first moved the points by more than {REPASS_MOVE_M * 100:.0f} cm)"))
    return replace(cal, nominal=nominal, delta=delta, result=result)


def line_strips(points: np.ndarray, t: np.ndarray, origin: Trajectory, nominal: Mounting,
                lines: np.ndarray) -> list[Strip]:
    """The points of each line as a strip in the map frame (id: the line's index in
    ``lines``; in the points' order), georeferenced with ``nominal``'s rotation from the
    sensor's origin (:func:`sensor_trajectory`; module docstring); points in no line (the
    turns) or at the origin (no return) left out. ``points`` (n, 3) m in the sensor's frame,
    ``t`` (n,) absolute s, ``lines`` (k, 2) s. Batch and live alike (each point's own).

    Raises
    ------
    TrajectoryError
        A point of a line outside ``origin``'s span.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(t) & (np.einsum("ij,ij->i", p, p) > 0.0)
    label = np.where(ok, line_of(t, lines), -1)
    keep = np.flatnonzero(label >= 0)
    # the rotation alone: the sensor's origin is the trajectory's (module docstring)
    geo = georeference(p[keep], t[keep], origin, Mounting(nominal.rotation, np.zeros(3)),
                       source="sensor-frame points")
    order = np.argsort(label[keep], kind="stable")
    bounds = np.searchsorted(label[keep][order], np.arange(len(lines) + 1))
    return [Strip(k, geo.xyz[order[a:b]], t[keep][order[a:b]])
            for k, (a, b) in enumerate(pairwise(bounds)) if b > a]


def mounting_calibration(result: CalibrationResult, nominal: Mounting,
                         lines: np.ndarray) -> MountingCalibration:
    """The calibrated mounting of a calibration of sensor-frame strips (``result``: its
    biases are the nominal's errors; ``lines``: the lines whose points made the strips),
    batch (:func:`calibrate_mounting`) or live alike."""
    # (a copy: the live calibrator asks for the mounting of one estimate more than once)
    result = replace(result, solution=copy.deepcopy(result.solution),
                     history=[h.copy() for h in result.history])
    sol = result.solution
    timing = _take_timing(result)
    delta, sigma = sol.delta.copy(), sol.sigma.copy()
    translation_sigma, rotation_sigma = _mounting_sigmas(sigma)
    said = _lever_arm_by_priors(result)
    if said and said not in sol.warnings:
        sol.warnings.append(said)
    return MountingCalibration(
        mounting=mounting_from_biases(nominal, delta), nominal=nominal,
        range_offset_m=float(delta[PARAMETER_INDEX["dr"]]), delta=delta, sigma=sigma,
        translation_sigma_m=translation_sigma, rotation_sigma_rad=rotation_sigma,
        lines=np.asarray(lines, dtype=np.float64).reshape(-1, 2), result=result, **timing)


def _take_timing(result: CalibrationResult) -> dict[str, Any]:
    """The timing bias out of :data:`TIMING_SLOT`'s place of ``result`` (which is left with
    the eight biases of docs/method.md, ``dS`` held at 0, the warnings naming ``dt``): the
    :class:`MountingCalibration` fields of ``dt``. Nothing where it was not asked for (the
    slot held: a general scanner's ``dS`` is no parameter)."""
    sol = result.solution
    said = sol.status[TIMING_SLOT]
    if said.state is ParameterState.FIXED:
        return {}
    i = PARAMETER_INDEX[TIMING_SLOT]
    out: dict[str, Any] = {}
    if said.state is ParameterState.ESTIMATED:
        j = sol.estimated.index(TIMING_SLOT)
        out = {"time_offset_s": float(sol.delta[i]), "time_offset_sigma_s": float(sol.sigma[i]),
               "time_offset_correlation": {n: float(sol.correlation[j, k])
                                           for k, n in enumerate(sol.estimated) if k != j}}
    else:
        out = {"time_offset_note": timing_statement(said.reason)}
    keep = [k for k, n in enumerate(sol.estimated) if n != TIMING_SLOT]
    sol.covariance = sol.covariance[np.ix_(keep, keep)]
    sol.correlation = sol.correlation[np.ix_(keep, keep)]
    sol.estimated = tuple(sol.estimated[k] for k in keep)
    sol.delta[i], sol.sigma[i] = 0.0, math.nan
    sol.status[TIMING_SLOT] = ParameterStatus(ParameterState.FIXED)
    sol.warnings = [re.sub(rf"\b{TIMING_SLOT}\b", "dt", w) for w in sol.warnings]
    if "time_offset_note" in out:
        sol.warnings.append(out["time_offset_note"])
    for h in result.history:
        h[i] = 0.0
    return out


def timing_statement(reason: str) -> str:
    """What a calibration says where the timing bias was asked for and the flight cannot see
    it (``reason``: the adjustment's, naming :data:`TIMING_SLOT`; where its sigma exceeded
    the limit, the two in ms)."""
    why = re.sub(r"\(sigma (\S+) above (\S+); dS needs [^)]*\)",
                 lambda m: f"(its sigma {float(m[1]) * 1e3:.3g} ms above "
                           f"{float(m[2]) * 1e3:.3g} ms)", reason)
    why = re.sub(rf"\b{TIMING_SLOT}\b", "dt", why)
    return (f"the timing bias dt cannot be seen on this flight ({why}): held at 0; it shows "
            "where the speed or the attitude's rate differs between overlapping strips "
            "(turns, lines flown at other speeds)")


def timing_text(offset_s: float, sigma_s: float | None, note: str, *,
                plus_minus: str = "+-") -> str:
    """The timing bias ``dt`` (``offset_s`` and its sigma ``sigma_s``, s; ``note``: the
    statement of one held at 0) in a few words, ms: ``+3.01 +- 0.09 ms`` where estimated
    (as many decimals as the sigma's first digit needs, 2 at least), ``held at 0`` where
    asked for and held, ``+1.00 ms (not estimated)`` where given another way, '' where not
    asked for (0, no sigma, no statement)."""
    if sigma_s is not None and math.isfinite(sigma_s):
        ms = sigma_s * 1e3
        digits = min(6, max(2, -math.floor(math.log10(ms)))) if ms > 0 else 2
        return f"{offset_s * 1e3:+.{digits}f} {plus_minus} {ms:.{digits}f} ms"
    if note:
        return "held at 0"
    return f"{offset_s * 1e3:+.2f} ms (not estimated)" if offset_s else ""


def _lever_arm_by_priors(result: CalibrationResult) -> str:
    """The warning that the horizontal lever arm is known through the priors of the strips'
    trajectory errors only (docs/method.md section 11: on straight lines it is a constant
    shift of each strip, as an offset is), or "" where no such errors were estimated with it."""
    sol, trajectory = result.solution, result.trajectory
    lever = [n for n in ("dX", "dY") if n in sol.estimated]
    if trajectory is None or not trajectory.model.estimated or not lever:
        return ""
    sigmas = ", ".join(f"{n} {sol.sigma[PARAMETER_INDEX[n]] * 1e3:.1f} mm" for n in lever)
    return (f"the lever arm across and along the track ({sigmas}) is told from the strips' "
            "trajectory offsets only by their a-priori sigmas "
            "(calibration.trajectory.offset_sigma_horizontal_m): the line's shift is the "
            "same either way; where the lever arm was surveyed better, hold it "
            "(calibration.solve_for without dX and dY)")


def _mounting_sigmas(sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sigmas of the calibrated translation (m) and rotation (rad) along and about
    ``base_link``'s axes from those of the biases (``sigma``, (8,)): ``t_bs`` moves by ``-P^T
    [dX, dY, dZ]`` and the rotation by ``-P^T [domega, dphi, dkappa]`` to first order
    (docs/method.md section 12), ``P`` a signed permutation: each axis of ``base_link`` takes
    the sigma of one body axis (x forward: ``dY``, ``dphi``; y left: ``dX``, ``domega``; z
    up: ``dZ``, ``dkappa``)."""
    body_axis = np.argmax(np.abs(P_BODY), axis=0)
    return sigma[0:3][body_axis], sigma[3:6][body_axis]


__all__ = [
    "LEVER_ARM",
    "MAX_PASSES",
    "MOUNTING_SOLVE_FOR",
    "NOMINAL_LEVER_ARM_SIGMA_M",
    "REPASS_MOVE_M",
    "TIMING_MAX_CORRELATION",
    "TIMING_MAX_SIGMA_S",
    "TIMING_SLOT",
    "MountingCalibration",
    "calibrate_mounting",
    "further_passes",
    "line_strips",
    "mounting_calibration",
    "mounting_settings",
    "points_moved",
    "rebased",
    "sensor_points",
    "sensor_trajectory",
    "timing_statement",
    "timing_text",
    "timing_unseen",
    "without_timing",
]
