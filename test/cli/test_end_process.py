"""How a ``lidarcal`` process ends (:func:`lidarcal_ros.cli.exit_status.end_process`): the
exit status, the exit handlers, everything written to stdout and to the output files, and the
interpreter's own ending where a thread still runs or ROS was started.

Each case runs in a fresh interpreter (the function ends the process).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import helpers_missions
import laspy
import numpy as np
from helpers_cli import run_process
from helpers_missions import MissionFiles, write_calibration_yaml
from mcap.reader import make_reader

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory


def _python(code: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, cwd=tmp_path, timeout=60, check=False)


def test_status_exit_handlers_and_buffered_output(tmp_path: Path) -> None:
    marker = tmp_path / "handler-ran"
    proc = _python(f"""
        import atexit, logging, sys
        from lidarcal_ros.cli.exit_status import end_process
        log = logging.getLogger("probe")
        handler = logging.FileHandler({str(tmp_path / "log.txt")!r}, delay=True)
        log.addHandler(handler)
        log.warning("kept")                      # flushed by logging's exit handler
        atexit.register(lambda: open({str(marker)!r}, "w").write("yes"))
        sys.stdout.write("x" * 200_000)          # more than a pipe's buffer, unflushed
        end_process(7)
        print("not reached")
    """, tmp_path)
    assert proc.returncode == 7, proc.stderr
    assert proc.stdout == "x" * 200_000
    assert marker.read_text() == "yes"
    assert (tmp_path / "log.txt").read_text() == "kept\n"


def test_a_thread_still_running_is_waited_for(tmp_path: Path) -> None:
    done = tmp_path / "thread-done"
    proc = _python(f"""
        import threading, time
        from lidarcal_ros.cli.exit_status import end_process
        def work():
            time.sleep(0.5)
            open({str(done)!r}, "w").write("done")
        threading.Thread(target=work).start()
        end_process(3)
    """, tmp_path)
    assert proc.returncode == 3, proc.stderr
    assert done.read_text() == "done"


def test_the_interpreter_ends_itself_once_ros_was_started(tmp_path: Path) -> None:
    # (a stand-in module: end_process looks only at whether rclpy was imported)
    proc = _python("""
        import atexit, sys, types
        sys.modules["rclpy"] = types.ModuleType("rclpy")
        class Late:
            def __del__(self):
                print("torn down")               # only the interpreter's teardown says this
        keep = Late()
        from lidarcal_ros.cli.exit_status import end_process
        end_process(0)
    """, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "torn down\n"


def test_a_profiler_still_writes_its_figures(tmp_path: Path) -> None:
    script = tmp_path / "probe.py"
    script.write_text("from lidarcal_ros.cli.exit_status import end_process\nend_process(0)\n")
    proc = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(tmp_path / "prof"),
                           str(script)], capture_output=True, text=True, cwd=tmp_path,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "prof").stat().st_size > 0


def test_without_ros_the_teardown_is_skipped(tmp_path: Path) -> None:
    proc = _python("""
        class Late:
            def __del__(self):
                print("torn down")
        keep = Late()
        from lidarcal_ros.cli.exit_status import end_process
        end_process(0)
    """, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ""


def test_correct_in_its_own_process_writes_whole_files(tmp_path: Path,
                                                       small_mission: MissionFiles) -> None:
    """``python -m lidarcal_ros correct`` (the console script's path): the LAZ file and the
    bag, read back by laspy and the mcap project's reader, hold every corrected point."""
    from lidarcal_ros.core.params import PARAMETER_NAMES
    from lidarcal_ros.io.bag.reader import open_bag

    calibration = write_calibration_yaml(tmp_path / "calibration.yaml",
                                         dict.fromkeys(PARAMETER_NAMES, 0.0))
    total = sum(int(np.isfinite(s.xyz).all(axis=1).sum()) for s in small_mission.mission.strips)
    laz = tmp_path / "out.laz"
    proc = run_process("correct", small_mission.bag, "--calibration", calibration, "-o", laz,
                       "-q", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert laspy.read(laz).header.point_count == total
    out = tmp_path / "out.mcap"
    proc = run_process("correct", small_mission.bag, "--calibration", calibration, "-o", out,
                       "-q", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    corrected = 0
    with out.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        for _schema, channel, message in reader.iter_messages(topics=["/lidar/points_corrected"]):
            assert channel.topic == "/lidar/points_corrected"
            corrected += 1
            assert message.data
    with open_bag(small_mission.bag) as bag:
        clouds = sum(1 for _ in bag.messages(["/lidar/points"]))
    assert corrected == clouds
