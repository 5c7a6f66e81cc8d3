"""Poses without an orientation among poses with one: which are bridged by slerp, and how
closely (``attitude.bridge_missing``, ``Trajectory.from_samples`` of a file)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lidarcal_ros.core.georeferencing.attitude import (
    attitude_from_quaternions,
    bridge_missing,
    normalise_quaternions,
    quaternions_from_attitude,
)
from lidarcal_ros.core.mission import BRIDGE_S, Trajectory


def _turning(t: np.ndarray) -> np.ndarray:
    """Quaternions of a platform rolling 4 deg at 0.5 Hz and turning 10 deg/s."""
    return quaternions_from_attitude(np.radians(4.0) * np.sin(np.pi * t), np.zeros_like(t),
                                     np.radians(10.0) * t)


def test_gaps_between_close_poses_are_bridged_others_not() -> None:
    t = np.arange(0.0, 2.0, 0.02)  # 50 Hz
    truth = normalise_quaternions(_turning(t))
    q = truth.copy()
    q[[10, 30, 31, 32, 33]] = np.nan  # 1 and 4 missing: neighbours 0.04 and 0.1 s apart
    q[50:56] = np.nan  # 6 missing: neighbours 0.14 s apart, more than BRIDGE_S
    q[[0, 99]] = np.nan  # at the ends: nothing on one side
    out, n = bridge_missing(t, q, max_gap_s=BRIDGE_S)
    assert n == 5
    assert np.isnan(out[[0, 99, *range(50, 56)], 0]).all()
    filled = [10, 30, 31, 32, 33]
    # the truth's rotations (q or -q), within slerp's miss of the roll's acceleration a over
    # the gap h: a h^2 / 8 (1.4e-4 rad over 0.04 s, 8.6e-4 rad over 0.1 s)
    dot = np.abs(np.einsum("ij,ij->i", out[filled], truth[filled]))
    miss = 2 * np.arccos(np.clip(dot, -1, 1))
    a = np.radians(4.0) * np.pi**2
    h = np.array([0.04, 0.1, 0.1, 0.1, 0.1])
    assert np.all(miss <= 1.05 * a * h**2 / 8), miss
    assert miss[0] > 0.2 * a * 0.04**2 / 8  # (a bound that says something)
    kept = ~np.isnan(q[:, 0])
    assert np.array_equal(np.abs(out[kept]), np.abs(q[kept]))


def test_a_gap_across_a_sign_flip_takes_the_short_arc() -> None:
    """The rows either side of a gap in opposite hemispheres (q and -q are one rotation):
    the bridge is between the rotations, not through the long way round."""
    t = np.array([0.0, 0.02, 0.04])
    q = normalise_quaternions(_turning(t))
    q[1] = np.nan
    q[2] = -q[2]
    out, n = bridge_missing(t, q, max_gap_s=BRIDGE_S)
    assert n == 1
    roll, _, heading = attitude_from_quaternions(out[1:2])
    true_roll, _, true_heading = attitude_from_quaternions(_turning(t[1:2]))
    assert np.degrees(heading[0] - true_heading[0]) == pytest.approx(0.0, abs=1e-3)
    assert np.degrees(roll[0] - true_roll[0]) == pytest.approx(0.0, abs=1e-2)


def test_nothing_missing_is_the_same_array() -> None:
    t = np.arange(0.0, 1.0, 0.02)
    q = normalise_quaternions(_turning(t))
    out, n = bridge_missing(t, q, max_gap_s=BRIDGE_S)
    assert n == 0 and out is q


def test_a_file_of_poses_says_what_it_bridged(caplog) -> None:
    t = np.arange(0.0, 2.0, 0.02)
    q = _turning(t)
    q[[10, 60]] = 0.0
    xyz = np.column_stack([t * 50.0, np.zeros_like(t), np.full_like(t, 1000.0)])
    with caplog.at_level(logging.WARNING):
        traj = Trajectory.from_samples(t, xyz, q, source="f.mcap: trajectory /p")
    assert traj.orientation is not None and not np.isnan(traj.orientation).any()
    assert [r.getMessage() for r in caplog.records] == [
        "f.mcap: trajectory /p: of 100 orientation quaternions, 2 zero: read as poses without "
        "orientation; 2 poses without one between poses with one at most 0.1 s apart: their "
        "orientation interpolated"]
    # without a source (a live buffer's, a test's): nothing screened, nothing bridged
    bare = Trajectory.from_samples(t, xyz, q)
    assert bare.orientation is not None and np.isnan(bare.orientation[[10, 60], 0]).all()
