"""Reading YAML files with one-line errors (parameters, calibration, truth, flight plans)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lidarcal_ros.errors import ConfigError


def read_yaml(path: str | Path, *, what: str = "file") -> Any:
    """Parse a YAML file.

    Raises
    ------
    ConfigError
        ``"<path>: cannot read <what> (<reason>)"`` or ``"<path>: <what> is not valid YAML at
        line N"``.
    """
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: {what} is not text") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}: {what} is not valid YAML{where}") from None


__all__ = ["read_yaml"]
