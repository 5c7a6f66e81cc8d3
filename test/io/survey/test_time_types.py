"""Time bases and formats of survey files: a LAS header's GPS time type, a trajectory file's
kind (by suffix, content, or as told) and its times in each base against known instants."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidarcal_ros.io.survey.las_reader import GpsTimeType, inspect_las
from lidarcal_ros.io.survey.trajectory_files import (
    TimeBase,
    TrajectoryFileError,
    TrajectoryFileKind,
    read_trajectory_file,
    to_gps_seconds,
    write_sbet,
)

#: 2023-11-14 22:13:20 UTC: UNIX 1.7e9 s, GPS - UTC 18 s, GPS week 2288 (from 1_383_782_400 s).
UNIX = 1_700_000_000.0
GPS = UNIX - 315_964_800.0 + 18.0


@pytest.mark.parametrize(("base", "raw", "week"), [
    (TimeBase.WEEK, GPS - 2288 * 604_800.0, 2288),
    (TimeBase.ADJUSTED, GPS - 1e9, None),
    (TimeBase.GPS, GPS, None),
    (TimeBase.UNIX, UNIX, None),
])
def test_each_base_gives_the_same_gps_seconds(base: TimeBase, raw: float,
                                              week: int | None) -> None:
    assert to_gps_seconds(np.array([raw]), base, week=week)[0] == pytest.approx(GPS, abs=1e-6)


def test_week_seconds_need_the_week() -> None:
    with pytest.raises(ValueError, match="GPS week"):
        to_gps_seconds(np.array([252_818.0]), TimeBase.WEEK)


@pytest.mark.parametrize(("type_", "want"), [(0, GpsTimeType.WEEK), (1, GpsTimeType.ADJUSTED)])
def test_las_header_bit_names_the_gps_time_type(tmp_path: Path, type_: int,
                                                want: GpsTimeType) -> None:
    import laspy

    header = laspy.LasHeader(version="1.2", point_format=1)
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType(type_)
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.zeros(2), np.zeros(2), np.zeros(2)
    las.gps_time = np.array([1.0, 2.0])
    las.write(str(tmp_path / "a.las"))
    assert inspect_las(tmp_path / "a.las").gps_time_type is want


def _sbet(path: Path) -> Path:
    t = np.array([1.0, 2.0, 3.0])
    return write_sbet(path, t, np.radians(np.full(3, 45.0)), np.radians(np.full(3, 7.0)),
                      np.full(3, 900.0))


def test_trajectory_file_kind_by_suffix_content_or_as_told(tmp_path: Path) -> None:
    """Without a kind the suffix decides, else the content (text or not); a kind given
    overrides the suffix."""
    text = "time,x,y,z\n1,0,0,900\n2,0,50,900\n"
    (tmp_path / "a.csv").write_text(text)
    (tmp_path / "a.traj").write_text(text)
    assert read_trajectory_file(tmp_path / "a.csv").kind is TrajectoryFileKind.ASCII
    assert read_trajectory_file(tmp_path / "a.traj").kind is TrajectoryFileKind.ASCII
    assert read_trajectory_file(_sbet(tmp_path / "a.out")).kind is TrajectoryFileKind.SBET
    assert read_trajectory_file(_sbet(tmp_path / "b.traj")).kind is TrajectoryFileKind.SBET
    # An SBET under a text suffix: read as text it is refused, as an SBET it is read.
    misnamed = _sbet(tmp_path / "c.dat")
    with pytest.raises(TrajectoryFileError, match="not a text trajectory"):
        read_trajectory_file(misnamed)
    traj = read_trajectory_file(misnamed, kind=TrajectoryFileKind.SBET)
    assert traj.kind is TrajectoryFileKind.SBET
    assert traj.b.tolist() == pytest.approx([45.0] * 3) and traj.t.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(TrajectoryFileError, match="not an SBET"):
        read_trajectory_file(tmp_path / "a.csv", kind=TrajectoryFileKind.SBET)
