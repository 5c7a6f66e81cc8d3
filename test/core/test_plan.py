"""`lidarcal plan`: docs/method.md section 7 from the normal matrix of a simulated plan."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.planning import FlightPlan, predict
from lidarcal_ros.core.simulation.raster_terrain import RasterTerrain
from lidarcal_ros.core.simulation.ray_casting import cast_rays
from lidarcal_ros.errors import ConfigError, InputError
from lidarcal_ros.io.survey.dsm import read_dsm
from lidarcal_ros.io.survey.plan_file import read_flight_plan

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
    ({"lines": PAPER, "terrain": "site.npy", "terrain_origin": [1, "a"]}, "terrain_origin"),
    ({"lines": PAPER, "terrain": "site.npy", "terrain_cell_m": 0}, "terrain_cell_m"),
    ({"lines": PAPER, "sensor": {"fov_deg": -5}}, "fov_deg"),
    ({"lines": PAPER, "control": [["a", 0, 0]]}, "control point 1"),
])
def test_bad_plans_are_refused_in_one_line(doc: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        FlightPlan.from_mapping(doc)


# ---------------------------------------------------------------------------- DSM terrain
CELL = 1.0
#: North-west corner and size of the site grid: every PAPER swath fits on it.
WEST, NORTH, COLS, ROWS = -900.0, 800.0, 1800, 1600


def _site(gables: bool) -> np.ndarray:
    """A site DSM (row 0 north, 1 m cells): gently rolling ground, and with ``gables`` a
    building every 60 m (12 x 9 m, gable roofs 8-12 m high, ridges alternately east-west
    and north-south, so that roof planes face all four ways)."""
    x = WEST + CELL * (np.arange(COLS) + 0.5)
    y = NORTH - CELL * (np.arange(ROWS) + 0.5)
    xx, yy = np.meshgrid(x, y)
    z = 50.0 + 3.0 * np.sin(xx / 300.0) + 2.0 * np.cos(yy / 250.0)
    if gables:
        u = np.mod(xx + 30.0, 60.0) - 30.0
        v = np.mod(yy + 30.0, 60.0) - 30.0
        east_west = (np.floor((xx + 30.0) / 60.0) + np.floor((yy + 30.0) / 60.0)) % 2 == 0
        inside = (np.abs(u) < 12.0) & (np.abs(v) < 9.0)
        rise = np.where(east_west, 1.0 - np.abs(v) / 9.0, 1.0 - np.abs(u) / 12.0)
        z = np.where(inside, z + 8.0 + 4.0 * rise, z)
    return z


def _write_npy_plan(tmp_path: Path, z: np.ndarray, **extra: object) -> Path:
    np.save(tmp_path / "site.npy", z)
    doc = {"terrain": "site.npy", "terrain_origin": [WEST, NORTH], "terrain_cell_m": CELL,
           "lines": PAPER, "control": [[0, 0, 0]], **extra}
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_rays_meet_a_gridded_dsm_on_its_surface() -> None:
    """Ray casting over a DSM: every hit lies on the bilinear surface; over a tilted plane
    the hit is the analytic intersection."""
    rng = np.random.default_rng(0)
    n = 5000
    origins = np.column_stack([rng.uniform(-100, 100, n), rng.uniform(-100, 100, n),
                               np.full(n, 1000.0)])
    theta = rng.uniform(-0.45, 0.45, n)
    d = np.column_stack([np.sin(theta), np.zeros(n), -np.cos(theta)])
    site = RasterTerrain(_site(True), west=WEST, north=NORTH, cell_m=CELL)
    hits = cast_rays(site, origins, d)
    assert np.max(np.abs(hits.xyz[:, 2] - site.height(hits.xyz[:, 0], hits.xyz[:, 1]))) < 1e-6
    # The first crossing: no sample of the ray above it lies under the surface.
    t_before = hits.t[:, None] * np.linspace(0.0, 0.999, 200)[None, :]
    p = origins[:, None, :] + t_before[..., None] * d[:, None, :]
    assert np.all(p[..., 2] >= site.height(p[..., 0], p[..., 1]) - 1e-9)
    xx, yy = np.meshgrid(WEST + CELL * (np.arange(COLS) + 0.5),
                         NORTH - CELL * (np.arange(ROWS) + 0.5))
    tilted = RasterTerrain(20.0 + 0.1 * xx - 0.05 * yy, west=WEST, north=NORTH, cell_m=CELL)
    hits = cast_rays(tilted, origins, d)
    # o_z + t d_z = 20 + 0.1 (o_x + t d_x) - 0.05 o_y
    t_exact = (origins[:, 2] - 20.0 - 0.1 * origins[:, 0] + 0.05 * origins[:, 1]) / (
        0.1 * d[:, 0] - d[:, 2])
    np.testing.assert_allclose(hits.t, t_exact, atol=1e-6)


def test_plan_over_a_site_dsm_with_gable_roofs(tmp_path: Path, capsys) -> None:
    """The paper's plan over a site DSM (.npy, georeferenced in the plan): buildings give the
    overlaps sloped planes, so with one control point the seven parameters are estimable."""
    path = _write_npy_plan(tmp_path, _site(True))
    assert main(["plan", str(path), "--json"]) == 0
    params = json.loads(capsys.readouterr().out)["parameters"]
    assert SEVEN <= {n for n, p in params.items() if p["estimable"]}


def test_plan_over_a_bare_site_dsm_hides_horizontal_parameters(tmp_path: Path) -> None:
    """The same site without buildings: the rolling ground's slopes (< 2 deg) are too gentle
    for the horizontal parameters, and the advice says why."""
    report = predict(read_flight_plan(_write_npy_plan(tmp_path, _site(False))))
    blind = {n for n, p in report.parameters.items() if not p.estimable}
    assert {"dX", "dY", "domega", "dkappa"} <= blind
    assert report.parameters["dphi"].estimable
    assert any("sloped features" in a for a in report.advice)


def test_geotiff_dsm_matches_the_npy_grid(tmp_path: Path) -> None:
    """A GeoTIFF (ModelPixelScale + ModelTiepoint, PixelIsArea, GDAL no-data) reads as the
    same grid as the .npy placed by the plan; a no-data cell takes its neighbour's height."""
    import tifffile

    z = _site(True).astype(np.float32)[:200, :300]
    z_nodata = z.copy()
    z_nodata[10, 10] = -9999.0
    extratags = [
        (33550, "d", 3, (CELL, CELL, 0.0), False),
        (33922, "d", 6, (0.0, 0.0, 0.0, WEST, NORTH, 0.0), False),
        (34735, "H", 8, (1, 1, 0, 1, 1025, 0, 1, 1), False),
        (42113, "s", 0, "-9999", False),
    ]
    tifffile.imwrite(tmp_path / "site.tif", z_nodata, extratags=extratags)
    np.save(tmp_path / "site.npy", z)
    tif = read_dsm(tmp_path / "site.tif")
    npy = read_dsm(tmp_path / "site.npy", cell_m=CELL, north_west=(WEST, NORTH))
    assert tif.extent == npy.extent == (WEST, WEST + 300 * CELL, NORTH - 200 * CELL, NORTH)
    x = WEST + CELL * (np.arange(300) + 0.5)
    y = np.full(300, NORTH - CELL * 20.5)
    np.testing.assert_allclose(tif.height(x, y), npy.height(x, y), atol=1e-4)
    at_gap = tif.height(WEST + 10.5 * CELL, NORTH - 10.5 * CELL)
    assert abs(float(at_gap) - float(z[10, 10])) < 15.0 and float(at_gap) > 0


