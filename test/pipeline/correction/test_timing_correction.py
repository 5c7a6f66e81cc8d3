"""The timing bias through the files: ``lidarcal calibrate``'s way with
``sensor_frame.estimate_timing`` writes it in the extrinsic block (read back by a plain YAML
reader), and ``lidarcal correct`` takes it off the points' times (pipeline/correction/
sensor_frame.py; docs/method.md section 12), against the simulator's truth.

A VLP-16 payload with a true dt of 3 ms (exact INS, no range noise, dZ 0: as
test_sensor_correction.py). Measured: dt 2.9989 ms (sigma 0.2 us without range noise); the
calibrated mounting with its dt put the points 0.0 mm from the truth (median), the same
mounting without dt 26.7 mm.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers_missions import light_payload

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.simulation.uav_payload import (
    UavPayloadMission,
    draw_biases,
    simulate_uav_payload,
)
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.calibration_file import ROOT_KEY, CalibrationRecord, read_calibration
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array
from lidarcal_ros.pipeline.calibration.sensor_frame import (
    calibrate_sensor_bag,
    format_mounting,
    load_sensor_bag,
    write_mounting_calibration,
    write_uav_simulation,
)
from lidarcal_ros.pipeline.correction.bag import correct_bag

CONFIG = FlightConfig.from_mapping({"topics.points": "/velodyne_points",
                                    "topics.trajectory": "/ins/odometry"})
TRUE_DT = 0.003


@dataclasses.dataclass
class _Case:
    mission: UavPayloadMission
    bag: Path
    calibration: Path
    lines: list[str]


@functools.cache
def _case(root: Path) -> _Case:
    biases = draw_biases(1)
    biases[PARAMETER_INDEX["dZ"]] = 0.0
    mission = simulate_uav_payload(light_payload(
        "vlp16", 1, range_noise_m=0.0, biases=tuple(float(b) for b in biases),
        time_offset_s=TRUE_DT))
    paths = write_uav_simulation(root / "uav", mission)
    data = load_sensor_bag(paths["bag"], CONFIG)
    assert data is not None
    cal = calibrate_sensor_bag(data, config=CONFIG.with_values(
        sensor_frame__estimate_timing=True))
    path = write_mounting_calibration(root / "cal.yaml", data, cal)
    return _Case(mission, paths["bag"], path, format_mounting(data, cal))


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> _Case:
    return _case(tmp_path_factory.mktemp("timing"))


def test_the_file_holds_the_timing_bias(case: _Case) -> None:
    block = yaml.safe_load(case.calibration.read_text())[ROOT_KEY]["extrinsic"]
    dt, sigma = block["time_offset_s"], block["time_offset_sigma_s"]
    assert isinstance(dt, float) and isinstance(sigma, float) and 0.0 < sigma < 2e-4
    # (no range noise: the sigma, 0.2 us, is below the model's own microsecond)
    assert abs(dt - TRUE_DT) < 1e-5
    assert set(block["time_offset_correlation"]) == {"dX", "dY", "domega", "dphi", "dkappa",
                                                     "dr"}
    assert "time_offset_not_estimable" not in block
    biases = yaml.safe_load(case.calibration.read_text())[ROOT_KEY]["biases"]
    assert biases["dS"] == {"value": 0.0, "sigma": None, "estimated": False}
    record = read_calibration(case.calibration)
    assert record.extrinsic is not None and record.extrinsic.time_offset_s == dt
    assert record.extrinsic.time_offset_sigma_s == sigma
    assert any("timing bias dt" in line and "ms" in line for line in case.lines)


def test_a_file_without_it_reads_as_zero(case: _Case, tmp_path: Path) -> None:
    doc = yaml.safe_load(case.calibration.read_text())
    block = doc[ROOT_KEY]["extrinsic"]
    for key in [k for k in block if k.startswith("time_offset")]:
        del block[key]
    older = tmp_path / "older.yaml"
    older.write_text(yaml.safe_dump(doc))
    record = read_calibration(older)
    assert record.extrinsic is not None
    assert record.extrinsic.time_offset_s == 0.0 and record.extrinsic.time_offset_sigma_s is None
    block["time_offset_s"] = 3.0  # (milliseconds written by mistake)
    older.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="time_offset_s"):
        read_calibration(older)


def _median_to_truth(case: _Case, record: CalibrationRecord, out: Path) -> float:
    report = correct_bag(case.bag, record, out, CONFIG)
    assert report.stats.not_corrected == 0
    topic = CONFIG["topics.corrected"]
    with open_bag(out) as bag:
        points = np.concatenate([
            cloud_to_array(bag.deserialize(memoryview(raw), msgtype, topic=topic), source=topic)
            for _t, msgtype, _ns, raw in bag.messages([topic])])
    xyz = np.column_stack([points["x"], points["y"], points["z"]])
    assert len(xyz) == len(case.mission.truth_xyz)
    return float(np.median(np.linalg.norm(xyz - case.mission.truth_xyz, axis=1)))


def test_the_correction_takes_it_off_the_times(case: _Case, tmp_path: Path) -> None:
    record = read_calibration(case.calibration)
    assert record.extrinsic is not None
    timed = _median_to_truth(case, record, tmp_path / "timed.mcap")
    untimed = _median_to_truth(case, dataclasses.replace(
        record, extrinsic=dataclasses.replace(record.extrinsic, time_offset_s=0.0)),
        tmp_path / "untimed.mcap")
    print(f"median to the truth: with dt {timed * 1e3:.1f} mm, without {untimed * 1e3:.1f} mm")
    assert timed < 0.005 and untimed > 3.0 * timed
    assert math.isfinite(timed)
