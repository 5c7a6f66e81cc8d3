"""The clouds of a bag handed to the correction once the trajectory read so far covers them.

So that ``lidarcal correct`` reads a bag whose trajectory comes with its clouds once
(docs/correction.md, "The trajectory gate").
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.rigorous import MODEL_SPAN_PAD_S
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.trajectory.buffer import TrajectoryBuffer
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.cloud.columns import resolve_time_field, time_span
from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples
from lidarcal_ros.pipeline.correction.stream import StreamCorrector

__all__ = ["REACH_SAMPLES", "RereadBag", "TrajectoryGate"]

#: Samples a cloud waits for beyond its reach: the correction reads up to two samples past a
#: point's time (the track heading's differences, the attitude spline's tangents).
REACH_SAMPLES = 4


class RereadBag(Exception):
    """The bag cannot be corrected in one pass with the result of two (not an error: the
    caller reads it again, the trajectory first)."""


@dataclass
class _Queued:
    tag: Any
    msg: Any
    points: np.ndarray
    t_last: float  # last finite point time, s (-inf: none)


class TrajectoryGate:
    """Clouds of a bag handed to a corrector once the trajectory covers them (module
    docstring); :meth:`known` for a trajectory read beforehand.

    Parameters
    ----------
    corrector : StreamCorrector
        Given each trajectory before the clouds it covers are pushed.
    samples : TrajectorySamples
        Where ``add_pose`` puts the trajectory messages.
    add_pose : callable(msgtype, raw)
        Add a trajectory message's CDR bytes to ``samples`` (refusing a wrong type).
    whole : callable() -> (Trajectory, frame)
        The whole trajectory of ``samples`` and its frame, made and checked as when the
        trajectory is read first (raising what that raises).
    source : str
        The bag, named in messages.
    topic : str
        The clouds' topic.
    max_held_points : int
        Most points waiting before :class:`RereadBag`.
    """

    def __init__(self, corrector: StreamCorrector, samples: TrajectorySamples,
                 add_pose: Callable[[str, Any], None],
                 whole: Callable[[], tuple[Trajectory, str]], *, source: str, topic: str,
                 max_held_points: int) -> None:
        self.corrector = corrector
        self.samples = samples
        self.source = source
        self.topic = topic
        self.max_held_points = max_held_points
        #: The trajectory's frame (None: no sample read yet).
        self.frame: str | None = None
        self._add_pose = add_pose
        self._whole = whole
        self._buffer = TrajectoryBuffer(keep_s=math.inf)
        self._fed = 0  # samples given to the buffer
        self._newest = -math.inf  # latest sample time read, s
        self._given: Trajectory | None = None  # the corrector's trajectory
        window = corrector.settings.window
        self._reach_s = max(window.window_s, MODEL_SPAN_PAD_S)
        self._least_samples = max(REACH_SAMPLES, window.min_samples)
        self._queue: deque[_Queued] = deque()
        self._queued_points = 0
        self._time_field: str | None = None
        self._finished = False

    @classmethod
    def known(cls, corrector: StreamCorrector, frame: str, *, source: str,
              topic: str) -> TrajectoryGate:
        """A gate for a corrector that has the whole trajectory (read first): every cloud
        passes at once."""
        gate = cls(corrector, TrajectorySamples(), _refuse_pose, _no_trajectory,
                   source=source, topic=topic, max_held_points=0)
        gate.frame, gate._finished = frame, True
        return gate

    @property
    def reading(self) -> bool:
        """The trajectory is read with the clouds (the gate was not made by :meth:`known`)."""
        return not self._finished

    def pose(self, msgtype: str, raw: Any) -> None:
        """Take a trajectory message (CDR bytes)."""
        n = len(self.samples)
        self._add_pose(msgtype, raw)
        if len(self.samples) > n:
            t = self.samples.t[-1]
            if t > self._newest:
                self._newest = t
            if self.frame is None:
                self.frame = next(iter(self.samples.frames))

    def cloud(self, tag: Any, msg: Any, points: np.ndarray) -> list[tuple[Any, np.ndarray]]:
        """Take a cloud (decoded message and points); the clouds now ready, ``(tag,
        points)`` in the order taken, their frame checked (the corrector given the
        trajectory they need).

        Raises
        ------
        InputError
            A cloud in another frame than the trajectory.
        RereadBag
            Too many points waiting.
        """
        if self._finished:
            self._check_frame(msg)
            return [(tag, points)]
        self._queue.append(_Queued(tag, msg, points, self._last_time(points)))
        self._queued_points += len(points)
        out = self._release()
        if self._queued_points > self.max_held_points:
            raise RereadBag(f"{self._queued_points} points waiting for the trajectory")
        return out

    def finish(self) -> list[tuple[Any, np.ndarray]]:
        """The bag has been read: the clouds still waiting, corrected with the whole
        trajectory (made and checked now), which the trajectories given before must begin.

        Raises
        ------
        RereadBag
            A trajectory given before is not the beginning of the whole one.
        """
        if self._finished:
            return []
        self._finished = True
        trajectory, self.frame = self._whole()
        if self._given is not None and not _begins(self._given, trajectory):
            raise RereadBag("the trajectory did not come in time order")
        self.corrector.set_trajectory(trajectory)
        out = []
        while self._queue:
            q = self._queue.popleft()
            self._check_frame(q.msg)
            out.append((q.tag, q.points))
        self._queued_points = 0
        return out

    # -- internals -------------------------------------------------------------------

    def _last_time(self, points: np.ndarray) -> float:
        if not len(points):
            return -math.inf
        if self._time_field not in (points.dtype.names or ()):  # (a cloud of another layout)
            self._time_field = resolve_time_field(
                points, self.corrector.settings.time_field, source=self.topic)
        t = points[self._time_field]
        # (compiled, one pass: numpy's max over a field of the message's rows, strided and
        # often unaligned, costs some 40 ns a point)
        last = time_span(t)[1]
        if math.isfinite(last):
            return last
        t = t[np.isfinite(t)]  # (no finite time, or an infinite one)
        return float(t.max()) if t.size else -math.inf

    def _release(self) -> list[tuple[Any, np.ndarray]]:
        """The queued clouds the trajectory covers, oldest first, stopping at the first that
        it does not. The trajectory is taken again (its new samples) only when that one
        may be covered and a batch's worth of points wait."""
        out: list[tuple[Any, np.ndarray]] = []
        while self._queue:
            head = self._queue[0]
            if not self._covers(head.t_last):
                if not (self._newest > head.t_last + self._reach_s
                        and len(self.samples) > self._fed
                        and self._queued_points >= self.corrector.batch_points):
                    break
                self._take_trajectory()
                if not self._covers(head.t_last):
                    break
            self._queue.popleft()
            self._queued_points -= len(head.points)
            self._check_frame(head.msg)
            out.append((head.tag, head.points))
        return out

    def _covers(self, t_last: float) -> bool:
        traj = self._given
        return (traj is not None and len(traj) >= self._least_samples
                and t_last + self._reach_s < traj.t[-REACH_SAMPLES])

    def _take_trajectory(self) -> None:
        s, a = self.samples, self._fed
        self._buffer.add_many(s.t[a:], s.xyz[a:], s.orientation[a:])
        self._fed = len(s)
        traj = self._buffer.trajectory()
        if self._given is not None and not _begins(self._given, traj):
            raise RereadBag("the trajectory did not come in time order")
        self._given = traj
        self.corrector.set_trajectory(traj)

    def _check_frame(self, msg: Any) -> None:
        if msg.header.frame_id != self.frame:
            raise InputError(f"{self.source}: clouds on {self.topic} are in frame "
                             f"'{msg.header.frame_id}' but the trajectory is in frame "
                             f"'{self.frame}'")


