"""Outputs the file system will not take: a directory, a dangling link, a missing directory,
a full disk, a read-only file system; and long and unicode names, which must just work.

Each case runs ``correct`` (to .mcap, .las, .laz), ``calibrate`` or ``import`` and checks
the answer: one line naming the output, exit status 1, nothing partial and no
``.lidarcal-tmp-*`` left, the inputs untouched. Tests run as root here, so a read-only
directory cannot be made by permissions: the read-only file system is simulated by making
``os.open`` fail with ``EROFS`` in the process.
"""

from __future__ import annotations

import errno
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import helpers_missions
import pytest
from helpers_cli import one_line_error, run
from helpers_las import plain_strips, write_las_tiles, write_mission_sbet
from helpers_missions import MissionFiles, write_calibration_yaml

from lidarcal_ros.io.bag.mission_bag import read_mission

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

#: The outputs tried: command and output name.
OUTPUTS = [("correct", "out.mcap"), ("correct", "out.las"), ("correct", "out.laz"),
           ("calibrate", "cal.yaml"), ("import", "bag.mcap")]


class Inputs:
    """A mission's inputs copied into one directory (``root/in``), outputs go to ``root/out``."""

    def __init__(self, small: MissionFiles, root: Path, *, name: str = "mission") -> None:
        self.root = root
        (root / "in").mkdir()
        (root / "out").mkdir()
        self.bag = Path(shutil.copytree(small.bag, root / "in" / name))
        self.calibration = write_calibration_yaml(root / "in" / "cal.yaml", small.sim.biases)
        self.config = Path(shutil.copy(small.fast_config, root / "in" / "fast.yaml"))
        (self.strip,) = write_las_tiles(plain_strips(small.sim), root / "in", tiles=(1, 1))
        self.sbet = write_mission_sbet(small.mission, root / "in" / "sbet.out")

    def args(self, command: str, output: Path) -> tuple[Any, ...]:
        """The command line writing ``output``."""
        crs = ("--crs", "EPSG:32633") if output.suffix in (".las", ".laz") else ()
        return {
            "correct": ("correct", self.bag, "--calibration", self.calibration, "-o", output,
                        *crs),
            "calibrate": ("calibrate", self.bag, "-o", output, "--config", self.config),
            "import": ("import", self.strip, "--trajectory", self.sbet, "-o", output,
                       "--qa-cell", "0"),
            "report": ("report", self.bag, "--calibration", self.calibration, "-o", output,
                       "--config", self.config),
        }[command]

    def snapshot(self) -> list[tuple[str, bytes]]:
        """Every input file with its bytes."""
        return [(str(p), p.read_bytes()) for p in sorted((self.root / "in").rglob("*"))
                if p.is_file()]


@pytest.fixture
def inputs(small_mission: MissionFiles, tmp_path: Path) -> Inputs:
    return Inputs(small_mission, tmp_path)


def left_in(directory: Path) -> list[str]:
    """The names in ``directory``, hidden temporaries included."""
    return sorted(p.name for p in directory.iterdir())


@pytest.mark.parametrize(("command", "name"), OUTPUTS)
def test_an_output_that_is_a_directory_is_refused(capsys, inputs, command, name) -> None:
    before = inputs.snapshot()
    out = inputs.root / "out" / name
    out.mkdir()
    (out / "theirs").write_text("keep\n")
    for overwrite in ((), ("--overwrite",)):
        rc, _, err = run(capsys, *inputs.args(command, out), *overwrite)
        assert one_line_error(rc, err, command) == (
            f"{out}: is a directory; -o/--output takes a file name here")
    assert left_in(inputs.root / "out") == [name] and left_in(out) == ["theirs"]
    assert inputs.snapshot() == before


@pytest.mark.parametrize(("command", "name"), OUTPUTS)
def test_a_dangling_link_as_output_is_refused_naming_it(capsys, inputs, command,
                                                        name) -> None:
    """Neither written through (its target may lie anywhere: a file would appear where the
    user did not name one) nor replaced by the output (the link was put there for a
    reason), with or without ``--overwrite``."""
    before = inputs.snapshot()
    out = inputs.root / "out" / name
    target = inputs.root / "elsewhere" / name
    out.symlink_to(target)
    for overwrite in ((), ("--overwrite",)):
        rc, _, err = run(capsys, *inputs.args(command, out), *overwrite)
        assert one_line_error(rc, err, command) == (
            f"{out}: is a symbolic link to {target}, which does not exist; remove the link "
            "or name the output itself")
    assert left_in(inputs.root / "out") == [name] and out.is_symlink()
    assert not (inputs.root / "elsewhere").exists()
    assert inputs.snapshot() == before


@pytest.mark.parametrize(("command", "name"), OUTPUTS)
def test_an_output_in_a_missing_directory_is_refused(capsys, inputs, command, name) -> None:
    before = inputs.snapshot()
    out = inputs.root / "out" / "no" / "such" / name
    rc, _, err = run(capsys, *inputs.args(command, out))
    assert one_line_error(rc, err, command) == (
        f"{out}: directory {out.parent} does not exist")
    assert left_in(inputs.root / "out") == []
    assert inputs.snapshot() == before


