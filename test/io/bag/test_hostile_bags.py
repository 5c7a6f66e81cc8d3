"""Bag metadata written to harm: files outside the bag, alias bombs, absurd nesting."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import helpers_missions
import pytest
import yaml
from helpers_missions import MissionFiles

from lidarcal_ros.errors import BagError
from lidarcal_ros.io.bag.reader import BagReader

mission_factory = helpers_missions.mission_factory


@pytest.fixture
def bag_copy(mission_factory: Callable[..., MissionFiles], tmp_path: Path) -> Path:
    """The small mission's bag, copied to be damaged."""
    return Path(shutil.copytree(mission_factory().bag, tmp_path / "mission"))


@pytest.mark.parametrize("named", ["../../etc/passwd", "/dev/zero", "../outside.mcap"])
def test_metadata_naming_files_outside_the_bag_is_refused(bag_copy: Path, named: str) -> None:
    meta = bag_copy / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    doc["rosbag2_bagfile_information"]["relative_file_paths"] = [named]
    meta.write_text(yaml.safe_dump(doc))
    with pytest.raises(BagError) as raised, BagReader(bag_copy):
        pass
    assert str(raised.value) == f"{meta}: names file(s) outside the bag: {named}; refused"


@pytest.mark.parametrize(("text", "expected"), [
    ("rosbag2_bagfile_information: &a [" + ", ".join(["x"] * 9) + "]\n"
     + "".join(f"b{i}: &b{i} [{', '.join(['*' + ('a' if i == 0 else f'b{i - 1}')] * 9)}]\n"
               for i in range(10)), "an alias bomb"),
    ("rosbag2_bagfile_information: " + "[" * 5000 + "]" * 5000 + "\n", "nests deeper"),
])
def test_hostile_metadata_is_refused_in_one_line(bag_copy: Path, text: str,
                                                 expected: str) -> None:
    (bag_copy / "metadata.yaml").write_text(text)
    with pytest.raises(BagError, match=expected) as raised, BagReader(bag_copy):
        pass
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize("where", ["the bag path", "the bag's storage file"])
def test_a_fifo_is_refused_not_read_forever(bag_copy: Path, where: str) -> None:
    """A FIFO would block the reader for ever (no writer) or feed it without end: refused in
    one line (checked in a child process, so a regression fails rather than hangs)."""
    import os
    import subprocess
    import sys

    if where == "the bag path":
        target = bag_copy.parent / "fifo"
        os.mkfifo(target)
        opened = target
    else:
        storage = next(bag_copy.glob("*.mcap"))
        storage.unlink()
        os.mkfifo(storage)
        opened, target = bag_copy, storage
    code = ("from lidarcal_ros.io.bag.reader import BagReader\n"
            "from lidarcal_ros.errors import BagError\n"
            f"try:\n    BagReader({str(opened)!r}).__enter__()\n"
            "except BagError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert out.strip() == f"{target}: not a regular file (a FIFO, socket or device); refused"
