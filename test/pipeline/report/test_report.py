"""``lidarcal report``: the HTML QA report, end to end on a small simulated mission.

The mission (helpers_missions, paper configuration and biases, the simulator's radiometric
constant as the calibration constant) is calibrated with ``lidarcal calibrate`` and evaluated
with ``lidarcal evaluate --json``; the report of the same bag under that calibration must
reproduce the calibration's own pair QA and control residuals, show the block (strips, their
flight lines, control and check points) as simulated, the swath-to-swath height differences
falling to the noise after calibration, evaluate's co-alignment and check points number for
number, the USGS LBS level those numbers meet, an absolute reflectance matching the simulated
one, the inputs with their SHA-256; be one self-contained file, and render every figure in
headless Chromium.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import html.parser
import json
import math
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_missions import FAST_SETTINGS, MissionFiles, write_params_file
from helpers_paths import REPO

from lidarcal_ros import __version__
from lidarcal_ros.cli.main import main
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.qa.quality_level import LBS_LEVELS, assess
from lidarcal_ros.core.simulation.scanning import INTENSITY_K
from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.io.report.content import ReportContent
from lidarcal_ros.io.report.page import figure_ids, render_html
from lidarcal_ros.io.survey.las_writer import parse_crs
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.report.block import FOOTPRINT_CELL_M, block_grids, block_pass
from lidarcal_ros.pipeline.report.build import build_report, trajectory_section
from lidarcal_ros.pipeline.report.calibration import read_report_calibration
from lidarcal_ros.pipeline.report.radiometry import (
    mean_raster,
    radiometry_section,
    slope_class_statistics,
)

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory

ROOT = REPO
#: The simulator's intensity of a reflectance-1 target at 1000 m (the reference range).
SIMULATOR_CONSTANT = INTENSITY_K / 1000.0**2
SECTIONS = ("summary", "quality", "block", "calibration", "swath", "pairs", "evaluation",
            "control", "radiometry", "provenance")


# ------------------------------------------------------------------ fixtures
@dataclasses.dataclass(frozen=True)
class Reported:
    """A calibrated and evaluated small mission and its report."""

    mission: MissionFiles
    calibration: Path
    config: Path
    evaluation: Path
    html: Path
    content: ReportContent
    cli_stdout: str
    cli_stderr: str


def _run(capsys: pytest.CaptureFixture[str], *args: Any) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def reported(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory
             ) -> Reported:
    """``lidarcal calibrate``, ``lidarcal evaluate --json`` and ``lidarcal report`` (CLI,
    in-process; the report evaluates by itself) on the small mission; the report's content
    computed once more through the pipeline, with the saved evaluation, for the numbers."""
    work = tmp_path_factory.mktemp("report")
    config = write_params_file(work / "config.yaml", {
        **FAST_SETTINGS, "radiometry.calibration_constant": SIMULATOR_CONSTANT})
    cal = work / "calibration.yaml"
    out = work / "report.html"
    evaluation = work / "evaluation.json"
    files = small_mission
    common = ["--config", config, "--control", files.control_csv]
    assert main([str(a) for a in ["calibrate", files.bag, "-o", cal, *common]]) == 0
    stdout, _ = _capture(["evaluate", files.bag, "--calibration", cal, "--config", config,
                          "--check-points", files.control_csv, "--json"])
    evaluation.write_text(stdout)
    stdout, stderr = _capture(["report", files.bag, "--calibration", cal, "-o", out, *common,
                               "--check-points", files.control_csv, "--crs", "EPSG:32633"])
    content = build_report(files.bag, cal, load_flight_config(config),
                           control_csv=files.control_csv, config_source=config,
                           check_points_csv=files.control_csv, evaluation_json=evaluation,
                           crs=parse_crs("EPSG:32633"))
    return Reported(files, cal, config, evaluation, out, content, stdout, stderr)


def _capture(args: list[Any]) -> tuple[str, str]:
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    assert rc == 0, out.getvalue() + err.getvalue()
    return out.getvalue(), err.getvalue()


def _calibration_doc(path: Path) -> dict[str, Any]:
    return yaml.safe_load(path.read_text())["lidarcal_calibration"]


class _Page(html.parser.HTMLParser):
    """Every ``<img>`` with its attributes, ``<body>``'s attributes, the text of each
    ``<section>`` and the cells of each table row by section."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[dict[str, str]] = []
        self.body: dict[str, str] = {}
        self.text: dict[str, str] = {}
        self.rows: dict[str, list[list[str]]] = {}
        self._section = ""
        self._row: list[str] | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = {k: v or "" for k, v in attrs}
        if tag == "img":
            self.images.append(values)
        elif tag == "body":
            self.body = values
        elif tag == "section":
            self._section = values.get("id", "")
            self.text[self._section] = ""
            self.rows[self._section] = []
        elif tag == "tr":
            self._row = []
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._row is not None and self._cell is not None:
            self._row.append("".join(self._cell).strip())
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self.rows.setdefault(self._section, []).append(self._row)
            self._row = None

    def handle_data(self, data: str) -> None:
        if self._section:
            self.text[self._section] += data
        if self._cell is not None:
            self._cell.append(data)

    def table(self, section: str, first: str) -> dict[str, list[str]]:
        """Rows of a section whose first cells are given, by that cell (the first match)."""
        out: dict[str, list[str]] = {}
        for row in self.rows[section]:
            if row and row[0] not in out:
                out[row[0]] = row
        return out


