"""Reading MCAP files within bounds: no read past the file's end, no chunk decompressed beyond
its declared size or :data:`CHUNK_LIMIT`, no scan through zeros (docs/internals.md, "Bags")."""

from __future__ import annotations

import io
import os
import shutil
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.rosbag2 import storage_mcap
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import McapReader

#: Most bytes a chunk (or a compressed message) may declare or expand to. rosbag2 writes
#: chunks of 768 KiB and lidarcal of about 1 MiB; one chunk holds at least one message, and
#: a PointCloud2 of 10 million 48-byte points is 480 MB. Beyond this, a decompression bomb.
CHUNK_LIMIT = 1 << 30

#: MCAP opcodes 0x01-0x10 are records, 0x80-0xFF user records; the rest are reserved. Zeros
#: (a hole in a sparse file, a file padded or overwritten) read as opcode 0.
_RESERVED = frozenset(range(0x11, 0x80)) | {0x00}
_RECORD = struct.Struct("<BQ")


class BeyondLimitError(ReaderError):
    """A chunk or message that declares or expands to more than the bounds allow: refused,
    not damage to read up to."""


class BoundedFile(io.BufferedReader):
    """A binary file whose reads stop at the size it had when opened: a length read from a
    damaged record asks for at most what is there, not an allocation of its size (the
    reader then reports the record cut short)."""

    def __init__(self, path: Path) -> None:
        raw = io.FileIO(path, "rb")
        super().__init__(raw)
        self.size = os.fstat(raw.fileno()).st_size

    def read(self, size: int | None = -1, /) -> bytes:
        """At most ``size`` bytes, and never past the size the file had when opened."""
        left = max(0, self.size - self.tell())
        return super().read(left if size is None or size < 0 else min(size, left))


def _refuse_size(size: int, what: str) -> None:
    if size > CHUNK_LIMIT:
        raise BeyondLimitError(f"{what} declares {size} bytes uncompressed, more than the "
                          f"{CHUNK_LIMIT >> 20} MiB any chunk may hold (a decompression bomb?)")


def bounded_decompress(data: bytes | memoryview, compression: str, size: int, *,
                       what: str = "a chunk") -> bytes:
    """``data`` decompressed, refused if ``size`` (what its record declares) is beyond
    :data:`CHUNK_LIMIT` or the data expands beyond ``size``: the output buffer never grows
    past ``size`` + 1 bytes, whatever the compressed frames claim.

    Raises
    ------
    rosbags.rosbag2.errors.ReaderError
        Unknown compression, a size beyond the limit, or data that expands beyond it or
        fails to decompress.
    """
    _refuse_size(size, what)
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        from backports import zstd

        def make() -> Any:
            return zstd.ZstdDecompressor()
    elif compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        def make() -> Any:
            return lz4.frame.LZ4FrameDecompressor()
    else:
        raise ReaderError(f"Unsupported chunk compression {compression!r}.")
    out = bytearray()
    rest = bytes(data)
    try:
        while rest:  # concatenated frames, each bounded by what is left of ``size``
            decoder = make()
            out += decoder.decompress(rest, max_length=size + 1 - len(out))
            if len(out) > size:
                raise BeyondLimitError(f"{what} expands beyond {size} bytes (a decompression "
                                  "bomb?)")
            if not decoder.eof:
                raise ReaderError(f"the compressed data of {what} is cut short")
            rest = decoder.unused_data
    except ReaderError:
        raise
    except Exception as err:  # the decoders' own errors: corrupt data
        raise ReaderError(f"cannot decompress {what} ({compression}: {err})") from None
    return bytes(out)


def decompress_chunk(data: bytes | memoryview, compression: str, size: int, crc: int) -> bytes:
    """A chunk's records: :func:`bounded_decompress`, then its size and CRC (0: none)
    checked."""
    raw = bounded_decompress(data, compression, size)
    if len(raw) != size:
        raise ReaderError(f"Chunk size mismatch: expected {size} bytes, got {len(raw)}.")
    if crc and zlib.crc32(raw) != crc:
        raise ReaderError("Chunk checksum mismatch.")
    return raw


def decompress_file(source: Path, target: Path) -> None:
    """A zstd-compressed file (a rosbag2 bag of compression mode ``file``) decompressed to
    ``target`` block by block: memory stays small whatever the file expands to, and an
    expansion beyond the free space of ``target``'s file system (less 256 MiB) is refused."""
    from backports import zstd

    room = shutil.disk_usage(target.parent).free - (256 << 20)
    written = 0
    decoder = zstd.ZstdDecompressor()
    pending = b""
    try:
        with source.open("rb") as src, target.open("wb") as dst:
            while True:
                if decoder.eof:  # the end, or another frame
                    pending = decoder.unused_data or src.read(1 << 20)
                    if not pending:
                        return
                    decoder = zstd.ZstdDecompressor()
                elif decoder.needs_input and not pending:
                    pending = src.read(1 << 20)
                    if not pending:
                        raise ReaderError(f"{source}: compressed data cut short")
                out = decoder.decompress(pending, max_length=1 << 24)
                pending = b""
                written += len(out)
                if written > room:
                    raise BeyondLimitError(f"{source} expands beyond the {max(room, 0) >> 20} MiB "
                                      f"free beside {target.parent} (a decompression bomb?)")
                dst.write(out)
    except ReaderError:
        raise
    except Exception as err:  # the decoder's own errors: corrupt data
        raise ReaderError(f"{source}: cannot decompress ({err})") from None


