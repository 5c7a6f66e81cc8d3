"""An output that is also an input (or inside one, or another output) is refused before any
work, whatever ``--overwrite``, and the input is left as it was."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import helpers_missions
import pytest
from helpers_cli import one_line_error, run
from helpers_missions import MissionFiles, write_calibration_yaml

from lidarcal_ros.core.params import PARAMETER_NAMES

mission_factory = helpers_missions.mission_factory


@pytest.fixture
def mission_copy(mission_factory: Callable[..., MissionFiles], tmp_path: Path) -> MissionFiles:
    """The small mission's files copied into this test's own directory."""
    m = mission_factory()
    bag = shutil.copytree(m.bag, tmp_path / "mission")
    control = Path(shutil.copy(m.control_csv, tmp_path / "control.csv"))
    return MissionFiles(m.sim, bag, control, m.truth, m.fast_config, tmp_path)


def snapshot(path: Path) -> list[tuple[str, bytes]]:
    """Every file under ``path`` (or ``path`` itself) with its bytes."""
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    return [(str(p), p.read_bytes()) for p in files if p.is_file()]


def test_calibrate_refuses_to_write_over_its_control_file(
        capsys: pytest.CaptureFixture[str], mission_copy: MissionFiles) -> None:
    before = snapshot(mission_copy.control_csv)
    rc, _, err = run(capsys, "calibrate", mission_copy.bag, "--control",
                     mission_copy.control_csv, "-o", mission_copy.control_csv, "--overwrite")
    reason = one_line_error(rc, err)
    assert reason.startswith(f"{mission_copy.control_csv}: is also an input"), reason
    assert snapshot(mission_copy.control_csv) == before


@pytest.mark.parametrize("where", ["the bag", "inside the bag", "the bag's storage file"])
def test_correct_refuses_an_output_over_an_input(
        capsys: pytest.CaptureFixture[str], mission_copy: MissionFiles, where: str) -> None:
    calibration = write_calibration_yaml(mission_copy.workdir / "calibration.yaml",
                                         dict.fromkeys(PARAMETER_NAMES, 0.0))
    output = {"the bag": mission_copy.bag,
              "inside the bag": mission_copy.bag / "corrected.laz",
              "the bag's storage file": next(mission_copy.bag.glob("*.mcap"))}[where]
    before = snapshot(mission_copy.bag) + snapshot(calibration)
    rc, _, err = run(capsys, "correct", mission_copy.bag, "--calibration", calibration,
                     "-o", output, "--overwrite", "--crs", "EPSG:32633")
    assert "is also an input" in one_line_error(rc, err, "correct")
    assert snapshot(mission_copy.bag) + snapshot(calibration) == before


def test_correct_refuses_one_path_for_both_outputs(
        capsys: pytest.CaptureFixture[str], mission_copy: MissionFiles) -> None:
    calibration = write_calibration_yaml(mission_copy.workdir / "calibration.yaml",
                                         dict.fromkeys(PARAMETER_NAMES, 0.0))
    out = mission_copy.workdir / "corrected.laz"
    rc, _, err = run(capsys, "correct", mission_copy.bag, "--calibration", calibration,
                     "-o", out, "--trajectory-out", out, "--crs", "EPSG:32633")
    assert "is also an input" in one_line_error(rc, err, "correct")
    assert not out.exists()


def test_a_huge_name_gives_a_short_line(capsys: pytest.CaptureFixture[str],
                                        mission_copy: MissionFiles) -> None:
    """A topic name of 200,000 characters is cut in the error line, its length said."""
    rc, _, err = run(capsys, "calibrate", mission_copy.bag, "--points", "/p" * 100_000,
                     "-o", mission_copy.workdir / "out.yaml")
    reason = one_line_error(rc, err)
    assert len(reason) < 2100 and reason.endswith("characters)"), reason[:2200]