def _parse(text: str) -> _Page:
    parser = _Page()
    parser.feed(text)
    return parser


@pytest.fixture(scope="module")
def page(reported: Reported) -> _Page:
    return _parse(reported.html.read_text(encoding="utf-8"))


# ------------------------------------------------------------------ strip pairs
def test_pair_rms_before_and_after_reproduce_the_calibration_qa(reported: Reported) -> None:
    """Per strip pair, the report's RMS before (zero biases) and after (the estimate) are the
    calibration's own QA numbers; before is large (the paper's biases: decimetres) and after
    at the noise level (2 cm range noise)."""
    doc = _calibration_doc(reported.calibration)
    qa = {tuple(p["strips"]): p for p in doc["strip_pairs"]}
    pairs = reported.content.pairs
    assert {p.strips for p in pairs} == set(qa), "the report covers every calibrated pair"
    for p in pairs:
        ref = qa[p.strips]
        assert p.before.rms == pytest.approx(ref["rms_before_m"], rel=0.02, abs=0.002), p.strips
        assert p.after.rms == pytest.approx(ref["rms_after_m"], rel=0.02, abs=0.002), p.strips
        assert p.after.p95 == pytest.approx(ref["p95_after_m"], rel=0.02, abs=0.002), p.strips
        assert p.after.rms < 0.04, p.strips
        assert p.after.rms < p.before.rms, p.strips
        assert p.qa_level == "OK"
        # positions in the overlap: inside the mission, one per discrepancy
        assert p.after.xy.shape == (p.after.distance.size, 2)
        assert p.after.distance.size > 500
    before = np.array([p.before.rms for p in pairs])
    after = np.array([p.after.rms for p in pairs])
    assert before.max() > 0.15 and np.median(before) > 0.08
    assert np.median(before / after) > 4.0


def test_control_residuals_before_and_after(reported: Reported) -> None:
    """The control point's residuals against every strip that sees it, as in the calibration
    file; after calibration they shrink (dr and the boresight biases removed)."""
    doc = _calibration_doc(reported.calibration)
    control = reported.content.control
    assert control, "the mission's control point is seen by its strips"
    ref = {(c["id"], c["strip"]): c for c in doc["control_residuals"]}
    assert {(c.control_id, c.strip_id) for c in control} == set(ref)
    for c in control:
        r = ref[(c.control_id, c.strip_id)]
        assert c.before == pytest.approx(r["before_m"], abs=1e-6)
        assert c.after == pytest.approx(r["after_m"], abs=1e-6)
    before = np.sqrt(np.mean([c.before**2 for c in control]))
    after = np.sqrt(np.mean([c.after**2 for c in control]))
    assert after < 0.5 * before


def test_bias_table_and_correlation_from_the_calibration_file(reported: Reported,
                                                              page: _Page) -> None:
    doc = _calibration_doc(reported.calibration)
    content = reported.content
    assert [b.name for b in content.biases] == list(doc["biases"])
    rows = page.table("calibration", "parameter")
    for b in content.biases:
        entry = doc["biases"][b.name]
        assert b.value == entry["value"]
        if entry["estimated"]:
            assert b.state == "estimated" and b.sigma == entry["sigma"]
        else:
            assert b.state in ("fixed", "not_estimable") and b.sigma is None
        if b.name == "dr":
            assert rows["dr"][1:4] == [f"{entry['value'] * 100:+.2f}",
                                       f"{entry['sigma'] * 100:.2f}", "cm"]
    assert content.correlation_names == doc["correlation"]["names"]
    np.testing.assert_allclose(content.correlation, doc["correlation"]["matrix"])
    facts = dict((r[0], r[1]) for r in page.rows["calibration"] if len(r) == 2)
    assert facts["sigma0 (a posteriori)"] == f"{doc['sigma0'] * 100:.2f} cm"
    assert facts["iterations"] == str(doc["iterations"])
    assert facts["point-positioning model"] == doc["model_detail"]


