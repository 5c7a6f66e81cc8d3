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


def billion_laughs(levels: int) -> str:
    """A YAML alias bomb: each level's list holds the previous level nine times."""
    lines = ['a0: &a0 ["lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(("text", "expected"), [
    (billion_laughs(12), "stands for more than 10,000,000 nodes once its aliases are expanded "
                         "(an alias bomb)"),
    ("a: " + "[" * 100_000 + "]" * 100_000 + "\n", "nests deeper than 100 levels"),
    ("a:\n" + "".join("  " * i + f"k{i}:\n" for i in range(1, 150)) + "  " * 150 + "v\n",
     "nests deeper than 100 levels"),
])
def test_hostile_documents_are_refused_in_one_line(tmp_path: Path, text: str,
                                                   expected: str) -> None:
    """An alias bomb and absurd nesting (flow and block) are refused as they are read,
    before memory or the stack run out."""
    path = tmp_path / "hostile.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as raised:
        read_yaml(path, what="calibration")
    message = str(raised.value)
    assert message == f"{path}: calibration {expected}; refused"


def test_a_few_aliases_and_the_usual_nesting_are_read(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text("base: &base {x: 1.0, y: 2.0}\n/**:\n  ros__parameters:\n"
                    "    a: *base\n    b: *base\n")
    doc = read_yaml(path)
    assert doc["/**"]["ros__parameters"] == {"a": {"x": 1.0, "y": 2.0},
                                             "b": {"x": 1.0, "y": 2.0}}


def test_a_file_beyond_the_size_bound_is_refused(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from lidarcal_ros.io import yaml_file

    monkeypatch.setattr(yaml_file, "MAX_YAML_BYTES", 1024)
    path = tmp_path / "big.yaml"
    path.write_text("x: 1\n" * 1000)
    with pytest.raises(ConfigError, match="is larger than"):
        read_yaml(path)
