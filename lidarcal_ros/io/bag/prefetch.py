"""Reading ahead and writing behind in a thread, while the caller works.

Reading a bag is mostly decompressing its chunks (zstd, which releases the interpreter lock)
and cutting them into records: done in a thread of its own (:func:`prefetched`), it overlaps
the caller's work on the messages already read instead of alternating with it. Writing a LAZ
file is mostly compressing its points (lazrs, which releases it too): :class:`WriteBehind`
does it in a thread of its own while the caller reads and corrects the next clouds.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from types import TracebackType
from typing import Any, TypeVar

_T = TypeVar("_T")
_DONE = object()


def prefetched(items: Callable[[], Iterator[_T]], *, depth: int = 4, batch: int = 32,
               name: str = "lidarcal-read") -> Iterator[_T]:
    """The items of ``items()``, produced in a thread up to ``depth * batch`` ahead of the
    caller.

    They are handed over ``batch`` at a time: each hand-over wakes the other thread, which
    then waits for the interpreter lock (up to its switch interval, 5 ms, while the numerics'
    threads hold it between their compiled calls), and a bag of points holds thousands of
    messages. An exception of the producer is raised in the caller at the point where the
    items stopped. Closing the returned generator early (``break``, an exception of the
    caller) stops the producer at its next item.

    Parameters
    ----------
    items : callable
        Makes the iterator, in the producing thread.
    depth : int
        Batches held ready at most.
    batch : int
        Items per hand-over.
    """
    ready: queue.Queue[object] = queue.Queue(maxsize=max(depth, 1))
    stop = threading.Event()
    failure: list[BaseException] = []

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                ready.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        chunk: list[_T] = []
        try:
            for item in items():
                chunk.append(item)
                if len(chunk) >= batch:
                    if not put(chunk):
                        return
                    chunk = []
        except BaseException as exc:  # handed to the caller
            failure.append(exc)
        if chunk:
            put(chunk)
        put(_DONE)

    thread = threading.Thread(target=produce, name=name, daemon=True)
    thread.start()
    try:
        while True:
            got = ready.get()
            if got is _DONE:
                break
            yield from got  # type: ignore[misc]
        if failure:
            raise failure[0]
    finally:
        stop.set()
        thread.join()


class WriteBehind:
    """Calls of ``write`` made in one thread of their own, in the order they are asked for;
    use as a context manager.

    Parameters
    ----------
    write : callable
        Called with the arguments of each :meth:`__call__`, one call at a time.
    depth : int, keyword-only
        Calls that may wait (queued or running) before :meth:`__call__` waits for the oldest:
        what the caller has handed over stays in memory until written.
    name : str, keyword-only
        The thread's name.

    An exception of ``write`` is raised in the caller: by the next :meth:`__call__`, by
    :meth:`finish`, or on leaving the ``with`` block (unless the block raised first). Leaving
    the block always waits for the calls still queued, so that nothing writes into a file
    its owner is removing.
    """

    def __init__(self, write: Callable[..., Any], *, depth: int = 2,
                 name: str = "lidarcal-write") -> None:
        self._write = write
        self._depth = max(1, depth)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=name)
        self._pending: deque[Future[Any]] = deque()

    def __call__(self, *args: Any) -> None:
        """Queue ``write(*args)``; wait first while ``depth`` calls are waiting."""
        while len(self._pending) >= self._depth:
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(self._write, *args))

    def finish(self) -> None:
        """Wait for every call queued; raise the first one's exception."""
        while self._pending:
            self._pending.popleft().result()

    def __enter__(self) -> WriteBehind:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        try:
            wait(self._pending)
            if exc_type is None:
                self.finish()
        finally:
            self._pending.clear()
            self._pool.shutdown(wait=True)


__all__ = ["WriteBehind", "prefetched"]
