"""docs/ against the code: the parameter tables of docs/nodes.md against the schema, and every
citation of a method section against the headings of docs/method.md."""

from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
from dataclasses import replace
from pathlib import Path
from types import ModuleType

import pytest

from lidarcal_ros.cli.exit_status import EXIT_STATUSES
from lidarcal_ros.core import config, flags

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_parameters",
                                                  ROOT / "scripts" / "docs_parameters.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_parameter_tables_match_the_schema() -> None:
    script = _script()
    text = (DOCS / "nodes.md").read_text()
    assert script.replaced(text) == text, (
        "docs/nodes.md's parameter tables differ from lidarcal_ros/core/config.py: run "
        "`.venv/bin/python scripts/docs_parameters.py --write`")


def test_every_parameter_has_a_row() -> None:
    """Each name of the schema and of each node's own parameters, with its default, in a row
    of docs/nodes.md (independently of the script's formatting code)."""
    rows = {m.group(1): m.group(2) for m in re.finditer(
        r"^\| `([^`]+)` \| \w+ \| `([^`]*)` \|", (DOCS / "nodes.md").read_text(), re.M)}
    for specs in (config.SCHEMA, *config.NODE_PARAMETERS.values()):
        for name, spec in specs.items():
            assert name in rows, f"{name} has no row in docs/nodes.md"
            if spec.kind == "str" and spec.default:
                assert rows[name] == spec.default, name


def test_a_changed_default_is_caught(monkeypatch: pytest.MonkeyPatch) -> None:
    """The check above fails when the schema changes and docs/nodes.md does not."""
    script = _script()
    text = (DOCS / "nodes.md").read_text()
    changed = dict(script.SCHEMA)
    changed["calibration.robust_k"] = replace(changed["calibration.robust_k"], default=2.5)
    monkeypatch.setattr(script, "SCHEMA", changed)
    assert script.replaced(text) != text
    monkeypatch.setattr(script, "SCHEMA", {**changed, "matching.new_rule": config.ParameterSpec(
        1.0, "float", "A parameter the docs do not know")})
    assert "`matching.new_rule`" in script.tables()


def test_the_script_refuses_a_file_without_markers() -> None:
    with pytest.raises(ValueError, match="markers"):
        _script().replaced("# nodes\n\nno tables here\n")


def _method_sections() -> set[int]:
    return {int(m.group(1)) for m in re.finditer(r"^## (\d+)\. ",
                                                 (DOCS / "method.md").read_text(), re.M)}


def test_method_has_the_twelve_sections_the_code_cites() -> None:
    assert _method_sections() == set(range(1, 13))


def test_every_cited_method_section_exists() -> None:
    """``docs/method.md section N`` / ``sections N-M`` anywhere in the tracked files names a
    heading of docs/method.md."""
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    sections = _method_sections()
    cited = re.compile(r"method\.md,? (?:sections?|§) ?(\d+)(?:\s*(?:-|and|,)\s*(\d+))?",
                       re.I)
    seen = 0
    for name in files:
        path = ROOT / name
        if path.suffix not in (".py", ".md", ".yaml", ".txt") or not path.is_file():
            continue
        for m in cited.finditer(" ".join(path.read_text(errors="replace").split())):
            for group in m.groups():
                if group is not None:
                    seen += 1
                    assert int(group) in sections, f"{name}: {m.group(0)!r}"
    assert seen > 20  # (the pattern finds the citations at all)


def _table_rows(text: str) -> dict[str, str]:
    """First cell -> the whole row, of every table row in ``text``."""
    return {m.group(1).strip("` "): m.group(0) for m in re.finditer(r"^\| ([^|]+) \|.*$",
                                                                     text, re.M)}


def test_interface_names_every_correction_flag() -> None:
    rows = _table_rows((DOCS / "interface.md").read_text())
    bits = {name: value for name, value in vars(flags).items() if name.startswith("FLAG_")}
    assert len(bits) >= 6
    for name, value in bits.items():
        assert str(value) in rows, f"{name} = {value} has no row in docs/interface.md"


def test_interface_names_every_exit_status() -> None:
    rows = _table_rows((DOCS / "interface.md").read_text())
    for status in EXIT_STATUSES:
        assert str(status) in rows, f"exit status {status} has no row in docs/interface.md"


def _calibration_file_keys() -> set[str]:
    """The top-level keys calibration_document writes, read from its source."""
    tree = ast.parse((ROOT / "lidarcal_ros" / "io" / "calibration_file.py").read_text())
    function = next(node for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)
                    and node.name == "calibration_document")
    keys: set[str] = set()
    for node in ast.walk(function):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and \
                node.target.id == "doc" and isinstance(node.value, ast.Dict):
            keys.update(str(k.value) for k in node.value.keys if isinstance(k, ast.Constant))
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Subscript) and \
                isinstance(node.targets[0].value, ast.Name) and \
                node.targets[0].value.id == "doc" and \
                isinstance(node.targets[0].slice, ast.Constant):
            keys.add(str(node.targets[0].slice.value))
    return keys


def test_interface_documents_every_key_of_the_calibration_file() -> None:
    keys = _calibration_file_keys()
    assert {"biases", "trajectory", "partial_strips", "convergence"} <= keys
    text = (DOCS / "interface.md").read_text()
    table = "\n".join(line for line in text.splitlines() if line.startswith("| `"))
    for key in keys:
        assert f"`{key}`" in table or f"`{key}." in table, (
            f"calibration file key {key!r} is not in docs/interface.md's table")


def test_no_citation_of_a_document_outside_the_repository() -> None:
    """The method and contract pages of the project's shared folder are not part of a clone:
    the package cites docs/ (data read from there, the test vectors and LAS samples, may
    stay: docs/method.md, "Test vectors")."""
    out = subprocess.run(["git", "grep", "-n", "-E", r"shared/(method|interface)\.md"],
                         cwd=ROOT, capture_output=True, text=True).stdout
    assert not out, out
