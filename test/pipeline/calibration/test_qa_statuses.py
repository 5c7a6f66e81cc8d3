"""What the crew reads: the estimate and strip-pair statuses, and their one-line summary."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad
from lidarcal_ros.io.cloud.messages import (
    ERROR,
    OK,
    WARN,
    StatusSpec,
    estimate_status,
    qa_summary,
)


def _solution() -> SimpleNamespace:
    delta = np.array([0.0506, -0.0404, 0.0, arcsec_to_rad(-28.97), arcsec_to_rad(-90.98),
                      arcsec_to_rad(45.58), 0.1179, 1.0e-4])
    sigma = np.array([0.0004, 0.0014, math.nan, arcsec_to_rad(0.34), arcsec_to_rad(0.04),
                      math.nan, 0.0031, 1.6e-6])
    states = {name: SimpleNamespace(state=ParameterState.ESTIMATED, reason="")
              for name in PARAMETER_NAMES}
    states["dZ"] = SimpleNamespace(state=ParameterState.FIXED, reason="")
    states["dkappa"] = SimpleNamespace(state=ParameterState.NOT_ESTIMABLE,
                                        reason="lines along one track")
    return SimpleNamespace(delta=delta, sigma=sigma, status=states)


def test_the_estimate_reads_in_arcsec_and_cm() -> None:
    status = estimate_status(_solution())
    assert status.level == OK and status.name == "lidarcal: estimate"
    assert status.message == (
        "dX +5.06 +- 0.04 cm, dY -4.04 +- 0.14 cm, domega -28.97 +- 0.34 arcsec, "
        "dphi -90.98 +- 0.04 arcsec, dr +11.79 +- 0.31 cm, dS +1.00e-04 +- 1.6e-06")
    assert status.values["dZ"] == "fixed at +0.00 cm"
    assert status.values["dkappa"] == "not estimable: lines along one track"
    assert list(status.values) == list(PARAMETER_NAMES)
    # where the headings came from, when the result says
    with_heading = estimate_status(_solution(), {1: HeadingSource.ATTITUDE,
                                                 2: HeadingSource.ATTITUDE})
    assert with_heading.values["heading"] == (
        "heading from the poses' orientation (IMU) for every strip")
    by_track = estimate_status(_solution(), {1: HeadingSource.TRACK})
    assert by_track.values["heading"] == "from the track"


def _pair(a: int, b: int, level: int, rms: float) -> StatusSpec:
    return StatusSpec(level, f"lidarcal: strips {a}&{b}", f"RMS {rms * 100:.1f} cm: x",
                      {"rms_after": f"{rms:.6g}"})


def test_the_summary_names_the_worst_pair() -> None:
    estimate = estimate_status(_solution())
    pairs = [_pair(1, 2, OK, 0.023), _pair(5, 6, WARN, 0.09), _pair(3, 4, OK, 0.07)]
    line = qa_summary([estimate, *pairs, StatusSpec(WARN, "lidarcal: observability", "")])
    assert line == f"{estimate.message}; strips 5&6: RMS 9.0 cm: x (worst of 3 pairs)"
    # the level first, then the RMS; an unknown RMS is the worst of its level
    pairs += [_pair(2, 3, ERROR, 0.05), _pair(4, 5, ERROR, math.nan)]
    assert qa_summary([estimate, *pairs]).endswith("strips 4&5: RMS nan cm: x (worst of 5 pairs)")
    assert qa_summary([estimate]) == estimate.message
    assert qa_summary([]) == "no estimate"
