"""Reading ahead and writing behind in a thread (io.prefetch): order, errors, waiting."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from lidarcal_ros.io.bag.prefetch import WriteBehind, prefetched


def test_prefetched_gives_every_item_in_order_and_raises_where_they_stop() -> None:
    def items() -> Iterator[int]:
        yield from range(100)
        raise OSError("disk gone")

    got: list[int] = []
    with pytest.raises(OSError, match="disk gone"):
        for item in prefetched(items, depth=2, batch=7):
            got.append(item)
    assert got == list(range(100))


def test_write_behind_writes_in_order_in_another_thread() -> None:
    written: list[int] = []
    threads: set[str] = set()

    def write(k: int) -> None:
        time.sleep(0.001 * (k % 3))
        threads.add(threading.current_thread().name)
        written.append(k)

    with WriteBehind(write, depth=3, name="test-writer") as write_behind:
        for k in range(50):
            write_behind(k)
        write_behind.finish()
        assert written == list(range(50))
    assert threads and all(name.startswith("test-writer") for name in threads)


def test_write_behind_raises_the_writers_error_in_the_caller() -> None:
    def write(k: int) -> None:
        if k == 3:
            raise OSError("no space left on device")

    with pytest.raises(OSError, match="no space"):
        with WriteBehind(write, depth=1) as write_behind:
            for k in range(10):
                write_behind(k)
    # and at the end of the block, when the last call fails
    with pytest.raises(OSError, match="no space"):
        with WriteBehind(write, depth=5) as write_behind:
            for k in range(4):
                write_behind(k)


def test_write_behind_waits_for_queued_writes_when_the_caller_fails() -> None:
    finished: list[int] = []

    def write(k: int) -> None:
        time.sleep(0.05)
        finished.append(k)

    with pytest.raises(RuntimeError, match="caller"):
        with WriteBehind(write, depth=4) as write_behind:
            write_behind(1)
            write_behind(2)
            raise RuntimeError("caller failed")
    # nothing writes after the block is left (its owner may be removing the file)
    assert finished == [1, 2]
