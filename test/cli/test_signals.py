"""Ctrl-C (SIGINT) and SIGTERM during a batch command: one line, its status, no output left."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import helpers_missions
import pytest
from helpers_missions import MissionFiles, write_calibration_yaml

from lidarcal_ros.cli.exit_status import EXIT_INTERRUPTED, EXIT_TERMINATED
from lidarcal_ros.core.params import PARAMETER_NAMES

mission_factory = helpers_missions.mission_factory

SIGNALS = [pytest.param(signal.SIGINT, EXIT_INTERRUPTED, "interrupted", id="SIGINT"),
           pytest.param(signal.SIGTERM, EXIT_TERMINATED, "terminated", id="SIGTERM")]


def signal_when_writing(args: list[str], out_dir: Path, signum: int, *, cwd: Path,
                        marker: str, delay_s: float) -> tuple[int, str]:
    """Run ``lidarcal ARGS``, send ``signum`` ``delay_s`` after a hidden file whose name holds
    ``marker`` appears in ``out_dir`` (the command checks or writes its output), and return
    its exit status and stderr."""
    proc = subprocess.Popen([sys.executable, "-m", "lidarcal_ros", *args], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and proc.poll() is None:
        if any(p.name.startswith(".") and marker in p.name for p in out_dir.iterdir()):
            time.sleep(delay_s)
            assert proc.poll() is None, "the command ended before the signal"
            proc.send_signal(signum)
            break
        time.sleep(0.005)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


@pytest.fixture(scope="module")
def long_mission(mission_factory: Callable[..., MissionFiles]) -> MissionFiles:
    """A mission whose correction takes a few seconds (time to be signalled while writing)."""
    return mission_factory(density=0.4, line_length_m=600.0)


@pytest.mark.parametrize(("signum", "status", "word"), SIGNALS)
@pytest.mark.parametrize("output", ["corrected.laz", "corrected_bag"])
@pytest.mark.parametrize(("marker", "delay_s"), [("tmp", 0.0), ("tmp", 0.4)],
                         ids=["opening", "writing"])
def test_a_signal_while_correcting_leaves_no_output(
        long_mission: MissionFiles, tmp_path: Path, signum: int, status: int, word: str,
        output: str, marker: str, delay_s: float) -> None:
    calibration = write_calibration_yaml(tmp_path / "calibration.yaml",
                                         dict.fromkeys(PARAMETER_NAMES, 0.0))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    crs = ["--crs", "EPSG:32633"] if output.endswith(".laz") else []
    bag_files = sorted((p.name, p.stat().st_size) for p in long_mission.bag.iterdir())
    rc, err = signal_when_writing(
        ["correct", str(long_mission.bag), "--calibration", str(calibration),
         "-o", str(out_dir / output), *crs], out_dir, signum, cwd=tmp_path,
        marker=marker, delay_s=delay_s)
    assert rc == status, err
    assert err.splitlines() == [f"lidarcal correct: {word}"], err
    assert list(out_dir.iterdir()) == []  # neither the output nor its temporary
    assert sorted((p.name, p.stat().st_size) for p in long_mission.bag.iterdir()) == bag_files


@pytest.mark.parametrize(("signum", "status", "word"), SIGNALS)
def test_a_signal_while_calibrating_leaves_no_output(long_mission: MissionFiles, tmp_path: Path,
                                                     signum: int, status: int, word: str) -> None:
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "lidarcal_ros", "calibrate",
                             str(long_mission.bag), "-o", str(out_dir / "calibration.yaml")],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    time.sleep(2.5)  # past the start (about 1.5 s), into the calibration
    assert proc.poll() is None, "the calibration ended before the signal"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == status, err
    assert err.splitlines()[-1] == f"lidarcal calibrate: {word}", err
    assert list(out_dir.iterdir()) == []


def test_two_writers_of_one_output(long_mission: MissionFiles, tmp_path: Path) -> None:
    """Two ``lidarcal correct`` to one output at once: one writes it, the other is refused in
    one line (the output exists, or appeared while it wrote) and leaves nothing."""
    calibration = write_calibration_yaml(tmp_path / "calibration.yaml",
                                         dict.fromkeys(PARAMETER_NAMES, 0.0))
    out = tmp_path / "out" / "corrected.laz"
    out.parent.mkdir()
    args = [sys.executable, "-m", "lidarcal_ros", "correct", str(long_mission.bag),
            "--calibration", str(calibration), "-o", str(out), "--crs", "EPSG:32633"]
    procs = [subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = sorted((p.wait(timeout=120), p.stderr.read() if p.stderr else "") for p in procs)
    (ok, _), (refused, err) = results
    assert (ok, refused) == (0, 1), results
    assert f"lidarcal correct: error: {out}: " in err and \
        ("exists" in err or "appeared while" in err), err
    assert [p.name for p in out.parent.iterdir()] == ["corrected.laz"]
