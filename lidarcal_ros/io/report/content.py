"""What the calibration report holds: :class:`ReportContent` and the parts it is made of.

Lengths in metres, angles in radians unless a field says otherwise; map positions in the map
frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.result import ControlResidual, PairDiscrepancies
from lidarcal_ros.core.qa.accuracy import AccuracySummary, RigidFit
from lidarcal_ros.core.qa.quality_level import QualityAssessment
from lidarcal_ros.core.qa.swath_differences import SwathDifferences
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryEstimate

__all__ = [
    "BiasEntry", "EvaluationSection", "FlightMap", "InputFile", "MapRaster", "PairSection",
    "Provenance", "RadiometrySection", "ReportContent", "SlopeClass", "StripRow",
    "TrajectorySection",
]


@dataclass
class BiasEntry:
    """One row of the bias table.

    Attributes
    ----------
    name : str
        Parameter key (docs/method.md section 1).
    value : float
        Estimate or fixed value, SI units (m, rad, 1).
    sigma : float or None
        Standard deviation, SI units; None where not estimated.
    state : ParameterState
        ``FIXED``: held at ``value``, not solved for.
    reason : str
        Why a parameter was not estimable (words from the observability analysis).
    """

    name: str
    value: float
    sigma: float | None
    state: ParameterState
    reason: str = ""


@dataclass
class PairSection:
    """Normal discrepancies of one strip pair before and after calibration.

    Attributes
    ----------
    before, after : PairDiscrepancies
        At zero biases and at the estimate (the same sample points; metres).
    qa_level : str
        ``OK``, ``WARN`` or ``ERROR`` for the RMS after (thresholds of the configuration).
    coverage : float or None
        Fraction of the smaller strip's footprint the pair overlaps (from the calibration
        file), if known.
    """

    before: PairDiscrepancies
    after: PairDiscrepancies
    qa_level: str
    coverage: float | None = None

    @property
    def strips(self) -> tuple[int, int]:
        """The pair's two strip ids, smaller first."""
        return self.after.strips


@dataclass
class SlopeClass:
    """Intensity statistics of the points whose terrain slope falls in ``[lo_deg, hi_deg)``.

    Attributes
    ----------
    lo_deg, hi_deg : float
        Slope bounds, degrees from horizontal.
    n_points : int
        Points used (corrected, with a normal and an intensity, not rough).
    vmr_intensity, vmr_reflectance : float
        Variance-to-mean ratio of the recorded intensity and of the reflectance put on the
        intensity's scale (one factor for all classes: equal means over every point used),
        intensity units; NaN for too few points.
    mean_intensity, mean_reflectance : float
        Means, intensity units and the reflectance's unit.
    """

    lo_deg: float
    hi_deg: float
    n_points: int
    vmr_intensity: float
    vmr_reflectance: float
    mean_intensity: float
    mean_reflectance: float

    @property
    def change(self) -> float:
        """Relative change of the VMR, ``after / before - 1`` (NaN when undefined)."""
        if not (math.isfinite(self.vmr_intensity) and self.vmr_intensity > 0
                and math.isfinite(self.vmr_reflectance)):
            return math.nan
        return self.vmr_reflectance / self.vmr_intensity - 1.0


