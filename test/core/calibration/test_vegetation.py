"""The incidence of canopy returns (lidarcal_ros.core.radiometry, "Incidence on vegetation"):
volume returns take no incidence correction and stay out of the normals' grid, checked on a
simulated strip with a canopy of known geometry added above its open ground."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_missions import MissionFiles
from numpy.lib import recfunctions

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_NORMAL,
    FLAG_ROUGH,
    FLAG_VOLUME,
)
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.radiometry import RadiometricModel, volume_returns
from lidarcal_ros.core.simulation.surface import ASPHALT, GRASS, SOIL
from lidarcal_ros.io.bag.mission_bag import strip_point_array
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.corrected_cloud import CloudTally, CorrectionStats
from lidarcal_ros.pipeline.correction.stream import StreamCorrector

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

#: Height of the canopy above the ground it shades, m, and its horizontal scatter (a crown
#: is no surface: its returns lie anywhere in a volume).
CANOPY_HEIGHT_M = (4.0, 12.0)
CANOPY_SCATTER_M = 1.5


def test_volume_returns_are_the_non_last_returns() -> None:
    rn = np.array([1, 1, 2, 1, 2, 3, 0, 2], dtype=np.uint8)
    nr = np.array([1, 2, 2, 3, 3, 3, 2, 1], dtype=np.uint8)
    got = volume_returns(rn, nr)
    assert got is not None
    # 1 of 1 and the last of each pulse are surfaces; 0 (unknown) and 2 of 1 (bad) too.
    np.testing.assert_array_equal(got, [False, True, False, True, True, False, False, False])
    assert volume_returns(None, nr) is None and volume_returns(rn, None) is None
    assert volume_returns(np.ones(4, np.uint8), np.ones(4, np.uint8)) is None


def test_volume_returns_take_no_incidence_correction() -> None:
    model = RadiometricModel(visibility_km=20.0)
    intensity = np.full(4, 50.0, np.float32)
    r = np.full(4, 800.0)
    cos_t = np.array([0.02, math.nan, 0.5, 1.0])
    volume = np.array([True, True, False, False])
    refl, grazing = model.reflectance(intensity, r, cos_t, volume=volume)
    normal, _ = model.reflectance(intensity, r, np.ones(4))
    # cos 1 whatever the normal said (grazing or none); the others as before.
    np.testing.assert_allclose(refl[:2], normal[:2], rtol=1e-7)
    assert refl[2] == pytest.approx(2.0 * normal[2], rel=1e-6)
    np.testing.assert_array_equal(grazing, [False, False, False, False])
    _, grazing_surface = model.reflectance(intensity, r, cos_t)
    assert grazing_surface[0]


def _with_canopy(sim: Any, seed: int = 5) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The first strip of a simulated mission with a canopy over part of its open ground: for
    40% of the pulses on soil, grass or asphalt, a first return 4-12 m up the beam, scattered
    1.5 m about it, of intensity 80; the ground return becomes the last of two. Returns the
    cloud (time order, the canopy return before its ground one) and, per point, the true
    incidence (NaN for canopy), whether it is canopy, ground under canopy or open ground."""
    strip = sim.mission.strips[0]
    n = len(strip)
    rng = np.random.default_rng(seed)
    cls = sim.surface_class[0]
    ground = np.isin(cls, (SOIL, GRASS, ASPHALT))
    shaded = ground & (rng.random(n) < 0.4)
    idx = np.flatnonzero(shaded)
    traj = sim.mission.trajectory
    origin = np.column_stack([np.interp(strip.t[idx], traj.t, traj.xyz[:, k]) for k in range(3)])
    beam = strip.xyz[idx] - origin
    beam /= np.linalg.norm(beam, axis=1)[:, None]
    up = rng.uniform(*CANOPY_HEIGHT_M, idx.size) / -beam[:, 2]  # along the beam, m
    canopy_xyz = strip.xyz[idx] - beam * up[:, None]
    canopy_xyz[:, :2] += rng.normal(0.0, CANOPY_SCATTER_M, (idx.size, 2))
    m = idx.size
    rn = np.concatenate([np.ones(n, np.uint8), np.ones(m, np.uint8)])
    nr = np.concatenate([np.where(shaded, 2, 1).astype(np.uint8), np.full(m, 2, np.uint8)])
    rn[idx] = 2
    order = np.lexsort((rn, np.concatenate([strip.t, strip.t[idx]])))
    assert strip.intensity is not None
    grown = dataclasses.replace(
        strip, xyz=np.concatenate([strip.xyz, canopy_xyz])[order],
        t=np.concatenate([strip.t, strip.t[idx]])[order],
        intensity=np.concatenate([strip.intensity, np.full(m, 80.0, np.float32)])[order],
        extra={"return_number": rn[order], "number_of_returns": nr[order]})
    truth = {
        "incidence": np.concatenate([sim.incidence_true[0], np.full(m, np.nan)])[order],
        "canopy": np.concatenate([np.zeros(n, bool), np.ones(m, bool)])[order],
        "under": np.concatenate([shaded, np.zeros(m, bool)])[order],
        "open": np.concatenate([ground & ~shaded, np.zeros(m, bool)])[order],
    }
    return strip_point_array(grown, {}, "test"), truth


