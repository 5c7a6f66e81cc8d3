"""Hostile names: an output that is one of its command's own inputs, for every command and
input, and names in unicode, with spaces and with newlines.

An output over an input is refused before any work, whatever ``--overwrite``: one line, exit
1, the input's bytes as they were. Names with spaces, newlines and non-Latin letters are read
and written like any other; an error naming one is still one line.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import helpers_missions
import laspy
import pytest
import yaml
from helpers_cli import one_line_error, run
from helpers_las import plain_strips, write_las_tiles, write_mission_sbet
from helpers_missions import MissionFiles, write_calibration_yaml

from lidarcal_ros.io.bag.mission_bag import read_mission

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


class Files:
    """A mission's inputs in one directory, under the names given."""

    def __init__(self, small: MissionFiles, root: Path, *, bag: str = "mission.mcap",
                 strip: str = "strip", calibration: str = "cal.yaml") -> None:
        self.root = root
        self.bag = Path(shutil.copy(next(small.bag.glob("*.mcap")), root / bag))
        self.calibration = write_calibration_yaml(root / calibration, small.sim.biases)
        self.config = Path(shutil.copy(small.fast_config, root / "fast.yaml"))
        self.control = Path(shutil.copy(small.control_csv, root / "control.csv"))
        (tiled,) = write_las_tiles(plain_strips(small.sim), root, tiles=(1, 1))
        self.strip = tiled.rename(root / f"{strip}{tiled.suffix}")  # (a LAZ)
        self.sbet = write_mission_sbet(small.mission, root / "sbet.out")
        lines = [{"id": 1, "start": [0, -150], "end": [0, 150], "height": 1150},
                 {"id": 2, "start": [0, 150], "end": [0, -150], "height": 1150}]
        self.lines = root / "lines.yaml"
        self.lines.write_text(yaml.safe_dump(lines))

    def snapshot(self) -> dict[str, bytes]:
        """Every file with its bytes."""
        return {p.name: p.read_bytes() for p in sorted(self.root.iterdir()) if p.is_file()}


@pytest.fixture
def files(small_mission: MissionFiles, tmp_path: Path) -> Files:
    return Files(small_mission, tmp_path)


#: Each command's inputs on its command line (the names of :class:`Files`' attributes).
COMMAND_INPUTS: dict[str, tuple[str, ...]] = {
    "calibrate": ("bag",), "correct": ("bag", "--calibration", "calibration"),
    "report": ("bag", "--calibration", "calibration"),
    "import": ("strip", "--trajectory", "sbet"), "recover": ("bag",)}
INPUT = "is also an input"
YAML_OUT = "lidarcal correct does not write .yaml files"
#: Each command with one of its inputs (with the options naming it, if more) as its output,
#: and the refusal.
SAME_PATH: dict[str, tuple[str, str, tuple[str, ...], str]] = {
    f"{command} -o {victim}": (command, victim, extra, refusal)
    for command, victim, extra, refusal in [
        ("calibrate", "bag", (), INPUT),
        ("calibrate", "config", ("--config", "config"), INPUT),
        ("calibrate", "control", ("--control", "control"), INPUT),
        ("correct", "bag", (), INPUT),
        ("correct", "calibration", (), YAML_OUT),
        ("correct", "config", ("--config", "config"), YAML_OUT),
        ("report", "bag", (), INPUT),
        ("report", "calibration", (), INPUT),
        ("report", "control", ("--control", "control"), INPUT),
        ("import", "strip", (), INPUT),
        ("import", "sbet", (), INPUT),
        ("recover", "bag", (), "the output must not be the damaged bag itself"),
    ]}


@pytest.mark.parametrize("case", SAME_PATH)
def test_an_output_that_is_its_own_input_is_refused(capsys, files, case) -> None:
    """With ``--overwrite``: refused before any work (``correct`` refuses a YAML output by
    its kind first), the input's bytes as they were."""
    command, which, extra, refusal = SAME_PATH[case]
    victim = getattr(files, which)
    args = [getattr(files, a, a) for a in (*COMMAND_INPUTS[command], *extra)]
    before = files.snapshot()
    rc, _, err = run(capsys, command, *args, "-o", victim, "--overwrite")
    reason = one_line_error(rc, err, command)
    assert reason.startswith(f"{victim}: {refusal}"), reason
    assert files.snapshot() == before


