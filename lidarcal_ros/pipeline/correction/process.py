"""The live correction in a child process, the clouds carried there and back in shared memory.

Why a child process, and how the clouds travel: docs/correction.md, "The live corrector".
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.allocator import tune_allocator
from lidarcal_ros.core.jit import start_without_blas
from lidarcal_ros.io.cloud.messages import cloud_header_cdr
from lidarcal_ros.io.cloud.pointcloud import point_fields
from lidarcal_ros.io.cloud.shared_ring import SharedRing
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.service import (
    CorrectedMessage,
    CorrectionEngine,
    ErrorHandler,
    ResultHandler,
    ServiceOptions,
    warm_up_engine,
)

__all__ = ["CorrectionProcess", "InboundRegion"]

logger = logging.getLogger(__name__)

#: Pipe capacity asked for (bytes): a cloud crosses in a few system calls instead of one per
#: 64 kB, and each of those calls gives the interpreter lock up and waits to take it back.
_PIPE_BYTES = 1 << 20


def _widen(conn: Any) -> None:
    """Ask for a larger pipe buffer (Linux; elsewhere a no-op)."""
    try:
        import fcntl

        fcntl.fcntl(conn.fileno(), fcntl.F_SETPIPE_SZ, _PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass


def _send_payload(conn: Any, parts: list[bytes | memoryview]) -> None:
    """Write the bytes of ``parts`` one after the other, framed as :meth:`multiprocessing.
    connection.Connection.send_bytes` does (4-byte big-endian length), in as few system
    calls as the pipe allows."""
    fd = conn.fileno()
    views = [memoryview(part).cast("B") for part in parts]
    os.write(fd, struct.pack("!i", sum(len(v) for v in views)))
    for view in views:
        while view:
            view = view[os.write(fd, view):]


def _recv_payload(conn: Any) -> bytes:
    """Read one payload written by :func:`_send_payload` (or ``send_bytes``)."""
    fd = conn.fileno()
    size = struct.unpack("!i", _read_exactly(fd, 4))[0]
    return _read_exactly(fd, size)


def _read_exactly(fd: int, size: int) -> bytes:
    parts = []
    remaining = size
    while remaining:
        part = os.read(fd, remaining)
        if not part:
            raise EOFError
        parts.append(part)
        remaining -= len(part)
    return parts[0] if len(parts) == 1 else b"".join(parts)


#: How long the child waits for a batch of a worker thread before it looks for requests.
_RESULT_POLL_S = 0.002


@dataclass(frozen=True)
class _Rings:
    """Where the rings' files are (the child maps them)."""

    inbound: str | None
    outbound: str | None
    size: int


@dataclass(frozen=True)
class InboundRegion:
    """A region of a correction process's inbound ring that a cloud is received into
    straight from DDS (:meth:`CorrectionProcess.inbound_region`): pushed as it lies, only
    its place on the pipe."""

    ring: SharedRing
    offset: int
    size: int

    @property
    def view(self) -> memoryview:
        """Its bytes, in place."""
        return self.ring.view(self.offset, self.size)

    def release(self) -> None:
        """Give the region back unused (its cloud was dropped or skipped)."""
        self.ring.free(self.offset)


def _attach(rings: _Rings) -> tuple[SharedRing | None, SharedRing | None]:
    try:
        inbound = SharedRing.attach(rings.inbound, rings.size) if rings.inbound else None
        outbound = SharedRing.attach(rings.outbound, rings.size) if rings.outbound else None
    except (OSError, ValueError) as exc:
        logger.warning("correction process: shared memory not mapped (%s); using pipes", exc)
        return None, None
    return inbound, outbound


