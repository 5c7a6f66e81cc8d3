"""LAS/LAZ headers and SBETs that claim more than their files hold: refused in one line
before anything loops over the claim."""

from __future__ import annotations

import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_cli import one_line_error, run_process

from lidarcal_ros.errors import InputError
from lidarcal_ros.io.survey.las_reader import LasFileError, inspect_las, iter_las_chunks
from lidarcal_ros.io.survey.trajectory_files import (
    MAX_TRAJECTORY_RECORDS,
    SBET_RECORD_BYTES,
    read_sbet,
    read_smrmsg,
)

ROOT = Path(__file__).parents[3]


def _las(path: Path, *, version: str = "1.2", n: int = 100) -> Path:
    """A small LAS/LAZ (by the suffix) of ``n`` points with GPS time."""
    import laspy

    header = laspy.LasHeader(point_format=6 if version == "1.4" else 1, version=version)
    header.scales = [0.01, 0.01, 0.01]
    header.offsets = [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x = np.arange(n, dtype=float)
    las.y = np.zeros(n)
    las.z = np.zeros(n)
    las.gps_time = np.arange(n, dtype=float)
    las.write(str(path))
    return path


def _patch(path: Path, offset: int, fmt: str, value: int) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))


def _refused_in_child(path: Path) -> tuple[str, float]:
    """Read ``path``'s header and points in a fresh interpreter (a regression hangs there,
    killed by the timeout, rather than the suite): its answer and the seconds taken."""
    code = ("from lidarcal_ros.io.survey.las_reader import inspect_las, iter_las_chunks\n"
            "from lidarcal_ros.errors import InputError\n"
            f"p = {str(path)!r}\n"
            "try:\n    inspect_las(p); print('read', sum(len(c) for c in iter_las_chunks(p)))\n"
            "except InputError as e:\n    print(e)\n")
    start = time.monotonic()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True, cwd=ROOT).stdout.strip()
    return out, time.monotonic() - start


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_header_claiming_four_billion_vlrs_is_refused_at_once(tmp_path: Path,
                                                                suffix: str) -> None:
    path = _las(tmp_path / f"vlrs{suffix}")
    room = struct.unpack_from("<I", path.read_bytes(), 96)[0] - 227
    _patch(path, 100, "<I", 0xFFFF_FFFF)
    answer, seconds = _refused_in_child(path)
    assert answer == (f"{path}: the header claims 4294967295 VLRs; the {room} bytes between the "
                      f"header and the points hold at most {room // 54}; refused")
    assert seconds < 20


def test_a_header_claiming_billions_of_extended_vlrs_is_refused(tmp_path: Path) -> None:
    path = _las(tmp_path / "evlrs.las", version="1.4")
    size = path.stat().st_size
    _patch(path, 235, "<Q", size - 10)
    _patch(path, 243, "<I", 0xFFFF_FFFF)
    with pytest.raises(LasFileError) as raised:
        inspect_las(path)
    assert str(raised.value) == (f"{path}: the header claims 4294967295 extended VLRs from byte "
                                 f"{size - 10}; the file's {size} bytes hold at most 0; refused")


@pytest.mark.parametrize(("version", "offset", "fmt", "record"),
                         [("1.2", 107, "<I", 28), ("1.4", 247, "<Q", 30)])
def test_more_points_than_the_file_holds_are_refused_before_reading(
        tmp_path: Path, version: str, offset: int, fmt: str, record: int) -> None:
    path = _las(tmp_path / "points.las", version=version)
    _patch(path, offset, fmt, 10**9)
    for read in (inspect_las, lambda p: list(iter_las_chunks(p))):
        with pytest.raises(LasFileError) as raised:
            read(path)
        assert str(raised.value) == (f"{path}: truncated: the header claims 1000000000 points "
                                     f"of {record} bytes, the file holds {100 * record} bytes "
                                     "of points (100 points)")


def test_points_placed_beyond_the_end_are_refused(tmp_path: Path) -> None:
    path = _las(tmp_path / "offset.las")
    _patch(path, 96, "<I", 10**9)
    with pytest.raises(LasFileError, match=r"places the points at byte 1000000000, beyond the "
                                           r"file's \d+ bytes \(truncated\?\)"):
        inspect_las(path)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_honest_files_and_a_truncated_one(tmp_path: Path, suffix: str) -> None:
    path = _las(tmp_path / f"ok{suffix}", n=1000)
    assert inspect_las(path).point_count == 1000
    assert sum(len(c) for c in iter_las_chunks(path, chunk_points=300)) == 1000
    data = path.read_bytes()
    path.write_bytes(data[:len(data) - 500])  # cut: the header's count stays
    with pytest.raises(LasFileError, match=rf"^{path}: (truncated|corrupt or truncated)"):
        list(iter_las_chunks(path))


def test_import_of_a_lying_las_fails_in_one_line_and_leaves_no_bag(tmp_path: Path) -> None:
    path = _las(tmp_path / "strip.las")
    _patch(path, 100, "<I", 0xFFFF_FFFF)
    out = tmp_path / "mission"
    done = run_process("import", path, "--trajectory", "estimate", "--crs", "EPSG:32632",
                       "-o", out, cwd=ROOT)
    reason = one_line_error(done.returncode, done.stderr, "import")
    assert reason.startswith(f"{path}: the header claims 4294967295 VLRs")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strip.las"]


def _sparse(path: Path, size: int) -> Path:
    with path.open("wb") as f:
        f.truncate(size)
    return path


def test_an_sbet_of_impossible_length_is_refused_without_reading(tmp_path: Path) -> None:
    records = MAX_TRAJECTORY_RECORDS + 1
    path = _sparse(tmp_path / "sbet_huge.out", records * SBET_RECORD_BYTES)
    start = time.monotonic()
    with pytest.raises(InputError) as raised:
        read_sbet(path)
    assert time.monotonic() - start < 5
    assert str(raised.value) == (f"{path}: {records} SBET records, more than the 50000000 of "
                                 "69 hours at 200 Hz; refused (a sparse or foreign file?)")
    smrmsg = _sparse(tmp_path / "smrmsg_huge.out", records * 80)
    with pytest.raises(InputError, match=rf"{records} smrmsg records, more than"):
        read_smrmsg(smrmsg)


@pytest.mark.parametrize("size", [1, SBET_RECORD_BYTES * 3 + 1, SBET_RECORD_BYTES * 3 - 1])
def test_an_sbet_not_of_whole_records_is_refused(tmp_path: Path, size: int) -> None:
    path = tmp_path / "sbet.out"
    path.write_bytes(bytes(size))
    with pytest.raises(InputError, match=rf"not an SBET: {size} bytes is not a whole number "
                                         "of 136-byte records"):
        read_sbet(path)
