"""LAS and LAZ files cut short, or whose header claims more points than they hold, through
``lidarcal import`` end to end: one line naming the file, exit 1, nothing at the output.

The LAZ (the small mission as one tile, 160878 points in four chunks of 50000) is cut at
offsets chosen in each of its parts: the header's VLRs, the chunk table's offset at the start
of the point data, the first chunk, the middle, inside the chunk table at the end and its last
byte. The file whole imports (the check that the cuts, not the file, are refused).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import helpers_missions
import laspy
import pytest
from helpers_cli import one_line_error, run
from helpers_las import plain_strips, write_las_tiles, write_mission_sbet
from helpers_missions import MissionFiles

from lidarcal_ros.io.bag.mission_bag import read_mission

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory


class Laz:
    """The small mission as one LAZ tile, its SBET, and where its parts lie."""

    def __init__(self, small: MissionFiles, root: Path) -> None:
        (self.path,) = write_las_tiles(plain_strips(small.sim), root, tiles=(1, 1))
        assert self.path.suffix == ".laz"
        self.sbet = write_mission_sbet(small.mission, root / "sbet.out")
        self.data = self.path.read_bytes()
        header = laspy.read(str(self.path)).header
        self.n = int(header.point_count)
        self.points_at = int(header.offset_to_point_data)
        (self.table_at,) = struct.unpack_from("<q", self.data, self.points_at)
        assert self.points_at < self.table_at < len(self.data)


@pytest.fixture(scope="module")
def laz(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory) -> Laz:
    return Laz(small_mission, tmp_path_factory.mktemp("laz"))


#: Where the LAZ is cut, in bytes kept (from its parts' offsets) and the error's words.
CUTS: dict[str, tuple[Callable[[Laz], int], str]] = {
    "in the header's VLRs": (lambda z: 300, "the header places the points at byte {at}, beyond "
                                            "the file's 300 bytes (truncated?)"),
    "in the chunk table's offset": (lambda z: z.points_at + 4, "corrupt or truncated point "
                                                               "data after 0 of {n} points"),
    "in the first chunk": (lambda z: z.points_at + 100, "corrupt or truncated point data "
                                                        "after 0 of {n} points"),
    "in the middle": (lambda z: len(z.data) // 2, "corrupt or truncated point data after 0 of "
                                                  "{n} points"),
    "in the chunk table": (lambda z: z.table_at + 10, "corrupt or truncated point data after "
                                                      "0 of {n} points"),
    "its last byte": (lambda z: len(z.data) - 1, "corrupt or truncated point data after 0 of "
                                                 "{n} points"),
}


def _import_refused(capsys: pytest.CaptureFixture[str], laz: Laz, path: Path,
                    words: str) -> None:
    before = path.read_bytes()
    out = path.with_name("bag")
    rc, _, err = run(capsys, "import", path, "--trajectory", laz.sbet, "-o", out, "--qa-cell",
                     "0")
    assert one_line_error(rc, err, "import").startswith(f"{path}: {words}")
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert path.read_bytes() == before


def test_the_whole_laz_imports(capsys, laz, tmp_path) -> None:
    rc, _, err = run(capsys, "import", laz.path, "--trajectory", laz.sbet, "-o",
                     tmp_path / "bag", "--qa-cell", "0", "-q")
    assert rc == 0, err
    assert read_mission(tmp_path / "bag").n_points == laz.n


@pytest.mark.parametrize("where", CUTS)
def test_a_laz_cut_short_is_one_line(capsys, laz, tmp_path, where) -> None:
    keep, words = CUTS[where]
    cut = tmp_path / "cut.laz"
    cut.write_bytes(laz.data[: keep(laz)])
    _import_refused(capsys, laz, cut, words.format(at=laz.points_at, n=laz.n))


@pytest.mark.parametrize("claimed", [200_000, 2**40])
def test_a_laz_header_claiming_more_points_than_its_chunks_hold(capsys, laz, tmp_path,
                                                                 claimed) -> None:
    """LAS 1.4's 64-bit point count raised (the legacy 32-bit one zero, as for more than
    2**32 points): refused in one line, read in chunks of bounded size, never allocated
    for the count claimed (2**40 points would be 30 TB)."""
    data = bytearray(laz.data)
    struct.pack_into("<I", data, 107, 0)
    struct.pack_into("<Q", data, 247, claimed)
    lying = tmp_path / "lying.laz"
    lying.write_bytes(bytes(data))
    _import_refused(capsys, laz, lying, f"corrupt or truncated point data after 0 of "
                                        f"{claimed} points")


@pytest.mark.parametrize("fraction", [0.0005, 0.5, 0.9999])
def test_a_las_cut_short_is_refused_before_reading(capsys, laz, tmp_path, fraction) -> None:
    whole = tmp_path / "whole.las"
    laspy.read(str(laz.path)).write(str(whole))
    data = whole.read_bytes()
    with laspy.open(str(whole)) as reader:  # (the LAZ's header without its laszip VLR)
        header = reader.header
    whole.unlink()
    cut = tmp_path / "cut.las"
    start = int(header.offset_to_point_data)
    keep = start + int(fraction * (len(data) - start))
    cut.write_bytes(data[:keep])
    size = header.point_format.size
    held = keep - start
    _import_refused(capsys, laz, cut, f"truncated: the header claims {laz.n} points of {size} "
                                      f"bytes, the file holds {held} bytes of points "
                                      f"({held // size} points)")