@dataclass
class MapRaster:
    """A grid of values over the mission, rows from south to north.

    Attributes
    ----------
    values : (ny, nx) float64
        Per cell, NaN where no point fell.
    x0, y0 : float
        Map-frame coordinates of the south-west corner of cell ``[0, 0]``, metres.
    cell_m : float
        Cell size, metres.
    """

    values: np.ndarray
    x0: float
    y0: float
    cell_m: float

    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)``, map frame, metres (for ``imshow``)."""
        ny, nx = self.values.shape
        return self.x0, self.x0 + nx * self.cell_m, self.y0, self.y0 + ny * self.cell_m


@dataclass
class RadiometrySection:
    """The radiometric part of the report.

    Attributes
    ----------
    slope_classes : list of SlopeClass
    intensity, reflectance : MapRaster
        Mean recorded intensity and mean reflectance per cell, on one grid.
    n_points, n_used : int
        Points corrected, and points entering the slope statistics.
    meaning : str
        What the reflectance is (:attr:`~lidarcal_ros.core.radiometry.RadiometricModel.meaning`).
    unit : str
        Its unit: ``1`` (Lambertian reflectance) or ``intensity units`` (relative).
    notes : list of str
        Sentences shown under the figures (atmosphere, reference target, points left out).
    """

    slope_classes: list[SlopeClass]
    intensity: MapRaster
    reflectance: MapRaster
    n_points: int
    n_used: int
    meaning: str = ""
    unit: str = "intensity units"
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class InputFile:
    """One input of the report: role, path, size (bytes) and SHA-256 (hex) of its content
    (of a directory: of its files' names and contents, in name order)."""

    role: str
    path: str
    size_bytes: int
    sha256: str


@dataclass
class Provenance:
    """What produced the report.

    Attributes
    ----------
    version : str
        lidarcal's.
    generated : str
        When, ISO 8601 UTC.
    command : str
        The command line, when run from one.
    inputs : list of InputFile
    configuration : list of (str, str, bool)
        Every flight-configuration parameter: name, value, whether it differs from the
        default.
    configuration_source : str
        The parameters file, or ``defaults``.
    """

    version: str
    generated: str
    command: str
    inputs: list[InputFile]
    configuration: list[tuple[str, str, bool]]
    configuration_source: str


@dataclass(frozen=True)
class StripRow:
    """One flight line (strip) of the block.

    Attributes
    ----------
    strip_id : int
    points : int
    start : str
        First point's time: ISO 8601 UTC for absolute times, else seconds.
    duration_s, length_m : float
        Time from first to last point and the trajectory's length over it.
    heading_deg : float
        Course over ground, degrees clockwise from grid north (0-360).
    speed_mps : float
    height_m : float
        Flying height above the ground: median trajectory height minus median point height.
    density_per_m2 : float
        Points over the footprint's area (cells holding points).
    """

    strip_id: int
    points: int
    start: str
    duration_s: float
    length_m: float
    heading_deg: float
    speed_mps: float
    height_m: float
    density_per_m2: float


@dataclass
class FlightMap:
    """What the block map shows (map frame, metres).

    Attributes
    ----------
    trajectory_xy : (k, 2) float
        The whole trajectory, thinned.
    lines : list of (int, (m, 2) float)
        Per strip, the trajectory while it was flown.
    coverage : MapRaster
        Strips covering each cell (0: none).
    control, check : list of (str, float, float)
        Control and check points: id, x, y.
    target : (xmin, ymin, xmax, ymax) or None
        The radiometric reference target.
    """

    trajectory_xy: np.ndarray
    lines: list[tuple[int, np.ndarray]]
    coverage: MapRaster
    control: list[tuple[str, float, float]] = field(default_factory=list)
    check: list[tuple[str, float, float]] = field(default_factory=list)
    target: tuple[float, float, float, float] | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """South-west and north-east corners of everything shown, with a margin."""
        left, right, bottom, top = self.coverage.extent()
        parts = [np.array([[left, bottom], [right, top]]), self.trajectory_xy]
        parts += [np.array([(x, y) for _, x, y in pts]) for pts in (self.control, self.check)
                  if pts]
        xy = np.concatenate(parts)
        lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
        margin = 0.03 * float(np.max(hi - lo))
        return lo - margin, hi + margin


@dataclass
class EvaluationSection:
    """``lidarcal evaluate``'s results (Tables 3 and 4 of the paper).

    Attributes
    ----------
    pairs : list of (int, int, RigidFit or None, RigidFit or None)
        Strip ids and the co-aligning transformation before and after.
    check : list of (str, list of int, float, float)
        Check point id, strips seeing it, residual before and after (m).
    source : str
        Computed for the report, or the file it was read from.
    """

    pairs: list[tuple[int, int, RigidFit | None, RigidFit | None]]
    check: list[tuple[str, list[int], float, float]]
    source: str

    def summary(self, state: str) -> AccuracySummary:
        """Check-point statistics ``before`` or ``after``."""
        k = 2 if state == "before" else 3
        return AccuracySummary.of(np.array([c[k] for c in self.check]))


@dataclass
class TrajectorySection:
    """Each strip's estimated trajectory error (the calibration file's ``trajectory`` block,
    docs/method.md section 11).

    Attributes
    ----------
    estimate : TrajectoryEstimate
        ``e_s(t)`` by strip id (delivered - true, map frame, m) with its sigmas.
    choice : str
        How the model was chosen, as the file says (``trajectory_model``; '' where absent).
    spans : dict of int -> (float, float)
        When each strip of the mission was flown (its points' first and last time, s).
    t0 : float
        Origin of the figure's time axis (the first strip's start), s.
    start : str
        ``t0`` in words (UTC where absolute).
    """

    estimate: TrajectoryEstimate
    choice: str
    spans: dict[int, tuple[float, float]]
    t0: float
    start: str


@dataclass
class ReportContent:
    """Everything the HTML report shows.

    Attributes
    ----------
    title : str
    facts : list of (str, str)
        The summary's lines (label, value).
    calibration_facts : list of (str, str)
        The calibration's lines (file, sigma0, redundancy, ...).
    biases : list of BiasEntry
        The eight parameters in docs/method.md order.
    correlation_names : list of str
        Estimated parameters, in the order of ``correlation``'s rows.
    correlation : (m, m) float64
    pairs : list of PairSection
    control : list of ControlResidual
        Metres, before and after.
    radiometry : RadiometrySection or None
        None where the clouds carry no intensity.
    strips : list of StripRow
    flight : FlightMap or None
    swath : SwathDifferences or None
    swath_limit_m : float
        Half-range of the dz colour scale, metres.
    quality : QualityAssessment or None
    evaluation : EvaluationSection or None
    provenance : Provenance or None
    crs : str
        The map frame's CRS as named on the axes ('' where not known).
    qa_warn_m, qa_error_m : float
        Thresholds of the pair QA, metres.
    smooth_slope_deg : float
        Steepest ground of the swath differences, degrees.
    warnings : list of str
    trajectory : TrajectorySection or None
        None where the calibration holds no trajectory errors.
    """

    title: str
    facts: list[tuple[str, str]]
    biases: list[BiasEntry]
    correlation_names: list[str]
    correlation: np.ndarray
    pairs: list[PairSection]
    control: list[ControlResidual]
    radiometry: RadiometrySection | None
    calibration_facts: list[tuple[str, str]] = field(default_factory=list)
    strips: list[StripRow] = field(default_factory=list)
    flight: FlightMap | None = None
    swath: SwathDifferences | None = None
    swath_limit_m: float = 0.16
    quality: QualityAssessment | None = None
    evaluation: EvaluationSection | None = None
    provenance: Provenance | None = None
    crs: str = ""
    qa_warn_m: float = 0.08
    qa_error_m: float = 0.16
    smooth_slope_deg: float = 10.0
    warnings: list[str] = field(default_factory=list)
    trajectory: TrajectorySection | None = None
