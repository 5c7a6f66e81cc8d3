"""``lidarcal correct`` and the live corrector on clouds in the sensor's frame, against the truth.

A simulated UAV payload (pipeline/correction/sensor_frame.py; docs/method.md section 12) is
calibrated as ``lidarcal calibrate`` does it, and corrected with that calibration, with the true
mounting and with the nominal one; each corrected point is compared with where its ray met the
terrain (the simulator's ``truth_xyz``, in the bag's order).

Measured (4 lines of 120 m, range noise 0 so that the distance is the geometry's alone): with an
exact INS the calibrated mounting put the points 0.0 mm (VLP-16, seed 1) and 0.1 mm (OS1-32, seed
2) from the truth (median), the true one 0.0 mm, the nominal 323 and 679 mm. With the
simulator's tactical-grade INS (2-3 cm of correlated position error) the true mounting leaves
31 and 40 mm, the calibrated 30 and 59 mm (the short mission's calibration takes up some of the
INS's error), the nominal 324 and 678 mm. ``dZ`` is 0 in these missions: it is held at the
nominal without control points, and a simulated 3.8 cm left the points 3.6 cm high.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from helpers_wait import wait_until

from lidarcal_ros.core.config import CORRECTOR_NODE, SCHEMA, FlightConfig, node_options
from lidarcal_ros.core.flags import FLAG_NO_NORMAL, FLAG_NOT_CORRECTED
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.simulation.uav_payload import (
    UavPayloadMission,
    UavPayloadSpec,
    draw_biases,
    simulate_uav_payload,
)
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.calibration_file import (
    ROOT_KEY,
    CalibrationRecord,
    Extrinsic,
    read_calibration,
)
from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array
from lidarcal_ros.io.survey.control import read_control_csv
from lidarcal_ros.pipeline.calibration.sensor_frame import (
    calibrate_sensor_bag,
    load_sensor_bag,
    mounting_solve_for,
    write_mounting_calibration,
    write_uav_simulation,
)
from lidarcal_ros.pipeline.correction.bag import CorrectOptions, correct_bag
from lidarcal_ros.pipeline.correction.live import CorrectorOptions, LiveCorrector

CONFIG = FlightConfig.from_mapping({"topics.points": "/velodyne_points",
                                    "topics.trajectory": "/ins/odometry"})
EXACT_INS = {"ins_position_sigma_m": (0.0, 0.0, 0.0), "ins_attitude_sigma_deg": (0.0, 0.0, 0.0)}


@dataclasses.dataclass
class _Case:
    mission: UavPayloadMission
    bag: Path
    calibration: Path
    workdir: Path


@functools.cache
def _case(layout: str, seed: int, exact: bool, root: Path) -> _Case:
    """A payload (``dZ`` 0: module docstring; no range noise) written and calibrated."""
    biases = draw_biases(seed)
    biases[PARAMETER_INDEX["dZ"]] = 0.0
    spec = UavPayloadSpec(layout=layout, seed=seed, columns={"vlp16": 100, "os1-32": 64}[layout],
                          line_length_m=120.0, range_noise_m=0.0,
                          biases=tuple(float(b) for b in biases),
                          **(EXACT_INS if exact else {}))  # type: ignore[arg-type]
    mission = simulate_uav_payload(spec)
    workdir = root / f"{layout}-{seed}-{'exact' if exact else 'ins'}"
    workdir.mkdir()
    paths = write_uav_simulation(workdir / "uav", mission)
    data = load_sensor_bag(paths["bag"], CONFIG)
    assert data is not None
    cal = write_mounting_calibration(workdir / "cal.yaml", data, calibrate_sensor_bag(data))
    return _Case(mission, paths["bag"], cal, workdir)


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("sensor-correct")


def _with_mounting(record: CalibrationRecord, mounting: Mounting, dr: float
                   ) -> CalibrationRecord:
    assert record.extrinsic is not None
    ext = record.extrinsic
    return dataclasses.replace(record, values={**record.values, "dr": dr},
                               extrinsic=Extrinsic(ext.parent, ext.child, mounting, ext.nominal))


def _corrected(path: Path) -> np.ndarray:
    topic = CONFIG["topics.corrected"]
    with open_bag(path) as bag:
        parts = [cloud_to_array(bag.deserialize(memoryview(raw), msgtype, topic=topic),
                                source=topic)
                 for _t, msgtype, _ns, raw in bag.messages([topic])]
    return np.concatenate(parts)


def _xyz(points: np.ndarray) -> np.ndarray:
    return np.column_stack([points["x"], points["y"], points["z"]])


def _median_to_truth(case: _Case, record: CalibrationRecord, name: str) -> float:
    """Correct the bag with ``record``; the median distance of its points to the truth, m."""
    out = case.workdir / f"{name}.mcap"
    report = correct_bag(case.bag, record, out, CONFIG)
    assert report.stats.not_corrected == 0
    points = _corrected(out)
    assert len(points) == len(case.mission.truth_xyz)  # (every point, in the bag's order)
    return float(np.median(np.linalg.norm(_xyz(points) - case.mission.truth_xyz, axis=1)))


def _three_mountings(case: _Case) -> dict[str, float]:
    m = case.mission
    record = read_calibration(case.calibration)
    got = {"calibrated": _median_to_truth(case, record, "calibrated"),
           "true": _median_to_truth(case, _with_mounting(
               record, m.truth_mounting, float(m.biases[PARAMETER_INDEX["dr"]])), "true"),
           "nominal": _median_to_truth(case, _with_mounting(record, m.nominal, 0.0),
                                       "nominal")}
    print({k: f"{v * 1e3:.1f} mm" for k, v in got.items()})
    return got


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_points_corrected_with_the_calibration_lie_on_the_truth(root: Path, layout: str,
                                                                 seed: int) -> None:
    got = _three_mountings(_case(layout, seed, True, root))
    assert got["true"] < 0.0005  # the georeferencing itself: the truth, to float32 points
    assert got["calibrated"] < 0.007  # the bar
    assert got["nominal"] > 0.2  # what the calibration corrected


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_with_a_noisy_ins_the_calibration_does_what_the_true_mounting_does(
        root: Path, layout: str, seed: int) -> None:
    got = _three_mountings(_case(layout, seed, False, root))
    assert 0.01 < got["true"] < 0.06  # the INS's own error, which no mounting removes
    assert got["calibrated"] < 2.0 * got["true"]
    assert got["nominal"] > 5.0 * got["calibrated"]


def test_las_output_holds_the_bags_points(root: Path) -> None:
    case = _case("vlp16", 1, True, root)
    import laspy

    correct_bag(case.bag, case.calibration, case.workdir / "out.mcap", CONFIG)
    correct_bag(case.bag, case.calibration, case.workdir / "out.laz", CONFIG)
    bag_points = _corrected(case.workdir / "out.mcap")
    las = laspy.read(case.workdir / "out.laz")
    assert len(las.points) == len(bag_points)
    order = np.argsort(bag_points["t"], kind="stable")
    las_order = np.argsort(np.asarray(las.gps_time), kind="stable")
    diff = np.abs(np.column_stack([las.x, las.y, las.z])[las_order] - _xyz(bag_points)[order])
    assert diff.max() < 0.001  # (LAS's millimetre scale)
    assert np.allclose(np.asarray(las["reflectance"])[las_order],
                       bag_points["reflectance"][order], equal_nan=True, rtol=1e-6)


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_every_point_with_neighbours_gets_a_normal_whatever_the_batch(
        root: Path, layout: str, seed: int) -> None:
    """A revolution spans some 50 m along track and a later one's lowest grid row may lie
    rows behind an earlier one's: no point falls behind its strip's grid (19% of the
    VLP-16's had no normal before: the strip's grid also ran on through the turns), and
    the output does not depend on how the clouds are batched."""
    case = _case(layout, seed, True, root)
    outputs = []
    for batch in (0, 20_000, 200_000):
        out = case.workdir / f"batch-{batch}.mcap"
        correct_bag(case.bag, case.calibration, out, CONFIG,
                    CorrectOptions(batch_points=batch))
        outputs.append(_corrected(out))
    flags = outputs[0]["correction_flags"]
    missing = np.count_nonzero(flags & FLAG_NO_NORMAL) / len(flags)
    print(f"{layout}: {missing:.3%} of the points without a normal")
    assert missing < 0.002  # (measured 0.03% and 0.06%)
    for other in outputs[1:]:
        _assert_same_correction(other, outputs[0])


def _assert_same_correction(a: np.ndarray, b: np.ndarray) -> None:
    """Every field of the corrected points equal, bit for bit (NaN where NaN)."""
    assert a.dtype == b.dtype and len(a) == len(b)
    for name in a.dtype.names or ():
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.mark.parametrize("batch_points", [0, 20_000])
def test_live_corrector_gives_the_offline_correction(root: Path, batch_points: int) -> None:
    """The bag's messages in log order into the live correction (in a thread of this
    process), with look-ahead: the points of ``lidarcal correct`` of the bag, normals,
    incidence, reflectance and flags included, whatever the batch."""
    case = _case("vlp16", 1, True, root)
    offline = _corrected_by_stamp(case, case.workdir / f"offline-{batch_points}.mcap")
    published: list[bytes] = []
    # (no time-out while the clouds are handed over: it would correct the held clouds
    # without look-ahead)
    options = dataclasses.replace(node_options(CorrectorOptions, CORRECTOR_NODE, {}),
                                  separate_process=False, lookahead=True,
                                  flush_timeout_s=60.0, batch_points=batch_points)
    live = LiveCorrector(CONFIG, options, publish=lambda cdr: published.append(bytes(cdr)),
                         calibration=str(case.calibration))
    try:
        with open_bag(case.bag) as bag:
            for topic, msgtype, _ns, raw in bag.messages(["/velodyne_points",
                                                          "/ins/odometry"]):
                if topic == "/velodyne_points":
                    live.add_cloud(bytes(raw))
                    continue
                msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                live.add_pose(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                              (p.x, p.y, p.z), msg.header.frame_id, (q.x, q.y, q.z, q.w))
        wait_until(lambda: live.waiting_clouds == 0, 120.0, "the clouds handed on",
                   state=lambda: f"{live.waiting_clouds} waiting")
    finally:
        live.close()
    assert live.stats.skipped == 0, live.stats.last_error
    clouds = [parse_cloud(cdr) for cdr in published]
    assert {c.frame_id for c in clouds} == {"map"}
    got = {c.stamp_ns: c.points for c in clouds}
    assert got.keys() == offline.keys()
    a = np.concatenate([got[k] for k in sorted(got)])
    b = np.concatenate([offline[k] for k in sorted(offline)])
    assert a.dtype.names == b.dtype.names
    geometry = np.abs(_xyz(a) - _xyz(b)).max()
    same = a["correction_flags"] == b["correction_flags"]
    refl = same & np.isfinite(a["reflectance"]) & np.isfinite(b["reflectance"])
    rel = np.abs(a["reflectance"][refl] / b["reflectance"][refl] - 1.0)
    print(f"live vs offline: xyz {geometry * 1e3:.4f} mm; flags differ for "
          f"{np.count_nonzero(~same)} of {len(a)} points; reflectance where they agree: "
          f"median {np.median(rel):.1e}")
    assert not (a["correction_flags"] & FLAG_NOT_CORRECTED).any()
    assert np.count_nonzero(a["correction_flags"] & FLAG_NO_NORMAL) < 0.002 * len(a)
    _assert_same_correction(a, b)


def test_live_corrector_skips_a_cloud_of_another_sensor(root: Path) -> None:
    case = _case("vlp16", 1, True, root)
    options = dataclasses.replace(node_options(CorrectorOptions, CORRECTOR_NODE, {}),
                                  separate_process=False)
    live = LiveCorrector(CONFIG, options, publish=lambda _cdr: None,
                         calibration=str(case.calibration))
    try:
        points = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("time", "<f4")])
        live.add_cloud(cloud_cdr(10**18, "os_sensor", points))
        wait_until(lambda: live.stats.skipped == 1, 10, "the cloud skipped")
    finally:
        live.close()
    assert live.stats.last_error == ("/velodyne_points: cloud in frame 'os_sensor'; the "
                                     "calibration's extrinsic block is the mounting of "
                                     "'velodyne'")


def test_live_cloud_waits_for_the_poses_at_its_true_times(root: Path, tmp_path: Path) -> None:
    """A timing bias below 0 (here -0.2 s) looks a cloud's poses up after its delivered
    times: the corrector holds the cloud while the poses reach its delivered last time only,
    and corrects every point once they reach its true last time."""
    case = _case("vlp16", 1, True, root)
    doc = yaml.safe_load(case.calibration.read_text())
    doc[ROOT_KEY]["extrinsic"]["time_offset_s"] = -0.2
    late = tmp_path / "late.yaml"
    late.write_text(yaml.safe_dump(doc))
    poses: list[tuple[float, Any, str, Any]] = []
    raws: list[bytes] = []
    with open_bag(case.bag) as bag:
        for topic, msgtype, _ns, raw in bag.messages(["/velodyne_points", "/ins/odometry"]):
            if topic == "/velodyne_points":
                raws.append(bytes(raw))
                continue
            msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            poses.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                          (p.x, p.y, p.z), msg.header.frame_id, (q.x, q.y, q.z, q.w)))
    cloud = parse_cloud(raws[len(raws) // 2])
    delivered_last = cloud.stamp_ns * 1e-9 + float(np.max(cloud.points["time"]))
    published: list[bytes] = []
    options = dataclasses.replace(node_options(CorrectorOptions, CORRECTOR_NODE, {}),
                                  separate_process=False, max_trajectory_wait_s=600.0)
    live = LiveCorrector(CONFIG, options, publish=lambda cdr: published.append(bytes(cdr)),
                         calibration=str(late))
    try:
        live.add_cloud(raws[len(raws) // 2])
        for pose in (p for p in poses if p[0] <= delivered_last + 0.1):
            live.add_pose(*pose)
        # (covered to its delivered last time and 0.1 s beyond: not yet to its true one)
        wait_until(lambda: live.waiting_clouds == 1, 10.0, "the cloud received")
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and not published:
            time.sleep(0.05)
        assert not published and live.waiting_clouds == 1
        for pose in (p for p in poses if delivered_last + 0.1 < p[0] <= delivered_last + 0.5):
            live.add_pose(*pose)
        wait_until(lambda: bool(published), 30.0, "the cloud corrected",
                   state=lambda: f"{live.waiting_clouds} waiting")
    finally:
        live.close()
    flags = parse_cloud(published[0]).points["correction_flags"]
    assert len(flags) == len(cloud.points)
    assert not (flags & FLAG_NOT_CORRECTED).any()


def _corrected_by_stamp(case: _Case, out: Path) -> dict[int, np.ndarray]:
    correct_bag(case.bag, case.calibration, out, CONFIG)
    topic = CONFIG["topics.corrected"]
    with open_bag(out) as bag:
        clouds: dict[int, Any] = {}
        for _t, msgtype, _ns, raw in bag.messages([topic]):
            msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
            clouds[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = \
                cloud_to_array(msg, source=topic)
    return clouds


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_control_points_bring_the_vertical_lever_arm_and_the_points_to_the_truth(
        root: Path, layout: str, seed: int) -> None:
    # the drawn dZ (some cm) this time, and six control points under the lines
    spec = UavPayloadSpec(layout=layout, seed=seed, columns={"vlp16": 100, "os1-32": 64}[layout],
                          line_length_m=120.0, range_noise_m=0.0, n_control=6,
                          **EXACT_INS)  # type: ignore[arg-type]
    m = simulate_uav_payload(spec)
    assert abs(m.biases[PARAMETER_INDEX["dZ"]]) > 0.02 and m.control is not None
    workdir = root / f"{layout}-{seed}-control"
    workdir.mkdir()
    paths = write_uav_simulation(workdir / "uav", m)
    control = read_control_csv(paths["control"])
    np.testing.assert_allclose(control.xyz, m.control.xyz)
    data = load_sensor_bag(paths["bag"], CONFIG)
    assert data is not None
    names, _ = mounting_solve_for(SCHEMA["calibration.solve_for"].default, has_control=True)
    assert "dZ" in names  # the default with control points
    cal = calibrate_sensor_bag(data, solve_for=names, control=control)
    lever = cal.mounting.translation - m.truth_mounting.translation
    assert np.abs(lever).max() < 0.008, lever  # z too now
    case = _Case(m, paths["bag"], write_mounting_calibration(workdir / "cal.yaml", data, cal),
                 workdir)
    assert _median_to_truth(case, read_calibration(case.calibration), "calibrated") < 0.007
