"""The MCAP storage of the bags lidarcal writes: rosbags' writer, its chunks compressed in
threads.

rosbags writes an MCAP file chunk by chunk and compresses each chunk (zstd) in the calling
thread before it takes the next message: a corrected mission is mostly point bytes, and their
compression was most of the time of writing one. Here a closed chunk goes to a small pool of
threads (zstd releases the interpreter lock while it works) and is written to the file, in
order, once compressed, while the caller goes on filling the next chunk; at most a few chunks
wait. Chunks are compressed at zstd level 1 (rosbags' default, 3, gives some 9% smaller
point clouds at half the speed). The file is rosbags' in every other respect (records,
indexes, summary, the rosbag2 metadata), and readers of MCAP read it as any other: messages in
log-time order through the chunk index.

:class:`BagWriterBackend` is rosbags' :class:`~rosbags.rosbag2.Writer` with this storage for
MCAP; :class:`lidarcal_ros.io.bag.BagWriter` writes through it.
"""

from __future__ import annotations

import os
import sys
from collections import defaultdict, deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from io import BytesIO
from pathlib import Path
from typing import Any

from rosbags.interfaces import Connection
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionMode, StoragePlugin
from rosbags.rosbag2.storage_mcap import (
    McapWriter,
    PendingChunk,
    write_record,
    write_string,
    write_uint16,
    write_uint32,
    write_uint64,
)

if sys.version_info >= (3, 14):  # pragma: no cover
    from compression import zstd
else:
    from backports import zstd

#: Uncompressed bytes of a chunk before it is closed (rosbags' size: a recording cut short
#: loses at most its last chunk, see ``lidarcal recover``).
CHUNK_BYTES = 1 << 20
#: zstd level of the chunks.
ZSTD_LEVEL = 1
#: Threads compressing chunks (two cores: the numerics and the reading take the rest).
COMPRESS_THREADS = min(2, os.cpu_count() or 1)
#: Closed chunks that may wait for their compression before the writer waits for the oldest.
MAX_PENDING = 8


#: zstd options of a chunk: its level, and a checksum of its content in the frame, which a
#: reader verifies (MCAP's own CRC is left 0, as rosbags leaves it: a damaged chunk of point
#: bytes, mostly literals at low levels, would otherwise decompress into wrong points).
_ZSTD_OPTIONS: dict[int, int] = {zstd.CompressionParameter.compression_level: ZSTD_LEVEL,
                                  zstd.CompressionParameter.checksum_flag: 1}


def _compress(data: bytes | memoryview) -> bytes:
    return zstd.compress(data, options=_ZSTD_OPTIONS)


class ThreadedMcapStorage(McapWriter):
    """rosbags' MCAP storage writer whose chunks are compressed in threads (module
    docstring); the records it writes are rosbags'."""

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        super().__init__(path, compression)
        self._pool: ThreadPoolExecutor | None = None
        self._compress: Callable[[bytes | memoryview], bytes] = _compress
        if self.compression:
            self._pool = ThreadPoolExecutor(max_workers=COMPRESS_THREADS,
                                            thread_name_prefix="lidarcal-mcap")
        self._pending: deque[tuple[PendingChunk, Future[bytes] | None]] = deque()

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        """Append a message record to the open chunk (rosbags' record, written straight into
        the chunk), closing the chunk past :data:`CHUNK_BYTES`."""
        self.message_start_time = min(timestamp, self.message_start_time)
        self.message_end_time = max(timestamp, self.message_end_time)
        self.channel_stats[connection.id] += 1
        chunk = self.chunk
        chunk.message_start_time = min(timestamp, chunk.message_start_time)
        chunk.message_end_time = max(timestamp, chunk.message_end_time)
        bio = chunk.bio
        chunk.msgs[connection.id].append((timestamp, bio.tell()))
        size = len(data) if isinstance(data, bytes) else memoryview(data).nbytes
        bio.write(b"\x05")
        write_uint64(bio, 22 + size)
        write_uint16(bio, connection.id)
        write_uint32(bio, 0)
        write_uint64(bio, timestamp)
        write_uint64(bio, timestamp)
        bio.write(data)
        if bio.tell() > CHUNK_BYTES:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Hand the open chunk to the compression threads and start a new one; write the
        chunks whose compression is done (waiting for the oldest past :data:`MAX_PENDING`)."""
        chunk = self.chunk
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        future = None if self._pool is None else self._pool.submit(
            self._compress, chunk.bio.getbuffer())
        self._pending.append((chunk, future))
        self._write_finished(wait=len(self._pending) > MAX_PENDING)

    def _write_finished(self, *, wait: bool = False, everything: bool = False) -> None:
        while self._pending:
            chunk, future = self._pending[0]
            if future is not None and not future.done() and not (wait or everything):
                return
            self._pending.popleft()
            if future is None:
                with chunk.bio.getbuffer() as data:
                    self._write_chunk(chunk, data)
            else:
                self._write_chunk(chunk, future.result())
            wait = False

    def _write_chunk(self, chunk: PendingChunk, compressed: bytes | memoryview) -> None:
        """The chunk record, its message indexes and its chunk index entry, as rosbags'
        ``close_chunk`` writes them."""
        size = chunk.bio.tell()
        rec = BytesIO()
        write_uint64(rec, chunk.message_start_time)
        write_uint64(rec, chunk.message_end_time)
        write_uint64(rec, size)
        write_uint32(rec, 0)
        write_string(rec, self.compression)
        write_uint64(rec, len(compressed))
        rec.write(compressed)

        chunk_start = self.bio.tell()
        write_record(self.bio, 0x06, rec)
        chunk_end = self.bio.tell()

        offsets: list[tuple[int, int]] = []
        for cid, msgs in chunk.msgs.items():
            offsets.append((cid, self.bio.tell()))
            rec = BytesIO()
            write_uint16(rec, cid)
            write_uint32(rec, len(msgs) * 16)
            for ts, offset in msgs:
                write_uint64(rec, ts)
                write_uint64(rec, offset)
            write_record(self.bio, 0x07, rec)

        rec = BytesIO()
        write_uint64(rec, chunk.message_start_time)
        write_uint64(rec, chunk.message_end_time)
        write_uint64(rec, chunk_start)
        write_uint64(rec, chunk_end - chunk_start)
        write_uint32(rec, len(offsets) * 10)
        for cid, offset in offsets:
            write_uint16(rec, cid)
            write_uint64(rec, offset)
        write_uint64(rec, self.bio.tell() - chunk_end)
        write_string(rec, self.compression)
        write_uint64(rec, len(compressed))
        write_uint64(rec, size)
        self.chunks.append(rec)

    def close(self, version: int, metadata: str) -> None:
        """Write the last chunks, then rosbags' summary and footer."""
        try:
            if self.chunk.bio.tell():
                self.close_chunk()
            self._write_finished(everything=True)
        finally:
            self._stop()
        super().close(version, metadata)

    def abort(self) -> None:
        self._stop()
        super().abort()

    def _stop(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class BagWriterBackend(Writer):
    """rosbags' rosbag2 writer with :class:`ThreadedMcapStorage` as its MCAP storage."""

    STORAGE_PLUGINS: Mapping[StoragePlugin, Callable[..., Any]] = {  # type: ignore[assignment]
        **Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: ThreadedMcapStorage}


__all__ = ["CHUNK_BYTES", "ZSTD_LEVEL", "BagWriterBackend", "ThreadedMcapStorage"]
