"""``lidarcal recover``: a bag whose recording was cut gives back what was readable.

The damaged bags are a small simulated mission's bag cut at a fraction of its MCAP file
(helpers_missions.truncate), with and without ``metadata.yaml`` (rosbag2 writes it only when a
recording ends). The recovered bag is read back with lidarcal's reader and compared with the
intact original, message by message; then it is calibrated.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import helpers_missions
import pytest
from helpers_missions import truncate

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.errors import BagError
from lidarcal_ros.io.bag.format import stamp_seconds
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.recovery import recover_bag
from lidarcal_ros.io.cloud.columns import time_span
from lidarcal_ros.io.cloud.messages import deserialize, parse_cloud
from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_mission

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


def _by_topic(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with open_bag(bag) as reader:
        for topic, _type, stamp, raw in reader.messages():
            out.setdefault(topic, []).append((stamp, bytes(raw)))
    return out


@pytest.mark.parametrize("metadata", [True, False], ids=["with metadata", "without metadata"])
def test_a_cut_bag_gives_back_its_readable_prefix(small_mission: Any, tmp_path: Path,
                                                  metadata: bool) -> None:
    cut = truncate(small_mission.bag, tmp_path / "cut", fraction=0.6)
    if not metadata:
        (cut / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="lidarcal recover"):
        open_bag(cut)  # refused as it was, with the way out named
    result = recover_bag(cut, tmp_path / "recovered")
    assert list(result.damage) == [str(cut / "mission.mcap")]

    original = _by_topic(small_mission.bag)
    recovered = _by_topic(tmp_path / "recovered")
    assert {t: len(m) for t, m in recovered.items()} == result.messages
    for topic, messages in recovered.items():  # the beginning of each topic, unchanged
        assert messages == original[topic][:len(messages)], topic
    assert 0 < len(recovered["/lidar/points"]) < len(original["/lidar/points"])
    assert result.start_ns == original["/lidar/trajectory"][0][0]
    # The clouds that reach past the last readable pose are left out, and only those.
    poses = recovered["/lidar/trajectory"]
    last_pose = max(stamp_seconds(deserialize(raw, "geometry_msgs/msg/PoseStamped").header.stamp)
                    for _, raw in poses)
    latest = [time_span(parse_cloud(raw).points["t"])[1]
              for _, raw in recovered["/lidar/points"]]
    assert max(latest) <= last_pose
    n_points = len(recovered["/lidar/points"])
    dropped = original["/lidar/points"][n_points:n_points + result.clouds_after_trajectory]
    assert all(time_span(parse_cloud(raw).points["t"])[1] > last_pose for _, raw in dropped)
    # and what is left calibrates (the strips it holds)
    config = FlightConfig.from_mapping(helpers_missions.FAST_SETTINGS)
    mission = load_mission(tmp_path / "recovered", config)
    assert 2 <= len(mission.strips) < len(small_mission.sim.mission.strips)
    assert math.isfinite(calibrate_mission(mission, config).solution.sigma0)


def test_an_intact_bag_is_copied_whole(small_mission: Any, tmp_path: Path) -> None:
    result = recover_bag(small_mission.bag, tmp_path / "copy.mcap")
    assert result.damage == {} and result.clouds_after_trajectory == 0
    assert _by_topic(tmp_path / "copy.mcap") == _by_topic(small_mission.bag)
    assert "no damage found" in "\n".join(result.lines())
    with open_bag(tmp_path / "copy.mcap") as bag:  # the control points stay latched
        assert bag.topics["/lidar/control_points"].transient_local
        assert not bag.topics["/lidar/points"].transient_local


def test_bad_requests_are_refused_in_one_line(small_mission: Any, tmp_path: Path,
                                              capsys: Any) -> None:
    nothing = tmp_path / "nothing.mcap"
    nothing.write_bytes(small_mission.bag.joinpath("mission.mcap").read_bytes()[:40])
    for args, reason in (
            ([nothing, "-o", tmp_path / "out"], "no message is readable"),
            ([small_mission.bag, "-o", small_mission.bag], "must not be the damaged bag"),
            ([tmp_path / "absent", "-o", tmp_path / "out"], "no such bag"),
            ([small_mission.bag.parent, "-o", tmp_path / "out"], "no .mcap file")):
        capsys.readouterr()
        assert main(["recover", *map(str, args)]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("lidarcal recover: error: "), err
        assert reason in err
    assert not (tmp_path / "out").exists()  # nothing half-written is left
    (tmp_path / "taken").mkdir()
    assert main(["recover", str(small_mission.bag), "-o", str(tmp_path / "taken")]) == 1
    assert "taken: exists (use --overwrite to replace it)" in capsys.readouterr().err
