"""The replay's publishing: a publish refused for back-pressure is waited out, within bounds."""

from __future__ import annotations

import time

import pytest

from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.nodes.player import publish_patiently, topic_depth


class _Refusing:
    """A publish that rcl refuses ``times`` times (a full reliable history), then takes."""

    def __init__(self, times: int) -> None:
        self.left = times
        self.calls = 0

    def __call__(self) -> None:
        self.calls += 1
        if self.left > 0:
            self.left -= 1
            raise LidarcalError("/ins/odometry: publishing failed (cannot publish data)")


def test_a_publish_taken_at_once_did_not_wait() -> None:
    publish = _Refusing(0)
    assert publish_patiently(publish, stall_s=1.0) is False
    assert publish.calls == 1


def test_a_refused_publish_is_tried_again_until_taken() -> None:
    publish = _Refusing(3)
    assert publish_patiently(publish, stall_s=5.0) is True
    assert publish.calls == 4


def test_a_publish_refused_past_the_stall_fails_with_its_reason() -> None:
    publish = _Refusing(10**9)
    started = time.monotonic()
    with pytest.raises(LidarcalError, match="cannot publish data"):
        publish_patiently(publish, stall_s=0.2)
    assert 0.2 <= time.monotonic() - started < 2.0
    assert publish.calls > 2


def test_other_failures_are_not_retried() -> None:
    calls = []

    def broken() -> None:
        calls.append(1)
        raise ValueError("not a refusal")

    with pytest.raises(ValueError):
        publish_patiently(broken, stall_s=5.0)
    assert len(calls) == 1


class _Topic:
    """A bag topic's count, as TopicInfo gives it."""

    def __init__(self, count: int) -> None:
        self.count = count


@pytest.mark.parametrize(("count", "span_s", "rate", "depth"), [
    (100 * 600, 600.0, 10.0, 2000),     # 100 Hz Odometry at 10x: 2 s of it
    (100 * 600, 600.0, 1.0, 200),       # the same in real time
    (10 * 600, 600.0, 1.0, 100),        # 10 Hz clouds: the floor
    (1000 * 600, 600.0, 20.0, 10_000),  # a 1 kHz IMU at 20x: the ceiling
    (1, 0.0, 1.0, 100),                 # one message (no span)
])
def test_a_topics_depth_holds_two_seconds_of_it_at_the_replays_pace(
        count: int, span_s: float, rate: float, depth: int) -> None:
    assert topic_depth(_Topic(count), span_s=span_s, rate=rate) == depth
