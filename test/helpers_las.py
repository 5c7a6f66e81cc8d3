"""LAS/LAZ tiles and SBETs written the way a survey delivers them, and real sample files.

``write_las_tiles`` writes strips (``plain_strips`` of a simulated mission, or
``add_first_returns`` with multiple returns on the exact laser ray) as LAS 1.4 / LAZ tiles in
adjusted standard GPS time (or week seconds), point source id = strip; ``write_mission_sbet``
writes a mission's trajectory as an SBET (GPS week seconds, geographic positions).
``real_las_file`` finds a real file: laspy's samples come from its source distribution on PyPI
(``scripts/test-data``, run by ``scripts/test``; under CI their absence fails the test),
lidR's are looked for in ``$LIDARCAL_REAL_LAS_DIR`` or ``shared/data/las`` and skipped when
absent.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.simulation.exact_model import biased_from_pulse
from lidarcal_ros.core.simulation.simulate import SimulatedMission
from lidarcal_ros.io.survey.las_reader import GpsTimeType
from lidarcal_ros.io.survey.las_writer import ADJUSTED_GPS_OFFSET, unix_to_adjusted_gps
from lidarcal_ros.io.survey.trajectory_files import WEEK_S, write_sbet

#: CRS of the tiles and SBETs written (UTM 33N).
CRS = "EPSG:32633"


def add_first_returns(
    sim: SimulatedMission, *, fraction: float = 0.3, seed: int = 0,
    separation: tuple[float, float] = (3.0, 30.0), noise_m: float = 0.02,
    scan_band_deg: dict[int, tuple[float, float]] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Per strip: the mission's points as last returns plus, for ``fraction`` of the pulses, a
    first return on the same (biased) laser ray, ``separation`` metres before the last.
    ``scan_band_deg``: strip id -> the mirror angles (deg) outside which its pulses have no
    first return (a tile holding one edge of that strip's swath).

    The ray of a pulse is exact: ``X_o + R_kappa dL + R_kappa R_B rho(r)`` is linear in the
    range ``r``, so the earlier return is the last one moved along the unit vector between
    the biased points at ranges ``r`` and ``r - 1`` of the true pulse (true firing position
    from the noiseless trajectory, true mirror angle, heading of the line).
    """
    rng = np.random.default_rng(seed)
    traj = sim.mission.trajectory
    out = []
    for k, strip in enumerate(sim.mission.strips):
        assert strip.intensity is not None  # simulated strips always carry intensity
        n = len(strip)
        xo = np.column_stack([np.interp(strip.t, traj.t, traj.xyz[:, i]) for i in range(3)])
        kappa = sim.lines[k]["kappa"]
        theta = sim.scan_angle_true[k].astype(np.float64)
        r_true = sim.range_true[k]
        up = (biased_from_pulse(xo, kappa, r_true - 1.0, theta, sim.biases)
              - biased_from_pulse(xo, kappa, r_true, theta, sim.biases))
        up /= np.linalg.norm(up, axis=1)[:, None]
        multi = rng.random(n) < fraction
        if scan_band_deg is not None and strip.strip_id in scan_band_deg:
            lo, hi = np.radians(scan_band_deg[strip.strip_id])
            multi &= (theta >= lo) & (theta <= hi)
        sep = rng.uniform(*separation, n)
        first = strip.xyz + sep[:, None] * up + rng.normal(0.0, noise_m, (n, 3))
        rn = np.where(multi, 2, 1).astype(np.uint8)
        idx = np.flatnonzero(multi)
        cols = {
            "xyz": np.concatenate([strip.xyz, first[idx]]),
            "t": np.concatenate([strip.t, strip.t[idx]]),
            "intensity": np.concatenate([strip.intensity, 0.5 * strip.intensity[idx]]),
            "return_number": np.concatenate([rn, np.ones(idx.size, np.uint8)]),
            "number_of_returns": np.concatenate([rn, np.full(idx.size, 2, np.uint8)]),
            "strip_id": np.full(n + idx.size, strip.strip_id, dtype=np.uint16),
        }
        order = np.argsort(cols["t"], kind="stable")
        out.append({key: v[order] for key, v in cols.items()})
    return out


def plain_strips(sim: SimulatedMission) -> list[dict[str, np.ndarray]]:
    """Per strip: the mission's points as single returns (the columns of
    :func:`write_las_tiles`)."""
    out = []
    for s in sim.mission.strips:
        assert s.intensity is not None  # simulated strips always carry intensity
        out.append({"xyz": s.xyz, "t": s.t, "intensity": s.intensity,
                    "return_number": np.ones(len(s), np.uint8),
                    "number_of_returns": np.ones(len(s), np.uint8),
                    "strip_id": np.full(len(s), s.strip_id, dtype=np.uint16)})
    return out