# ------------------------------------------------------------------ block
def test_block_table_and_map_show_the_flight_as_simulated(reported: Reported,
                                                          page: _Page) -> None:
    """One row per strip: its points, the line's flying height above the (near-zero) ground,
    its course, duration and speed as simulated, and points over footprint as density; the
    map holds each strip's line, the control and the check points."""
    sim = reported.mission.sim
    content = reported.content
    lines = {ln["id"]: ln for ln in sim.lines}
    rows = {r.strip_id: r for r in content.strips}
    assert set(rows) == {s.strip_id for s in sim.mission.strips}
    table = page.table("block", "strip")
    for strip in sim.mission.strips:
        row, line = rows[strip.strip_id], lines[strip.strip_id]
        assert row.points == len(strip)
        assert row.height_m == pytest.approx(line["height"], abs=5.0)
        course = math.degrees(math.atan2(*line["direction"])) % 360.0
        assert abs((row.heading_deg - course + 180.0) % 360.0 - 180.0) < 0.5
        assert row.duration_s == pytest.approx(line["t_last"] - line["t_first"], abs=0.01)
        assert row.speed_mps == pytest.approx(sim.config["speed_mps"], rel=0.02)
        assert 0.02 < row.density_per_m2 < 2.0
        cells = table[str(strip.strip_id)]
        assert cells[1] == str(len(strip)) and cells[5] == f"{row.heading_deg:.1f}"
        assert cells[7] == f"{row.height_m:.0f}"
    flight = content.flight
    assert flight is not None
    assert [sid for sid, _ in flight.lines] == [s.strip_id for s in sim.mission.strips]
    control = sim.mission.control
    assert control is not None
    assert [c[0] for c in flight.control] == control.ids == [c[0] for c in flight.check]
    assert flight.coverage.values.max() >= 4  # the paper's block: up to six strips overlap
    assert "EPSG:32633" in page.text["block"]


# ------------------------------------------------------------------ swath differences
def test_swath_differences_fall_to_the_noise_after_calibration(reported: Reported,
                                                                page: _Page) -> None:
    """Over smooth ground every pair's heights differ by decimetres before (boresight and
    range biases) and by the noise after (2 cm range noise: RMSDz under 3 cm), on the same
    cells; the table gives those numbers, the mosaics are one scale of +-16 cm."""
    swath = reported.content.swath
    assert swath is not None
    assert {p.strips for p in swath.pairs} == {p.strips for p in reported.content.pairs}
    before, after = swath.statistics("before"), swath.statistics("after")
    assert after.n_cells > 20_000
    assert after.rmsdz < 0.03 and before.rmsdz > 4 * after.rmsdz
    assert after.max_abs < 0.16
    for p in swath.pairs:
        assert abs(float(np.mean(p.after))) < 0.005, p.strips  # no offset left
        assert p.earlier < p.later  # the simulator flies the lines in id order
    table = page.table("swath", "all")
    assert table["all"][2:5] == [str(after.n_cells), f"{before.rmsdz * 100:.1f}",
                                 f"{after.rmsdz * 100:.1f}"]
    assert np.isfinite(swath.before).sum() > 1000 and np.isfinite(swath.after).sum() > 1000
    assert "one colour scale of \u00b116 cm" in page.text["swath"]


# ------------------------------------------------------------------ evaluation
def test_evaluate_results_are_folded_in(reported: Reported, page: _Page) -> None:
    """The co-alignment of every pair and the check-point residuals are lidarcal evaluate's:
    the report read from its JSON holds its numbers, and the report that evaluated by itself
    (the CLI's) shows the same tables."""
    doc = json.loads(reported.evaluation.read_text())
    section = reported.content.evaluation
    assert section is not None and str(reported.evaluation) in section.source
    by_pair = {(a, b): (before, after) for a, b, before, after in section.pairs}
    for p in doc["pairs"]:
        before, after = by_pair[tuple(p["strips"])]
        for state, fit in (("before", before), ("after", after)):
            assert fit is not None
            assert fit.rms_after == pytest.approx(p[state]["rms_after_m"], abs=1e-12)
            assert fit.n_matches == p[state]["matches"]
            for i, name in enumerate(("tx", "ty", "tz", "omega", "phi", "kappa")):
                value = p[state]["values"][name]
                assert (math.isnan(fit.values[i]) if value is None
                        else fit.values[i] == pytest.approx(value, abs=1e-12))
    residuals = {c["id"]: c for c in doc["check_points"]["residuals"]}
    assert {c[0] for c in section.check} == set(residuals)
    assert section.summary("after").rmse == pytest.approx(doc["check_points"]["after"]["rmse"])
    # The CLI's report evaluated by itself: the same tables.
    from_json = _parse(render_html(reported.content)).rows["evaluation"]
    assert page.rows["evaluation"] == from_json
    rows = page.table("evaluation", "after")
    summary = doc["check_points"]["after"]
    assert rows["after"][1:5] == [str(summary["n"]), f"{summary['mean'] * 100:+.1f}",
                                  f"{summary['std'] * 100:.1f}", f"{summary['rmse'] * 100:.1f}"]


# ------------------------------------------------------------------ quality level
def test_quality_level_follows_the_lbs_thresholds() -> None:
    """Each measure against each level; a level is met when every assessed measure is."""
    ql2 = assess(rmsdz_m=0.05, max_dz_m=0.12, anpd_per_m2=3.0, nva_rmse_m=0.08,
                 n_check_points=30)
    assert ql2.best is not None and ql2.best.name == "QL2"
    assert ql2.statement() == ("Meets USGS LBS QL2 on interswath RMSDz, interswath max |dz|, "
                               "NVA RMSEz, aggregate nominal pulse density; QL1 is missed on "
                               "aggregate nominal pulse density.")
    ql0 = assess(rmsdz_m=0.02, max_dz_m=0.07, anpd_per_m2=10.0)
    assert ql0.best is not None and ql0.best.name == "QL0"
    assert ql0.statement().endswith("not assessed: NVA RMSEz.")
    low = assess(rmsdz_m=0.2, max_dz_m=0.3, anpd_per_m2=1.0)
    assert low.best is None and "QL3 is missed on interswath RMSDz" in low.statement()
    assert [level.name for level in LBS_LEVELS] == ["QL0", "QL1", "QL2", "QL3"]


