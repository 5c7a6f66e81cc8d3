"""``lidarcal calibrate --dask``: the strip pairs matched on a two-worker local Dask cluster (and
by the in-process executor) give the serial estimate bit for bit, whatever the point model,
trajectory model and ``calibration.memory``; a worker killed in a task is replaced and the
estimate unchanged; the one-line refusals."""

from __future__ import annotations

from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import helpers_dask
import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run
from helpers_missions import MissionFiles

from lidarcal_ros.core.calibration.calibrate import calibrate
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.simulation.flight_path import RoughAir
from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.pipeline.calibration.bounded import ReducedMission
from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_for_calibration
from lidarcal_ros.pipeline.executor import DaskExecutor, Executor, SerialExecutor

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission
cluster = helpers_dask.cluster

#: The point models: the small paper mission (level: quasi-rigorous) and one flown in rough
#: air with the INS attitude on its trajectory (rigorous, docs/method.md section 10).
MISSIONS: dict[str, dict[str, Any]] = {
    "level": {},
    "rigorous": {"density": 0.1, "line_length_m": 250.0, "seed": 11, "rough_air": RoughAir()},
}


def _calibrated(files: MissionFiles, executor: Executor | None = None,
                values: dict[str, Any] | None = None) -> CalibrationResult:
    """The mission calibrated with its fast settings and ``values`` (dotted names as
    ``with_values`` takes them), its pairs matched (and a bounded mission's samples chosen)
    by ``executor`` if given."""
    config = load_flight_config(files.fast_config).with_values(**(values or {}))
    mission = load_for_calibration(files.bag, config, executor=executor)
    return calibrate_mission(mission, config, executor=executor)


def _assert_same(parted: CalibrationResult, serial: CalibrationResult) -> None:
    """The same estimate, sigmas, sigma0, iterations, model choices and QA, bit for bit."""
    a, b = parted.solution, serial.solution
    assert np.array_equal(a.delta, b.delta)
    assert np.array_equal(a.sigma, b.sigma, equal_nan=True)
    assert a.sigma0 == b.sigma0 and a.redundancy == b.redundancy
    assert parted.iterations == serial.iterations
    assert parted.trajectory_choice == serial.trajectory_choice
    assert parted.pairs == serial.pairs and parted.control == serial.control
    assert parted.n_pair_correspondences == serial.n_pair_correspondences > 0


#: A tactical INS's errors (``ins.*``): the sigmas allow for them, whatever runs the pairs.
INS_ERRORS = {"ins__position_sigma_m": 0.02, "ins__height_sigma_m": 0.03,
              "ins__attitude_sigma_arcsec": 18.0, "ins__heading_sigma_arcsec": 36.0}


@pytest.mark.parametrize(("kind", "memory", "trajectory", "ins"), [
    ("level", "whole", "auto", False), ("rigorous", "whole", "none", True),
    ("level", "bounded", "none", True)])
def test_two_workers_give_the_serial_estimate(
        mission_factory: Any, cluster: DaskExecutor, kind: str, memory: str,
        trajectory: str, ins: bool) -> None:
    files = mission_factory(**MISSIONS[kind])
    values = {"calibration__memory": memory, "calibration__trajectory__model": trajectory,
              **(INS_ERRORS if ins else {})}
    serial = _calibrated(files, None, values)
    parted = _calibrated(files, cluster, values)
    _assert_same(parted, serial)
    want = PositioningModel.RIGOROUS if kind == "rigorous" else PositioningModel.LEVEL
    assert {c.model for c in parted.models.values()} == {want}
    # (and an estimate worth comparing: the simulated biases found)
    truth = files.sim.biases
    for name in ("dX", "domega"):
        i = ("dX", "dY", "dZ", "domega", "dphi", "dkappa", "dr", "dS").index(name)
        assert abs(parted.solution.delta[i] - truth[name]) < 4 * parted.solution.sigma[i]


def test_the_in_process_executor_gives_the_serial_estimate(small_mission: MissionFiles) -> None:
    values = {"calibration__trajectory__model": "drift"}
    _assert_same(_calibrated(small_mission, SerialExecutor(), values),
                 _calibrated(small_mission, None, values))
    # told the INS's errors, with the strips' trajectory errors reduced out: the same again,
    # the estimate unchanged and every sigma wider
    told = _calibrated(small_mission, SerialExecutor(), {**values, **INS_ERRORS})
    _assert_same(told, _calibrated(small_mission, None, {**values, **INS_ERRORS}))
    plain = _calibrated(small_mission, None, values).solution
    assert np.array_equal(told.solution.delta, plain.delta)
    est = np.isfinite(plain.sigma)
    assert np.all(told.solution.sigma[est] > plain.sigma[est])


