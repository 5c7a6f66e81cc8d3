"""The paper's accuracy measures (``lidarcal evaluate``): point-to-patch ICP between strips
(Table 3) against known rigid transformations, and check-point residuals (Table 4) on a
simulated mission before and after its true biases are removed."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_missions import write_calibration_yaml

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.calibration.tin import Tin, TinQuality
from lidarcal_ros.core.georeferencing.bias_model import boresight_matrix
from lidarcal_ros.core.params import as_vector
from lidarcal_ros.core.qa.accuracy import AccuracySummary, rigid_icp, tin_heights
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.pipeline.evaluation import Evaluation, evaluate_mission

mission_factory = helpers_missions.mission_factory

ARCSEC = math.pi / 180.0 / 3600.0
#: A mission with three surveyed points (one would serve as control; here all are checks).
MISSION = {"scenario": "paper", "density": 0.2, "line_length_m": 250.0, "seed": 11,
           "n_control": 3}


def _hills(xy: np.ndarray) -> np.ndarray:
    """A surface with slopes of every aspect (m): gable-like ridges and a dome."""
    x, y = xy[:, 0], xy[:, 1]
    return (8.0 * np.abs(np.sin(x / 23.0)) + 6.0 * np.abs(np.cos(y / 17.0))
            + 0.002 * (x - 40.0) ** 2 - 0.001 * x * y)


def _sample(rng: np.random.Generator, n: int, surface: Any, noise: float) -> np.ndarray:
    xy = rng.uniform(0.0, 200.0, (n, 2))
    return np.column_stack([xy, surface(xy) + rng.normal(0.0, noise, n)])


def _tin(xyz: np.ndarray) -> Tin:
    return Tin(xyz, TinQuality(max_edge_m=6.0))


def test_icp_recovers_a_known_rigid_transformation() -> None:
    """Strip a is strip b's surface moved by 30/-20/10 cm and 60/-90/40 arcsec: the fit
    moves a's points back onto the surface and its angles undo the rotation."""
    rng = np.random.default_rng(3)
    b = _sample(rng, 60_000, _hills, 0.01)
    a_true = _sample(rng, 40_000, _hills, 0.01)
    c0 = a_true.mean(axis=0)
    rot0 = boresight_matrix(60 * ARCSEC, -90 * ARCSEC, 40 * ARCSEC)
    t0 = np.array([0.30, -0.20, 0.10])
    a = (a_true - c0) @ rot0.T + c0 + t0
    fit = rigid_icp(a, _tin(b), b, max_normal_distance=2.0)
    assert fit is not None and fit.converged and fit.determined.all()
    rot = boresight_matrix(*fit.values[3:])
    back = (a - fit.centroid) @ rot.T + fit.centroid + fit.values[:3]
    assert np.max(np.abs(back - a_true)) < 0.01  # m
    np.testing.assert_allclose(fit.values[3:] / ARCSEC, [-60.0, 90.0, -40.0], atol=2.0)
    assert fit.rms_before > 0.05 and fit.rms_after < 0.02
    # Sigmas describe the noise: a centimetre of it over 40 000 points.
    assert np.all(fit.sigmas[:3] < 0.005) and np.all(fit.sigmas[3:] < 5 * ARCSEC)


def test_icp_over_flat_ground_says_what_it_cannot_see() -> None:
    """A tilted plane without relief: the horizontal shifts and the rotation about the
    vertical are undetermined (reported, not zero); the height and tilts are found."""
    rng = np.random.default_rng(4)

    def plane(xy: np.ndarray) -> np.ndarray:
        return 0.01 * xy[:, 0] + 0.02 * xy[:, 1]

    b = _sample(rng, 30_000, plane, 0.01)
    a = _sample(rng, 20_000, plane, 0.01) + np.array([0.5, 0.5, 0.2])
    fit = rigid_icp(a, _tin(b), b, max_normal_distance=2.0)
    assert fit is not None
    assert fit.determined.tolist() == [False, False, True, True, True, False]
    assert all(math.isnan(fit.values[i]) for i in (0, 1, 5))
    # Along the vertical the pair differs by 0.2 m plus the plane's rise over 0.5/0.5 m.
    assert fit.values[2] == pytest.approx(-(0.2 - 0.01 * 0.5 - 0.02 * 0.5), abs=0.005)
    assert fit.as_dict()["tx"] is None


def test_icp_without_overlap_returns_none() -> None:
    rng = np.random.default_rng(5)
    b = _sample(rng, 5_000, _hills, 0.01)
    a = b + np.array([1000.0, 0.0, 0.0])
    assert rigid_icp(a, _tin(b), b, max_normal_distance=2.0) is None


