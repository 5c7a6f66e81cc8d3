"""Copying the compressed chunks of indexed MCAP files into a bag being written.

When it applies and why the output is the same: docs/internals.md, "Bags".
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any, BinaryIO

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
    QosDurability,
)
from rosbags.rosbag2.storage_mcap import (
    Channel,
    ChunkInfo,
    McapReader,
    Schema,
    get_qos,
    write_channel,
    write_schema,
)

from lidarcal_ros.io.bag.chunk_writer import chunk_index_record

logger = logging.getLogger(__name__)

#: Chunk compressions that the output may carry: every reader of the project's bags (rosbags,
#: the ``mcap`` library, :mod:`lidarcal_ros.io.bag.chunk_reader`) decompresses them.
COPYABLE_COMPRESSIONS = frozenset({"", "zstd", "lz4"})
_SCHEMA_ENCODINGS = {"ros2msg": MessageDefinitionFormat.MSG,
                     "ros2idl": MessageDefinitionFormat.IDL}
_COPY_BLOCK = 1 << 22


@dataclass(frozen=True)
class CopiedChannel:
    """A channel of the input whose messages are copied: its record and its schema's, as
    the input holds them, and its normalised message type."""

    channel: Channel
    schema: Schema
    msgtype: str


@dataclass
class ChunkCopy:
    """What :func:`adopt_and_copy` copies: the files' chunks, and the channels and schemas
    (by id) that their messages are on.

    Attributes
    ----------
    files : list of rosbags McapReader
        The open input files, whose chunks are copied in file order.
    channels : dict of int to CopiedChannel
    schemas : dict of int to Schema
    messages : int
        Messages in the copied chunks.
    """

    files: list[McapReader]
    channels: dict[int, CopiedChannel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    messages: int = 0

    @property
    def topics(self) -> set[str]:
        """Topics whose messages are in the copied chunks."""
        return {c.channel.topic for c in self.channels.values()}


def _transient_local(metadata: bytes) -> bool:
    qos = get_qos(metadata)
    return bool(qos) and all(q.durability == QosDurability.TRANSIENT_LOCAL for q in qos)


def _schema_id(reader: McapReader, name: str) -> int | None:
    ids = [k for k, s in reader.schemas.items() if s.name == name]
    return ids[0] if len(ids) == 1 else None


class _Refusal(Exception):
    """Why the chunks of a bag cannot be copied (logged by :func:`plan_chunk_copy`, never
    raised out of it: the messages are then written one by one)."""


def _file_channels(reader: McapReader, topics: dict[str, Any], new_topics: Collection[str]
                   ) -> dict[int, CopiedChannel]:
    """The channels of one file that hold messages, checked one by one."""
    out: dict[int, CopiedChannel] = {}
    for conn in reader.connections:
        if not conn.msgcount:
            continue
        channel = reader.channels[conn.id]
        info = topics.get(channel.topic)
        schema_id = _schema_id(reader, channel.schema)
        if channel.topic in new_topics:
            raise _Refusal(f"topic {channel.topic} is also written new")
        if info is None or channel.schema != info.msgtype:
            raise _Refusal(f"schema name {channel.schema} of {channel.topic} is not the "
                           "normalised type name")
        if channel.message_encoding != "cdr" or schema_id is None:
            raise _Refusal(f"channel {channel.topic} is not CDR with one schema of its name")
        schema = reader.schemas[schema_id]
        if schema.encoding not in _SCHEMA_ENCODINGS:
            raise _Refusal(f"schema {schema.name} is encoded {schema.encoding!r}")
        if _transient_local(channel.metadata) != info.transient_local:
            raise _Refusal(f"QoS of {channel.topic} differs between the file and the bag")
        out[conn.id] = CopiedChannel(channel, schema, info.msgtype)
    return out


def _check_chunks(reader: McapReader) -> int:
    """Messages in the chunks of one file, checked to be all of its messages, in chunks
    whose message indexes follow them and whose compression the output may carry."""
    stats = reader.statistics
    if reader.metadata.message_count and not reader.chunks:
        raise _Refusal(f"{reader.path} has no chunk index")
    count = 0
    for chunk in reader.chunks:
        if chunk.compression not in COPYABLE_COMPRESSIONS:
            raise _Refusal(f"{reader.path}: chunk compression {chunk.compression!r}")
        after = chunk.chunk_start_offset + chunk.chunk_length
        if any(not after <= offset < after + chunk.message_index_length
               for offset in chunk.message_index_offsets.values()):
            raise _Refusal(f"{reader.path}: message indexes apart from their chunk")
        count += sum(chunk.channel_count.values())
    if stats is None or count != stats.message_count:
        raise _Refusal(f"{reader.path}: messages outside the indexed chunks")
    return count


def plan_chunk_copy(bag: Any, new_topics: Collection[str], new_msgtypes: Collection[str]
                    ) -> ChunkCopy | None:
    """Whether the messages of an open bag can be passed through by copying its chunks.

    Parameters
    ----------
    bag : BagReader
        The open input (:class:`lidarcal_ros.io.bag.reader.BagReader`).
    new_topics, new_msgtypes : collection of str
        Topics the output adds (their channels, and the schemas of their types not in the
        input, take ids after the input's), and their types.

    Returns
    -------
    ChunkCopy or None
        None (the reason logged) unless every file is an indexed MCAP whose messages are
        all in chunks of a compression the output may carry, on CDR channels of normalised
        type names, each topic under one channel id and each type under one schema id,
        each id the same record in every file, and ids that leave the next ones free for
        ``new_topics``.
    """
    readers = bag.indexed_files()
    plan = ChunkCopy(list(readers or ()))
    # Every record of every file, with messages or not: the copied chunks may hold them.
    channels: dict[int, Channel] = {}
    schemas: dict[int, Schema] = {}
    try:
        if readers is None:
            raise _Refusal("its messages are compressed one by one")
        for reader in readers:
            for kind, records, held in (("channel", channels, reader.channels),
                                        ("schema", schemas, reader.schemas)):
                for key, record in held.items():
                    if records.setdefault(key, record) != record:
                        raise _Refusal(f"{kind} id {key} differs between the files")
            plan.messages += _check_chunks(reader)
            for cid, copied in _file_channels(reader, bag.topics, new_topics).items():
                plan.channels[cid] = copied
                plan.schemas[copied.schema.id] = copied.schema
        topics = [c.channel.topic for c in plan.channels.values()]
        names = [s.name for s in plan.schemas.values()]
        if len(set(topics)) != len(topics) or len(set(names)) != len(names):
            raise _Refusal("a topic or type under several ids")
        # The writer numbers new channels and schemas from one past how many it has.
        if any(len(plan.channels) + k in channels for k in range(1, len(new_topics) + 1)):
            raise _Refusal(f"channel ids {sorted(channels)} leave no id for new topics")
        fresh = {t for t in new_msgtypes if t not in names}
        if any(len(plan.schemas) + k in schemas for k in range(1, len(fresh) + 1)):
            raise _Refusal(f"schema ids {sorted(schemas)} leave no id for new types")
    except _Refusal as why:
        logger.info("%s: chunks not copied (%s); messages written one by one", bag.path, why)
        return None
    return plan


def adopt_and_copy(writer: Any, plan: ChunkCopy, digests: dict[str, str]) -> None:
    """Give a freshly opened writer the input's channels and schemas, then copy the input's
    chunks into its file.

    Parameters
    ----------
    writer : BagWriterBackend
        Open, with no connection yet.
    plan : ChunkCopy
    digests : dict of str to str
        The type description hash (RIHS01) of each copied type, for ``metadata.yaml``.
    """
    storage = writer.storage
    for schema in sorted(plan.schemas.values(), key=lambda s: s.id):
        storage.schemas.append(schema)
        writer.added_types.add(schema.name)
    for cid in sorted(plan.channels):
        copied = plan.channels[cid]
        schema, channel = copied.schema, copied.channel
        connection = Connection(
            id=cid, topic=channel.topic, msgtype=copied.msgtype,
            msgdef=MessageDefinition(_SCHEMA_ENCODINGS[schema.encoding], schema.data),
            digest=digests[copied.msgtype], msgcount=0,
            ext=ConnectionExtRosbag2(serialization_format=channel.message_encoding,
                                     offered_qos_profiles=get_qos(channel.metadata)),
            owner=writer)
        writer.connections.append(connection)
        writer.counts[cid] = 0
        storage.channels.append(channel)
        storage.channel_stats[cid] = 0
    # The records also open the data section, ahead of the messages on them, for readers
    # that read a file from its start (the input's may have been outside its chunks).
    for schema in storage.schemas:
        write_schema(storage.bio, schema)
    for channel in storage.channels:
        write_channel(storage.bio, channel, storage.schemas)
    for reader in plan.files:
        with reader.path.open("rb") as source:
            for chunk in sorted(reader.chunks, key=lambda c: c.chunk_start_offset):
                _copy_chunk(writer, source, chunk)


def _copy_bytes(source: BinaryIO, out: BinaryIO, offset: int, size: int) -> None:
    """``size`` bytes of ``source`` from ``offset`` appended to ``out``: file to file in
    the kernel where it can, else through a buffer."""
    out.flush()
    at = out.tell()
    done = 0
    try:
        while done < size:
            n = os.copy_file_range(source.fileno(), out.fileno(), size - done,
                                   offset + done, at + done)
            if n == 0:
                raise EOFError(f"MCAP data at {offset} cut short")
            done += n
    except OSError:  # a file system (or kernel) without it: copy what is left
        source.seek(offset + done)
        out.seek(at + done)
        while done < size:
            block = source.read(min(size - done, _COPY_BLOCK))
            if not block:
                raise EOFError(f"MCAP data at {offset} cut short") from None
            out.write(block)
            done += len(block)
    out.seek(at + size)


def _copy_chunk(writer: Any, source: BinaryIO, chunk: ChunkInfo) -> None:
    """One chunk record and its message indexes, copied; its chunk index entry and the
    counts and times of the writer's statistics and metadata."""
    storage = writer.storage
    start = storage.bio.tell()
    _copy_bytes(source, storage.bio, chunk.chunk_start_offset,
                chunk.chunk_length + chunk.message_index_length)
    shift = start - chunk.chunk_start_offset
    storage.chunks.append(chunk_index_record(
        chunk.message_start_time, chunk.message_end_time, start, chunk.chunk_length,
        [(cid, offset + shift) for cid, offset in chunk.message_index_offsets.items()],
        chunk.message_index_length, chunk.compression, chunk.compressed_size,
        chunk.uncompressed_size))
    for cid, count in chunk.channel_count.items():
        storage.channel_stats[cid] += count
        writer.counts[cid] += count
    if chunk.channel_count:
        storage.message_start_time = min(storage.message_start_time, chunk.message_start_time)
        storage.message_end_time = max(storage.message_end_time, chunk.message_end_time)
        writer.min_timestamp = min(writer.min_timestamp, chunk.message_start_time)
        writer.max_timestamp = max(writer.max_timestamp, chunk.message_end_time)


__all__ = ["COPYABLE_COMPRESSIONS", "ChunkCopy", "CopiedChannel", "adopt_and_copy",
           "plan_chunk_copy"]
