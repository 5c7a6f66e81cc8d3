"""The shared unit formatters (``core.units``)."""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.units import (
    finite_or_none,
    format_cm,
    format_number,
    format_percent,
    status_value,
)


def test_values_for_yaml_and_json() -> None:
    assert finite_or_none(math.nan) is None and finite_or_none(None) is None
    assert finite_or_none(math.inf) is None
    assert finite_or_none(np.float64(0.25)) == 0.25
    assert type(finite_or_none(np.float64(0.25))) is float
    assert finite_or_none(np.int64(7)) == 7 and type(finite_or_none(np.int64(7))) is int


def test_lengths_numbers_and_shares_as_text() -> None:
    assert format_cm(0.0162) == "1.6" and format_cm(0.0162, sign=True) == "+1.6"
    assert format_cm(0.0162, unit="cm") == "1.6 cm"
    assert format_cm(math.nan) == "n/a" and format_cm(math.nan, missing="-") == "-"
    assert format_number(0.123456) == "0.1235" and format_number(math.inf) == "n/a"
    assert format_number(3) == "3"
    assert status_value(0.1234567) == "0.123457" and status_value(math.nan) == "nan"
    assert format_percent(0.4449) == "44%" and format_percent(math.nan) == "n/a"
