"""The MCAP storage of the bags lidarcal writes: rosbags' writer, its chunks compressed in threads.

The compression level and the checksum: docs/internals.md, "Bags".
"""

from __future__ import annotations

import os
import sys
from collections import defaultdict, deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
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
ZSTD_LEVEL = -3
#: Threads compressing chunks (two cores: the numerics and the reading take the rest).
COMPRESS_THREADS = min(2, os.cpu_count() or 1)
#: Closed chunks that may wait for their compression before the writer waits for the oldest.
MAX_PENDING = 8
#: Messages up to this size are copied into the chunk's small records; larger ones are kept
#: as parts of it, by reference.
_SMALL_BYTES = 4096

_ZSTD_OPTIONS: dict[int, int] = {zstd.CompressionParameter.compression_level: ZSTD_LEVEL,
                                 zstd.CompressionParameter.checksum_flag: 1}

Buffer = bytes | bytearray | memoryview


def compress_parts(parts: Sequence[Buffer], size: int) -> bytes:
    """One zstd frame of the concatenation of ``parts`` (``size`` bytes in all: written into
    the frame's header, as a one-shot compression would), compressed straight from them."""
    compressor = zstd.ZstdCompressor(options=_ZSTD_OPTIONS)
    compressor.set_pledged_input_size(size)
    out = [compressor.compress(part) for part in parts]
    out.append(compressor.flush())
    return b"".join(out)


@dataclass
class _Chunk:
    """A closed chunk: its records' parts and what its index needs."""

    start: int
    end: int
    size: int
    msgs: dict[int, list[tuple[int, int]]]
    parts: list[Buffer] = field(default_factory=list)


def chunk_index_record(start: int, end: int, offset: int, length: int,
                       message_indexes: Sequence[tuple[int, int]], index_length: int,
                       compression: str, compressed_size: int, uncompressed_size: int
                       ) -> BytesIO:
    """The body of a chunk's Chunk Index record (MCAP, opcode 0x08), as rosbags' writer
    keeps them for the summary: message log times ``start`` to ``end`` (ns), the chunk
    record's file ``offset`` and ``length``, ``(channel id, file offset)`` of each of its
    message index records and their total ``index_length`` (bytes), its compression and
    sizes."""
    rec = BytesIO()
    write_uint64(rec, start)
    write_uint64(rec, end)
    write_uint64(rec, offset)
    write_uint64(rec, length)
    write_uint32(rec, len(message_indexes) * 10)
    for cid, index_offset in message_indexes:
        write_uint16(rec, cid)
        write_uint64(rec, index_offset)
    write_uint64(rec, index_length)
    write_string(rec, compression)
    write_uint64(rec, compressed_size)
    write_uint64(rec, uncompressed_size)
    return rec


