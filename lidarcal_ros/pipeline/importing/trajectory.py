"""An import's trajectory: a delivered file in the map frame, or one rebuilt from the points.

The rules for positions, attitude and the estimate: docs/import.md.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import attitude_from_quaternions
from lidarcal_ros.core.georeferencing.rigorous import choose_model
from lidarcal_ros.core.mission import Trajectory, screen_samples
from lidarcal_ros.core.trajectory.estimation import (
    EstimatedTrajectory,
    EstimateSettings,
    estimate_trajectory,
)
from lidarcal_ros.errors import InputError, TrajectoryError
from lidarcal_ros.io.survey.trajectory_crs import map_orientation, project
from lidarcal_ros.io.survey.trajectory_files import (
    TrajectoryFile,
    TrajectoryFileKind,
    read_smrmsg,
    read_trajectory_file,
    smrmsg_beside,
)
from lidarcal_ros.pipeline.importing.points import PointsFrame, PointsRead
from lidarcal_ros.pipeline.importing.strips import StripAssembly, StripSummary
from lidarcal_ros.pipeline.importing.time_bases import TimeRule

logger = logging.getLogger(__name__)

#: Samples of a trajectory file kept beyond the points' first and last time, seconds.
_MARGIN_S = 5.0


@dataclass
class DeliveredTrajectory:
    """A trajectory file in the map frame (raw times).

    Attributes
    ----------
    file : TrajectoryFile
    xyz : (n, 3) float64
        Positions in the points' CRS, metres.
    orientation : (n, 4) float64 or None
        Map-frame quaternions (x, y, z, w) where the file has attitude.
    full_attitude : bool
        ``orientation`` carries roll and pitch, not the heading alone.
    position_sigma : (n, 3) float64 or None
        Each sample's position sigma east, north, up (m) from the accuracy file, where one
        was given or found (the meridian convergence between true and grid north, a few
        degrees, left out of the horizontal pair).
    accuracy : Path or None
        That accuracy file.
    """

    file: TrajectoryFile
    xyz: np.ndarray
    orientation: np.ndarray | None
    full_attitude: bool
    position_sigma: np.ndarray | None = None
    accuracy: Path | None = None


@dataclass
class BagTrajectory:
    """The trajectory an import writes, on the bag's clock.

    Attributes
    ----------
    trajectory : Trajectory
        Map frame, metres.
    kind : str
        What it is, in words (file name and what its poses carry, or the estimate).
    source : str
        Named in coverage errors: the file's path, or ``"trajectory estimate"``.
    attitude_range_deg : dict of str to (float, float)
        Range of the poses' roll and pitch, degrees, when they carry the attitude.
    estimate : EstimatedTrajectory or None
        The estimate and its quality, when rebuilt from the points.
    dropped_strips : list of int
        Strips the estimate could not place: left out.
    """

    trajectory: Trajectory
    kind: str
    source: str
    attitude_range_deg: dict[str, tuple[float, float]] = field(default_factory=dict)
    estimate: EstimatedTrajectory | None = None
    dropped_strips: list[int] = field(default_factory=list)


# ---------------------------------------------------------------------------- from a file
def read_delivered_trajectory(path: str | os.PathLike[str], trajectory_crs: str | None,
                          frame: PointsFrame, *,
                          accuracy: str | os.PathLike[str] | None = None
                          ) -> DeliveredTrajectory:
    """Read a trajectory file and bring it into the map frame (docs/import.md, "Trajectory files").

    Parameters
    ----------
    path : path-like
    trajectory_crs : str or None
        CRS of its positions (default EPSG:4979 for geographic ones, else the points').
    frame : PointsFrame
        The points' CRS and units: the map frame.
    accuracy : path-like, ``"none"`` or None, keyword-only
        Its accuracy file (``smrmsg``); None: the one beside an SBET by POSPac's names
        (:func:`~lidarcal_ros.io.survey.trajectory_files.smrmsg_beside`) where there is one.

    Raises
    ------
    TrajectoryError, InputError
        An unreadable file, or geographic positions without a CRS of the points; an
        accuracy file unreadable, truncated, holding a non-finite value, or not covering
        the trajectory's times.
    """
    traj_file = read_trajectory_file(Path(str(path)))
    traj_crs = _trajectory_crs(trajectory_crs, traj_file)
    xyz = _trajectory_in_map(traj_file, frame.crs, traj_crs, frame.unit_factors)
    orientation, full_attitude = map_orientation(
        traj_file, traj_crs, frame.crs if traj_crs else None)
    found = _accuracy_file(accuracy, traj_file)
    sigma = None
    if found is not None:
        sigma = read_smrmsg(found).enu_at(traj_file.t, where=str(traj_file.path))
        logger.info("%s: position sigmas from %s", traj_file.path, found)
    return DeliveredTrajectory(traj_file, xyz, orientation, full_attitude, sigma, found)


def _accuracy_file(accuracy: str | os.PathLike[str] | None, traj: TrajectoryFile
                   ) -> Path | None:
    """The accuracy file to read: the one given, none for ``"none"``, else an SBET's
    ``smrmsg`` beside it."""
    if accuracy is not None:
        return None if str(accuracy) == "none" else Path(accuracy)
    return smrmsg_beside(traj.path) if traj.kind is TrajectoryFileKind.SBET else None


def _trajectory_crs(text: str | None, traj: TrajectoryFile) -> Any:
    import pyproj

    from lidarcal_ros.io.survey.las_writer import parse_crs

    if text:
        c = parse_crs(text)
    elif traj.geographic:
        c = pyproj.CRS.from_epsg(4979)
    else:
        return None
    if c.is_geographic and len(c.axis_info) < 3:
        c = c.to_3d()
    return c


def _trajectory_in_map(
    traj: TrajectoryFile, points_crs: Any, traj_crs: Any, factors: tuple[float, float]
) -> np.ndarray:
    """Trajectory positions in the map frame (points' CRS scaled to metres)."""
    hfac, vfac = factors
    if traj_crs is None:  # already in the points' CRS and units
        pos = np.column_stack([traj.a, traj.b, traj.c])
        return pos * np.array([hfac, hfac, vfac])
    if points_crs is None:
        raise InputError(
            f"{traj.path}: the trajectory is in {traj_crs.name} but the points' CRS is unknown "
            "(no CRS in the LAS headers): give --crs EPSG:N"
        )
    pos = project(traj, traj_crs, points_crs)
    three_d = points_crs.is_compound or len(points_crs.axis_info) >= 3
    return pos * np.array([hfac, hfac, vfac if three_d else 1.0])


def trajectory_from_file(given: DeliveredTrajectory, raw_t: np.ndarray, rule: TimeRule,
                         strips: StripAssembly, points_range: tuple[float, float],
                         rate_hz: float) -> BagTrajectory:
    """The file's samples on the bag's clock, screened (a warning line counts what is left
    out), kept within 5 s of the points at ``rate_hz`` (Hz, 0: all).

    Parameters
    ----------
    given : DeliveredTrajectory
    raw_t : (n,) float64
        The file's times as read under ``rule`` (week seconds unwrapped), seconds.
    rule : TimeRule
    strips : StripAssembly
        Their spans are checked against the samples (to the read pass's time bin: exactly
        while the bag is written).
    points_range : (float, float)
        First and last raw point time, seconds.
    rate_hz : float

    Raises
    ------
    TrajectoryError
        The samples do not cover a strip's span, or leave a gap over 2 s inside one.
    """
    where = str(given.file.path)
    t_clock = rule.trajectory(raw_t)
    c0, c1 = rule.points(np.array(points_range))
    usable = screen_samples(raw_t, given.xyz, where)
    whole = Trajectory.from_samples(
        t_clock[usable], given.xyz[usable],
        None if given.orientation is None else given.orientation[usable],
        full_attitude=given.full_attitude,
        position_sigma=None if given.position_sigma is None else given.position_sigma[usable])
    inside = np.flatnonzero((whole.t >= c0 - _MARGIN_S) & (whole.t <= c1 + _MARGIN_S))
    traj = whole.take(inside[_decimate(whole.t[inside], rate_hz)])
    kind, attitude_range = _trajectory_kind(traj, given.file)
    if given.accuracy is not None and traj.position_sigma is not None:
        h = np.hypot(traj.position_sigma[:, 0], traj.position_sigma[:, 1]) / math.sqrt(2.0)
        v = traj.position_sigma[:, 2]
        kind += (f"; position sigmas from {given.accuracy.name} (horizontal "
                 f"{np.nanmin(h) * 100:.1f}-{np.nanmax(h) * 100:.1f} cm, vertical "
                 f"{np.nanmin(v) * 100:.1f}-{np.nanmax(v) * 100:.1f} cm)")
    check_coverage(traj, strips.surely_inside(rule), where)  # fail fast, before writing
    return BagTrajectory(traj, kind, where, attitude_range)


def _decimate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices keeping at most ``rate_hz`` samples per second (0: all)."""
    if rate_hz <= 0 or t.size < 3:
        return np.arange(t.size)
    dt = float(np.median(np.diff(t)))
    step = max(1, int(round((1.0 / rate_hz) / dt))) if dt > 0 else 1
    keep = np.arange(0, t.size, step)
    if keep[-1] != t.size - 1:
        keep = np.append(keep, t.size - 1)
    return keep


def _trajectory_kind(traj: Trajectory, traj_file: TrajectoryFile
                     ) -> tuple[str, dict[str, tuple[float, float]]]:
    """What the imported poses carry, in words, and the range of their roll and pitch
    (degrees, from the quaternions written: what the calibration will see)."""
    name = f"{traj_file.kind.value.upper()} {traj_file.path.name}"
    if traj.orientation is None:
        return f"{name}, positions only", {}
    if not traj.full_attitude:
        return f"{name}, with heading only", {}
    roll, pitch, _ = attitude_from_quaternions(traj.orientation)
    ranges = {label: (float(np.degrees(np.nanmin(v))), float(np.degrees(np.nanmax(v))))
              for label, v in (("roll", roll), ("pitch", pitch))}
    return f"{name}, with attitude (roll, pitch, heading)", ranges


# ---------------------------------------------------------------------------- from the rays
def trajectory_from_rays(read: PointsRead, strips: StripAssembly, rule: TimeRule,
                         settings: EstimateSettings) -> BagTrajectory:
    """The trajectory rebuilt from the rays the read pass kept, per strip; strips it cannot
    place are listed in ``dropped_strips`` and said in a warning line, as are those kept
    weak or as level flight.

    Raises
    ------
    TrajectoryError
        No ray at all, or no strip placed.
    """
    assert read.rays is not None
    first_path = read.infos[0].path
    rays = read.rays.rays()
    rays.group = strips.map.map(rays.group.astype(np.uint16), rays.t)
    rays.t = rule.points(rays.t)
    spans = strips.spans(rule)
    if not len(rays):
        first, last = read.returns_seen
        raise TrajectoryError(
            f"{first_path}: no trajectory can be rebuilt from multiple returns: "
            + (f"{first} first and {last} last returns of multi-return "
               "pulses, but no pulse holds both (thinned to one return per pulse?)"
               if first or last else "no point belongs to a pulse with several returns")
            + "; give a trajectory file with --trajectory"
        )
    estimated = estimate_trajectory(rays, spans, settings)
    dropped = sorted(estimated.failed_strips)
    if len(dropped) == len(spans):
        worst = next((q for q in estimated.segments if q.level == "ERROR"), None)
        why = f" (strip {worst.strip_id}: {worst.message})" if worst is not None else ""
        raise TrajectoryError(
            f"{first_path}: no strip's trajectory could be rebuilt from multiple returns"
            f"{why}; give a trajectory file with --trajectory"
        )
    for outcome in estimated.strips:
        if not outcome.kept or outcome.fallback:
            logger.warning("trajectory estimate, %s", outcome.summary)
    return BagTrajectory(estimated.trajectory, "estimated from multiple returns",
                         "trajectory estimate", estimate=estimated, dropped_strips=dropped)


# ---------------------------------------------------------------------------- checks
def check_coverage(traj: Trajectory, strips: list[StripSummary], where: str, *,
                   max_gap_s: float = 2.0) -> None:
    """Every strip's span must lie inside the trajectory, without gaps over ``max_gap_s``
    (the calibration's local line fits need samples on both sides of every point).

    Raises
    ------
    TrajectoryError
        Named ``where``: the first strip not covered.
    """
    tt = traj.t
    for s in strips:
        if not len(tt) or tt[0] > s.t_first or tt[-1] < s.t_last:
            span = f"{tt[0]:.3f}-{tt[-1]:.3f} s" if len(tt) else "nothing"
            raise TrajectoryError(
                f"{where}: trajectory covers {span} but strip {s.strip_id} spans "
                f"{s.t_first:.3f}-{s.t_last:.3f} s; it does not cover the points' times"
            )
        a = max(int(np.searchsorted(tt, s.t_first, side="right")) - 1, 0)
        b = min(int(np.searchsorted(tt, s.t_last, side="left")), len(tt) - 1)
        if b > a:
            gaps = np.diff(tt[a:b + 1])
            k = int(np.argmax(gaps))
            if gaps[k] > max_gap_s:
                raise TrajectoryError(
                    f"{where}: trajectory gap of {gaps[k]:.2f} s at {tt[a + k]:.3f} s inside "
                    f"strip {s.strip_id}; it does not cover the points' times"
                )


def model_note(traj: Trajectory) -> str:
    """The model ``matching.model auto`` gives the whole trajectory, and why."""
    if len(traj) < 2:
        return ""
    choice = choose_model(traj, float(traj.t[0]), float(traj.t[-1]))
    return f"{choice.model} ({choice.reason})"


__all__ = ["BagTrajectory", "DeliveredTrajectory", "check_coverage", "model_note",
           "read_delivered_trajectory", "trajectory_from_file", "trajectory_from_rays"]
