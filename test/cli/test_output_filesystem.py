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
import tempfile
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
            "report": ("report", self.bag, "--calibration", self.calibration, "-o", output),
            "simulate": ("simulate", "-o", output, "--scenario", "flat", "--density", "0.05",
                         "--line-length", "300"),
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
    """In the child before exec: files cannot grow past ``nbytes``, as a shell's ``ulimit -f``
    would start it, SIGXFSZ at its default (killing the process). Writes past the limit
    then fail with ``EFBIG`` ("File too large"), as on a full disk, because the interpreter
    ignores SIGXFSZ on starting (as it does SIGPIPE); a command dying of it would leave its
    temporaries behind, which each test would see."""
    signal.signal(signal.SIGXFSZ, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, resource.RLIM_INFINITY))


#: Bytes a child may write to any one file: less than each output takes (the smallest, the
#: calibration, some 3 kB), more than the Python caches it may write on starting.
FULL_AT = {"cal.yaml": 1000}


@pytest.mark.parametrize(("command", "name"), [*OUTPUTS, ("import", "bag"), ("correct", "bag"),
                                               ("report", "report.html"), ("simulate", "sim")])
def test_a_full_disk_is_one_line_and_leaves_the_previous_output(inputs, command,
                                                                name) -> None:
    """In a child process whose files cannot grow past a limit: one line with the operating
    system's reason, no partial file or temporary, the previous output and inputs untouched."""
    out = inputs.root / "out" / name
    args = [str(a) for a in inputs.args(command, out)] + (["-q"] if command != "simulate" else [])
    rc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *args],
                        capture_output=True, text=True, timeout=300, check=False)
    assert rc.returncode == 0, rc.stderr
    kept = {p.relative_to(out.parent): p.read_bytes()
            for p in ([out, *out.rglob("*")] if out.is_dir() else [out]) if p.is_file()}
    assert sum(map(len, kept.values())) > FULL_AT.get(name, 100_000)
    kept_beside = {p: p.read_bytes() for p in out.parent.iterdir() if p != out}
    before = inputs.snapshot()
    proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *args, "--overwrite"],
                          capture_output=True, text=True, timeout=300, check=False,
                          preexec_fn=lambda: _limit_file_size(FULL_AT.get(name, 100_000)))
    # A bag fails while written or, its last chunk flushed on closing, while finished.
    what = {".yaml": "write calibration ", ".las": "write ", ".laz": "write ",
            ".html": "write the report "}.get(out.suffix, "(write|finish) bag ")
    assert re.fullmatch(f"{re.escape(str(out))}: cannot {what}\\(File too large\\)",
                        one_line_error(proc.returncode, proc.stderr, command))
    # simulate's control and truth files beside its bag: the previous ones, no new one
    assert left_in(inputs.root / "out") == sorted([name, *(p.name for p in kept_beside)])
    assert all(p.read_bytes() == data for p, data in kept_beside.items())
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


def test_a_full_disk_leaves_neither_the_calibration_nor_its_urdf_joint(tmp_path) -> None:
    """A sensor-frame calibration with its URDF joint beside it: the disk full at the
    calibration (written with the joint, all or none) leaves no joint beside no calibration,
    and the previous pair as it was (before: the new joint was left, the old calibration)."""
    from lidarcal_ros.io.calibration_file import urdf_path

    bag = tmp_path / "uav"
    subprocess.run([sys.executable, "-m", "lidarcal_ros", "simulate", "--uav", "--layout",
                    "os1-32", "--seed", "2", "--columns", "32", "--uav-line-length", "80",
                    "--exact-ins", "-o", str(bag)], capture_output=True, timeout=300, check=True)
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "mounting.yaml"
    args = [sys.executable, "-m", "lidarcal_ros", "calibrate", str(bag), "--points",
            "/velodyne_points", "--trajectory", "/ins/odometry", "-o", str(out), "-q"]
    first = subprocess.run(args, capture_output=True, text=True, timeout=300, check=False)
    assert first.returncode == 0, first.stderr
    kept = {p.name: p.read_bytes() for p in (out, urdf_path(out))}
    assert len(kept[out.name]) > 1000 > len(kept[urdf_path(out).name]) > 100
    urdf_path(out).unlink()  # the joint the full disk would let through: none before either
    proc = subprocess.run([*args, "--overwrite"], capture_output=True, text=True, timeout=300,
                          check=False, preexec_fn=lambda: _limit_file_size(1000))
    assert one_line_error(proc.returncode, proc.stderr.splitlines()[-1] + "\n", "calibrate") \
        == f"{out}: cannot write calibration (File too large)"
    assert left_in(tmp_path / "out") == [out.name]
    assert out.read_bytes() == kept[out.name]