def test_report_states_the_level_its_numbers_meet(reported: Reported, page: _Page) -> None:
    """The measures are the report's own numbers (swath differences after calibration,
    points over covered area, evaluate's check-point RMSE), and the level the thresholds
    give: this sparse mission (0.4 points/m^2) meets none, for its density."""
    content = reported.content
    quality = content.quality
    assert quality is not None and content.swath is not None
    measured = {c.name: c.value for c in quality.criteria}
    after = content.swath.statistics("after")
    assert measured["interswath RMSDz"] == after.rmsdz
    assert measured["interswath max |dz|"] == after.max_abs
    assert content.evaluation is not None
    assert measured["NVA RMSEz"] == content.evaluation.summary("after").rmse
    # The density: every point over the area of the 10 m cells any strip covers.
    strips = reported.mission.mission.strips
    corner = np.min([s.xyz[:, :2].min(axis=0) for s in strips], axis=0)
    cells = np.unique(np.concatenate([np.floor((s.xyz[:, :2] - corner) / FOOTPRINT_CELL_M)
                                      for s in strips]), axis=0)
    n_points = sum(len(s) for s in strips)
    assert measured["aggregate nominal pulse density"] == pytest.approx(
        n_points / (len(cells) * FOOTPRINT_CELL_M**2), rel=1e-9)
    expected = next((level.name for level in LBS_LEVELS
                     if after.rmsdz <= level.rmsdz_m and after.max_abs <= level.max_dz_m
                     and measured["NVA RMSEz"] <= level.nva_rmse_m
                     and measured["aggregate nominal pulse density"] >= level.anpd_per_m2),
                    None)
    # Relative accuracy within QL0's thresholds but for the largest difference; too sparse
    # for any level.
    assert after.rmsdz <= 0.04 and after.max_abs <= 0.16
    assert quality.best is None and expected is None
    assert quality.statement().startswith("Does not meet USGS LBS QL3 on ")
    assert "QL3 is missed on aggregate nominal pulse density." in quality.statement()
    assert quality.statement() in page.text["summary"]
    assert "USGS LBS none" in reported.cli_stdout
    levels = page.table("quality", "measure")
    assert levels["interswath RMSDz"][1] == f"{after.rmsdz * 100:.1f} cm"


# ------------------------------------------------------------------ radiometry
def test_reflectance_is_the_simulated_lambertian_reflectance(reported: Reported,
                                                             page: _Page) -> None:
    """With the calibration constant in the configuration, the report's reflectance map
    holds the simulated surfaces' reflectance, cell by cell, and says what it is."""
    section = reported.content.radiometry
    assert section is not None and section.unit == "1"
    assert "Lambertian reflectance" in section.meaning
    assert section.meaning in page.text["radiometry"].replace("\n", " ")
    sim = reported.mission.sim
    raster = section.reflectance
    truth = mean_raster(np.concatenate([x[:, :2] for x in sim.true_xyz]),
                        np.concatenate(sim.reflectance_true), x0=raster.x0, y0=raster.y0,
                        cell_m=raster.cell_m, shape=raster.values.shape)
    both = np.isfinite(raster.values) & np.isfinite(truth.values)
    assert both.sum() > 1000
    ratio = raster.values[both] / truth.values[both]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.03)
    assert np.median(np.abs(ratio - 1.0)) < 0.06


def test_vmr_of_intensity_falls_after_radiometric_correction_on_gentle_slopes(
    reported: Reported,
) -> None:
    """The paper's Fig. 5: the variance-to-mean ratio of reflectance (on the intensity's
    scale) is below that of the recorded intensity in every class under 30 degrees (ranges of
    540 m and 1150 m, and incidence, no longer spread the values)."""
    section = reported.content.radiometry
    assert section is not None
    gentle = [c for c in section.slope_classes if c.hi_deg <= 30.0]
    assert len(gentle) == 3
    assert all(c.n_points > 100 for c in gentle)
    for c in gentle:
        assert c.vmr_reflectance < 0.8 * c.vmr_intensity, c
        assert c.change < -0.2
    assert section.n_used > 0.5 * section.n_points
    assert np.isfinite(section.reflectance.values).mean() > 0.3
    assert section.reflectance.values.shape == section.intensity.values.shape