class ThreadedMcapStorage(McapWriter):
    """rosbags' MCAP storage writer whose chunks are lists of parts compressed in threads
    (docs/internals.md, "Bags"); the records it writes are rosbags'."""

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        super().__init__(path, compression)
        self._pool: ThreadPoolExecutor | None = None
        if self.compression:
            self._pool = ThreadPoolExecutor(max_workers=COMPRESS_THREADS,
                                            thread_name_prefix="lidarcal-mcap")
        self._pending: deque[tuple[_Chunk, Future[bytes] | None]] = deque()
        self._parts: list[Buffer] = []
        self._small = bytearray()  # small records, copied, after the last part
        self._size = 0

    def _take_small(self) -> None:
        if self._small:
            self._parts.append(bytes(self._small))
            self._small.clear()

    def _take_records(self) -> None:
        """Schema and channel records rosbags wrote into the chunk's buffer (its
        ``add_msgtype`` / ``add_connection``), in their place among the messages."""
        bio = self.chunk.bio
        if bio.tell():
            self._small += bio.getbuffer()
            self._size += bio.tell()
            self.chunk.bio = BytesIO()

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        """Append a message record to the open chunk (rosbags' record; the message's bytes
        kept by reference), closing the chunk past :data:`CHUNK_BYTES`."""
        self.message_start_time = min(timestamp, self.message_start_time)
        self.message_end_time = max(timestamp, self.message_end_time)
        self.channel_stats[connection.id] += 1
        chunk = self.chunk
        chunk.message_start_time = min(timestamp, chunk.message_start_time)
        chunk.message_end_time = max(timestamp, chunk.message_end_time)
        self._take_records()
        chunk.msgs[connection.id].append((timestamp, self._size))
        size = memoryview(data).nbytes
        small = self._small
        small += b"\x05"
        small += (22 + size).to_bytes(8, "little")
        small += connection.id.to_bytes(2, "little")
        small += b"\x00\x00\x00\x00"
        stamp = timestamp.to_bytes(8, "little")
        small += stamp
        small += stamp
        if size <= _SMALL_BYTES:
            small += data
        else:
            self._take_small()
            self._parts.append(data)
        self._size += 31 + size  # op, length, channel, sequence, two times: 31 bytes
        if self._size > CHUNK_BYTES:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Hand the open chunk to the compression threads and start a new one; write the
        chunks whose compression is done (waiting for the oldest past :data:`MAX_PENDING`)."""
        self._take_records()
        self._take_small()
        old = self.chunk
        chunk = _Chunk(old.message_start_time, old.message_end_time, self._size, old.msgs,
                       self._parts)
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        self._parts, self._size = [], 0
        future = None if self._pool is None else self._pool.submit(
            compress_parts, chunk.parts, chunk.size)
        self._pending.append((chunk, future))
        self._write_finished(wait=len(self._pending) > MAX_PENDING)

    def _write_finished(self, *, wait: bool = False, everything: bool = False) -> None:
        while self._pending:
            chunk, future = self._pending[0]
            if future is not None and not future.done() and not (wait or everything):
                return
            self._pending.popleft()
            self._write_chunk(chunk, b"".join(chunk.parts) if future is None
                              else future.result())
            wait = False

    def _write_chunk(self, chunk: _Chunk, data: bytes) -> None:
        """The chunk record (its data written as it is, not copied into the record first),
        its message indexes and its chunk index entry, as rosbags' ``close_chunk`` writes
        them."""
        head = BytesIO()
        write_uint64(head, chunk.start)
        write_uint64(head, chunk.end)
        write_uint64(head, chunk.size)
        write_uint32(head, 0)
        write_string(head, self.compression)
        write_uint64(head, len(data))

        bio = self.bio
        chunk_start = bio.tell()
        bio.write(b"\x06")
        write_uint64(bio, head.tell() + len(data))
        bio.write(head.getbuffer())
        bio.write(data)
        chunk_end = bio.tell()

        offsets: list[tuple[int, int]] = []
        for cid, msgs in chunk.msgs.items():
            offsets.append((cid, bio.tell()))
            rec = BytesIO()
            write_uint16(rec, cid)
            write_uint32(rec, len(msgs) * 16)
            for ts, offset in msgs:
                write_uint64(rec, ts)
                write_uint64(rec, offset)
            write_record(bio, 0x07, rec)

        self.chunks.append(chunk_index_record(
            chunk.start, chunk.end, chunk_start, chunk_end - chunk_start, offsets,
            bio.tell() - chunk_end, self.compression, len(data), chunk.size))

    def close(self, version: int, metadata: str) -> None:
        """Write the last chunks, then rosbags' summary and footer."""
        try:
            if self._size or self.chunk.bio.tell():
                self.close_chunk()
            self._write_finished(everything=True)
        finally:
            self._stop()
        super().close(version, metadata)

    def abort(self) -> None:
        """Stop the compressing threads (chunks not yet compressed are dropped), then abort as
        rosbags does."""
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


__all__ = ["CHUNK_BYTES", "ZSTD_LEVEL", "BagWriterBackend", "ThreadedMcapStorage",
           "chunk_index_record", "compress_parts"]
