"""``lidarcal evaluate``: the paper's accuracy measures on a mission, before and after calibration.

Numerics in :mod:`lidarcal_ros.core.qa.accuracy` (docs/method.md section 9).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.calibration.pairs import footprint_keys
from lidarcal_ros.core.calibration.tin import Tin
from lidarcal_ros.core.georeferencing.bias_model import correct_geometry
from lidarcal_ros.core.mission import ControlPoints, Mission
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.qa.accuracy import (
    RIGID_NAMES,
    AccuracySummary,
    RigidFit,
    rigid_icp,
    tin_heights,
)
from lidarcal_ros.core.units import finite_or_none, format_cm
from lidarcal_ros.errors import CalibrationError, ConfigError
from lidarcal_ros.pipeline.correction.apply import flagged_geometry

logger = logging.getLogger(__name__)


@dataclass
class PairAlignment:
    """Table 3 row: one strip pair's co-aligning transformation before and after."""

    strip_a: int
    strip_b: int
    overlap_cells: int
    before: RigidFit | None
    after: RigidFit | None


@dataclass
class CheckPointResidual:
    """Table 4 row: surface height minus surveyed height at one check point (metres)."""

    point_id: str
    strips: list[int]
    before: float
    after: float


@dataclass
class Evaluation:
    """Everything ``lidarcal evaluate`` reports.

    ``delta``: the biases evaluated (SI, docs/method.md order), None where not known.
    """

    pairs: list[PairAlignment]
    check_points: list[CheckPointResidual] = field(default_factory=list)
    delta: np.ndarray | None = None

    def summary(self, which: str) -> AccuracySummary:
        """Check-point statistics ``before`` or ``after``."""
        return AccuracySummary.of(np.array([getattr(c, which) for c in self.check_points]))

    def as_dict(self) -> dict[str, Any]:
        """Plain types for JSON (SI units; None where undetermined)."""

        def fit(f: RigidFit | None) -> dict[str, Any] | None:
            if f is None:
                return None
            return {"values": f.as_dict(),
                    "sigmas": {n: (float(s) if d else None) for n, s, d in
                               zip(RIGID_NAMES, f.sigmas, f.determined, strict=True)},
                    "rms_before_m": f.rms_before, "rms_after_m": f.rms_after,
                    "matches": f.n_matches, "iterations": f.iterations,
                    "converged": f.converged}

        out: dict[str, Any] = {"pairs": [
            {"strips": [p.strip_a, p.strip_b], "overlap_cells": p.overlap_cells,
             "before": fit(p.before), "after": fit(p.after)} for p in self.pairs]}
        if self.delta is not None:
            out["biases"] = {n: float(v) for n, v in zip(PARAMETER_NAMES, self.delta,
                                                         strict=True)}
        if self.check_points:
            out["check_points"] = {
                "residuals": [{"id": c.point_id, "strips": c.strips,
                               "before_m": finite_or_none(c.before),
                               "after_m": finite_or_none(c.after)}
                              for c in self.check_points],
                "before": {k: finite_or_none(v) for k, v in vars(self.summary("before")).items()},
                "after": {k: finite_or_none(v) for k, v in vars(self.summary("after")).items()},
            }
        return out


    @classmethod
    def from_dict(cls, doc: Any, *, source: str = "evaluation") -> Evaluation:
        """Read back :meth:`as_dict` (``lidarcal evaluate --json``).

        Raises
        ------
        ConfigError
            One line naming ``source`` and the key at fault.
        """
        try:
            biases = doc.get("biases") if isinstance(doc, Mapping) else None
            delta = (np.array([float(biases[n]) for n in PARAMETER_NAMES])
                     if isinstance(biases, Mapping) else None)
            pairs = [PairAlignment(int(p["strips"][0]), int(p["strips"][1]),
                                   int(p["overlap_cells"]), _fit_from(p["before"]),
                                   _fit_from(p["after"])) for p in doc["pairs"]]
            checks = doc.get("check_points") or {}
            residuals = [CheckPointResidual(str(c["id"]), [int(s) for s in c["strips"]],
                                            _float(c["before_m"]), _float(c["after_m"]))
                         for c in checks.get("residuals", [])]
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
            raise ConfigError(f"{source}: not an evaluation of lidarcal evaluate --json "
                              f"({type(exc).__name__}: {exc})") from None
        return cls(pairs, residuals, delta)


def _float(v: Any) -> float:
    return math.nan if v is None else float(v)


