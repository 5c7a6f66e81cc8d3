"""`lidarcal plan`: method.md section 7 from the normal matrix of a simulated plan."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.planning import FlightPlan, predict
from lidarcal_ros.errors import ConfigError

HALF = 200.0  # metres: short lines keep the tests quick; the geometry is what matters


def _line(i: int, x: float, north: bool, height: float) -> dict:
    a, b = [x, -HALF], [x, HALF]
    return {"id": i, "start": a if north else b, "end": b if north else a, "height": height}


PAPER = [_line(1, 0, True, 1150), _line(2, 0, False, 1150), _line(3, 0, True, 540),
         _line(4, 0, False, 540), _line(5, -300, True, 1150), _line(6, 300, True, 1150)]
SEVEN = {"dX", "dY", "domega", "dphi", "dkappa", "dr", "dS"}


def _estimable(doc: dict) -> set[str]:
    report = predict(FlightPlan.from_mapping(doc))
    return {n for n, p in report.parameters.items() if p.estimable}


def test_paper_configuration_with_one_control_point(tmp_path: Path, capsys) -> None:
    doc = {"sensor": {"fov_deg": 50.0, "range_noise_m": 0.03}, "terrain": "built-up",
           "lines": PAPER, "control": [[0, 0, 0]]}
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["plan", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    params = out["parameters"]
    assert set(params) == {"dX", "dY", "dZ", "domega", "dphi", "dkappa", "dr", "dS"}
    assert SEVEN <= {n for n, p in params.items() if p["estimable"]}
    for name in SEVEN:
        p = params[name]
        assert p["sigma"] > 0 and 0 <= p["max_correlation"] <= 1 and p["correlated_with"]


def test_without_control_dz_is_not_estimable() -> None:
    report = predict(FlightPlan.from_mapping({"lines": PAPER}))
    assert not report.parameters["dZ"].estimable
    assert any(a.startswith("dZ:") and "control" in a for a in report.advice)
    assert {n for n, p in report.parameters.items() if p.estimable} >= SEVEN - {"dr"}


def test_one_track_cannot_see_dkappa() -> None:
    report = predict(FlightPlan.from_mapping({"lines": PAPER[:4], "control": [[0, 0, 0]]}))
    assert not report.parameters["dkappa"].estimable
    advice = " ".join(report.advice)
    assert "one track" in advice and "same direction" in advice


def test_flat_terrain_hides_horizontal_parameters() -> None:
    report = predict(FlightPlan.from_mapping({"terrain": "flat", "lines": PAPER,
                                              "control": [[0, 0, 0]]}))
    for name in ("dX", "dY", "domega", "dkappa"):
        assert not report.parameters[name].estimable, name
    assert report.parameters["dphi"].estimable
    assert any("flat" in a for a in report.advice)


@pytest.mark.parametrize("doc, message", [
    ({}, "lines"),
    ({"lines": [{"id": 1, "start": [0, 0]}]}, "line 1"),
    ({"lines": PAPER, "terrain": "dsm.tif"}, "DSM"),
    ({"lines": PAPER, "sensor": {"fov_deg": -5}}, "fov_deg"),
    ({"lines": PAPER, "control": [["a", 0, 0]]}, "control point 1"),
])
def test_bad_plans_are_refused_in_one_line(doc: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        FlightPlan.from_mapping(doc)
