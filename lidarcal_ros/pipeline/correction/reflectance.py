"""The calibration constant of the reflectance, measured on a reference target of known reflectance.

The target and which of its points count: docs/correction.md, "The reflectance".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidarcal_ros.core.config import FlightConfig, parse_target_box
from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
    FLAG_VOLUME,
)
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.radiometry import constant_from_target, volume_returns
from lidarcal_ros.pipeline.correction.apply import (
    CorrectionSettings,
    NormalsFit,
    correct_columns,
    trajectory_heading,
)

#: Steepest incidence of a target point, degrees (the median stays on the Lambertian part).
TARGET_MAX_INCIDENCE_DEG = 60.0
#: Points around the box read with it, m: the surface normals of the points on its edge see
#: their whole neighbourhood.
TARGET_MARGIN_M = 20.0
#: Flags of points left out of the target.
_UNTRUSTED = (FLAG_NOT_CORRECTED | FLAG_NO_NORMAL | FLAG_NO_INTENSITY | FLAG_ROUGH | FLAG_GRAZING
              | FLAG_VOLUME)


@dataclass(frozen=True)
class TargetMeasurement:
    """A reference target measured on a mission.

    Attributes
    ----------
    box : (xmin, ymin, xmax, ymax)
        Map frame, m.
    known_reflectance : float
        The target's Lambertian reflectance (configuration).
    n_points : int
        Trusted points inside the box.
    median_relative : float
        Their median relative reflectance, intensity units.
    constant : float
        The calibration constant, intensity units.
    """

    box: tuple[float, float, float, float]
    known_reflectance: float
    n_points: int
    median_relative: float
    constant: float

    def describe(self) -> str:
        """One sentence for reports."""
        x0, y0, x1, y1 = self.box
        return (f"calibration constant {self.constant:.6g} from the reference target "
                f"({x0:.1f}, {y0:.1f})-({x1:.1f}, {y1:.1f}) of reflectance "
                f"{self.known_reflectance:g}: median relative reflectance "
                f"{self.median_relative:.6g} over {self.n_points} points")


def target_of(config: FlightConfig) -> tuple[tuple[float, float, float, float], float] | None:
    """The configured reference target (box, reflectance), or None."""
    text = str(config["radiometry.reference_target"])
    if not text:
        return None
    return parse_target_box(text), float(config["radiometry.reference_target_reflectance"])


def trusted_in_box(xyz: np.ndarray, flags: np.ndarray, incidence: np.ndarray,
                   box: tuple[float, float, float, float]) -> np.ndarray:
    """Points inside ``box`` whose reflectance is trusted (docs/correction.md, "The
    reflectance")."""
    x0, y0, x1, y1 = box
    x, y = xyz[:, 0], xyz[:, 1]
    with np.errstate(invalid="ignore"):
        steep = ~(incidence < math.radians(TARGET_MAX_INCIDENCE_DEG))
    return ((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            & ((flags & _UNTRUSTED) == 0) & ~steep)


def measure_target(
    parts: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    box: tuple[float, float, float, float],
    known_reflectance: float,
) -> TargetMeasurement:
    """The calibration constant from corrected points.

    Parameters
    ----------
    parts : iterable of (xyz, relative reflectance, flags, incidence)
        Corrected points ((n, 3) map frame, m), their reflectance computed *without* a
        calibration constant (intensity units), ``correction_flags`` and incidence (rad).
    box, known_reflectance
        The target.

    Raises
    ------
    ConfigError
        No trusted point inside the box, or a reflectance out of range.
    """
    values = [refl[trusted_in_box(xyz, flags, inc, box)] for xyz, refl, flags, inc in parts]
    relative = np.concatenate(values) if values else np.empty(0)
    constant = constant_from_target(relative, known_reflectance)
    used = int(np.count_nonzero(np.isfinite(relative) & (relative > 0)))
    return TargetMeasurement(box, float(known_reflectance), used,
                             constant * float(known_reflectance), constant)


def relative_settings(settings: CorrectionSettings) -> CorrectionSettings:
    """``settings`` without a calibration constant (the reflectance in intensity units)."""
    return dataclasses.replace(settings, radiometry=settings.radiometry.with_constant(0.0))


def with_constant(settings: CorrectionSettings, constant: float) -> CorrectionSettings:
    """``settings`` with the calibration constant ``constant`` (intensity units)."""
    return dataclasses.replace(settings, radiometry=settings.radiometry.with_constant(constant))


def measure_target_on_mission(
    mission: Mission,
    settings: CorrectionSettings,
    target: tuple[tuple[float, float, float, float], float],
) -> TargetMeasurement:
    """A reference target (box, known reflectance) measured on a mission in memory: the
    points of each strip within :data:`TARGET_MARGIN_M` of the box corrected with
    ``settings`` but without a calibration constant.

    Raises
    ------
    ConfigError
        No trusted point inside the box.
    """
    box, known = target
    m = TARGET_MARGIN_M
    relative = relative_settings(settings)

    def corrected() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        for strip in mission.strips:
            if strip.intensity is None or not len(strip):
                continue
            x, y = strip.xyz[:, 0], strip.xyz[:, 1]
            near = (x >= box[0] - m) & (x <= box[2] + m) & (y >= box[1] - m) & (y <= box[3] + m)
            if not near.any():
                continue
            heading = trajectory_heading(mission.trajectory, float(np.nanmedian(strip.t)))
            volume = volume_returns(strip.extra.get("return_number"),
                                    strip.extra.get("number_of_returns"))
            res = correct_columns(strip.xyz[near], strip.t[near], strip.intensity[near],
                                  mission.trajectory, relative,
                                  normals=NormalsFit(heading=heading),
                                  source=f"strip {strip.strip_id}",
                                  volume=None if volume is None else volume[near],
                                  strip_id=strip.strip_id)
            yield res.xyz, res.reflectance, res.flags, res.incidence

    return measure_target(corrected(), box, known)


def measure_target_in_bag(
    bag: str | Path,
    settings: CorrectionSettings,
    config: FlightConfig,
) -> TargetMeasurement | None:
    """The configured reference target measured on a mission bag (None when the
    configuration names no target): only the points within :data:`TARGET_MARGIN_M` of the
    box are read (:func:`measure_target_on_mission`)."""
    target = target_of(config)
    if target is None:
        return None
    from lidarcal_ros.pipeline.calibration.procedure import (
        load_mission,  # (the calibration's imports)
    )

    (x0, y0, x1, y1), _ = target
    m = TARGET_MARGIN_M
    mission = load_mission(bag, config, box=(x0 - m, y0 - m, x1 + m, y1 + m))
    return measure_target_on_mission(mission, settings, target)


__all__ = [
    "TARGET_MARGIN_M", "TARGET_MAX_INCIDENCE_DEG", "TargetMeasurement", "measure_target",
    "measure_target_in_bag", "measure_target_on_mission", "relative_settings", "target_of",
    "trusted_in_box", "with_constant",
]
