"""MCAP files built record by record, to be made hostile: chunks that lie, bombs, holes."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

MAGIC = b"\x89MCAP0\r\n"
SCHEMA = "std_msgs/msg/String"
TOPIC = "/chatter"

#: Most bytes one zstd block may expand to.
_ZSTD_BLOCK = 1 << 17


def _str(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def record(opcode: int, body: bytes) -> bytes:
    """One MCAP record: opcode, length, body."""
    return struct.pack("<BQ", opcode, len(body)) + body


def string_message(text: str) -> bytes:
    """CDR of a std_msgs/String."""
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


def message_record(log_time: int, data: bytes, *, channel: int = 1) -> bytes:
    """A Message record on ``channel``."""
    return record(0x05, struct.pack("<HIQQ", channel, 0, log_time, log_time) + data)


def zstd_zeros(size: int, *, declared: int | None = None) -> bytes:
    """A zstd frame of RLE blocks that expands to ``size`` zero bytes (some 4 bytes per
    128 KiB: a 3 GiB bomb in 100 kB, built at once), whose header declares ``declared``
    (default ``size``)."""
    out = bytearray(struct.pack("<I", 0xFD2FB528))
    # Not single-segment: a 1 MiB window (as a streaming compressor writes), so a decoder
    # streams it rather than refusing a frame-sized window.
    out += b"\xc0" + bytes([10 << 3]) + struct.pack("<Q", size if declared is None else declared)
    left = size
    while left > 0:
        n = min(left, _ZSTD_BLOCK)
        left -= n
        header = (1 if left == 0 else 0) | (1 << 1) | (n << 3)  # RLE block
        out += struct.pack("<I", header)[:3] + b"\x00"
    return bytes(out)


def lz4_zeros(size: int) -> bytes:
    """An LZ4 frame expanding to ``size`` zero bytes (about size/255 bytes of it)."""
    import lz4.frame  # type: ignore[import-untyped]

    compressor = lz4.frame.LZ4FrameCompressor(block_size=lz4.frame.BLOCKSIZE_MAX4MB)
    block = bytes(1 << 24)
    out = [compressor.begin()]
    left = size
    while left > 0:
        n = min(left, len(block))
        out.append(compressor.compress(block[:n]))
        left -= n
    out.append(compressor.flush())
    return b"".join(out)


@dataclass
class Chunk:
    """A chunk as it is written: its compressed bytes and what its header claims."""

    data: bytes
    compression: str
    uncompressed_size: int
    crc: int = 0
    start: int = 1_000_000_000
    end: int = 1_000_000_000
    count: int = 1


def chunk_of(records: bytes, compression: str = "zstd") -> Chunk:
    """An honest chunk of ``records``."""
    if compression == "zstd":
        from backports import zstd

        data = zstd.compress(records)
    elif compression == "lz4":
        import lz4.frame

        data = lz4.frame.compress(records)
    else:
        data = records
    return Chunk(data, compression, len(records), zlib.crc32(records))


def mcap_file(chunks: list[Chunk], *, summary: bool = True) -> bytes:
    """An MCAP file of the ros2 profile: header, a std_msgs/String schema and channel, the
    ``chunks``, and (with ``summary``) a chunk index and statistics in a summary section
    (without it, readers scan the data section)."""
    out = bytearray(MAGIC)
    out += record(0x01, _str("ros2") + _str("lidarcal test"))
    schema = record(0x03, struct.pack("<H", 1) + _str(SCHEMA) + _str("ros2msg")
                    + _str("string data"))
    channel = record(0x04, struct.pack("<HH", 1, 1) + _str(TOPIC) + _str("cdr")
                     + struct.pack("<I", 0))
    out += schema + channel
    indexes = []
    for chunk in chunks:
        offset = len(out)
        body = (struct.pack("<QQQI", chunk.start, chunk.end, chunk.uncompressed_size, chunk.crc)
                + _str(chunk.compression) + struct.pack("<Q", len(chunk.data)) + chunk.data)
        out += record(0x06, body)
        length = len(out) - offset
        index_offset = len(out)
        entries = b"".join(struct.pack("<QQ", chunk.start + k, 0) for k in range(chunk.count))
        out += record(0x07, struct.pack("<HI", 1, len(entries)) + entries)
        indexes.append(record(0x08, struct.pack("<QQQQ", chunk.start, chunk.end, offset, length)
                              + struct.pack("<I", 10) + struct.pack("<HQ", 1, index_offset)
                              + struct.pack("<Q", len(out) - index_offset)
                              + _str(chunk.compression)
                              + struct.pack("<QQ", len(chunk.data), chunk.uncompressed_size)))
    out += record(0x0F, struct.pack("<I", 0))
    summary_start = 0
    if summary:
        summary_start = len(out)
        out += schema + channel + b"".join(indexes)
        count = sum(c.count for c in chunks)
        stats = struct.pack("<QHIIIIQQ", count, 1, 1, 0, 0, len(chunks),
                            min((c.start for c in chunks), default=0),
                            max((c.end for c in chunks), default=0))
        out += record(0x0B, stats + struct.pack("<I", 10) + struct.pack("<HQ", 1, count))
    out += record(0x02, struct.pack("<QQI", summary_start, 0, 0))
    out += MAGIC
    return bytes(out)


def valid_mcap(messages: int = 3, compression: str = "zstd") -> bytes:
    """A small valid bag file: ``messages`` std_msgs/String messages in one chunk."""
    records = b"".join(message_record(1_000_000_000 + k, string_message(f"hello {k}"))
                       for k in range(messages))
    chunk = chunk_of(records, compression)
    chunk.end = 1_000_000_000 + messages - 1
    chunk.count = messages
    return mcap_file([chunk])
