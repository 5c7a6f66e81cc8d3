"""Byte regions handed between two processes through one shared-memory file.

Who allocates and frees, and why it never blocks: docs/correction.md, "Shared memory".
"""

from __future__ import annotations

import errno
import mmap
import os
import tempfile
import threading
from collections import deque
from pathlib import Path

#: Where the ring's file is created: memory-backed where the system has it.
_SHM_DIR = Path("/dev/shm")
_MAP_POPULATE = getattr(mmap, "MAP_POPULATE", 0)
#: What ``posix_fallocate`` says on file systems that cannot reserve space (the ring then
#: only gets its size).
_NO_FALLOCATE = {errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}


class SharedRing:
    """A shared-memory byte ring (docs/correction.md, "Shared memory"). Use :meth:`create` or
    :meth:`attach`.

    Parameters
    ----------
    path : str
        The ring's file.
    size : int
        Bytes.
    """

    def __init__(self, path: str, size: int) -> None:
        self.path = path
        self.size = int(size)
        fd = os.open(path, os.O_RDWR)
        try:
            # Mapped with its page tables filled now (Linux), not page by page as the first
            # clouds pass through it.
            self._map = mmap.mmap(fd, self.size, flags=mmap.MAP_SHARED | _MAP_POPULATE)
        finally:
            os.close(fd)
        self._view = memoryview(self._map)
        self._lock = threading.Lock()
        # Regions in the order allocated: [start, end, freed].
        self._regions: deque[list[int]] = deque()
        self._by_start: dict[int, list[int]] = {}

    @classmethod
    def create(cls, size: int, *, prefix: str = "lidarcal-ring-") -> SharedRing:
        """A new ring of ``size`` bytes, its space reserved.

        Raises
        ------
        OSError
            No room for it (a small ``/dev/shm``), or the file cannot be created.
        """
        directory = Path(_SHM_DIR if _SHM_DIR.is_dir() else tempfile.gettempdir())
        _remove_orphans(directory, prefix)
        fd, path = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}-", dir=directory)
        try:
            try:
                os.posix_fallocate(fd, 0, int(size))
            except AttributeError:  # not on this system (macOS): size only
                os.ftruncate(fd, int(size))
            except OSError as exc:
                if exc.errno not in _NO_FALLOCATE:
                    raise
                os.ftruncate(fd, int(size))  # the file system cannot reserve: size only
        except BaseException:
            os.close(fd)
            os.unlink(path)
            raise
        os.close(fd)
        try:
            return cls(path, size)
        except BaseException:
            os.unlink(path)
            raise

    @classmethod
    def attach(cls, path: str, size: int) -> SharedRing:
        """Map a ring another process created."""
        return cls(path, size)

    def unlink(self) -> None:
        """Remove the ring's file (both sides keep their mapping); idempotent."""
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    # -- the writer's book -------------------------------------------------------------
    def allocate(self, size: int) -> int | None:
        """Offset of a free region of ``size`` bytes, now in use; None when there is no
        room (the caller sends the bytes another way)."""
        size = int(size)
        with self._lock:
            if size <= 0 or size > self.size:
                return None
            if not self._regions:
                start = 0
            else:
                first, last = self._regions[0][0], self._regions[-1]
                if last[0] >= first:  # not wrapped: room after the last, or before the first
                    if last[1] + size <= self.size:
                        start = last[1]
                    elif size <= first:
                        start = 0
                    else:
                        return None
                elif last[1] + size <= first:  # wrapped: room between the last and the first
                    start = last[1]
                else:
                    return None
            region = [start, start + size, 0]
            self._regions.append(region)
            self._by_start[start] = region
            return start

    def free(self, offset: int) -> None:
        """The reader is done with the region at ``offset`` (in any order)."""
        with self._lock:
            region = self._by_start.pop(offset, None)
            if region is None:
                return
            region[2] = 1
            while self._regions and self._regions[0][2]:
                self._regions.popleft()

    def clear(self) -> None:
        """Forget every region (the reader is gone)."""
        with self._lock:
            self._regions.clear()
            self._by_start.clear()

    @property
    def regions_in_use(self) -> int:
        """Regions allocated and not yet freed."""
        with self._lock:
            return len(self._by_start)

    # -- both sides --------------------------------------------------------------------
    def view(self, offset: int, size: int) -> memoryview:
        """The bytes of a region, in place."""
        if offset < 0 or offset + size > self.size:
            raise ValueError(f"region {offset}+{size} outside a ring of {self.size} bytes")
        return self._view[offset:offset + size]

    def write(self, offset: int, parts: list[bytes | memoryview]) -> int:
        """Copy ``parts`` one after the other into the ring from ``offset``; returns the
        bytes written."""
        at = offset
        for part in parts:
            data = memoryview(part).cast("B")
            self._view[at:at + len(data)] = data
            at += len(data)
        return at - offset

    def close(self) -> None:
        """Unmap (only once no view of it is left; otherwise the mapping stays until the
        process ends)."""
        try:
            self._view.release()
            self._map.close()
        except BufferError:
            pass


def _remove_orphans(directory: Path, prefix: str) -> None:
    """Remove the ring files of processes that no longer run (killed before the other side
    had mapped the ring, when the file is normally removed): their memory is otherwise kept
    until the next reboot."""
    for path in directory.glob(f"{prefix}*-*"):
        pid_text = path.name[len(prefix):].split("-", 1)[0]
        if not pid_text.isdigit():
            continue
        try:
            os.kill(int(pid_text), 0)
        except ProcessLookupError:
            path.unlink(missing_ok=True)
        except (PermissionError, OSError):
            pass  # another user's process, or alive


__all__ = ["SharedRing"]
