"""The heading of the local trajectory from the IMU's orientation (``core.heading``): its
convention, how it reaches the calibration and the correction from bags and streams, and
that it removes what a crab the track cannot show does to both."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from helpers_missions import MissionFiles, mission_factory  # noqa: F401  (fixture)

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, calibrate
from lidarcal_ros.core.georeferencing.attitude import (
    headings_from_quaternions,
    normalise_quaternions,
    quaternions_from_headings,
)
from lidarcal_ros.core.georeferencing.heading import (
    HeadingSource,
    choose_heading,
    describe_heading_policy,
    describe_heading_use,
    window_headings,
)
from lidarcal_ros.core.georeferencing.local_trajectory import window_lines
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer
from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.bag.mission_bag import read_mission, write_mission_bag
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, correct_columns

WIND = (5.0, 0.0)  # m/s east: 4.8 degrees of crab at 60 m/s on north-south lines


# ---------------------------------------------------------------- convention
def heading_from_quaternion(*q: float) -> float:
    """The heading a trajectory gives a pose of orientation ``q`` (identity: none)."""
    return float(headings_from_quaternions(normalise_quaternions(np.array(q)))[0])


def _quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), REP-103."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def test_kappa_is_the_yaw_less_a_quarter_turn_whatever_the_roll_and_pitch() -> None:
    # Body x forward (REP-103): yaw 90 degrees flies north, docs/method.md's kappa 0; yaw 0 flies
    # east, kappa -90 degrees (forward = (-sin kappa, cos kappa)).
    assert heading_from_quaternion(*_quaternion(0, 0, math.pi / 2)) == pytest.approx(0.0)
    assert heading_from_quaternion(*_quaternion(0, 0, 0.3)) == pytest.approx(0.3 - math.pi / 2)
    assert heading_from_quaternion(*_quaternion(0, 0, -math.pi / 2)) == pytest.approx(math.pi)
    # roll and pitch of a turn do not move the heading of the forward axis
    for roll, pitch in ((0.2, 0.0), (-0.3, 0.1), (0.0, -0.15)):
        got = heading_from_quaternion(*_quaternion(roll, pitch, 1.1))
        assert got == pytest.approx(1.1 - math.pi / 2, abs=1e-12)
    # not normalised: the same heading
    x, y, z, w = _quaternion(0.1, 0.05, 2.0)
    assert heading_from_quaternion(3 * x, 3 * y, 3 * z, 3 * w) == pytest.approx(
        heading_from_quaternion(x, y, z, w), abs=1e-14)


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, -1.0),
                               (0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.3, 0.9),
                               (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5))])
def test_identity_zero_non_finite_or_vertical_orientations_give_no_heading(
        q: tuple[float, float, float, float]) -> None:
    assert math.isnan(heading_from_quaternion(*q))


def test_level_quaternion_of_a_heading_round_trips() -> None:
    for kappa in np.linspace(-math.pi + 1e-9, math.pi, 37):
        got = heading_from_quaternion(*quaternions_from_headings(np.array([kappa]))[0])
        assert math.remainder(got - kappa, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_window_heading_is_a_circular_mean_and_needs_every_sample() -> None:
    deg = np.radians([179.0, -179.0, 178.0, -178.0, 10.0, 20.0, np.nan, 30.0])
    got = window_headings(deg, np.array([0, 2, 4, 5]), np.array([2, 4, 6, 8]))
    assert abs(math.remainder(got[0] - math.pi, 2 * math.pi)) < 1e-12  # across +-180
    assert abs(math.remainder(got[1] - math.pi, 2 * math.pi)) < 1e-12
    assert math.degrees(got[2]) == pytest.approx(15.0)
    assert math.isnan(got[3])  # a sample without orientation


def test_auto_takes_an_agreeing_attitude_and_refuses_another_convention(
        caplog: pytest.LogCaptureFixture) -> None:
    track = np.radians([0.0, 180.0, 0.5])
    crabbed = track + np.radians([4.8, -4.8, 4.8])
    assert np.array_equal(choose_heading(track, crabbed, HeadingSource.AUTO), crabbed)
    assert np.array_equal(choose_heading(track, crabbed, HeadingSource.TRACK), track)
    assert np.array_equal(choose_heading(track, None, HeadingSource.AUTO), track)
    assert np.array_equal(
        choose_heading(track, np.array([0.1, np.nan, 0.2]), HeadingSource.AUTO), track)
    # a body frame of another convention (y forward): 90 degrees off the track
    with caplog.at_level(logging.WARNING, logger="lidarcal_ros.core.georeferencing.heading"):
        assert np.array_equal(
            choose_heading(track, track + math.pi / 2, HeadingSource.AUTO), track)
    assert "disagrees with the track by 90 degrees" in caplog.text
    # forced: used as given
    assert np.array_equal(choose_heading(track, track + math.pi / 2, HeadingSource.ATTITUDE),
                          track + math.pi / 2)
    with pytest.raises(TrajectoryError, match="'attitude' but the trajectory has no "
                       "orientation"):
        choose_heading(track, None, HeadingSource.ATTITUDE, source="strip 3")


def test_window_lines_take_the_heading_the_mode_asks_for() -> None:
    t = np.arange(0.0, 10.0, 0.01)
    xyz = np.column_stack([np.zeros_like(t), 60.0 * t, np.full_like(t, 1000.0)])  # north
    crab = math.radians(4.0)
    traj = Trajectory(t, xyz, quaternions_from_headings(np.full(t.size, crab)))
    pts = np.linspace(1.0, 9.0, 50)
    assert np.allclose(window_lines(pts, traj, heading_source=HeadingSource.AUTO).kappa, crab)
    assert np.allclose(window_lines(pts, traj, heading_source=HeadingSource.TRACK).kappa, 0.0,
                       atol=1e-9)
    bare = Trajectory(t, xyz)
    assert np.allclose(window_lines(pts, bare).kappa, 0.0, atol=1e-9)
    with pytest.raises(TrajectoryError, match=r"strip 9: matching\.heading_source"):
        window_lines(pts, bare, heading_source=HeadingSource.ATTITUDE, source="strip 9")


def test_the_words_for_which_heading_was_used() -> None:
    assert describe_heading_use({1: HeadingSource.ATTITUDE, 2: HeadingSource.TRACK,
                                 3: HeadingSource.ATTITUDE}) == (
        "heading from the poses' orientation (IMU) for strips 1, 3; from the track for 2")
    assert describe_heading_policy(HeadingSource.AUTO, False) == (
        "from the track (the poses carry no orientation)")
    assert describe_heading_policy(HeadingSource.TRACK, True).endswith(
        "(matching.heading_source track)")
    assert "within 20 deg" in describe_heading_policy(HeadingSource.AUTO, True)


# ---------------------------------------------------------------- carried through
def test_trajectory_keeps_each_samples_heading_through_sorting_and_slicing() -> None:
    t = np.array([3.0, 1.0, 2.0, 2.0, np.nan])
    xyz = np.arange(15.0).reshape(5, 3)
    h = np.array([0.3, 0.1, 0.2, 0.9, 0.5])
    traj = Trajectory.from_samples(t, xyz, quaternions_from_headings(h))
    assert traj.t.tolist() == [1.0, 2.0, 3.0]
    assert traj.heading is not None and np.allclose(traj.heading, [0.1, 0.2, 0.3])
    assert np.allclose(traj.take(slice(1, None)).heading, [0.2, 0.3])  # type: ignore[arg-type]
    assert Trajectory.from_samples(t, xyz, np.full((5, 4), np.nan)).heading is None
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (5, 1))
    assert Trajectory.from_samples(t, xyz, identity).heading is None  # identity: none
    with pytest.raises(TrajectoryError, match="3 stamps but 2 orientations"):
        Trajectory(t[:3], xyz[:3], quaternions_from_headings(h[:2]))


def test_live_trajectory_buffer_keeps_the_headings_in_order_and_window() -> None:
    buf = TrajectoryBuffer(keep_s=5.0)
    for k in [0, 1, 2, 4, 3, *range(5, 12)]:  # one out of order
        q = quaternions_from_headings(np.array([0.01 * k]))[0]
        buf.add(float(k), (0.0, float(k), 100.0), "map", tuple(q))
    traj = buf.trajectory()
    assert traj.t.tolist() == [float(k) for k in range(6, 12)]  # the last 5 s
    assert traj.heading is not None and np.allclose(traj.heading, 0.01 * traj.t)
    assert buf.oriented_samples == 12
    buf.add_many(np.array([12.0, 13.0]), np.zeros((2, 3)))  # without orientation
    assert buf.oriented_samples == 12
    traj = buf.trajectory()
    assert traj.heading is not None and np.isnan(traj.heading[-2:]).all()
    assert np.allclose(traj.heading[:-2], 0.01 * traj.t[:-2])


def test_bag_round_trip_writes_and_reads_the_orientation(tmp_path: Path) -> None:
    from lidarcal_ros.core.mission import Mission, Strip

    t = np.arange(0.0, 4.0, 0.01)
    heading = np.radians(3.0) + 0.001 * t
    traj = Trajectory(t, np.column_stack([0 * t, 60 * t, 1000 + 0 * t]),
                      quaternions_from_headings(heading))
    strip = Strip(1, np.array([[1.0, 60.0, 0.0], [2.0, 120.0, 0.0]]), np.array([1.0, 2.0]))
    path = write_mission_bag(tmp_path / "att", Mission(traj, [strip]))
    back = read_mission(path).trajectory
    assert back.heading is not None
    assert np.allclose(back.heading, heading, atol=1e-12)
    bare = write_mission_bag(tmp_path / "bare", Mission(Trajectory(traj.t, traj.xyz), [strip]))
    assert read_mission(bare).trajectory.heading is None


# ---------------------------------------------------------------- what it is for
def _errors_in_sigmas(result: object, biases: dict[str, float]) -> dict[str, float]:
    sol = result.solution  # type: ignore[attr-defined]
    return {n: abs(sol.delta[i] - biases[n]) / sol.sigma[i]
            for i, n in enumerate(PARAMETER_NAMES)
            if n in biases and math.isfinite(sol.sigma[i]) and sol.sigma[i] > 0}


def test_calibration_of_a_crabbed_mission_is_unbiased_with_the_attitude(
        mission_factory: Callable[..., MissionFiles]) -> None:  # noqa: F811
    """4.8 degrees of crab: with the heading from the track the boresight and lever arm
    come out tens of sigmas off (bench/README.md, "Crab"); with the IMU's heading, read back
    from the bag, every estimate is within three sigmas of the truth."""
    crabbed = mission_factory(density=0.2, line_length_m=220.0, seed=41, wind_mps=WIND,
                              attitude=True)
    mission = read_mission(crabbed.bag)
    assert mission.trajectory.heading is not None
    assert {round(abs(ln["crab_deg"]), 1) for ln in crabbed.sim.lines} == {4.8}
    by_attitude = calibrate(mission, CalibrationSettings())  # auto
    by_track = calibrate(mission, CalibrationSettings(heading_source=HeadingSource.TRACK))
    attitude_errors = _errors_in_sigmas(by_attitude, crabbed.sim.biases)
    track_errors = _errors_in_sigmas(by_track, crabbed.sim.biases)
    assert max(attitude_errors.values()) < 3.0, attitude_errors
    assert max(track_errors.values()) > 8.0, track_errors
    assert by_attitude.converged
    # and each says which heading it took, strip by strip
    assert set(by_attitude.heading_from.values()) == {"attitude"}
    assert set(by_track.heading_from.values()) == {"track"}
    assert describe_heading_use(by_attitude.heading_from) == (
        "heading from the poses' orientation (IMU) for every strip")
    # the crab each strip was flown with, seen as the attitude less the track
    want = {ln["id"]: ln["crab_deg"] for ln in crabbed.sim.lines}
    assert by_attitude.crab_deg == pytest.approx(want, abs=0.05)
    assert describe_heading_use(by_attitude.heading_from, by_attitude.crab_deg) == (
        "heading from the poses' orientation (IMU) for every strip (crab -4.8 to +4.8 deg)")
    assert describe_heading_use(by_track.heading_from) is None


def test_correction_of_a_crabbed_mission_lands_on_the_truth_with_the_attitude(
        mission_factory: Callable[..., MissionFiles]) -> None:  # noqa: F811
    """Without range noise, the true biases removed with the IMU's heading put each point
    back on the surface to a fraction of a millimetre (the linearisation); with the track's
    heading the offsets come out turned by the crab and leave centimetres."""
    crabbed = mission_factory(density=0.2, line_length_m=220.0, seed=41, wind_mps=WIND,
                              attitude=True, range_noise_m=0.0)
    sim = crabbed.sim
    delta = np.array([sim.biases[n] for n in PARAMETER_NAMES])
    strip, truth = sim.mission.strips[0], sim.true_xyz[0]
    worst: dict[str, float] = {}
    for mode in (HeadingSource.AUTO, HeadingSource.TRACK):
        settings = CorrectionSettings(delta=delta, heading_source=mode)
        res = correct_columns(strip.xyz, strip.t, strip.intensity, sim.mission.trajectory,
                              settings)
        worst[mode] = float(np.percentile(np.linalg.norm(res.xyz - truth, axis=1), 99))
    assert worst["auto"] < 0.001, worst
    assert worst["track"] > 0.03, worst


def test_a_stream_left_uncorrected_for_want_of_orientation_warns_now_and_then(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """Live, 'attitude' with poses that carry none leaves each cloud uncorrected (flagged):
    one warning, then silence for a while, then one that counts the clouds in between."""
    from lidarcal_ros.pipeline.correction import apply as correction

    t = np.arange(0.0, 10.0, 0.01)
    bare = Trajectory(t, np.column_stack([0 * t, 60 * t, 1000 + 0 * t]))
    pts_t = np.linspace(1.0, 2.0, 50)
    xyz = np.column_stack([np.full(50, 100.0), 60 * pts_t, np.zeros(50)])
    source = "/test/attitude_without_orientation"
    with caplog.at_level(logging.WARNING, logger="lidarcal_ros.pipeline.correction.apply"):
        for _ in range(5):
            ok, lines = correction.served_frames(pts_t, xyz, bare, source=source,
                                                 heading_source=HeadingSource.ATTITUDE)
            assert lines is None and not ok.any()
        assert len(caplog.records) == 1
        assert "'attitude' but the trajectory has no orientation" in caplog.text
        warnings = correction.UNCORRECTED_WARNINGS
        assert warnings.passed_over(source) == 4
        # as if the quiet time had passed
        monkeypatch.setattr(warnings, "clock",
                            lambda: time.monotonic() + correction.UNCORRECTED_WARNING_S)
        correction.served_frames(pts_t, xyz, bare, source=source,
                                 heading_source=HeadingSource.ATTITUDE)
    assert len(caplog.records) == 2
    assert "(and 4 more clouds since the last warning)" in caplog.records[-1].getMessage()
