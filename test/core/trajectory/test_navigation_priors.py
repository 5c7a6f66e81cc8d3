"""Each strip's trajectory-error priors from the navigation solution's own per-epoch sigmas
(an SBET's smrmsg carried by the trajectory; docs/method.md section 11), and their ties
across the flight (a Gauss-Markov process)."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest
from helpers_missions import SMALL_MISSION

from lidarcal_ros.core.calibration.calibrate import (
    CalibrationSettings,
    Calibrator,
    calibrate,
)
from lidarcal_ros.core.mission import Mission, Trajectory
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.core.trajectory.strip_errors import (
    NAVIGATION_SIGMA_FLOOR_M,
    TrajectoryErrorSettings,
    TrajectoryModel,
    TrajectoryState,
    coefficient_times,
    strip_offset_sigmas,
)

#: Each strip's navigation accuracy, m (horizontal per axis, vertical), strips in id order:
#: from a millimetre (below the floor) to 16 cm.
SIGMAS = [(0.001, 0.001), (0.01, 0.015), (0.02, 0.03), (0.04, 0.05), (0.08, 0.1),
          (0.16, 0.2)]


@cache
def _simulated() -> SimulatedMission:
    return simulate_mission(SimulationSpec.from_options(**{**SMALL_MISSION, "n_control": 0}))


def _with_errors(sim: SimulatedMission, offsets: dict[int, np.ndarray],
                 sigmas: dict[int, tuple[float, float]]) -> Mission:
    """``sim``'s mission with each strip's points and trajectory moved by its offset (m), the
    trajectory carrying each strip's sigmas while it is flown (and 1 m in the turns)."""
    mission = sim.mission
    traj = mission.trajectory
    xyz, sigma = traj.xyz.copy(), np.full((len(traj), 3), 1.0)
    strips = []
    for strip in mission.strips:
        t0, t1 = float(strip.t.min()), float(strip.t.max())
        near = (traj.t >= t0 - 2.0) & (traj.t <= t1 + 2.0)
        xyz[near] += offsets[strip.strip_id]
        h, v = sigmas[strip.strip_id]
        sigma[near] = (h, h, v)
        strips.append(replace(strip, xyz=strip.xyz + offsets[strip.strip_id]))
    moved = Trajectory(traj.t, xyz, traj.orientation, full_attitude=traj.full_attitude,
                       position_sigma=sigma)
    return Mission(moved, strips, mission.control, mission.frame_id)


def _settings(model: TrajectoryModel = TrajectoryModel.OFFSET) -> CalibrationSettings:
    return CalibrationSettings(max_candidates_per_pair=10_000, per_class_cap=500,
                               trajectory=TrajectoryErrorSettings(model))


def test_each_strip_s_prior_is_its_navigation_accuracy() -> None:
    """Six strips whose trajectory says 1 mm to 16 cm: each strip's block of the prior
    matrix is ``1 / sigma^2`` of its own sigmas (1 mm raised to the 5 mm floor); a strip
    whose samples carry no sigma keeps the configured 5 cm; a trajectory without sigmas
    gives the configured priors throughout."""
    sim = _simulated()
    ids = [s.strip_id for s in sim.mission.strips]
    sigmas = dict(zip(ids, SIGMAS, strict=True))
    mission = _with_errors(sim, {sid: np.zeros(3) for sid in ids}, sigmas)
    settings = _settings()
    cal = Calibrator.from_mission(mission, settings)
    prior = cal.trajectory.prior(settings.trajectory).toarray()
    want = np.concatenate([1.0 / np.maximum(np.array([h, h, v]), NAVIGATION_SIGMA_FLOOR_M) ** 2
                           for h, v in SIGMAS])
    np.testing.assert_allclose(np.diag(prior), want, rtol=1e-12)
    assert np.count_nonzero(prior - np.diag(np.diag(prior))) == 0
    np.testing.assert_allclose(cal.trajectory.prior_sigmas(settings.trajectory),
                               1.0 / np.sqrt(want), rtol=1e-12)
    # one strip's samples without a sigma: the configured prior for that strip alone
    assert mission.trajectory.position_sigma is not None
    no_sigma = mission.trajectory.position_sigma.copy()
    first = mission.strips[0]
    no_sigma[(mission.trajectory.t >= first.t.min() - 2.0)
             & (mission.trajectory.t <= first.t.max() + 2.0)] = np.nan
    partly = Mission(replace(mission.trajectory, position_sigma=no_sigma), mission.strips,
                     None, mission.frame_id)
    prior = np.diag(Calibrator.from_mission(partly, settings).trajectory.prior(
        settings.trajectory).toarray())
    np.testing.assert_allclose(prior[:3], 1.0 / settings.trajectory.offset_sigmas ** 2)
    np.testing.assert_allclose(prior[3:], want[3:])
    plain = Calibrator.from_mission(sim.mission, settings)
    np.testing.assert_allclose(np.diag(plain.trajectory.prior(settings.trajectory).toarray()),
                               np.tile(1.0 / settings.trajectory.offset_sigmas ** 2, len(ids)))


