"""pipeline/throttled_log.py: a lasting condition said at most once a while, by its kind."""

from __future__ import annotations

import logging

import pytest

from lidarcal_ros.pipeline import throttled_log
from lidarcal_ros.pipeline.throttled_log import ThrottledLog


def test_lines_of_one_kind_are_throttled_others_are_not(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    clock = [100.0]
    monkeypatch.setattr(throttled_log.time, "monotonic", lambda: clock[0])
    log = ThrottledLog(logging.getLogger("lidarcal.test"))
    with caplog.at_level(logging.WARNING, logger="lidarcal.test"):
        log.log(logging.WARNING, 5.0, "malformed cloud skipped: field x missing")
        clock[0] += 1.0
        log.log(logging.WARNING, 5.0, "malformed cloud skipped: field t missing")  # same kind
        log.log(logging.WARNING, 5.0, "backlog over its bound: 3 clouds dropped")
        clock[0] += 4.5
        log.log(logging.WARNING, 5.0, "malformed cloud skipped: again")
    assert [r.getMessage() for r in caplog.records] == [
        "malformed cloud skipped: field x missing",
        "backlog over its bound: 3 clouds dropped",
        "malformed cloud skipped: again",
    ]
