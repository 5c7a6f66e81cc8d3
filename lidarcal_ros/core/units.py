"""The unit formatters every output shares, and the parser of values given with a unit.

Metres shown in centimetres, missing values written as such; the biases' own display rules are
in :mod:`lidarcal_ros.core.params`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any, SupportsFloat

#: Length units of :func:`parse_quantity`: metres per unit.
LENGTH_UNITS: dict[str, float] = {"mm": 0.001, "cm": 0.01, "m": 1.0}
#: Time units of :func:`parse_quantity`: seconds per unit.
TIME_UNITS: dict[str, float] = {"ms": 0.001, "s": 1.0, "min": 60.0, "h": 3600.0}


def finite_or_none(value: SupportsFloat | None) -> float | None:
    """``value`` for YAML and JSON: None (``null``) where it is missing or not finite, a
    whole number as a Python ``int`` (a count stays a count), else a Python ``float``."""
    if value is None:
        return None
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return int(value)
    v = float(value)
    return v if math.isfinite(v) else None


def format_cm(value_m: float, *, sign: bool = False, unit: str = "", missing: str = "n/a"
              ) -> str:
    """A length given in metres, shown in centimetres to a millimetre (``+1.6`` with
    ``sign``; ``unit`` appended after a space, e.g. ``"cm"``); ``missing`` where not
    finite."""
    if not math.isfinite(value_m):
        return missing
    text = f"{value_m * 100:+.1f}" if sign else f"{value_m * 100:.1f}"
    return f"{text} {unit}" if unit else text


def format_number(value: Any, fmt: str = ".4g", *, missing: str = "n/a") -> str:
    """A float in ``fmt``, ``missing`` where not finite; anything else as ``str``."""
    if isinstance(value, float):
        return format(value, fmt) if math.isfinite(value) else missing
    return str(value)


def status_value(value: Any) -> str:
    """A value of a ``diagnostic_msgs/KeyValue``: a float to six significant digits
    (``nan`` where not finite, as a program parsing it back reads it), anything else as
    ``str``."""
    return format_number(value, ".6g", missing="nan")


def format_percent(fraction: float, *, missing: str = "n/a") -> str:
    """A share (0-1) in whole percent, ``missing`` where not finite."""
    return missing if not math.isfinite(fraction) else f"{fraction * 100:.0f}%"


def parse_quantity(text: str, units: Mapping[str, float], *, bare_one: bool = False) -> float:
    """A number with an optional unit suffix (a key of ``units``; the longest that ends the text
    wins, so ``cm`` is not read as ``m``) in SI: the number times the unit's factor, the number
    alone where no unit ends it. ``bare_one``: a unit without a number is 1 of it (``s`` as in
    ``cm/s``).

    Raises
    ------
    ValueError
        What is left once the unit is taken off is not a number.
    """
    raw, factor = text.strip(), 1.0
    for suffix in sorted(units, key=len, reverse=True):
        if raw.endswith(suffix):
            raw, factor = raw[: -len(suffix)].strip(), units[suffix]
            break
    if bare_one and not raw:
        return factor
    return float(raw) * factor


__all__ = ["LENGTH_UNITS", "TIME_UNITS", "finite_or_none", "format_cm", "format_number",
           "format_percent", "parse_quantity", "status_value"]