@pytest.mark.parametrize("model", [TrajectoryModel.DRIFT, TrajectoryModel.SPLINE],
                         ids=["drift", "spline"])
def test_drift_and_spline_take_the_strip_s_offset_sigmas(model: TrajectoryModel) -> None:
    """The drift model's offsets and a spline's coefficients take the strip's sigmas; the
    drift rate and the spline's steps keep the configured drift sigma."""
    sim = _simulated()
    ids = [s.strip_id for s in sim.mission.strips]
    mission = _with_errors(sim, {sid: np.zeros(3) for sid in ids},
                           dict(zip(ids, SIGMAS, strict=True)))
    settings = _settings(model)
    state = Calibrator.from_mission(mission, settings).trajectory
    for k, (h, v) in enumerate(SIGMAS):
        basis = state.bases[k]
        sig = np.maximum(np.array([h, h, v]), NAVIGATION_SIGMA_FLOOR_M)
        np.testing.assert_allclose(basis.offset_sigmas(settings.trajectory), sig)
        block = basis.prior(settings.trajectory).toarray()
        if model is TrajectoryModel.DRIFT:
            np.testing.assert_allclose(np.diag(block), np.concatenate(
                [1.0 / sig ** 2, np.full(3, settings.trajectory.drift_sigma_m_per_s ** -2)]))
        else:  # (first and last coefficient: the offset prior plus one random-walk step)
            step = settings.trajectory.drift_sigma_m_per_s * settings.trajectory.knot_interval_s
            np.testing.assert_allclose(np.diag(block)[:3], 1.0 / sig ** 2 + 1.0 / step ** 2)


def test_strip_offset_sigmas_is_the_rms_over_the_span() -> None:
    """Horizontal ``sqrt(mean((s_E^2 + s_N^2) / 2))``, vertical ``sqrt(mean(s_U^2))`` over
    the samples in the span; the mid-time interpolation where none falls in it; NaN for a
    component no sample has; None without sigmas."""
    t = np.arange(10.0)
    sigma = np.column_stack([np.full(10, 0.03), np.full(10, 0.04), np.arange(10) * 0.01])
    traj = Trajectory(t, np.zeros((10, 3)), position_sigma=sigma)
    got = strip_offset_sigmas(traj, 2.0, 4.0)
    assert got is not None
    h = np.sqrt((0.03 ** 2 + 0.04 ** 2) / 2)
    np.testing.assert_allclose(got, [h, h, np.sqrt(np.mean([0.02 ** 2, 0.03 ** 2,
                                                            0.04 ** 2]))])
    between = strip_offset_sigmas(traj, 4.2, 4.8)  # (no sample inside: at 4.5 s)
    assert between is not None
    np.testing.assert_allclose(between[2], 0.045)
    sigma[:, 2] = np.nan
    got = strip_offset_sigmas(Trajectory(t, np.zeros((10, 3)), position_sigma=sigma), 0, 9)
    assert got is not None and np.isnan(got[2]) and got[0] == pytest.approx(h)
    assert strip_offset_sigmas(Trajectory(t, np.zeros((10, 3))), 0.0, 9.0) is None


