"""The correction of a set of points: a calibration and the radiometric model applied to them.

What ``lidarcal correct``, the corrector node and the QA report share (:func:`correct_columns`,
:func:`correct_cloud`); the steps per point: docs/correction.md, "Per point" (docs/method.md
sections 2-4 and 8). Map frame, metres, radians.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing import correction_kernels
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry, PositioningModel
from lidarcal_ros.core.georeferencing.local_trajectory import (
    DEFAULT_WINDOW,
    TrajectoryWindow,
    WindowLines,
    geometry_on_lines,
    served_by_trajectory,
    window_lines,
)
from lidarcal_ros.core.georeferencing.rigorous import (
    ModelChoice,
    attitude_segments,
    choose_model,
    rigorous_geometry,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals.grid_normals import GridNormals, cell_size, finite_rows, grid_normals
from lidarcal_ros.core.radiometry import RadiometricModel, volume_returns
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryEstimate
from lidarcal_ros.errors import ConfigError, TrajectoryError
from lidarcal_ros.io.calibration_file import CalibrationRecord
from lidarcal_ros.io.cloud.columns import DEFAULT_COORDINATE_TOLERANCE_M, extract_columns
from lidarcal_ros.pipeline.correction.corrected_cloud import (
    NO_ROWS,
    CorrectedColumns,
    RowTarget,
    build_corrected,
)

__all__ = [
    "UNCORRECTED_WARNINGS", "UNCORRECTED_WARNING_S", "CorrectionSettings", "NormalsFit",
    "ServedFrames", "UncorrectedWarnings", "correct_cloud", "correct_columns",
    "flagged_geometry", "served_frames", "surface_points", "trajectory_heading",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CorrectionSettings:
    """Everything the correction of a cloud needs besides the cloud and the trajectory.

    Attributes
    ----------
    delta : (8,) float64
        Biases (docs/method.md order, SI) to remove.
    radiometry : RadiometricModel
    window : TrajectoryWindow
        The local-trajectory window (``matching.trajectory_window_s``).
    heading_source : HeadingSource
        ``matching.heading_source`` (:mod:`lidarcal_ros.core.georeferencing.heading`).
    model : PositioningModel
        ``matching.model`` (:mod:`lidarcal_ros.core.georeferencing.rigorous`); a calibration
        file that says which model estimated its biases decides it (:meth:`from_config`).
    time_field : str
        Cloud field holding the firing time (``time_field``; aliases accepted).
    coordinate_tolerance_m : float
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (``sensor.range_noise_m``;
        :func:`~lidarcal_ros.io.cloud.pointcloud.extract_columns`).
    """

    delta: np.ndarray
    radiometry: RadiometricModel = field(default_factory=RadiometricModel)
    window: TrajectoryWindow = DEFAULT_WINDOW
    heading_source: HeadingSource = HeadingSource.AUTO
    model: PositioningModel = PositioningModel.AUTO
    time_field: str = "t"
    coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M
    #: Each strip's trajectory error, removed with the biases (docs/method.md section 11).
    trajectory_errors: TrajectoryEstimate | None = None

    @classmethod
    def from_config(
        cls, config: FlightConfig, calibration: CalibrationRecord | np.ndarray
    ) -> CorrectionSettings:
        """From a flight configuration and a calibration (record or bias vector).

        The biases are those of the model that estimated them: a calibration whose every
        strip was ``level`` or ``rigorous`` (its ``model``) is applied with that model, a
        ``mixed`` one, or one that does not say, with ``matching.model``.
        """
        delta = (calibration.delta if isinstance(calibration, CalibrationRecord)
                 else np.asarray(calibration, dtype=np.float64))
        model = PositioningModel(config["matching.model"])
        if isinstance(calibration, CalibrationRecord) and calibration.model in (
                PositioningModel.LEVEL, PositioningModel.RIGOROUS):
            model = PositioningModel(calibration.model)
        if delta.shape != (8,) or not np.isfinite(delta).all():
            raise ConfigError(f"calibration: expected 8 finite biases, got {delta}")
        return cls(
            delta=np.asarray(delta, dtype=np.float64),
            radiometry=RadiometricModel.from_config(config),
            window=TrajectoryWindow(float(config["matching.trajectory_window_s"])),
            heading_source=HeadingSource(config["matching.heading_source"]),
            model=model,
            time_field=str(config["time_field"]),
            coordinate_tolerance_m=float(config["sensor.range_noise_m"]),
            trajectory_errors=(calibration.trajectory
                               if isinstance(calibration, CalibrationRecord) else None),
        )


@dataclass(frozen=True)
class ServedFrames:
    """Where the served points of a cloud get their firing position and body frame.

    Attributes
    ----------
    window : (m,) int64
        For each served point in order: its window of ``lines`` (level), or the trajectory
        sample starting its segment (rigorous).
    lines : WindowLines or None
        The local-trajectory lines (level model; None for the rigorous one).
    choice : ModelChoice
        The model the points got, and why.
    """

    window: np.ndarray
    lines: WindowLines | None
    choice: ModelChoice

    @property
    def rigorous(self) -> bool:
        """Whether the points got the rigorous model (no local-trajectory lines)."""
        return self.lines is None


def served_frames(
    t: np.ndarray,
    xyz: np.ndarray,
    trajectory: Trajectory,
    *,
    window: TrajectoryWindow = DEFAULT_WINDOW,
    source: str = "cloud",
    all_finite: bool = False,
    heading_source: HeadingSource = HeadingSource.AUTO,
    model: PositioningModel = PositioningModel.AUTO,
) -> tuple[np.ndarray, ServedFrames | None]:
    """The points the trajectory can serve
    (:func:`~lidarcal_ros.core.georeferencing.local_trajectory.served_by_trajectory`;
    ``all_finite``: the caller knows every point and time to be finite) and how they get their
    frames, by the model ``matching.model`` chooses
    (:func:`~lidarcal_ros.core.georeferencing.rigorous.choose_model`; ``heading_source`` as
    :func:`~lidarcal_ros.core.georeferencing.local_trajectory.window_lines`), flagging the others
    instead of raising.

    Returns
    -------
    ok : (n,) bool
        Finite point and time, covered by the trajectory, at least 1 m below it.
    frames : ServedFrames or None
        For the points ``ok`` (in order); None when there are none.
    """
    ok = served_by_trajectory(t, xyz, trajectory, window=window, all_finite=all_finite)
    if not ok.any():
        return ok, None
    ts = t if ok.all() else t[ok]
    try:
        choice = choose_model(trajectory, float(ts[0]), float(ts[-1]), mode=model,
                              heading_source=heading_source, source=source)
        if choice.model == PositioningModel.RIGOROUS:
            segment = attitude_segments(ts, trajectory, source=source)
            return ok, ServedFrames(segment, None, choice)
        lines = window_lines(ts, trajectory, window=window, source=source,
                             heading_source=heading_source)
    except TrajectoryError as exc:
        UNCORRECTED_WARNINGS.left_uncorrected(ok, source, exc)
        return ok, None
    return ok, ServedFrames(lines.window, lines, choice)


def flagged_geometry(
    t: np.ndarray,
    xyz: np.ndarray,
    trajectory: Trajectory,
    *,
    window: TrajectoryWindow = DEFAULT_WINDOW,
    source: str = "cloud",
    heading_source: HeadingSource = HeadingSource.AUTO,
    model: PositioningModel = PositioningModel.AUTO,
) -> tuple[np.ndarray, LaserGeometry]:
    """The laser geometry of the points :func:`served_frames` serves (in order, for the
    points ``ok``; :func:`~lidarcal_ros.core.georeferencing.rigorous.rigorous_geometry` or
    :func:`~lidarcal_ros.core.georeferencing.local_trajectory.geometry_on_lines`), flagging the
    others instead of raising."""
    ok, frames = served_frames(t, xyz, trajectory, window=window, source=source,
                               heading_source=heading_source, model=model)
    if frames is not None:
        sel = slice(None) if ok.all() else ok
        try:
            if frames.lines is None:
                return ok, rigorous_geometry(t[sel], xyz[sel], trajectory, window=window,
                                             source=source)
            return ok, geometry_on_lines(t[sel], xyz[sel], frames.lines, source=source)
        except TrajectoryError as exc:
            UNCORRECTED_WARNINGS.left_uncorrected(ok, source, exc)
    return ok, LaserGeometry.empty()


#: Least wall time between two warnings of clouds left uncorrected from one source, s: a
#: stream of 20 clouds a second through a trajectory gap (or with 'attitude' asked of poses
#: without orientation) would otherwise log every cloud; the flags and counts say the rest.
UNCORRECTED_WARNING_S = 10.0


class UncorrectedWarnings:
    """Say why the clouds of a source were left uncorrected, at most every ``every_s`` of
    wall time per source, counting the clouds passed over in silence in between.

    Parameters
    ----------
    every_s : float
        Least wall time between two warnings of one source, s.
    clock : callable() -> float
        Wall time, s (:func:`time.monotonic`; a test may put another in :attr:`clock`).
    """

    def __init__(self, every_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self.clock = clock
        # per source: when it last warned (s of ``clock``) and the clouds passed over since
        self._last: dict[str, tuple[float, int]] = {}

    def passed_over(self, source: str) -> int:
        """Clouds of ``source`` left uncorrected since its last warning, not warned of."""
        return self._last.get(source, (-math.inf, 0))[1]

    def left_uncorrected(self, ok: np.ndarray, source: str, exc: TrajectoryError) -> None:
        """Flag every point ``ok`` of a cloud as not served, and say why (or count it)."""
        now = self.clock()
        last, since = self._last.get(source, (-math.inf, 0))
        if now - last >= self.every_s:
            more = f" (and {since} more clouds since the last warning)" if since else ""
            logger.warning("%s: %s; %d points left uncorrected%s", source, exc, int(ok.sum()),
                           more)
            self._last[source] = (now, 0)
        else:
            self._last[source] = (last, since + 1)
        ok[:] = False


#: The warnings of every correction in this process.
UNCORRECTED_WARNINGS = UncorrectedWarnings(UNCORRECTED_WARNING_S)


def trajectory_heading(trajectory: Trajectory, t: float) -> float:
    """Heading ``kappa`` (rad, ``atan2(-d_x, d_y)``) of the trajectory around time ``t``
    (0 if undefined)."""
    n = len(trajectory)
    if n < 2 or not math.isfinite(t):
        return 0.0
    i = int(np.clip(np.searchsorted(trajectory.t, t), 1, n - 1))
    a, b = max(i - 2, 0), min(i + 2, n - 1)
    d = trajectory.xyz[b] - trajectory.xyz[a]
    if math.hypot(d[0], d[1]) <= 0:
        return 0.0
    return math.atan2(-d[0], d[1])


@dataclass(frozen=True)
class NormalsFit:
    """How :func:`correct_columns` fits the normals of points whose normals it is not given.

    Attributes
    ----------
    group : (n,) int or None
        Strip id per point; points of different strips are never neighbours for normals.
    context_xyz : (m, 3) float64 or None
        Further delivered points, map frame, m, that are neighbours but not corrected (the
        end of the previous chunk, the start of the next).
    context_group : (m,) int or None
        The strip of each context point.
    heading : float or None
        Flight heading, rad, to align the normals' grid with; default: the trajectory's at
        the points' median time (:func:`trajectory_heading`).
    cell_m : (float, float) or None
        Grid cell ``(along, across)`` of the normals, m; default
        :func:`~lidarcal_ros.core.normals.grid_normals.cell_size` of the points.
    """

    group: np.ndarray | None = None
    context_xyz: np.ndarray | None = None
    context_group: np.ndarray | None = None
    heading: float | None = None
    cell_m: tuple[float, float] | None = None


def _fitted_normals(xyz: np.ndarray, t: np.ndarray, trajectory: Trajectory,
                    fit: NormalsFit) -> GridNormals:
    """Grid normals of points fitted with their context (:func:`correct_columns`)."""
    n = xyz.shape[0]
    group, context_xyz, context_group = fit.group, fit.context_xyz, fit.context_group
    heading, cell_m = fit.heading, fit.cell_m
    if heading is None:
        heading = trajectory_heading(trajectory, float(np.nanmedian(t)))
    # Normals from the delivered coordinates of the points and their context.
    if context_xyz is not None and len(context_xyz):
        all_xyz = np.concatenate([xyz, context_xyz])
        all_group = None
        if group is not None or context_group is not None:
            g0 = group if group is not None else np.zeros(n, dtype=np.int64)
            g1 = (context_group if context_group is not None
                  else np.zeros(len(context_xyz), dtype=np.int64))
            all_group = np.concatenate([np.asarray(g0, dtype=np.int64),
                                        np.asarray(g1, dtype=np.int64)])
    else:
        all_xyz, all_group = xyz, group
    if cell_m is None:
        finite = finite_rows(xyz) & np.isfinite(t)
        cell_m = cell_size(xyz[finite], heading, t[finite])
    return grid_normals(all_xyz, heading, cell_m=cell_m, group=all_group)


def surface_points(xyz: np.ndarray, volume: np.ndarray | None) -> np.ndarray:
    """The points a normals grid takes: ``xyz`` (map frame, m) with the volume returns
    (``volume``, or None: none) made NaN, which leaves them out of the grid (no normal, and
    nobody's neighbour); ``xyz`` itself when there are none."""
    if volume is None or not volume.any():
        return xyz
    out = xyz.copy()
    out[volume] = np.nan
    return out


def correct_columns(
    xyz: np.ndarray,
    t: np.ndarray,
    intensity: np.ndarray | None,
    trajectory: Trajectory,
    settings: CorrectionSettings,
    *,
    normals: GridNormals | NormalsFit | None = None,
    source: str = "cloud",
    all_finite: bool = False,
    rows: RowTarget | None = None,
    volume: np.ndarray | None = None,
    strip_id: np.ndarray | int | None = None,
) -> CorrectedColumns:
    """Correct the geometry and compute reflectance of a set of points (docs/correction.md).

    Parameters
    ----------
    xyz : (n, 3) float64
        Delivered points, map frame, m.
    t : (n,) float64
        Firing times, s, on the trajectory's clock.
    intensity : (n,) float or None
        Recorded intensity; None (or NaN per point) gives NaN reflectance.
    trajectory : Trajectory
    settings : CorrectionSettings
    normals : GridNormals or NormalsFit, optional
        The points' normals when already known (the
        :class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector` fits them per strip
        as the clouds arrive), else how to fit them (default ``NormalsFit()``: the points on
        their own, one strip, the grid along the trajectory's heading).
    source : str
        Named in log messages.
    all_finite : bool
        Every point and time is known to be finite (the check is skipped).
    rows : RowTarget, optional
        Write the corrected cloud of the points
        (:func:`~lidarcal_ros.pipeline.correction.corrected_cloud.row_target`) instead of the
        columns, which are then returned empty (one pass less over the points).
    volume : (n,) bool, optional
        Volume returns (:func:`~lidarcal_ros.core.radiometry.volume_returns`): no
        incidence correction; left out of the normals fitted here (given normals should
        have left them out too).

    Returns
    -------
    CorrectedColumns
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.float64)
    if settings.trajectory_errors is not None and strip_id is not None and t.size:
        # X_b - e_s(t) (docs/method.md section 11); the firing positions stay the delivered ones,
        # which moves each laser vector by e (centimetres of hundreds of metres: below 1e-4
        # of the biases' correction and of the range)
        xyz = xyz - settings.trajectory_errors.errors(strip_id, t)
    n = t.shape[0]
    m = 0 if rows is not None else n  # (the columns are written without rows)
    flags = np.empty(m, dtype=np.uint8)
    rng = np.empty(m, dtype=np.float32)
    inc = np.empty(m, dtype=np.float32)
    scan = np.empty(m, dtype=np.float32)
    refl = np.empty(m, dtype=np.float32)
    out_xyz = np.empty((m, 3))
    if n == 0:
        return CorrectedColumns(out_xyz, rng, inc, scan, refl, flags)
    ok, frames = served_frames(t, xyz, trajectory, window=settings.window, source=source,
                               all_finite=all_finite, heading_source=settings.heading_source,
                               model=settings.model)
    gn = normals if isinstance(normals, GridNormals) else _fitted_normals(
        surface_points(xyz, volume), t, trajectory,
        normals if normals is not None else NormalsFit())
    lines = _NO_LINES if frames is None or frames.lines is None else frames.lines
    rigorous = frames is not None and frames.rigorous
    q = trajectory.orientation
    correction_kernels.correct_returns(
        t, xyz, ok, _NO_WINDOW if frames is None else frames.window, rigorous,
        (lines.t_mean, lines.p_mean, lines.velocity, lines.cos_kappa, lines.sin_kappa),
        (trajectory.t, trajectory.xyz, q if rigorous and q is not None else _NO_QUATERNIONS),
        np.asarray(settings.delta, dtype=np.float64),
        np.ascontiguousarray(gn.normals[:n], dtype=np.float64),
        _NO_ROUGH if gn.rough is None else np.ascontiguousarray(gn.rough[:n]),
        _NO_ROUGH if volume is None else np.ascontiguousarray(volume, dtype=bool),
        _NO_INTENSITY if intensity is None else np.ascontiguousarray(intensity,
                                                                      dtype=np.float32),
        settings.radiometry.kernel_constants(), (out_xyz, rng, inc, scan, refl, flags),
        NO_ROWS if rows is None else rows)
    return CorrectedColumns(out_xyz, rng, inc, scan, refl, flags, gn.cell_m,
                            None if frames is None else frames.choice)


#: "None" of the compiled correction's optional columns.
_NO_ROUGH = np.zeros(0, dtype=bool)
_NO_INTENSITY = np.zeros(0, dtype=np.float32)
_NO_WINDOW = np.zeros(0, dtype=np.int64)
_NO_QUATERNIONS = np.zeros((0, 4))
_NO_LINES = WindowLines(_NO_WINDOW, np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)),
                        np.zeros(1), np.zeros(1), np.zeros(1))


def correct_cloud(
    points: np.ndarray,
    trajectory: Trajectory,
    settings: CorrectionSettings,
    *,
    context: np.ndarray | None = None,
    source: str = "cloud",
) -> tuple[np.ndarray, CorrectedColumns]:
    """Correct one cloud (a structured point array) on its own.

    Parameters
    ----------
    points : structured array
        Fields of docs/interface.md (``x, y, z``, time, optional ``intensity``, ``strip_id``).
    trajectory : Trajectory
    settings : CorrectionSettings
    context : (m, 3) float64, optional
        Delivered neighbours for the normals (e.g. the previous cloud's points).
    source : str
        Topic or file named in messages.

    Returns
    -------
    corrected : structured array
        :func:`~lidarcal_ros.pipeline.correction.corrected_cloud.corrected_dtype` of the input.
    columns : CorrectedColumns
    """
    cols = extract_columns(points, time_field=settings.time_field, source=source,
                           coordinate_tolerance_m=settings.coordinate_tolerance_m)
    res = correct_columns(cols.xyz, cols.t, cols.intensity, trajectory, settings,
                          normals=NormalsFit(group=cols.strip_id, context_xyz=context),
                          source=source,
                          volume=volume_returns(cols.return_number, cols.number_of_returns),
                          strip_id=cols.strip_id)
    return build_corrected(points, res), res