class _PlacingExecutor(SerialExecutor):
    """The in-process executor with two made-up places, recording where each task went."""

    def __init__(self) -> None:
        #: (key, place, args) of each task, in order; the place of each future (by id).
        self.tasks: list[tuple[str, str | None, tuple[Any, ...]]] = []
        self.place_of: dict[int, str | None] = {}

    def places(self) -> list[str]:
        return ["tcp://worker-1", "tcp://worker-2"]

    def submit(self, fn: Any, *args: Any, key: str, place: str | None = None) -> Any:
        self.tasks.append((key, place, args))
        future = super().submit(fn, *args, key=key, place=place)
        self.place_of[id(future)] = place
        return future


def test_strips_stay_at_their_homes_and_pairs_go_to_their_surface_strip(
        small_mission: MissionFiles) -> None:
    values = {"calibration__trajectory__model": "auto"}
    placing = _PlacingExecutor()
    _assert_same(_calibrated(small_mission, placing, values),
                 _calibrated(small_mission, None, values))
    kind = {key: key.split("-")[2].rstrip("0123456789") for key, _, _ in placing.tasks}
    strips = [(place, args[0]) for key, place, args in placing.tasks if kind[key] == "strip"]
    # each strip sent once (both of auto's models share it), the pairs' matching shared
    # (15 pairs, strip b of 0 to 5 each: 8 and 7, where dealing by points alone gave 6 and 9)
    assert len({ps.strip_id for _, ps in strips}) == len(strips) == 6
    observed = Counter(place for key, place, _ in placing.tasks if kind[key] == "observe")
    assert min(observed.values()) >= 0.85 * max(observed.values())
    pair_tasks = [(place, args) for key, place, args in placing.tasks
                  if kind[key] in ("choose", "observe", "qa")]
    assert len(pair_tasks) > 2 * 15
    for place, (side, strip, job) in pair_tasks:
        # at the home of strip b, with strip a's matched points cut at strip a's home
        assert place == placing.place_of[id(strip)]
        a = side.result()
        index = job.pair.candidates if job.pair.sample is None else job.pair.sample
        assert len(a.strip) == index.size < len(strip.result().strip)
    cuts = [(place, args) for key, place, args in placing.tasks if kind[key] == "side"]
    homes = {ps.strip_id: place for place, ps in strips}
    assert cuts and all(place == homes[args[0].result().strip_id] for place, args in cuts)
    strip_tasks = [(place, args[0]) for key, place, args in placing.tasks
                   if kind[key] in ("control", "laserqa")]
    assert strip_tasks and all(place == placing.place_of[id(s)] for place, s in strip_tasks)


def test_a_bounded_missions_samples_are_chosen_in_a_pass_a_worker(
        small_mission: MissionFiles) -> None:
    values = {"calibration__trajectory__model": "none", "calibration__memory": "bounded"}
    placing = _PlacingExecutor()
    _assert_same(_calibrated(small_mission, placing, values),
                 _calibrated(small_mission, None, values))
    passes = [(place, args) for key, place, args in placing.tasks if "-samples" in key]
    # one task a worker, the pairs dealt between them, each pair once
    assert sorted(str(place) for place, _ in passes) == placing.places()
    dealt = [len(args[1]) for _, args in passes]
    assert min(dealt) >= 1 and sum(dealt) == 15


@pytest.mark.parametrize("kind", sorted(MISSIONS))
def test_a_bounded_serial_run_matches_as_tasks_with_the_threads_estimate(
        mission_factory: Any, kind: str) -> None:
    files = mission_factory(**MISSIONS[kind])
    config = load_flight_config(files.fast_config).with_values(
        calibration__memory="bounded", calibration__trajectory__model="auto")
    mission = load_for_calibration(files.bag, config)
    assert isinstance(mission, ReducedMission)
    # (the serial command's way, one strip b's pairs after another in this process, against
    # the matcher's own threads on the same reduced mission)
    tasks = calibrate_mission(mission, config)
    threads = calibrate(mission, config.calibration_settings(), whole=mission.whole,
                        samples=mission.samples)
    _assert_same(tasks, threads)