def _fit_from(doc: Any) -> RigidFit | None:
    """A :class:`RigidFit` from its :meth:`Evaluation.as_dict` form (None stays None)."""
    if doc is None:
        return None
    values = np.array([_float(doc["values"][n]) for n in RIGID_NAMES])
    sigmas = np.array([_float(doc["sigmas"][n]) for n in RIGID_NAMES])
    return RigidFit(values=values, sigmas=sigmas, determined=np.isfinite(values),
                    rms_before=_float(doc["rms_before_m"]), rms_after=_float(doc["rms_after_m"]),
                    n_matches=int(doc["matches"]), iterations=int(doc["iterations"]),
                    converged=bool(doc["converged"]))


def corrected_strips(
    mission: Mission, delta: np.ndarray, settings: CalibrationSettings
) -> list[np.ndarray]:
    """Every strip's points corrected by ``delta`` (eq. [13]), map frame, metres; points the
    trajectory cannot serve are left out."""
    out = []
    for strip in mission.strips:
        ok, geo = flagged_geometry(strip.t, strip.xyz, mission.trajectory,
                                   window=settings.window,
                                   source=f"strip {strip.strip_id}",
                                   heading_source=settings.heading_source,
                                   model=settings.model)
        xyz = strip.xyz[ok]
        if np.any(delta):
            xyz = correct_geometry(xyz, delta, geo)
        out.append(xyz)
    return out


def _tin(xyz: np.ndarray, n_cells: int, settings: CalibrationSettings) -> Tin:
    density = xyz.shape[0] / max(n_cells * settings.overlap_cell_m ** 2, 1.0)
    return Tin(xyz, settings.tin_quality(density))


def evaluate_mission(
    mission: Mission,
    delta: np.ndarray,
    settings: CalibrationSettings,
    *,
    check_points: ControlPoints | None = None,
    max_points_per_pair: int = 100_000,
    seed: int = 0,
    progress: Callable[[str, float], None] | None = None,
) -> Evaluation:
    """Tables 3 and 4 of the paper for ``mission`` before and after the estimate ``delta``.

    Parameters
    ----------
    mission : Mission
    delta : (8,) float64
        Estimated biases, SI units (docs/method.md section 1).
    settings : CalibrationSettings
        Overlap and TIN rules (as the calibration used them).
    check_points : ControlPoints, optional
        Surveyed points not used in the adjustment.
    max_points_per_pair : int
        Points of the first strip of a pair used by the ICP (a random subset beyond).
    seed : int
        Seed of that subset.
    progress : callable(stage, fraction), optional

    Raises
    ------
    CalibrationError
        No two strips overlap and there are no check points: nothing to evaluate.
    """
    delta = np.asarray(delta, dtype=np.float64).reshape(N_PARAMETERS)
    rng = np.random.default_rng(seed)
    if progress is not None:
        progress("evaluation: correcting strips", 0.0)
    states = {"before": corrected_strips(mission, np.zeros(N_PARAMETERS), settings),
              "after": corrected_strips(mission, delta, settings)}
    cells = [np.unique(footprint_keys(x, settings.overlap_cell_m)) for x in states["before"]]
    # One TIN per strip, on its delivered points; after the correction its vertices move by
    # a smooth field of centimetres to decimetres (as in the calibration's own matching).
    tins: dict[int, Tin] = {}
    shifts: dict[str, list[np.ndarray | None]] = {
        "before": [None] * len(states["before"]),
        "after": [b - a for b, a in zip(states["before"], states["after"])]}

    def tin(k: int) -> Tin:
        if k not in tins:
            tins[k] = _tin(states["before"][k], cells[k].size, settings)
        return tins[k]

    pairs: list[PairAlignment] = []
    ids = [s.strip_id for s in mission.strips]
    for a in range(len(ids)):
        if progress is not None:
            progress("evaluation: co-alignment (ICP)", a / max(len(ids), 1))
        for b in range(a + 1, len(ids)):
            common = np.intersect1d(cells[a], cells[b], assume_unique=True)
            if common.size < settings.min_overlap_cells:
                continue
            inside = np.flatnonzero(np.isin(footprint_keys(states["before"][a],
                                                   settings.overlap_cell_m), common))
            if inside.size > max_points_per_pair:
                inside = np.sort(rng.choice(inside, max_points_per_pair, replace=False))
            fits: dict[str, RigidFit | None] = {}
            for which in ("before", "after"):
                fits[which] = rigid_icp(states[which][a][inside], tin(b), states[which][b],
                                        max_normal_distance=settings.max_normal_distance_m,
                                        vertex_shift=shifts[which][b])
            pairs.append(PairAlignment(ids[a], ids[b], int(common.size),
                                       fits["before"], fits["after"]))
            logger.info("strips %d & %d: rigid fit %s -> %s", ids[a], ids[b],
                        _short(fits["before"]), _short(fits["after"]))
    residuals: list[CheckPointResidual] = []
    if check_points is not None and len(check_points):
        if progress is not None:
            progress("evaluation: check points", 0.0)
        heights: dict[str, np.ndarray] = {}
        for which in ("before", "after"):
            per_strip = np.full((len(ids), len(check_points)), np.nan)
            cp_cells = footprint_keys(check_points.xyz, settings.overlap_cell_m)
            for k in range(len(ids)):
                seen = np.isin(cp_cells, cells[k])
                if seen.any():
                    per_strip[k, seen] = tin_heights(tin(k), states[which][k],
                                                     check_points.xyz[seen, :2],
                                                     vertex_shift=shifts[which][k])
            heights[which] = per_strip
        for c, pid in enumerate(check_points.ids):
            seen = np.isfinite(heights["before"][:, c]) | np.isfinite(heights["after"][:, c])
            if not seen.any():
                logger.warning("check point %s: no strip covers it", pid)
            z = check_points.xyz[c, 2]
            residuals.append(CheckPointResidual(
                pid, [ids[k] for k in np.flatnonzero(seen)],
                _mean(heights["before"][:, c] - z), _mean(heights["after"][:, c] - z)))
    if not pairs and not residuals:
        raise CalibrationError("no overlapping strips and no check points: nothing to "
                               "evaluate")
    return Evaluation(pairs, residuals, delta)


