"""``lidarcal report --dask``: the block pass and the evaluation on a two-worker local Dask
cluster give the serial report's content bit for bit, and the command the serial page but
for its time and command line; a worker killed in a strip's pass is replaced and the content
unchanged; the one-line refusals."""

from __future__ import annotations

import re
from pathlib import Path

import helpers_dask
import helpers_missions
import pytest
from helpers_cli import one_line_error, run
from helpers_missions import MissionFiles

from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.io.report.content import ReportContent
from lidarcal_ros.pipeline.executor import DaskExecutor, Executor
from lidarcal_ros.pipeline.report.build import build_report

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory
cluster = helpers_dask.cluster
calibration = helpers_missions.small_calibration


def _content(files: MissionFiles, calibration: Path, executor: Executor | None = None
             ) -> ReportContent:
    """The small mission's report content, its control point as a check point too; without
    the time it was made (the one thing two runs differ in)."""
    content = build_report(files.bag, calibration, load_flight_config(None),
                           check_points_csv=files.control_csv, executor=executor)
    assert content.provenance is not None
    content.provenance.generated = ""
    content.facts = [f for f in content.facts if f[0] != "generated"]
    return content


@pytest.fixture(scope="module")
def serial(small_mission: MissionFiles, calibration: Path) -> ReportContent:
    return _content(small_mission, calibration)


def test_two_workers_give_the_serial_content(
        small_mission: MissionFiles, calibration: Path, cluster: DaskExecutor,
        serial: ReportContent) -> None:
    parted = _content(small_mission, calibration, cluster)
    assert helpers_dask.differences(parted, serial) == []
    # (and content worth comparing: every strip passed, with its radiometry and map; the
    # pairs evaluated; the swath differences fallen after the correction)
    assert len(serial.strips) == len(small_mission.mission.strips)
    assert serial.radiometry is not None and serial.swath is not None
    assert serial.flight is not None and serial.flight.coverage.values.max() >= 2
    assert serial.evaluation is not None and len(serial.evaluation.pairs) >= 10
    before, after = (serial.swath.statistics(w).rmsdz for w in ("before", "after"))
    assert after < 0.5 * before


def test_a_killed_worker_is_replaced_and_the_content_unchanged(
        small_mission: MissionFiles, calibration: Path, cluster: DaskExecutor,
        serial: ReportContent, tmp_path: Path) -> None:
    marker = tmp_path / "killed"
    # (killed in a strip's pass: the strips it held are sent again from the scheduler)
    killing = helpers_dask.KillingExecutor(cluster, marker, part="-pass")
    parted = _content(small_mission, calibration, killing)
    assert marker.exists()  # (a worker did die)
    assert helpers_dask.differences(parted, serial) == []


def test_the_command_through_a_scheduler_writes_the_serial_page(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles, calibration: Path,
        cluster: DaskExecutor, tmp_path: Path) -> None:
    address = cluster.client.scheduler.address
    pages = {}
    for label, extra in (("serial", []), ("dask", ["--dask", address])):
        out = tmp_path / label / "report.html"
        out.parent.mkdir()
        rc, _out, err = run(capsys, "report", small_mission.bag, "--calibration", calibration,
                            "-o", out, "-q", *extra)
        assert rc == 0, err
        # (the time it was made and its command line aside: the figures' bytes too)
        page = re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", "TIME", out.read_text())
        pages[label] = page.replace(f" --dask {address}", "").replace(f"/{label}/", "/")
    assert pages["dask"] == pages["serial"]
    assert pages["serial"].count("data:image/png;base64,") >= 5


@pytest.mark.parametrize(("value", "words"), [
    ("local:0", "--dask local:0: N must be 1 to"),
    ("udp://host:1", "--dask udp://host:1: only a tcp:// scheduler address is supported")])
def test_a_bad_value_is_refused_before_any_work(
        capsys: pytest.CaptureFixture[str], tmp_path: Path, value: str, words: str) -> None:
    # (the bag and the calibration do not exist: the value is refused before they are read)
    rc, _out, err = run(capsys, "report", tmp_path / "missing", "--calibration",
                        tmp_path / "missing.yaml", "-o", tmp_path / "r.html", "--dask", value)
    assert words in one_line_error(rc, err, "report")
    assert not (tmp_path / "r.html").exists()
