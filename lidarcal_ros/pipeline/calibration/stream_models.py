"""The calibrators a live calibration runs for its trajectory model (docs/method.md section 11).

One for a model set, two for ``auto``, compared as ``lidarcal calibrate`` compares them
(docs/nodes.md, "How the calibrator works").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.calibrate import (
    CalibrationSettings,
    Calibrator,
    choose_trajectory_model,
    with_trajectory_model,
)
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.mission import ControlPoints, Strip, Trajectory
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryModel, TrajectoryRows
from lidarcal_ros.errors import CalibrationError, InputError
from lidarcal_ros.pipeline.calibration.checkpoint import ModelState

__all__ = ["ModelCalibrators"]

#: What an ``auto`` estimate says of its model before the two models were compared.
NOT_COMPARED = "auto: none (each strip's spline is tried once the estimate has converged)"


class ModelCalibrators:
    """The calibrator whose estimate is published (:attr:`active`) and, for ``auto``, the
    other model's (:attr:`rival`); docs/nodes.md.

    Parameters
    ----------
    settings : CalibrationSettings
    control : ControlPoints, optional
    """

    def __init__(self, settings: CalibrationSettings, *,
                 control: ControlPoints | None = None) -> None:
        self.active: Calibrator
        self.rival: Calibrator | None = None
        if settings.trajectory.model is TrajectoryModel.AUTO:
            self.active = Calibrator(with_trajectory_model(settings, TrajectoryModel.NONE),
                                     control=control)
            self.rival = Calibrator(with_trajectory_model(settings, TrajectoryModel.SPLINE),
                                    control=control)
            #: The ``trajectory_choice`` of the estimates published.
            self.choice = NOT_COMPARED
        else:
            self.active = Calibrator(settings, control=control)
            self.choice = settings.trajectory.model.value

    @property
    def calibrators(self) -> list[Calibrator]:
        """The active calibrator, then the rival if any."""
        return [self.active] + ([self.rival] if self.rival is not None else [])

    def add_strip(self, strip: Strip, trajectory: Trajectory) -> list[tuple[int, int]]:
        """Prepare a strip once for every calibrator; the pairs it forms
        (:meth:`Calibrator.add_strip`, which says what it raises)."""
        formed = self.active.add_strip(strip, trajectory)
        if self.rival is not None:
            self.rival.add_prepared_strip(self.active.strips[-1])
        return formed

    def add_released(self, strip_id: int, span: tuple[float, float]) -> None:
        """Hold a strip released before a restart, flown over ``span`` (first and last time,
        s), for its trajectory error alone (:meth:`Calibrator.add_released_strip`), in every
        calibrator."""
        ps = self.active.add_released_strip(strip_id, span)
        if self.rival is not None:
            self.rival.add_prepared_strip(ps, span=span)

    def drop_strip(self, strip_id: int) -> int:
        """Release a strip's points in every calibrator (each matches the strip's pairs it
        never matched first: the points are shared); the points released."""
        for cal in self.calibrators:
            cal.match_before_release(strip_id)
        return sum(cal.drop_strip(strip_id) for cal in self.calibrators)

    def set_control(self, control: ControlPoints | None) -> None:
        """Control points for every calibrator's runs from now on."""
        for cal in self.calibrators:
            cal.set_control(control)

    def label(self, result: CalibrationResult) -> CalibrationResult:
        """``result`` of the active calibrator, its ``trajectory_choice`` said."""
        result.trajectory_choice = self.choice
        return result

    def choose(self, active: CalibrationResult,
               rival: CalibrationResult | CalibrationError) -> CalibrationResult:
        """``auto``: of the active calibrator's result and the rival's (or why the rival
        determined nothing), the one ``lidarcal calibrate`` would choose; its calibrator is
        the active one from now on."""
        assert self.rival is not None
        if self.active.settings.trajectory.model is TrajectoryModel.NONE:
            chosen = choose_trajectory_model(active, rival)
        elif isinstance(rival, CalibrationError):
            # (batch would fail: the trajectory as exact determines nothing, the spline does)
            chosen = active
            chosen.trajectory_choice = f"auto: spline (the trajectory as exact: {rival})"
        else:
            chosen = choose_trajectory_model(rival, active)
        if chosen is not active:
            self.active, self.rival = self.rival, self.active
        self.choice = chosen.trajectory_choice
        return chosen

    # ------------------------------------------------------------------ checkpoints
    def states(self) -> list[ModelState]:
        """Every calibrator's state for a checkpoint, the active one's first."""
        return [_state_of(cal) for cal in self.calibrators]

    def restore(self, states: Sequence[ModelState], choice: str) -> None:
        """Take the calibrators' states back from a checkpoint (the strips held added first):
        each calibrator the state of its model (another model's estimate where the checkpoint
        holds none of its own), the one published first active again."""
        if not states:
            return
        if self.rival is not None and states[0].model == self.rival.settings.trajectory.model.value:
            self.active, self.rival = self.rival, self.active
        if self.rival is not None and choice.startswith("auto"):
            self.choice = choice
        for cal in self.calibrators:
            model = cal.settings.trajectory.model.value
            _restore(cal, next((s for s in states if s.model == model), states[0]))


