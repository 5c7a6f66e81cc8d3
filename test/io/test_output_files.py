"""io/output_files.py: outputs refused before any work, written whole or not at all."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lidarcal_ros.errors import OutputError
from lidarcal_ros.io.output_files import check_output, temporary_beside, write_text


def test_an_existing_output_needs_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "out.yaml"
    path.write_text("old")
    with pytest.raises(OutputError, match="exists \\(use --overwrite to replace it\\)"):
        check_output(path, overwrite=False)
    assert check_output(path, overwrite=True) == path
    assert path.read_text() == "old"  # checking never touches the output


def test_a_directory_where_a_file_goes_is_refused(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="is a directory"):
        check_output(tmp_path, overwrite=True)
    assert check_output(tmp_path / "bag", overwrite=False, directory=True) == tmp_path / "bag"


def test_a_missing_parent_is_refused(tmp_path: Path) -> None:
    with pytest.raises(OutputError) as raised:
        check_output(tmp_path / "no" / "such" / "out.las", overwrite=False)
    assert "\n" not in str(raised.value) and "out.las" in str(raised.value)


def test_write_text_replaces_whole_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "calibration.yaml"
    path.write_text("previous\n")
    assert write_text(path, "new\n", what="calibration") == path
    assert path.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yaml"]


def test_a_failed_write_keeps_the_previous_output(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "calibration.yaml"
    path.write_text("previous\n")

    def full_disk(*_args: object, **_kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OutputError, match="No space left on device"):
        write_text(path, "new\n", what="calibration")
    assert path.read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yaml"]


def test_the_temporary_is_hidden_beside_the_output(tmp_path: Path) -> None:
    temporary = temporary_beside(tmp_path / "out.laz")
    assert temporary.parent == tmp_path and temporary.name.startswith(".")


def test_an_output_that_appears_meanwhile_is_not_replaced(tmp_path: Path) -> None:
    """Without overwrite, a file another writer put at the output while this one wrote is
    left as it is, and this one's output discarded (no temporary left)."""
    path = tmp_path / "calibration.yaml"
    check_output(path, overwrite=False)
    path.write_text("the other writer's\n")
    with pytest.raises(OutputError, match="appeared while this command was writing it"):
        write_text(path, "mine\n", what="calibration", overwrite=False)
    assert path.read_text() == "the other writer's\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yaml"]


def test_a_bag_that_appears_meanwhile_is_not_replaced(tmp_path: Path) -> None:
    from lidarcal_ros.io.bag.writer import BagWriter

    path = tmp_path / "out_bag"
    with pytest.raises(OutputError, match="appeared while"):
        with BagWriter(path) as writer:
            writer.add_topic("/lidar/trajectory", "geometry_msgs/msg/PoseStamped")
            path.mkdir()
            (path / "theirs.mcap").write_bytes(b"theirs")
    assert [p.name for p in path.iterdir()] == ["theirs.mcap"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out_bag"]


def test_install_with_overwrite_replaces_a_directory(tmp_path: Path) -> None:
    from lidarcal_ros.io.output_files import install

    new, path = tmp_path / ".new", tmp_path / "bag"
    new.mkdir()
    (new / "a.mcap").write_bytes(b"new")
    path.mkdir()
    (path / "b.mcap").write_bytes(b"old")
    install(new, path, overwrite=True)
    assert [p.name for p in path.iterdir()] == ["a.mcap"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


@pytest.mark.parametrize("name", ["a" * 250 + ".laz", "ü" * 120 + ".yaml", "x" * 255])
def test_long_and_unicode_names_are_written(tmp_path: Path, name: str) -> None:
    """A legal name of up to 255 bytes: its hidden temporary must not pass the limit."""
    path = tmp_path / name
    check_output(path, overwrite=False)
    write_text(path, "done\n", what="calibration", overwrite=False)
    assert path.read_text() == "done\n"
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_files_written_together_are_all_or_none(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The second file's write fails (a full disk): neither file is new, the first's
    previous content kept, no temporary left; both written when nothing fails."""
    from lidarcal_ros.io import output_files

    first, second = tmp_path / "cal.yaml", tmp_path / "cal.urdf.xml"
    first.write_text("old calibration")
    real_open = open

    def full_at_second(path: object, *args: object, **kwargs: object) -> object:
        if Path(str(path)) == temporary_beside(second):
            raise OSError(28, "No space left on device", str(path))
        return real_open(path, *args, **kwargs)  # type: ignore[call-overload]

    monkeypatch.setattr(output_files, "open", full_at_second, raising=False)
    files = [(first, b"new calibration", "calibration"), (second, b"<joint/>", "URDF joint")]
    with pytest.raises(OutputError) as raised:
        output_files.write_together(files)
    assert str(raised.value) == f"{second}: cannot write URDF joint (No space left on device)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.yaml"]
    assert first.read_text() == "old calibration"
    monkeypatch.undo()
    output_files.write_together(files)
    assert first.read_bytes() == b"new calibration" and second.read_bytes() == b"<joint/>"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.urdf.xml", "cal.yaml"]


def test_a_name_longer_than_the_file_system_takes_is_refused(tmp_path: Path) -> None:
    assert check_output(tmp_path / ("a" * 255), overwrite=False) == tmp_path / ("a" * 255)
    with pytest.raises(OutputError, match=r"name of 256 bytes; the file system takes at most "
                                          r"255$"):
        check_output(tmp_path / ("ü" * 128), overwrite=False)
