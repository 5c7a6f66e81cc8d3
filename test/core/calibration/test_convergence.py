"""An adjustment whose matching oscillates converges within the re-matching noise, or ends
saying why (calibration_iteration.judge_convergence).

- The re-matching noise (:func:`rematching_noise`) is the spread of the step that swapping
  correspondences produces: checked against the steps of many random swaps.
- :class:`MatchedSet` counts the correspondences that entered or left (a point matched to
  another patch does both).
- The rule on step sequences: contracting steps go on; steps that stopped shrinking within
  the noise converge (up to a sigma) or end not converged (beyond); steps beyond the noise go
  on.
- A simulated mission whose matching flips between two sets for ever (0.15 sigma each way,
  which the old rule ran to ``max_iterations`` without converging) converges within the
  re-matching noise in five iterations, near its truth, with the outcome in the summary and
  the calibration file, exit status 0.
- The real forest tile (lidR's Megaplot.laz), patches loosened so it matches, converges with
  its outcome stated.
"""

from __future__ import annotations

from pathlib import Path

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_cli import run
from helpers_las import real_las_file
from helpers_missions import write_params_file

from lidarcal_ros.core.adjustment.least_squares import NormalEquations, Observations, solve
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Calibrator, calibrate
from lidarcal_ros.core.calibration.iteration import (
    NOISE_Z,
    Iteration,
    MatchedSet,
    judge_convergence,
    rematching_noise,
)
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec

mission_factory = helpers_missions.mission_factory

SOLVE = ("dX", "dY", "domega", "dphi", "dkappa")
#: A paper mission with forest-like range noise (30 cm) and ten correspondences per class:
#: from the fourth iteration on its matching flips between two sets, moving dphi by
#: 0.15 sigma each way.
OSCILLATING = {"scenario": "paper", "density": 0.1, "line_length_m": 250.0, "seed": 1,
               "range_noise_m": 0.3}
OSCILLATING_SETTINGS = {"matching.max_candidates_per_pair": 10_000,
                        "matching.per_class_cap": 10}


# ---------------------------------------------------------------------------- noise
def _solution(rows: np.ndarray, y: np.ndarray, estimated: tuple[str, ...]):
    obs = Observations(rows, y, np.ones(len(y)), np.zeros(len(y), np.int64),
                       np.arange(len(y)))
    return solve(NormalEquations.from_observations(obs), solve_for=estimated, fixed={})


def test_rematching_noise_is_the_spread_of_steps_from_swapped_correspondences() -> None:
    """Solve with 400 observations, then with 8 of them swapped for 8 others (known
    sigma0 0.05; a change small beside the normal equations, as between matchings): over 400
    draws, the steps' standard deviation per parameter is the
    predicted re-matching noise to 10% (the swapped-in rows carry dY twice as strongly);
    nothing changed, no noise."""
    rng = np.random.default_rng(3)
    estimated = ("dX", "dY", "dr")
    idx = [PARAMETER_NAMES.index(n) for n in estimated]
    n, m = 400, 8
    pool = np.zeros((n + m, N_PARAMETERS))
    pool[:, idx] = rng.normal(size=(n + m, 3)) * (1.0, 0.5, 2.0)
    pool[n:, idx[1]] *= 2.0  # the swapped-in rows carry dY strongly
    steps = []
    for _ in range(400):
        y = rng.normal(scale=0.05, size=n + m)
        keep = np.ones(n + m, bool)
        keep[n:] = False
        before = _solution(pool[keep], y[keep], estimated)
        keep[:m] = False
        keep[n:] = True
        after = _solution(pool[keep], y[keep], estimated)
        steps.append(after.delta - before.delta)
    sol = _solution(pool[m:], np.random.default_rng(4).normal(scale=0.05, size=n), estimated)
    changed = np.concatenate([pool[:m], pool[n:]])
    noise = rematching_noise(sol, changed.T @ changed)
    spread = np.std(np.array(steps), axis=0)
    assert np.allclose(spread[idx], noise[idx], rtol=0.1), (spread[idx], noise[idx])
    assert np.isnan(noise[PARAMETER_NAMES.index("domega")])
    assert np.all(rematching_noise(sol, np.zeros((N_PARAMETERS,) * 2))[idx] == 0.0)


