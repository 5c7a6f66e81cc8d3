"""Which quality level of the USGS Lidar Base Specification (LBS) a mission meets.

The measures assessed: docs/internals.md, "Quality measures".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: ASPRS (2014) asks for at least this many NVA check points for a formal test of a project.
MIN_NVA_CHECK_POINTS = 20


@dataclass(frozen=True)
class QualityLevel:
    """The LBS thresholds of one quality level.

    Attributes
    ----------
    name : str
    rmsdz_m, max_dz_m : float
        Interswath RMSDz and largest |dz|, metres (at most).
    nva_rmse_m : float
        Non-vegetated vertical accuracy, RMSEz, metres (at most).
    anpd_per_m2 : float
        Aggregate nominal pulse density, pulses per square metre (at least).
    """

    name: str
    rmsdz_m: float
    max_dz_m: float
    nva_rmse_m: float
    anpd_per_m2: float


#: The LBS quality levels, best first.
LBS_LEVELS: tuple[QualityLevel, ...] = (
    QualityLevel("QL0", 0.04, 0.08, 0.05, 8.0),
    QualityLevel("QL1", 0.08, 0.16, 0.10, 8.0),
    QualityLevel("QL2", 0.08, 0.16, 0.10, 2.0),
    QualityLevel("QL3", 0.16, 0.32, 0.20, 0.5),
)


@dataclass(frozen=True)
class Criterion:
    """One measure against every level.

    Attributes
    ----------
    name : str
    value : float
        As measured (SI: metres or per square metre); NaN when not assessed.
    attribute : str
        The :class:`QualityLevel` field it is compared with.
    at_least : bool
        The threshold is a minimum (density), else a maximum.
    note : str
        How it was measured.
    """

    name: str
    value: float
    attribute: str
    at_least: bool = False
    note: str = ""

    @property
    def assessed(self) -> bool:
        """Whether the measure has a value (it is finite)."""
        return math.isfinite(self.value)

    def threshold(self, level: QualityLevel) -> float:
        """The level's threshold for this measure (SI, as ``value``)."""
        return float(getattr(level, self.attribute))

    def met(self, level: QualityLevel) -> bool | None:
        """Whether the level's threshold is met (None: not assessed)."""
        if not self.assessed:
            return None
        limit = self.threshold(level)
        return self.value >= limit if self.at_least else self.value <= limit


@dataclass(frozen=True)
class QualityAssessment:
    """The measures and the best level they all meet."""

    criteria: tuple[Criterion, ...]

    def met(self, level: QualityLevel) -> bool:
        """Every assessed measure within the level's threshold."""
        return all(c.met(level) is not False for c in self.criteria)

    @property
    def best(self) -> QualityLevel | None:
        """The best level met (None: not even QL3)."""
        return next((level for level in LBS_LEVELS if self.met(level)), None)

    def statement(self) -> str:
        """One sentence: the best level met, what fails the next one, what was not
        assessed."""
        best = self.best
        assessed = [c.name for c in self.criteria if c.assessed]
        head = (f"Meets USGS LBS {best.name}" if best is not None
                else "Does not meet USGS LBS QL3") + f" on {', '.join(assessed)}"
        better = LBS_LEVELS[:LBS_LEVELS.index(best)] if best is not None else LBS_LEVELS
        if better:
            nearest = better[-1]
            failing = [c.name for c in self.criteria if c.met(nearest) is False]
            head += f"; {nearest.name} is missed on {', '.join(failing)}"
        missing = [c.name for c in self.criteria if not c.assessed]
        if missing:
            head += f"; not assessed: {', '.join(missing)}"
        return head + "."


def assess(*, rmsdz_m: float, max_dz_m: float, anpd_per_m2: float, nva_rmse_m: float = math.nan,
           n_check_points: int = 0, dz_note: str = "") -> QualityAssessment:
    """The LBS measures of a mission (NaN: not assessed)."""
    nva_note = f"{n_check_points} check point{'' if n_check_points == 1 else 's'}"
    if 0 < n_check_points < MIN_NVA_CHECK_POINTS:
        nva_note += (f" (fewer than the {MIN_NVA_CHECK_POINTS} of a formal test: "
                     "indicative)")
    return QualityAssessment((
        Criterion("interswath RMSDz", rmsdz_m, "rmsdz_m", note=dz_note),
        Criterion("interswath max |dz|", max_dz_m, "max_dz_m", note=dz_note),
        Criterion("NVA RMSEz", nva_rmse_m, "nva_rmse_m",
                  note=nva_note if n_check_points else "no check points"),
        Criterion("aggregate nominal pulse density", anpd_per_m2, "anpd_per_m2",
                  at_least=True, note="points over the area the strips cover"),
    ))


__all__ = [
    "LBS_LEVELS",
    "MIN_NVA_CHECK_POINTS",
    "Criterion",
    "QualityAssessment",
    "QualityLevel",
    "assess",
]
