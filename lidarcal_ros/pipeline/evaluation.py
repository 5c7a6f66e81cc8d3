"""``lidarcal evaluate``: the paper's accuracy measures on a mission, before and after calibration.

Numerics in :mod:`lidarcal_ros.core.qa.accuracy` (docs/method.md section 9). The strips'
correction, each pair's ICP and each strip's check-point heights are tasks of an executor
(here, or on Dask workers: ``--dask``), each strip sent once in its task; the pairs' subsets
are drawn and the results gathered here in the serial order.
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
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
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
from lidarcal_ros.pipeline.executor import (
    CommandTasks,
    Executor,
    SerialExecutor,
    TaskFuture,
    results_in_order,
)

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
    return [_corrected(strip, mission.trajectory, delta, settings) for strip in mission.strips]


def _corrected(strip: Strip, trajectory: Trajectory, delta: np.ndarray,
               settings: CalibrationSettings) -> np.ndarray:
    """``strip``'s points the trajectory serves, corrected by ``delta`` (map frame, m)."""
    ok, geo = flagged_geometry(strip.t, strip.xyz, trajectory, window=settings.window,
                               source=f"strip {strip.strip_id}",
                               heading_source=settings.heading_source, model=settings.model)
    xyz = strip.xyz[ok]
    if np.any(delta):
        xyz = correct_geometry(xyz, delta, geo)
    return xyz


@dataclass
class _StripStates:
    """A strip as the evaluation holds it (a task's result, kept where it ran): its points
    the trajectory serves as delivered (``before``) and corrected (``after``), map frame,
    metres, and the vertex shift of the corrected ones (delivered - corrected); its footprint
    cells (sorted keys of :func:`footprint_keys`) and the points in each."""

    before: np.ndarray
    after: np.ndarray
    shift: np.ndarray
    cells: np.ndarray
    counts: np.ndarray


@dataclass(frozen=True)
class _PairJob:
    """One pair's ICP for a task: the footprint cells the two strips share, which of the
    first strip's points in them to use (their ranks; None: all), the settings."""

    common: np.ndarray
    pick: np.ndarray | None
    settings: CalibrationSettings


def _strip_states(strip: Strip, trajectory: Trajectory, delta: np.ndarray,
                  settings: CalibrationSettings) -> _StripStates:
    """``strip`` delivered and corrected by ``delta`` (a task)."""
    before = _corrected(strip, trajectory, np.zeros(N_PARAMETERS), settings)
    after = _corrected(strip, trajectory, delta, settings)
    cells, counts = np.unique(footprint_keys(before, settings.overlap_cell_m),
                              return_counts=True)
    return _StripStates(before, after, before - after, cells, counts)


def _footprint(states: _StripStates) -> tuple[np.ndarray, np.ndarray]:
    """The strip's footprint cells and their points (a task: what this process needs)."""
    return states.cells, states.counts


def _strip_tin(states: _StripStates, settings: CalibrationSettings) -> Tin:
    """The TIN of the strip's delivered points (a task); after the correction its vertices
    move by a smooth field of centimetres to decimetres (as in the calibration's own
    matching)."""
    density = states.before.shape[0] / max(states.cells.size * settings.overlap_cell_m ** 2,
                                           1.0)
    return Tin(states.before, settings.tin_quality(density))


def _pair_fits(a: _StripStates, b: _StripStates, tin_b: Tin, job: _PairJob
               ) -> tuple[RigidFit | None, RigidFit | None]:
    """The rigid fits of ``a``'s points in the shared cells onto ``b``'s TIN, as delivered
    and as corrected (a task)."""
    s = job.settings
    inside = np.flatnonzero(np.isin(footprint_keys(a.before, s.overlap_cell_m), job.common))
    if job.pick is not None:
        inside = inside[job.pick]
    return (rigid_icp(a.before[inside], tin_b, b.before,
                      max_normal_distance=s.max_normal_distance_m, vertex_shift=None),
            rigid_icp(a.after[inside], tin_b, b.after,
                      max_normal_distance=s.max_normal_distance_m, vertex_shift=b.shift))


