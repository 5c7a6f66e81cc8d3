"""The eight system parameters of docs/method.md section 1: names, order, units.

A bias is ``nominal value used by the system - true value``. Files and messages carry SI units
(metres, radians, dimensionless); reports show angles in arcseconds.
"""

from __future__ import annotations

import math

import numpy as np

#: Parameter keys in the one order used by code, files, messages and reports.
PARAMETER_NAMES: tuple[str, ...] = ("dX", "dY", "dZ", "domega", "dphi", "dkappa", "dr", "dS")
N_PARAMETERS = len(PARAMETER_NAMES)
PARAMETER_INDEX: dict[str, int] = {name: i for i, name in enumerate(PARAMETER_NAMES)}

#: SI unit of each parameter.
SI_UNITS: dict[str, str] = {
    "dX": "m", "dY": "m", "dZ": "m",
    "domega": "rad", "dphi": "rad", "dkappa": "rad",
    "dr": "m", "dS": "1",
}

#: Lever-arm, boresight, range and scale groups (for reports and advice).
LEVER_ARM = ("dX", "dY", "dZ")
BORESIGHT = ("domega", "dphi", "dkappa")
ANGLES = frozenset(BORESIGHT)

ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


def rad_to_arcsec(value: float) -> float:
    """Radians to arcseconds."""
    return value * ARCSEC_PER_RAD


def arcsec_to_rad(value: float) -> float:
    """Arcseconds to radians."""
    return value / ARCSEC_PER_RAD


def display_value(name: str, value: float) -> tuple[float, str]:
    """A parameter value in the unit people read: arcsec for angles, cm for lengths.

    Returns ``(value_in_display_unit, unit_label)``.
    """
    if name in ANGLES:
        return rad_to_arcsec(value), "arcsec"
    if SI_UNITS[name] == "m":
        return value * 100.0, "cm"
    return value, ""


def format_value(name: str, value: float, *, sign: bool = True, width: int = 0) -> str:
    """A parameter value as people read it: ``"-90.98 arcsec"``, ``"+5.06 cm"``, ``"+1.00e-04"``
    (``sign`` False: no plus sign, for standard deviations, dS with one decimal; ``width``:
    least width of the number, for tables)."""
    shown, unit = display_value(name, value)
    if name == "dS":
        return f"{shown:+{width}.2e}" if sign else f"{shown:{width}.1e}"
    return f"{shown:+{width}.2f} {unit}" if sign else f"{shown:{width}.2f} {unit}"


def format_estimate(name: str, value: float, sigma: float) -> str:
    """An estimate with its standard deviation, the unit once: ``"-90.98 +- 0.04 arcsec"``."""
    shown, unit = display_value(name, value)
    spread, _ = display_value(name, sigma)
    if name == "dS":
        return f"{shown:+.2e} +- {spread:.1e}"
    return f"{shown:+.2f} +- {spread:.2f} {unit}"


def parse_parameter_list(text: str) -> tuple[str, ...]:
    """Parse a comma-separated parameter list such as ``"dX,dY,domega"``.

    Raises
    ------
    ValueError
        If a name is not one of :data:`PARAMETER_NAMES`.
    """
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    unknown = [n for n in names if n not in PARAMETER_INDEX]
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(PARAMETER_NAMES)}"
        )
    return tuple(n for n in PARAMETER_NAMES if n in names)


def as_vector(values: dict[str, float]) -> np.ndarray:
    """Dict of parameter values (missing keys = 0) to a vector in :data:`PARAMETER_NAMES` order."""
    return np.array([float(values.get(name, 0.0)) for name in PARAMETER_NAMES])


def as_dict(vector: np.ndarray) -> dict[str, float]:
    """Vector in :data:`PARAMETER_NAMES` order to a dict."""
    return {name: float(v) for name, v in zip(PARAMETER_NAMES, vector)}


__all__ = [
    "ANGLES", "ARCSEC_PER_RAD", "BORESIGHT", "LEVER_ARM", "N_PARAMETERS", "PARAMETER_INDEX",
    "PARAMETER_NAMES", "SI_UNITS", "arcsec_to_rad", "as_dict", "as_vector", "display_value",
    "format_estimate", "format_value", "parse_parameter_list", "rad_to_arcsec",
]
