"""Reading ahead in a thread: the items of an iterator produced while the caller works.

Reading a bag is mostly decompressing its chunks (zstd, which releases the interpreter lock)
and cutting them into records: done in a thread of its own, it overlaps the caller's work on
the messages already read instead of alternating with it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from typing import TypeVar

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


__all__ = ["prefetched"]