def _refuse_pose(msgtype: str, raw: Any) -> None:
    raise AssertionError("the trajectory was read first")


def _no_trajectory() -> tuple[Trajectory, str]:
    raise AssertionError("the trajectory was read first")


def _begins(part: Trajectory, whole: Trajectory) -> bool:
    """``whole`` begins with ``part``: the same samples, bit for bit, with the same attitude
    flags."""
    n = len(part)
    if (n > len(whole) or part.full_attitude != whole.full_attitude
            or (part.orientation is None) != (whole.orientation is None)):
        return False
    pairs: list[tuple[np.ndarray | None, np.ndarray | None]] = [(part.t, whole.t),
                                                               (part.xyz, whole.xyz)]
    if part.orientation is not None and whole.orientation is not None:
        pairs.append((part.orientation, whole.orientation))
        pairs.append((part.heading, whole.heading))
    return all(_same_start(a, b) for a, b in pairs)


def _same_start(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """``b`` begins with the rows of ``a``, bit for bit (NaN included)."""
    if a is None or b is None:
        return a is b
    b = b[:a.shape[0]]
    if (a.shape == b.shape and a.strides == b.strides
            and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]):
        return True  # the same memory (rows a trajectory buffer handed out stay as they are)
    return a.shape == b.shape and a.tobytes() == b.tobytes()
