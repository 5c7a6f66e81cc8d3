"""What a calibration reports: its result and the quality figures of its strip pairs.

:class:`CalibrationResult` is everything ``lidarcal calibrate`` reports and writes: the
adjustment, the QA of every strip pair (:class:`PairStats`, point by point
:class:`PairDiscrepancies`) and of every control point (:class:`ControlResidual`).
:class:`NothingEstimated` carries the result of a calibration that could estimate nothing.
:func:`robust_qa` is the statistic of every pair figure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Solution
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.georeferencing.rigorous import LaserVectorQA, ModelChoice
from lidarcal_ros.core.qa.overlap_grid import PairQA
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryEstimate
from lidarcal_ros.errors import CalibrationError


@dataclass
class PairStats:
    """QA of one strip pair: RMS normal discrepancy before and after calibration (metres)."""

    strip_a: int
    strip_b: int
    coverage: float
    correspondences: int
    rms_before: float
    rms_after: float
    n_before: int
    n_after: int
    p95_after: float = float("nan")  # 95th percentile of |discrepancy| after, metres


@dataclass
class PairDiscrepancies:
    """Normal discrepancies of one strip pair's sample points at one estimate (the QA of
    :class:`PairStats`, point by point).

    Attributes
    ----------
    points_strip, tin_strip : int
        Id of the strip whose points are matched, and of the strip whose TIN patches they are
        matched to.
    xy : (k, 2) float64
        Map-frame position of each matched point as delivered, metres.
    distance : (k,) float64
        Signed normal distance of each point from its patch, point minus patch along the
        patch's upward normal, after correcting both strips by the estimate; metres.
    rms, p95 : float
        RMS and 95th percentile of ``|distance|`` without gross mismatches, metres (the
        statistics of :class:`PairStats`).
    """

    points_strip: int
    tin_strip: int
    xy: np.ndarray
    distance: np.ndarray
    rms: float
    p95: float

    @property
    def strips(self) -> tuple[int, int]:
        """The two strip ids, smaller first (as in :class:`PairStats`)."""
        a, b = sorted((self.points_strip, self.tin_strip))
        return a, b


@dataclass
class ControlResidual:
    """Normal discrepancy of one control point against one strip, before and after (metres)."""

    control_id: str
    strip_id: int
    before: float
    after: float


@dataclass
class CalibrationResult:
    """Everything ``lidarcal calibrate`` reports and writes."""

    solution: Solution
    iterations: int
    converged: bool
    pairs: list[PairStats]
    control: list[ControlResidual]
    n_pair_correspondences: int
    n_control_correspondences: int
    history: list[np.ndarray]
    dropped_non_finite: int = 0
    thinned_points: int = 0  # left out by calibration.thinning_cell_m
    #: Strips a live input delivered only in part, with what is missing, by strip id
    #: (:mod:`lidarcal_ros.pipeline.calibration.strip_coverage`; empty offline).
    partial_strips: dict[int, str] = field(default_factory=dict)
    #: Where each strip's heading came from (``TRACK`` or ``ATTITUDE``), and its median crab
    #: (attitude less track, deg; NaN without attitude), by strip id.
    heading_from: dict[int, HeadingSource] = field(default_factory=dict)
    crab_deg: dict[int, float] = field(default_factory=dict)
    #: The point-positioning model of each strip and why (:mod:`~lidarcal_ros.core.
    #: georeferencing`), and the QA of its laser vectors, by strip id.
    models: dict[int, ModelChoice] = field(default_factory=dict)
    laser_qa: dict[int, LaserVectorQA] = field(default_factory=dict)
    #: Why nothing was estimated
    #: (:meth:`~lidarcal_ros.core.calibration.calibrate.Calibrator.unestimated_result`), empty
    #: otherwise.
    nothing_estimated: str = ""
    #: Where nothing was estimated: the strip pairs' height agreement on smooth cells, which
    #: needs no patch (:mod:`lidarcal_ros.core.qa.overlap_grid`).
    height_agreement: list[PairQA] = field(default_factory=list)
    #: How the iterations ended, in words (:func:`~lidarcal_ros.core.calibration.iteration.
    #: judge_convergence`): "converged: ...", "converged within the re-matching noise: ...",
    #: "not converged: ..."; empty where no adjustment ran.
    convergence: str = ""
    #: CPU seconds of the calibration's threads in each of its stages
    #: (:class:`~lidarcal_ros.core.calibration.threads.StageClock`).
    stage_seconds: dict[str, float] = field(default_factory=dict)
    #: Each strip's trajectory error estimated with the biases (docs/method.md section 11), or
    #: None where the trajectory was taken as exact.
    trajectory: TrajectoryEstimate | None = None
    #: The trajectory model that ran, and where ``auto`` chose it, why.
    trajectory_choice: str = "none"


class NothingEstimated(CalibrationError):
    """The adjustment could estimate nothing; :attr:`result` still says how well the strips
    agree as delivered.

    Attributes
    ----------
    reason : str
        Why nothing could be estimated (the message of the adjustment's refusal).
    result : CalibrationResult
        The calibration that moves no point
        (:meth:`~lidarcal_ros.core.calibration.calibrate.Calibrator.unestimated_result`): every bias
        at its fixed value, none estimated, not converged, with the strip pairs' QA.
    """

    def __init__(self, reason: str, result: CalibrationResult) -> None:
        super().__init__(reason)
        self.reason = reason
        self.result = result


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def robust_qa(distances: np.ndarray, floor_m: float) -> tuple[float, float]:
    """RMS and 95th percentile of |discrepancy| without gross mismatches (metres).

    Correspondences further than ``max(floor_m, 5 x 1.4826 x median |d|)`` from their patch are
    left out: points on walls or in trees matched to a neighbouring roof or ground patch. The
    scale is taken about zero, so a systematic offset between strips widens the cut and shows
    in full rather than being trimmed away.
    """
    d = np.abs(distances[np.isfinite(distances)])
    if not d.size:
        return float("nan"), float("nan")
    cut = max(floor_m, 5.0 * 1.4826 * float(np.median(d)))
    kept = d[d <= cut]
    return _rms(kept), float(np.percentile(kept, 95))


__all__ = [
    "CalibrationResult", "ControlResidual", "NothingEstimated", "PairDiscrepancies",
    "PairStats", "robust_qa",
]
