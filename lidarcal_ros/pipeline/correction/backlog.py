"""The clouds a live corrector holds before the correction: waiting, ready, or dropped.

The rules: docs/correction.md, "The live corrector".
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Protocol

__all__ = ["MAX_PUSH_POINTS", "TRAJECTORY_MARGIN_S", "Region", "WaitingCloud", "WaitingClouds",
           "take_ready"]

#: A cloud waits for a trajectory sample this far past its last point time, s.
TRAJECTORY_MARGIN_S = 0.02
#: Most points handed to the correction at once when a backlog has built up: larger batches
#: only cost cache and memory, and the corrector would fall further behind.
MAX_PUSH_POINTS = 400_000


class Region(Protocol):
    """Where a cloud was received in place (shared memory), given back if it is dropped."""

    def release(self) -> None:
        """Give the memory back."""


@dataclass
class WaitingCloud:
    """A cloud received and not yet reported back.

    Attributes
    ----------
    raw : bytes or memoryview
        Its CDR bytes (emptied once handed to the correction, which then owns them).
    received : float
        When it arrived, s (:func:`time.monotonic`).
    size : int
        Bytes received.
    parsed : bool
        Its header and time span have been read (:attr:`n_points`, :attr:`t_max`).
    n_points : int
    t_max : float
        Its last point time, s (-inf: none finite).
    region : Region or None
        The shared memory ``raw`` lies in, when it was received there: given back
        (:meth:`release`) when the cloud is dropped or skipped, handed on with it otherwise.
    """

    raw: bytes | memoryview
    received: float
    size: int = 0
    parsed: bool = False
    n_points: int = 0
    t_max: float = -math.inf
    region: Region | None = None

    def release(self) -> None:
        """The cloud will not be corrected: its shared memory, if any, is free again."""
        region = self.region
        self.raw, self.region = b"", None
        if region is not None:
            region.release()


class WaitingClouds:
    """The clouds received and not yet handed to the correction, oldest first."""

    def __init__(self) -> None:
        self._clouds: deque[WaitingCloud] = deque()
        #: Bytes of the clouds waiting.
        self.bytes = 0

    def __len__(self) -> int:
        return len(self._clouds)

    def __iter__(self) -> Iterator[WaitingCloud]:
        return iter(self._clouds)

    def append(self, cloud: WaitingCloud) -> None:
        """Add ``cloud``, the newest, counting its bytes."""
        self._clouds.append(cloud)
        self.bytes += cloud.size

    def pop_oldest(self, count: int) -> None:
        """Forget the ``count`` oldest clouds (handed on or skipped)."""
        for _ in range(count):
            self.bytes -= self._clouds.popleft().size

    def drop_oldest(self, limit_bytes: int) -> tuple[int, int]:
        """Drop the oldest clouds while more than ``limit_bytes`` wait (0: no limit), the
        newest always kept; returns how many clouds and bytes were dropped."""
        if not limit_bytes or self.bytes <= limit_bytes:
            return 0, 0
        dropped = dropped_bytes = 0
        while len(self._clouds) > 1 and self.bytes > limit_bytes:
            cloud = self._clouds.popleft()
            self.bytes -= cloud.size
            dropped += 1
            dropped_bytes += cloud.size
            cloud.release()
        return dropped, dropped_bytes


def take_ready(clouds: list[WaitingCloud], trajectory_end: float, waited_since: float,
               now: float, wait_s: float, parse: Callable[[WaitingCloud], bool]
               ) -> tuple[list[WaitingCloud], int]:
    """The clouds to hand to the correction now, oldest first, and how many of ``clouds``
    are done with (handed on, or skipped by ``parse``).

    Parameters
    ----------
    clouds : list of WaitingCloud
        Oldest first.
    trajectory_end : float
        Time of the last trajectory sample, s (-inf: none).
    waited_since : float
        When the last trajectory sample arrived, s (monotonic): a cloud waits from the later
        of this and its own arrival.
    now : float
        Now, s (monotonic).
    wait_s : float
        ``max_trajectory_wait_s``.
    parse : callable(WaitingCloud) -> bool
        Reads a cloud's header and time span the first time it is seen (False: malformed,
        skipped).

    Returns
    -------
    ready : list of WaitingCloud
        Up to the first cloud the trajectory does not cover yet (the order is kept), at most
        :data:`MAX_PUSH_POINTS` points beyond the first.
    done : int
        The clouds of ``ready`` and the malformed ones among them.
    """
    done = 0
    ready: list[WaitingCloud] = []
    ready_points = 0
    for cloud in clouds:
        if not cloud.parsed and not parse(cloud):
            done += 1
            continue
        waited = now - max(cloud.received, waited_since)
        if cloud.t_max + TRAJECTORY_MARGIN_S > trajectory_end and waited < wait_s:
            break
        ready.append(cloud)
        done += 1
        ready_points += cloud.n_points
        if ready_points >= MAX_PUSH_POINTS:
            break  # under a backlog: batches of bounded size keep the numerics efficient
    return ready, done