def _bounded(compression: str) -> Any:
    def decompress(data: bytes, size: int) -> bytes:
        return bounded_decompress(data, compression, size)
    return decompress


# rosbags decompresses every chunk (on opening an unindexed file, scanning, reading) through
# this table, which it passes the declared size; its own entries ignore the size and grow the
# output as far as the data goes (a 3 GiB zstd bomb: 6 GB resident, a minute).
storage_mcap.DECOMPRESSORS.update({"zstd": _bounded("zstd"), "lz4": _bounded("lz4")})


def check_records(bio: BinaryIO, start: int, end: int, *, what: str) -> None:
    """Walk the records from ``start`` to ``end`` by their lengths (seeking, not reading
    them), refusing a reserved opcode or a record running past ``end``: before a library
    reads them one by one, which through the zeros of a sparse 50 GB file takes hours."""
    pos = start
    while pos < end:
        bio.seek(pos)
        head = bio.read(_RECORD.size)
        if len(head) < _RECORD.size:
            raise ReaderError(f"{what} cut short at offset {pos}")
        opcode, length = _RECORD.unpack(head)
        if opcode in _RESERVED:
            zeros = " (zeros: a hole or padding, not a recording)" if head == bytes(9) else ""
            raise ReaderError(f"no MCAP record at offset {pos} of the {what}: reserved "
                              f"opcode 0x{opcode:02x}{zeros}")
        pos += _RECORD.size + length
        if pos > end:
            raise ReaderError(f"a record at offset {pos - length - _RECORD.size} of the {what} "
                              f"runs {pos - end} bytes past its end")
        if opcode == 0x0F:  # data end: what follows is the summary, read on its own
            return


class BoundedMcapReader(McapReader):
    """rosbags' MCAP reader on a :class:`BoundedFile`, whose sections are walked by
    :func:`check_records` before rosbags reads them and whose chunk index is checked against
    the file and :data:`CHUNK_LIMIT` on opening."""

    def open(self) -> None:
        """Open the file and read its summary (or scan it), within bounds."""
        try:
            self.bio = BoundedFile(Path(str(self.path)))
        except OSError as err:
            raise ReaderError(f"Could not open file {str(self.path)!r}: {err.strerror}."
                              ) from err
        try:
            self._open()
            self._check_chunks()
        except BaseException:
            self.close()
            raise

    def read_index(self) -> None:
        """The summary section, checked first."""
        assert isinstance(self.bio, BoundedFile)
        check_records(self.bio, self.data_end, self.bio.size - 37, what="summary")  # footer: 37
        super().read_index()

    def meta_scan(self) -> None:
        """The data section of a file without a summary, checked first."""
        assert self.bio is not None
        check_records(self.bio, self.data_start, self.data_end, what="data section")
        super().meta_scan()

    def _check_chunks(self) -> None:
        assert isinstance(self.bio, BoundedFile)
        size = self.bio.size
        for chunk in self.chunks:
            where = f"the chunk at offset {chunk.chunk_start_offset}"
            _refuse_size(chunk.uncompressed_size, where)
            if (chunk.chunk_start_offset + chunk.chunk_length > size
                    or chunk.compressed_size > chunk.chunk_length):
                raise ReaderError(f"the chunk index places {where} ({chunk.chunk_length} "
                                  f"bytes) beyond the file's {size} bytes")


def chunk_records(stream: BinaryIO, *, limit: int) -> Iterator[Any]:
    """The records of an MCAP stream as the ``mcap`` library's stream reader gives them,
    chunks opened here (bounded by :func:`bounded_decompress`) and records of a reserved
    opcode taken as the end of the readable part (raises there)."""
    from mcap.exceptions import McapError
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    class _Reader(StreamReader):
        def _read_record(self, opcode: int, length: int) -> Any:
            if opcode in _RESERVED:
                raise McapError(f"no MCAP record at offset {stream.tell() - 9}: reserved "
                                f"opcode 0x{opcode:02x}")
            return super()._read_record(opcode, length)

    for record in _Reader(stream, emit_chunks=True, record_size_limit=limit).records:
        if isinstance(record, Chunk):
            data = bounded_decompress(record.data, record.compression, record.uncompressed_size)
            if record.uncompressed_crc and zlib.crc32(data) != record.uncompressed_crc:
                raise McapError("chunk checksum mismatch")
            if len(data) != record.uncompressed_size:
                raise McapError(f"chunk size mismatch: declared {record.uncompressed_size} "
                                f"bytes, holds {len(data)}")
            yield from breakup_chunk(Chunk(
                compression="", data=data, message_start_time=record.message_start_time,
                message_end_time=record.message_end_time,
                uncompressed_crc=0, uncompressed_size=len(data)))
        else:
            yield record


__all__ = ["CHUNK_LIMIT", "BeyondLimitError", "BoundedFile", "BoundedMcapReader",
           "bounded_decompress", "check_records", "chunk_records", "decompress_chunk",
           "decompress_file"]
