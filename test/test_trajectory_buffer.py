"""The live nodes' rolling trajectory buffer (lidarcal_ros.core.trajectory_buffer)."""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core import trajectory_buffer
from lidarcal_ros.core.trajectory_buffer import TrajectoryBuffer


def test_a_buffer_that_is_never_read_stays_bounded() -> None:
    """Fed for long (an hour at 200 Hz, looped three times as a looped replay does) and
    never asked for its trajectory, the buffer keeps at most ``keep_s`` of samples plus
    one merge's worth, not every sample ever added."""
    buffer = TrajectoryBuffer(keep_s=60.0)
    hour = np.arange(0.0, 3600.0, 0.005)
    for _loop in range(3):
        for t in hour[::7]:  # one by one, as a node's callback adds them
            buffer.add(float(t), (0.0, 60.0 * float(t), 1000.0), "map")
    assert buffer.samples == 3 * len(hour[::7])
    kept = len(buffer)
    assert kept <= 60.0 / (7 * 0.005) + trajectory_buffer._MAX_PENDING + 2
    assert kept < buffer.samples / 20  # (1.5M samples added)
    assert buffer.end == hour[::7][-1]


def test_the_trajectory_is_sorted_without_duplicates_and_trimmed() -> None:
    buffer = TrajectoryBuffer(keep_s=10.0)
    t = np.arange(0.0, 30.0, 0.01)
    xyz = np.column_stack([np.zeros_like(t), 60.0 * t, np.full_like(t, 1000.0)])
    rng = np.random.default_rng(1)
    order = rng.permutation(t.size)
    buffer.add_many(t[order], xyz[order])
    buffer.add_many(t[-50:], xyz[-50:])  # repeated samples
    traj = buffer.trajectory()
    assert np.all(np.diff(traj.t) > 0)
    assert traj.t[-1] == t[-1] and traj.t[-1] - traj.t[0] <= 10.0 + 1e-9
    np.testing.assert_array_equal(traj.xyz[:, 1], 60.0 * traj.t)


def test_poses_left_out_are_counted() -> None:
    """A live buffer leaves out poses with a non-finite stamp or position and stamps it
    already holds, and counts them (the nodes report the count on /diagnostics)."""
    buffer = TrajectoryBuffer(keep_s=100.0)
    buffer.add_many(np.arange(10.0), np.zeros((10, 3)))
    buffer.add(5.0, (1.0, 0.0, 0.0))  # a stamp held already, out of order
    buffer.add(11.0, (np.nan, 0.0, 0.0))
    assert len(buffer.trajectory()) == 10 and buffer.left_out == 2