def test_slope_class_statistics_and_mean_raster_on_known_values() -> None:
    rng = np.random.default_rng(3)
    slope = np.concatenate([np.full(4000, 5.0), np.full(4000, 25.0), np.full(10, 45.0)])
    intensity = np.concatenate([rng.poisson(100.0, 4000), rng.poisson(400.0, 4000),
                                np.ones(10)]).astype(float)
    classes = slope_class_statistics(slope, intensity, intensity / 4.0,
                                     (0.0, 10.0, 30.0, 90.0), min_points=20)
    assert [c.n_points for c in classes] == [4000, 4000, 10]
    assert classes[0].vmr_intensity == pytest.approx(1.0, rel=0.1)  # Poisson: VMR 1
    assert classes[1].vmr_intensity == pytest.approx(1.0, rel=0.1)
    # A reflectance proportional to the intensity, in any unit, has the same VMR.
    assert classes[0].vmr_reflectance == pytest.approx(classes[0].vmr_intensity)
    assert classes[0].mean_reflectance == pytest.approx(classes[0].mean_intensity / 4.0)
    assert classes[0].change == pytest.approx(0.0, abs=1e-9)
    # Halving the spread about each class's mean halves the VMR.
    means = np.where(slope < 10, 100.0, np.where(slope < 30, 400.0, 1.0))
    calmer = slope_class_statistics(slope, intensity, (means + intensity) / 2.0,
                                    (0.0, 10.0, 30.0, 90.0), min_points=20)
    assert calmer[0].change == pytest.approx(-0.75, abs=0.05)
    assert np.isnan(classes[2].vmr_intensity)  # too few points
    xy = np.array([[0.5, 0.5], [0.6, 0.4], [1.5, 0.5], [9.0, 9.0]])
    raster = mean_raster(xy, np.array([1.0, 3.0, 5.0, 7.0]), x0=0.0, y0=0.0, cell_m=1.0,
                         shape=(2, 3))
    assert raster.values[0, 0] == 2.0 and raster.values[0, 1] == 5.0
    assert np.isnan(raster.values[1]).all()  # the point at (9, 9) is outside


def test_clouds_without_intensity_report_no_radiometry(reported: Reported) -> None:
    mission: Mission = reported.mission.mission
    no_intensity = dataclasses.replace(
        mission, strips=[dataclasses.replace(s, intensity=None) for s in mission.strips])
    config = load_flight_config(reported.config)
    settings = CorrectionSettings.from_config(
        config, read_report_calibration(reported.calibration).record)
    footprint, swath, maps = block_grids(no_intensity, config)
    passed = block_pass(no_intensity, settings, swath_grid=swath, footprint_grid=footprint,
                        map_grid=maps)
    assert radiometry_section(passed, settings, maps) is None
    assert len(passed.surfaces) == len(mission.strips)  # the geometry is there all the same
    content = dataclasses.replace(reported.content, pairs=[], radiometry=None)
    text = render_html(content)
    assert "no intensity" in text
    assert 'id="fig-vmr-slope"' not in text and 'id="fig-reflectance-map"' not in text
    assert {img.get("id") for img in _parse(text).images} == figure_ids(content)


# ------------------------------------------------------------------ summary and provenance
def test_a_thinned_report_uses_and_says_the_calibration_s_thinning(reported: Reported
                                                                     ) -> None:
    """With ``calibration.thinning_cell_m`` the report reads the points as the calibration
    does (the same sample points) and says how many were left out."""
    from lidarcal_ros.pipeline.calibration.procedure import load_mission

    files = reported.mission
    config = load_flight_config(files.fast_config).with_values(
        calibration__thinning_cell_m=2.0)
    thinned = load_mission(files.bag, config)
    assert 0 < thinned.thinned_points < files.mission.n_points
    content = build_report(files.bag, reported.calibration, config,
                           control_csv=files.control_csv, evaluation_json=reported.evaluation)
    facts = dict(content.facts)
    assert facts["points thinned"].startswith(f"{thinned.thinned_points} left out")
    assert f"{thinned.n_points} points" in facts["mission"]
    assert "points thinned" not in dict(reported.content.facts)


def test_the_report_says_where_the_heading_comes_from(reported: Reported) -> None:
    # the small mission's poses carry identity orientations: the track, as docs/method.md
    assert dict(reported.content.facts)["heading"] == (
        "from the track (the poses carry no orientation)")


def _sha256_of_tree(path: Path) -> tuple[int, str]:
    """Independently of lidarcal: the files of a directory, relative names and contents."""
    sha = hashlib.sha256()
    size = 0
    for root, dirs, names in os.walk(path):
        dirs.sort()
        for name in sorted(names):
            file = Path(root) / name
            data = file.read_bytes()
            sha.update(file.relative_to(path).as_posix().encode() + b"\0" + data)
            size += len(data)
    return size, sha.hexdigest()


