"""``lidarcal correct`` to a bag copies the input's compressed chunks for the messages it
passes through (:mod:`lidarcal_ros.io.bag.chunk_copy`).

A small simulated mission is corrected twice, chunks copied and (forced) messages written one
by one; both outputs are read back by independent readers (the ``mcap`` library, rosbags'
AnyReader) and by lidarcal's BagReader, which must agree message for message, topic by
topic. Inputs that do not allow the copy (schema names without ``/msg/``, sqlite3) take the
message-by-message path.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import helpers_missions
import pytest
from helpers_missions import (
    MissionFiles,
    write_calibration_yaml,
    write_mcap_ros2_bag,
    write_params_file,
)

from lidarcal_ros.cli.main import main
from lidarcal_ros.io.bag.reader import ReadableMcap, open_bag
from lidarcal_ros.io.bag.writer import BagWriter

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

CORRECTED = "/lidar/points_corrected"
#: What :mod:`lidarcal_ros.io.bag.chunk_copy` logs when it leaves the chunks alone.
NOT_COPIED = "chunks not copied"

Messages = dict[str, list[tuple[int, bytes]]]


@contextmanager
def messages_one_by_one() -> Iterator[None]:
    """Correction as if no input allowed its chunks to be copied."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(BagWriter, "copy_chunks_of", lambda *_args, **_kw: None)
        yield


def correct(bag: Path, cal: Path, out: Path, *extra: str) -> None:
    assert main(["correct", str(bag), "--calibration", str(cal), "-o", str(out), *extra]) == 0


def assert_reads_as_one_by_one(bag: Path, cal: Path, work: Path) -> tuple[Any, Any]:
    """``work/out.mcap`` (corrected from ``bag``) reads back, through the mcap library, rosbags
    and BagReader, as ``bag`` corrected with every message written one by one
    (``work/reference.mcap``) does; the mcap library's messages by topic and their order."""
    with messages_one_by_one():
        correct(bag, cal, work / "reference.mcap")
    written, order = read_with_mcap(work / "out.mcap")
    reference, reference_order = read_with_mcap(work / "reference.mcap")
    assert written == reference and order == reference_order
    assert read_with_rosbags(work / "out.mcap") == reference
    assert read_with_bag_reader(work / "out.mcap") == order
    return written, order


def mcap_file(bag: Path) -> Path:
    return bag if bag.suffix == ".mcap" else bag / f"{bag.name}.mcap"


