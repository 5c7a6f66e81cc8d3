"""ROS 2 parameters files (``/**: ros__parameters:``) as flight configurations."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from lidarcal_ros.core.config import NODE_PARAMETERS, SCHEMA, FlightConfig, undeclared
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.yaml_file import read_yaml

logger = logging.getLogger(__name__)


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


def read_parameters_file(path: str | Path) -> tuple[dict[str, Any], list[str]]:
    """Read the ``ros__parameters`` that reach lidarcal's nodes, as dotted names.

    Parameters from the ``/**`` wildcard section come first, then those of each node's own
    section (``lidarcal_calibrator`` or ``/lidarcal_calibrator``; more specific wins), as
    ``--params-file`` applies them. Sections of other nodes are not read.

    Returns
    -------
    values : dict
        Every parameter read, by dotted name.
    undeclared : list of str
        The keys no lidarcal node declares (in a node's own section: that node does not),
        e.g. misspelt ones, which the nodes would ignore; those of a node's section named
        ``name (lidarcal_calibrator)``.

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
    unknown: list[str] = []
    found = False
    sections: list[tuple[str, str | None]] = [("/**", None)]
    sections += [(s, node) for node in NODE_PARAMETERS for s in (node, f"/{node}")]
    for section, node in sections:
        body = doc.get(section)
        if isinstance(body, Mapping) and isinstance(body.get("ros__parameters"), Mapping):
            values = flatten(body["ros__parameters"])
            flat.update(values)
            unknown += [n if node is None else f"{n} ({node})"
                        for n in undeclared(values, node)]
            found = True
    if not found:
        raise ConfigError(f"{path}: no 'ros__parameters' section under '/**'")
    return flat, unknown


def warn_undeclared(source: str, names: Iterable[str]) -> None:
    """Name, in one warning line, parameters that no lidarcal node declares (a misspelt key
    would otherwise leave its parameter at the default without a word)."""
    names = list(names)
    if names:
        logger.warning("%s: %d parameter(s) ignored, not declared by the lidarcal node(s) "
                       "given them (misspelt?): %s", source, len(names), ", ".join(names))


def load_flight_config(path: str | Path | None) -> FlightConfig:
    """The flight configuration from a parameters file (defaults if ``path`` is None).

    The nodes' own parameters in the file are passed over (they serve ``--params-file``);
    keys no node declares are named in one warning line (:func:`warn_undeclared`).

    Raises
    ------
    ConfigError
        The file cannot be read, or a flight-configuration value is refused (one line naming
        the file and the parameter).
    """
    if path is None:
        return FlightConfig()
    flat, unknown = read_parameters_file(path)
    warn_undeclared(str(path), unknown)
    flight = {name: value for name, value in flat.items() if name in SCHEMA}
    control = flight.get("calibration.control_points_file")
    if isinstance(control, str) and control and not Path(control).is_absolute():
        # Relative paths in a parameters file are relative to the file, not to the caller.
        flight["calibration.control_points_file"] = str(Path(path).parent / control)
    return FlightConfig.from_mapping(flight, source=str(path), check=False)


__all__ = ["flatten", "load_flight_config", "read_parameters_file", "warn_undeclared"]