def test_provenance_names_every_input_with_its_size_and_hash(reported: Reported,
                                                             page: _Page) -> None:
    provenance = reported.content.provenance
    assert provenance is not None and provenance.version == __version__
    generated = datetime.datetime.strptime(provenance.generated, "%Y-%m-%d %H:%M:%S UTC")
    assert abs(datetime.datetime.now() - generated) < datetime.timedelta(days=1)
    files = {f.role: f for f in provenance.inputs}
    assert set(files) == {"bag", "calibration", "flight configuration", "control points",
                          "check points", "evaluation"}
    for role in ("calibration", "flight configuration", "evaluation"):
        data = Path(files[role].path).read_bytes()
        assert files[role].size_bytes == len(data)
        assert files[role].sha256 == hashlib.sha256(data).hexdigest()
    assert (files["bag"].size_bytes, files["bag"].sha256) == _sha256_of_tree(
        reported.mission.bag)
    rows = page.table("provenance", "input")
    assert rows["bag"][3] == _sha256_of_tree(reported.mission.bag)[1]
    text = page.text["provenance"]
    assert f"radiometry.calibration_constant = {SIMULATOR_CONSTANT:g}" in text
    assert "lidarcal report " in text  # the command line
    changed = [r for r in page.rows["provenance"] if r and r[0] == "matching.per_class_cap"]
    assert changed and changed[0][1] == str(FAST_SETTINGS["matching.per_class_cap"])


# ------------------------------------------------------------------ the HTML file
def test_html_is_one_self_contained_file_with_every_section(reported: Reported,
                                                            page: _Page) -> None:
    text = reported.html.read_text(encoding="utf-8")
    assert "report written to" in reported.cli_stdout
    lowered = text.lower()
    assert "http://" not in lowered and "https://" not in lowered
    assert "<link" not in lowered and "@import" not in lowered and "url(" not in lowered
    ids = [img.get("id") for img in page.images]
    assert set(ids) == figure_ids(reported.content) >= {
        "fig-flight-map", "fig-swath-dz", "fig-correlation", "fig-vmr-slope",
        "fig-reflectance-map"}
    assert len(ids) == len(set(ids))
    for img in page.images:
        assert img["src"].startswith("data:image/png;base64,"), img["id"]
        assert img.get("alt"), img["id"]
    assert list(page.text) == list(SECTIONS)
    # (no trajectory errors in this calibration: no such section, nor a link to it)
    assert reported.content.trajectory is None and 'href="#trajectory"' not in text
    for b in reported.content.biases:
        assert f"<td>{b.name}</td>" in text
    for c in reported.content.control:
        assert f"<td>{c.control_id}</td>" in text


def test_trajectory_errors_get_a_section_with_each_strip(reported: Reported, tmp_path: Path
                                                          ) -> None:
    """A calibration holding trajectory errors: a section after the calibration's with the
    model as the file says it, a figure of each strip's E, N, U error over time, and a row per
    strip with its offset and drift and their sigmas (cm, mm/s), read from the file; a strip
    of the file the bag lacks is listed as such."""
    from lidarcal_ros.core.trajectory.strip_errors import (
        StripError,
        TrajectoryEstimate,
        TrajectoryModel,
    )
    from lidarcal_ros.io.calibration_file import trajectory_document

    mission = reported.mission.mission
    strips = {}
    for k, strip in enumerate(mission.strips):
        t_ref = 0.5 * float(strip.t.min() + strip.t.max())
        strips[strip.strip_id] = StripError.linear(
            strip.strip_id, t_ref, np.array([0.01 * k, -0.02, 0.03]),
            np.array([0.02, 0.02, 0.01]), np.array([0.001, 0.0, -0.0005 * k]),
            np.array([0.0015, 0.0015, 0.0008]))
    strips[99] = StripError.linear(99, 1e9, np.zeros(3), np.full(3, 0.05), np.zeros(3),
                                   np.full(3, 0.002))
    doc = yaml.safe_load(reported.calibration.read_text())
    doc["lidarcal_calibration"]["trajectory"] = trajectory_document(
        TrajectoryEstimate(TrajectoryModel.DRIFT, strips))
    doc["lidarcal_calibration"]["trajectory_model"] = "auto: drift (a reason)"
    path = tmp_path / "with_trajectory.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    section = trajectory_section(mission, read_report_calibration(path))
    assert section is not None and section.choice == "auto: drift (a reason)"
    assert set(section.spans) == {s.strip_id for s in mission.strips}
    content = dataclasses.replace(reported.content, trajectory=section)
    text = render_html(content)
    page = _parse(text)
    assert list(page.text) == [*SECTIONS[:4], "trajectory", *SECTIONS[4:]]
    assert 'href="#trajectory"' in text and "auto: drift (a reason)" in page.text["trajectory"]
    ids = [img.get("id") for img in page.images]
    assert set(ids) == figure_ids(content) and "fig-trajectory-errors" in ids
    rows = page.table("trajectory", "strip")
    assert rows["strip"][3:] == ["offset E (cm)", "offset N (cm)", "offset U (cm)",
                                 "drift E (mm/s)", "drift N (mm/s)", "drift U (mm/s)"]
    for k, strip in enumerate(mission.strips):
        row = rows[str(strip.strip_id)]
        assert row[3:6] == [f"+{k:.1f} \u00b1 2.0", "-2.0 \u00b1 2.0", "+3.0 \u00b1 1.0"]
        assert row[6] == "+1.00 \u00b1 1.50" and row[8].endswith("\u00b1 0.80")
    assert rows["99"][1] == "not in the bag"
    assert "covariance of offset and drift left out" in text


