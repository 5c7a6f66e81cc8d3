"""Apply a calibration and the radiometric model to clouds: `lidarcal correct` and the
corrector node share this module.

Per point (method.md sections 2-4 and 8), steps 1-3 and 5 in one compiled pass
(:func:`lidarcal_ros.core.correction_kernels.correct_returns`):

1. the local trajectory gives ``x, z, kappa, beta`` and the firing position ``X_o(t)``
   (:func:`lidarcal_ros.core.local_trajectory.laser_geometry`);
2. the point is moved by the estimated biases, ``X_c = X_b - A(x, z, kappa, beta) delta``
   (eq. [13], :func:`lidarcal_ros.core.model.correct_points`);
3. ``range = |X_c - X_o|`` (m), laser direction ``l = (X_c - X_o) / range``, and
   ``scan_angle = atan(x_c / z_c)`` (rad, method.md's ``beta`` of the corrected point, positive
   to the left of the flight direction). This is the physical mirror angle: the recorded one
   divided by the scale ``1 + dS``, i.e. ``(1 - dS) beta`` to first order. The firing point is
   taken at the IMU origin: the lever arm itself (not only its bias) is unknown to the
   quasi-rigorous method; at airborne ranges it changes angles by < 1e-3 rad;
4. the local surface normal from a grid plane fit over the point's neighbourhood in its own
   strip (:mod:`lidarcal_ros.core.normals`), ``incidence = arccos |n . l|`` (rad);
5. ``reflectance`` by the radar equation (:mod:`lidarcal_ros.core.radiometry`), with
   ``cos(incidence)`` clamped at ``radiometry.min_cos_incidence``; where the normal is
   uncertain (flagged rough or grazing) the incidence term is bounded at
   ``radiometry.uncertain_incidence_max_deg`` (60 deg): at building edges a plane mixing roof
   and ground gives a steep incidence that the surface does not have, and dividing by its
   cosine would make the point several times too bright (the incidence field keeps the
   estimate; the flags say it is uncertain).

Normals are fitted to the delivered (uncorrected) coordinates: the correction is a smooth field
(its gradient is of the order of the boresight angles and ``dS``, below 1e-3), so it would turn
the normals by less than 0.1 deg, and this way the context points of neighbouring chunks need
no correction of their own and points the trajectory does not cover still help their neighbours.

Output: every input field, ``x, y, z`` corrected (in their own type), and the FLOAT32 fields
``reflectance``, ``range``, ``incidence``, ``scan_angle`` plus the UINT8 ``correction_flags``
(bits below). Nothing is silently wrong: a point that cannot be corrected keeps its delivered
coordinates, gets NaN in the four derived fields and a flag, and is counted.

Streaming: :class:`StreamCorrector` takes clouds one at a time. The points of each strip
join one grid of cells (:class:`~lidarcal_ros.core.strip_normals.StripNormals`), each point binned
and evaluated once, so the normals do not depend on how the stream is cut into clouds: a
cloud is released once the clouds after it cover the grid rows its normals read (the
look-ahead), or at once without look-ahead. Clouds are corrected in batches
(``batch_points``; 0 = each cloud as soon as it can be, as the node does). Memory holds the
clouds waiting for their look-ahead and a few grid rows, whatever the mission length.
"""

from __future__ import annotations

