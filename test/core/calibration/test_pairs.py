"""core/calibration/pairs.py: footprints, overlaps and the stratified sample of a strip pair."""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core.calibration.pairs import (
    FootprintGrid,
    footprint_keys,
    ground_speed,
    outside_strips,
    stratified_sample,
)
from lidarcal_ros.core.calibration.tin import PatchMatches
from lidarcal_ros.core.mission import Strip, Trajectory


def grid_points(x0: float, x1: float, y0: float, y1: float, step: float) -> np.ndarray:
    """Points on a regular grid over [x0, x1) x [y0, y1) at height 0, metres."""
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_footprint_keys_are_one_per_cell_across_the_axes() -> None:
    xy = np.array([[0.1, 0.1], [4.9, 4.9], [5.0, 0.0], [-0.1, 0.0], [0.0, -0.1],
                   [-1e6, 2e6]])
    keys = footprint_keys(xy, 5.0)
    assert keys[0] == keys[1]  # one cell
    assert len(set(keys[[0, 2, 3, 4]].tolist())) == 4  # neighbours on each side of 0
    assert len(set(keys.tolist())) == 5


def test_interior_is_the_one_cell_erosion_of_a_block() -> None:
    grid = FootprintGrid(cell=2.0)
    cells = np.unique(grid.keys(grid_points(0.0, 10.0, 0.0, 8.0, 1.0)))  # 5 x 4 cells
    interior = grid.interior(cells)
    assert cells.size == 20 and interior.size == 3 * 2
    expected = np.unique(grid.keys(grid_points(2.5, 8.0, 2.5, 6.0, 2.0)))
    np.testing.assert_array_equal(np.sort(interior), expected)


def test_positions_outside_every_strip() -> None:
    strips = [Strip(1, grid_points(0.0, 50.0, 0.0, 20.0, 1.0), np.arange(1000.0)),
              Strip(2, grid_points(0.0, 50.0, 30.0, 50.0, 1.0), np.arange(1000.0))]
    control = np.array([[10.0, 10.0, 0.0], [10.0, 25.0, 0.0], [10.0, 40.0, 0.0],
                        [80.0, 10.0, 0.0]])
    np.testing.assert_array_equal(outside_strips(strips, control, 2.0),
                                  [False, True, False, True])
    assert outside_strips([], control, 2.0).all()


def test_ground_speed_is_the_median_over_the_times() -> None:
    t = np.arange(0.0, 20.0, 0.5)
    speed = np.where(t < 10.0, 50.0, 60.0)
    x = np.concatenate([[0.0], np.cumsum(speed[:-1] * 0.5)])
    trajectory = Trajectory(t, np.column_stack([x, np.zeros_like(x), np.full_like(x, 900.0)]))
    assert ground_speed(trajectory, np.array([2.0, 8.0])) == 50.0
    assert ground_speed(trajectory, np.array([12.0, 18.0])) == 60.0
    assert np.isnan(ground_speed(trajectory, np.array([])))


def test_the_sample_caps_each_slope_and_aspect_class() -> None:
    """Flat patches capped at cap x factor, each sloped (slope, aspect) class at cap, the
    points kept those of lowest priority, invalid matches never."""
    rng = np.random.default_rng(5)
    n_flat, n_roof = 400, 100
    tilt = np.radians(30.0)
    east_roof = [np.sin(tilt), 0.0, np.cos(tilt)]  # aspect 90 deg: sector 2, steep class
    normal = np.array([[0.0, 0.0, 1.0]] * n_flat + [east_roof] * n_roof)
    valid = np.ones(n_flat + n_roof, dtype=bool)
    valid[:10] = False
    matches = PatchMatches(valid, np.zeros(valid.size, np.int64), normal,
                           np.full((valid.size, 3), 1 / 3), np.zeros(valid.size))
    candidates = np.arange(1000, 1000 + valid.size)  # indices into the point strip
    priority = rng.permutation(2000).astype(np.float64)
    sample = stratified_sample(matches, candidates, priority, per_class_cap=20,
                               flat_class_factor=4)
    flat, roof = sample[sample < 1000 + n_flat], sample[sample >= 1000 + n_flat]
    assert flat.size == 80 and roof.size == 20
    assert np.all(np.diff(sample) > 0) and not np.isin(candidates[:10], sample).any()
    valid_flat = candidates[10:n_flat]
    lowest = np.sort(valid_flat[np.argsort(priority[valid_flat])[:80]])
    np.testing.assert_array_equal(flat, lowest)
