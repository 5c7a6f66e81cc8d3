"""`lidarcal simulate` a line and a block at a time (core.simulation.simulate.stream_mission,
io.bag.mission_bag.write_mission_stream, procedure.write_simulation_stream): the same files,
message for message, as the mission simulated whole and written by write_mission_bag."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers_missions import Trajectory

from lidarcal_ros.core.simulation import scanning
from lidarcal_ros.core.simulation.flight_path import RoughAir
from lidarcal_ros.core.simulation.simulate import simulate_mission, stream_mission
from lidarcal_ros.core.simulation.spec import TYPICAL_TRAJECTORY_ERRORS, SimulationSpec
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.bag.mission_bag import read_mission, write_mission_stream
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.pipeline.calibration.procedure import (
    simulation_paths,
    write_simulation,
    write_simulation_stream,
)


def _messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with open_bag(bag) as reader:
        return [(topic, log_ns, bytes(raw))
                for topic, _, log_ns, raw in reader.messages(list(reader.topics))]


SPECS = {
    "level, 4 lines": dict(scenario="one_track", density=0.3, line_length_m=300.0),
    "rough air, trajectory errors, 6 lines": dict(
        scenario="paper", density=0.2, line_length_m=250.0, rough_air=RoughAir()),
}


@pytest.mark.parametrize("name", SPECS)
def test_streamed_simulation_writes_the_same_files_as_the_whole(tmp_path, monkeypatch, name):
    """Blocks far smaller than a line (so chunks of 0.1 s straddle them) and the noise drawn
    for the points before the trajectory's: the same messages, bit for bit, and the same
    control points and truth."""
    monkeypatch.setattr(scanning, "PULSE_BLOCK", 1009)
    spec = SimulationSpec.from_options(seed=5, **SPECS[name])
    if "errors" in name:
        spec = replace(spec, trajectory_errors=TYPICAL_TRAJECTORY_ERRORS)
    whole = write_simulation(tmp_path / "whole", simulate_mission(spec))
    streamed, n_points = write_simulation_stream(tmp_path / "streamed", stream_mission(spec))
    sim = simulate_mission(spec)
    assert n_points == sim.mission.n_points > 10 * 1009
    got, want = _messages(streamed["bag"]), _messages(whole["bag"])
    assert len(got) == len(want)
    assert got == want
    for key in ("control", "truth"):
        assert streamed[key].read_text() == whole[key].read_text()


def test_stream_lines_hold_the_simulated_strips():
    spec = SimulationSpec.from_options(seed=2, scenario="one_track", density=0.2,
                                       line_length_m=200.0)
    sim = simulate_mission(spec)
    stream = stream_mission(spec)
    assert stream.config is None  # the truth only once every line was made
    for line, strip in zip(stream.lines(), sim.mission.strips, strict=True):
        t, xyz, intensity = (np.concatenate(v) for v in zip(*line.blocks(), strict=True))
        assert line.strip_id == strip.strip_id and line.n_points == len(strip)
        np.testing.assert_array_equal(t, strip.t)
        np.testing.assert_array_equal(xyz, strip.xyz)
        np.testing.assert_array_equal(intensity, strip.intensity)
        assert (line.t_first, line.t_last) == (strip.t[0], strip.t[-1])
    assert stream.config == sim.config


def test_stream_written_bag_reads_back_as_the_mission(tmp_path):
    spec = SimulationSpec.from_options(seed=1, scenario="one_track", density=0.2,
                                       line_length_m=200.0)
    paths, _ = write_simulation_stream(tmp_path / "s", stream_mission(spec))
    got = read_mission(paths["bag"])
    sim = simulate_mission(spec)
    for a, b in zip(got.strips, sim.mission.strips, strict=True):
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(got.trajectory.xyz, sim.mission.trajectory.xyz)
    assert simulation_paths(tmp_path / "s") == paths


class _Line:
    def __init__(self, strip_id: int, t: np.ndarray) -> None:
        self.strip_id, self.t = strip_id, t
        self.trajectory = Trajectory(np.array([t[0] - 0.5, t[0] + 0.5]), np.zeros((2, 3)))
        self.t_first, self.t_last = float(t[0]), float(t[-1])

    def blocks(self):
        yield self.t, np.zeros((len(self.t), 3)), np.ones(len(self.t), dtype=np.float32)


@pytest.mark.parametrize(("lines", "reason"), [
    ([_Line(1, np.array([10.0, 11.0])), _Line(2, np.array([10.5, 12.0]))],
     "begins before the previous strip ends"),
    ([_Line(1, np.array([10.0, 9.0]))], "not finite and non-decreasing"),
    ([_Line(1, np.array([10.0, np.nan]))], "not finite and non-decreasing"),
])
def test_stream_out_of_order_is_refused_and_leaves_nothing(tmp_path, lines, reason):
    with pytest.raises(InputError, match=reason):
        write_mission_stream(tmp_path / "bag", lines)
    assert not (tmp_path / "bag").exists()
