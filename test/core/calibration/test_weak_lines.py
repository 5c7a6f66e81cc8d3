"""Weak data kept and reported rather than dropped or refused without a word.

- A flight line whose multiple returns rebuild its sensor path poorly (few of them, or a fan
  of rays a few degrees wide: the tile holds one edge of the swath) keeps its points, with a
  level-flight trajectory at the altitude of the lines rebuilt well and its sigma stated.
- ``lidarcal calibrate`` that can estimate nothing (one strip, no overlap, nothing
  observable, no usable patches) still prints how well the strips agree as delivered, and
  with ``--write-identity`` writes a calibration that moves no point, which ``lidarcal
  correct`` accepts.
- Trajectory poses with non-finite positions, or at stamps repeated at other positions, are
  left out and counted in one warning line.

Synthetic cases have known truth; the real case (lidR's Megaplot.laz: a forest tile, two
passes, heights above ground, one pass holding one edge of its swath) runs when the file is
available (``$LIDARCAL_REAL_LAS_DIR`` or ``shared/data/las``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_cli import run
from helpers_las import add_first_returns, real_las_file, write_las_tiles
from helpers_missions import shift_strip, subset, without_control

from lidarcal_ros.cli.exit_status import EXIT_NOTHING_ESTIMATED
from lidarcal_ros.core.calibration.calibrate import Calibrator
from lidarcal_ros.core.mission import Mission, Trajectory
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.core.trajectory.estimation import EstimateSettings
from lidarcal_ros.core.trajectory.segments import SegmentModel
from lidarcal_ros.io.bag.mission_bag import read_mission, write_mission_bag
from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.pipeline.importing.importer import import_mission
from lidarcal_ros.pipeline.importing.options import ImportOptions, Returns

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

ORIGIN = (500_000.0, 5_000_000.0)


def calibration_body(path: Path) -> dict[str, Any]:
    body = yaml.safe_load(path.read_text())["lidarcal_calibration"]
    assert isinstance(body, dict)
    return body


# ---------------------------------------------------------------------------- weak lines
@pytest.fixture(scope="module")
def three_lines() -> SimulatedMission:
    """Three parallel lines at 1150 m, 350 m apart (each overlaps the next by two thirds)."""
    lines = [{"id": i + 1, "start": (x, -125.0), "end": (x, 125.0), "height": 1150.0}
             for i, x in enumerate((-350.0, 0.0, 350.0))]
    return simulate_mission(SimulationSpec.from_options(lines=lines, density=0.05, seed=3,
                                                        origin=ORIGIN))


def _position_error(traj: Trajectory, truth: Trajectory, t0: float, t1: float) -> np.ndarray:
    """Largest |error| per coordinate of ``traj`` against ``truth`` over ``[t0, t1]``."""
    sel = (traj.t >= t0) & (traj.t <= t1)
    at = np.column_stack([np.interp(traj.t[sel], truth.t, truth.xyz[:, i]) for i in range(3)])
    return np.abs(traj.xyz[sel] - at).max(axis=0)


def test_weak_line_on_one_edge_of_its_swath_is_kept(three_lines, tmp_path) -> None:
    """Strip 3's multiple returns all lie 13-16 deg off nadir (a 3 deg fan): its rays alone
    put the sensor's height nowhere (sigma far over 5 m), so it used to be left out. It is
    kept, flying level at the altitude of strips 1 and 2, its sigma stated, and the rays then
    place it where it flew."""
    strips = add_first_returns(three_lines, fraction=0.3, seed=4, scan_band_deg={3: (13, 16)})
    tiles = write_las_tiles(strips, tmp_path, tiles=(1, 1), laz=())
    report = import_mission(tiles, tmp_path / "bag",
                            ImportOptions(trajectory="estimate", returns=Returns.LAST))
    est = report.estimate
    assert est is not None and not est.failed_strips
    assert [s.strip_id for s in report.strips] == [1, 2, 3]
    assert read_mission(tmp_path / "bag").n_points == three_lines.mission.n_points
    by_id = {s.strip_id: s for s in est.strips}
    assert not by_id[1].fallback and not by_id[2].fallback
    weak = by_id[3]
    assert weak.kept and weak.fallback and weak.sigma_m > 5.0
    assert weak.summary.startswith(f"strip 3: position sigma {weak.sigma_m:.1f} m (")
    assert " m horizontally; weak: " in weak.summary
    assert "deg across the track" in weak.summary
    assert "kept, level flight at the altitude of strips 1 and 2, 1150 +- " in weak.summary
    assert f"    {weak.summary}" in report.lines()
    (q,) = [q for q in est.segments if q.strip_id == 3]
    assert q.level == "WARN" and q.weak and q.model is SegmentModel.LEVEL
    assert q.altitude_from == (1, 2)
    assert q.fan_deg < 4.0
    t0, t1 = report.strips[2].t_first, report.strips[2].t_last
    error = _position_error(est.trajectory, three_lines.mission.trajectory, t0, t1)
    assert error.max() < 1.0, error  # the right altitude, and the rays do the rest
    assert error.max() < weak.sigma_m

    # Not allowed a sigma that large, the line is left out and the report says why.
    report = import_mission(tiles, tmp_path / "strict", ImportOptions(
        trajectory="estimate", returns=Returns.LAST,
        estimate=EstimateSettings(max_weak_fraction=0.01)))
    assert report.dropped_strips == [3]
    assert report.estimate is not None
    (left_out,) = [s for s in report.estimate.strips if not s.kept]
    assert left_out.summary.startswith("strip 3: left out, no trajectory could be rebuilt (")
    assert "over 1% of the height" in left_out.summary


def test_weak_line_flown_at_another_altitude_keeps_its_own(tmp_path) -> None:
    """Few multiple returns on strip 3 (20 rays, across the whole fan), flown at 700 m where
    strips 1 and 2 fly at 1150 m: its own rays fix its height, which disagrees with theirs,
    and it is kept at its own, saying so."""
    lines = [{"id": i + 1, "start": (x, -125.0), "end": (x, 125.0), "height": h}
             for i, (x, h) in enumerate(((-300.0, 1150.0), (0.0, 1150.0), (300.0, 700.0)))]
    sim = simulate_mission(SimulationSpec.from_options(lines=lines, density=0.05, seed=5,
                                                       origin=ORIGIN))
    strips = add_first_returns(sim, fraction=0.3, seed=6)
    third = strips[2]
    first = np.flatnonzero((third["return_number"] == 1) & (third["number_of_returns"] == 2))
    drop = np.random.default_rng(0).permutation(first)[20:]
    strips[2] = {key: np.delete(v, drop, axis=0) for key, v in third.items()}
    tiles = write_las_tiles(strips, tmp_path, tiles=(1, 1), laz=())
    report = import_mission(tiles, tmp_path / "bag",
                            ImportOptions(trajectory="estimate", returns=Returns.LAST))
    est = report.estimate
    assert est is not None and not est.failed_strips
    weak = {s.strip_id: s for s in est.strips}[3]
    assert weak.kept and weak.fallback
    assert "few multiple returns, 20 rays" in weak.summary
    assert "kept, level flight at the altitude of its own rays" in weak.summary
    assert "(strips 1 and 2 at 1150 m: another altitude)" in weak.summary
    (q,) = [q for q in est.segments if q.strip_id == 3]
    assert q.altitude_from == ()
    assert abs(q.altitude_m - 700.0) < 3.0 * q.altitude_sigma_m + 1.0
    t0, t1 = report.strips[2].t_first, report.strips[2].t_last
    error = _position_error(est.trajectory, sim.mission.trajectory, t0, t1)
    assert error.max() < 3.0 * weak.sigma_m + 1.0, (error, weak.sigma_m)
    assert read_mission(tmp_path / "bag").n_points == sim.mission.n_points


# ---------------------------------------------------------------------------- nothing estimable
def test_single_strip_reports_and_writes_an_identity_calibration(capsys, tmp_path,
                                                               small_mission) -> None:
    """One strip: nothing to estimate. Without the option: the reason in one line, exit 1,
    no file, and stdout says what --write-identity would do. With it: exit 5, a file that
    ``correct`` accepts and that moves no point, reflectance computed."""
    bag = write_mission_bag(tmp_path / "one", without_control(subset(small_mission.mission,
                                                                      [1])))
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config)
    assert rc == 1 and not cal.exists()
    (line,) = err.splitlines()
    assert line.startswith("lidarcal calibrate: error: ")
    assert "nothing estimated: " in out
    assert "no strip pair overlaps" in out and "--write-identity" in out

    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config,
                       "--write-identity")
    assert rc == EXIT_NOTHING_ESTIMATED
    (line,) = err.splitlines()
    assert line.startswith("lidarcal calibrate: warning: nothing could be estimated (")
    assert line.endswith(f"{cal} moves no point")
    assert f"written to {cal}" in out
    body = calibration_body(cal)
    for name in PARAMETER_NAMES:
        entry = body["biases"][name]
        assert entry["value"] == 0.0 and entry["sigma"] is None and entry["estimated"] is False
    assert body["converged"] is False and body["sigma0"] is None
    assert body["strip_pairs"] == [] and body["nothing_estimated"]

    corrected = tmp_path / "corrected.mcap"
    rc, out, err = run(capsys, "correct", bag, "--calibration", cal, "-o", corrected)
    assert rc == 0, err
    got = read_mission(corrected, points_topic="/lidar/points_corrected")
    want = small_mission.mission.strips[0]
    (strip,) = got.strips
    order = np.argsort(strip.t, kind="stable")
    assert np.allclose(strip.xyz[order], want.xyz[np.argsort(want.t, kind="stable")],
                       rtol=0, atol=1e-9)
    assert np.isfinite(strip.extra["reflectance"]).mean() > 0.9


def test_strips_apart_report_no_overlap(capsys, tmp_path, small_mission) -> None:
    apart = shift_strip(subset(small_mission.mission, [1, 3]), 3, (5000.0, 0.0, 0.0))
    bag = write_mission_bag(tmp_path / "apart", without_control(apart))
    cal = tmp_path / "cal.yaml"
    rc, out, _ = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config,
                     "--write-identity")
    assert rc == EXIT_NOTHING_ESTIMATED
    assert "no strip pair overlaps" in out
    assert calibration_body(cal)["strip_pairs"] == []
    rc, out, _ = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config,
                     "--write-identity", "--json", "--overwrite")
    assert rc == EXIT_NOTHING_ESTIMATED
    doc = json.loads(out)["lidarcal_calibration"]
    assert doc["nothing_estimated"].startswith("no overlap between strips")
    assert doc == calibration_body(cal)


def test_nothing_observable_still_reports_the_agreement(capsys, tmp_path,
                                                        small_mission) -> None:
    """Overlapping strips, no control, only dZ asked for (which strips cannot see): the
    table gives each pair's agreement as delivered, the figures of the strip pairs'
    discrepancies at zero correction (computed here independently), and the file holds
    them."""
    mission = without_control(small_mission.mission)
    bag = write_mission_bag(tmp_path / "no_control", mission)
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config,
                       "--solve-for", "dZ", "--write-identity")
    assert rc == EXIT_NOTHING_ESTIMATED, err
    assert "nothing estimated: nothing left to estimate (dZ: " in out
    config = load_flight_config(small_mission.fast_config)
    settings = config.calibration_settings()
    settings.solve_for = ("dZ",)
    expected = Calibrator.from_mission(read_mission(bag), settings).pair_discrepancies(
        np.zeros(len(PARAMETER_NAMES)))
    pairs = calibration_body(cal)["strip_pairs"]
    assert [p["strips"] for p in pairs] == [list(d.strips) for d in expected]
    assert len(pairs) >= 10
    for p, d in zip(pairs, expected, strict=True):
        assert p["correspondences"] == d.distance.size > 0
        assert p["rms_after_m"] == pytest.approx(d.rms, rel=1e-9)
        assert p["p95_after_m"] == pytest.approx(d.p95, rel=1e-9)
        row = f"{d.strips[0]:>3} & {d.strips[1]:<3}"
        line = next(ln for ln in out.splitlines() if ln.startswith(row))  # the patch table
        assert f"{d.rms * 100:.1f} cm" in line and f"{d.p95 * 100:.1f} cm" in line


# ---------------------------------------------------------------------------- trajectory oddities
def _oddities(mission: Mission) -> tuple[Mission, np.ndarray]:
    """12 poses with NaN positions and 3 stamps repeated 1.0, 4.2 and 2.5 m away (written after
    the pose they repeat); returns the mission and the indices of the poses spoiled."""
    out = subset(mission, [1, 2])
    traj = out.trajectory
    n = len(traj)
    spoiled = np.linspace(n // 10, n - n // 10, 12).astype(np.int64)
    xyz = traj.xyz.copy()
    xyz[spoiled, 1] = np.nan
    repeated = spoiled[[2, 5, 8]] + 3
    offsets = np.array([[1.0, 0.0, 0.0], [0.0, 4.2, 0.0], [0.0, 0.0, 2.5]])
    out.trajectory = Trajectory(np.concatenate([traj.t, traj.t[repeated]]),
                                np.concatenate([xyz, xyz[repeated] + offsets]))
    return out, spoiled


def test_nan_positions_and_conflicting_repeats_are_counted(capsys, caplog, tmp_path,
                                                           small_mission) -> None:
    """The poses with NaN positions are left out, and both poses of each stamp repeated
    elsewhere (which one is right is unknown), in one warning line; every point is kept, and
    the poses kept are the originals (poses all at one stamp: test_bad_inputs)."""
    spoiled_mission, spoiled = _oddities(small_mission.mission)
    bag = write_mission_bag(tmp_path / "odd", spoiled_mission)
    with caplog.at_level(logging.WARNING, logger="lidarcal_ros.core.mission"):
        rc, out, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml",
                           "--config", small_mission.fast_config)
    assert rc == 0, err
    n = len(small_mission.mission.trajectory)
    (record,) = [r for r in caplog.records if r.name == "lidarcal_ros.core.mission"]
    assert record.getMessage() == (
        f"{bag}: trajectory /lidar/trajectory: 18 of {n + 3} poses left out: 12 with a "
        "non-finite stamp or position; 6 at 3 stamps repeated at positions up to 4.2 m apart "
        f"(first at t={small_mission.mission.trajectory.t[spoiled[2] + 3]:.3f} s; which one "
        "is right is unknown)")
    # nothing else lost: every point, and the poses kept are the originals
    n_points = sum(len(s) for s in spoiled_mission.strips)
    assert f"{n_points} points" in out.splitlines()[0]
    got = read_mission(bag).trajectory
    truth = small_mission.mission.trajectory
    keep = np.setdiff1d(np.arange(n), np.concatenate([spoiled, spoiled[[2, 5, 8]] + 3]))
    assert np.array_equal(got.t, truth.t[keep])
    assert np.array_equal(got.xyz, truth.xyz[keep])


# ---------------------------------------------------------------------------- real tile
def test_real_megaplot_both_passes_kept_calibrated_or_reported_and_corrected(
        capsys, tmp_path) -> None:
    """The lidR sample Megaplot.laz (forest, UTM 17N, no trajectory): pass 2 holds one edge of its
    swath (multiple returns 13-16 deg off nadir), which its rays cannot place in height.
    Both passes are kept, pass 2 at pass 1's altitude with its sigma stated; the forest
    offers no plane patch, so calibrate estimates nothing, says how well the passes agree
    (heights of last returns on smooth cells) and with --write-identity writes the
    calibration that correct turns into reflectance for every point."""
    import laspy

    path = real_las_file("Megaplot.laz")
    bag = tmp_path / "bag"
    rc, out, err = run(capsys, "import", path, "--trajectory", "estimate", "-o", bag)
    assert rc == 0, err
    n_points = len(laspy.read(str(path)).points)
    assert out.splitlines()[0].startswith(f"imported {n_points} of {n_points} points")
    lines = out.splitlines()
    (pass1,) = [ln for ln in lines if ln.startswith("    strip 1: ")]
    (pass2,) = [ln for ln in lines if ln.startswith("    strip 2: ")]
    assert pass1.startswith("    strip 1: rebuilt from ")
    assert "horizontally; weak: " in pass2 and "deg across the track" in pass2
    assert "kept, level flight at the altitude of strip 1, " in pass2
    mission = read_mission(bag)
    assert [s.strip_id for s in mission.strips] == [1, 2]
    assert mission.n_points == n_points

    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--write-identity")
    if rc == 0:  # something estimated honestly: a calibration with its sigmas
        body = calibration_body(cal)
        assert any(body["biases"][n]["estimated"] for n in PARAMETER_NAMES)
    else:
        assert rc == EXIT_NOTHING_ESTIMATED, err
        assert "  1 & 2 " in out  # the pair's line of the agreement table
        body = calibration_body(cal)
        assert body["converged"] is False
        assert body["strip_pairs"][0]["strips"] == [1, 2]
    corrected = tmp_path / "corrected.laz"
    rc, out, err = run(capsys, "correct", bag, "--calibration", cal, "-o", corrected)
    assert rc == 0, err
    las = laspy.read(str(corrected))
    assert len(las.points) == n_points
    assert np.isfinite(np.asarray(las["reflectance"])).mean() > 0.5
