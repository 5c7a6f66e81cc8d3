"""``lidarcal report``: the HTML calibration report, end to end on a small simulated mission.

The mission (helpers_missions, paper configuration and biases) is calibrated with ``lidarcal
calibrate``; the report of the same bag under that calibration must reproduce the
calibration's own pair QA (large RMS before, small after), show the control residuals, show
the variance-to-mean ratio of intensity falling after radiometric correction on gentle
slopes, be one self-contained file, and render every figure in headless Chromium.
"""

from __future__ import annotations

import dataclasses
import html.parser
import os
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
from helpers_missions import MissionFiles

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.io.html_report import ReportContent, render_html
from lidarcal_ros.pipeline.report import (
    build_report,
    mean_raster,
    radiometry_section,
    read_report_calibration,
    slope_class_statistics,
)

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ fixtures
@dataclasses.dataclass(frozen=True)
class Reported:
    """A calibrated small mission and its report."""

    mission: MissionFiles
    calibration: Path
    html: Path
    content: ReportContent
    cli_stdout: str


def _run(capsys: pytest.CaptureFixture[str], *args: Any) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def reported(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory
             ) -> Reported:
    """``lidarcal calibrate`` then ``lidarcal report`` (CLI, in-process) on the small
    mission; the report's content computed once more through the pipeline for the numbers."""
    work = tmp_path_factory.mktemp("report")
    cal = work / "calibration.yaml"
    out = work / "report.html"
    common = ["--config", small_mission.fast_config, "--control", small_mission.control_csv]
    assert main([str(a) for a in ["calibrate", small_mission.bag, "-o", cal, *common]]) == 0
    stdout = _capture_stdout(["report", small_mission.bag, "--calibration", cal, "-o", out,
                              *common])
    config = load_flight_config(small_mission.fast_config)
    content = build_report(small_mission.bag, cal, config,
                           control_csv=small_mission.control_csv)
    return Reported(small_mission, cal, out, content, stdout)


def _capture_stdout(args: list[Any]) -> str:
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        rc = main([str(a) for a in args])
    assert rc == 0, buffer.getvalue()
    return buffer.getvalue()


def _calibration_doc(path: Path) -> dict[str, Any]:
    return yaml.safe_load(path.read_text())["lidarcal_calibration"]


def _expected_figure_ids(content: ReportContent) -> set[str]:
    ids = {"fig-correlation", "fig-vmr-slope", "fig-reflectance-map"}
    ids |= {f"fig-pair-{a}-{b}" for a, b in (p.strips for p in content.pairs)}
    return ids