def _limit_file_size(nbytes: int) -> None:
    """In the child before exec: writes past ``nbytes`` fail with ``EFBIG`` ("File too
    large"), as on a full disk, instead of killing the process with SIGXFSZ."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, resource.RLIM_INFINITY))


#: Bytes a child may write to any one file: less than each output takes (the smallest, the
#: calibration, some 3 kB), more than the Python caches it may write on starting.
FULL_AT = {"cal.yaml": 1000}


@pytest.mark.parametrize(("command", "name"), [*OUTPUTS, ("import", "bag"), ("correct", "bag"),
                                               ("report", "report.html")])
def test_a_full_disk_is_one_line_and_leaves_the_previous_output(inputs, command,
                                                                name) -> None:
    """In a child process whose files cannot grow past a limit: one line with the operating
    system's reason, no partial file or temporary, the previous output and inputs untouched."""
    out = inputs.root / "out" / name
    args = [str(a) for a in inputs.args(command, out)]
    rc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *args, "-q"],
                        capture_output=True, text=True, timeout=300, check=False)
    assert rc.returncode == 0, rc.stderr
    kept = {p.relative_to(out.parent): p.read_bytes()
            for p in ([out, *out.rglob("*")] if out.is_dir() else [out]) if p.is_file()}
    assert sum(map(len, kept.values())) > FULL_AT.get(name, 100_000)
    before = inputs.snapshot()
    proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *args, "-q", "--overwrite"],
                          capture_output=True, text=True, timeout=300, check=False,
                          preexec_fn=lambda: _limit_file_size(FULL_AT.get(name, 100_000)))
    # A bag fails while written or, its last chunk flushed on closing, while finished.
    what = {".yaml": "write calibration ", ".las": "write ", ".laz": "write ",
            ".html": "write the report "}.get(
        out.suffix, "(write|finish) bag ")
    assert re.fullmatch(f"{re.escape(str(out))}: cannot {what}\\(File too large\\)",
                        one_line_error(proc.returncode, proc.stderr, command))
    assert left_in(inputs.root / "out") == [name]
    after = {p.relative_to(out.parent): p.read_bytes()
             for p in ([out, *out.rglob("*")] if out.is_dir() else [out]) if p.is_file()}
    assert after == kept
    assert inputs.snapshot() == before


@pytest.mark.parametrize("uav", [False, True])
def test_a_full_disk_while_simulating_leaves_none_of_the_files(tmp_path, uav) -> None:
    """``lidarcal simulate`` writes a bag, control points and the truth: a file that cannot
    grow is one line, and none of the three is left (nor a temporary)."""
    out = tmp_path / "out"
    out.mkdir()
    args = ["--uav", "--columns", "32", "--uav-line-length", "60", "--control", "3"] if uav \
        else ["--density", "0.05", "--line-length", "300"]
    proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", "simulate", "-o",
                           str(out / "sim"), *args],
                          capture_output=True, text=True, timeout=300, check=False,
                          preexec_fn=lambda: _limit_file_size(100_000))
    assert re.fullmatch(f"{re.escape(str(out / 'sim'))}: cannot (write|finish) bag "
                        "\\(File too large\\)",
                        one_line_error(proc.returncode, proc.stderr, "simulate"))
    assert left_in(out) == []


@pytest.mark.parametrize(("command", "name"), OUTPUTS)
def test_a_read_only_file_system_is_one_line(capsys, inputs, monkeypatch, command,
                                             name) -> None:
    """Simulated (as root, permissions do not stop a write): creating anything in the
    output directory fails with EROFS."""
    before = inputs.snapshot()
    out_dir = inputs.root / "out"
    real_open = os.open

    def read_only(path: Any, flags: int, *args: Any, **kwargs: Any) -> int:
        if Path(os.fsdecode(path)).parent == out_dir and flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    out = out_dir / name
    rc, _, err = run(capsys, *inputs.args(command, out))
    assert one_line_error(rc, err, command) == (
        f"{out}: cannot write in {out_dir} (Read-only file system)")
    assert left_in(out_dir) == []
    assert inputs.snapshot() == before


LONG = "é" * 60 + "a" * 130 + "ü" * 30 + "x" * 5  # 255 bytes in UTF-8


@pytest.mark.parametrize(("command", "name"), [*OUTPUTS, ("import", "bag"),
                                               ("correct", "bag")])
def test_long_and_unicode_names_are_read_and_written(capsys, small_mission, tmp_path, command,
                                                     name) -> None:
    """Inputs named in unicode, an output whose name takes all 255 bytes a name may have."""
    stem, suffix = os.path.splitext(name)
    out_name = LONG[: 255 - len(suffix.encode()) - len(stem)] + stem + suffix
    while len(out_name.encode()) > 255:
        out_name = out_name[1:]
    inputs = Inputs(small_mission, tmp_path, name="Flug_über_Zürich_飛行")
    strip = inputs.strip.rename(inputs.strip.with_name("Streifen_ü_飛.las"))
    inputs.strip = strip
    out = tmp_path / "out" / out_name
    assert len(out.name.encode()) in (254, 255)
    rc, _, err = run(capsys, *inputs.args(command, out))
    assert rc == 0, err
    assert left_in(tmp_path / "out") == [out_name]
    if command == "import" or (command == "correct" and suffix in (".mcap", "")):
        topic = "/lidar/points_corrected" if command == "correct" else "/lidar/points"
        assert read_mission(out, points_topic=topic).n_points == \
            small_mission.mission.n_points