def test_bad_dsm_one_line(tmp_path: Path, capsys) -> None:
    # A DSM too small for the swaths.
    np.save(tmp_path / "small.npy", np.zeros((50, 50)))
    small = tmp_path / "small.yaml"
    small.write_text(yaml.safe_dump({"terrain": "small.npy", "lines": PAPER}))
    # A missing file, a file that is not a grid, a TIFF without georeference.
    missing = tmp_path / "missing.yaml"
    missing.write_text(yaml.safe_dump({"terrain": "nowhere.tif", "lines": PAPER}))
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    junk = tmp_path / "junk.yaml"
    junk.write_text(yaml.safe_dump({"terrain": "junk.npy", "lines": PAPER}))
    import tifffile

    tifffile.imwrite(tmp_path / "plain.tif", np.zeros((10, 10), dtype=np.float32))
    plain = tmp_path / "plain.yaml"
    plain.write_text(yaml.safe_dump({"terrain": "plain.tif", "lines": PAPER}))
    for path, words in ((small, "beyond the DSM"), (missing, "not found"),
                        (junk, "NumPy"), (plain, "georeference")):
        assert main(["plan", str(path)]) != 0
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, err
    with pytest.raises(InputError, match="2-D"):
        np.save(tmp_path / "flat.npy", np.zeros(10))
        read_dsm(tmp_path / "flat.npy")
    with pytest.raises(ConfigError, match="not been read"):
        predict(FlightPlan.from_mapping({"terrain": "site.npy", "lines": PAPER}))
    assert math.isfinite(RasterTerrain(np.array([[np.nan, 1.0], [2.0, np.nan]]), west=0,
                                       north=0, cell_m=1).height(0.5, -0.5))


