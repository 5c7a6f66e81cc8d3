"""ROS 2 parameters files (``/**: ros__parameters:``) as flight configurations."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.yaml_file import read_yaml


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mapping to dotted names (``{'a': {'b': 1}}`` -> ``{'a.b': 1}``)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def read_parameters_file(path: str | Path, *, node_names: tuple[str, ...] = ()) -> dict[str, Any]:
    """Read the ``ros__parameters`` of a parameters file as dotted names.

    Parameters from the ``/**`` wildcard section come first, then those of any section named in
    ``node_names`` (more specific wins), as ``ros2 run --params-file`` applies them.

    Raises
    ------
    ConfigError
        Unreadable file, not YAML, or no ``ros__parameters`` section.
    """
    path = Path(path)
    doc = read_yaml(path, what="parameters file")
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{path}: expected '/**: ros__parameters:' at the top")
    flat: dict[str, Any] = {}
    found = False
    for section in ("/**", *node_names, *(f"/{n}" for n in node_names)):
        body = doc.get(section)
        if isinstance(body, Mapping) and isinstance(body.get("ros__parameters"), Mapping):
            flat.update(flatten(body["ros__parameters"]))
            found = True
    if not found:
        raise ConfigError(f"{path}: no 'ros__parameters' section under '/**'")
    return flat


def load_flight_config(path: str | Path | None) -> FlightConfig:
    """The flight configuration from a parameters file (defaults if ``path`` is None)."""
    if path is None:
        return FlightConfig()
    flat = read_parameters_file(path, node_names=(
        "lidarcal_calibrator", "lidarcal_corrector", "lidarcal_flight_config"))
    control = flat.get("calibration.control_points_file")
    if isinstance(control, str) and control and not Path(control).is_absolute():
        # Relative paths in a parameters file are relative to the file, not to the caller.
        flat["calibration.control_points_file"] = str(Path(path).parent / control)
    return FlightConfig.from_mapping(flat, source=str(path), check=False)
