"""Flight lines split from a trajectory (core/trajectory/lines.py): against the simulated UAV
payload's line labels (the turns dropped, each line one strip), and the cases beside it: a
hover, a gap, a slow arc, bad settings."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.uav_payload import UavPayloadSpec, simulate_uav_payload
from lidarcal_ros.core.trajectory.lines import line_of, straight_lines
from lidarcal_ros.errors import ConfigError


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_the_lines_are_the_simulated_ones_without_the_turns(layout: str, seed: int) -> None:
    m = simulate_uav_payload(UavPayloadSpec(layout=layout, seed=seed, columns=16, n_lines=4,
                                            line_length_m=100.0))
    lines = straight_lines(m.trajectory)
    assert lines.shape == (4, 2)
    label = line_of(m.clouds.absolute_times(), lines)
    for k in range(4):
        truth = m.line[label == k]
        # every point of a strip was recorded on that line, none in a turn ...
        assert np.array_equal(np.unique(truth), [k])
        # ... and the strip holds nearly all of the line (a second lost at each end)
        assert truth.size > 0.9 * np.count_nonzero(m.line == k)
    assert not (label[m.line < 0] >= 0).any()


def _trajectory(t: np.ndarray, xy: np.ndarray) -> Trajectory:
    return Trajectory(t, np.column_stack([xy, np.full(t.size, 60.0)]))


def test_a_hover_a_gap_and_a_slow_arc() -> None:
    t = np.arange(0.0, 60.0, 0.01)
    # 20 s east at 8 m/s, 10 s hovering, 30 s north
    x = np.where(t < 20.0, 8.0 * t, 160.0)
    y = np.where(t < 30.0, 0.0, 8.0 * (t - 30.0))
    lines = straight_lines(_trajectory(t, np.column_stack([x, y])))
    # (the chord reaches a second into the hover: a quarter second more is left out)
    np.testing.assert_allclose(lines, [[1.0, 18.75], [31.25, 58.99]], atol=0.02)
    # a gap of 5 s in the samples splits a line (no track is known across it)
    keep = (t < 10.0) | (t > 15.0)
    gapped = straight_lines(_trajectory(t[keep], np.column_stack([8.0 * t, 0 * t])[keep]))
    np.testing.assert_allclose(gapped, [[1.0, 8.99], [16.01, 58.99]], atol=0.02)
    # an arc turning 1 deg/s is a line, at 3 deg/s it is not
    for rate, count in ((1.0, 1), (3.0, 0)):
        psi = np.radians(rate) * t
        xy = np.column_stack([np.sin(psi), 1.0 - np.cos(psi)]) * 8.0 / np.radians(rate)
        assert len(straight_lines(_trajectory(t, xy))) == count
    assert line_of(np.array([0.5, 5.0, 30.0]), lines).tolist() == [-1, 0, -1]
    assert line_of(np.array([5.0]), np.empty((0, 2))).tolist() == [-1]


def test_bad_settings_are_refused() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    with pytest.raises(ConfigError, match="window_s must be positive"):
        straight_lines(_trajectory(t, np.column_stack([t, t])), window_s=0.0)