def test_a_banked_turn_over_one_track_shows_dkappa() -> None:
    """Lines all on one track cannot see dkappa (docs/method.md section 7, remark 6); a banked
    turn across them can, by the rigorous model's normal matrix (the poses' INS attitude,
    section 10), better than by the level model's; the report names the model."""
    turn = {"id": 7, "start": [-150, -HALF], "end": [150, HALF], "height": 1150,
            "bank_deg": 20}
    base = {"lines": PAPER[:4], "control": [[0, 0, 0]]}
    rigorous = predict(FlightPlan.from_mapping({**base, "lines": [*PAPER[:4], turn]}))
    assert rigorous.model == "rigorous (INS attitude at 50 Hz) for every strip"
    assert rigorous.parameters["dkappa"].estimable
    level = predict(FlightPlan.from_mapping({**base, "lines": [*PAPER[:4], turn],
                                             "model": "level"}))
    assert level.model == "level (matching.model level) for every strip"
    sigma_r, sigma_l = rigorous.parameters["dkappa"].sigma, level.parameters["dkappa"].sigma
    assert sigma_r is not None and sigma_l is not None and sigma_r < sigma_l
    with pytest.raises(ConfigError, match="model must be one of"):
        FlightPlan.from_mapping({**base, "model": "exact"})
    with pytest.raises(ConfigError, match="line 7"):
        FlightPlan.from_mapping({**base, "lines": [*PAPER[:4], {**turn, "bank_deg": "x"}]})


def _rotated(lines: list[dict], heading_deg: float) -> list[dict]:
    """``lines`` turned by ``heading_deg`` about the origin (counter-clockwise)."""
    c, s = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))

    def turn(p: list[float]) -> list[float]:
        return [c * p[0] - s * p[1], s * p[0] + c * p[1]]

    return [{**ln, "start": turn(ln["start"]), "end": turn(ln["end"])} for ln in lines]


def test_the_contract_example_plan_prints_its_table(tmp_path: Path, capsys) -> None:
    """docs/interface.md's example: lines 3-4 east-west (a level pose heading east is the identity
    quaternion), with and without its control point."""
    lines = [{"id": 1, "start": [0, -HALF], "end": [0, HALF], "height": 1150},
             {"id": 2, "start": [0, HALF], "end": [0, -HALF], "height": 1150},
             {"id": 3, "start": [-HALF, 0], "end": [HALF, 0], "height": 540},
             {"id": 4, "start": [HALF, 0], "end": [-HALF, 0], "height": 540},
             {"id": 5, "start": [-150, -HALF], "end": [-150, HALF], "height": 540},
             {"id": 6, "start": [150, -HALF], "end": [150, HALF], "height": 540}]
    for control in ([[-60, 40, 41.2]], None):
        doc = {"sensor": {"fov_deg": 50.0, "range_noise_m": 0.03}, "terrain": "built-up",
               "lines": lines, **({"control": control} if control else {})}
        path = tmp_path / "plan.yaml"
        path.write_text(yaml.safe_dump(doc))
        assert main(["plan", str(path)]) == 0
        out = capsys.readouterr().out
        assert "model: rigorous (INS attitude at 50 Hz) for every strip" in out
        rows = [ln.split()[0] for ln in out.splitlines()[1:9]]
        assert rows == ["dX", "dY", "dZ", "domega", "dphi", "dkappa", "dr", "dS"]
        assert out.count(" estimable ") >= 7


