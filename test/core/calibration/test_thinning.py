"""Thinning before calibration (``calibration.thinning_cell_m``): one point per map cell per
strip and cloud, the same in ``lidarcal calibrate`` and in the calibrator node, and an
estimate that stays with the truth while far fewer points are held."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lidarcal_ros.core.calibration.thinning import first_per_cell
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.io.bag.mission_bag import write_mission_bag
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.cloud.columns import extract_columns
from lidarcal_ros.io.cloud.messages import parse_cloud
from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_mission
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration


def _first_per_cell_by_sorting(xyz: np.ndarray, group: np.ndarray, cell: float,
                               valid: np.ndarray) -> np.ndarray:
    """The reference: ``np.unique`` of the (group, cell) keys of the valid points."""
    idx = np.flatnonzero(valid)
    keys = np.stack([group[idx], np.floor(xyz[idx, 0] / cell), np.floor(xyz[idx, 1] / cell)],
                    axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    keep = np.zeros(len(xyz), dtype=bool)
    keep[idx[first]] = True
    return keep


@pytest.mark.parametrize(("width_m", "groups"), [
    (3.0, 1),        # a cloud of one strip: a flag per cell of its box
    (3.0, 2),        # two strips in one cloud: the hash table
    (30_000.0, 1),   # a box too wide for flags: the hash table
])
def test_the_first_point_of_each_cell_is_kept(width_m: float, groups: int) -> None:
    rng = np.random.default_rng(3)
    n = 20_000
    xyz = np.column_stack([rng.uniform(0, 800, n) + 512_345.6,
                           rng.uniform(0, width_m, n) + 4_123_456.7, rng.normal(size=n)])
    group = rng.integers(1, 1 + groups, n)
    valid = rng.random(n) > 0.01
    xyz[~valid & (rng.random(n) < 0.5), 0] = np.nan
    keep = first_per_cell(xyz, group, 0.5, valid=valid)
    np.testing.assert_array_equal(keep, _first_per_cell_by_sorting(xyz, group, 0.5, valid))
    assert 0 < keep.sum() < valid.sum()
    # by default the points with finite x and y count
    finite = np.isfinite(xyz[:, 0])
    np.testing.assert_array_equal(first_per_cell(xyz, group, 0.5),
                                  _first_per_cell_by_sorting(xyz, group, 0.5, finite))
    assert not first_per_cell(xyz[:0], group[:0], 0.5).size
    # a wild but finite coordinate: no overflow, the others thinned as before
    wild = xyz.copy()
    wild[0, :2] = (1e300, -1e300)
    keep_wild = first_per_cell(wild, group, 0.5)
    assert keep_wild[0] and np.array_equal(keep_wild[1:], first_per_cell(xyz[1:], group[1:],
                                                                         0.5))
    with pytest.raises(ValueError, match="positive"):
        first_per_cell(xyz, group, 0.0)


@pytest.fixture(scope="module")
def dense() -> SimulatedMission:
    """The paper's six strips, denser than the sample (some 2-5 points per square metre)."""
    return simulate_mission(SimulationSpec.from_options(density=2.0, line_length_m=160.0, seed=23))


@pytest.fixture(scope="module")
def dense_bag(dense: SimulatedMission, tmp_path_factory: pytest.TempPathFactory) -> Path:
    # A point with a non-finite height: dropped and counted, and no cell's representative
    # (its cell keeps the next point there).
    strips = [dataclasses.replace(s, xyz=s.xyz.copy()) for s in dense.mission.strips]
    strips[0].xyz[100, 2] = np.nan
    return write_mission_bag(tmp_path_factory.mktemp("thinning") / "dense",
                             dataclasses.replace(dense.mission, strips=strips))


def _config(cell: float) -> FlightConfig:
    return FlightConfig.from_mapping({"calibration.thinning_cell_m": cell})


def test_a_bag_read_thinned_and_the_same_bag_streamed_keep_the_same_points(
        dense_bag: Path) -> None:
    config = _config(1.0)
    full = load_mission(dense_bag, _config(0.0))
    thinned = load_mission(dense_bag, config)
    assert thinned.thinned_points == full.n_points - thinned.n_points
    assert full.dropped_non_finite == thinned.dropped_non_finite == 1
    assert thinned.n_points < 0.6 * full.n_points
    # at most one point per cell and message: over a whole strip a few per cell at most
    for strip in thinned.strips:
        cells = np.floor(strip.xyz[:, :2] / 1.0).astype(np.int64)
        _, counts = np.unique(cells, axis=0, return_counts=True)
        assert counts.max() <= 3 and counts.mean() < 1.2
    # the calibrator node's way: each message decoded and added as it comes
    stream = StreamingCalibration(config, strip_gap_s=1e9)  # (no strip closes early)
    with open_bag(dense_bag) as bag:
        for topic, _type, _ns, raw in bag.messages(["/lidar/points"]):
            cloud = parse_cloud(raw, source=topic)
            stream.add_cloud(extract_columns(cloud.points), cloud.frame_id)
    assert stream.thinned_points == thinned.thinned_points
    assert stream.dropped_non_finite == thinned.dropped_non_finite == 1
    assert stream.n_points == thinned.n_points
    for sid in stream.open_strip_ids:
        live = stream.open_strip(sid)
        batch = next(s for s in thinned.strips if s.strip_id == sid)
        np.testing.assert_array_equal(live.xyz, batch.xyz)
        np.testing.assert_array_equal(live.t, batch.t)


def test_a_thinned_calibration_stays_with_the_truth(dense: SimulatedMission,
                                                    dense_bag: Path) -> None:
    """Thinned to a third of the points, the estimate is still within three of its sigmas
    of the simulated truth, and its sigmas grow as fewer points support them, not more."""
    full = calibrate_mission(load_mission(dense_bag, _config(0.0)), _config(0.0))
    config = _config(1.0)
    mission = load_mission(dense_bag, config)
    result = calibrate_mission(mission, config)
    assert result.thinned_points == mission.thinned_points > 0
    sol = result.solution
    checked = 0
    for i, name in enumerate(PARAMETER_NAMES):
        if name not in sol.estimated:
            continue
        truth = dense.biases[name]
        assert abs(sol.delta[i] - truth) <= 3.0 * sol.sigma[i], name
        assert sol.sigma[i] <= 3.0 * full.solution.sigma[i], name
        checked += 1
    assert checked >= 6
    assert result.converged
