"""Small simulated missions and bag variants shared by tests.

Expose the fixtures in a test module (``test/`` is on ``sys.path``; a plain assignment keeps
ruff's F811 quiet where a fixture argument would shadow an imported name)::

    import helpers_missions

    small_mission = helpers_missions.small_mission
    mission_factory = helpers_missions.mission_factory

    def test_something(small_mission):
        bag = small_mission.bag                  # rosbag2 directory (control on the bag)
        cfg = small_mission.fast_config          # parameters file: quick adjustment
        sim = small_mission.sim                  # SimulatedMission (truth, mission, ...)

``mission_factory(**options)`` (the keywords of ``SimulationSpec.from_options``) gives a
:class:`MissionFiles` for other settings; results are cached for the session, so reuse is
free. Missions are treated as read-only; the transforms below (``subset``, ``shift_strip``,
``without_trajectory``, ``with_non_finite``, ``without_control``) return modified copies.
``small_calibration`` is a calibration file of the small mission's true biases.
``write_cloud_bag`` writes clouds of any field layout and frames with lidarcal's BagWriter,
and ``write_mcap_ros2_bag`` writes the same mission with the mcap project's own ROS 2 writer
(a bare ``.mcap`` whose schema names lack ``/msg/``).
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from lidarcal_ros.core.mission import Mission, Strip, Trajectory
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.core.simulation.uav_payload import UavPayloadSpec
from lidarcal_ros.io.bag.format import seconds_to_ns
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.calibration.procedure import write_simulation

#: A six-strip "paper" mission over 250 m lines, about 160 000 points: simulates in < 1 s.
SMALL_MISSION: dict[str, Any] = {"scenario": "paper", "density": 0.1, "line_length_m": 250.0,
                                 "seed": 7}

#: Flight-configuration values (dotted names) that make a small mission calibrate in ~2 s.
FAST_SETTINGS: dict[str, Any] = {
    "matching.max_candidates_per_pair": 10_000,
    "matching.per_class_cap": 500,
}


def write_params_file(path: Path, values: dict[str, Any], *, section: str = "/**") -> Path:
    """A ROS 2 parameters file (``/**: ros__parameters:``) holding dotted-name ``values``."""
    tree: dict[str, Any] = {}
    for name, value in values.items():
        node = tree
        *parents, leaf = name.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    path.write_text(yaml.safe_dump({section: {"ros__parameters": tree}}, sort_keys=False))
    return path


def write_calibration_yaml(path: Path, biases: dict[str, float], *, drop: str | None = None,
                           override: dict[str, float] | None = None) -> Path:
    """A calibration file of docs/interface.md with the given bias values."""
    values = {**biases, **(override or {})}
    doc = {"lidarcal_calibration": {
        "biases": {n: {"value": float(values[n]), "sigma": None, "estimated": n != "dZ"}
                   for n in PARAMETER_NAMES if n != drop},
        "sigma0": 0.02, "redundancy": 1000, "iterations": 1, "converged": True,
        "correlation": {"names": [], "matrix": []},
        "correspondences": {"strip_pairs": 0, "control": 0},
    }}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@dataclass(frozen=True)
class MissionFiles:
    """A simulated mission and its files (see ``lidarcal simulate``).

    Attributes
    ----------
    sim : SimulatedMission
    bag : Path
        rosbag2 directory written by lidarcal, control points on ``/lidar/control_points``.
    control_csv, truth : Path
        ``id,x,y,z`` control points; truth YAML (``biases:``), as ``lidarcal simulate``.
    fast_config : Path
        Parameters file with :data:`FAST_SETTINGS`.
    workdir : Path
        Directory holding the above; put nothing else there.
    """

    sim: SimulatedMission
    bag: Path
    control_csv: Path
    truth: Path
    fast_config: Path
    workdir: Path

    @property
    def mission(self) -> Mission:
        return self.sim.mission


def _key(kwargs: dict[str, Any]) -> str:
    return ",".join(f"{k}={kwargs[k]!r}" for k in sorted(kwargs))


@pytest.fixture(scope="session")
def mission_factory(
    tmp_path_factory: pytest.TempPathFactory,
) -> Callable[..., MissionFiles]:
    """``make(**options) -> MissionFiles`` (``SimulationSpec.from_options`` keywords), cached
    per session.

    Unspecified arguments default to :data:`SMALL_MISSION`.
    """
    cache: dict[str, MissionFiles] = {}

    def make(**kwargs: Any) -> MissionFiles:
        args = {**SMALL_MISSION, **kwargs}
        key = _key(args)
        if key not in cache:
            work = tmp_path_factory.mktemp("mission")
            sim = simulate_mission(SimulationSpec.from_options(**args))
            paths = write_simulation(work / "mission", sim)
            cache[key] = MissionFiles(
                sim=sim,
                bag=paths["bag"],
                control_csv=paths.get("control", work / "mission_control.csv"),
                truth=paths["truth"],
                fast_config=write_params_file(work / "fast.yaml", FAST_SETTINGS),
                workdir=work,
            )
        return cache[key]

    return make


@pytest.fixture(scope="session")
def small_mission(mission_factory: Callable[..., MissionFiles]) -> MissionFiles:
    """The :data:`SMALL_MISSION` (six overlapping strips, one control point)."""
    return mission_factory()


@pytest.fixture(scope="session")
def small_calibration(small_mission: MissionFiles,
                      tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A calibration file of the :data:`SMALL_MISSION`'s true biases (expose it under the
    name a module uses, e.g. ``calibration = helpers_missions.small_calibration``)."""
    return write_calibration_yaml(tmp_path_factory.mktemp("cal") / "cal.yaml",
                                  small_mission.sim.biases)


# ------------------------------------------------------------------ mission transforms
def _copy(mission: Mission) -> Mission:
    """A copy whose arrays can be modified without touching ``mission``."""
    return copy.deepcopy(mission)


def subset(mission: Mission, strip_ids: Sequence[int]) -> Mission:
    """Only the strips ``strip_ids`` (trajectory and control kept)."""
    out = _copy(mission)
    out.strips = [s for s in out.strips if s.strip_id in set(strip_ids)]
    return out


def strip_span(mission: Mission, strip_id: int) -> tuple[float, float]:
    """First and last point time of a strip, seconds."""
    s = next(s for s in mission.strips if s.strip_id == strip_id)
    return float(np.nanmin(s.t)), float(np.nanmax(s.t))


def without_trajectory(mission: Mission, t0: float, t1: float) -> Mission:
    """The trajectory samples in ``[t0, t1]`` removed (a gap)."""
    out = _copy(mission)
    keep = (out.trajectory.t < t0) | (out.trajectory.t > t1)
    out.trajectory = Trajectory(out.trajectory.t[keep], out.trajectory.xyz[keep])
    return out


def shift_strip(mission: Mission, strip_id: int, dxyz: Sequence[float],
                margin_s: float = 5.0) -> Mission:
    """Move a strip and the trajectory while it was flown by ``dxyz`` (consistent geometry).

    The trajectory is shifted within ``margin_s`` of the strip's time span, so the other
    strips' samples must be further away in time (lines are 30 s apart in the simulator).
    """
    out = _copy(mission)
    d = np.asarray(dxyz, dtype=np.float64)
    t0, t1 = strip_span(out, strip_id)
    strip = next(s for s in out.strips if s.strip_id == strip_id)
    strip.xyz = strip.xyz + d
    near = (out.trajectory.t >= t0 - margin_s) & (out.trajectory.t <= t1 + margin_s)
    xyz = out.trajectory.xyz.copy()
    xyz[near] += d
    out.trajectory = Trajectory(out.trajectory.t, xyz)
    return out


def without_control(mission: Mission) -> Mission:
    out = _copy(mission)
    out.control = None
    return out


def with_non_finite(mission: Mission, per_strip: int = 2, seed: int = 0) -> tuple[Mission, int]:
    """NaN/inf put into ``per_strip`` points of every strip (x, z or t, in turn).

    Returns the mission and the number of points spoiled.
    """
    out = _copy(mission)
    rng = np.random.default_rng(seed)
    n = 0
    bad = (np.nan, np.inf, -np.inf)
    for k, s in enumerate(out.strips):
        idx = rng.choice(len(s), per_strip, replace=False)
        xyz, t = s.xyz.copy(), s.t.copy()
        for j, i in enumerate(idx):
            which = (k + j) % 3
            if which == 2:
                t[i] = np.nan
            else:
                xyz[i, 2 * which] = bad[(k + j) % 3]
        s.xyz, s.t = xyz, t
        n += per_strip
    return out, n


# ------------------------------------------------------------------ live input
#: One message of a mission as a live node receives it: (time s, "cloud" or "pose", payload);
#: a cloud's payload is its CloudColumns, a pose's its position (3,) and quaternion xyzw (4,),
#: NaN where the trajectory has no orientation.
StreamEvent = tuple[float, str, Any]


def stream_events(mission: Mission, seconds: float = 0.5) -> list[StreamEvent]:
    """The mission as a bag would carry it: chunks of ``seconds`` of each strip and the
    trajectory samples, in time order."""
    traj = mission.trajectory
    events: list[StreamEvent] = []
    for strip in mission.strips:
        assert strip.intensity is not None  # simulated strips always carry intensity
        edges = np.arange(strip.t[0], strip.t[-1] + seconds, seconds)
        for a, b in itertools.pairwise(edges):
            sel = (strip.t >= a) & (strip.t < b)
            if sel.any():
                cols = CloudColumns(strip.xyz[sel], strip.t[sel], strip.intensity[sel],
                                    np.full(int(sel.sum()), strip.strip_id, np.uint32))
                events.append((float(strip.t[sel][0]), "cloud", cols))
    orientation = (traj.orientation if traj.orientation is not None
                   else np.full((len(traj.t), 4), np.nan))  # (NaN: none)
    for t, xyz, q in zip(traj.t, traj.xyz, orientation, strict=True):
        events.append((float(t), "pose", (xyz, q)))
    events.sort(key=lambda e: e[0])
    return events


# ------------------------------------------------------------------ writing variants
def cloud_chunks(strip: Strip, chunk_seconds: float = 0.1) -> Iterator[slice]:
    """Consecutive time windows of a (time-sorted) strip."""
    t = strip.t
    start = 0
    while start < len(t):
        stop = int(np.searchsorted(t, t[start] + chunk_seconds, side="left"))
        stop = max(stop, start + 1)
        yield slice(start, stop)
        start = stop


def strip_points(strip: Strip, dtype: np.dtype | list[tuple[str, str]] | None = None,
                 *, rename: dict[str, str] | None = None) -> np.ndarray:
    """A strip as a structured array; fields are filled by name from x, y, z, t, intensity,
    strip_id (after ``rename``, e.g. ``{"t": "gps_time"}``); others are zero."""
    dt = np.dtype(dtype if dtype is not None else [
        ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"), ("intensity", "<f4"),
        ("strip_id", "<u2")])
    values = {"x": strip.xyz[:, 0], "y": strip.xyz[:, 1], "z": strip.xyz[:, 2], "t": strip.t,
              "intensity": strip.intensity if strip.intensity is not None else 0.0,
              "strip_id": strip.strip_id}
    for a, b in (rename or {}).items():
        values[b] = values.pop(a)
    out = np.zeros(len(strip), dtype=dt)
    for name in dt.names or ():
        if name in values:
            out[name] = values[name]
    return out


def write_mission_clouds(writer: BagWriter, mission: Mission, *,
                         topic: str = "/lidar/points", chunk_seconds: float = 0.5) -> None:
    """The mission's clouds in chunks of ``chunk_seconds``, strip after strip, each logged at
    its first point's time, in the map frame (the poses are the caller's)."""
    for s in mission.strips:
        pts = strip_points(s)
        for sl in cloud_chunks(s, chunk_seconds):
            writer.write_cloud(topic, seconds_to_ns(float(s.t[sl.start])), "map", pts[sl])


def write_cloud_bag(
    path: Path,
    mission: Mission,
    *,
    dtype: np.dtype | list[tuple[str, str]] | None = None,
    rename: dict[str, str] | None = None,
    cloud_frame: str | None = None,
    trajectory_frame: str | None = None,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    chunk_seconds: float = 0.5,
    max_chunks_per_strip: int | None = None,
) -> Path:
    """Write a mission with lidarcal's :class:`BagWriter`, clouds in any layout and frames.

    ``max_chunks_per_strip`` keeps only the first chunks of each strip (fast bags for tests
    that fail before any numerics). No control topic is written.
    """
    events: list[tuple[int, int, Any]] = []
    for s in mission.strips:
        pts = strip_points(s, dtype, rename=rename)
        for k, sl in enumerate(cloud_chunks(s, chunk_seconds)):
            if max_chunks_per_strip is not None and k >= max_chunks_per_strip:
                break
            events.append((seconds_to_ns(float(s.t[sl.start])), 1, pts[sl]))
    for t, xyz in zip(mission.trajectory.t, mission.trajectory.xyz):
        events.append((seconds_to_ns(float(t)), 0, xyz))
    events.sort(key=lambda e: (e[0], e[1]))
    cf = cloud_frame or mission.frame_id
    tf = trajectory_frame or mission.frame_id
    with BagWriter(path) as writer:
        for stamp, kind, payload in events:
            if kind == 1:
                writer.write_cloud(points_topic, stamp, cf, payload)
            else:
                writer.write_pose(trajectory_topic, stamp, tf, payload)
    return path


def _ros2_msgdef(msgtype: str) -> str:
    from rosbags.typesys import Stores, get_typestore

    return str(get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)[0])


def _cloud_dict(points: np.ndarray, stamp_ns: int, frame: str) -> dict[str, Any]:
    codes = {"f8": 8, "f4": 7, "u4": 6, "u2": 4, "u1": 2}
    layout: dict[str, Any] = dict(points.dtype.fields or {})
    fields = [{"name": n, "offset": layout[n][1], "datatype": codes[layout[n][0].str[1:]],
               "count": 1} for n in points.dtype.names or ()]
    return {"header": {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9},
                       "frame_id": frame},
            "height": 1, "width": len(points), "fields": fields, "is_bigendian": False,
            "point_step": points.dtype.itemsize, "row_step": points.nbytes,
            "data": points.tobytes(), "is_dense": bool(np.isfinite(
                np.stack([points["x"], points["y"], points["z"]])).all())}


def write_mcap_ros2_bag(path: Path, mission: Mission, *, chunk_seconds: float = 0.5) -> Path:
    """The mission as a bare ``.mcap`` written by ``mcap_ros2.writer.Writer``.

    Schema names without ``/msg/`` (``sensor_msgs/PointCloud2``, ``geometry_msgs/PoseStamped``),
    as that library's users write them; the same fields as lidarcal writes (``x, y, z, t``
    FLOAT64, ``intensity`` FLOAT32, ``strip_id`` UINT16), control points as one cloud.
    """
    from mcap_ros2.writer import Writer

    events: list[tuple[int, int, Any]] = []
    for s in mission.strips:
        pts = strip_points(s)
        for sl in cloud_chunks(s, chunk_seconds):
            events.append((seconds_to_ns(float(s.t[sl.start])), 1, pts[sl]))
    for t, xyz in zip(mission.trajectory.t, mission.trajectory.xyz):
        events.append((seconds_to_ns(float(t)), 0, xyz))
    events.sort(key=lambda e: (e[0], e[1]))
    frame = mission.frame_id
    with path.open("wb") as stream:
        writer = Writer(stream)
        pc = writer.register_msgdef("sensor_msgs/PointCloud2",
                                    _ros2_msgdef("sensor_msgs/msg/PointCloud2"))
        ps = writer.register_msgdef("geometry_msgs/PoseStamped",
                                    _ros2_msgdef("geometry_msgs/msg/PoseStamped"))
        if mission.control is not None and len(mission.control):
            xyz = np.asarray(mission.control.xyz, dtype=np.float64).reshape(-1, 3)
            cp = np.zeros(len(xyz), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
            cp["x"], cp["y"], cp["z"] = xyz.T
            first = events[0][0] if events else 0
            writer.write_message("/lidar/control_points", pc, _cloud_dict(cp, first, frame),
                                 log_time=first, publish_time=first)
        for stamp, kind, payload in events:
            if kind == 1:
                msg = _cloud_dict(payload, stamp, frame)
                writer.write_message("/lidar/points", pc, msg, log_time=stamp,
                                     publish_time=stamp)
            else:
                x, y, z = (float(v) for v in payload)
                writer.write_message("/lidar/trajectory", ps, {
                    "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9},
                               "frame_id": frame},
                    "pose": {"position": {"x": x, "y": y, "z": z},
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                }, log_time=stamp, publish_time=stamp)
        writer.finish()
    return path


def truncate(src: Path, dst: Path, fraction: float = 0.5) -> Path:
    """A copy of a bag (directory or bare .mcap) with its MCAP file cut to ``fraction``."""
    import shutil

    if src.is_dir():
        shutil.copytree(src, dst)
        mcaps = sorted(dst.glob("*.mcap"))
    else:
        shutil.copyfile(src, dst)
        mcaps = [dst]
    for f in mcaps:
        data = f.read_bytes()
        f.write_bytes(data[: int(len(data) * fraction)])
    return dst


__all__ = [
    "FAST_SETTINGS",
    "SMALL_MISSION",
    "MissionFiles",
    "cloud_chunks",
    "mission_factory",
    "shift_strip",
    "small_mission",
    "strip_points",
    "strip_span",
    "subset",
    "truncate",
    "with_non_finite",
    "without_control",
    "without_trajectory",
    "write_cloud_bag",
    "write_mcap_ros2_bag",
    "write_mission_clouds",
    "write_params_file",
]


def with_trajectory_errors(mission: Mission, *, seed: int, offset_m: Sequence[float] = (
        0.04, 0.04, 0.05), drift_m_per_s: float = 0.001, oscillation_m: float = 0.01,
        period_s: float = 60.0) -> tuple[Mission, dict[int, Callable[[np.ndarray], np.ndarray]]]:
    """Each strip's points and the trajectory while it was flown moved by a trajectory error
    ``e_s(t)`` (docs/method.md section 11: a random offset, drift and slow oscillation about the
    strip's mid time), as a navigation solution's error moves them; with ``e_s`` by strip id."""
    out = _copy(mission)
    rng = np.random.default_rng(seed)
    traj = out.trajectory
    xyz = traj.xyz.copy()
    errors: dict[int, Callable[[np.ndarray], np.ndarray]] = {}
    for strip in out.strips:
        t0, t1 = strip_span(out, strip.strip_id)
        mid = 0.5 * (t0 + t1)
        offset = rng.normal(0.0, offset_m, 3)
        drift = rng.normal(0.0, drift_m_per_s, 3)
        phase = rng.uniform(0.0, 2.0 * np.pi, 3)

        def error(t: np.ndarray, offset: np.ndarray = offset, drift: np.ndarray = drift,
                  phase: np.ndarray = phase, mid: float = mid) -> np.ndarray:
            dt = (np.asarray(t, dtype=np.float64) - mid)[:, None]
            return offset + dt * drift + oscillation_m * np.sin(2 * np.pi * dt / period_s
                                                                + phase)

        errors[strip.strip_id] = error
        strip.xyz = strip.xyz + error(strip.t)
        near = (traj.t >= t0 - 2.0) & (traj.t <= t1 + 2.0)
        xyz[near] += error(traj.t[near])
    out.trajectory = Trajectory(traj.t, xyz, traj.orientation,
                                full_attitude=traj.full_attitude)
    return out, errors


# ------------------------------------------------------------------ UAV payloads

#: A payload's INS without errors (UavPayloadSpec's options).
EXACT_INS: dict[str, Any] = {"ins_position_sigma_m": (0.0, 0.0, 0.0),
                             "ins_attitude_sigma_deg": (0.0, 0.0, 0.0)}
#: Firings a revolution of a light payload mission by layout (a tenth of the VLP-16's).
LIGHT_COLUMNS = {"vlp16": 100, "os1-32": 64}


def light_payload(layout: str, seed: int, **options: Any) -> UavPayloadSpec:
    """A light UAV payload (4 lines of 120 m, :data:`LIGHT_COLUMNS`, an exact INS; some 0.4M
    points), ``options`` over it."""
    return UavPayloadSpec(**{"layout": layout, "seed": seed, "columns": LIGHT_COLUMNS[layout],
                             "n_lines": 4, "line_length_m": 120.0, **EXACT_INS, **options})


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two rotation matrices, rad."""
    return math.acos(min(1.0, max(-1.0, (float(np.trace(a.T @ b)) - 1.0) / 2.0)))
