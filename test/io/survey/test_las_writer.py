"""LAS/LAZ records written in one compiled pass (lidarcal_ros.io.survey.las_kernels) against laspy's
own field setters as the writer used them, byte for byte, on clouds with every awkward value."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.io.survey.las_writer import (
    _MAX_SCALED,
    EXTRA_DIMENSIONS,
    LasChunkWriter,
    unix_to_adjusted_gps,
)

T0 = 1.7e9


def _records_numpy(points: np.ndarray, header: laspy.LasHeader, gps_standard: bool
                   ) -> tuple[laspy.ScaleAwarePointRecord, dict[str, int]]:
    """What LasChunkWriter.write did with laspy's setters (the reference)."""
    counts = {"non_finite": 0, "out_of_range": 0, "clipped": 0, "withheld": 0}
    xyz = np.column_stack([np.asarray(points[c], dtype=np.float64) for c in "xyz"])
    t = np.asarray(points["t"], dtype=np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    counts["non_finite"] = int((~finite).sum())
    points, xyz, t = points[finite], xyz[finite], t[finite]
    fits = (np.abs((xyz - header.offsets) / header.scales) < _MAX_SCALED).all(axis=1)
    counts["out_of_range"] = int((~fits).sum())
    points, xyz, t = points[fits], xyz[fits], t[fits]
    n = len(points)
    names = points.dtype.names or ()
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec.gps_time = unix_to_adjusted_gps(t) if gps_standard else t
    if "intensity" in names:
        values = points["intensity"]
        if values.dtype == np.uint16:
            rec.intensity = values
        elif values.dtype == np.uint8:
            rec.intensity = np.asarray(values, dtype=np.uint16) * np.uint16(257)
        else:
            v = np.nan_to_num(np.rint(np.asarray(values, dtype=np.float64)), nan=0.0)
            counts["clipped"] = int(((v < 0) | (v > 65535)).sum())
            rec.intensity = np.clip(v, 0, 65535).astype(np.uint16)
    if "strip_id" in names:
        rec.point_source_id = np.clip(np.asarray(points["strip_id"], dtype=np.int64), 0, 65535)
    one = np.ones(n, dtype=np.uint8)
    rec.return_number = np.clip(points["return_number"], 1, 15).astype(np.uint8) \
        if "return_number" in names else one
    rec.number_of_returns = one
    if "scan_angle" in names:
        steps = np.degrees(-np.asarray(points["scan_angle"], dtype=np.float64)) / 0.006
        rec.scan_angle = np.clip(np.nan_to_num(np.rint(steps)), -30000, 30000).astype(np.int16)
    for name, kind, _ in EXTRA_DIMENSIONS:
        if name in names:
            rec[name] = np.asarray(points[name]).astype(kind)
        elif kind.startswith("f"):
            rec[name] = np.full(n, np.nan, dtype=kind)
    if "correction_flags" in names:
        withheld = (np.asarray(points["correction_flags"]) & FLAG_NOT_CORRECTED) != 0
        rec.withheld = withheld.astype(np.uint8)
        counts["withheld"] = int(withheld.sum())
    return rec, counts


def _cloud(intensity: str, n: int = 4000, *, times: float = T0) -> np.ndarray:
    rng = np.random.default_rng(3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"), ("intensity", intensity),
              ("strip_id", "<u2"), ("return_number", "u1"), ("reflectance", "<f4"),
              ("range", "<f4"), ("incidence", "<f4"), ("scan_angle", "<f4"),
              ("correction_flags", "u1")]
    pts = np.zeros(n, dtype=fields)
    pts["x"] = 4.5e5 + rng.uniform(-500, 500, n)
    pts["y"] = 5.4e6 + rng.uniform(-500, 500, n)
    pts["z"] = rng.uniform(-10, 60, n)
    pts["x"][::97] += 0.0005  # halfway between two millimetres: rounded half to even
    pts["t"] = times + np.sort(rng.uniform(0, 50, n))
    if intensity == "<f4":
        pts["intensity"] = rng.uniform(-100, 70000, n)
        pts["intensity"][::13] = np.nan
        pts["intensity"][::17] = np.inf
    else:
        pts["intensity"] = rng.integers(0, np.iinfo(np.dtype(intensity)).max, n)
    pts["strip_id"] = rng.integers(0, 9, n)
    pts["return_number"] = rng.integers(0, 20, n)
    pts["reflectance"] = rng.uniform(0, 1, n)
    pts["range"] = rng.uniform(900, 1400, n)
    pts["incidence"] = rng.uniform(0, 1.5, n)
    pts["scan_angle"] = rng.uniform(-0.5, 0.5, n)
    pts["scan_angle"][::11] = np.nan
    pts["scan_angle"][::23] = 4.0  # beyond the LAS range: clipped
    pts["correction_flags"] = rng.choice([0, 1, 2, 4, 5, 16], n)
    pts["x"][5] = np.nan  # not stored
    pts["z"][7] = np.inf
    pts["y"][9] = 1e12  # beyond LAS's 32-bit coordinates
    return pts


@pytest.mark.parametrize("intensity", ["<f4", "<u2", "u1"])
@pytest.mark.parametrize("times", [T0, 1234.5])  # UNIX times, and GPS week times
def test_records_are_those_of_lasps_setters(tmp_path: Path, intensity: str,
                                           times: float) -> None:
    cloud = _cloud(intensity, times=times)
    out = tmp_path / "out.las"
    with LasChunkWriter(out, time_field="t") as writer:
        writer.write(cloud[:1500])
        writer.write(cloud[1500:])
        header = writer.header
        gps_standard = bool(writer.gps_standard)
        stats = writer.stats
    expected = [_records_numpy(part, header, gps_standard) for part in (cloud[:1500],
                                                                        cloud[1500:])]
    want = np.concatenate([rec.array for rec, _ in expected])
    got = laspy.read(out).points.array
    assert got.dtype == want.dtype
    np.testing.assert_array_equal(got.view(np.uint8), want.view(np.uint8))
    assert stats.skipped_non_finite == sum(c["non_finite"] for _, c in expected) == 2
    assert stats.skipped_out_of_range == sum(c["out_of_range"] for _, c in expected) == 1
    assert stats.clipped_intensity == sum(c["clipped"] for _, c in expected)
    assert stats.withheld == sum(c["withheld"] for _, c in expected) > 0
    assert stats.points == len(want) == len(cloud) - 3
    if intensity == "<f4":
        assert stats.clipped_intensity > 100


def test_absent_fields_keep_their_defaults(tmp_path: Path) -> None:
    cloud = _cloud("<f4")[["x", "y", "z", "t"]]
    out = tmp_path / "out.laz"
    with LasChunkWriter(out, time_field="t") as writer:
        writer.write(cloud)
        header = writer.header
    want, _ = _records_numpy(np.asarray(cloud), header, True)
    got = laspy.read(out).points.array
    np.testing.assert_array_equal(got.view(np.uint8), want.array.view(np.uint8))
    assert np.isnan(got["reflectance"]).all() and (got["bit_fields"] == 0x11).all()
