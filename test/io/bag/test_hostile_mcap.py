"""MCAP files built to harm: decompression bombs, lying chunk headers, sparse zeros, files cut
while they are read. Each is refused in one line, in bounded memory and time."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import helpers_mcap as mc
import pytest
from helpers_cli import one_line_error, run_process

from lidarcal_ros.errors import BagError
from lidarcal_ros.io.bag.mcap_bounds import CHUNK_LIMIT, bounded_decompress
from lidarcal_ros.io.bag.reader import BagReader, ReadableMcap

GIB = 1 << 30

#: What reading a small bag costs (interpreter, numpy, rosbags): some 100-150 MB resident. A
#: bomb decompressed would add its 2-3 GiB.
MEMORY_BOUND_MB = 400


def _read_in_child(path: Path) -> tuple[str, float, float]:
    """Open ``path`` and read every message in a fresh interpreter: its one-line answer
    ('read N' or the BagError), seconds, and peak resident MB (VmHWM: its own; getrusage's
    maxrss keeps the larger peak of the test process it was forked from)."""
    code = (
        "import re\n"
        "from lidarcal_ros.errors import BagError\n"
        "from lidarcal_ros.io.bag.reader import BagReader\n"
        "try:\n"
        f"    with BagReader({str(path)!r}) as bag:\n"
        "        print('read', sum(1 for _ in bag.messages()))\n"
        "except BagError as e:\n"
        "    print(e)\n"
        "status = open('/proc/self/status').read()\n"
        "print(int(re.search(r'VmHWM:\\s*(\\d+)', status).group(1)) / 1024)\n")
    start = time.monotonic()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, cwd=Path(__file__).parents[3]).stdout
    seconds = time.monotonic() - start
    answer, peak = out.strip().splitlines()
    return answer, seconds, float(peak)


BOMBS = {
    "zstd declaring 3 GiB": lambda: [mc.Chunk(mc.zstd_zeros(3 * GIB), "zstd", 3 * GIB)],
    "lz4 declaring 2 GiB": lambda: [mc.Chunk(mc.lz4_zeros(2 * GIB), "lz4", 2 * GIB)],
}
LIARS = {
    # Headers that claim 1000 bytes of what expands to GiBs: the decoders' output is bounded.
    "zstd expanding to 3 GiB": lambda: [mc.Chunk(mc.zstd_zeros(3 * GIB, declared=1000), "zstd",
                                                 1000)],
    "zstd frame without its size": lambda: [mc.Chunk(mc.zstd_zeros(3 * GIB, declared=0), "zstd",
                                                     1000)],
    "lz4 expanding to 2 GiB": lambda: [mc.Chunk(mc.lz4_zeros(2 * GIB), "lz4", 1000)],
}


@pytest.mark.parametrize("summary", [True, False], ids=["indexed", "unindexed"])
@pytest.mark.parametrize("bomb", list(BOMBS))
def test_a_chunk_declaring_gibs_is_refused_before_decompressing(tmp_path: Path, bomb: str,
                                                                summary: bool) -> None:
    path = tmp_path / "bomb.mcap"
    path.write_bytes(mc.mcap_file(BOMBS[bomb](), summary=summary))
    answer, seconds, peak = _read_in_child(path)
    declared = 3 * GIB if bomb.startswith("zstd") else 2 * GIB
    where = "the chunk at offset 138" if summary else "a chunk"
    assert answer == (f"{path}: {where} declares {declared} bytes uncompressed, more than the "
                      "1024 MiB any chunk may hold (a decompression bomb?); refused")
    assert seconds < 20
    assert peak < MEMORY_BOUND_MB


@pytest.mark.parametrize("liar", list(LIARS))
def test_a_chunk_expanding_beyond_its_header_is_refused_in_bounded_memory(tmp_path: Path,
                                                                           liar: str) -> None:
    path = tmp_path / "liar.mcap"
    path.write_bytes(mc.mcap_file(LIARS[liar]()))
    answer, seconds, peak = _read_in_child(path)
    assert answer.startswith(f"{path}: ")
    assert ("expands beyond 1000 bytes (a decompression bomb?); refused" in answer
            or "truncated or corrupt MCAP (cannot decompress a chunk" in answer), answer
    assert seconds < 20
    assert peak < MEMORY_BOUND_MB


def test_bounded_decompress_keeps_honest_chunks_and_refuses_the_rest() -> None:
    records = b"lidar" * 10_000
    for compression in ("zstd", "lz4", ""):
        chunk = mc.chunk_of(records, compression)
        assert bounded_decompress(chunk.data, compression, len(records)) == records
    two_frames = mc.chunk_of(records[:20], "zstd").data + mc.chunk_of(records[20:], "zstd").data
    assert bounded_decompress(two_frames, "zstd", len(records)) == records
    with pytest.raises(Exception, match="expands beyond 49999 bytes"):
        bounded_decompress(mc.chunk_of(records).data, "zstd", len(records) - 1)
    with pytest.raises(Exception, match="more than the 1024 MiB"):
        bounded_decompress(b"", "zstd", CHUNK_LIMIT + 1)
    with pytest.raises(Exception, match="is cut short"):
        bounded_decompress(mc.chunk_of(records).data[:-5], "zstd", len(records))
    with pytest.raises(Exception, match="Unsupported chunk compression 'bz2'"):
        bounded_decompress(b"x", "bz2", 1)


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_honest_bags_of_each_compression_are_read(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "ok.mcap"
    path.write_bytes(mc.valid_mcap(5, compression))
    with BagReader(path) as bag:
        got = [(topic, t) for topic, _type, t, _raw in bag.messages()]
    assert got == [(mc.TOPIC, 1_000_000_000 + k) for k in range(5)]
    assert [m.data for _c, _s, m in ReadableMcap(path).messages()] == \
        [mc.string_message(f"hello {k}") for k in range(5)]


def _sparse(path: Path, head: bytes, tail: bytes = b"", size: int = 50 * GIB) -> None:
    """``head``, then zeros (a hole, costing no disk) up to ``size`` bytes, then ``tail``."""
    with path.open("wb") as f:
        f.write(head)
        f.truncate(size - len(tail))
        f.seek(size - len(tail))
        f.write(tail)


def _footer(summary_start: int) -> bytes:
    import struct

    return mc.record(0x02, struct.pack("<QQI", summary_start, 0, 0)) + mc.MAGIC


@pytest.mark.parametrize("tail", ["zeros", "a footer without summary", "a summary of zeros"])
def test_a_sparse_50_gib_file_is_refused_in_seconds(tmp_path: Path, tail: str) -> None:
    """Zeros read as records of opcode 0 and length 0, nine bytes at a time: hours of
    reading for 50 GiB, now refused at the first of them."""
    head = mc.valid_mcap(1)[:42]  # magic and header record: a valid start
    path = tmp_path / "sparse.mcap"
    ends = {"zeros": b"", "a footer without summary": _footer(0),
            "a summary of zeros": _footer(100)}
    _sparse(path, head, ends[tail])
    if os.stat(path).st_blocks * 512 > 1 << 24:
        pytest.skip("the file system does not keep sparse files")
    answer, seconds, peak = _read_in_child(path)
    assert seconds < 20
    assert peak < MEMORY_BOUND_MB
    assert answer.startswith(f"{path}: truncated or corrupt MCAP (")
    if tail != "zeros":
        section = "data section" if tail == "a footer without summary" else "summary"
        offset = 42 if section == "data section" else 100
        assert (f"no MCAP record at offset {offset} of the {section}: reserved opcode 0x00 "
                "(zeros: a hole or padding, not a recording)") in answer


def test_a_chunk_index_pointing_past_the_end_is_refused(tmp_path: Path) -> None:
    data = bytearray(mc.valid_mcap(3))
    # The chunk index's chunk_length (after its times and offset) made 1 TB.
    index = data.rindex(b"\x08", 0, len(data) - 60)
    while data[index + 9 + 16:index + 9 + 24] != (138).to_bytes(8, "little"):
        index = data.rindex(b"\x08", 0, index)
    data[index + 9 + 24:index + 9 + 32] = (10**12).to_bytes(8, "little")
    path = tmp_path / "index.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r"the chunk index places the chunk at offset 138 "
                                       r"\(1000000000000 bytes\) beyond the file's"):
        BagReader(path)


def test_a_record_claiming_more_than_the_file_is_not_allocated(tmp_path: Path) -> None:
    """The summary's schema record with a length of 1 TB: reads stop at the file's end."""
    data = bytearray(mc.valid_mcap(3))
    summary = int.from_bytes(data[-37 + 9:-37 + 17], "little")
    assert data[summary] == 0x03
    data[summary + 1:summary + 9] = (10**12).to_bytes(8, "little")
    path = tmp_path / "record.mcap"
    path.write_bytes(bytes(data))
    answer, seconds, peak = _read_in_child(path)
    assert answer.startswith(f"{path}: truncated or corrupt MCAP (")
    assert peak < MEMORY_BOUND_MB
    assert seconds < 20


def test_a_bomb_refused_by_the_cli_leaves_no_output(tmp_path: Path) -> None:
    path = tmp_path / "bomb.mcap"
    path.write_bytes(mc.mcap_file(BOMBS["zstd declaring 3 GiB"]()))
    out = tmp_path / "calibration.yaml"
    done = run_process("calibrate", path, "-o", out, cwd=Path(__file__).parents[3])
    reason = one_line_error(done.returncode, done.stderr)
    assert reason.endswith("(a decompression bomb?); refused")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bomb.mcap"]


def test_a_file_cut_while_it_is_read_names_the_file(tmp_path: Path) -> None:
    """Opened whole, then truncated under the reader (a copy still arriving, a disk
    failing): the reads come short and the reader says so, naming the file."""
    chunks = []
    for k in range(12):  # more than the reader decompresses ahead, beyond its file buffer
        records = b"".join(mc.message_record(1_000_000_000 + k,
                                             mc.string_message(os.urandom(500).hex()))
                           for _ in range(20))
        chunk = mc.chunk_of(records)
        chunk.start = chunk.end = 1_000_000_000 + k
        chunks.append(chunk)
    path = tmp_path / "cut.mcap"
    path.write_bytes(mc.mcap_file(chunks))
    with BagReader(path) as bag:
        messages = bag.messages()
        next(messages)
        with path.open("r+b") as f:
            f.truncate(200)
        with pytest.raises(BagError) as raised:
            list(messages)
    assert str(raised.value).startswith(f"{path}: truncated or corrupt MCAP (")
    assert "\n" not in str(raised.value)


def test_a_file_compressed_bag_expanding_beyond_the_disk_is_refused(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bag of compression mode 'file': decompressed to disk block by block, never whole in
    memory, and refused when it would fill the disk (here: a disk of 300 MiB free)."""
    import shutil

    import yaml

    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap.zstd").write_bytes(mc.zstd_zeros(2 * GIB))
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "storage_identifier": "mcap", "relative_file_paths": ["bag_0.mcap.zstd"],
        "compression_mode": "file", "compression_format": "zstd"}}))
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage",
                        lambda _p: usage._replace(free=300 << 20))
    with pytest.raises(BagError, match=r"bag_0.mcap.zstd expands beyond the 44 MiB free beside "
                                       r".* \(a decompression bomb\?\); refused"):
        BagReader(bag)