def write_las_tiles(
    strips: list[dict[str, np.ndarray]], directory: Path, *, crs: str | None = CRS,
    tiles: tuple[int, int] = (2, 2), laz: Sequence[int] = (0,),
    time_type: GpsTimeType = GpsTimeType.ADJUSTED,
    version: str = "1.4", point_format: int = 6, point_source_id: bool = True,
) -> list[Path]:
    """Write the points as a grid of LAS/LAZ tiles (0.001 m scale).

    ``time_type``: ``ADJUSTED`` (UNIX times to adjusted standard GPS time, encoding bit
    set) or ``WEEK`` (GPS week seconds, bit clear). Tiles listed in ``laz`` are LAZ.
    Points within a tile are stored in reverse time order (the importer must sort).
    """
    import laspy
    import pyproj

    cols = {key: np.concatenate([s[key] for s in strips]) for key in strips[0]}
    xyz = cols["xyz"]
    gps = unix_to_adjusted_gps(cols["t"])
    if time_type is GpsTimeType.WEEK:
        gps = np.mod(gps + ADJUSTED_GPS_OFFSET, WEEK_S)
    nx, ny = tiles
    ex = np.quantile(xyz[:, 0], np.linspace(0, 1, nx + 1)[1:-1])
    ey = np.quantile(xyz[:, 1], np.linspace(0, 1, ny + 1)[1:-1])
    tile = np.searchsorted(ex, xyz[:, 0]) * ny + np.searchsorted(ey, xyz[:, 1])
    paths = []
    for k in range(nx * ny):
        sel = np.flatnonzero(tile == k)[::-1]
        header = laspy.LasHeader(version=version, point_format=point_format)
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = np.floor(xyz[sel].min(axis=0) / 1000.0) * 1000.0
        header.global_encoding.gps_time_type = (
            laspy.header.GpsTimeType.STANDARD if time_type is GpsTimeType.ADJUSTED
            else laspy.header.GpsTimeType.WEEK_TIME)
        if version == "1.4" and point_format >= 6:
            header.global_encoding.wkt = True
        if crs is not None:
            header.add_crs(pyproj.CRS.from_user_input(crs))
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz[sel, 0], xyz[sel, 1], xyz[sel, 2]
        las.gps_time = gps[sel]
        las.intensity = np.clip(np.rint(cols["intensity"][sel]), 0, 65535).astype(np.uint16)
        las.return_number = cols["return_number"][sel]
        las.number_of_returns = cols["number_of_returns"][sel]
        if point_source_id:
            las.point_source_id = cols["strip_id"][sel]
        path = directory / f"tile{k}.{'laz' if k in laz else 'las'}"
        las.write(str(path))
        paths.append(path)
    return paths


def write_mission_sbet(mission: Mission, path: Path, *, crs: str = CRS,
                       wander_rad: float = 0.0) -> Path:
    """The mission's trajectory as an SBET: GPS week seconds, lat/lon (rad), ellipsoidal
    height (the map heights, taken as ellipsoidal); where the trajectory has headings, the
    platform heading and wander angle of an SBET (true heading = platform heading - wander,
    clockwise from true north: the map's grid heading ``-kappa`` turned by PROJ's meridian
    convergence, the angle from true north to grid north)."""
    import pyproj

    to_geo = pyproj.Transformer.from_crs(pyproj.CRS(crs).to_3d(), "EPSG:4979", always_xy=True)
    traj = mission.trajectory
    lon, lat, h = to_geo.transform(traj.xyz[:, 0], traj.xyz[:, 1], traj.xyz[:, 2])
    sow = np.mod(unix_to_adjusted_gps(traj.t) + ADJUSTED_GPS_OFFSET, WEEK_S)
    attitude = {}
    if traj.heading is not None:
        convergence = np.radians(pyproj.Proj(crs).get_factors(lon, lat).meridian_convergence)
        true_heading = -traj.heading + convergence
        attitude = {"heading": true_heading + wander_rad,
                    "wander_angle": np.full(len(traj), wander_rad)}
    return write_sbet(path, sow, np.radians(lat), np.radians(lon), h, **attitude)


#: Files of laspy's source distribution, fetched by scripts/test-data (run by scripts/test).
LASPY_SAMPLES = ("simple.las", "autzen_trim.laz", "append-bug.laz",
                 "file_with_both_wkt_and_geotiff_vlrs.las")


def _real_dirs() -> list[Path]:
    repo = Path(__file__).resolve().parents[1]
    env = os.environ.get("LIDARCAL_REAL_LAS_DIR")
    return ([Path(env)] if env else []) + [
        repo.parent / "shared" / "data" / "las", repo / ".venv" / "test-data" / "laspy"]


def real_las_file(name: str) -> Path:
    """The real LAS/LAZ file ``name``, or the test skipped (failed under CI for laspy's
    samples, which ``scripts/test-data`` fetches)."""
    for d in _real_dirs():
        if (d / name).is_file():
            return d / name
    if name in LASPY_SAMPLES and os.environ.get("CI"):
        pytest.fail(f"real test file {name} missing: scripts/test-data did not fetch it")
    pytest.skip(f"real test file {name} not available (scripts/test-data, "
                "$LIDARCAL_REAL_LAS_DIR or shared/data/las)")