def test_progress_is_reported_and_quiet_off_a_terminal(reported: Reported) -> None:
    """Every stage calls the progress callback (the CLI's bar shows it on a terminal); off a
    terminal, as here, the CLI writes nothing to stderr."""
    stages: list[str] = []
    content = build_report(reported.mission.bag, reported.calibration,
                           load_flight_config(reported.config),
                           evaluation_json=reported.evaluation,
                           progress=lambda stage, _fraction: stages.append(stage))
    from lidarcal_ros.io.report.page import render_html as render

    render(content, progress=lambda stage, _fraction: stages.append(stage))
    for stage in ("reading the bag", "hashing bag", "choosing sample points",
                  "correcting strips", "drawing figures"):
        assert stage in stages, (stage, sorted(set(stages)))
    assert reported.cli_stderr == ""


def test_cli_report_bad_input_is_one_line(reported: Reported, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    m = reported.mission
    out = tmp_path / "r.html"

    def error(*args: Any) -> str:
        rc, _, err = _run(capsys, "report", *args)
        assert rc == 1, err
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("lidarcal report: error: "), err
        assert "Traceback" not in err
        return lines[0]

    cal = ["--calibration", reported.calibration]
    assert "exists" in error(m.bag, *cal, "-o", reported.html)
    assert "missing.yaml" in error(m.bag, "--calibration", tmp_path / "missing.yaml",
                                   "-o", out)
    bad = tmp_path / "bad.yaml"
    doc = yaml.safe_load(reported.calibration.read_text())
    doc["lidarcal_calibration"]["correlation"]["matrix"] = [[1.0]]
    bad.write_text(yaml.safe_dump(doc))
    assert "correlation.matrix" in error(m.bag, "--calibration", bad, "-o", out)
    assert "nowhere" in error(tmp_path / "nowhere", *cal, "-o", out)
    assert "directory" in error(m.bag, *cal, "-o", tmp_path)
    other = json.loads(reported.evaluation.read_text())
    other["biases"]["dphi"] += 1e-6
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert "other biases" in error(m.bag, *cal, "--evaluation", tmp_path / "other.json",
                                   "-o", out)
    (tmp_path / "broken.json").write_text('{"pairs": [{"strips": [1]}]}')
    assert "not an evaluation" in error(m.bag, *cal, "--evaluation",
                                        tmp_path / "broken.json", "-o", out)
    assert "--crs" in error(m.bag, *cal, "--crs", "EPSG:999999", "-o", out)
    assert not out.exists()


# ------------------------------------------------------------------ headless Chromium
def _chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    reason = "no chromium binary (bash scripts/system-deps installs Debian's chromium as root)"
    if os.environ.get("CI"):
        pytest.fail(reason)
    pytest.skip(reason)


def _chromium_run(browser: str, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    command = [browser, "--headless", "--disable-gpu", "--no-sandbox",
               "--no-first-run", "--disable-extensions", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-default-browser-check",
               f"--user-data-dir={profile}", "--virtual-time-budget=10000", *args]
    env = {**os.environ, "HOME": str(profile)}
    return subprocess.run(command, capture_output=True, text=True, timeout=180, env=env,
                          check=False)


def test_every_figure_renders_in_headless_chromium(reported: Reported, tmp_path: Path) -> None:
    """Chromium loads the file offline; the page's own script marks each ``<img>`` that
    decoded (``complete`` and ``naturalWidth > 0``) and counts them on ``<body>``; a
    screenshot of the top of the page (summary, quality table, block map) is not blank.
    ``LIDARCAL_REPORT_SCREENSHOT=path.png`` keeps a screenshot of the whole page."""
    browser = _chromium()
    url = reported.html.resolve().as_uri()
    done = _chromium_run(browser, tmp_path / "profile", "--dump-dom", url)
    assert done.returncode == 0, done.stderr[-2000:]
    parsed = _parse(done.stdout)
    expected = figure_ids(reported.content)
    assert {img.get("id") for img in parsed.images} == expected
    not_rendered = [img.get("id") for img in parsed.images if img.get("data-rendered") != "1"]
    assert not not_rendered, f"figures that did not render: {not_rendered}"
    assert parsed.body.get("data-figures-total") == str(len(expected))
    assert parsed.body.get("data-figures-rendered") == str(len(expected))

    keep = os.environ.get("LIDARCAL_REPORT_SCREENSHOT")
    shot = Path(keep) if keep else tmp_path / "report.png"
    height = 24_000 if keep else 2400
    done = _chromium_run(browser, tmp_path / "profile", "--hide-scrollbars",
                         f"--window-size=1280,{height}", f"--screenshot={shot}", url)
    assert done.returncode == 0 and shot.is_file(), done.stderr[-2000:]
    from PIL import Image

    with Image.open(shot) as image:
        assert image.size == (1280, height)
        grey = np.asarray(image.convert("L").crop((0, 0, 1280, 2400)), dtype=np.float64)
    assert grey.std() > 20.0, "the screenshot is blank"
    assert (grey < 100).mean() > 0.01, "no dark pixels: nothing drawn"


# ------------------------------------------------------------------ scripts/system-deps
def test_system_deps_script_is_executable_bash_printing_one_line() -> None:
    path = ROOT / "scripts" / "system-deps"
    assert path.read_text().startswith("#!/usr/bin/env bash\n")
    assert path.stat().st_mode & stat.S_IXUSR
    assert subprocess.run(["bash", "-n", str(path)], check=False).returncode == 0
    assert "bash scripts/system-deps" in (ROOT / "scripts" / "test").read_text()
    if shutil.which("chromium") or shutil.which("chromium-browser"):  # nothing to install
        done = subprocess.run(["bash", str(path)], capture_output=True, text=True,
                              timeout=60, check=False)
        assert done.returncode == 0 and len(done.stdout.splitlines()) == 1, done
        assert done.stderr == ""


def test_report_module_imports_no_rclpy() -> None:
    code = ("import sys, lidarcal_ros.pipeline.report.build, lidarcal_ros.io.report.page; "
            "sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_no_figure_is_left_without_a_unit_or_coordinates(reported: Reported) -> None:
    """Map axes name the CRS; no figure caption speaks of coordinates relative to an
    origin."""
    text = reported.html.read_text(encoding="utf-8")
    assert "relative to (" not in text
    assert re.search(r"Coordinates: EPSG:32633 \(WGS 84 / UTM zone 33N\)", text)


def test_a_file_with_an_empty_correlation_is_read(tmp_path: Path) -> None:
    """``correlation: {names: [], matrix: []}`` (nothing correlated, as a file of surveyed
    values writes it) is a 0 x 0 matrix, not a malformed one."""
    from helpers_missions import write_calibration_yaml

    from lidarcal_ros.core.params import PARAMETER_NAMES

    path = write_calibration_yaml(tmp_path / "cal.yaml", dict.fromkeys(PARAMETER_NAMES, 0.0))
    cal = read_report_calibration(path)
    assert cal.correlation_names == [] and cal.correlation.shape == (0, 0)


@pytest.mark.parametrize("case", ["estimated", "held", "not tried"])
def test_the_mounting_and_its_timing_bias_in_the_calibration_table(tmp_path: Path,
                                                                    case: str) -> None:
    """A calibration file with the ``extrinsic`` block of clouds in the sensor's frame: the
    written page's calibration table shows the mounting against the nominal and the timing
    bias dt in ms with its sigma where estimated, held at 0 with the calibration's statement
    where the flight could not see it, no line where the calibration did not try."""
    from helpers_missions import write_calibration_yaml

    from lidarcal_ros.core.calibration.extrinsic import timing_statement
    from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
    from lidarcal_ros.core.params import PARAMETER_NAMES
    from lidarcal_ros.io.calibration_file import Extrinsic
    from lidarcal_ros.io.report.page import write_html_report

    path = write_calibration_yaml(tmp_path / "cal.yaml", dict.fromkeys(PARAMETER_NAMES, 0.0))
    nominal = Mounting(np.eye(3), np.array([0.10, 0.0, -0.05]))
    turned = Mounting(np.array([[1.0, 0.0, 0.0], [0.0, math.cos(1e-3), -math.sin(1e-3)],
                                [0.0, math.sin(1e-3), math.cos(1e-3)]]),
                      np.array([0.103, 0.004, -0.05]))  # 5.0 mm and 206.3 arcsec
    statement = timing_statement("dS depends on the other biases nearly (multiple "
                                 "correlation 0.996, -0.99 with dY): only their combination "
                                 "is determined")
    cases: dict[str, dict[str, Any]] = {
        "estimated": {"time_offset_s": 0.0030142, "time_offset_sigma_s": 8.9e-5,
                      "time_offset_correlation": {"dY": -0.6}},
        "held": {"time_offset_note": statement}, "not tried": {}}
    timing = cases[case]
    doc = yaml.safe_load(path.read_text())
    doc["lidarcal_calibration"]["extrinsic"] = Extrinsic("base_link", "velodyne", turned,
                                                         nominal, **timing).document()
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    cal = read_report_calibration(path)
    content = ReportContent(title="t", facts=[], biases=cal.biases,
                            correlation_names=cal.correlation_names,
                            correlation=cal.correlation, pairs=[], control=[],
                            radiometry=None, calibration_facts=cal.facts)
    page = _parse(write_html_report(tmp_path / "report.html", content).read_text("utf-8"))
    rows = page.table("calibration", "")
    assert re.fullmatch(r"base_link -> velodyne: translation \+0\.1030, \+0\.0040, -0\.0500 m, "
                        r"rotation \(qx, qy, qz, qw\) \+0\.000500, [+-]0\.000000, "
                        r"[+-]0\.000000, \+1\.000000; 5\.0 mm and 206\.3 arcsec from the "
                        r"nominal", rows["mounting"][1]), rows["mounting"]
    if case == "not tried":
        assert "timing bias dt" not in rows and "dt" not in page.text["calibration"]
        return
    dt = rows["timing bias dt"][1]
    if case == "estimated":
        assert dt.startswith("+3.01 \u00b1 0.09 ms, estimated with the mounting")
    else:
        assert dt == statement and ": held at 0; " in dt
        assert "multiple correlation 0.996, -0.99 with dY" in dt
