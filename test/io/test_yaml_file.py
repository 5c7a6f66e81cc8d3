"""io/yaml_file.py: YAML read with one-line errors naming the file and what is wrong."""

from __future__ import annotations

from pathlib import Path

import pytest

from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.yaml_file import read_yaml


def test_a_document_is_read_back(tmp_path: Path) -> None:
    path = tmp_path / "calibration.yaml"
    path.write_text("calibration:\n  biases: {dX: 0.01, domega: -4.4e-4}\n  strips: [1, 2]\n")
    assert read_yaml(path) == {"calibration": {"biases": {"dX": 0.01, "domega": -4.4e-4},
                                               "strips": [1, 2]}}


@pytest.mark.parametrize(("content", "expected"), [
    (b"a: 1\nb: [1, 2\nc: 3\n", "is not valid YAML at line"),
    (b"\xff\xfe\x00binary", "is not text"),
])
def test_bad_content_is_one_line_naming_the_file(tmp_path: Path, content: bytes,
                                                  expected: str) -> None:
    path = tmp_path / "flight.yaml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as raised:
        read_yaml(path, what="flight configuration")
    message = str(raised.value)
    assert "\n" not in message and message.startswith(str(path)) and expected in message
    assert "flight configuration" in message


def test_a_missing_file_says_it_cannot_be_read(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot read plan \(No such file or directory\)"):
        read_yaml(tmp_path / "absent.yaml", what="plan")


def test_python_tags_are_refused_not_run(tmp_path: Path) -> None:
    path = tmp_path / "hostile.yaml"
    path.write_text("x: !!python/object/apply:os.system ['echo owned']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        read_yaml(path)
