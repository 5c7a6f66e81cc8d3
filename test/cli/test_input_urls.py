"""Bags and LAS files named by URL (http:// on loopback, as s3:// would be): ``calibrate``,
``correct``, ``evaluate`` and ``import`` give what they give from the paths, serially and on a
two-worker Dask cluster whose workers fetch the bag themselves; ``report`` names the URL with
the bag's digest; a URL that names nothing is refused in one line."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import helpers_dask
import helpers_missions
import laspy
import numpy as np
import pytest
from helpers_cli import one_line_error, run
from helpers_http import served
from helpers_las import plain_strips, write_las_tiles, write_mission_sbet
from helpers_missions import MissionFiles

from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.io.bag.mission_bag import read_mission
from lidarcal_ros.io.report.digest import digest
from lidarcal_ros.io.url_cache import CACHE_ENV
from lidarcal_ros.pipeline.executor import DaskExecutor

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission
small_calibration = helpers_missions.small_calibration
cluster = helpers_dask.cluster


@pytest.fixture(scope="module", autouse=True)
def url_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The copies kept in the test's own cache (set before the module's cluster starts:
    its workers inherit it)."""
    cache = tmp_path_factory.mktemp("url_cache")
    before = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(cache)
    yield cache
    if before is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = before


@pytest.fixture(scope="module")
def site(small_mission: MissionFiles) -> Iterator[str]:
    """The small mission's directory on http://127.0.0.1:PORT."""
    with served(small_mission.bag.parent) as (base, _):
        yield base


def _calibrate(capsys: pytest.CaptureFixture[str], bag: str | Path, config: Path, out: Path,
               *extra: str) -> bytes:
    rc, _, err = run(capsys, "calibrate", bag, "--config", config, "-o", out, "-q", *extra)
    assert rc == 0, err
    return out.read_bytes()


@pytest.mark.parametrize("memory", ["whole", "bounded"])
def test_calibrate_reads_a_bag_url_as_its_path(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles, site: str,
        url_cache: Path, tmp_path: Path, memory: str) -> None:
    config = helpers_missions.write_params_file(tmp_path / "config.yaml", {
        **helpers_missions.FAST_SETTINGS, "calibration.memory": memory,
        "calibration.trajectory.model": "none"})
    url = f"{site}/{small_mission.bag.name}"
    from_path = _calibrate(capsys, small_mission.bag, config, tmp_path / "path.yaml")
    assert _calibrate(capsys, url, config, tmp_path / "url.yaml") == from_path
    assert any(url_cache.rglob("metadata.yaml"))


def test_evaluate_reads_a_bag_url_as_its_path(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles, site: str,
        small_calibration: Path) -> None:
    answers = []
    for bag in (f"{site}/{small_mission.bag.name}", small_mission.bag):
        rc, out, err = run(capsys, "evaluate", bag, "--calibration", small_calibration,
                           "--json")
        assert rc == 0, err
        answers.append(json.loads(out))
    assert answers[0] == answers[1]


def test_the_report_of_a_bag_url_names_it_with_the_paths_digest(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles, site: str,
        small_calibration: Path, tmp_path: Path) -> None:
    url = f"{site}/{small_mission.bag.name}"
    out = tmp_path / "report.html"
    rc, _, err = run(capsys, "report", url, "--calibration", small_calibration, "-o", out,
                     "-q")
    assert rc == 0, err
    page = out.read_text()
    _, sha = digest(small_mission.bag)
    assert url in page and sha in page


def test_workers_fetch_the_bag_themselves(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles, site: str,
        cluster: DaskExecutor, small_calibration: Path, tmp_path: Path) -> None:
    url = f"{site}/{small_mission.bag.name}"
    address = cluster.client.scheduler.address
    # the bounded calibration's sample pass and the correction's parts read it on the workers
    config = helpers_missions.write_params_file(tmp_path / "config.yaml", {
        **helpers_missions.FAST_SETTINGS, "calibration.memory": "bounded",
        "calibration.trajectory.model": "none"})
    assert _calibrate(capsys, url, config, tmp_path / "dask.yaml", "--dask", address) == \
        _calibrate(capsys, small_mission.bag, config, tmp_path / "serial.yaml")
    outputs = {}
    for label, bag, extra in (("url", url, ["--dask", address]),
                              ("path", small_mission.bag, [])):
        out = tmp_path / f"{label}.las"
        rc, _, err = run(capsys, "correct", bag, "--calibration", small_calibration,
                         "-o", out, "-q", *extra)
        assert rc == 0, err
        outputs[label] = laspy.read(out)
    for name in ("X", "Y", "Z", "gps_time", "intensity"):
        assert np.array_equal(outputs["url"][name], outputs["path"][name]), name


def test_import_reads_las_urls_as_their_paths(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    sim = simulate_mission(SimulationSpec.from_options(
        density=0.05, line_length_m=150.0, seed=5, origin=(500_000.0, 5_000_000.0)))
    (tmp_path / "tiles").mkdir()
    tiles = write_las_tiles(plain_strips(sim), tmp_path / "tiles", laz=(1,))
    sbet = write_mission_sbet(sim.mission, tmp_path / "mission.out")
    bags = {}
    with served(tmp_path / "tiles") as (base, requests):
        for label, inputs in (("url", [f"{base}/{t.name}" for t in tiles]),
                              ("path", [str(t) for t in tiles])):
            bags[label] = tmp_path / label
            rc, _, err = run(capsys, "import", *inputs, "--trajectory", sbet,
                             "-o", bags[label])
            assert rc == 0, err
        assert {path.lstrip("/") for method, path in requests if method == "GET"} == \
            {t.name for t in tiles}
    url, path = read_mission(bags["url"]), read_mission(bags["path"])
    assert [s.strip_id for s in url.strips] == [s.strip_id for s in path.strips]
    for a, b in zip(url.strips, path.strips, strict=True):
        assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.t, b.t)


@pytest.mark.parametrize("command", ["calibrate", "correct"])
def test_a_url_naming_nothing_is_refused_in_one_line(
        capsys: pytest.CaptureFixture[str], site: str, small_calibration: Path,
        tmp_path: Path, command: str) -> None:
    extra = ["--calibration", small_calibration] if command == "correct" else []
    rc, _, err = run(capsys, command, f"{site}/no_such_bag", *extra,
                     "-o", tmp_path / "out.las")
    reason = one_line_error(rc, err, command)
    assert reason == f"bag {site}/no_such_bag: not found"
    assert not (tmp_path / "out.las").exists()