def read_with_mcap(path: Path) -> tuple[Messages, list[tuple[str, int, bytes]]]:
    """The ``mcap`` library's reading, in log-time order: messages by topic, and all of
    them in its order."""
    from mcap.reader import make_reader

    by_topic: Messages = defaultdict(list)
    order = []
    with mcap_file(path).open("rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            by_topic[channel.topic].append((message.log_time, bytes(message.data)))
            order.append((channel.topic, message.log_time, bytes(message.data)))
    return dict(by_topic), order


def read_with_rosbags(path: Path) -> Messages:
    from rosbags.highlevel import AnyReader

    by_topic: Messages = defaultdict(list)
    with AnyReader([path]) as reader:
        for connection, log_time, raw in reader.messages():
            by_topic[connection.topic].append((log_time, bytes(raw)))
    return dict(by_topic)


def read_with_bag_reader(path: Path) -> list[tuple[str, int, bytes]]:
    with open_bag(path) as bag:
        return [(topic, log_time, bytes(raw)) for topic, _t, log_time, raw in bag.messages()]


def summary(path: Path) -> Any:
    from mcap.reader import make_reader

    with mcap_file(path).open("rb") as f:
        return make_reader(f).get_summary()


def chunk_data(path: Path) -> list[tuple[str, bytes, set[str]]]:
    """Every chunk of an MCAP file: its compression, compressed bytes and the topics of its
    messages (by the chunk index)."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    info = summary(path)
    out = []
    with mcap_file(path).open("rb") as f:
        for index in info.chunk_indexes:
            f.seek(index.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(f))
            topics = {info.channels[c].topic for c in index.message_index_offsets}
            out.append((chunk.compression, bytes(chunk.data), topics))
    return out


@pytest.fixture(scope="module")
def outputs(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory,
            ) -> dict[str, Path]:
    """The small mission corrected with its true biases to .mcap and to a rosbag2 directory,
    chunks copied and messages one by one."""
    work = tmp_path_factory.mktemp("chunk-copy")
    cal = write_calibration_yaml(work / "cal.yaml", small_mission.sim.biases)
    out = {"cal": cal, "work": work}
    for name in ("copied.mcap", "copied"):
        out[name] = work / name
        correct(small_mission.bag, cal, out[name])
    with messages_one_by_one():
        for name in ("one_by_one.mcap", "one_by_one"):
            out[name] = work / name
            correct(small_mission.bag, cal, out[name])
    return out


def test_copied_output_holds_the_same_messages_for_every_reader(
        outputs: dict[str, Path]) -> None:
    copied, order = read_with_mcap(outputs["copied.mcap"])
    reference, reference_order = read_with_mcap(outputs["one_by_one.mcap"])
    assert set(copied) == {"/lidar/control_points", "/lidar/trajectory", "/lidar/points",
                           CORRECTED}
    assert copied == reference
    assert order == reference_order
    # rosbags, and lidarcal's reader merging the copied chunks with the new ones
    assert read_with_rosbags(outputs["copied.mcap"]) == reference
    assert read_with_bag_reader(outputs["copied.mcap"]) == order
    assert read_with_rosbags(outputs["copied"]) == reference
    assert read_with_bag_reader(outputs["copied"]) == order


def test_copied_chunks_are_the_inputs(small_mission: MissionFiles,
                                      outputs: dict[str, Path]) -> None:
    """Every chunk of the input is in the output as it was; the other chunks hold only the
    corrected clouds."""
    inputs = {data for _c, data, _t in chunk_data(small_mission.bag)}
    chunks = chunk_data(outputs["copied.mcap"])
    copied = [topics for _c, data, topics in chunks if data in inputs]
    new = [topics for _c, data, topics in chunks if data not in inputs]
    assert len(copied) == len(inputs)
    assert new and all(topics == {CORRECTED} for topics in new)
    assert {compression for compression, _d, _t in chunks} == {"zstd"}


def test_summary_and_metadata_match_messages_one_by_one(outputs: dict[str, Path]) -> None:
    """Channels, schemas, statistics and rosbag2's metadata.yaml (counts, QoS, times)."""
    from ruamel.yaml import YAML

    copied, reference = summary(outputs["copied.mcap"]), summary(outputs["one_by_one.mcap"])
    assert copied.channels == reference.channels
    assert copied.schemas == reference.schemas
    for field in ("message_count", "channel_message_counts", "message_start_time",
                  "message_end_time", "schema_count", "channel_count"):
        assert getattr(copied.statistics, field) == getattr(reference.statistics, field)
    # every message is in exactly one chunk of the index
    counts: dict[int, int] = defaultdict(int)
    for index in copied.chunk_indexes:
        assert index.message_index_length > 0
    with open_bag(outputs["copied.mcap"]) as bag:
        (reader,) = bag.indexed_files() or []
        for chunk in reader.chunks:
            for cid, n in chunk.channel_count.items():
                counts[cid] += n
    assert counts == copied.statistics.channel_message_counts

    def metadata(bag: Path) -> dict[str, Any]:
        info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())
        info = info["rosbag2_bagfile_information"]
        for key in ("relative_file_paths", "files"):
            info.pop(key)
        return dict(info)

    assert metadata(outputs["copied"]) == metadata(outputs["one_by_one"])


def test_copied_output_corrected_again(outputs: dict[str, Path], caplog: Any) -> None:
    """A bag written by the copy is itself copied (its chunks overlap in time) when corrected
    again into another topic: the same clouds come out."""
    work = outputs["work"]
    again = work / "again.mcap"
    config = write_params_file(work / "again.yaml",
                               {"topics.corrected": "/lidar/points_corrected_again"})
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(outputs["copied.mcap"], outputs["cal"], again, "--config", str(config))
    assert NOT_COPIED not in caplog.text
    first, _ = read_with_mcap(outputs["copied.mcap"])
    second, order = read_with_mcap(again)
    assert second.pop("/lidar/points_corrected_again") == first[CORRECTED]
    assert second == first
    assert read_with_bag_reader(again) == order
    assert read_with_rosbags(again) == {**first, "/lidar/points_corrected_again":
                                        first[CORRECTED]}


