"""io/survey/control.py: control point files, read back, and the bounds of a hostile one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.survey import control
from lidarcal_ros.io.survey.control import read_control_csv, write_control_csv


def test_write_then_read(tmp_path: Path) -> None:
    points = ControlPoints(["C1", "C2"], np.array([[500000.125, 5400000.5, 12.25],
                                                  [500010.0, 5400010.0, 13.0]]))
    path = tmp_path / "control.csv"
    write_control_csv(path, points)
    back = read_control_csv(path)
    assert back.ids == ["C1", "C2"]
    np.testing.assert_array_equal(back.xyz, points.xyz)


def test_bom_crlf_and_comments_are_read(tmp_path: Path) -> None:
    path = tmp_path / "control.csv"
    path.write_bytes(b"\xef\xbb\xbfID, X, Y, Z\r\n# surveyed 2026\r\nA,1,2,3\r\n\r\nB,4,5,6\r\n")
    back = read_control_csv(path)
    assert back.ids == ["A", "B"] and back.xyz.tolist() == [[1, 2, 3], [4, 5, 6]]


def test_duplicates_are_named_even_in_a_long_file(tmp_path: Path) -> None:
    """The duplicate check is a set lookup: 50,000 rows read at once (a list made a million
    rows take minutes)."""
    rows = [f"C{i},{i},{i},1.0" for i in range(50_000)] + ["C7,0,0,0"]
    path = tmp_path / "control.csv"
    path.write_text("id,x,y,z\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError, match="line 50002: duplicate id 'C7'"):
        read_control_csv(path)


def test_more_control_points_than_taken_are_refused(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(control, "MAX_CONTROL_POINTS", 1000)
    path = tmp_path / "control.csv"
    path.write_text("id,x,y,z\n" + "".join(f"C{i},{i},0,0\n" for i in range(1001)))
    with pytest.raises(InputError, match="1,001 control points; at most 1,000 are taken"):
        read_control_csv(path)
