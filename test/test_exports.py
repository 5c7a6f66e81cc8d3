"""Each layer package exports exactly its modules' public names, without importing them."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import lidarcal_ros

PACKAGE_DIR = Path(lidarcal_ros.__file__).parent
LAYERS = ["core", "io", "pipeline", "cli", "nodes", "ros"]


@pytest.mark.parametrize("layer", LAYERS)
def test_layer_exports_every_public_name_of_its_modules(layer: str) -> None:
    package = importlib.import_module(f"lidarcal_ros.{layer}")
    expected: dict[str, str] = {}
    for path in sorted((PACKAGE_DIR / layer).glob("*.py")):
        if path.name == "__init__.py":
            continue
        module = importlib.import_module(f"lidarcal_ros.{layer}.{path.stem}")
        for name in module.__all__:
            if (PACKAGE_DIR / layer / f"{name}.py").exists():
                # A function named as its module (core.calibrate.calibrate): once the
                # module is imported the package attribute is the module, as Python sets it.
                continue
            assert name not in expected, f"{name} in both {expected[name]} and {path.stem}"
            expected[name] = path.stem
    assert sorted(package.__all__) == sorted(expected), "run scripts/update_exports.py"
    for name, module_name in expected.items():
        defined = getattr(importlib.import_module(f"lidarcal_ros.{layer}.{module_name}"), name)
        assert getattr(package, name) is defined, name
    assert set(package.__all__) <= set(dir(package)) and "__name__" in dir(package)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        package.not_a_name  # noqa: B018 (the lookup is the test)


def test_importing_a_layer_loads_none_of_its_heavy_modules() -> None:
    # The command line's start must not pay for numba, matplotlib or rclpy because a layer
    # package was imported for one small module.
    code = ("import sys, lidarcal_ros.core, lidarcal_ros.io, lidarcal_ros.pipeline, "
            "lidarcal_ros.ros; from lidarcal_ros.core import format_cm; "
            "print(' '.join(m for m in ('numba', 'matplotlib', 'rclpy', 'laspy') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": str(PACKAGE_DIR.parent)})
    assert out.stdout.strip() == ""
