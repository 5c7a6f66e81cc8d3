"""Zero and unnormalised orientation quaternions among good ones, end to end: a bag whose
``nav_msgs/Odometry`` carries the INS attitude, through ``lidarcal calibrate`` with the
rigorous model (docs/method.md section 10).

The same mission twice: its quaternions of unit length, and the same with every third one
scaled by 2 (or by 1e-3) and every fiftieth zero. Scaled quaternions are the same rotations
(normalised), a zero one a pose without orientation between poses that have one: the
estimate must be the unit one's, and the warning line said once.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_missions import MissionFiles, write_mission_clouds, write_params_file

from lidarcal_ros.core.mission import Mission
from lidarcal_ros.io.bag.format import ODOMETRY, seconds_to_ns
from lidarcal_ros.io.bag.writer import BagWriter

mission_factory = helpers_missions.mission_factory


@pytest.fixture(scope="module")
def crabbed(mission_factory: Callable[..., MissionFiles]) -> MissionFiles:
    """The small mission flown crabbed (4 m/s crosswind), its poses carrying the heading."""
    return mission_factory(wind_mps=(4.0, 0.0), attitude=True)


def _odometry_bag(path: Path, mission: Mission,
                  spoil: Callable[[int, np.ndarray], None] | None = None) -> Path:
    """The mission's clouds and its trajectory as Odometry, each quaternion (xyzw) given to
    ``spoil(i, q)`` to change in place."""
    traj = mission.trajectory
    assert traj.orientation is not None
    with BagWriter(path) as writer:
        write_mission_clouds(writer, mission)
        t: Any = writer._types
        zero3 = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        for i in range(len(traj)):
            q = traj.orientation[i].astype(np.float64)
            if spoil is not None:
                spoil(i, q)
            stamp = seconds_to_ns(float(traj.t[i]))
            x, y, z = (float(v) for v in traj.xyz[i])
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=t["geometry_msgs/msg/Quaternion"](
                    x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
            msg = t[ODOMETRY](
                header=writer._header(stamp, "map"), child_frame_id="base_link",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose,
                                                              covariance=np.zeros(36)),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](
                    twist=t["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3),
                    covariance=np.zeros(36)))
            writer.write_message("/lidar/trajectory", ODOMETRY, stamp, msg)
    return path


def _calibrate(bag: Path, config: Path, out: Path) -> tuple[dict[str, Any], list[str]]:
    """``lidarcal calibrate`` in a fresh interpreter, numpy's RuntimeWarning an error: the
    calibration and the lines said on stderr."""
    proc = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", "lidarcal_ros",
                           "calibrate", str(bag), "-o", str(out), "--config", str(config), "-q"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return yaml.safe_load(out.read_text())["lidarcal_calibration"], proc.stderr.splitlines()


def _scaled_and_zero(scale: float) -> Callable[[int, np.ndarray], None]:
    def spoil(i: int, q: np.ndarray) -> None:
        if i % 50 == 7:
            q[:] = 0.0
        elif i % 3 == 0:
            q *= scale
    return spoil


@pytest.fixture(scope="module")
def unit(crabbed: MissionFiles, tmp_path_factory: pytest.TempPathFactory
         ) -> tuple[dict[str, Any], Path]:
    """The calibration of the Odometry bag with unit quaternions, and the rigorous config."""
    work = tmp_path_factory.mktemp("unit")
    config = write_params_file(work / "rigorous.yaml", {**helpers_missions.FAST_SETTINGS,
                                                        "matching.model": "rigorous"})
    cal, said = _calibrate(_odometry_bag(work / "unit", crabbed.mission), config,
                           work / "cal.yaml")
    assert said == []
    assert cal["model"] == "rigorous"
    return cal, config


@pytest.mark.parametrize("scale", [2.0, 1e-3])
def test_zero_and_scaled_quaternions_give_the_unit_estimate(crabbed, unit, tmp_path,
                                                            scale) -> None:
    reference, config = unit
    mission = crabbed.mission
    bag = _odometry_bag(tmp_path / "spoilt", mission, _scaled_and_zero(scale))
    cal, said = _calibrate(bag, config, tmp_path / "cal.yaml")
    n = len(mission.trajectory)
    zeros = len(range(7, n, 50))
    scaled = len([i for i in range(0, n, 3) if i % 50 != 7])
    assert said == [f"lidarcal calibrate: warning: {bag}: trajectory /lidar/trajectory: of {n} "
                    f"orientation quaternions, {scaled} not of unit length (norms {scale:.3g} "
                    f"to {scale:.3g}): normalised; {zeros} zero: read as poses without "
                    f"orientation; {zeros} poses without one between poses with one at most "
                    "0.1 s apart: their orientation interpolated"]
    assert cal["model"] == "rigorous"
    for name, ref in reference["biases"].items():
        got = cal["biases"][name]
        assert got["estimated"] == ref["estimated"], name
        if ref["estimated"]:  # the same estimate: within a hundredth of its sigma
            assert abs(got["value"] - ref["value"]) <= 0.01 * ref["sigma"], (name, got, ref)
            assert got["sigma"] == pytest.approx(ref["sigma"], rel=0.01), name
