"""Timing of ``lidarcal replay``: which bag message goes out when, without ROS.

Bag times in nanoseconds, wall times in seconds; the rules (window, loop, latched topics,
``/clock``): docs/nodes.md, "The helper nodes of the CLI".
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from lidarcal_ros.errors import ConfigError

Message = tuple[str, str, int, bytes]
_NS = 1_000_000_000


@dataclass(frozen=True)
class ReplayWindow:
    """Bag-time window replayed, nanoseconds (``end_ns`` inclusive)."""

    start_ns: int
    end_ns: int

    @property
    def duration_s(self) -> float:
        """The window's length, s (0 when empty)."""
        return max(self.end_ns - self.start_ns, 0) / _NS


def replay_window(
    bag_start_ns: int, bag_end_ns: int, *, start_s: float = 0.0, duration_s: float | None = None
) -> ReplayWindow:
    """The window of ``--start`` / ``--duration`` (seconds from the bag's first message).

    Raises
    ------
    ConfigError
        Negative or non-finite start or duration, or a start beyond the bag's end.
    """
    if not (math.isfinite(start_s) and start_s >= 0):
        raise ConfigError(f"--start must be a non-negative number of seconds, got {start_s}")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError(f"--duration must be a positive number of seconds, got {duration_s}")
    lo = bag_start_ns + round(start_s * _NS)
    if lo > bag_end_ns:
        length = (bag_end_ns - bag_start_ns) / _NS
        raise ConfigError(f"--start {start_s} s is beyond the end of the bag ({length:.3f} s long)")
    hi = bag_end_ns if duration_s is None else min(bag_end_ns, lo + round(duration_s * _NS))
    return ReplayWindow(lo, hi)


@dataclass
class ReplayStats:
    """What a replay did."""

    messages: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    passes: int = 0
    clock_messages: int = 0
    max_lateness_s: float = 0.0  # largest wall delay of a message behind its schedule
    wall_s: float = 0.0
    interrupted: bool = False

    def count(self, topic: str) -> None:
        """Count one message published on ``topic``."""
        self.messages += 1
        self.per_topic[topic] = self.per_topic.get(topic, 0) + 1


class Pacer:
    """Waits until scheduled wall times, publishing the clock meanwhile.

    ``now`` is a monotonic clock in seconds; ``wait(seconds)`` sleeps and returns True when the
    replay is to stop (e.g. ``threading.Event.wait``).
    """

    def __init__(
        self,
        rate: float,
        *,
        clock: Callable[[int], None] | None = None,
        clock_hz: float = 40.0,
        now: Callable[[], float] = time.monotonic,
        wait: Callable[[float], bool] | None = None,
    ) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"--rate must be a positive number, got {rate}")
        if clock is not None and not (math.isfinite(clock_hz) and clock_hz > 0):
            raise ConfigError(f"--clock-hz must be positive, got {clock_hz}")
        self.rate = rate
        self.clock = clock
        self.clock_period = 1.0 / clock_hz
        self.now = now
        self._stop = threading.Event()
        self.wait = wait if wait is not None else self._stop.wait
        self.wall0 = 0.0
        self.bag0_ns = 0
        self._next_clock = 0.0
        self.clock_messages = 0

    def start(self, bag0_ns: int) -> None:
        """A new pass: bag time ``bag0_ns`` is now."""
        self.wall0 = self.now()
        self.bag0_ns = bag0_ns
        self._next_clock = self.wall0
        self._tick(self.wall0)

    def bag_time_ns(self, wall: float) -> int:
        """The bag time (ns) due at wall time ``wall`` (s, of ``now``) in this pass."""
        return self.bag0_ns + round((wall - self.wall0) * self.rate * _NS)

    def wall_time(self, bag_ns: int) -> float:
        """The wall time (s, of ``now``) at which bag time ``bag_ns`` (ns) is due in this pass."""
        return self.wall0 + (bag_ns - self.bag0_ns) / _NS / self.rate

    def _tick(self, wall: float) -> None:
        if self.clock is not None and wall >= self._next_clock:
            self.clock(self.bag_time_ns(wall))
            self.clock_messages += 1
            self._next_clock = max(self._next_clock + self.clock_period, wall)

    def until(self, bag_ns: int) -> tuple[bool, float]:
        """Wait until bag time ``bag_ns`` is due; returns (stop requested, lateness in s)."""
        target = self.wall_time(bag_ns)
        while True:
            wall = self.now()
            self._tick(wall)
            if wall >= target:
                return False, wall - target
            step = target - wall
            if self.clock is not None:
                step = min(step, max(self._next_clock - wall, 0.0))
            if self.wait(step):
                return True, 0.0

    def stop(self) -> None:
        """Ask for a stop: a wait of :meth:`until` on the pacer's own event (the default
        ``wait``) ends at once."""
        self._stop.set()


