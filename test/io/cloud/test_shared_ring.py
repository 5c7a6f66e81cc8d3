"""The shared-memory ring between the corrector node and its correction process: regions
never overlap and stay inside the ring, space comes back in ring order whatever order the
regions are freed in, a full ring says so instead of blocking, another process reads what
was written in place, and a ring that cannot get its memory is refused with no file left."""

from __future__ import annotations

import errno
import multiprocessing
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lidarcal_ros.io.cloud import shared_ring
from lidarcal_ros.io.cloud.shared_ring import SharedRing


@pytest.fixture
def ring() -> Iterator[SharedRing]:
    r = SharedRing.create(1000)
    yield r
    r.unlink()
    r.close()


def test_regions_fill_the_ring_in_order_and_wrap_once_the_oldest_are_freed(
        ring: SharedRing) -> None:
    assert [ring.allocate(300) for _ in range(3)] == [0, 300, 600]
    assert ring.allocate(200) is None  # 100 bytes left at the end, the start is in use
    ring.free(300)  # not the oldest: no space comes back yet
    assert ring.allocate(200) is None
    ring.free(0)  # now 0..600 is free: the next region wraps to the start
    assert ring.allocate(200) == 0
    assert ring.allocate(400) == 200
    assert ring.allocate(1) is None  # wrapped: up to the oldest region (600) only
    ring.free(600)
    ring.free(0)
    ring.free(200)
    assert ring.regions_in_use == 0
    assert ring.allocate(1000) == 0  # all of it once empty
    assert ring.allocate(0) is None and ring.allocate(1001) is None


def test_random_traffic_never_overlaps_and_always_fits_an_empty_ring(ring: SharedRing) -> None:
    rng = np.random.default_rng(3)
    live: dict[int, int] = {}  # offset -> size, as the test sees it
    for _ in range(5000):
        if live and rng.random() < 0.45:
            freed = list(live)[int(rng.integers(len(live)))]
            del live[freed]
            ring.free(freed)
            continue
        size = int(rng.integers(1, 400))
        offset = ring.allocate(size)
        if offset is None:
            continue
        assert 0 <= offset and offset + size <= ring.size
        for other, other_size in live.items():
            assert offset + size <= other or other + other_size <= offset
        live[offset] = size
    for offset in list(live):
        ring.free(offset)
    assert ring.regions_in_use == 0
    assert ring.allocate(ring.size) == 0


def test_write_and_view_round_trip(ring: SharedRing) -> None:
    data = np.arange(50, dtype=np.float64)
    offset = ring.allocate(8 + data.nbytes)
    assert offset is not None
    assert ring.write(offset, [b"headhead", data.data]) == 8 + data.nbytes
    view = ring.view(offset, 8 + data.nbytes)
    assert bytes(view[:8]) == b"headhead"
    np.testing.assert_array_equal(np.frombuffer(view[8:], dtype=np.float64), data)
    with pytest.raises(ValueError, match="outside"):
        ring.view(990, 20)


def _child_reads(path: str, size: int, offset: int, n: int, answer: multiprocessing.Queue
                 ) -> None:
    other = SharedRing.attach(path, size)
    view = other.view(offset, n)
    answer.put(bytes(view))
    other.write(offset, [bytes(reversed(bytes(view)))])


def test_another_process_reads_in_place_after_the_file_is_unlinked() -> None:
    ring = SharedRing.create(1 << 16)
    try:
        payload = os.urandom(5000)
        offset = ring.allocate(len(payload))
        assert offset is not None
        ring.write(offset, [payload])
        ctx = multiprocessing.get_context("spawn")
        answer = ctx.Queue()
        child = ctx.Process(target=_child_reads,
                            args=(ring.path, ring.size, offset, len(payload), answer))
        child.start()
        assert answer.get(timeout=60) == payload
        child.join(timeout=30)
        assert child.exitcode == 0
        # the child wrote back into the same memory
        assert bytes(ring.view(offset, len(payload))) == payload[::-1]
        ring.unlink()
        assert not Path(ring.path).exists()
        assert bytes(ring.view(offset, len(payload))) == payload[::-1]  # mapping kept
    finally:
        ring.unlink()
        ring.close()


def test_no_room_for_the_ring_is_an_error_at_creation_and_leaves_no_file(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(shared_ring, "_SHM_DIR", tmp_path)

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError, match="No space"):
        SharedRing.create(1 << 20)
    assert list(tmp_path.iterdir()) == []


def test_files_of_processes_that_died_before_unlinking_are_removed(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(shared_ring, "_SHM_DIR", tmp_path)
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    orphan = tmp_path / f"lidarcal-ring-{int(dead.stdout)}-abc"
    alive = tmp_path / f"lidarcal-ring-{os.getpid()}-def"
    other = tmp_path / "unrelated-file"
    for path in (orphan, alive, other):
        path.write_bytes(b"x")
    ring = SharedRing.create(4096)
    try:
        assert not orphan.exists()
        assert alive.exists() and other.exists() and Path(ring.path).exists()
        assert Path(ring.path).name.startswith(f"lidarcal-ring-{os.getpid()}-")
    finally:
        ring.unlink()
        ring.close()