def _check_heights(states: _StripStates, tin: Tin, xy: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The strip's surface heights at ``xy`` (map frame, m), delivered and corrected (a
    task)."""
    return (tin_heights(tin, states.before, xy, vertex_shift=None),
            tin_heights(tin, states.after, xy, vertex_shift=states.shift))


def evaluate_mission(
    mission: Mission,
    delta: np.ndarray,
    settings: CalibrationSettings,
    *,
    check_points: ControlPoints | None = None,
    max_points_per_pair: int = 100_000,
    seed: int = 0,
    progress: Callable[[str, float], None] | None = None,
    executor: Executor | CommandTasks | None = None,
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
    executor : Executor or CommandTasks, optional
        Where the strips are corrected and each pair's ICP and each strip's check-point
        heights computed (default: here); the subsets are drawn and the results gathered
        here, in the serial order, so the evaluation is the serial one.

    Raises
    ------
    CalibrationError
        No two strips overlap and there are no check points: nothing to evaluate.
    """
    delta = np.asarray(delta, dtype=np.float64).reshape(N_PARAMETERS)
    tasks = executor if isinstance(executor, CommandTasks) else \
        CommandTasks(executor or SerialExecutor(), "evaluate")
    rng = np.random.default_rng(seed)
    if progress is not None:
        progress("evaluation: correcting strips", 0.0)
    trajectory = tasks.send(mission.trajectory, "trajectory")
    states = [tasks.submit(_strip_states, tasks.send(strip, f"strip{strip.strip_id}"),
                           trajectory, delta, settings, key=f"states{k}")
              for k, strip in enumerate(mission.strips)]
    footprints = results_in_order([tasks.submit(_footprint, s, key=f"footprint{k}")
                                   for k, s in enumerate(states)])
    cells = [c for c, _ in footprints]
    tins: dict[int, TaskFuture[Tin]] = {}

    def tin(k: int) -> TaskFuture[Tin]:
        if k not in tins:
            tins[k] = tasks.submit(_strip_tin, states[k], settings, key=f"tin{k}")
        return tins[k]

    ids = [s.strip_id for s in mission.strips]
    pair_fits: list[tuple[int, int, int, TaskFuture[tuple[RigidFit | None, RigidFit | None]]]] = []
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            common = np.intersect1d(cells[a], cells[b], assume_unique=True)
            if common.size < settings.min_overlap_cells:
                continue
            # (the subset drawn here, pair after pair, as a serial run draws it)
            n_inside = int(footprints[a][1][np.isin(cells[a], common)].sum())
            pick = np.sort(rng.choice(n_inside, max_points_per_pair, replace=False)) \
                if n_inside > max_points_per_pair else None
            pair_fits.append((a, b, int(common.size), tasks.submit(
                _pair_fits, states[a], states[b], tin(b), _PairJob(common, pick, settings),
                key=f"pair{a}-{b}")))
    pairs: list[PairAlignment] = []
    for i, (a, b, n_common, future) in enumerate(pair_fits):
        if progress is not None:
            progress("evaluation: co-alignment (ICP)", i / len(pair_fits))
        before, after = future.result()
        pairs.append(PairAlignment(ids[a], ids[b], n_common, before, after))
        logger.info("strips %d & %d: rigid fit %s -> %s", ids[a], ids[b], _short(before),
                    _short(after))
    residuals: list[CheckPointResidual] = []
    if check_points is not None and len(check_points):
        if progress is not None:
            progress("evaluation: check points", 0.0)
        cp_cells = footprint_keys(check_points.xyz, settings.overlap_cell_m)
        seen_by = [np.isin(cp_cells, cells[k]) for k in range(len(ids))]
        found = {k: tasks.submit(_check_heights, states[k], tin(k),
                                 check_points.xyz[seen_by[k], :2], key=f"check{k}")
                 for k in range(len(ids)) if seen_by[k].any()}
        heights = {which: np.full((len(ids), len(check_points)), np.nan)
                   for which in ("before", "after")}
        for k, strip_heights in found.items():
            heights["before"][k, seen_by[k]], heights["after"][k, seen_by[k]] = \
                strip_heights.result()
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