class _Images(html.parser.HTMLParser):
    """Every ``<img>`` of a document with its attributes, and ``<body>``'s attributes."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[dict[str, str]] = []
        self.body: dict[str, str] = {}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = {k: v or "" for k, v in attrs}
        if tag == "img":
            self.images.append(values)
        elif tag == "body":
            self.body = values


def _parse(text: str) -> _Images:
    parser = _Images()
    parser.feed(text)
    return parser


# ------------------------------------------------------------------ geometry
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


def test_bias_table_and_correlation_from_the_calibration_file(reported: Reported) -> None:
    doc = _calibration_doc(reported.calibration)
    content = reported.content
    assert [b.name for b in content.biases] == list(doc["biases"])
    for b in content.biases:
        entry = doc["biases"][b.name]
        assert b.value == entry["value"]
        if entry["estimated"]:
            assert b.state == "estimated" and b.sigma == entry["sigma"]
        else:
            assert b.state in ("fixed", "not_estimable") and b.sigma is None
    assert content.correlation_names == doc["correlation"]["names"]
    np.testing.assert_allclose(content.correlation, doc["correlation"]["matrix"])


# ------------------------------------------------------------------ radiometry
def test_vmr_of_intensity_falls_after_radiometric_correction_on_gentle_slopes(
    reported: Reported,
) -> None:
    """The paper's Fig. 5: the variance-to-mean ratio of reflectance is below that of the
    recorded intensity in every class under 30 degrees (ranges of 540 m and 1150 m, and
    incidence, no longer spread the values)."""
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
    reflectance = intensity / 4.0
    classes = slope_class_statistics(slope, intensity, reflectance, (0.0, 10.0, 30.0, 90.0),
                                     min_points=20)
    assert [c.n_points for c in classes] == [4000, 4000, 10]
    assert classes[0].vmr_intensity == pytest.approx(1.0, rel=0.1)  # Poisson: VMR 1
    assert classes[1].vmr_intensity == pytest.approx(1.0, rel=0.1)
    assert classes[0].vmr_reflectance == pytest.approx(classes[0].vmr_intensity / 4.0)
    assert classes[0].change == pytest.approx(-0.75)
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
    config = load_flight_config(reported.mission.fast_config)
    delta = read_report_calibration(reported.calibration).record.delta
    assert radiometry_section(no_intensity, delta, config) is None
    text = render_html(dataclasses.replace(reported.content, pairs=[], radiometry=None))
    assert "no intensity" in text
    assert 'id="fig-vmr-slope"' not in text and 'id="fig-reflectance-map"' not in text


def test_a_thinned_report_uses_and_says_the_calibration_s_thinning(reported: Reported
                                                                     ) -> None:
    """With ``calibration.thinning_cell_m`` the report reads the points as the calibration
    does (the same sample points) and says how many were left out."""
    from lidarcal_ros.pipeline.calibration import load_mission

    files = reported.mission
    config = load_flight_config(files.fast_config).with_values(
        calibration__thinning_cell_m=2.0)
    thinned = load_mission(files.bag, config)
    assert 0 < thinned.thinned_points < files.mission.n_points
    content = build_report(files.bag, reported.calibration, config,
                           control_csv=files.control_csv)
    facts = dict(content.facts)
    assert facts["points thinned"].startswith(f"{thinned.thinned_points} left out")
    assert f"{thinned.n_points} points" in facts["mission"]
    assert "points thinned" not in dict(reported.content.facts)


def test_the_report_says_where_the_heading_comes_from(reported: Reported) -> None:
    # the small mission's poses carry identity orientations: the track, as method.md
    assert dict(reported.content.facts)["heading"] == (
        "from the track (the poses carry no orientation)")


# ------------------------------------------------------------------ the HTML file
def test_html_is_one_self_contained_file(reported: Reported) -> None:
    text = reported.html.read_text(encoding="utf-8")
    assert "report written to" in reported.cli_stdout
    lowered = text.lower()
    assert "http://" not in lowered and "https://" not in lowered
    assert "<link" not in lowered and "@import" not in lowered and "url(" not in lowered
    parsed = _parse(text)
    ids = [img.get("id") for img in parsed.images]
    assert set(ids) == _expected_figure_ids(reported.content)
    assert len(ids) == len(set(ids))
    for img in parsed.images:
        assert img["src"].startswith("data:image/png;base64,"), img["id"]
        assert img.get("alt"), img["id"]
    for b in reported.content.biases:
        assert f"<td>{b.name}</td>" in text
    for c in reported.content.control:
        assert f"<td>{c.control_id}</td>" in text


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

    assert "exists" in error(m.bag, "--calibration", reported.calibration, "-o", reported.html)
    assert "missing.yaml" in error(m.bag, "--calibration", tmp_path / "missing.yaml",
                                   "-o", out)
    bad = tmp_path / "bad.yaml"
    doc = yaml.safe_load(reported.calibration.read_text())
    doc["lidarcal_calibration"]["correlation"]["matrix"] = [[1.0]]
    bad.write_text(yaml.safe_dump(doc))
    assert "correlation.matrix" in error(m.bag, "--calibration", bad, "-o", out)
    assert "nowhere" in error(tmp_path / "nowhere", "--calibration", reported.calibration,
                              "-o", out)
    assert "directory" in error(m.bag, "--calibration", reported.calibration, "-o", tmp_path)
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
    decoded (``complete`` and ``naturalWidth > 0``) and counts them on ``<body>``."""
    browser = _chromium()
    url = reported.html.resolve().as_uri()
    done = _chromium_run(browser, tmp_path / "profile", "--dump-dom", url)
    assert done.returncode == 0, done.stderr[-2000:]
    parsed = _parse(done.stdout)
    expected = _expected_figure_ids(reported.content)
    assert {img.get("id") for img in parsed.images} == expected
    not_rendered = [img.get("id") for img in parsed.images if img.get("data-rendered") != "1"]
    assert not not_rendered, f"figures that did not render: {not_rendered}"
    assert parsed.body.get("data-figures-total") == str(len(expected))
    assert parsed.body.get("data-figures-rendered") == str(len(expected))

    shot = tmp_path / "report.png"
    done = _chromium_run(browser, tmp_path / "profile", "--hide-scrollbars",
                         "--window-size=1280,2400", f"--screenshot={shot}", url)
    assert done.returncode == 0 and shot.is_file(), done.stderr[-2000:]
    from PIL import Image

    with Image.open(shot) as image:
        assert image.size == (1280, 2400)
        grey = np.asarray(image.convert("L"), dtype=np.float64)
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
    code = ("import sys, lidarcal_ros.pipeline.report, lidarcal_ros.io.html_report; "
            "sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