def test_simulate_refuses_to_write_its_truth_over_its_lines(capsys, files) -> None:
    """``simulate --lines L -o OUT`` writes OUT, OUT_control.csv and OUT_truth.yaml: the
    lines file named as one of the three is refused, not replaced."""
    before = files.snapshot()
    truth = files.root / "sim_truth.yaml"
    files.lines.rename(truth)
    rc, _, err = run(capsys, "simulate", "--lines", truth, "-o", files.root / "sim",
                     "--overwrite", "--density", "0.05")
    assert one_line_error(rc, err, "simulate").startswith(f"{truth}: is also an input")
    assert truth.read_bytes() == before["lines.yaml"]
    assert not (files.root / "sim").exists()
    assert not (files.root / "sim_control.csv").exists()


#: Names a user may give: spaces, a newline, letters of other scripts.
NAMES = ["Überflug_航线_1", "flight line 7 (copy)", "two\nlines"]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("suffix", [".mcap", ".las", ".laz", ".yaml", ""])
def test_hostile_names_are_read_and_written(capsys, small_mission, tmp_path, name,
                                            suffix) -> None:
    """The inputs and the output under ``name``: the command succeeds and writes exactly the
    output named, no temporary beside it."""
    files = Files(small_mission, tmp_path, bag=f"{name}.mcap", strip=name,
                  calibration=f"{name}.cal.yaml")
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / f"{name}{suffix}"
    crs: tuple[Any, ...] = ("--crs", "EPSG:32633")
    if suffix == ".yaml":
        args: tuple[Any, ...] = ("calibrate", files.bag, "--config", files.config, "-o", out)
    elif suffix == "":
        args = ("import", files.strip, "--trajectory", files.sbet, "-o", out, "--qa-cell", "0")
    else:
        args = ("correct", files.bag, "--calibration", files.calibration, "-o", out,
                *(crs if suffix != ".mcap" else ()))
    rc, _, err = run(capsys, *args, "-q")
    assert rc == 0, err
    assert [p.name for p in (tmp_path / "out").iterdir()] == [out.name]
    n = small_mission.mission.n_points
    if suffix in (".las", ".laz"):
        assert laspy.read(out).header.point_count == n
    elif suffix == ".yaml":
        assert yaml.safe_load(out.read_text())["lidarcal_calibration"]["converged"] is True
    else:
        topic = "/lidar/points" if suffix == "" else "/lidar/points_corrected"
        assert read_mission(out, points_topic=topic).n_points == n


def test_an_error_naming_a_file_with_a_newline_is_one_line(capsys, tmp_path) -> None:
    bag = tmp_path / "no\nsuch bag.mcap"
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal\n.yaml")
    reason = one_line_error(rc, err)
    assert "no such bag.mcap" in reason, reason
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("suffix", [".yaml", ".las", ".mcap", ""])
def test_a_name_longer_than_the_file_system_takes_is_refused_before_any_work(
        capsys, files, suffix) -> None:
    """256 bytes (128 two-byte letters): refused at once, not after the work when written
    (``File name too long``); a sensor-frame calibration's URDF joint beside a 255-byte
    calibration name (``X.urdf.xml``, 259 bytes) likewise."""
    room = 256 - len(suffix)
    out = files.root / ("ü" * (room // 2) + "x" * (room % 2) + suffix)
    assert len(out.name.encode()) == 256
    args: tuple[Any, ...] = {
        ".yaml": ("calibrate", files.bag),
        ".las": ("correct", files.bag, "--calibration", files.calibration, "--crs",
                 "EPSG:32633"),
        ".mcap": ("correct", files.bag, "--calibration", files.calibration),
        "": ("import", files.strip, "--trajectory", files.sbet),
    }[suffix]
    before = files.snapshot()
    rc, _, err = run(capsys, *args, "-o", out)
    assert one_line_error(rc, err, args[0]) == (
        f"{out}: name of 256 bytes; the file system takes at most 255")
    assert files.snapshot() == before


def test_a_urdf_joint_name_past_the_limit_is_refused_before_writing(capsys, tmp_path) -> None:
    """A sensor-frame calibration named in 255 bytes: its URDF joint beside it
    (``NAME.urdf.xml``) would take 259; refused before the calibration, nothing written."""
    bag = tmp_path / "uav"
    rc, _, err = run(capsys, "simulate", "--uav", "--layout", "vlp16", "--seed", "2",
                     "--columns", "16", "--uav-line-length", "40", "--exact-ins", "-o", bag)
    assert rc == 0, err
    out = tmp_path / ("ü" * 124 + "xx" + ".yaml")
    assert len(out.name.encode()) == 255
    rc, _, err = run(capsys, "calibrate", bag, "--points", "/velodyne_points", "--trajectory",
                     "/ins/odometry", "-o", out, "-q")
    urdf = out.with_name(out.stem + ".urdf.xml")
    assert one_line_error(rc, err.splitlines()[-1] + "\n") == (
        f"{urdf}: name of 259 bytes; the file system takes at most 255")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["uav", "uav_truth.yaml"]