def replay(
    messages: Callable[[], Iterable[Message]],
    publish: Callable[[str, str, int, bytes], None],
    window: ReplayWindow,
    pacer: Pacer,
    *,
    latched: Iterable[str] = (),
    loop: bool = False,
    max_passes: int | None = None,
    stop: Callable[[], bool] = lambda: False,
) -> ReplayStats:
    """Publish a bag's messages with their original timing scaled by ``pacer.rate``.

    Parameters
    ----------
    messages : callable
        Returns a fresh iterator of ``(topic, msgtype, log_time_ns, raw)`` in log-time order
        (``BagReader.messages``), called once per pass.
    publish : callable(topic, msgtype, log_time_ns, raw)
    window : ReplayWindow
    pacer : Pacer
    latched : topics offered transient-local; their last message before the window is
        published when a pass starts.
    loop : bool
        Start again at the end (until ``stop()`` or ``max_passes``).
    stop : callable
        Polled between messages; True ends the replay.

    Returns
    -------
    ReplayStats
    """
    stats = ReplayStats()
    latched_set = set(latched)
    started = pacer.now()
    try:
        while True:
            stats.passes += 1
            pacer.start(window.start_ns)
            held: dict[str, Message] = {}
            began = False
            for msg in messages():
                topic, _msgtype, ns, _raw = msg
                if ns < window.start_ns:
                    if topic in latched_set:
                        held[topic] = msg
                    continue
                if ns > window.end_ns:
                    break
                if not began:
                    began = True
                    for early in held.values():
                        publish(*early)
                        stats.count(early[0])
                    held.clear()
                interrupted, late = pacer.until(ns)
                if interrupted or stop():
                    stats.interrupted = True
                    return stats
                stats.max_lateness_s = max(stats.max_lateness_s, late)
                publish(*msg)
                stats.count(topic)
            for early in held.values():  # a window holding nothing but latched history
                publish(*early)
                stats.count(early[0])
            if not loop or stop() or (max_passes is not None and stats.passes >= max_passes):
                # Let the clock reach the window end before finishing.
                interrupted, _ = pacer.until(window.end_ns)
                stats.interrupted = interrupted
                return stats
    finally:
        stats.clock_messages = pacer.clock_messages
        stats.wall_s = pacer.now() - started


@dataclass
class SubscriberWait:
    """How :func:`wait_for_subscribers` ended: the topics still short of subscribers, the
    last subscriber counts, whether a ``lidarcal run`` seen was still starting its suite, the
    seconds waited and whether a stop was requested."""

    missing: list[str]
    counts: dict[str, int]
    suite_starting: bool
    waited_s: float
    stopped: bool = False

    @property
    def ready(self) -> bool:
        """Whether the replay may start: every topic has its subscribers, no suite is still
        starting, no stop was asked for."""
        return not self.missing and not self.suite_starting and not self.stopped


def wait_for_subscribers(
    counts: Callable[[], dict[str, int]],
    *,
    timeout_s: float,
    minimum: int = 1,
    settle_s: float = 1.0,
    suite_starting: Callable[[], bool] = lambda: False,
    now: Callable[[], float] = time.monotonic,
    wait: Callable[[float], bool] | None = None,
    poll_s: float = 0.05,
) -> SubscriberWait:
    """Wait until every topic of ``counts()`` (subscribers per topic) has ``minimum``
    subscribers, the counts have not changed for ``settle_s`` seconds and no ``lidarcal run``
    is still starting its nodes (``suite_starting()``), or until ``timeout_s`` seconds.

    The settle time is there because the nodes of a suite are matched one by one: the first
    match alone would start the replay while the others' subscriptions are still being
    matched, and their first messages would be lost. ``suite_starting`` covers a node whose
    process has not even created it yet (a calibrator importing for seconds on a busy
    machine), which no subscriber count can show. ``wait(seconds)`` sleeps and returns True
    when the wait is to stop (e.g. ``threading.Event.wait``).
    """
    if not (math.isfinite(timeout_s) and timeout_s >= 0):
        raise ConfigError(f"--wait-for-subscribers must be a non-negative number of seconds, "
                          f"got {timeout_s}")
    if minimum < 1:
        raise ConfigError(f"--min-subscribers must be at least 1, got {minimum}")
    sleep = wait if wait is not None else threading.Event().wait
    started = now()
    seen: dict[str, int] | None = None
    steady_since = started
    while True:
        t = now()
        current = counts()
        if current != seen:
            seen, steady_since = current, t
        missing = sorted(topic for topic, n in current.items() if n < minimum)
        starting = suite_starting()
        settled = not missing and not starting and t - steady_since >= settle_s
        if settled or t - started >= timeout_s:
            return SubscriberWait(missing, dict(current), starting, t - started)
        if sleep(poll_s):
            return SubscriberWait(missing, dict(current), starting, now() - started,
                                  stopped=True)


def iter_window(messages: Iterable[Message], window: ReplayWindow) -> Iterator[Message]:
    """The messages inside ``window`` (no timing); for tests and dry runs."""
    for msg in messages:
        if msg[2] < window.start_ns:
            continue
        if msg[2] > window.end_ns:
            break
        yield msg


__all__ = [
    "Message", "Pacer", "ReplayStats", "ReplayWindow", "SubscriberWait", "iter_window", "replay",
    "replay_window", "wait_for_subscribers",
]