def _child_main(inbox: Any, outbox: Any, freed: Any, settings: CorrectionSettings,
                options: ServiceOptions, rings: _Rings) -> None:
    """The child process: requests from ``inbox``, results to ``outbox``, the outbound
    regions the node process is done with from ``freed`` (docs/correction.md)."""
    inbound, outbound = _attach(rings)
    outbox.send(("mapped", inbound is not None))
    # glibc's threshold for giving back free heap stays high here: a lower one returned the
    # heap the warm-up grew, and at 4M points/s the first chunks then faulted it in again
    # (a start-up backlog that took seconds, not one, to drain).
    tune_allocator()
    try:
        start_without_blas()  # (nothing else runs in this process yet)
        warm_up_engine(settings, options)
    except Exception:  # only a warm-up
        logger.debug("warm-up failed", exc_info=True)
    _widen(inbox)
    _widen(outbox)
    results_out = _ResultSender(outbox, outbound, freed)

    def on_error(tag: Any, reason: str) -> None:
        outbox.send(("error", tag, reason))

    def on_failed(tag: Any, reason: str) -> None:  # its corrected cloud may hold ring space
        results_out.discard(tag)
        on_error(tag, reason)

    engine = CorrectionEngine(settings, options,
                     placer=results_out.place if outbound is not None else None,
                     on_failed=on_failed)
    send_results = results_out.send

    def payloads(entries: list[tuple[Any, int | None, int]]
                 ) -> list[tuple[Any, bytes | memoryview]]:
        out: list[tuple[Any, bytes | memoryview]] = []
        for tag, offset, size in entries:
            if offset is None:
                out.append((tag, _recv_payload(inbox)))
            else:
                assert inbound is not None
                out.append((tag, inbound.view(offset, size)))  # read in place
        return out

    while True:
        try:
            # With batches in the worker threads, their results go out as they finish,
            # not with the next request.
            while engine.corrector.in_flight and not inbox.poll():
                send_results(engine.collect(timeout=_RESULT_POLL_S))
            request = inbox.recv()
        except (EOFError, OSError):  # the node process is gone
            return
        kind = request[0]
        tags: list[Any] = []
        try:
            if kind == "poses":
                engine.poses(request[1], request[2], request[3])
            elif kind == "push":
                tags = [tag for tag, _, _ in request[1]]
                send_results(engine.push(payloads(request[1]), on_error))
            elif kind == "release":
                send_results(engine.release())
            elif kind == "settings":
                engine.corrector.set_settings(request[1])
            elif kind == "lookahead":
                engine.corrector.set_lookahead(request[1])
            elif kind == "keep":
                engine.trajectory.keep_s = float(request[1])
            elif kind == "flush":
                send_results(engine.flush())
                outbox.send(("flushed",))
                return
        except (EOFError, OSError):
            return
        except Exception as exc:  # a bug: report the clouds of this request, keep serving
            reason = f"internal error: {type(exc).__name__}: {exc}"
            logger.exception("correction process")
            for tag in tags:
                results_out.discard(tag)
                on_error(tag, reason)