def _mean(values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    return float(v.mean()) if v.size else math.nan


def _short(fit: RigidFit | None) -> str:
    if fit is None:
        return "none"
    return f"RMS {100 * fit.rms_after:.1f} cm"


def format_evaluation(ev: Evaluation) -> str:
    """Tables 3 and 4 as text: shifts in cm, rotations in arcsec, '-' where undetermined;
    the RMS normal discrepancy of the pair as it is and after the rigid fit."""
    arcsec = 180.0 / math.pi * 3600.0
    lines = ["relative accuracy: rigid transformation co-aligning each strip pair "
             "(point-to-patch ICP)",
             "strips  state      tx cm   ty cm   tz cm  omega \"   phi \"  kappa \""
             "  RMS cm (fitted)  matches"]

    def row(label: str, f: RigidFit | None) -> str:
        if f is None:
            return f"{label}  (no correspondences)"
        cells = []
        for i, v in enumerate(f.values):
            if not f.determined[i] or not math.isfinite(v):
                cells.append(f"{'-':>7}")
            else:
                cells.append(f"{v * (100.0 if i < 3 else arcsec):+7.1f}")
        return (f"{label} " + " ".join(cells)
                + f"  {100 * f.rms_before:6.1f} ({100 * f.rms_after:4.1f})  {f.n_matches:7d}")

    for p in ev.pairs:
        pair = f"{p.strip_a:>2} & {p.strip_b:<2}"
        lines.append(row(f"{pair} before", p.before))
        lines.append(row(f"{' ' * len(pair)} after ", p.after))
    if ev.check_points:
        lines.append("")
        lines.append("absolute accuracy: check points (strip surface minus surveyed height)")
        lines.append("point            strips            before cm   after cm")
        for c in ev.check_points:
            lines.append(f"{c.point_id:<16} {','.join(map(str, c.strips)) or '-':<16} "
                         f"{format_cm(c.before, sign=True, missing='-'):>10} "
                         f"{format_cm(c.after, sign=True, missing='-'):>10}")
        for which in ("before", "after"):
            s = ev.summary(which)
            lines.append(f"{which:<6} n={s.n}  mean {format_cm(s.mean, sign=True, missing='-')} "
                         f"cm  std {format_cm(s.std, missing='-')} cm  RMSE "
                         f"{format_cm(s.rmse, missing='-')} cm  max |r| "
                         f"{format_cm(s.max_abs, missing='-')} cm")
    return "\n".join(lines)


__all__ = [
    "CheckPointResidual", "Evaluation", "PairAlignment", "corrected_strips",
    "evaluate_mission", "format_evaluation",
]