def test_a_trusted_strip_anchors_the_others() -> None:
    """Without control the strips' common shift rests on the priors alone. Five strips off by
    8 cm vertically and one exact strip whose trajectory says 5 mm (the others 10 cm): the
    estimated offsets follow the truth within 1.5 cm; with the configured 5 cm for every
    strip the same mission splits the shift between the strips and the biases (off by 3 cm
    or more)."""
    sim = _simulated()
    ids = [s.strip_id for s in sim.mission.strips]
    offsets = {sid: np.array([0.0, 0.0, 0.0 if sid == ids[0] else 0.08]) for sid in ids}
    sigmas = {sid: (0.005, 0.005) if sid == ids[0] else (0.1, 0.1) for sid in ids}
    mission = _with_errors(sim, offsets, sigmas)
    settings = _settings()
    told = calibrate(mission, settings)
    assert told.trajectory is not None
    plain = Mission(replace(mission.trajectory, position_sigma=None), mission.strips, None,
                    mission.frame_id)
    configured = calibrate(plain, settings)
    assert configured.trajectory is not None

    def worst(result: object) -> float:
        est = result.trajectory.strips  # type: ignore[attr-defined]
        return max(abs(est[sid].offset[2] - offsets[sid][2]) for sid in ids)

    assert worst(told) < 0.015, worst(told)
    assert worst(configured) > 0.03, worst(configured)


@pytest.mark.parametrize("model", [TrajectoryModel.OFFSET, TrajectoryModel.DRIFT,
                                   TrajectoryModel.SPLINE], ids=["offset", "drift", "spline"])
def test_the_gauss_markov_prior_is_the_process_s_covariance(model: TrajectoryModel) -> None:
    """With ``correlation_s`` the offset-like coefficients of all strips are one first-order
    Gauss-Markov process per axis: the prior's inverse is ``s_i s_j exp(-|t_i - t_j| / tau)``
    at their times (a spline's Greville abscissae), each strip's sigmas its own; a drift's
    rate keeps its own sigma and no tie; strips an hour apart are independent, as without
    ``correlation_s``."""
    state = TrajectoryState(model, 7.0)
    state.add_strip(0.0, 25.0)
    state.add_strip(40.0, 61.0, navigation_sigmas=np.array([0.01, 0.01, 0.04]))
    state.add_strip(3700.0, 3730.0)
    settings = TrajectoryErrorSettings(model, 0.02, 0.03, knot_interval_s=7.0,
                                       correlation_s=30.0)
    prior = state.prior(settings).toarray()
    times = np.repeat(np.concatenate([coefficient_times(b) for b in state.bases]), 3)
    axes = np.tile(np.arange(3), times.size // 3)
    sigmas = state.prior_sigmas(settings)
    rate = ~np.isfinite(times)
    with np.errstate(invalid="ignore"):
        want = np.where(axes[:, None] == axes[None, :], np.outer(sigmas, sigmas)
                        * np.exp(-np.abs(times[:, None] - times[None, :]) / 30.0), 0.0)
    want[rate] = 0.0
    want[:, rate] = 0.0
    want[rate, rate] = settings.drift_sigma_m_per_s ** 2
    np.testing.assert_allclose(np.linalg.inv(prior), want, atol=1e-9 * want.max())
    assert rate.any() == (model is TrajectoryModel.DRIFT)
    last = state.starts[2]
    assert np.abs(np.linalg.inv(prior)[:last, last:]).max() < 1e-12
    independent = state.prior(replace(settings, correlation_s=0.0)).toarray()
    np.testing.assert_allclose(independent[last:, last:],
                               state.bases[2].prior(settings).toarray())
    assert np.count_nonzero(independent[:last, last:]) == 0


def test_a_shared_time_ties_two_strips_by_a_hundredth_of_the_sigma() -> None:
    """Two strips flown at once (two scanners on one INS) have coefficients at one time: the
    prior ties them with a sigma of a hundredth of the process's (no infinite weight)."""
    state = TrajectoryState(TrajectoryModel.OFFSET)
    state.add_strip(0.0, 20.0)
    state.add_strip(0.0, 20.0)
    settings = TrajectoryErrorSettings(TrajectoryModel.OFFSET, 0.02, 0.02, correlation_s=30.0)
    covariance = np.linalg.inv(state.prior(settings).toarray())
    difference = covariance[0, 0] + covariance[3, 3] - 2.0 * covariance[0, 3]
    assert np.sqrt(difference) == pytest.approx(0.02 * 0.01, rel=0.02)
    assert np.sqrt(covariance[0, 0]) == pytest.approx(0.02, rel=1e-6)
