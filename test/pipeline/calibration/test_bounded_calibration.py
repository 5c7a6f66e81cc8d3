"""``calibration.memory: bounded`` (pipeline/calibration/bounded.py, core/calibration/bounded.py):
the reduced mission read in four passes gives the sample points and the estimate of the whole
mission, and the truth, on simulated missions with known biases, level and in rough air; what
it holds does not grow with the mission."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_missions import MissionFiles

from lidarcal_ros.core.calibration.bounded import LowestPriority, StripExtent
from lidarcal_ros.core.calibration.calibrate import Calibrator
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


def test_samples_chosen_in_passes_are_the_whole_missions(both: tuple) -> None:
    files, _, _, reduced = both
    cal = Calibrator.from_mission(files.mission, _config().calibration_settings())
    cal.matcher.choose_samples(cal.pairs)
    held = {s.strip_id: s for s in reduced.strips}
    assert len(reduced.samples) == len(cal.pairs) > 0
    for pair in cal.pairs:
        a, b = cal.strips[pair.a], cal.strips[pair.b]
        index, before = reduced.samples[(a.strip_id, b.strip_id)]
        assert pair.sample is not None and pair.before is not None
        np.testing.assert_array_equal(held[a.strip_id].xyz[index], a.strip.xyz[pair.sample])
        np.testing.assert_allclose(before, pair.before, atol=1e-9)


def test_what_is_held_does_not_grow_with_the_mission(
        mission_factory: Callable[..., MissionFiles]) -> None:
    # samples of a few hundred points a pair: their neighbourhoods a small part of the
    # overlaps, as a pair's 17,000 are of a mission of some 20M points and more
    config = _config(**{"matching.max_candidates_per_pair": 300, "matching.per_class_cap": 20})
    short = load_reduced_mission(mission_factory(**MISSIONS["level"]).bag, config)
    long = load_reduced_mission(
        mission_factory(**{**MISSIONS["level"], "line_length_m": 600.0}).bag, config)
    assert long.n_points > 1.8 * short.n_points
    assert long.n_held < 1.15 * short.n_held
    assert long.n_held < 0.4 * long.n_points
    # the sample choice held the surface near the candidates waiting, not the strips
    assert long.held_choosing < 0.25 * long.n_points


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
    for block, start in enumerate(range(0, 5000, 700)):
        ext.add(xyz[start:start + 700], t[start:start + 700], block=block)
    ext.finish()
    keys = footprint_keys(xyz, 10.0)
    np.testing.assert_array_equal(ext.cells, np.unique(keys))
    assert ext.n_points == 5000 and ext.span == (t[0], t[-1])
    assert ext.density == pytest.approx(5000 / (ext.cells.size * 100.0))
    # the last block with a point in each cell
    blocks = np.arange(5000) // 700
    for cell, last in zip(ext.cells, ext.last, strict=True):
        assert last == blocks[keys == cell].max()


def test_last_block_near_looks_as_far_as_the_radius() -> None:
    ext = StripExtent(1, 10.0)
    ext.add(np.array([[5.0, 5.0, 0.0]]), np.array([1.0]), block=3)
    ext.add(np.array([[25.0, 5.0, 0.0], [35.0, 5.0, 0.0]]), np.array([2.0, 3.0]), block=7)
    ext.finish()
    xy = np.array([[5.0, 5.0], [55.0, 5.0], [500.0, 5.0]])
    # within a cell's reach: the cell and its neighbours
    np.testing.assert_array_equal(ext.last_block_near(xy, 5.0), [3, -1, -1])
    # 25 m: three cells each way
    np.testing.assert_array_equal(ext.last_block_near(xy, 25.0), [7, 7, -1])


def test_bounded_refuses_thinning(tmp_path: Path,
                                  mission_factory: Callable[..., MissionFiles]) -> None:
    files = mission_factory(**MISSIONS["level"])
    with pytest.raises(ConfigError, match="thinning_cell_m"):
        MissionBlocks(files.bag, thinning_cell_m=0.5)