def test_input_without_normalised_schema_names_is_written_one_by_one(
        small_mission: MissionFiles, outputs: dict[str, Path], tmp_path: Path,
        caplog: Any) -> None:
    """Schema names without ``/msg/`` (the ``mcap_ros2`` writer's): the output's records
    would not be the input's, so nothing is copied; the messages are passed through as
    written one by one."""
    bag = write_mcap_ros2_bag(tmp_path / "foreign.mcap", small_mission.mission)
    out = tmp_path / "out.mcap"
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(bag, outputs["cal"], out)
    assert NOT_COPIED in caplog.text and "normalised type name" in caplog.text
    written, _ = read_with_mcap(out)
    source, _ = read_with_mcap(bag)
    assert {t: m for t, m in written.items() if t != CORRECTED} == source
    assert len(written[CORRECTED]) == len(source["/lidar/points"])
    assert not {data for _c, data, _t in chunk_data(bag)} & {
        data for _c, data, _t in chunk_data(out)}


def test_sqlite_input_is_refused_as_before(outputs: dict[str, Path], tmp_path: Path,
                                           capsys: Any) -> None:
    db3 = tmp_path / "mission.db3"
    db3.write_bytes(b"SQLite format 3\x00" + b"\0" * 100)
    assert main(["correct", str(db3), "--calibration", str(outputs["cal"]),
                 "-o", str(tmp_path / "out.mcap")]) != 0
    assert "sqlite3 storage is not supported" in capsys.readouterr().err
    assert not (tmp_path / "out.mcap").exists()


def split_bag(source: Path, bagdir: Path, layout: str) -> Path:
    """``source`` rewritten as a rosbag2 directory of two MCAP files, cut at the middle of
    its time span; ``layout``: ``same_ids`` (both files number the topics alike),
    ``reordered`` (the second in the reverse order), ``empty_topic`` (the second has one
    more topic, without messages)."""
    bagdir.mkdir()
    with open_bag(source) as bag:
        topics = dict(bag.topics)
        messages = list(bag.messages())
        middle = (bag.start_ns + bag.end_ns) // 2
    latched = [t for t, info in topics.items() if info.transient_local]
    for k, name in enumerate(("split_0.mcap", "split_1.mcap")):
        with BagWriter(bagdir / name, latched_topics=latched) as writer:
            for topic in sorted(topics, reverse=k == 1 and layout == "reordered"):
                writer.add_topic(topic, topics[topic].msgtype)
            if k == 1 and layout == "empty_topic":
                writer.add_topic("/empty", "std_msgs/msg/String")
            for topic, msgtype, log_time, raw in messages:
                if (log_time >= middle) == (k == 1):
                    writer.write_raw(topic, msgtype, log_time, raw)
    (bagdir / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n"
        "  relative_file_paths: [split_0.mcap, split_1.mcap]\n  compression_mode: ''\n"
        "  compression_format: ''\n  topics_with_message_count: []\n")
    return bagdir


@pytest.mark.parametrize("layout", ["same_ids", "reordered", "empty_topic"])
def test_bag_of_several_files(small_mission: MissionFiles, outputs: dict[str, Path],
                              tmp_path: Path, caplog: Any, layout: str) -> None:
    """The files' chunks are copied when their channel ids agree (a channel without
    messages too: its record is in a chunk, and its id is not free for the corrected
    clouds); else the messages are written one by one. Either way the output holds what
    writing them one by one gives."""
    bag = split_bag(small_mission.bag, tmp_path / "split", layout)
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(bag, outputs["cal"], tmp_path / "out.mcap")
    assert (NOT_COPIED in caplog.text) == (layout != "same_ids")
    written, _order = assert_reads_as_one_by_one(bag, outputs["cal"], tmp_path)
    # the corrected clouds are those of the mission in one file
    assert written[CORRECTED] == read_with_mcap(outputs["copied.mcap"])[0][CORRECTED]


