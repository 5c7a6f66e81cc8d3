"""The live nodes' rolling trajectory buffer (lidarcal_ros.core.trajectory.buffer)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lidarcal_ros.core.trajectory import buffer as trajectory_buffer
from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer


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


def _attitude_samples(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """``n`` samples at 200 Hz: a wavy path and an attitude given with arbitrary signs and
    lengths, every 37th missing (NaN)."""
    rng = np.random.default_rng(seed)
    t = 1.7e9 + np.arange(n) / 200.0
    s = np.sin(np.arange(n) / 200.0)
    xyz = np.column_stack([s, 60.0 * np.arange(n) / 200.0, 1000.0 + s])
    half = 0.5 * np.column_stack([0.05 * s, 0.02 * s, 1.0 + 0.3 * s])  # roll, pitch, yaw
    q = np.column_stack([np.sin(half[:, 0]), np.sin(half[:, 1]), np.sin(half[:, 2]),
                         np.cos(half[:, 2])])
    q *= rng.choice([-1.0, 1.0], (n, 1)) * rng.uniform(0.5, 2.0, (n, 1))
    q[::37] = np.nan
    return t, xyz, q


def test_samples_arriving_in_order_are_normalised_once_and_what_was_handed_out_stays() -> None:
    """Fed a few samples at a time (as a node hands them on) with trimming, the buffer's
    trajectory is the one built from its kept samples at once: the same positions, the same
    quaternions up to the sign (q and -q are one rotation; the hemisphere is carried from
    row to row), headings and full-attitude flag; and a trajectory handed out earlier is
    not changed by what comes after (another thread may be correcting with it)."""
    from lidarcal_ros.core.mission import Trajectory

    t, xyz, q = _attitude_samples(6000)
    buffer = TrajectoryBuffer(keep_s=5.0)
    rng = np.random.default_rng(1)
    pos, early, early_copy = 0, None, None
    while pos < len(t):
        k = int(rng.integers(1, 40))
        buffer.add_many(t[pos:pos + k], xyz[pos:pos + k], q[pos:pos + k])
        pos += k
        traj = buffer.trajectory()
        if early is None and pos > 500:
            assert traj.orientation is not None
            early = traj
            early_copy = (traj.t.copy(), traj.xyz.copy(), traj.orientation.copy())
    first = int(np.searchsorted(t, t[-1] - 5.0))
    whole = Trajectory(t[first:], xyz[first:], q[first:])
    assert traj.t[0] == t[first] and np.array_equal(traj.t, whole.t)
    assert np.array_equal(traj.xyz, whole.xyz)
    assert traj.orientation is not None and whole.orientation is not None
    same_sign = np.nansum(traj.orientation * whole.orientation, axis=1)
    np.testing.assert_array_equal(np.abs(traj.orientation), np.abs(whole.orientation))
    assert (np.abs(same_sign[np.isfinite(traj.orientation[:, 0])]) > 0.999).all()
    np.testing.assert_array_equal(traj.heading, whole.heading)
    assert traj.full_attitude == whole.full_attitude
    # the attitude is consistent from row to row, as interpolation needs
    dots = np.einsum("ij,ij->i", traj.orientation[1:], traj.orientation[:-1])
    assert (dots[np.isfinite(dots)] > 0).all()
    assert early is not None and early_copy is not None
    np.testing.assert_array_equal(early.t, early_copy[0])
    np.testing.assert_array_equal(early.xyz, early_copy[1])
    np.testing.assert_array_equal(early.orientation, early_copy[2])


def test_a_level_attitude_once_dropped_and_out_of_order_samples() -> None:
    """The full-attitude flag follows the samples kept (a tilted attitude trimmed away leaves
    a heading only); an attitude that stops leaves positions only once its samples are
    trimmed; samples out of order are sorted in."""
    buffer = TrajectoryBuffer(keep_s=1.0)
    t = np.arange(0, 450) * 0.01
    xyz = np.column_stack([np.zeros_like(t), 60.0 * t, np.full_like(t, 1000.0)])
    tilted = np.tile([0.01, 0.0, 0.0, 1.0], (100, 1))
    level = np.tile([0.0, 0.0, 0.6, 0.8], (100, 1))
    buffer.add_many(t[:100], xyz[:100], tilted)
    assert buffer.trajectory().full_attitude
    buffer.add_many(t[100:200], xyz[100:200], level)
    assert buffer.trajectory().full_attitude  # the tilted samples are still kept
    buffer.add_many(t[200:300], xyz[200:300], level)
    traj = buffer.trajectory()
    assert not traj.full_attitude and traj.orientation is not None
    buffer.add_many(t[300:], xyz[300:])  # no attitude any more
    traj = buffer.trajectory()
    assert traj.orientation is None and len(traj) == 101
    buffer.add_many(t[440:430:-1] + 0.005, xyz[440:430:-1])  # late, out of order
    traj = buffer.trajectory()
    assert np.all(np.diff(traj.t) > 0) and len(traj) == 111


def test_the_identity_is_a_level_pose_heading_east_among_poses_with_attitude() -> None:
    """An identity quaternion is "no orientation" only where every pose is the identity; in a
    trajectory with attitude it is a level pose heading due east, batch, sliced and live."""
    from lidarcal_ros.core.georeferencing.attitude import IDENTITY_XYZW, quaternions_from_attitude
    from lidarcal_ros.core.mission import Trajectory

    n = 40
    t = np.arange(n) * 0.02
    xyz = np.column_stack([t * 60.0, np.zeros(n), np.full(n, 500.0)])
    north = quaternions_from_attitude(np.zeros(20), np.zeros(20), np.zeros(20))
    east = np.tile(IDENTITY_XYZW, (20, 1))
    q = np.concatenate([north, east])
    batch = Trajectory(t, xyz, q)
    assert batch.orientation is not None and np.isfinite(batch.orientation).all()
    assert batch.heading is not None and np.allclose(batch.heading[20:], -np.pi / 2)
    tail = batch.take(slice(25, 40))  # identity rows only, taken from poses with attitude
    assert tail.orientation is not None and np.isfinite(tail.orientation).all()
    assert Trajectory(t, xyz, np.tile(IDENTITY_XYZW, (n, 1))).orientation is None

    live = TrajectoryBuffer()
    live.add_many(t[:20], xyz[:20], q[:20])
    live.trajectory()  # the first rows merged before the east-bound ones arrive
    live.add_many(t[20:], xyz[20:], q[20:])
    got = live.trajectory()
    assert got.orientation is not None
    np.testing.assert_allclose(got.orientation, batch.orientation)
    bare = TrajectoryBuffer()
    for k in range(n):
        bare.add(float(t[k]), tuple(xyz[k]), orientation=IDENTITY_XYZW)
    assert bare.trajectory().orientation is None


def _flight(t: np.ndarray) -> np.ndarray:
    """Positions of a straight line at 60 m/s (m)."""
    return np.column_stack([60.0 * t, np.zeros(t.size), np.full(t.size, 1000.0)])


@pytest.mark.parametrize("one_by_one", [True, False])
def test_a_clock_stepping_back_restarts_the_buffer_from_its_stamp(one_by_one: bool) -> None:
    """10 s of poses, then the clock steps back 4 s and runs on (a second flight at those
    stamps, 500 m away): the old clock's poses from the step on are dropped, counted and
    said, so that the stamps 6-10 s carry the new flight only; swapped neighbours are not a
    step."""
    from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer

    old_t = np.arange(0.0, 10.0, 0.1)
    new_t = np.arange(6.05, 12.0, 0.1)  # (no stamp of the old clock's)
    new_xyz = _flight(new_t + 0.0) + np.array([0.0, 500.0, 0.0])
    t = np.concatenate([old_t, new_t])
    xyz = np.concatenate([_flight(old_t), new_xyz])
    t[[3, 7]] = t[[7, 3]]  # reordered on the way (0.4 s): sorted, no step
    buffer = TrajectoryBuffer(keep_s=math.inf)
    if one_by_one:
        for ti, p in zip(t, xyz):
            buffer.add(float(ti), tuple(p))
    else:
        buffer.add_many(t[:50], xyz[:50])
        buffer.add_many(t[50:], xyz[50:])
    traj = buffer.trajectory()
    assert buffer.steps_back == 1
    assert buffer.last_step_back == "stamps went backwards at t=6.050 s, 3.850 s back from " \
                                    "t=9.900 s"
    old_kept = old_t < 6.05
    assert len(traj) == int(old_kept.sum()) + new_t.size
    assert buffer.left_out == int((~old_kept).sum())
    later = traj.t >= 6.05
    np.testing.assert_allclose(traj.xyz[later], new_xyz)
    assert np.all(np.diff(traj.t) > 0)


def test_the_calibrators_samples_drop_the_old_clock_alike() -> None:
    """The live calibrator's samples: the same step in one array or in two."""
    from lidarcal_ros.pipeline.calibration.stream_inputs import TrajectorySamples

    old_t, new_t = np.arange(0.0, 10.0, 0.1), np.arange(6.05, 12.0, 0.1)
    t = np.concatenate([old_t, new_t])
    xyz = np.concatenate([_flight(old_t), _flight(new_t + 0.0) + np.array([0.0, 500.0, 0.0])])
    for parts in ([slice(0, None)], [slice(0, 70), slice(70, None)]):
        samples = TrajectorySamples()
        for sl in parts:
            samples.add(t[sl], xyz[sl], None)
        traj = samples.trajectory
        assert samples.steps_back == 1 and samples.newest == pytest.approx(11.95)
        assert "stamps went backwards at t=6.050 s, 3.850 s back" in samples.last_step_back
        assert samples.left_out == 39
        np.testing.assert_allclose(traj.xyz[traj.t >= 6.05, 1], 500.0)
