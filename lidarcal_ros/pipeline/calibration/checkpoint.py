"""Checkpoint files of the live calibration: everything it needs to resume, in one ``.npz``.

What it holds: docs/nodes.md, "How the calibrator works". Files of earlier versions of the same
format version, which lack some counters, are read too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal_ros.core.adjustment.ins_noise import PoseLoading
from lidarcal_ros.core.adjustment.least_squares import NormalEquations, Observations
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.mission import ControlPoints, Strip
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryRows
from lidarcal_ros.errors import InputError

__all__ = ["CHECKPOINT_VERSION", "ModelState", "SensorFrameState", "StreamCheckpoint",
           "read_checkpoint", "write_checkpoint"]

CHECKPOINT_VERSION = 3

_FROZEN_FIELDS = ("rows", "y", "weights", "group", "cluster")
_ROWS_FIELDS = ("strip_a", "t_a", "strip_b", "t_b", "normal", "applied")


@dataclass
class ModelState:
    """One trajectory model's calibration: its estimate (``PARAMETER_NAMES`` order, SI), the
    matching threshold (m), every strip's trajectory error (strip ids, first and last times
    (S, 2) s, every strip's coefficients one after another, ``starts`` (S + 1) where each
    strip's begin) and the frozen correspondences expressed at them, their trajectory terms
    naming strips by id (-1: none), not by index."""

    model: str
    delta: np.ndarray
    threshold: float
    frozen: Observations
    trajectory_ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    spans: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    params: np.ndarray = field(default_factory=lambda: np.empty(0))
    starts: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))

    def strip_params(self, strip_id: int) -> np.ndarray | None:
        """The coefficients saved for strip ``strip_id``, None where none are."""
        where = np.flatnonzero(self.trajectory_ids == strip_id)
        if not where.size:
            return None
        k = int(where[0])
        return self.params[int(self.starts[k]):int(self.starts[k + 1])]


@dataclass
class SensorFrameState:
    """Clouds in the sensor's frame fed to the calibration
    (:class:`~lidarcal_ros.pipeline.calibration.sensor_stream.SensorFrameFeed`): its frames,
    the nominal mounting the calibration's trajectory was made with (None: none yet), the
    lines closed (k, 2) s, the poses of the base frame as received (times, positions,
    quaternions xyzw), the points held in the sensor's frame (n, 3) m with their times s,
    the newest pose handed on and the time up to which points were, s, and its counters
    (turn, late, overflow points)."""

    frame_id: str
    base_frame: str
    map_frame: str
    nominal: Mounting | None
    lines: np.ndarray
    poses: tuple[np.ndarray, np.ndarray, np.ndarray]
    pending_xyz: np.ndarray
    pending_t: np.ndarray
    fed_t: float
    handed_t: float
    counters: tuple[int, int, int]


def _sensor_arrays(state: SensorFrameState) -> dict[str, np.ndarray]:
    t, xyz, q = state.poses
    # (the rotation matrix itself: a quaternion's round trip moves it by 1e-16)
    nominal = np.full(12, np.nan) if state.nominal is None else \
        np.concatenate([state.nominal.translation, state.nominal.rotation.ravel()])
    return {"sensor_frames": np.array([state.frame_id, state.base_frame, state.map_frame]),
            "sensor_nominal": nominal, "sensor_lines": state.lines, "sensor_traj_t": t,
            "sensor_traj_xyz": xyz, "sensor_traj_orientation": q,
            "sensor_pending_xyz": state.pending_xyz, "sensor_pending_t": state.pending_t,
            "sensor_times": np.array([state.fed_t, state.handed_t]),
            "sensor_counters": np.array(state.counters, dtype=np.int64)}


def _sensor_of(data: np.lib.npyio.NpzFile) -> SensorFrameState | None:
    if "sensor_frames" not in data:
        return None
    frame_id, base_frame, map_frame = (str(v) for v in data["sensor_frames"])
    nominal = np.array(data["sensor_nominal"])
    fed_t, handed_t = (float(v) for v in data["sensor_times"])
    turn, late, overflow = (int(v) for v in data["sensor_counters"])
    return SensorFrameState(
        frame_id=frame_id, base_frame=base_frame, map_frame=map_frame,
        nominal=None if np.isnan(nominal).any() else Mounting(nominal[3:].reshape(3, 3),
                                                              nominal[:3]),
        lines=np.array(data["sensor_lines"]).reshape(-1, 2),
        poses=(np.array(data["sensor_traj_t"]), np.array(data["sensor_traj_xyz"]),
               np.array(data["sensor_traj_orientation"])),
        pending_xyz=np.array(data["sensor_pending_xyz"]),
        pending_t=np.array(data["sensor_pending_t"]), fed_t=fed_t, handed_t=handed_t,
        counters=(turn, late, overflow))


@dataclass
class StreamCheckpoint:
    """The state of a live calibration (docs/nodes.md); map frame, m, s, SI units."""

    frame_id: str | None
    #: Trajectory samples as received: times (n,), positions (n, 3), quaternions xyzw (n, 4).
    trajectory: tuple[np.ndarray, np.ndarray, np.ndarray]
    #: Complete strips the calibration holds, in the order they were added to it.
    closed: list[Strip]
    #: Strips being flown: the points held so far.
    open: list[Strip]
    #: The calibration of each trajectory model run, the one published first.
    models: list[ModelState]
    converged: bool
    normal_equations: NormalEquations
    control: ControlPoints | None
    dropped_points: int = 0
    dropped_non_finite: int = 0
    thinned_points: int = 0
    auto_thinning_cell_m: float = 0.0
    uncovered_points: int = 0
    uncovered_strips: list[int] = field(default_factory=list)
    rejected_strips: list[tuple[int, str]] = field(default_factory=list)
    dropped_strips: list[int] = field(default_factory=list)
    #: The trajectory model published, and where ``auto`` chose it, why.
    trajectory_choice: str = ""
    #: Clouds in the sensor's frame (None: map-frame clouds; then the trajectory is the
    #: sensor's origin's and the strips the lines').
    sensor: SensorFrameState | None = None


def _model_arrays(k: int, state: ModelState) -> dict[str, np.ndarray]:
    """The arrays of model ``k`` (the first under the names of files with one model)."""
    pre = f"m{k}_" if k else ""
    arrays = {f"{pre}delta": state.delta, f"{pre}threshold": np.array(state.threshold),
              f"{pre}traj_model": np.array(state.model), f"{pre}traj_ids": state.trajectory_ids,
              f"{pre}traj_spans": state.spans, f"{pre}traj_params": state.params,
              f"{pre}traj_starts": state.starts}
    for name in _FROZEN_FIELDS:
        arrays[f"{pre}frozen_{name}"] = getattr(state.frozen, name)
    rows = state.frozen.trajectory
    if rows is not None:
        for name in _ROWS_FIELDS:
            arrays[f"{pre}frozen_traj_{name}"] = getattr(rows, name)
    loading = state.frozen.pose_loading
    if loading is not None:
        arrays[f"{pre}frozen_loading_nodes"] = loading.nodes
        arrays[f"{pre}frozen_loading_coef"] = loading.coef
    return arrays


def _model_of(data: np.lib.npyio.NpzFile, k: int) -> ModelState:
    pre = f"m{k}_" if k else ""
    rows = None
    if f"{pre}frozen_traj_strip_a" in data:
        rows = TrajectoryRows(*(np.array(data[f"{pre}frozen_traj_{name}"])
                                for name in _ROWS_FIELDS))
    a, y, w, group, cluster = (np.array(data[f"{pre}frozen_{name}"]) for name in _FROZEN_FIELDS)
    loading = None
    if f"{pre}frozen_loading_nodes" in data:  # (where the INS's errors were given)
        loading = PoseLoading(np.array(data[f"{pre}frozen_loading_nodes"], dtype=np.int64),
                              np.array(data[f"{pre}frozen_loading_coef"], dtype=np.float32))
    frozen = Observations(a, y, w, group, cluster, rows, loading)
    state = ModelState("none", np.array(data[f"{pre}delta"]), float(data[f"{pre}threshold"]),
                       frozen)
    if f"{pre}traj_spans" in data:  # (files of earlier versions: the trajectory as exact)
        state.model = str(data[f"{pre}traj_model"])
        state.trajectory_ids = np.array(data[f"{pre}traj_ids"], dtype=np.int64)
        state.spans = np.array(data[f"{pre}traj_spans"]).reshape(-1, 2)
        state.params = np.array(data[f"{pre}traj_params"])
        state.starts = np.array(data[f"{pre}traj_starts"], dtype=np.int64)
    return state


def _strip_arrays(prefix: str, strips: list[Strip]) -> dict[str, np.ndarray]:
    arrays = {f"{prefix}_ids": np.array([s.strip_id for s in strips], dtype=np.int64)}
    for strip in strips:
        key = f"{prefix}_{strip.strip_id}"
        arrays[f"{key}_xyz"], arrays[f"{key}_t"] = strip.xyz, strip.t
        if strip.intensity is not None:
            arrays[f"{key}_i"] = strip.intensity
    return arrays


def _strips_of(data: np.lib.npyio.NpzFile, prefix: str) -> list[Strip]:
    strips = []
    for sid in data[f"{prefix}_ids"]:
        key = f"{prefix}_{int(sid)}"
        inten = data[f"{key}_i"] if f"{key}_i" in data else None
        strips.append(Strip(int(sid), data[f"{key}_xyz"], data[f"{key}_t"], inten))
    return strips


def write_checkpoint(path: str | Path, state: StreamCheckpoint) -> Path:
    """Write ``state`` to ``path`` (``.npz``), replacing it whole."""
    path = Path(path)
    t, xyz, q = state.trajectory
    neq = state.normal_equations
    arrays: dict[str, np.ndarray] = {
        "version": np.array(CHECKPOINT_VERSION),
        "traj_t": t, "traj_xyz": xyz, "traj_orientation": q,
        "models": np.array(len(state.models)),
        "trajectory_choice": np.array(state.trajectory_choice),
        "converged": np.array(state.converged),
        "counters": np.array([state.dropped_points, state.dropped_non_finite,
                              state.thinned_points]),
        "auto_thinning_cell_m": np.array(state.auto_thinning_cell_m),
        "uncovered_points": np.array(state.uncovered_points),
        "uncovered_strips": np.array(state.uncovered_strips, dtype=np.int64),
        "rejected_ids": np.array([i for i, _ in state.rejected_strips], dtype=np.int64),
        "rejected_reasons": np.array([r for _, r in state.rejected_strips], dtype=np.str_),
        "dropped_strips": np.array(state.dropped_strips, dtype=np.int64),
        "neq_n": neq.n, "neq_u": neq.u, "neq_yy": np.array(neq.yy),
        "neq_count": np.array(neq.count),
        "frame_id": np.array(state.frame_id or ""),
        **_strip_arrays("closed", state.closed),
        **_strip_arrays("open", state.open),
    }
    for k, model in enumerate(state.models):
        arrays.update(_model_arrays(k, model))
    if state.sensor is not None:
        arrays.update(_sensor_arrays(state.sensor))
    if state.control is not None:
        arrays["control_xyz"] = state.control.xyz
        arrays["control_ids"] = np.array(state.control.ids)
    tmp = path.with_name(path.name + ".tmp.npz")
    with tmp.open("wb") as fh:
        np.savez(fh, allow_pickle=False, **arrays)
    tmp.replace(path)
    return path


def read_checkpoint(path: str | Path) -> StreamCheckpoint:
    """Read a checkpoint :func:`write_checkpoint` wrote.

    Raises
    ------
    InputError
        Unreadable file, or a format version this one does not know.
    """
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read checkpoint ({exc})") from None
    with data:
        if int(data["version"]) != CHECKPOINT_VERSION:
            raise InputError(f"{path}: checkpoint version {int(data['version'])} unknown")
        control = None
        if "control_xyz" in data:
            control = ControlPoints([str(i) for i in data["control_ids"]], data["control_xyz"])
        counters = [int(v) for v in data["counters"]]
        state = StreamCheckpoint(
            frame_id=str(data["frame_id"]) or None,
            trajectory=(data["traj_t"], data["traj_xyz"], data["traj_orientation"]),
            closed=_strips_of(data, "closed"),
            open=_strips_of(data, "open"),
            models=[_model_of(data, k) for k in range(int(data["models"]) if "models" in data
                                                       else 1)],
            # (files of earlier versions lack it: not known to be converged)
            converged=bool(data["converged"]) if "converged" in data else False,
            normal_equations=NormalEquations(
                np.array(data["neq_n"]), np.array(data["neq_u"]), float(data["neq_yy"]),
                int(data["neq_count"])),
            control=control,
            dropped_points=counters[0],
            dropped_non_finite=counters[1],
            dropped_strips=[int(v) for v in data["dropped_strips"]],
        )
        # (files of earlier versions lack these)
        if len(counters) > 2:
            state.thinned_points = counters[2]
        if "auto_thinning_cell_m" in data:
            state.auto_thinning_cell_m = float(data["auto_thinning_cell_m"])
        if "uncovered_points" in data:
            state.uncovered_points = int(data["uncovered_points"])
            state.uncovered_strips = [int(v) for v in data["uncovered_strips"]]
        state.sensor = _sensor_of(data)
        if "trajectory_choice" in data:
            state.trajectory_choice = str(data["trajectory_choice"])
        if "rejected_ids" in data:
            state.rejected_strips = [(int(i), str(r)) for i, r in
                                     zip(data["rejected_ids"], data["rejected_reasons"],
                                         strict=True)]
    return state
