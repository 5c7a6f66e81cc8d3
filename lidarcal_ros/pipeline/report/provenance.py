"""The provenance of ``lidarcal report``: the inputs with size and SHA-256, the configuration."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lidarcal_ros.core.calibration.calibrate import Progress
from lidarcal_ros.core.config import SCHEMA, FlightConfig
from lidarcal_ros.io.report.content import InputFile
from lidarcal_ros.io.report.digest import digest
from lidarcal_ros.io.url_cache import local_source, source_of

__all__ = ["configuration_table", "describe_inputs"]


def configuration_table(config: FlightConfig) -> list[tuple[str, str, bool]]:
    """Every parameter of ``config``: name, value, whether it differs from the default."""
    return [(name, _parameter_text(config[name]), config[name] != spec.default)
            for name, spec in SCHEMA.items()]


def _parameter_text(value: Any) -> str:
    return ", ".join(value) if isinstance(value, list) else str(value)


def describe_inputs(files: Sequence[tuple[str, str | Path | None]], *,
                    progress: Progress | None = None) -> list[InputFile]:
    """Size and SHA-256 of each input (role, path); None paths are left out."""
    present = [(role, source_of(path)) for role, path in files if path is not None]
    out = []
    for k, (role, path) in enumerate(present):
        if progress is not None:
            progress(f"hashing {role}", k / max(len(present), 1))
        size, sha = digest(local_source(path, what=role))  # (a URL: its copy here)
        out.append(InputFile(role, str(path), size, sha))
    return out