def test_tin_heights_interpolate_the_surface() -> None:
    rng = np.random.default_rng(6)

    def plane(xy: np.ndarray) -> np.ndarray:
        return 100.0 + 0.1 * xy[:, 0] - 0.05 * xy[:, 1]

    pts = _sample(rng, 20_000, plane, 0.0)
    q = np.array([[50.0, 60.0], [150.5, 20.25], [500.0, 500.0]])
    h = tin_heights(_tin(pts), pts, q)
    np.testing.assert_allclose(h[:2], plane(q[:2]), atol=1e-9)
    assert math.isnan(h[2])
    s = AccuracySummary.of(np.array([0.03, -0.01, np.nan, 0.02]))
    assert s.n == 3 and s.rmse == pytest.approx(math.sqrt((9 + 1 + 4) / 3) / 100)


@pytest.fixture(scope="module")
def evaluated(mission_factory: Any) -> dict[str, Any]:
    files = mission_factory(**MISSION)
    settings = CalibrationSettings()
    ev = evaluate_mission(files.sim.mission, as_vector(files.sim.biases), settings,
                          check_points=files.sim.mission.control, max_points_per_pair=20_000)
    return {"files": files, "ev": ev}


def test_pairs_align_after_the_true_correction(evaluated: dict[str, Any]) -> None:
    """Table 3 on a mission with the paper's biases: opposite strips are offset by
    decimetres and tilted by twice dphi before; after removing the true biases every
    determined shift is below 1 cm and every rotation below 10 arcsec."""
    ev = evaluated["ev"]
    sim = evaluated["files"].sim
    assert len(ev.pairs) >= 10
    dphi = sim.biases["dphi"]
    opposite = 0
    for p in ev.pairs:
        assert p.before is not None and p.after is not None
        after = p.after
        shifts = np.abs(after.values[:3][after.determined[:3]])
        angles = np.abs(after.values[3:][after.determined[3:]]) / ARCSEC
        assert np.all(shifts < 0.01), (p.strip_a, p.strip_b, after.values)
        assert np.all(angles < 10.0), (p.strip_a, p.strip_b, angles)
        assert after.rms_before < p.before.rms_before + 1e-9
        before_phi = p.before.values[4]
        if abs(before_phi) > abs(dphi):  # flown in opposite directions
            opposite += 1
            assert abs(before_phi) == pytest.approx(2 * abs(dphi), rel=0.15)
            assert np.nanmax(np.abs(p.before.values[:2])) > 0.10
    assert opposite >= 4


def test_check_points_before_and_after(evaluated: dict[str, Any]) -> None:
    """Table 4: the surveyed points lie on the true surface; before correction the strips
    are off by the range and lever-arm biases, after it by the noise."""
    ev = evaluated["ev"]
    assert len(ev.check_points) == 3
    assert all(c.strips for c in ev.check_points)
    before, after = ev.summary("before"), ev.summary("after")
    assert before.n == after.n == 3
    assert before.rmse > 0.05
    assert after.rmse < 0.02
    assert after.rmse < before.rmse / 4


def test_cli_evaluate_json_and_text(evaluated: dict[str, Any], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    files = evaluated["files"]
    cal = write_calibration_yaml(tmp_path / "cal.yaml", files.sim.biases)
    args = ["evaluate", str(files.bag), "--calibration", str(cal),
            "--check-points", str(files.control_csv), "--max-points", "5000"]
    assert main([*args, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {"pairs", "check_points"} <= set(doc)
    first = doc["pairs"][0]
    assert set(first["after"]["values"]) == {"tx", "ty", "tz", "omega", "phi", "kappa"}
    assert doc["check_points"]["after"]["rmse"] < 0.02
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "relative accuracy" in text and "absolute accuracy" in text and "RMSE" in text


def test_json_reads_back_with_the_biases_evaluated(evaluated: dict[str, Any]) -> None:
    """``--json`` names the biases it evaluated, and reads back into the same tables (what
    ``lidarcal report --evaluation`` shows)."""
    ev = evaluated["ev"]
    doc = json.loads(json.dumps(ev.as_dict()))
    assert doc["biases"] == pytest.approx(evaluated["files"].sim.biases)
    back = Evaluation.from_dict(doc)
    assert back.delta is not None and np.array_equal(back.delta, ev.delta)
    assert back.as_dict() == ev.as_dict()
    with pytest.raises(ConfigError, match=r"x\.json: not an evaluation"):
        Evaluation.from_dict({"pairs": [{"strips": [1, 2]}]}, source="x.json")


def test_cli_evaluate_bad_input_one_line(evaluated: dict[str, Any], tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    files = evaluated["files"]
    bad = tmp_path / "cp.csv"
    bad.write_text("id,x,y\n1,2,3\n")
    cal = tmp_path / "cal.yaml"
    cal.write_text("lidarcal_calibration: {}\n")
    for args in (["--calibration", str(cal)],
                 ["--calibration", str(files.truth)],
                 ["--calibration", str(cal), "--check-points", str(bad)]):
        rc = main(["evaluate", str(files.bag), *args])
        err = capsys.readouterr().err.strip()
        assert rc != 0 and err.count("\n") == 0 and "error" in err, err