def rewrite_with_mcap(source: Path, bag: Path, compression: str, *,
                      unknown_topic: bool = False) -> Path:
    """The messages of ``source`` rewritten by the ``mcap`` library's writer (``compression``:
    lz4, zstd, none); ``unknown_topic`` adds a topic of a type without a definition."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with mcap_file(source).open("rb") as f, bag.open("wb") as out:
        reader = make_reader(f)
        info = reader.get_summary()
        assert info is not None
        writer = Writer(out, compression=CompressionType[compression.upper()])
        writer.start(profile="ros2", library="test")
        for schema in info.schemas.values():
            writer.register_schema(schema.name, schema.encoding, schema.data)
        for channel in info.channels.values():
            writer.register_channel(channel.topic, channel.message_encoding,
                                    channel.schema_id, channel.metadata)
        unknown = 0
        if unknown_topic:
            unknown = writer.register_channel(
                "/unknown", "cdr", writer.register_schema("my_pkg/msg/Thing", "ros2msg", b""))
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            writer.add_message(channel.id, message.log_time, message.data,
                               message.publish_time)
            if unknown:
                writer.add_message(unknown, message.log_time, b"\0\1\0\0", message.log_time)
        writer.finish()
    return bag


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_chunks_of_other_compressions(small_mission: MissionFiles, outputs: dict[str, Path],
                                      tmp_path: Path, caplog: Any, compression: str) -> None:
    """lz4 and uncompressed chunks (of the ``mcap`` library's writer) are copied as they
    are, and read back by every reader."""
    bag = rewrite_with_mcap(small_mission.bag, tmp_path / "input.mcap", compression)
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(bag, outputs["cal"], tmp_path / "out.mcap")
    assert NOT_COPIED not in caplog.text
    chunks = chunk_data(tmp_path / "out.mcap")
    assert {c for c, _d, t in chunks if CORRECTED not in t} == {
        "" if compression == "none" else compression}
    _written, order = assert_reads_as_one_by_one(bag, outputs["cal"], tmp_path)
    # a reader from the start of the file (lidarcal recover's) meets every channel first
    assert sum(1 for _ in ReadableMcap(tmp_path / "out.mcap").messages()) == len(order)


def test_messages_compressed_one_by_one_are_written_one_by_one(
        small_mission: MissionFiles, outputs: dict[str, Path], tmp_path: Path,
        caplog: Any) -> None:
    """A rosbag2 bag of zstd-compressed messages (compression_mode: message): its chunks
    hold compressed messages, which the output passes through decompressed."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    from lidarcal_ros.io.bag.format import standard_typestore

    bag = tmp_path / "compressed"
    typestore = standard_typestore()
    with open_bag(small_mission.bag) as source:
        writer = Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
        with writer:
            connections = {topic: writer.add_connection(topic, info.msgtype,
                                                        typestore=typestore)
                           for topic, info in source.topics.items()}
            for topic, _msgtype, log_time, raw in source.messages():
                writer.write(connections[topic], log_time, raw)
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(bag, outputs["cal"], tmp_path / "out.mcap")
    assert NOT_COPIED in caplog.text and "compressed one by one" in caplog.text
    written, _order = read_with_mcap(tmp_path / "out.mcap")
    assert written == read_with_mcap(outputs["copied.mcap"])[0]


def test_topic_that_cannot_be_written_is_left_out(
        small_mission: MissionFiles, outputs: dict[str, Path], tmp_path: Path,
        caplog: Any) -> None:
    """A topic of a type without a definition is left out of the output, with a warning,
    so its chunks cannot be copied as they are."""
    bag = rewrite_with_mcap(small_mission.bag, tmp_path / "input.mcap", "zstd",
                            unknown_topic=True)
    with caplog.at_level(logging.INFO, logger="lidarcal_ros"):
        correct(bag, outputs["cal"], tmp_path / "out.mcap")
    assert NOT_COPIED in caplog.text and "unknown message type my_pkg/msg/Thing" in caplog.text
    assert "topic /unknown not passed through" in caplog.text
    written, _order = read_with_mcap(tmp_path / "out.mcap")
    assert written == read_with_mcap(outputs["copied.mcap"])[0]


def test_copy_through_a_buffer(small_mission: MissionFiles, outputs: dict[str, Path],
                               tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the kernel cannot copy file to file (after a first part), the chunks are
    copied through a buffer: the same file."""
    import errno

    from lidarcal_ros.io.bag import chunk_copy as mcap_chunk_copy

    calls: list[int] = []
    mcap_chunk_copy_range = mcap_chunk_copy.os.copy_file_range

    def partly(src: int, dst: int, count: int, offset_src: int, offset_dst: int) -> int:
        if calls:
            raise OSError(errno.EXDEV, "cross-device")
        calls.append(count)
        return int(mcap_chunk_copy_range(src, dst, min(count, 1000), offset_src, offset_dst))

    # (the same name: rosbag2's metadata in the file names it)
    for way in ("in_kernel", "buffered"):
        (tmp_path / way).mkdir()
        if way == "buffered":
            monkeypatch.setattr(mcap_chunk_copy.os, "copy_file_range", partly)
        correct(small_mission.bag, outputs["cal"], tmp_path / way / "out.mcap")
    assert calls
    assert ((tmp_path / "buffered/out.mcap").read_bytes()
            == (tmp_path / "in_kernel/out.mcap").read_bytes())
