"""The import-layer contract of ARCHITECTURE.md: imports only run downward, rclpy only in nodes."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers_paths import REPO

PACKAGE = REPO / "lidarcal_ros"

#: Each layer's rank: a module may import its own layer and those of a lower rank.
LAYER_RANK = {
    "errors": 0, "core": 1, "io": 2, "ros": 2, "pipeline": 3, "nodes": 4, "cli": 5,
    "__main__": 6,
}
#: The only modules that may import rclpy (the nodes, and the CLI where it starts them).
RCLPY_ALLOWED = ("nodes", "cli.ros_commands")
#: Most modules one folder of the package may hold (sub-packages by concern).
MAX_MODULES_PER_FOLDER = 15


def layer_of(module: str) -> str:
    """The layer of a dotted module name under lidarcal_ros (``lidarcal_ros.io.bag.reader``: io)."""
    return module.split(".")[1]


def imported_modules(source: str, module: str) -> Iterator[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, at any depth of the file."""
    package = module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            yield node.lineno, target


def violations(source: str, module: str) -> list[str]:
    """Each import of ``module`` (its ``source``) that breaks the layer contract, as a sentence."""
    found = []
    own = layer_of(module)
    for line, target in imported_modules(source, module):
        if target.startswith("lidarcal_ros."):
            other = layer_of(target)
            if LAYER_RANK.get(other, 0) > LAYER_RANK[own]:
                found.append(f"{module}:{line} imports {target} (upward: {own} -> {other})")
        elif target.split(".")[0] == "rclpy":
            inner = module.removeprefix("lidarcal_ros.")
            if not inner.startswith(RCLPY_ALLOWED):
                found.append(f"{module}:{line} imports rclpy outside nodes/")
    return found


def package_modules() -> Iterator[tuple[str, Path]]:
    """(dotted name, path) of every module of the package."""
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def test_every_layer_is_ranked() -> None:
    layers = {layer_of(name) for name, _ in package_modules() if name.count(".") >= 1}
    assert layers <= set(LAYER_RANK), layers - set(LAYER_RANK)


def test_no_import_runs_upward() -> None:
    found = [v for name, path in package_modules() if name.count(".") >= 1
             for v in violations(path.read_text(encoding="utf-8"), name)]
    assert not found, "\n".join(found)


@pytest.mark.parametrize(("module", "source", "expected"), [
    ("lidarcal_ros.core.qa.accuracy", "from lidarcal_ros.io.bag import reader\n", "core -> io"),
    ("lidarcal_ros.io.bag.reader",
     "def f():\n    from lidarcal_ros.pipeline.calibration import procedure\n", "io -> pipeline"),
    ("lidarcal_ros.pipeline.report.build", "import lidarcal_ros.nodes.topics\n",
     "pipeline -> nodes"),
    ("lidarcal_ros.core.calibration.tin", "from ...io import las\n", "core -> io"),
    ("lidarcal_ros.pipeline.correction.apply", "import rclpy\n", "rclpy outside nodes"),
])
def test_the_check_finds_an_upward_import(module: str, source: str, expected: str) -> None:
    found = violations(source, module)
    assert len(found) == 1 and expected in found[0], found


def test_downward_and_sideways_imports_pass() -> None:
    source = ("from lidarcal_ros.core.params import PARAMETER_NAMES\n"
              "from lidarcal_ros.io.bag import reader\nfrom . import stream\nimport numpy\n")
    assert violations(source, "lidarcal_ros.pipeline.correction.bag") == []
    assert violations("import rclpy\n", "lidarcal_ros.nodes.corrector") == []


def test_no_folder_holds_more_than_fifteen_modules() -> None:
    crowded = {str(folder.relative_to(REPO)): count
               for folder in [PACKAGE, *PACKAGE.rglob("*/")] if folder.name != "__pycache__"
               if (count := len([p for p in folder.glob("*.py") if p.name != "__init__.py"]))
               > MAX_MODULES_PER_FOLDER}
    assert not crowded, crowded
