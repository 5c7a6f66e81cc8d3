"""``calibration.memory: bounded`` (pipeline/calibration/bounded.py, core/calibration/bounded.py):
the reduced mission read in three passes gives the estimate of the whole mission, and the
truth, on simulated missions with known biases, level and in rough air."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_missions import MissionFiles

from lidarcal_ros.core.calibration.bounded import LowestPriority, StripExtent
from lidarcal_ros.core.calibration.pairs import footprint_keys
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad
from lidarcal_ros.core.simulation.flight_path import RoughAir
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.bag.mission_blocks import MissionBlocks
from lidarcal_ros.pipeline.calibration.bounded import ReducedMission, load_reduced_mission
from lidarcal_ros.pipeline.calibration.procedure import (
    calibrate_mission,
    load_for_calibration,
    load_mission,
)

mission_factory = helpers_missions.mission_factory

#: Candidates few enough that a pair's neighbourhoods leave much of its strips out.
SETTINGS: dict[str, Any] = {"matching.max_candidates_per_pair": 1500,
                            "matching.per_class_cap": 300}
#: How far an estimate may be from the truth (a small mission): 2 cm, 5 arcsec, 5e-5.
TRUTH_TOLERANCE = {"dX": 0.02, "dY": 0.02, "dr": 0.02, "dS": 5e-5,
                   "domega": arcsec_to_rad(5), "dphi": arcsec_to_rad(5),
                   "dkappa": arcsec_to_rad(5)}
MISSIONS: dict[str, dict[str, Any]] = {
    "level": {"density": 0.15, "line_length_m": 300.0, "seed": 11},
    "rough air": {"density": 0.15, "line_length_m": 300.0, "seed": 11, "rough_air": RoughAir()},
}


def _config(**values: Any) -> FlightConfig:
    return FlightConfig.from_mapping({**SETTINGS, **values})


@pytest.fixture(scope="module", params=sorted(MISSIONS))
def both(request: pytest.FixtureRequest, mission_factory: Callable[..., MissionFiles]
         ) -> tuple[MissionFiles, Any, Any, ReducedMission]:
    files = mission_factory(**MISSIONS[request.param])
    whole = calibrate_mission(load_mission(files.bag, _config()), _config())
    config = _config(**{"calibration.memory": "bounded"})
    reduced = load_for_calibration(files.bag, config)
    assert isinstance(reduced, ReducedMission)
    return files, whole, calibrate_mission(reduced, config), reduced


def test_bounded_equals_whole_within_a_tenth_of_sigma(both: tuple) -> None:
    files, whole, bounded, reduced = both
    assert reduced.n_points == files.mission.n_points
    assert reduced.n_held < 0.8 * reduced.n_points  # the neighbourhoods leave points out
    assert bounded.n_pair_correspondences == pytest.approx(whole.n_pair_correspondences,
                                                           rel=0.01)
    sol_w, sol_b = whole.solution, bounded.solution
    assert sol_b.estimated == sol_w.estimated
    for i, name in enumerate(PARAMETER_NAMES):
        if name in sol_w.estimated:
            assert abs(sol_b.delta[i] - sol_w.delta[i]) <= 0.1 * sol_w.sigma[i], name


def test_bounded_recovers_the_biases(both: tuple) -> None:
    files, _, bounded, _ = both
    sol = bounded.solution
    assert bounded.converged
    for i, name in enumerate(PARAMETER_NAMES):
        if name in sol.estimated:
            err = abs(sol.delta[i] - files.sim.biases[name])
            assert err <= TRUTH_TOLERANCE[name], (name, err)
    assert len(bounded.control) == len(files.mission.strips)  # the control point in each


def test_reduced_strips_keep_the_whole_footprint_and_priorities(
        mission_factory: Callable[..., MissionFiles]) -> None:
    files = mission_factory(**MISSIONS["level"])
    reduced = load_reduced_mission(files.bag, _config())
    by_id = {s.strip_id: s for s in files.mission.strips}
    for strip in reduced.strips:
        full = by_id[strip.strip_id]
        extent, priority = reduced.whole[strip.strip_id]
        assert extent.n_points == len(full)
        assert extent.span == (full.t.min(), full.t.max())
        np.testing.assert_array_equal(extent.cells, np.unique(footprint_keys(full.xyz, 10.0)))
        # each held point carries the priority the whole strip's draw gives it
        index = np.searchsorted(full.t, strip.t)
        np.testing.assert_array_equal(full.xyz[index], strip.xyz)
        whole_priority = np.random.default_rng([0, strip.strip_id]).random(len(full))
        np.testing.assert_array_equal(priority, whole_priority[index])


def test_lowest_priority_keeps_the_k_lowest_of_all_blocks() -> None:
    rng = np.random.default_rng(3)
    priority = rng.random(10_000)
    keep = LowestPriority(700)
    for start in range(0, priority.size, 333):
        stop = start + 333
        keep.add(priority[start:stop], np.arange(start, min(stop, priority.size)),
                 np.zeros((priority[start:stop].size, 3)))
    index, _, _ = keep.result()
    np.testing.assert_array_equal(index, np.sort(np.argsort(priority)[:700]))


def test_strip_extent_counts_cells_and_span_block_by_block() -> None:
    rng = np.random.default_rng(4)
    xyz = rng.uniform(0, 500, (5000, 3))
    t = np.sort(rng.uniform(10, 20, 5000))
    ext = StripExtent(1, 10.0)
    for start in range(0, 5000, 700):
        ext.add(xyz[start:start + 700], t[start:start + 700])
    ext.finish()
    np.testing.assert_array_equal(ext.cells, np.unique(footprint_keys(xyz, 10.0)))
    assert ext.n_points == 5000 and ext.span == (t[0], t[-1])
    assert ext.density == pytest.approx(5000 / (ext.cells.size * 100.0))


def test_bounded_refuses_thinning(tmp_path: Path,
                                  mission_factory: Callable[..., MissionFiles]) -> None:
    files = mission_factory(**MISSIONS["level"])
    with pytest.raises(ConfigError, match="thinning_cell_m"):
        MissionBlocks(files.bag, thinning_cell_m=0.5)
