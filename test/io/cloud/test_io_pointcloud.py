"""PointCloud2 bytes <-> numpy: layouts, aliases, zero copy, errors."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from lidarcal_ros.errors import CloudFormatError
from lidarcal_ros.io.cloud.columns import extract_columns
from lidarcal_ros.io.cloud.pointcloud import (
    FLOAT32,
    FLOAT64,
    UINT8,
    UINT16,
    UINT32,
    array_to_cloud_parts,
    cloud_dtype,
    cloud_to_array,
    make_point_dtype,
    without_padding_garbage,
)


def _msg(fields, point_step, data, width, height=1, row_step=None, is_bigendian=False):
    return SimpleNamespace(
        fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
        point_step=point_step,
        row_step=width * point_step if row_step is None else row_step,
        width=width,
        height=height,
        is_bigendian=is_bigendian,
        data=data,
    )


def _cloud_from(arr: np.ndarray, **kw):
    fields, step, data = array_to_cloud_parts(arr)
    return _msg(fields, step, data.tobytes(), len(arr), **kw)


def test_padding_is_zeroed_whatever_memory_held() -> None:
    """An aligned layout's padding after numpy's copies holds whatever memory was there;
    ``without_padding_garbage`` gives the same fields with the padding zero, and a layout
    without padding back as it is."""
    dt = np.dtype([("x", "<f8"), ("intensity", "<f4"), ("ring", "u1")], align=True)
    assert dt.itemsize == 16  # 3 bytes of padding
    junk = np.frombuffer(bytearray(b"\xab" * 16 * 64), dtype=dt)  # (writable, no copy)
    junk["x"], junk["intensity"], junk["ring"] = np.arange(64.0), 2.5, 7
    assert np.frombuffer(junk.tobytes(), np.uint8).reshape(-1, 16)[:, 13:].all()
    clean = without_padding_garbage(junk)
    assert not np.frombuffer(clean.tobytes(), np.uint8).reshape(-1, 16)[:, 13:].any()
    for name in dt.names or ():
        assert np.array_equal(clean[name], junk[name])
    packed = np.zeros(8, dtype=[("x", "<f8"), ("y", "<f8")])
    assert without_padding_garbage(packed) is packed


def test_padding_and_odd_order_round_trip():
    # t first, z before x, 4 bytes of padding after intensity, 8 trailing bytes.
    dt = np.dtype(
        {
            "names": ["t", "intensity", "z", "x", "y", "strip_id"],
            "formats": ["<f8", "<u2", "<f8", "<f8", "<f8", "<u4"],
            "offsets": [0, 8, 16, 24, 32, 40],
            "itemsize": 52,
        }
    )
    src = np.zeros(4, dtype=dt)
    src["x"] = [1.5, -2.25, 3e5, 4.0]
    src["y"] = [10.0, 20.0, 30.0, 40.0]
    src["z"] = [0.1, 0.2, 0.3, 0.4]
    src["t"] = [1.7e9 + 0.125, 1.7e9 + 0.25, 1.7e9 + 0.375, 1.7e9 + 0.5]
    src["intensity"] = [0, 1, 65535, 7]
    src["strip_id"] = [3, 3, 70000, 3]
    fields, step, data = array_to_cloud_parts(src)
    assert step == 52
    assert ("intensity", 8, UINT16, 1) in fields and ("strip_id", 40, UINT32, 1) in fields
    arr = cloud_to_array(_msg(fields, step, bytes(data), 4))
    assert arr.dtype.itemsize == 52
    assert np.array_equal(arr, src)
    cols = extract_columns(arr)
    assert cols.xyz.dtype == np.float64 and cols.xyz.shape == (4, 3)
    assert np.array_equal(cols.xyz, np.column_stack([src["x"], src["y"], src["z"]]))
    assert np.array_equal(cols.t, src["t"])
    assert cols.intensity is not None and cols.intensity.dtype == np.float32
    assert cols.intensity.tolist() == [0.0, 1.0, 65535.0, 7.0]
    assert cols.strip_id is not None and cols.strip_id.dtype == np.uint32
    assert cols.strip_id.tolist() == [3, 3, 70000, 3]
    assert cols.return_number is None and cols.number_of_returns is None


def test_float32_coordinates_upcast_and_uint8_intensity():
    fields = [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1),
              ("t", 16, FLOAT64, 1), ("intensity", 24, UINT8, 1),
              ("return_number", 25, UINT8, 1), ("number_of_returns", 26, UINT8, 1)]
    dt = cloud_dtype(fields, 32)
    src = np.zeros(3, dtype=dt)
    src["x"] = [0.5, 1.25, -3.0]
    src["y"] = [2.0, 3.0, 4.0]
    src["z"] = [100.0, 101.5, 99.25]
    src["t"] = [5.0, 6.0, 7.0]
    src["intensity"] = [9, 200, 255]
    src["return_number"] = [1, 2, 1]
    src["number_of_returns"] = [2, 2, 1]
    cols = extract_columns(cloud_to_array(_msg(fields, 32, src.tobytes(), 3)))
    assert cols.xyz.dtype == np.float64
    assert cols.xyz.tolist() == [[0.5, 2.0, 100.0], [1.25, 3.0, 101.5], [-3.0, 4.0, 99.25]]
    assert cols.intensity is not None and cols.intensity.tolist() == [9.0, 200.0, 255.0]
    assert cols.return_number is not None and cols.return_number.dtype == np.uint8
    assert cols.return_number.tolist() == [1, 2, 1]
    assert cols.number_of_returns is not None and cols.number_of_returns.tolist() == [2, 2, 1]
    assert cols.strip_id is None


@pytest.mark.parametrize("alias", ["time", "timestamp", "gps_time"])
def test_time_alias_and_point_source_id(alias, caplog):
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), (alias, "<f8"),
                   ("point_source_id", "<u2")])
    src = np.zeros(2, dtype=dt)
    src[alias] = [11.5, 12.5]
    src["point_source_id"] = [42, 43]
    with caplog.at_level(logging.DEBUG, logger="lidarcal_ros.io.cloud.columns"):
        cols = extract_columns(cloud_to_array(_cloud_from(src)), source="/lidar/points")
    assert cols.time_field == alias
    assert cols.t.tolist() == [11.5, 12.5]
    assert cols.strip_id is not None and cols.strip_id.tolist() == [42, 43]
    assert alias in caplog.text


def test_explicit_time_field_and_ambiguous_aliases():
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("time", "<f8"),
                   ("gps_time", "<f8")])
    src = np.zeros(1, dtype=dt)
    src["time"], src["gps_time"] = 1.0, 2.0
    arr = cloud_to_array(_cloud_from(src))
    with pytest.raises(CloudFormatError, match="several time aliases"):
        extract_columns(arr)
    assert extract_columns(arr, time_field="gps_time").t.tolist() == [2.0]


def test_row_padding():
    # 2 rows of 3 points, 5 spare bytes at the end of every row.
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8")])
    grid = np.zeros((2, 3), dtype=dt)
    grid["x"] = np.arange(6.0).reshape(2, 3)
    grid["t"] = 100 + np.arange(6.0).reshape(2, 3)
    row_step = 3 * dt.itemsize + 5
    buf = bytearray(2 * row_step)
    for r in range(2):
        buf[r * row_step: r * row_step + 3 * dt.itemsize] = grid[r].tobytes()
        buf[r * row_step + 3 * dt.itemsize: (r + 1) * row_step] = b"\xff" * 5
    fields, step, _ = array_to_cloud_parts(grid.reshape(-1))
    arr = cloud_to_array(_msg(fields, step, bytes(buf), 3, height=2, row_step=row_step))
    assert arr.shape == (6,)
    assert arr["x"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert arr["t"].tolist() == [100.0, 101.0, 102.0, 103.0, 104.0, 105.0]
    # The last row may come without its padding.
    arr2 = cloud_to_array(_msg(fields, step, bytes(buf[:-5]), 3, height=2, row_step=row_step))
    assert np.array_equal(arr2, arr)


def test_zero_copy_view():
    src = np.zeros(1000, dtype=make_point_dtype(("reflectance",)))
    src["x"] = np.arange(1000.0)
    fields, step, data = array_to_cloud_parts(src)
    assert np.shares_memory(data, src)
    payload = np.frombuffer(src.tobytes(), dtype=np.uint8)  # e.g. a rosbags message field
    arr = cloud_to_array(_msg(fields, step, payload, 1000))
    assert np.shares_memory(arr, payload)
    raw = src.tobytes()
    arr_b = cloud_to_array(_msg(fields, step, raw, 1000))
    assert arr_b.base is not None and arr_b["x"][999] == 999.0
    assert not arr_b.flags.owndata


def test_big_endian():
    dt = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f4"), ("t", ">f8"), ("strip_id", ">u2")])
    src = np.zeros(2, dtype=dt)
    src["x"], src["y"], src["z"] = [1.5, 2.5], [-1.0, 7.0], [0.25, 0.5]
    src["t"], src["strip_id"] = [3.0, 4.0], [258, 1]
    fields = [("x", 0, FLOAT64, 1), ("y", 8, FLOAT64, 1), ("z", 16, FLOAT32, 1),
              ("t", 20, FLOAT64, 1), ("strip_id", 28, UINT16, 1)]
    arr = cloud_to_array(_msg(fields, dt.itemsize, src.tobytes(), 2, is_bigendian=True))
    cols = extract_columns(arr)
    assert cols.xyz.tolist() == [[1.5, -1.0, 0.25], [2.5, 7.0, 0.5]]
    assert cols.t.tolist() == [3.0, 4.0]
    assert cols.strip_id is not None and cols.strip_id.tolist() == [258, 1]
    # Writing converts to little-endian bytes.
    fields2, step2, data2 = array_to_cloud_parts(src)
    back = cloud_to_array(_msg(fields2, step2, data2.tobytes(), 2))
    assert back.dtype["x"].byteorder in ("<", "=")
    assert back["strip_id"].tolist() == [258, 1] and back["z"].tolist() == [0.25, 0.5]


def test_count_field_is_subarray():
    fields = [("x", 0, FLOAT64, 1), ("y", 8, FLOAT64, 1), ("z", 16, FLOAT64, 1),
              ("t", 24, FLOAT64, 1), ("normal", 32, FLOAT32, 3)]
    dt = cloud_dtype(fields, 44)
    assert dt["normal"].shape == (3,)
    src = np.zeros(2, dtype=dt)
    src["normal"] = [[0, 0, 1], [0, 1, 0]]
    fields2, step, _ = array_to_cloud_parts(src)
    assert ("normal", 32, FLOAT32, 3) in fields2 and step == 44


def test_missing_fields_named():
    dt = np.dtype([("x", "<f8"), ("z", "<f8"), ("t", "<f8")])
    arr = cloud_to_array(_cloud_from(np.zeros(2, dtype=dt)))
    with pytest.raises(CloudFormatError) as info:
        extract_columns(arr, source="/lidar/points")
    msg = str(info.value)
    assert "/lidar/points" in msg and "'y'" not in msg and " y" in msg
    assert "fields present: x, z, t" in msg and "\n" not in msg

    dt2 = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("stamp", "<f8")])
    arr2 = cloud_to_array(_cloud_from(np.zeros(1, dtype=dt2)))
    with pytest.raises(CloudFormatError, match=r"lacks time field 't'.*x, y, z, stamp"):
        extract_columns(arr2, source="bag.mcap")


def test_wrong_types_named():
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f4")])
    with pytest.raises(CloudFormatError, match="field 't' is FLOAT32; expected FLOAT64"):
        extract_columns(cloud_to_array(_cloud_from(np.zeros(1, dtype=dt))))
    dt = np.dtype([("x", "<i4"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8")])
    with pytest.raises(CloudFormatError, match="field 'x' is INT32"):
        extract_columns(cloud_to_array(_cloud_from(np.zeros(1, dtype=dt))))


def test_bad_layouts():
    with pytest.raises(CloudFormatError, match=r"field 'y'.*beyond point_step 12"):
        cloud_dtype([("x", 0, FLOAT64, 1), ("y", 8, FLOAT64, 1)], 12)
    with pytest.raises(CloudFormatError, match="field 'q' has unknown PointField datatype 9"):
        cloud_dtype([("q", 0, 9, 1)], 8)
    with pytest.raises(CloudFormatError, match="fields 'x' and 'y' overlap"):
        cloud_dtype([("x", 0, FLOAT64, 1), ("y", 4, FLOAT32, 1)], 16)
    fields = [("x", 0, FLOAT64, 1)]
    with pytest.raises(CloudFormatError, match=r"/pts: data has 20 bytes"):
        cloud_to_array(_msg(fields, 8, b"\0" * 20, 3), source="/pts")
    with pytest.raises(CloudFormatError, match="row_step 8 < width 2"):
        cloud_to_array(_msg(fields, 8, b"\0" * 16, 2, row_step=8))


def test_make_point_dtype():
    dt = make_point_dtype(("reflectance", "range", "incidence", "scan_angle"))
    assert dt.names == ("x", "y", "z", "t", "intensity", "strip_id", "reflectance",
                        "range", "incidence", "scan_angle")
    assert [dt[n].str for n in ("x", "t", "intensity", "strip_id", "range")] == [
        "<f8", "<f8", "<f4", "<u2", "<f4"]
    assert dt.itemsize % 8 == 0
    assert "intensity" not in (make_point_dtype(intensity=False).names or ())
    with pytest.raises(CloudFormatError, match="'t' clashes"):
        make_point_dtype(("t",))


def test_time_span_skips_nan_and_says_nan_when_there_is_no_time() -> None:
    import math
    import warnings

    from lidarcal_ros.io.cloud.columns import time_span

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning for all-NaN times either
        assert time_span(np.array([3.0, np.nan, 1.0, 2.0])) == (1.0, 3.0)
        assert all(math.isnan(v) for v in time_span(np.array([np.nan, np.nan])))
        assert all(math.isnan(v) for v in time_span(np.empty(0)))


def test_extracted_columns_carry_their_time_span_and_whether_all_is_finite() -> None:
    """Both are found in the extraction's pass, so that the correction need not look again."""
    from lidarcal_ros.io.cloud.columns import time_span

    pts = np.zeros(40, dtype=make_point_dtype())
    pts["t"] = 100.0 + np.arange(40) * 0.01
    pts["x"] = np.arange(40)
    cols = extract_columns(pts)
    assert cols.t_span == (100.0, 100.39) and cols.all_finite
    for field, row, value in (("t", 0, np.nan), ("x", 5, np.inf), ("z", 39, np.nan)):
        bad = pts.copy()
        bad[field][row] = value
        cols = extract_columns(bad)
        assert cols.t_span == time_span(bad["t"]) and cols.all_finite is False
        finite = cols.finite()
        assert not finite[row] and finite.sum() == 39
        kept = cols.take(finite)
        assert len(kept) == 39 and kept.strip_id is not None and len(kept.strip_id) == 39
        np.testing.assert_array_equal(kept.xyz, cols.xyz[finite])
        assert kept.all_finite is None and kept.t_span is None
    cols = extract_columns(pts)
    assert cols.finite().all() and cols.take(np.arange(5)).all_finite
    nat = pts.copy()
    nat["t"] = np.nan
    lo, hi = extract_columns(nat).t_span or (0.0, 0.0)
    assert np.isnan(lo) and np.isnan(hi)


def test_big_endian_fields_are_read_and_judged_like_little_endian_ones() -> None:
    """The compiled loops take native byte order; other clouds go the numpy way."""
    from lidarcal_ros.io.cloud.columns import extract_xyz
    from lidarcal_ros.io.cloud.messages import is_dense_byte

    little = np.zeros(50, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f4")])
    little["x"], little["y"], little["z"] = np.arange(50), -np.arange(50), 0.5
    big = little.astype([("x", ">f8"), ("y", ">f8"), ("z", ">f4")])
    np.testing.assert_array_equal(extract_xyz(big), extract_xyz(little))
    assert is_dense_byte(big) == is_dense_byte(little) == b"\x01"
    big["y"][7] = np.nan
    assert is_dense_byte(big) == b"\x00"