class _ResultSender:
    """The child's side of the results: each corrected cloud is built straight into the
    outbound ring, behind its message header (:meth:`place`, from the worker threads), so
    that sending it (:meth:`send`) copies nothing; a cloud that found no room is serialised
    and goes into the ring afterwards, or through the pipe."""

    def __init__(self, outbox: Any, ring: SharedRing | None, freed: Any) -> None:
        self._outbox = outbox
        self._ring = ring
        self._freed = freed
        self._lock = threading.Lock()
        # tag -> (region offset, message offset, message bytes)
        self._placed: dict[Any, tuple[int, int, int]] = {}

    def _take_freed(self) -> None:
        """Give back the regions the node process is done with."""
        assert self._ring is not None
        with self._lock:
            while self._freed.poll():
                self._ring.free(self._freed.recv())

    def place(self, tag: Any, stamp: int, frame_id: str, n: int, dtype: np.dtype[Any]
              ) -> np.ndarray | None:
        """The rows to build a corrected cloud in, inside the ring, or None (no room)."""
        ring = self._ring
        assert ring is not None
        head = cloud_header_cdr(stamp, frame_id, point_fields(dtype), dtype.itemsize, n)
        data = n * dtype.itemsize
        size = len(head) + data + 1  # + is_dense
        self._take_freed()
        offset = ring.allocate(size + 7)
        if offset is None:
            return None
        start = offset + (-(offset + len(head))) % 8  # the points 8-byte aligned
        ring.write(start, [head])
        self._placed[tag] = (offset, start, size)
        return np.frombuffer(ring.view(start + len(head), data), dtype=dtype, count=n)

    def discard(self, tag: Any) -> None:
        """A cloud placed but never sent (an internal error): its region is free again."""
        placed = self._placed.pop(tag, None)
        if placed is not None and self._ring is not None:
            self._ring.free(placed[0])

    def send(self, results: list[CorrectedMessage]) -> None:
        for r in results:
            placed = self._placed.pop(r.tag, None)
            offset: int | None
            parts: list[bytes | memoryview] = []
            if placed is not None:
                assert self._ring is not None
                offset, start, size = placed
                self._ring.write(start + size - 1, [b"\x01" if r.dense else b"\x00"])
            else:
                parts = list(r.cdr_parts())
                offset, start, size = self._copy_into_ring(parts)
            self._outbox.send(("out", r.tag, len(r.points), r.not_corrected, r.seconds,
                               offset, start, size))
            if offset is None:
                _send_payload(self._outbox, parts)

    def _copy_into_ring(self, parts: list[bytes | memoryview]) -> tuple[int | None, int, int]:
        """A cloud built outside the ring, serialised as ``parts``: copied into the ring if
        it has room now (its region offset, message offset and size; offset None: not)."""
        size = sum(memoryview(p).nbytes for p in parts)
        if self._ring is None:
            return None, 0, size
        self._take_freed()
        offset = self._ring.allocate(size)
        if offset is not None:
            self._ring.write(offset, parts)
        return offset, offset or 0, size


def _create_rings(size: int) -> tuple[SharedRing | None, SharedRing | None]:
    """The two rings of ``size`` bytes, or none where shared memory cannot be had or is not
    wanted (``size`` 0): then pipes carry all."""
    if size <= 0:
        return None, None
    inbound = outbound = None
    try:
        inbound = SharedRing.create(size)
        outbound = SharedRing.create(size)
    except OSError as exc:
        logger.warning("no shared memory for the correction process (%s): clouds go "
                       "through pipes", exc)
        if inbound is not None:
            inbound.unlink()
            inbound.close()
        return None, None
    return inbound, outbound