import functools
import heapq
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core import correction_kernels
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
)
from lidarcal_ros.core.geometry import LEVEL, RIGOROUS, LaserGeometry
from lidarcal_ros.core.georeferencing import (
    ModelChoice,
    attitude_segments,
    check_model_setting,
    choose_model,
    rigorous_geometry,
)
from lidarcal_ros.core.heading import check_orientation
from lidarcal_ros.core.local_trajectory import (
    WindowLines,
    geometry_on_lines,
    served_by_trajectory,
    window_lines,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals import (
    GridNormals,
    cell_size,
    finite_rows,
    grid_normals,
    no_normals,
)
from lidarcal_ros.core.radiometry import RadiometricModel, describe_alpha
from lidarcal_ros.core.strip_normals import NormalsTask, StripNormals
from lidarcal_ros.errors import (
    BagError,
    ConfigError,
    InputError,
    LidarcalError,
    TrajectoryError,
)
from lidarcal_ros.io.calibration_file import CalibrationRecord, read_calibration
from lidarcal_ros.io.cloud_columns import (
    DEFAULT_COORDINATE_TOLERANCE_M,
    CloudColumns,
    extract_columns,
    float32_warning,
    resolve_time_field,
    time_span,
)
from lidarcal_ros.io.pointcloud import cloud_to_array, make_point_dtype
from lidarcal_ros.io.prefetch import prefetched

logger = logging.getLogger(__name__)

#: Fields added to the corrected clouds (name, numpy type).
ADDED_FIELDS: tuple[tuple[str, str], ...] = (
    ("reflectance", "<f4"),
    ("range", "<f4"),
    ("incidence", "<f4"),
    ("scan_angle", "<f4"),
    ("correction_flags", "u1"),
)
#: Default batch of the offline correction, points.
DEFAULT_BATCH_POINTS = 200_000
#: Most points of a strip held for their look-ahead beyond a batch: bounds memory when the
#: points stop advancing along track (they would otherwise wait for ever).
_MAX_LOOKAHEAD_POINTS = 500_000
#: A strip's normals grid is restarted after a turn of more than this (rad) or a gap in time
#: of more than this (s): the grid is aligned with the flight line.
_MAX_GRID_TURN_RAD = math.radians(15.0)
_MAX_GRID_GAP_S = 2.0
#: Points per LAS write (corrected clouds are gathered into runs of this size).
_LAS_RUN_POINTS = 100_000

# ---------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class CorrectionSettings:
    """Everything the correction of a cloud needs besides the cloud and the trajectory.

    Attributes
    ----------
    delta : (8,) float64
        Biases (method.md order, SI) to remove.
    radiometry : RadiometricModel
    window_s : float
        Half-width of the local-trajectory window, s (``matching.trajectory_window_s``).
    min_samples : int
        Fewest trajectory samples in a window.
    heading_source : str
        ``matching.heading_source`` (:mod:`lidarcal_ros.core.heading`).
    model : str
        ``matching.model``: ``auto``, ``level`` or ``rigorous``
        (:mod:`lidarcal_ros.core.georeferencing`); a calibration file that says which model
        estimated its biases decides it (:meth:`from_config`).
    time_field : str
        Cloud field holding the firing time (``time_field``; aliases accepted).
    coordinate_tolerance_m : float
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (``sensor.range_noise_m``;
        :func:`~lidarcal_ros.io.cloud_columns.extract_columns`).
    """

    delta: np.ndarray
    radiometry: RadiometricModel = field(default_factory=RadiometricModel)
    window_s: float = 0.5
    min_samples: int = 2
    heading_source: str = "auto"
    model: str = "auto"
    time_field: str = "t"
    coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M

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
        model = str(config["matching.model"])
        if isinstance(calibration, CalibrationRecord) and calibration.model in (LEVEL,
                                                                              RIGOROUS):
            model = calibration.model
        if delta.shape != (8,) or not np.isfinite(delta).all():
            raise ConfigError(f"calibration: expected 8 finite biases, got {delta}")
        return cls(
            delta=np.asarray(delta, dtype=np.float64),
            radiometry=RadiometricModel.from_config(config),
            window_s=float(config["matching.trajectory_window_s"]),
            heading_source=str(config["matching.heading_source"]),
            model=model,
            time_field=str(config["time_field"]),
            coordinate_tolerance_m=float(config["sensor.range_noise_m"]),
        )


@dataclass
class CorrectionStats:
    """Counts over everything corrected so far."""

    clouds: int = 0
    points: int = 0
    not_corrected: int = 0
    grazing: int = 0
    no_normal: int = 0
    no_intensity: int = 0
    rough: int = 0
    seconds: float = 0.0
    non_finite: int = 0  # points with a non-finite coordinate (also not corrected)
    #: Points corrected by each point-positioning model, and the latest reason each was
    #: chosen (:mod:`lidarcal_ros.core.georeferencing`).
    model_points: dict[str, int] = field(default_factory=dict)
    model_reason: dict[str, str] = field(default_factory=dict)

    def add_model(self, model: str, reason: str, points: int) -> None:
        """Count ``points`` corrected by ``model`` (chosen for ``reason``)."""
        self.model_points[model] = self.model_points.get(model, 0) + points
        self.model_reason[model] = reason

    def describe_models(self) -> str:
        """One line on the models the points got, e.g. ``"rigorous (INS attitude at 50 Hz)
        for 100% of the points"``."""
        total = sum(self.model_points.values())
        if not total:
            return "no point corrected"
        return "; ".join(f"{m} ({self.model_reason[m]}) for "
                         f"{100.0 * k / total:.0f}% of the points"
                         for m, k in sorted(self.model_points.items(), key=lambda kv: -kv[1]))

    def add(self, tally: CloudTally) -> None:
        """Count a corrected cloud (or several: tallies add up)."""
        self.points += tally.points
        self.non_finite += int(tally.counts[256])
        self.not_corrected += tally.flagged(FLAG_NOT_CORRECTED)
        self.grazing += tally.flagged(FLAG_GRAZING)
        self.no_normal += tally.flagged(FLAG_NO_NORMAL)
        self.no_intensity += tally.flagged(FLAG_NO_INTENSITY)
        self.rough += tally.flagged(FLAG_ROUGH)


#: Each possible ``correction_flags`` byte, the index of :attr:`CloudTally.counts`.
_FLAG_BYTES = np.arange(256)


@dataclass(frozen=True)
class CloudTally:
    """What a corrected cloud holds, counted while it was built (:func:`build_corrected`).

    Attributes
    ----------
    counts : (257,) int64
        ``counts[f]``: the points whose ``correction_flags`` byte is ``f``; ``counts[256]``:
        the points with a non-finite coordinate (kept from the input: such a point cannot
        be corrected).
    """

    counts: np.ndarray

    @classmethod
    def empty(cls) -> CloudTally:
        return cls(np.zeros(257, dtype=np.int64))

    @property
    def points(self) -> int:
        return int(self.counts[:256].sum())

    @property
    def dense(self) -> bool:
        """Every coordinate finite (PointCloud2's ``is_dense``)."""
        return int(self.counts[256]) == 0

    def flagged(self, mask: int) -> int:
        """Points with any of the bits of ``mask`` set."""
        return int(self.counts[:256][(_FLAG_BYTES & mask) != 0].sum())

    def __add__(self, other: CloudTally) -> CloudTally:
        return CloudTally(self.counts + other.counts)


# ---------------------------------------------------------------------------- core
@dataclass
class CorrectedColumns:
    """Per-point results of :func:`correct_columns`.

    Attributes
    ----------
    xyz : (n, 3) float64
        Corrected points (delivered ones where not corrected), map frame, m.
    range, incidence, scan_angle, reflectance : (n,) float32
        m, rad, rad, and the reflectance of :mod:`lidarcal_ros.core.radiometry` (Lambertian
        with a calibration constant, else relative in intensity units); NaN where unknown.
    flags : (n,) uint8
        ``FLAG_*`` bits.
    cell_m : (float, float)
        Grid cell ``(along, across)`` of the normals, m.
    """

    xyz: np.ndarray
    range: np.ndarray
    incidence: np.ndarray
    scan_angle: np.ndarray
    reflectance: np.ndarray
    flags: np.ndarray
    cell_m: tuple[float, float] = (math.nan, math.nan)
    #: The point-positioning model of the served points, and why
    #: (:func:`~lidarcal_ros.core.georeferencing.choose_model`); None where none was served.
    choice: ModelChoice | None = None

    def __len__(self) -> int:
        return int(self.flags.shape[0])


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
        return self.lines is None


def served_frames(
    t: np.ndarray,
    xyz: np.ndarray,
    trajectory: Trajectory,
    *,
    window_s: float = 0.5,
    min_samples: int = 2,
    source: str = "cloud",
    all_finite: bool = False,
    heading_source: str = "auto",
    model: str = "auto",
) -> tuple[np.ndarray, ServedFrames | None]:
    """The points the trajectory can serve
    (:func:`~lidarcal_ros.core.local_trajectory.served_by_trajectory`; ``all_finite``: the
    caller knows every point and time to be finite) and how they get their frames, by the
    model ``matching.model`` chooses (:func:`~lidarcal_ros.core.georeferencing.choose_model`;
    ``heading_source`` as :func:`~lidarcal_ros.core.local_trajectory.window_lines`),
    flagging the others instead of raising.

    Returns
    -------
    ok : (n,) bool
        Finite point and time, covered by the trajectory, at least 1 m below it.
    frames : ServedFrames or None
        For the points ``ok`` (in order); None when there are none.
    """
    ok = served_by_trajectory(t, xyz, trajectory, window_s=window_s,
                              min_samples=min_samples, all_finite=all_finite)
    if not ok.any():
        return ok, None
    ts = t if ok.all() else t[ok]
    try:
        choice = choose_model(trajectory, float(ts[0]), float(ts[-1]), mode=model,
                              heading_source=heading_source, source=source)
        if choice.model == RIGOROUS:
            segment = attitude_segments(ts, trajectory, source=source)
            return ok, ServedFrames(segment, None, choice)
        lines = window_lines(ts, trajectory, window_s=window_s, min_samples=min_samples,
                             source=source, heading_source=heading_source)
    except TrajectoryError as exc:
        _left_uncorrected(ok, source, exc)
        return ok, None
    return ok, ServedFrames(lines.window, lines, choice)


def flagged_geometry(
    t: np.ndarray,
    xyz: np.ndarray,
    trajectory: Trajectory,
    *,
    window_s: float = 0.5,
    min_samples: int = 2,
    source: str = "cloud",
    heading_source: str = "auto",
    model: str = "auto",
) -> tuple[np.ndarray, LaserGeometry]:
    """The laser geometry of the points :func:`served_frames` serves (in order, for the
    points ``ok``; :func:`~lidarcal_ros.core.georeferencing.rigorous_geometry` or
    :func:`~lidarcal_ros.core.local_trajectory.geometry_on_lines`), flagging the others
    instead of raising."""
    ok, frames = served_frames(t, xyz, trajectory, window_s=window_s,
                               min_samples=min_samples, source=source,
                               heading_source=heading_source, model=model)
    if frames is not None:
        sel = slice(None) if ok.all() else ok
        try:
            if frames.lines is None:
                return ok, rigorous_geometry(t[sel], xyz[sel], trajectory, window_s=window_s,
                                             min_samples=min_samples, source=source)
            return ok, geometry_on_lines(t[sel], xyz[sel], frames.lines, source=source)
        except TrajectoryError as exc:
            _left_uncorrected(ok, source, exc)
    return ok, LaserGeometry.empty()


#: Least wall time between two warnings of clouds left uncorrected from one source, s: a
#: stream of 20 clouds a second through a trajectory gap (or with 'attitude' asked of poses
#: without orientation) would otherwise log every cloud; the flags and counts say the rest.
UNCORRECTED_WARNING_S = 10.0
#: Per source: when it last warned (monotonic s) and the clouds left uncorrected since.
_uncorrected_warned: dict[str, tuple[float, int]] = {}


def _left_uncorrected(ok: np.ndarray, source: str, exc: TrajectoryError) -> None:
    """Flag every point ``ok`` of a cloud as not served, and say why (at most every
    :data:`UNCORRECTED_WARNING_S` per source, with the clouds passed over in silence)."""
    now = time.monotonic()
    last, since = _uncorrected_warned.get(source, (-math.inf, 0))
    if now - last >= UNCORRECTED_WARNING_S:
        more = f" (and {since} more clouds since the last warning)" if since else ""
        logger.warning("%s: %s; %d points left uncorrected%s", source, exc, int(ok.sum()), more)
        _uncorrected_warned[source] = (now, 0)
    else:
        _uncorrected_warned[source] = (last, since + 1)
    ok[:] = False


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


def _fitted_normals(
    xyz: np.ndarray, t: np.ndarray, trajectory: Trajectory, *, group: np.ndarray | None,
    context_xyz: np.ndarray | None, context_group: np.ndarray | None,
    heading: float | None, cell_m: tuple[float, float] | None,
) -> GridNormals:
    """Grid normals of points fitted with their context (:func:`correct_columns`)."""
    n = xyz.shape[0]
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


def correct_columns(
    xyz: np.ndarray,
    t: np.ndarray,
    intensity: np.ndarray | None,
    trajectory: Trajectory,
    settings: CorrectionSettings,
    *,
    group: np.ndarray | None = None,
    context_xyz: np.ndarray | None = None,
    context_group: np.ndarray | None = None,
    heading: float | None = None,
    cell_m: tuple[float, float] | None = None,
    normals: GridNormals | None = None,
    source: str = "cloud",
    all_finite: bool = False,
    rows: RowTarget | None = None,
) -> CorrectedColumns:
    """Correct the geometry and compute reflectance of a set of points (module docstring).

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
    group : (n,) int, optional
        Strip id per point; points of different strips are never neighbours for normals.
    context_xyz, context_group : optional
        Further delivered points (and their strips) that are neighbours but not corrected
        (the end of the previous chunk, the start of the next).
    heading : float, optional
        Flight heading (rad) to align the normals' grid; default from the trajectory.
    cell_m : (float, float), optional
        Grid cell ``(along, across)`` of the normals (m); default
        :func:`~lidarcal_ros.core.normals.cell_size` of ``xyz``.
    normals : GridNormals, optional
        The points' normals when already known (:class:`StreamCorrector` fits them per
        strip as the clouds arrive); then ``group``, ``context_*``, ``heading`` and
        ``cell_m`` are not used.
    source : str
        Named in log messages.
    all_finite : bool
        Every point and time is known to be finite (the check is skipped).
    rows : RowTarget, optional
        Write the corrected cloud of the points (:func:`row_target`) instead of the
        columns, which are then returned empty (one pass less over the points).

    Returns
    -------
    CorrectedColumns
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.float64)
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
    ok, frames = served_frames(t, xyz, trajectory, window_s=settings.window_s,
                               min_samples=settings.min_samples, source=source,
                               all_finite=all_finite, heading_source=settings.heading_source,
                               model=settings.model)
    gn = normals if normals is not None else _fitted_normals(
        xyz, t, trajectory, group=group, context_xyz=context_xyz, context_group=context_group,
        heading=heading, cell_m=cell_m)
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
        _NO_INTENSITY if intensity is None else np.ascontiguousarray(intensity,
                                                                      dtype=np.float32),
        settings.radiometry.kernel_constants(), (out_xyz, rng, inc, scan, refl, flags),
        _NO_ROWS if rows is None else rows)
    return CorrectedColumns(out_xyz, rng, inc, scan, refl, flags, gn.cell_m,
                            None if frames is None else frames.choice)


#: The rows of a corrected cloud as the compiled loops write them
#: (:func:`row_target`): the output and input rows as words, the output's fields ``x, y, z,
#: reflectance, range, incidence, scan_angle, correction_flags`` and the tally's counts.
RowTarget = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                  np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: "None" of the compiled correction's optional columns.
_NO_ROUGH = np.zeros(0, dtype=bool)
_NO_INTENSITY = np.zeros(0, dtype=np.float32)
_NO_WINDOW = np.zeros(0, dtype=np.int64)
_NO_QUATERNIONS = np.zeros((0, 4))
_NO_ROWS: RowTarget = (np.zeros((0, 1), np.uint64), np.zeros((0, 1), np.uint64), np.zeros(0),
                       np.zeros(0), np.zeros(0), np.zeros(0, np.float32),
                       np.zeros(0, np.float32), np.zeros(0, np.float32),
                       np.zeros(0, np.float32), np.zeros(0, np.uint8),
                       np.zeros(257, np.int64))
_NO_LINES = WindowLines(_NO_WINDOW, np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)),
                        np.zeros(1), np.zeros(1), np.zeros(1))


# ---------------------------------------------------------------------------- clouds
@functools.lru_cache(maxsize=64)  # (a stream has one or two layouts; each cloud asks)
def corrected_dtype(dtype: np.dtype[Any]) -> np.dtype[Any]:
    """The layout of a corrected cloud: the input fields at their offsets (minus any named
    like an added one), then :data:`ADDED_FIELDS` (4-byte aligned)."""
    added = {name for name, _ in ADDED_FIELDS}
    fields: Mapping[str, Any] = dtype.fields or {}
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for name, (fdt, off, *_rest) in fields.items():
        if name in added:
            continue
        names.append(name)
        formats.append(fdt)
        offsets.append(int(off))
    pos = (dtype.itemsize + 3) // 4 * 4
    for name, kind in ADDED_FIELDS:
        k = np.dtype(kind)
        pos = (pos + k.itemsize - 1) // k.itemsize * k.itemsize
        names.append(name)
        formats.append(k)
        offsets.append(pos)
        pos += k.itemsize
    itemsize = (pos + 7) // 8 * 8
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": itemsize})


def build_corrected(points: np.ndarray, res: CorrectedColumns, a: int = 0,
                    b: int | None = None, *, out: np.ndarray | None = None,
                    tally: CloudTally | None = None) -> np.ndarray:
    """The corrected cloud of ``points`` from rows ``a:b`` of ``res``.

    Parameters
    ----------
    out : structured array, optional
        Where to build it: ``len(points)`` rows of ``corrected_dtype(points.dtype)`` (for
        instance in the buffer a message is serialised into); by default a new array.
        Every byte of it is written: the input's bytes, the added fields and zeros between
        them, so the bytes do not depend on what the buffer held. Its rows must be
        contiguous.
    tally : CloudTally, optional
        Counts of the cloud's flags and non-finite points to add to (in the same pass as
        the rows are written).
    """
    n = len(points)
    b = a + n if b is None else b
    dtype = corrected_dtype(points.dtype)
    fresh = out is None
    if out is None:
        out = np.zeros(n, dtype=dtype)  # (cheaper than zeroing the gaps between fields)
    elif out.dtype != dtype or out.shape != (n,):
        raise ValueError(f"output of {out.shape} {out.dtype} for {n} points of {dtype}")
    if n == 0:
        return out
    points = np.ascontiguousarray(points)
    counts = tally.counts if tally is not None else np.zeros(257, dtype=np.int64)
    target = row_target(points, out, counts)
    if target is not None:
        # The usual layout: one compiled pass row by row instead of nine over the output.
        (out_words, in_words, x, y, z, reflectance, range_m, incidence, scan_angle,
         flags, _) = target
        correction_kernels.fill_corrected_rows(
            out_words, in_words, x, y, z, res.xyz[a:b], reflectance, range_m, incidence,
            scan_angle, flags, res.reflectance[a:b], res.range[a:b], res.incidence[a:b],
            res.scan_angle[a:b], res.flags[a:b], counts)
        return out
    if tally is not None:
        counts[:256] += correction_kernels.byte_counts(np.ascontiguousarray(res.flags[a:b]))
        counts[256] += int(np.count_nonzero(~np.isfinite(res.xyz[a:b]).all(axis=1)))
    if not fresh:
        # A used buffer: zero the added part of each row (whole 8-byte words; the row size
        # is a multiple of 8) before the input's bytes go in front of it.
        words = out.view(np.uint64).reshape(n, dtype.itemsize // 8)
        words[:, points.dtype.itemsize // 8:] = 0
    rows = out.view(np.uint8).reshape(n, dtype.itemsize)
    rows[:, :points.dtype.itemsize] = points.view(np.uint8).reshape(n, points.dtype.itemsize)
    out["x"] = res.xyz[a:b, 0]
    out["y"] = res.xyz[a:b, 1]
    out["z"] = res.xyz[a:b, 2]
    out["reflectance"] = res.reflectance[a:b]
    out["range"] = res.range[a:b]
    out["incidence"] = res.incidence[a:b]
    out["scan_angle"] = res.scan_angle[a:b]
    out["correction_flags"] = res.flags[a:b]
    return out


def row_target(points: np.ndarray, out: np.ndarray, counts: np.ndarray) -> RowTarget | None:
    """Where the compiled loops write the corrected cloud of ``points`` (contiguous) into
    ``out`` (``len(points)`` rows of :func:`corrected_dtype`, contiguous) and count its flags
    into ``counts`` (a :class:`CloudTally`'s); None for a layout whose rows are not whole
    4-byte words. The rows are copied in 8-byte words where both layouts allow (the
    corrected rows always do)."""
    if points.dtype.itemsize % 4:
        return None
    n = len(points)
    word = np.dtype(np.uint64 if points.dtype.itemsize % 8 == 0 else np.uint32)
    return (out.view(word).reshape(n, out.dtype.itemsize // word.itemsize),
            points.view(word).reshape(n, points.dtype.itemsize // word.itemsize),
            out["x"], out["y"], out["z"], out["reflectance"], out["range"],
            out["incidence"], out["scan_angle"], out["correction_flags"], counts)


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
        Fields of interface.md (``x, y, z``, time, optional ``intensity``, ``strip_id``).
    trajectory : Trajectory
    settings : CorrectionSettings
    context : (m, 3) float64, optional
        Delivered neighbours for the normals (e.g. the previous cloud's points).
    source : str
        Topic or file named in messages.

    Returns
    -------
    corrected : structured array
        :func:`corrected_dtype` of the input.
    columns : CorrectedColumns
    """
    cols = extract_columns(points, time_field=settings.time_field, source=source,
                           coordinate_tolerance_m=settings.coordinate_tolerance_m)
    res = correct_columns(cols.xyz, cols.t, cols.intensity, trajectory, settings,
                          group=cols.strip_id, context_xyz=context, source=source)
    return build_corrected(points, res), res


#: ``place(tag, n, dtype)``: an array of ``n`` rows of ``dtype`` to build a corrected cloud
#: in, or None (:class:`StreamCorrector`'s ``place``).
OutputPlacer = Callable[[Any, int, np.dtype], "np.ndarray | None"]


@dataclass
class _Message:
    """A cloud in :class:`StreamCorrector` waiting for the normals of its points."""

    tag: Any
    points: np.ndarray
    columns: CloudColumns
    normals: GridNormals | None = None  # filled as its strips' evaluations come
    strip_parts: list[tuple[int, np.ndarray | None]] = field(default_factory=list)
    parts: int = 0  # strips among its points
    scheduled: int = 0  # parts whose normals are being (or have been) evaluated

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class _Strip:
    """The normals of one strip as its clouds arrive, and where the strip stands."""

    normals: StripNormals
    t_last: float


@dataclass
class _Job:
    """Clouds to be corrected together, and the evaluation of their normals."""

    tasks: list[NormalsTask]
    messages: list[_Message]
    trajectory: Trajectory
    settings: CorrectionSettings
    place: OutputPlacer | None = None


def _deliver(results: list[tuple[Any, GridNormals]]) -> None:
    """Put normals evaluated per strip into the clouds they belong to."""
    for key, g in results:
        m: _Message
        idx: np.ndarray | None
        m, idx = key
        if idx is None:
            m.normals = g
        else:
            if m.normals is None:
                m.normals = no_normals(len(m))
            assert m.normals.rough is not None and g.rough is not None
            m.normals.normals[idx] = g.normals
            m.normals.valid[idx] = g.valid
            m.normals.rough[idx] = g.rough
            m.normals.cell_m = g.cell_m


def _whole_normals(job: _Job) -> GridNormals | None:
    """The job's normals in one piece when one evaluation covers exactly its clouds, each
    of one strip (the usual case: no per-cloud copies); else None."""
    if len(job.tasks) != 1:
        return None
    keys = job.tasks[0].keys
    if len(keys) != len(job.messages) or any(
            key[1] is not None or key[0] is not m  # type: ignore[index]
            for key, m in zip(keys, job.messages, strict=True)):
        return None
    return job.tasks[0].run_whole()


def _job_columns(msgs: list[_Message]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """xyz, t and intensity (NaN for clouds without) of the clouds of a job, concatenated."""
    if len(msgs) == 1:
        c = msgs[0].columns
        return c.xyz, c.t, c.intensity
    xyz = np.concatenate([m.columns.xyz for m in msgs])
    t = np.concatenate([m.columns.t for m in msgs])
    inten = None
    if any(m.columns.intensity is not None for m in msgs):
        inten = np.concatenate([m.columns.intensity if m.columns.intensity is not None
                                else np.full(len(m), np.nan, np.float32) for m in msgs])
    return xyz, t, inten


def _run_job(job: _Job, source: str
             ) -> tuple[list[np.ndarray], list[CloudTally], float, ModelChoice | None]:
    """Correct one batch of clouds: the corrected clouds, their tallies, seconds spent, and
    the model their points got."""
    started = time.perf_counter()
    msgs = job.messages
    whole = _whole_normals(job)
    if len(msgs) == 1 and len(msgs[0]):
        done = _run_one(job, msgs[0], whole, source, started)
        if done is not None:
            return done
    for task in job.tasks if whole is None else ():
        _deliver(task.run())
    if whole is not None:
        xyz, t, inten = _job_columns(msgs)
        gn = whole
    elif len(msgs) == 1:
        c, g = msgs[0].columns, msgs[0].normals or no_normals(len(msgs[0]))
        xyz, t, inten, gn = c.xyz, c.t, c.intensity, g
    else:
        xyz, t, inten = _job_columns(msgs)
        normals = [m.normals or no_normals(len(m)) for m in msgs]
        rough = [g.rough for g in normals]
        gn = GridNormals(np.concatenate([g.normals for g in normals]),
                         np.concatenate([g.valid for g in normals]),
                         normals[-1].cell_m,
                         np.concatenate([r if r is not None else np.zeros(len(m), bool)
                                         for r, m in zip(rough, msgs, strict=True)]))
    res = correct_columns(xyz, t, inten, job.trajectory, job.settings, normals=gn,
                          source=source,
                          all_finite=all(m.columns.all_finite for m in msgs))
    out: list[np.ndarray] = []
    tallies: list[CloudTally] = []
    a = 0
    for m in msgs:
        b = a + len(m)
        where = (job.place(m.tag, len(m), corrected_dtype(m.points.dtype))
                 if job.place is not None else None)
        tallies.append(CloudTally.empty())
        out.append(build_corrected(m.points, res, a, b, out=where, tally=tallies[-1]))
        a = b
    return out, tallies, time.perf_counter() - started, res.choice


def _run_one(job: _Job, m: _Message, whole: GridNormals | None, source: str, started: float
             ) -> tuple[list[np.ndarray], list[CloudTally], float, ModelChoice | None] | None:
    """:func:`_run_job` of one cloud (the usual batch of the node), corrected straight into
    its rows (:func:`row_target`); None for a layout that needs the columns."""
    points = np.ascontiguousarray(m.points)
    dtype = corrected_dtype(points.dtype)
    where = job.place(m.tag, len(m), dtype) if job.place is not None else None
    out = where if where is not None else np.empty(len(m), dtype=dtype)  # (all written)
    tally = CloudTally.empty()
    target = row_target(points, out, tally.counts)
    if target is None:
        if where is not None:  # (placed: the general path builds the cloud there)
            job.place = _placed(m.tag, where)
        return None
    if whole is None:
        for task in job.tasks:
            _deliver(task.run())
    gn = whole if whole is not None else m.normals or no_normals(len(m))
    c = m.columns
    res = correct_columns(c.xyz, c.t, c.intensity, job.trajectory, job.settings, normals=gn,
                          source=source, all_finite=bool(c.all_finite), rows=target)
    return [out], [tally], time.perf_counter() - started, res.choice


def _placed(tag: Any, where: np.ndarray) -> OutputPlacer:
    """A placer that gives ``tag`` the output already placed for it."""
    return lambda t, n, dtype: where if t == tag else None


class StreamCorrector:
    """Correct a stream of clouds, with neighbours across cloud boundaries (module docstring).

    Parameters
    ----------
    trajectory : Trajectory
        The trajectory of the mission (at least up to the clouds pushed).
    settings : CorrectionSettings
    batch_points : int
        Clouds are corrected in batches of at least this many points (fewer, larger numpy
        calls); 0 corrects each cloud as soon as its normals are final (least latency).
    workers : int
        Batches corrected in parallel threads; 1 corrects in the calling thread.
    lookahead : bool
        Wait until the points after a cloud are there before fitting its normals, so that
        points at a cloud's leading edge have neighbours on both sides: the normals do not
        depend on how the stream is cut into clouds. False fits them at once against the
        points before (least latency).
    source : str
        Topic named in messages.
    place : callable(tag, n, dtype), optional
        Where to build each corrected cloud: an array of ``n`` rows of ``dtype`` (for
        instance inside the buffer it will be sent from), or None for a new array. Called
        from the worker threads.
    on_failed : callable(tag, exception), optional
        Called for each cloud of a batch whose correction raised (a bug, not bad input:
        malformed clouds are refused by :meth:`push`); the stream goes on with the next
        batch. Without it the exception propagates, and the clouds of that batch are lost.
    keep_tallies : bool
        Keep the :class:`CloudTally` of each corrected cloud in :attr:`tallies`, by tag,
        for the caller to take (tags must then be unique).

    Notes
    -----
    The normals of each strip come from one grid per strip (:class:`StripNormals`): every
    point is binned and evaluated once, whatever the clouds' size. :meth:`push` returns the
    corrected clouds that became ready, as ``(tag, array)`` in the order pushed;
    :meth:`release` corrects everything held now (a time-out: later clouds still see these
    points as neighbours); :meth:`flush` ends the stream (and stops the workers). Held in
    memory: the clouds waiting for their look-ahead (a few grid rows), the moment sums of the
    grid rows around them and ``workers + 1`` batches in flight. The output does not depend
    on the number of workers or on timing.
    """

    def __init__(
        self,
        trajectory: Trajectory,
        settings: CorrectionSettings,
        *,
        batch_points: int = DEFAULT_BATCH_POINTS,
        workers: int = 1,
        lookahead: bool = True,
        source: str = "cloud",
        place: OutputPlacer | None = None,
        on_failed: Callable[[Any, Exception], None] | None = None,
        keep_tallies: bool = False,
    ) -> None:
        self.trajectory = trajectory
        self.keep_tallies = keep_tallies
        self.tallies: dict[Any, CloudTally] = {}
        self.place = place
        self.on_failed = on_failed
        self.settings = settings
        self.batch_points = max(int(batch_points), 0)
        self.workers = max(int(workers), 1)
        self.lookahead = lookahead
        self.source = source
        self.stats = CorrectionStats()
        self._queue: deque[_Message] = deque()
        self._strips: dict[int, _Strip] = {}
        self._warned_intensity = False
        self._float32_step = 0.0  # the coarsest FLOAT32 coordinate step warned about
        self._pool: ThreadPoolExecutor | None = None
        self._inflight: deque[tuple[list[Any], Future[Any]]] = deque()
        self._late_done = 0
        self._tasks: list[NormalsTask] = []
        self._unbinned: list[_Message] = []  # queued, not yet given to the strips' grids
        self._unbinned_points = 0

    @property
    def held_points(self) -> int:
        """Points pushed and not yet released."""
        return sum(len(m) for m in self._queue)

    @property
    def late_points(self) -> int:
        """Points that arrived behind their strip's grid (no normal), so far."""
        return sum(s.normals.late_points for s in self._strips.values()) + self._late_done

    def set_trajectory(self, trajectory: Trajectory) -> None:
        """Use a newer trajectory (e.g. grown while streaming) from the next batch on."""
        self.trajectory = trajectory

    def set_settings(self, settings: CorrectionSettings) -> None:
        """Use new settings (calibration, radiometry) from the next batch on."""
        self.settings = settings

    def start(self) -> None:
        """Start the worker threads now (they otherwise start with the first batch)."""
        if self.workers > 1 and self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.workers,
                                            thread_name_prefix="lidarcal-correct")

    def close(self) -> None:
        """Stop the workers (also done by :meth:`flush`)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def push(self, points: np.ndarray, tag: Any = None) -> list[tuple[Any, np.ndarray]]:
        """Add a cloud (structured array); returns the corrected clouds now ready.

        Raises
        ------
        CloudFormatError
            The cloud lacks ``x, y, z`` or its time field, or has unsupported types (nothing
            is added).
        """
        return self.push_many([(points, tag)])

    def push_many(
        self, clouds: list[tuple[np.ndarray, Any]], *,
        on_error: Callable[[Any, LidarcalError], None] | None = None,
    ) -> list[tuple[Any, np.ndarray]]:
        """Add several clouds at once (one evaluation of the normals for all: a backlog
        catches up faster); returns the corrected clouds now ready.

        Parameters
        ----------
        clouds : list of (structured array, tag)
        on_error : callable(tag, error), optional
            Called for each malformed cloud, which is then skipped; without it the first
            malformed cloud raises before anything is added.
        """
        msgs: list[_Message] = []
        for points, tag in clouds:
            try:
                msgs.append(self._message(points, tag))
            except LidarcalError as exc:
                if on_error is None:
                    raise
                on_error(tag, exc)
        for m in msgs:
            self._enqueue(m)
        if self._unbinned_points >= self.batch_points:
            self._bin_pending()
        return self._drain(final=False)

    def set_lookahead(self, lookahead: bool) -> None:
        """Wait for look-ahead (or not) from the next cloud on."""
        self.lookahead = lookahead
        for s in self._strips.values():
            s.normals.lookahead = lookahead

    def release(self) -> list[tuple[Any, np.ndarray]]:
        """Correct everything held now, without waiting for look-ahead (the strips' grids
        are kept: later clouds still have these points as neighbours); with worker threads,
        waits for the batches in flight."""
        out = self._drain(final=True)
        out.extend(self._collect(wait_all=True))
        return out

    @property
    def in_flight(self) -> int:
        """Batches handed to the worker threads and not yet returned."""
        return len(self._inflight)

    def collect_ready(self, timeout: float = 0.0) -> list[tuple[Any, np.ndarray]]:
        """The corrected clouds of batches the worker threads have finished (in order),
        waiting up to ``timeout`` seconds for the oldest one. Without it the results of
        the last batches before a pause would wait for the next :meth:`push`."""
        if self._inflight and timeout > 0:
            wait([self._inflight[0][1]], timeout=timeout)
        return self._collect(wait_all=False)

    def flush(self) -> list[tuple[Any, np.ndarray]]:
        """Correct everything held (the end of the stream); stop the workers."""
        try:
            out = self.release()
            for s in self._strips.values():
                self._late_done += s.normals.late_points
            self._strips.clear()
        finally:
            self.close()
        return out

    # -- internals -------------------------------------------------------------------

    def _message(self, points: np.ndarray, tag: Any) -> _Message:
        cols = extract_columns(points, time_field=self.settings.time_field, source=self.source,
                               coordinate_tolerance_m=self.settings.coordinate_tolerance_m)
        if cols.coordinate_step_m > self._float32_step:
            self._float32_step = cols.coordinate_step_m
            note = float32_warning(cols.coordinate_step_m, self.settings.coordinate_tolerance_m)
            if note:
                logger.warning("%s: %s", self.source, note)
        if len(points) and cols.intensity is None and not self._warned_intensity:
            logger.warning("%s: clouds without an 'intensity' field: geometry is corrected, "
                           "reflectance is NaN (flag %d)", self.source, FLAG_NO_INTENSITY)
            self._warned_intensity = True
        return _Message(tag, points, cols)

    def _enqueue(self, m: _Message) -> None:
        """Queue a cloud and note the strips among its points (binned later, in batches)."""
        self._queue.append(m)
        if not len(m):
            return
        g = m.columns.strip_id
        if g is None or g.min() == g.max():
            m.strip_parts = [(-1 if g is None else int(g[0]), None)]
        else:
            m.strip_parts = [(int(k), np.flatnonzero(g == k)) for k in np.unique(g)]
        m.parts = len(m.strip_parts)
        self._unbinned.append(m)
        self._unbinned_points += len(m)

    def _bin_pending(self) -> None:
        """Give the points of the queued clouds to the grids of their strips, in order; the
        clouds of a strip are binned together (fewer, larger numpy calls)."""
        batches: dict[int, list[tuple[object, np.ndarray, np.ndarray | None]]] = {}

        def bin_strip(strip_id: int) -> None:
            parts = batches.pop(strip_id, None)
            if parts:
                self._strips[strip_id].normals.add_many(parts)

        for m in self._unbinned:
            cols = m.columns
            for strip_id, idx in m.strip_parts:
                xyz = cols.xyz if idx is None else cols.xyz[idx]
                t = cols.t if idx is None else cols.t[idx]
                t_lo, t_hi = (cols.t_span if idx is None and cols.t_span is not None
                              else time_span(t))
                heading = trajectory_heading(self.trajectory, 0.5 * (t_lo + t_hi))
                strip = self._strips.get(strip_id)
                if strip is not None and self._strip_ended(strip, heading, t_lo):
                    bin_strip(strip_id)
                    self._finish_strip(strip_id)
                    strip = None
                if strip is None:
                    strip = _Strip(StripNormals(self._heading_at, lookahead=self.lookahead),
                                   t_hi)
                    self._strips[strip_id] = strip
                if math.isfinite(t_hi):
                    strip.t_last = (max(strip.t_last, t_hi) if math.isfinite(strip.t_last)
                                    else t_hi)
                batches.setdefault(strip_id, []).append(((m, idx), xyz, t))
        for strip_id in list(batches):
            bin_strip(strip_id)
        self._unbinned, self._unbinned_points = [], 0

    def _heading_at(self, t: float) -> float:
        return trajectory_heading(self.trajectory, t)

    @staticmethod
    def _strip_ended(strip: _Strip, heading: float, t_lo: float) -> bool:
        """A gap in time or a turn: the strip's grid no longer fits the new points."""
        turn = abs(math.remainder(heading - strip.normals.heading, 2.0 * math.pi))
        if not math.isfinite(turn):  # (grid not started yet)
            turn = 0.0
        gap = t_lo - strip.t_last if math.isfinite(t_lo + strip.t_last) else 0.0
        return turn > _MAX_GRID_TURN_RAD or gap > _MAX_GRID_GAP_S

    def _finish_strip(self, strip_id: int) -> None:
        strip = self._strips.pop(strip_id)
        self._schedule(strip.normals.take_ready(final=True))
        self._late_done += strip.normals.late_points

    def _schedule(self, task: NormalsTask | None) -> None:
        if task is None:
            return
        self._tasks.append(task)
        for key in task.keys:
            message: _Message = key[0]  # type: ignore[index]
            message.scheduled += 1

    def _drain(self, *, final: bool) -> list[tuple[Any, np.ndarray]]:
        if final and self._unbinned:
            self._bin_pending()
        # Strips that ended long before the newest point: finish them (their last clouds
        # would otherwise wait for a look-ahead that never comes, and hold up the output).
        newest = max((s.t_last for s in self._strips.values()), default=math.nan)
        for strip_id, s in list(self._strips.items()):
            if newest - s.t_last > _MAX_GRID_GAP_S:
                self._finish_strip(strip_id)
        for s in self._strips.values():
            # A strip whose points stop advancing along track (hovering, stalled times)
            # would hold its clouds for ever: bounded.
            stalled = s.normals.pending_points() > _MAX_LOOKAHEAD_POINTS + self.batch_points
            self._schedule(s.normals.take_ready(final=final or stalled,
                                                min_points=self.batch_points))
        done: list[_Message] = []
        while self._queue and self._queue[0].scheduled == self._queue[0].parts:
            done.append(self._queue.popleft())
        out: list[tuple[Any, np.ndarray]] = []
        if not done:
            return out
        # The evaluations go with the clouds they complete, into a worker; one that also
        # serves a cloud still waiting (for another strip's normals) runs here, now.
        in_job = {id(m) for m in done}
        tasks, self._tasks = self._tasks, []
        job_tasks: list[NormalsTask] = []
        for task in tasks:
            if all(id(key[0]) in in_job for key in task.keys):  # type: ignore[index]
                job_tasks.append(task)
            else:
                _deliver(task.run())
        self._submit(_Job(job_tasks, done, self.trajectory, self.settings, self.place), out)
        return out

    def _submit(self, job: _Job, out: list[tuple[Any, np.ndarray]]) -> None:
        tags = [m.tag for m in job.messages]
        if self.workers == 1:
            try:
                result = _run_job(job, self.source)
            except Exception as exc:
                self._failed(tags, exc)
                return
            self._account(tags, result, out)
            return
        self.start()
        assert self._pool is not None
        self._inflight.append((tags, self._pool.submit(_run_job, job, self.source)))
        out.extend(self._collect(wait_all=False))

    def _collect(self, *, wait_all: bool) -> list[tuple[Any, np.ndarray]]:
        """Results of finished batches, in order; waits while too many are in flight."""
        out: list[tuple[Any, np.ndarray]] = []
        while self._inflight and (wait_all or self._inflight[0][1].done()
                                  or len(self._inflight) > self.workers):
            tags, future = self._inflight.popleft()
            try:
                result = future.result()
            except Exception as exc:
                self._failed(tags, exc)
                continue
            self._account(tags, result, out)
        return out

    def _failed(self, tags: list[Any], exc: Exception) -> None:
        """A batch raised: its clouds go to ``on_failed`` (or the exception on up)."""
        if self.on_failed is None:
            raise exc
        logger.error("%s: correction of %d cloud(s) failed: %s: %s", self.source, len(tags),
                     type(exc).__name__, exc, exc_info=exc)
        for tag in tags:
            self.on_failed(tag, exc)

    def _account(self, tags: list[Any],
                 result: tuple[list[np.ndarray], list[CloudTally], float, ModelChoice | None],
                 out: list[tuple[Any, np.ndarray]]) -> None:
        clouds, tallies, seconds, choice = result
        self.stats.clouds += len(clouds)
        self.stats.seconds += seconds
        if choice is not None:
            self.stats.add_model(choice.model, choice.reason,
                                 sum(t.points - t.flagged(FLAG_NOT_CORRECTED) for t in tallies))
        for tag, tally in zip(tags, tallies, strict=True):
            self.stats.add(tally)
            if self.keep_tallies:
                self.tallies[tag] = tally
        out.extend(zip(tags, clouds, strict=True))


# ---------------------------------------------------------------------------- bags
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
        out.append(f"grazing incidence (clamped): {s.grazing}; rough surface: {s.rough}; "
                   f"no normal: {s.no_normal}; not corrected (trajectory): {s.not_corrected}; "
                   f"without intensity: {s.no_intensity}")
        out.extend(f"warning: {w}" for w in self.warnings)
        return out


def output_kind(path: str | Path) -> str:
    """``las`` for ``.las``/``.laz``, else ``bag`` (``.mcap`` file or rosbag2 directory)."""
    return "las" if Path(path).suffix.lower() in (".las", ".laz") else "bag"


def read_trajectory(bag: Any, topic: str) -> tuple[Trajectory, set[str]]:
    """First pass: every trajectory sample of an open bag, and the frames they are in."""
    from lidarcal_ros.io.trajectory_messages import TRAJECTORY_TYPES, TrajectorySamples

    samples = TrajectorySamples()
    decode = functools.partial(bag.deserialize, topic=topic)
    for _topic, msgtype, _ns, raw in prefetched(lambda: bag.messages([topic])):
        if msgtype not in TRAJECTORY_TYPES:
            raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
        samples.add_raw(msgtype, raw, decode)
    if not samples:
        raise BagError(f"{bag.path}: topic {topic} has no messages")
    return samples.trajectory(f"{bag.path}: trajectory {topic}"), samples.frames


def correct_bag(
    bag_path: str | Path,
    calibration: str | Path | CalibrationRecord,
    output: str | Path,
    config: FlightConfig | None = None,
    *,
    crs: Any = None,
    overwrite: bool = False,
    batch_points: int = DEFAULT_BATCH_POINTS,
    workers: int = 1,
    progress: Callable[[str, float], None] | None = None,
) -> CorrectionReport:
    """Correct every cloud of a mission bag; write a bag or a LAS/LAZ file.

    Parameters
    ----------
    bag_path : path
        rosbag2 directory or ``.mcap`` with the topics of ``config``.
    calibration : path or CalibrationRecord
        Calibration file of interface.md.
    output : path
        ``.las``/``.laz``: LAS 1.4 point format 6 (:mod:`lidarcal_ros.io.las`); otherwise a
        rosbag2 bag (bare MCAP for ``.mcap``) with the corrected clouds on
        ``topics.corrected`` and every input message passed through unchanged.
    config : FlightConfig, optional
        Defaults when None.
    crs : pyproj.CRS, optional
        CRS of the map frame, written into LAS output (ignored, with a warning, for bags).
    overwrite : bool
        Replace an existing output.
    batch_points : int
        Points corrected together (memory is about 1 kB per point of batch).
    workers : int
        Batches corrected in parallel (reading and writing stay in the calling thread:
        they are mostly Python code, and threads of their own only contend for the
        interpreter lock).
    progress : callable(stage, fraction), optional

    Returns
    -------
    CorrectionReport

    Raises
    ------
    BagError, CloudFormatError, InputError, ConfigError, TrajectoryError
        One line naming the file, topic or field at fault.
    """
    from lidarcal_ros.io.bag_format import POINTCLOUD2
    from lidarcal_ros.io.bag_reader import open_bag
    from lidarcal_ros.io.trajectory_messages import TRAJECTORY_TYPES

    started = time.perf_counter()
    # The compiled loops load while the trajectory is read (their first call in a process
    # costs some 0.5 s; reading is mostly decompression, which leaves the interpreter free).
    threading.Thread(target=warm_up, name="lidarcal-warm-up", daemon=True).start()
    config = config or FlightConfig()
    record = (calibration if isinstance(calibration, CalibrationRecord)
              else read_calibration(calibration))
    settings = CorrectionSettings.from_config(config, record)
    out_path = Path(output)
    kind = output_kind(out_path)
    points_topic = config["topics.points"]
    traj_topic = config["topics.trajectory"]
    corrected_topic = config["topics.corrected"]
    bag_path = Path(bag_path)
    if out_path.resolve() == bag_path.resolve():
        raise InputError(f"{out_path}: output would overwrite the input bag")
    warnings: list[str] = []
    if crs is not None and kind == "bag":
        warnings.append("--crs applies to LAS/LAZ output only; ignored for a bag")
        logger.warning("%s", warnings[-1])

    with open_bag(bag_path) as bag:
        for topic, types in ((points_topic, (POINTCLOUD2,)),
                             (traj_topic, tuple(TRAJECTORY_TYPES))):
            if topic not in bag.topics:
                raise BagError(f"{bag.path}: topic {topic} not found; topics present: "
                               f"{', '.join(bag.topics) or 'none'}")
            got = bag.topics[topic].msgtype
            if got not in types:
                raise BagError(f"{bag.path}: topic {topic} has type {got}; expected "
                               f"{' or '.join(types)}")
            if bag.topics[topic].count == 0:
                raise BagError(f"{bag.path}: topic {topic} has no messages")
        if corrected_topic in bag.topics and kind == "bag":
            raise BagError(f"{bag.path}: already has topic {corrected_topic}; a corrected "
                           "bag cannot be corrected again into the same topic")
        if progress:
            progress("reading trajectory", 0.0)
        trajectory, traj_frames = read_trajectory(bag, traj_topic)
        if len(traj_frames) > 1:
            raise InputError(f"{bag.path}: poses on {traj_topic} are in several frames: "
                             f"{sorted(traj_frames)}")
        frame = next(iter(traj_frames))
        check_orientation(settings.heading_source, trajectory, f"{bag.path}: {traj_topic}")
        check_model_setting(settings.model, trajectory, f"{bag.path}: {traj_topic}")
        meaning = settings.radiometry.meaning
        if not settings.radiometry.absolute:
            from lidarcal_ros.pipeline.reflectance import measure_target_in_bag, with_constant

            target = measure_target_in_bag(bag_path, settings, config)
            if target is not None:
                settings = with_constant(settings, target.constant)
                meaning = f"{settings.radiometry.meaning} The {target.describe()}."
        corrector = StreamCorrector(trajectory, settings, batch_points=batch_points,
                                    workers=workers, source=points_topic,
                                    keep_tallies=kind == "bag")
        n_clouds = max(bag.topics[points_topic].count, 1)
        report = CorrectionReport(out_path, kind, corrector.stats, frame_id=frame,
                                  atmosphere=describe_alpha(settings.radiometry),
                                  reflectance=meaning, warnings=warnings)
        try:
            corrector.start()  # the workers start while the clouds are read
            if kind == "las":
                _correct_to_las(bag, corrector, out_path, points_topic, frame, crs, overwrite,
                                n_clouds, progress, report)
            else:
                _correct_to_bag(bag, corrector, out_path, points_topic, corrected_topic,
                                frame, overwrite, n_clouds, progress, report)
        finally:
            corrector.close()
    s = corrector.stats
    if s.not_corrected > s.non_finite:
        report.warnings.append(
            f"{s.not_corrected - s.non_finite} of {s.points} points not covered by the "
            "trajectory (or not below it): left uncorrected, flagged "
            f"{FLAG_NOT_CORRECTED} in correction_flags")
        logger.warning("%s: %s", bag_path, report.warnings[-1])
    if s.non_finite and kind == "bag":
        report.warnings.append(
            f"{s.non_finite} of {s.points} points with a non-finite x, y or z: passed on as "
            f"delivered, flagged {FLAG_NOT_CORRECTED} in correction_flags")
        logger.warning("%s: %s", bag_path, report.warnings[-1])
    if s.no_intensity:
        report.warnings.append(f"{s.no_intensity} points without intensity: reflectance NaN")
    if crs is None and kind == "las":
        report.warnings.append("written without a CRS: the LAS/LAZ file does not say where "
                               "its map frame is (give it with --crs, e.g. --crs EPSG:32633)")
        logger.warning("%s: %s", out_path, report.warnings[-1])
    report.seconds = time.perf_counter() - started
    return report


def _cloud_points(bag: Any, msgtype: str, raw: bytes, topic: str, frame: str) -> tuple[Any,
                                                                                        np.ndarray]:
    from lidarcal_ros.io.bag_format import POINTCLOUD2

    if msgtype != POINTCLOUD2:
        raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
    # (through a memoryview: rosbags would copy bytes to cut off their CDR header)
    msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
    if msg.header.frame_id != frame:
        raise InputError(f"{bag.path}: clouds on {topic} are in frame '{msg.header.frame_id}' "
                         f"but the trajectory is in frame '{frame}'")
    return msg, cloud_to_array(msg, source=topic)


def _correct_to_las(
    bag: Any, corrector: StreamCorrector, out_path: Path, points_topic: str, frame: str,
    crs: Any, overwrite: bool, n_clouds: int,
    progress: Callable[[str, float], None] | None, report: CorrectionReport,
) -> None:
    from lidarcal_ros.io.las import LasChunkWriter

    seen = 0
    time_field: str | None = None
    # Corrected clouds are written in runs of at least this many points (fewer, larger LAZ
    # chunks); clouds of one layout only in a run.
    run: list[np.ndarray] = []
    run_points = 0

    with LasChunkWriter(out_path, time_field=corrector.settings.time_field, crs=crs,
                        overwrite=overwrite,
                        reflectance_description=corrector.settings.radiometry.las_description,
                        ) as writer:

        def write_run(parts: list[np.ndarray]) -> None:
            writer.write(np.concatenate(parts) if len(parts) > 1 else parts[0])

        def write(done: list[tuple[Any, np.ndarray]], *, final: bool = False) -> None:
            nonlocal run, run_points
            for _tag, corrected in done:
                if run and corrected.dtype != run[0].dtype:
                    write_run(run)
                    run, run_points = [], 0
                run.append(corrected)
                run_points += len(corrected)
            if run and (final or run_points >= _LAS_RUN_POINTS):
                write_run(run)
                run, run_points = [], 0

        for topic, msgtype, _ns, raw in prefetched(lambda: bag.messages([points_topic])):
            _msg, points = _cloud_points(bag, msgtype, raw, topic, frame)
            if time_field is None and len(points):
                time_field = resolve_time_field(points, corrector.settings.time_field,
                                                source=topic)
                writer.time_field = time_field
            write(corrector.push(points, None))
            seen += 1
            if progress and seen % 50 == 0:
                progress("correcting", seen / n_clouds)
        write(corrector.flush(), final=True)
        _check_something_corrected(corrector.stats, bag.path, points_topic)
    report.las_skipped_non_finite = writer.stats.skipped_non_finite
    for count, why in ((writer.stats.skipped_non_finite, "with non-finite coordinates"),
                       (writer.stats.skipped_out_of_range, "more than 2147 km from the others "
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


def _correct_to_bag(
    bag: Any, corrector: StreamCorrector, out_path: Path, points_topic: str,
    corrected_topic: str, frame: str, overwrite: bool, n_clouds: int,
    progress: Callable[[str, float], None] | None, report: CorrectionReport,
) -> None:
    from lidarcal_ros.io.bag_format import POINTCLOUD2
    from lidarcal_ros.io.bag_writer import BagWriter
    from lidarcal_ros.io.pointcloud import point_fields
    from lidarcal_ros.io.ros_messages import cloud_header_cdr, stamp_ns

    latched = [t for t, info in bag.topics.items() if info.transient_local]
    # Output queue keyed by (input sequence number, 0 = passed through / 1 = corrected).
    # Passed-through messages are ready at once, corrected clouds when their batch is
    # released; everything before the oldest cloud still held is written, so the output
    # keeps the input's (log-time) order.
    ready: list[tuple[int, int, Any]] = []
    held: deque[int] = deque()
    clouds: dict[int, tuple[int, Any]] = {}  # input sequence number -> log time, message
    # Each corrected cloud is built in the bytes of its message (the input's header, then
    # the points, 8-byte aligned, then is_dense), which the writer then copies once.
    messages: dict[int, np.ndarray] = {}
    skipped_topics: set[str] = set()
    seen = 0

    def place(k_: int, n_: int, dtype_: np.dtype[Any]) -> np.ndarray:
        """(from the worker threads)"""
        _ns, msg_ = clouds[k_]
        head = cloud_header_cdr(stamp_ns(msg_.header.stamp), msg_.header.frame_id,
                                point_fields(dtype_), dtype_.itemsize, n_)
        pad = (-len(head)) % 8
        size = len(head) + n_ * dtype_.itemsize + 1
        buf = np.empty(pad + size, dtype=np.uint8)
        buf[pad:pad + len(head)] = np.frombuffer(head, dtype=np.uint8)
        messages[k_] = buf[pad:]
        return buf[pad + len(head):pad + size - 1].view(dtype_)

    corrector.place = place
    with BagWriter(out_path, overwrite=overwrite, latched_topics=latched) as writer:

        def write_corrected(ns_: int, message: np.ndarray) -> None:
            writer.write_raw(corrected_topic, POINTCLOUD2, ns_, message.data)

        def write_raw(topic_: str, msgtype_: str, ns_: int, raw_: bytes) -> None:
            if topic_ in skipped_topics:
                return
            try:
                writer.write_raw(topic_, msgtype_, ns_, raw_,
                                 msgdef=bag.topics[topic_].msgdef or None)
            except BagError as exc:
                skipped_topics.add(topic_)
                report.warnings.append(f"topic {topic_} not passed through ({exc})")
                logger.warning("%s", report.warnings[-1])
                return
            report.passthrough_messages += 1

        def emit(limit: tuple[float, int]) -> None:
            while ready and (ready[0][0], ready[0][1]) < limit:
                _, kind_, payload = heapq.heappop(ready)
                (write_corrected if kind_ == 1 else write_raw)(*payload)

        def collect(done: list[tuple[Any, np.ndarray]]) -> None:
            for k_, _corrected in done:
                ns_, _msg = clouds.pop(k_)
                message = messages.pop(k_)
                message[-1] = corrector.tallies.pop(k_).dense
                heapq.heappush(ready, (k_, 1, (ns_, message)))
                held.remove(k_)

        for k, (topic, msgtype, ns, raw) in enumerate(prefetched(bag.messages)):
            heapq.heappush(ready, (k, 0, (topic, msgtype, ns, raw)))
            if topic == points_topic:
                msg, points = _cloud_points(bag, msgtype, raw, topic, frame)
                held.append(k)
                clouds[k] = (ns, msg)
                collect(corrector.push(points, k))
                seen += 1
                if progress and seen % 50 == 0:
                    progress("correcting", seen / n_clouds)
            emit((held[0], 1) if held else (math.inf, 0))
        collect(corrector.flush())
        emit((math.inf, 0))
        _check_something_corrected(corrector.stats, bag.path, points_topic)


def warm_up() -> None:
    """Correct a small synthetic cloud (of the lidarcal layout, read-only as a decoded one
    is), so that the compiled loops of the correction are loaded, and numba initialised, now
    rather than by the first cloud."""
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


def iter_corrected(
    clouds: Iterator[np.ndarray], trajectory: Trajectory, settings: CorrectionSettings, *,
    batch_points: int = DEFAULT_BATCH_POINTS, source: str = "cloud",
) -> Iterator[np.ndarray]:
    """Corrected clouds of an iterable of clouds, in order (in-memory streaming)."""
    corrector = StreamCorrector(trajectory, settings, batch_points=batch_points, source=source)
    for points in clouds:
        for _tag, out in corrector.push(points):
            yield out
    for _tag, out in corrector.flush():
        yield out
