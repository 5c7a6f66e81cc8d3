"""Reading the messages of an indexed MCAP file chunk by chunk, decompressed ahead in threads.

docs/internals.md, "Bags".
"""

from __future__ import annotations

import heapq
import itertools
import os
import struct
from collections import deque
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor

from rosbags.rosbag2.storage_mcap import ChunkInfo, McapReader

from lidarcal_ros.io.bag.mcap_bounds import decompress_chunk

#: Threads decompressing chunks, and chunks decompressed ahead of the caller.
DECOMPRESS_THREADS = min(2, os.cpu_count() or 1)
CHUNKS_AHEAD = 4

_RECORD = struct.Struct("<BQ")  # opcode, length
_MESSAGE = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time


def in_time_order(chunks: Sequence[ChunkInfo]) -> bool:
    """Whether every chunk (in file order) starts no earlier than the one before it ends."""
    return all(b.message_start_time >= a.message_end_time
               for a, b in itertools.pairwise(chunks))


def chunk_messages(reader: McapReader, channels: set[int]
                   ) -> Iterator[tuple[int, int, bytes]] | None:
    """``(channel id, log time ns, message bytes)`` of the messages on ``channels``, in
    log-time order, as rosbags' reader gives them (equal times in the order of their chunks
    in the file, then in the chunk); None where this way does not apply (no chunk index)."""
    if not reader.chunks:
        return None
    chunks = [c for c in reader.chunks if any(c.channel_count.get(k, 0) for k in channels)]
    if in_time_order(reader.chunks):
        return _in_order(reader, chunks, channels)
    return _merged(reader, chunks, channels)


def _chunk_bytes(reader: McapReader, chunk: ChunkInfo) -> tuple[bytes, int]:
    """A chunk's compressed data and the CRC of its uncompressed data (0: none)."""
    bio = reader.bio
    assert bio is not None
    bio.seek(chunk.chunk_start_offset + 9 + 24)
    (crc,) = struct.unpack("<I", bio.read(4))
    bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
    data = bio.read(chunk.compressed_size)
    if len(data) != chunk.compressed_size:
        raise EOFError(f"chunk at {chunk.chunk_start_offset} cut short")
    return data, crc


def _decompressed(reader: McapReader, chunks: list[ChunkInfo]
                  ) -> Iterator[tuple[ChunkInfo, bytes]]:
    """Each of ``chunks`` in turn with its decompressed data, decompressed ahead in
    threads."""
    pool = ThreadPoolExecutor(max_workers=DECOMPRESS_THREADS,
                              thread_name_prefix="lidarcal-unzstd")
    ahead: deque[tuple[ChunkInfo, Future[bytes]]] = deque()
    todo = iter(chunks)
    try:
        while True:
            while len(ahead) < CHUNKS_AHEAD:
                chunk = next(todo, None)
                if chunk is None:
                    break
                data, crc = _chunk_bytes(reader, chunk)
                ahead.append((chunk, pool.submit(decompress_chunk, data, chunk.compression,
                                                 chunk.uncompressed_size, crc)))
            if not ahead:
                return
            chunk, future = ahead.popleft()
            yield chunk, future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _in_order(reader: McapReader, chunks: list[ChunkInfo], channels: set[int]
              ) -> Iterator[tuple[int, int, bytes]]:
    """Chunks that follow each other in time: their messages chunk after chunk."""
    for _chunk, data in _decompressed(reader, chunks):
        yield from _records(data, channels)


def _merged(reader: McapReader, chunks: list[ChunkInfo], channels: set[int]
            ) -> Iterator[tuple[int, int, bytes]]:
    """Chunks that overlap in time: their messages merged by (log time, chunk offset in
    the file, place in the chunk), the order of rosbags' and the ``mcap`` library's
    readers.

    The chunks are decompressed in the order of their first message; a chunk joins the
    merge when its first message time is reached, so only the chunks open at one time are
    held (a copied input chunk and a new one beside it, in a corrected bag)."""
    order = sorted(chunks, key=lambda c: (c.message_start_time, c.chunk_start_offset))
    loaded = _decompressed(reader, order)
    pending = next(loaded, None)
    # (log time of the chunk's next message, chunk offset, index of it, the chunk's messages)
    heap: list[tuple[int, int, int, list[tuple[int, int, bytes]]]] = []
    while True:
        while pending is not None and (not heap or pending[0].message_start_time <= heap[0][0]):
            chunk, data = pending
            messages = _records(data, channels)
            if messages:
                heapq.heappush(heap, (messages[0][1], chunk.chunk_start_offset, 0, messages))
            pending = next(loaded, None)
        if not heap:
            return
        _, offset, index, messages = heap[0]
        yield messages[index]
        index += 1
        if index < len(messages):
            heapq.heapreplace(heap, (messages[index][1], offset, index, messages))
        else:
            heapq.heappop(heap)


def _records(buf: bytes, channels: set[int]) -> list[tuple[int, int, bytes]]:
    """The message records of a decompressed chunk on ``channels``, sorted by log time."""
    out = []
    view = memoryview(buf)
    pos, end = 0, len(buf)
    while pos < end:
        op, length = _RECORD.unpack_from(buf, pos)
        body = pos + 9
        pos = body + length
        if pos > end:
            raise EOFError("a record runs past the end of its chunk")
        if op == 0x05:
            channel, _seq, log_time, _publish = _MESSAGE.unpack_from(buf, body)
            if channel in channels:
                out.append((channel, log_time, bytes(view[body + 22:pos])))
    out.sort(key=lambda m: m[1])
    return out


__all__ = ["chunk_messages", "in_time_order"]