class _HeldCorrections(_PlacingExecutor):
    """The placing executor counting, as each task starts, the strips (as sent, whole)
    holding a correction."""

    def __init__(self) -> None:
        super().__init__()
        self.sent: list[Any] = []
        self.held: list[tuple[str, int]] = []

    def submit(self, fn: Any, *args: Any, key: str, place: str | None = None) -> Any:
        if "-strip" in key:
            self.sent.append(args[0])
        self.held.append((key, sum(ps.corrected is not None for ps in self.sent)))
        return super().submit(fn, *args, key=key, place=place)


def test_one_whole_strip_is_corrected_at_a_time(small_mission: MissionFiles) -> None:
    values = {"calibration__trajectory__model": "drift", "calibration__memory": "bounded"}
    held = _HeldCorrections()
    _assert_same(_calibrated(small_mission, held, values),
                 _calibrated(small_mission, None, values))
    kinds = Counter(key.split("-")[2].rstrip("0123456789") for key, _ in held.held)
    assert kinds["observe"] > 2 * 15 and kinds["release"] >= kinds["observe"] // 15
    # each task finds at most the strip it runs at corrected (of the strips as sent)
    assert max(n for _, n in held.held) == 1
    assert all(ps.corrected is None for ps in held.sent)
    # the pairs of one strip b matched together, then it released before the next b's
    last, released = None, True
    for key, _, args in held.tasks:
        name = key.split("-")[2]
        if name.startswith("release") and args[0] is last:
            released = True
        elif name.startswith("observe") and args[1] is not last:
            assert released, key
            last, released = args[1], False


class _TwoThreads(SerialExecutor):
    """Tasks in two threads of this process, as a Dask worker of two threads runs them (a
    task's future arguments waited for in its thread)."""

    def __init__(self) -> None:
        self.pool = ThreadPoolExecutor(2)

    def submit(self, fn: Any, *args: Any, key: str, place: str | None = None) -> Any:
        return self.pool.submit(
            lambda: fn(*(a.result() if isinstance(a, Future) else a for a in args)))


@pytest.mark.parametrize("memory", ["whole", "bounded"])
def test_a_worker_of_two_threads_gives_the_serial_estimate(
        small_mission: MissionFiles, memory: str) -> None:
    # (two tasks of one strip share its latest correction, and a release forgets it: they
    # take the strip in turn)
    values = {"calibration__trajectory__model": "drift", "calibration__memory": memory}
    threads = _TwoThreads()
    try:
        _assert_same(_calibrated(small_mission, threads, values),
                     _calibrated(small_mission, None, values))
    finally:
        threads.pool.shutdown()


def test_a_killed_worker_is_replaced_and_the_estimate_unchanged(
        small_mission: MissionFiles, cluster: DaskExecutor, tmp_path: Path) -> None:
    values = {"calibration__trajectory__model": "none"}
    serial = _calibrated(small_mission, None, values)
    marker = tmp_path / "killed"
    # (killed in an iteration's matching: the strips it held are prepared again elsewhere)
    killing = helpers_dask.KillingExecutor(cluster, marker, part="-observe")
    parted = _calibrated(small_mission, killing, values)
    assert marker.exists()  # (a worker did die)
    _assert_same(parted, serial)


def test_the_command_through_a_scheduler_writes_the_serial_file(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles,
        cluster: DaskExecutor, tmp_path: Path) -> None:
    config = helpers_missions.write_params_file(tmp_path / "config.yaml", {
        **helpers_missions.FAST_SETTINGS, "calibration.trajectory.model": "none"})
    docs = {}
    for label, extra in (("serial", []), ("dask", ["--dask", cluster.client.scheduler.address])):
        out = tmp_path / f"{label}.yaml"
        rc, _out, err = run(capsys, "calibrate", small_mission.bag, "--config", config,
                            "-o", out, "-q", *extra)
        assert rc == 0, err
        doc = yaml.safe_load(out.read_text())["lidarcal_calibration"]
        docs[label] = doc
    assert docs["dask"]["biases"] == docs["serial"]["biases"]
    assert docs["dask"] == docs["serial"]


@pytest.mark.parametrize(("value", "words"), [
    ("local:0", "--dask local:0: N must be 1 to"),
    ("tcp://nowhere", "--dask tcp://nowhere: expected tcp://HOST:PORT")])
def test_a_bad_value_is_refused_before_any_work(
        capsys: pytest.CaptureFixture[str], tmp_path: Path, value: str, words: str) -> None:
    rc, _out, err = run(capsys, "calibrate", tmp_path / "missing", "-o", tmp_path / "cal.yaml",
                        "--dask", value)
    assert words in one_line_error(rc, err, "calibrate")
    assert not (tmp_path / "cal.yaml").exists()
