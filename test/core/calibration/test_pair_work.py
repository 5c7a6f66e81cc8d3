"""The pair tasks' strips (core/calibration/pair_work.py): a strip held at its home is used by
one task at a time in a process, so a release cannot forget its correction under a task that
reads it; a side is the points asked for, in that order, without TIN or correction."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Calibrator
from lidarcal_ros.core.calibration.pair_work import _alone_with, release_task, sample_side
from lidarcal_ros.core.calibration.pairs import Correction, PreparedStrip
from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec


@pytest.fixture()
def prepared_strip() -> PreparedStrip:
    sim = simulate_mission(SimulationSpec.from_options(density=0.05, line_length_m=150.0,
                                                       seed=5))
    return Calibrator.from_mission(sim.mission, CalibrationSettings()).matcher.strips[0]


def test_a_release_waits_for_the_task_using_the_strip(prepared_strip: PreparedStrip) -> None:
    ps = prepared_strip
    ps.corrected = Correction(b"key", ps.strip.xyz.copy(), None, None)
    with _alone_with(ps):
        releasing = threading.Thread(target=release_task, args=(ps,))
        releasing.start()
        releasing.join(timeout=0.3)
        assert releasing.is_alive() and ps.corrected is not None
    releasing.join(timeout=10)
    assert not releasing.is_alive() and ps.corrected is None


def test_a_side_is_the_points_asked_for_in_order(prepared_strip: PreparedStrip) -> None:
    ps = prepared_strip
    index = np.array([7, 2, 5])
    side = sample_side(ps, index)
    assert np.array_equal(side.strip.xyz, ps.strip.xyz[index])
    assert np.array_equal(side.strip.t, ps.strip.t[index])
    assert side.tin is None and side.corrected is None and side.strip.strip_id == ps.strip_id