def test_matched_set_counts_entered_left_and_moved_correspondences() -> None:
    """Pair 0: sample points 0-4 matched to patches 10-14; next time point 1 is gone, point
    2 matched another patch, point 5 entered and point 3 was rejected by the robust weights;
    pair 1 left entirely. 1 + 2 + 1 + 1 + 2 (pair 1) = 7 changed, and the matrix is the
    sum of their rows' outer products."""
    def set_of(patches: dict[int, list[int]], rejected: dict[int, list[int]]) -> MatchedSet:
        layout, parts, start = [], [], 0
        for pair, tri in patches.items():
            tri_a = np.array(tri)
            k = int((tri_a >= 0).sum())
            rows = np.zeros((k, N_PARAMETERS))
            rows[:, 0] = 100 * pair + tri_a[tri_a >= 0]  # (a row told apart by its patch)
            w = np.ones(k)
            w[rejected.get(pair, [])] = 0.0
            parts.append(Observations(rows, np.zeros(k), w, np.full(k, pair), np.zeros(k, int)))
            layout.append((pair, start, tri_a))
            start += k
        return MatchedSet.of(Observations.concatenate(parts), layout)

    before = set_of({0: [10, 11, 12, 13, 14, -1], 1: [1, 2]}, {})
    after = set_of({0: [10, -1, 22, 13, 14, 15]}, {0: [2]})  # row 2: point 3's
    n, normal = after.changes(before)
    assert n == 7
    moved = np.array([22.0, 15.0, 11.0, 12.0, 13.0, 101.0, 102.0])
    assert normal[0, 0] == pytest.approx(float(np.sum(moved**2)))
    assert after.changes(after)[0] == 0


# ---------------------------------------------------------------------------- the rule
def _judge(step_sigmas: list[float], noise_sigmas: list[float], fraction: float = 0.01):
    """The verdict on iterations whose dphi steps are ``step_sigmas`` (alternating in sign,
    sigma 1) with re-matching noises ``noise_sigmas`` (the first iteration's NaN)."""
    sigma = np.full(N_PARAMETERS, np.nan)
    sigma[PARAMETER_NAMES.index("dphi")] = 1.0
    steps, noises, history = [], [], []
    x = np.zeros(N_PARAMETERS)
    for k, (s, nz) in enumerate(zip(step_sigmas, noise_sigmas, strict=True)):
        step = np.zeros(N_PARAMETERS)
        step[PARAMETER_NAMES.index("dphi")] = s * (-1) ** k
        x = x + step
        noise = np.where(np.isfinite(sigma), nz, np.nan)
        steps.append(step)
        noises.append(noise)
        history.append(x.copy())
    return judge_convergence(history, steps, [sigma] * len(steps), noises,
                             [4] * len(steps), fraction)


def test_contracting_steps_go_on_until_below_the_fraction() -> None:
    """Steps shrinking by 4 each time are progress even within the noise; they converge the
    usual way, below 0.01 sigma."""
    nan = float("nan")
    going = _judge([30, 0.8, 0.2, 0.05], [nan, 1.0, 1.0, 1.0])
    assert not going.converged and not going.ended
    assert going.outcome == "not converged: its last step moved dphi by 0.05 sigma; 4 " \
        "correspondences changed at the last matching, which moves dphi by 1 sigma (one " \
        "standard deviation)"
    done = _judge([30, 0.8, 0.2, 0.05, 0.005], [nan, 1.0, 1.0, 1.0, 1.0])
    assert done.converged and done.ended
    assert done.outcome == "converged: every step below 0.01 sigma"


def test_steps_that_stopped_shrinking_within_the_noise_converge_there() -> None:
    """0.15-sigma steps back and forth, re-matching noise 0.07 sigma: converged within the
    re-matching noise at the fourth iteration (the last step no smaller than half the one
    two before), the figures stated; at the third, the steps were still shrinking."""
    nan = float("nan")
    assert not _judge([20, 0.25, 0.14], [nan, 0.2, 0.07]).ended
    verdict = _judge([20, 0.25, 0.14, 0.15], [nan, 0.2, 0.07, 0.07])
    assert verdict.converged and verdict.ended
    assert verdict.outcome.startswith(
        "converged within the re-matching noise: the last two steps (up to 0.15 sigma) "
        "stopped shrinking and are what re-matching alone moves the estimate by: 4 "
        "correspondences changed at the last matching, which moves dphi by 0.07 sigma")
    # one step more than NOISE_Z noises: the matching does not explain it; go on
    beyond = _judge([20, 0.25, 0.14, 0.15], [nan, 0.2, 0.07, 0.15 / (NOISE_Z + 0.1)])
    assert not beyond.ended and not beyond.converged
    # steps of 0.15 sigma with a noise of 0.001 sigma: an oscillation the matching does not
    # explain is no convergence
    assert not _judge([20, 0.15, 0.15, 0.15, 0.15], [nan] + [0.001] * 4).ended


def test_steps_beyond_a_sigma_within_the_noise_end_not_converged() -> None:
    """1.5-sigma steps back and forth that re-matching explains (noise 0.8 sigma): more
    iterations cannot converge it, so it ends at once, not converged, saying so."""
    nan = float("nan")
    verdict = _judge([20, 2.0, 1.4, 1.5], [nan, 1.0, 0.8, 0.8])
    assert verdict.ended and not verdict.converged
    assert verdict.outcome.startswith("not converged, and more iterations will not converge "
                                      "it: the last two steps (up to 1.5 sigma) stopped "
                                      "shrinking")
    assert verdict.outcome.endswith("the matching determines the estimate to about 1.5 "
                                    "sigma only")