@pytest.mark.parametrize("model", ["auto", "level"])
def test_every_heading_plans_alike(model: str) -> None:
    """The paper's configuration turned through 0-345 deg: the same parameters estimable,
    sigmas within a factor 2 of the north-south plan's (the terrain under the lines varies),
    with the INS attitude (rigorous model) and without (level)."""
    doc = {"lines": PAPER, "sensor": {"density": 0.05}, "model": model}
    north = predict(FlightPlan.from_mapping(doc))
    estimable = {n for n, p in north.parameters.items() if p.estimable}
    assert SEVEN - {"dr"} <= estimable <= SEVEN
    for heading in range(15, 360, 15):
        report = predict(FlightPlan.from_mapping({**doc, "lines": _rotated(PAPER, heading)}))
        want = "rigorous (INS attitude at 50 Hz)" if model == "auto" else "level"
        assert report.model.startswith(want) and report.model.endswith("for every strip"), \
            (heading, report.model)
        assert {n for n, p in report.parameters.items() if p.estimable} == estimable, heading
        for name in estimable:
            sigma, sigma_north = report.parameters[name].sigma, north.parameters[name].sigma
            assert sigma is not None and sigma_north is not None
            assert 0.5 < sigma / sigma_north < 2.0, (heading, name, sigma / sigma_north)


def test_banked_and_turning_lines_plan_at_any_heading() -> None:
    """Banked lines (constant roll) and a turning line, flown east, south-west and north-west,
    over the paper's opposite pairs turned alike: the rigorous model on every strip, dkappa
    seen through the attitude as on the north-south plan."""
    for heading in (90, 225, 300):
        bank = {"id": 7, "start": [-150, -HALF], "end": [150, HALF], "height": 1150,
                "bank_deg": 20}
        turn = {"id": 8, "start": [200, -HALF], "end": [200, HALF], "height": 900,
                "turn_deg_s": 1.5}
        lines = _rotated([*PAPER[:4], bank, turn], heading)
        report = predict(FlightPlan.from_mapping({"lines": lines, "control": [[0, 0, 0]],
                                                  "sensor": {"density": 0.05}}))
        assert report.model == "rigorous (INS attitude at 50 Hz) for every strip", heading
        assert report.parameters["dkappa"].estimable, heading
        assert {"dX", "dphi", "domega"} <= {n for n, p in report.parameters.items()
                                            if p.estimable}, heading


def test_a_plan_of_one_line_due_east() -> None:
    """Level poses all heading due east are identity quaternions, which alone read as no
    attitude: the plan runs the level model (the same geometry) and says so."""
    report = predict(FlightPlan.from_mapping({"lines": [
        {"id": 1, "start": [-HALF, 0], "end": [HALF, 0], "height": 540}],
        "sensor": {"density": 0.05}}))
    assert report.model.startswith("level"), report.model
    assert not any(p.estimable for p in report.parameters.values())


def test_what_a_plan_separates_with_trajectory_errors(tmp_path: Path, capsys) -> None:
    """The same correspondences analysed with each strip's drift estimated too (docs/method.md
    section 11): the lever arm, a constant shift of each straight strip, is lost to the
    strips' offsets and the advice says so; dphi stays; crossing lines keep dkappa; the
    predicted sigmas are no smaller than with the trajectory as exact."""
    parallel = predict(FlightPlan.from_mapping({"lines": PAPER, "control": [[0, 0, 0]]}))
    with_errors = parallel.with_trajectory_errors
    assert set(with_errors) == set(PARAMETER_NAMES)
    assert not with_errors["dX"].estimable and with_errors["dphi"].estimable
    for name, p in with_errors.items():
        exact = parallel.parameters[name]
        if p.estimable and exact.sigma is not None:
            assert p.sigma is not None and p.sigma >= 0.999 * exact.sigma, name
    assert any(a.startswith("dX") and "surveyed value" in a for a in parallel.advice)
    crossing = [*PAPER[:4], *({**ln, "id": ln["id"] + 10} for ln in _rotated(PAPER[:2], 90))]
    crossed = predict(FlightPlan.from_mapping({"lines": crossing, "control": [[0, 0, 0]]}))
    assert crossed.with_trajectory_errors["dkappa"].estimable
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump({"lines": PAPER, "control": [[0, 0, 0]]}))
    assert main(["plan", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["with_trajectory_errors"]["model"] == "drift"
    assert doc["with_trajectory_errors"]["parameters"]["dX"]["estimable"] is False