def _state_of(cal: Calibrator) -> ModelState:
    """A calibrator's :class:`ModelState`: its frozen correspondences' strips by id."""
    ids = np.array([ps.strip_id for ps in cal.strips], dtype=np.int64)
    frozen = cal.frozen_observations()
    rows = frozen.trajectory
    if rows is not None:
        by_id = np.append(ids, -1)  # (index -1: no strip)
        frozen = Observations(frozen.rows, frozen.y, frozen.weights, frozen.group,
                              frozen.cluster, TrajectoryRows(
                                  by_id[rows.strip_a], rows.t_a, by_id[rows.strip_b], rows.t_b,
                                  rows.normal, rows.applied), frozen.pose_loading)
    return ModelState(cal.settings.trajectory.model.value, cal.delta.copy(),
                      float(cal.threshold), frozen, ids, cal.trajectory.spans,
                      cal.trajectory.params.copy(),
                      np.array(cal.trajectory.starts, dtype=np.int64))


def _restore(cal: Calibrator, state: ModelState) -> None:
    """Set ``cal``'s estimate, threshold, trajectory errors and frozen correspondences to
    ``state``'s (strips by id; another model's: its estimate and threshold, and its frozen
    correspondences without their trajectory terms)."""
    cal.delta = np.array(state.delta, dtype=np.float64)
    cal.threshold = state.threshold
    traj = cal.trajectory
    same = state.model == cal.settings.trajectory.model.value and traj.active
    held = [ps.strip_id for ps in cal.strips]
    for k, sid in enumerate(held):
        saved = state.strip_params(sid) if same else None
        if saved is not None and saved.shape == traj.strip_params(k).shape:
            traj.strip_params(k)[:] = saved
    frozen = state.frozen
    rows = frozen.trajectory
    if rows is not None:
        rows = _renumbered(rows, held) if same else None
        frozen = Observations(frozen.rows, frozen.y, frozen.weights, frozen.group,
                              frozen.cluster, rows, frozen.pose_loading)
    cal.restore_frozen(frozen)  # (expressed at the saved estimate and trajectory errors)


def _renumbered(rows: TrajectoryRows, held: list[int]) -> TrajectoryRows:
    """Trajectory terms naming strips by id, by index into the strips ``held``."""
    index = {sid: k for k, sid in enumerate(held)}
    uniq = np.unique(np.concatenate([rows.strip_a, rows.strip_b]))
    missing = [int(u) for u in uniq if u >= 0 and int(u) not in index]
    if missing:
        raise InputError(f"checkpoint: frozen correspondences of strips {missing}, which it "
                         "does not hold")

    def lookup(ids: np.ndarray) -> np.ndarray:
        uniq, inverse = np.unique(ids, return_inverse=True)
        return np.array([index.get(int(u), -1) for u in uniq], dtype=np.int64)[inverse]

    return TrajectoryRows(lookup(rows.strip_a), rows.t_a, lookup(rows.strip_b), rows.t_b,
                          rows.normal, rows.applied)