def _as_another_user() -> Any:
    """A ``preexec_fn`` that runs a child as ``nobody`` (root here: permissions do not stop
    root), None when this process is not root; the test skipped, saying why, when such a
    child cannot run ``lidarcal`` at all."""
    if os.geteuid() != 0:
        return None

    def drop() -> None:
        os.setgid(65534)
        os.setuid(65534)

    try:
        probe = subprocess.run([sys.executable, "-c", "import lidarcal_ros"], preexec_fn=drop,
                               capture_output=True, text=True, timeout=60, check=False)
        refusal = probe.stderr.strip().splitlines()[-1:] if probe.returncode else []
    except OSError as exc:
        refusal = [str(exc)]
    if refusal:
        pytest.skip("a real read-only directory needs a user other than root, and this "
                    f"machine's interpreter ({sys.executable}) or checkout cannot be run by "
                    f"one ({refusal[0]}); test_a_read_only_file_system_is_one_line simulates "
                    "it (EROFS) instead")
    return drop


def test_a_directory_this_user_cannot_write_is_one_line(small_mission, tmp_path) -> None:
    """As a user who may not write the output directory (mode 0555): one line with the
    operating system's reason, before any work, nothing written."""
    preexec = _as_another_user()
    root = Path(tempfile.mkdtemp(prefix="lidarcal-ro-"))
    try:
        os.chmod(root, 0o755)
        bag = Path(shutil.copytree(small_mission.bag, root / "mission"))
        calibration = write_calibration_yaml(root / "cal.yaml", small_mission.sim.biases)
        for p in [bag, *bag.iterdir(), calibration]:
            os.chmod(p, 0o755 if p.is_dir() else 0o644)
        out_dir = root / "out"
        out_dir.mkdir(mode=0o555)
        os.chmod(out_dir, 0o555)
        out = out_dir / "out.laz"
        proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", "correct", str(bag),
                               "--calibration", str(calibration), "-o", str(out), "--crs",
                               "EPSG:32633"], preexec_fn=preexec, capture_output=True,
                              text=True, timeout=300, check=False)
        assert one_line_error(proc.returncode, proc.stderr, "correct") == (
            f"{out}: cannot write in {out_dir} (Permission denied)")
        assert left_in(out_dir) == []
    finally:
        shutil.rmtree(root)  # (as root: the 0555 directory's mode stops nothing)


def test_a_full_disk_leaves_neither_the_cloud_nor_the_trajectory_out(inputs) -> None:
    """``correct -o out.laz --trajectory-out traj.mcap`` with files limited below the
    cloud's size: one line, neither output nor a temporary of either."""
    out, trajectory = inputs.root / "out" / "out.laz", inputs.root / "out" / "traj.mcap"
    args = [str(a) for a in inputs.args("correct", out)]
    proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *args, "--trajectory-out",
                           str(trajectory), "-q"], capture_output=True, text=True,
                          timeout=300, check=False,
                          preexec_fn=lambda: _limit_file_size(100_000))
    assert one_line_error(proc.returncode, proc.stderr, "correct") == (
        f"{out}: cannot write (File too large)")
    assert left_in(inputs.root / "out") == []