# ---------------------------------------------------------------------------- a mission
@pytest.fixture(scope="module")
def oscillating() -> SimulatedMission:
    return simulate_mission(SimulationSpec.from_options(**OSCILLATING))


def test_a_mission_oscillating_between_two_matchings_converges_within_the_noise(
        oscillating: SimulatedMission) -> None:
    """The matching flips between two sets from the fourth iteration (4 correspondences,
    dphi back and forth by 0.15 sigma): twenty iterations never converge by the steps alone;
    the rule ends it at the fifth, converged within the re-matching noise, dphi (all so few
    correspondences determine) within 3 sigma of its truth."""
    settings = CalibrationSettings(solve_for=SOLVE, max_candidates_per_pair=10_000,
                                   per_class_cap=10, max_iterations=20)
    cal = Calibrator.from_mission(oscillating.mission, settings)
    ratios = []
    done: Iteration | None = None
    with cal.workers.threads():
        for item in cal.iterate():
            if item is None:
                continue
            done = item
            est = np.isfinite(done.solution.sigma)
            ratios.append(float(np.max(np.abs(done.step[est]) / done.solution.sigma[est])))
            if done.ended or done.number == 12:
                break
    assert done is not None
    assert done.number == 5 and done.converged and done.ended
    assert done.outcome.startswith("converged within the re-matching noise")
    assert 0.1 < ratios[-1] < 0.2 and ratios[-1] > 0.5 * ratios[-3]  # not shrinking

    result = calibrate(oscillating.mission, settings)
    assert result.converged and result.iterations == 5
    assert result.convergence == done.outcome
    sol = result.solution
    assert "dphi" in sol.estimated  # (the others too weakly determined by so few)
    for name in sol.estimated:
        i = PARAMETER_NAMES.index(name)
        assert abs(sol.delta[i] - oscillating.biases[name]) < 3 * sol.sigma[i], name


def test_cli_states_convergence_within_the_noise_and_exits_0(capsys, tmp_path,
                                                             mission_factory) -> None:
    """``lidarcal calibrate`` of the oscillating mission: exit 0, the summary says
    "converged within the re-matching noise" with a ``convergence:`` line, and the file
    carries ``converged: true`` and the same words under ``convergence``."""
    files = mission_factory(**OSCILLATING)
    config = write_params_file(tmp_path / "osc.yaml", OSCILLATING_SETTINGS)
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", files.bag, "-o", cal, "--config", config,
                       "--solve-for", ",".join(SOLVE), "--quiet")
    assert rc == 0, err
    assert ", 5 iterations, converged within the re-matching noise; " in out
    (line,) = [ln for ln in out.splitlines() if ln.startswith("convergence: ")]
    doc = yaml.safe_load(cal.read_text())["lidarcal_calibration"]
    assert doc["converged"] is True
    assert line == f"convergence: {doc['convergence']}"
    assert doc["convergence"].startswith("converged within the re-matching noise: ")


def test_plainly_converged_file_says_how_and_the_summary_adds_no_line(
        capsys, tmp_path, small_mission) -> None:
    """A mission that converges the usual way: no ``convergence:`` line in the summary, the
    file says ``converged: every step below 0.01 sigma``."""
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", small_mission.bag, "-o", cal, "--config",
                       small_mission.fast_config, "--quiet")
    assert rc == 0, err
    assert not [ln for ln in out.splitlines() if ln.startswith("convergence: ")]
    doc = yaml.safe_load(cal.read_text())["lidarcal_calibration"]
    assert doc["convergence"] == "converged: every step below 0.01 sigma"


small_mission = helpers_missions.small_mission


# ---------------------------------------------------------------------------- real tile
def test_real_megaplot_forest_converges_with_its_outcome_stated(capsys, tmp_path) -> None:
    """The lidR sample Megaplot.laz (two forest passes, trajectory rebuilt from multiple returns):
    with patches loosened until the canopy matches (bends to 60 deg, edges of 12 spacings,
    3 m), calibrate ends with exit status 0 and a stated outcome in fewer than the ten
    iterations the steps alone needed."""
    path = real_las_file("Megaplot.laz")
    bag = tmp_path / "bag"
    rc, _, err = run(capsys, "import", path, "--trajectory", "estimate", "-o", bag)
    assert rc == 0, err
    config = write_params_file(tmp_path / "loose.yaml", {
        "matching.max_bend_deg": 60.0, "matching.max_edge_factor": 12.0,
        "matching.max_slope_deg": 85.0, "matching.max_normal_distance_m": 3.0})
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--config", config, "--solve-for",
                       "domega,dphi,dkappa", "--quiet")
    assert rc == 0, err
    assert " iterations, converged" in out
    doc = yaml.safe_load(Path(cal).read_text())["lidarcal_calibration"]
    assert doc["converged"] is True and doc["iterations"] < 10
    assert doc["convergence"].startswith("converged")
    assert doc["biases"]["dphi"]["estimated"] is True