def _corrected(sim: Any, points: np.ndarray) -> tuple[np.ndarray, CorrectionStats]:
    settings = CorrectionSettings.from_config(
        FlightConfig(), np.array([sim.biases[n] for n in PARAMETER_NAMES]))
    corrector = StreamCorrector(sim.mission.trajectory, settings, batch_points=20_000)
    out = [c for start in range(0, len(points), 7000)
           for _, c in corrector.push(points[start:start + 7000])]
    out.extend(c for _, c in corrector.flush())
    return np.concatenate(out), corrector.stats


def test_canopy_returns_get_no_incidence_and_leave_the_ground_normals_alone(
        small_mission: MissionFiles) -> None:
    sim = small_mission.sim
    points, truth = _with_canopy(sim)
    p, stats = _corrected(sim, points)
    # The same cloud without return numbers: every return taken as a surface (the rule of
    # clouds that do not say), the canopy inside the normals' grid.
    plain = recfunctions.drop_fields(points, ["return_number", "number_of_returns"],
                                     usemask=False)
    q, plain_stats = _corrected(sim, plain)
    flags, canopy = p["correction_flags"], truth["canopy"]
    # Canopy: flagged volume, no incidence, never grazing nor without a normal, and the
    # reflectance of normal incidence (cos 1) from its own range.
    assert np.array_equal((flags & FLAG_VOLUME) != 0, canopy)
    assert np.isnan(p["incidence"][canopy]).all()
    assert not (flags[canopy] & (FLAG_GRAZING | FLAG_NO_NORMAL | FLAG_ROUGH)).any()
    model = RadiometricModel.from_config(FlightConfig())
    want, _ = model.reflectance(p["intensity"][canopy], p["range"][canopy],
                                np.ones(int(canopy.sum())))
    np.testing.assert_allclose(p["reflectance"][canopy], want, rtol=2e-6)
    # Ground under the canopy: its normals from the last returns, as good as the open
    # ground's; with the canopy in the grid they tilt and their incidence is wrong.
    def error_deg(cloud: np.ndarray, sel: np.ndarray) -> float:
        return float(np.degrees(np.nanmedian(np.abs(cloud["incidence"][sel]
                                                     - truth["incidence"][sel]))))

    under, open_ground = truth["under"], truth["open"]
    err_under, err_open, err_plain = (error_deg(p, under), error_deg(p, open_ground),
                                      error_deg(q, under))
    print(f"median incidence error, deg: ground under canopy {err_under:.2f}, open ground "
          f"{err_open:.2f}; under canopy without return numbers {err_plain:.2f}")
    assert err_under < 1.0 and err_under < 1.5 * err_open + 0.1
    assert err_plain > 5.0 * err_under
    # Clamped grazing: the canopy's scattered returns as surfaces graze their planes.
    grazing = np.mean((flags & FLAG_GRAZING) != 0)
    grazing_plain = np.mean((q["correction_flags"] & FLAG_GRAZING) != 0)
    print(f"clamped grazing: {100 * grazing:.1f}% with the rule, {100 * grazing_plain:.1f}% "
          "without return numbers")
    assert grazing_plain > 0.02 and grazing < 0.3 * grazing_plain
    # The summary says which rule each share got.
    share = 100.0 * canopy.mean()
    assert stats.volume == int(canopy.sum())
    line = stats.describe_incidence()
    assert line.startswith("surface normal for ")
    assert f"none for volume (canopy) returns {share:.0f}%" in line
    assert "volume" not in plain_stats.describe_incidence() and plain_stats.volume == 0


def test_incidence_summary_counts_each_point_once() -> None:
    from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED

    flags = np.array([0] * 70 + [FLAG_VOLUME] * 27 + [FLAG_GRAZING | FLAG_ROUGH] * 2
                     + [FLAG_ROUGH] + [FLAG_NOT_CORRECTED] * 5, dtype=np.uint8)
    stats = CorrectionStats()
    stats.add(CloudTally(np.concatenate([np.bincount(flags, minlength=256), [0]])))
    assert stats.incidence_rules == {"surface normal": 70,
                                     "none for volume (canopy) returns": 27,
                                     "bounded (rough)": 1, "clamped grazing": 2,
                                     "no normal": 0}
    assert stats.describe_incidence() == (
        "surface normal for 70% of the points, none for volume (canopy) returns 27%, "
        "bounded (rough) 1%, clamped grazing 2%")
    assert CorrectionStats().describe_incidence() == "no point corrected"