class CorrectionProcess:
    """The correction in a child process with its own interpreter lock (docs/correction.md).

    Clouds go to the child and back through two shared-memory rings
    (:mod:`~lidarcal_ros.io.cloud.shared_ring`): one copy into the ring, read in place, and only
    their place on the pipe. A cloud that finds no room, or a host without shared memory,
    uses the pipe itself.

    Parameters
    ----------
    settings : CorrectionSettings
    options : ServiceOptions
    on_result, on_error : callables
        Called from a reader thread of this process, in the order the clouds were pushed.
    on_failure : callable(reason), optional
        The child process died; the clouds it held are reported to ``on_error`` first.
    """

    def __init__(self, settings: CorrectionSettings, options: ServiceOptions, *,
                 on_result: ResultHandler, on_error: ErrorHandler,
                 on_failure: Callable[[str], None] | None = None) -> None:
        self._on_result = on_result
        self._on_error = on_error
        self._on_failure = on_failure
        size = options.ring_bytes
        self._inbound, self._outbound = _create_rings(size)
        self._rings = [r for r in (self._inbound, self._outbound) if r is not None]
        rings = _Rings(self._inbound.path if self._inbound else None,
                       self._outbound.path if self._outbound else None, size)
        self._inbound_ready = False  # the child has mapped the inbound ring
        ctx = multiprocessing.get_context("spawn")  # never fork a process that runs threads
        child_in, self._inbox = ctx.Pipe(duplex=False)
        self._outbox, child_out = ctx.Pipe(duplex=False)
        # The outbound regions this process is done with go back on a pipe of their own: on
        # the request pipe, the reader thread could wait behind a cloud that the worker
        # thread sends while the child waits for the reader to take a result (a deadlock).
        child_freed, self._freed = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_child_main, name="lidarcal-correction",
                                    args=(child_in, child_out, child_freed, settings, options,
                                          rings), daemon=True)
        try:
            self._process.start()
        except BaseException:
            self._drop_rings()
            raise
        child_in.close()
        child_out.close()
        child_freed.close()
        _widen(self._inbox)
        _widen(self._outbox)
        self._send_lock = threading.Lock()
        # Tags pushed and not yet reported, in order, with the offset of their inbound region.
        self._pending: dict[Any, int | None] = {}
        self._pending_lock = threading.Lock()
        self._flushed = threading.Event()
        self._closing = False
        #: Clouds carried so far, by way: ``ring in`` (of which ``in place``: received into
        #: the ring, :meth:`inbound_region`), ``pipe in``, ``ring out``, ``pipe out``.
        self.carried = dict.fromkeys(("ring in", "in place", "pipe in", "ring out",
                                      "pipe out"), 0)
        self._reader = threading.Thread(target=self._read, name="lidarcal-correction-reader",
                                        daemon=True)
        self._reader.start()

    @property
    def alive(self) -> bool:
        """Whether the child process runs."""
        return self._process.is_alive()

    @property
    def ring_paths(self) -> list[str]:
        """The files of the shared-memory rings this process made (none: pipes only); they
        are gone once the child has mapped them, or has died."""
        return [ring.path for ring in self._rings]

    def kill(self) -> None:
        """End the child process at once (as a crash would: the clouds it held are reported
        to ``on_error`` and ``on_failure`` is called)."""
        self._process.kill()

    @property
    def shared_memory(self) -> bool:
        """Whether clouds go through the shared-memory rings (once the child has mapped
        them)."""
        return self._inbound_ready

    def poses(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None = None
              ) -> None:
        """Add trajectory samples (s; map frame, m; orientation quaternions (n, 4) xyzw, NaN
        rows or None: none)."""
        self._send(("poses", np.asarray(t, dtype=np.float64),
                    np.asarray(xyz, dtype=np.float64),
                    None if orientation is None
                    else np.asarray(orientation, dtype=np.float64).reshape(-1, 4)))

    def inbound_region(self, size: int) -> InboundRegion | None:
        """Room in the inbound ring to receive a cloud of ``size`` bytes into, so that
        :meth:`push` need not copy it; None without a ring (yet), or when it is full."""
        ring = self._inbound
        if ring is None or not self._inbound_ready:
            return None
        offset = ring.allocate(size)
        return None if offset is None else InboundRegion(ring, offset, size)

    def push(self, clouds: list[tuple[Any, bytes | memoryview | InboundRegion]]) -> None:
        """Correct clouds (tag, CDR bytes, or a region of this process's inbound ring they
        were received into); results come through the handlers."""
        if not clouds:
            return
        entries: list[tuple[Any, int | None, int]] = []
        copies: list[tuple[int | None, bytes | memoryview]] = []
        ring = self._inbound if self._inbound_ready else None
        with self._pending_lock:
            for tag, raw in clouds:
                if isinstance(raw, InboundRegion) and raw.ring is ring:
                    offset: int | None = raw.offset  # received in place: no copy
                    size = raw.size
                    self.carried["in place"] += 1
                else:
                    data = raw.view if isinstance(raw, InboundRegion) else raw
                    size = memoryview(data).nbytes
                    offset = ring.allocate(size) if ring is not None else None
                    copies.append((offset, data))
                self._pending[tag] = offset
                entries.append((tag, offset, size))
        by_pipe: list[bytes | memoryview] = []
        for offset, data in copies:
            if offset is None:
                by_pipe.append(data)
            else:
                assert ring is not None
                ring.write(offset, [data])
        self.carried["pipe in"] += len(by_pipe)
        self.carried["ring in"] += len(entries) - len(by_pipe)
        with self._send_lock:
            try:
                self._inbox.send(("push", entries))
                for raw in by_pipe:
                    _send_payload(self._inbox, [raw])
            except (OSError, ValueError):
                self._fail("the correction process is not running")

    def release(self) -> None:
        """Correct what is held now, without waiting for look-ahead."""
        self._send(("release",))

    def poll(self) -> None:
        """Nothing to do: the child sends the results of its worker threads by itself."""

    def set_settings(self, settings: CorrectionSettings) -> None:
        """Use new settings (calibration, radiometry) from the child's next batch on."""
        self._send(("settings", settings))

    def set_lookahead(self, lookahead: bool) -> None:
        """Wait for look-ahead (or not) from the child's next cloud on."""
        self._send(("lookahead", bool(lookahead)))

    def set_trajectory_keep(self, seconds: float) -> None:
        """Keep this many seconds of trajectory."""
        self._send(("keep", float(seconds)))

    def close(self, timeout: float = 10.0) -> None:
        """Correct and report everything held, then stop the child process."""
        self._closing = True
        self._send(("flush",))
        self._flushed.wait(timeout)
        self._reader.join(timeout=1.0)
        self._process.join(timeout=2.0)
        if self._process.is_alive():
            self._process.kill()
        self._inbox.close()
        self._freed.close()
        if not self._reader.is_alive():
            self._outbox.close()
        self._drop_rings()

    def _drop_rings(self) -> None:
        for ring in self._rings:
            ring.unlink()
            ring.close()

    def _send(self, request: tuple[Any, ...]) -> None:
        with self._send_lock:
            try:
                self._inbox.send(request)
            except (OSError, ValueError):
                self._fail("the correction process is not running")

    def _read(self) -> None:
        while True:
            try:
                reply = self._outbox.recv()
                if reply[0] == "out":
                    _kind, tag, n, bad, seconds, offset, start, size = reply
                    self.carried["pipe out" if offset is None else "ring out"] += 1
                    self._done(tag)
                    if offset is None:
                        self._on_result(tag, _recv_payload(self._outbox), n, bad, seconds)
                    else:
                        self._result_in_ring(tag, offset, start, size, n, bad, seconds)
                elif reply[0] == "error":
                    self._done(reply[1])
                    self._on_error(reply[1], reply[2])
                elif reply[0] == "mapped":
                    # Both sides have the rings mapped: their files can go.
                    for ring in self._rings:
                        ring.unlink()
                    self._inbound_ready = bool(reply[1]) and self._inbound is not None
                elif reply[0] == "flushed":
                    self._flushed.set()
                    return
            except (EOFError, OSError):
                self._fail("the correction process ended")
                return
            except Exception:  # a handler failed: keep reading
                logger.exception("correction result handler")

    def _result_in_ring(self, tag: Any, offset: int, start: int, size: int, n: int,
                        bad: int, seconds: float) -> None:
        """Hand on a corrected cloud in place in the outbound ring (the handler publishes it
        from there), then give its region back to the child."""
        assert self._outbound is not None
        try:
            with self._outbound.view(start, size) as cdr:
                self._on_result(tag, cdr, n, bad, seconds)
        finally:
            self._freed.send(offset)  # a few bytes: never waits

    def _done(self, tag: Any) -> None:
        with self._pending_lock:
            offset = self._pending.pop(tag, None)
        if offset is not None and self._inbound is not None:
            self._inbound.free(offset)

    def _fail(self, reason: str) -> None:
        """Report the clouds the child held as lost, once."""
        with self._pending_lock:
            lost, self._pending = list(self._pending), {}
            self._inbound_ready = False
        for ring in self._rings:
            ring.clear()
            ring.unlink()  # (if the child died before it mapped them)
        if self._closing and not lost:
            self._flushed.set()
            return
        for tag in lost:
            self._on_error(tag, reason)
        self._flushed.set()
        if self._on_failure is not None and not self._closing:
            self._on_failure(reason)
