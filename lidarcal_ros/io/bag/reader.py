"""Reading rosbag2 bags with MCAP storage, without ROS.

What is accepted and refused: docs/internals.md, "Bags". Messages as CDR bytes in log-time
order; times integer nanoseconds.
"""

from __future__ import annotations

import heapq
import logging
import os
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinitionFormat,
    Qos,
    QosDurability,
)
from rosbags.rosbag2.errors import ReaderError
from rosbags.typesys import get_types_from_idl, get_types_from_msg

from lidarcal_ros.errors import BagError, ConfigError, brief, one_line
from lidarcal_ros.io.bag.chunk_reader import chunk_messages
from lidarcal_ros.io.bag.format import add_standard_types, empty_typestore, normalize_msgtype
from lidarcal_ros.io.bag.mcap_bounds import (
    CHUNK_LIMIT,
    BeyondLimitError,
    BoundedFile,
    BoundedMcapReader,
    bounded_decompress,
    chunk_records,
    decompress_file,
)
from lidarcal_ros.io.url_cache import local_source

logger = logging.getLogger(__name__)

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag.

    Attributes
    ----------
    msgtype : str
        Normalised message type (``pkg/msg/Type``).
    count : int
        Number of messages.
    qos : tuple of rosbags.interfaces.Qos
        Offered QoS profiles recorded with the topic (empty if unknown).
    msgdef : str
        Message definition text stored in the bag ('' if none).
    """

    msgtype: str
    count: int
    qos: tuple[Qos, ...] = ()
    msgdef: str = ""

    @property
    def transient_local(self) -> bool:
        """Whether every recorded publisher offered transient-local durability."""
        return bool(self.qos) and all(
            q.durability == QosDurability.TRANSIENT_LOCAL for q in self.qos
        )


@dataclass
class _File:
    path: Path
    reader: BoundedMcapReader
    connections: list[Connection] = field(default_factory=list)


class ReadableMcap:
    """The messages of one MCAP file, read from the start up to its first damaged record
    (what stopped the reading is kept in ``damage``; empty for an intact file). The
    ``mcap`` library's stream reader needs no summary or footer, so this reads a file whose
    recording was cut."""

    #: Records larger than this are taken as damage, not read (bytes).
    RECORD_LIMIT = 2**31

    def __init__(self, path: Path) -> None:
        self.path = path
        self.damage = ""

    def messages(self) -> Iterator[tuple[Any, Any, Any]]:
        """``(channel, schema or None, message)`` records in file order."""
        from mcap.records import Channel, Message, Schema

        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        with BoundedFile(self.path) as stream:
            records = chunk_records(stream, limit=self.RECORD_LIMIT)
            while True:
                # Only the reader's own failures are damage, not those of the consumer.
                try:
                    record = next(records)
                except StopIteration:
                    return
                except Exception as exc:
                    self.damage = one_line(exc)
                    return
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel = channels[record.channel_id]
                    yield channel, schemas.get(channel.schema_id), record


def _foreign_encodings(path: Path) -> str:
    """The channels of an MCAP file that do not hold CDR-encoded ROS 2 messages, as
    ``topic (encoding), ...`` ('' when every one does, or none can be read)."""
    from mcap.records import Channel, Schema

    schemas: dict[int, str] = {}
    foreign: dict[str, str] = {}
    try:
        with BoundedFile(path) as stream:
            for record in chunk_records(stream, limit=ReadableMcap.RECORD_LIMIT):
                if isinstance(record, Schema):
                    schemas[record.id] = record.encoding
                elif isinstance(record, Channel):
                    schema = schemas.get(record.schema_id, "")
                    if record.message_encoding != "cdr":
                        foreign[record.topic] = record.message_encoding or "no encoding"
                    elif schema not in ("ros2msg", "ros2idl", ""):
                        foreign[record.topic] = f"schema {schema}"
    except Exception:  # damage: what was readable before it is reported
        logger.debug("%s: stopped reading channels", path, exc_info=True)
    return ", ".join(f"{topic} ({encoding})" for topic, encoding in foreign.items())


def _damage_message(path: Path, what: str) -> str:
    count = sum(1 for _ in ReadableMcap(path).messages())
    return (f"{path}: truncated or corrupt MCAP ({what}); {count} messages were readable "
            "before the damage (lidarcal recover BAG -o NEW keeps them)")


class BagReader:
    """An open rosbag2 bag (MCAP storage) or bare MCAP file; use as a context manager.

    Attributes
    ----------
    path : pathlib.Path
    topics : dict of str to TopicInfo
    start_ns, end_ns : int
        Log times of the first and last message, nanoseconds (0 for an empty bag).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = local_source(path, what="bag")  # (a URL: its copy here)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns = 0
        self.end_ns = 0
        self._files: list[_File] = []
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        self._message_compressed = False
        # The bag's own definitions decode its messages; the standard ones only stand in for
        # those it lacks (see _collect_topics).
        self._typestore = empty_typestore()
        self._connection_types: dict[tuple[int, int], str] = {}
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    # -- opening -----------------------------------------------------------------------

    def _open(self) -> None:
        path = self.path
        if not path.exists():
            raise BagError(f"{path}: no such bag (file or directory not found)")
        meta_qos: dict[str, list[Qos]] = {}
        if path.is_file() and path.name == "metadata.yaml":
            path = path.parent
        if path.is_dir():
            files, meta_qos = self._files_of_directory(path)
        else:
            files = [path]
        for file in files:
            if not file.is_file():  # a FIFO, socket or device would block or never end
                raise BagError(f"{file}: not a regular file (a FIFO, socket or device); "
                               "refused")
            self._open_file(file)
        self._collect_topics(meta_qos)

    def _files_of_directory(self, path: Path) -> tuple[list[Path], dict[str, list[Qos]]]:
        meta = path / "metadata.yaml"
        if not meta.exists():
            mcaps = sorted(path.glob("*.mcap"))
            if mcaps:
                logger.info("%s: no metadata.yaml; reading %d MCAP file(s)", path, len(mcaps))
                return mcaps, {}
            if any(path.glob("*.db3")):
                raise BagError(
                    f"{path}: sqlite3 storage is not supported; convert the bag to MCAP "
                    "(ros2 bag convert)"
                )
            raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml and no .mcap file)")
        from lidarcal_ros.io.yaml_file import read_yaml

        try:
            doc = read_yaml(meta, what="bag metadata")
            if not isinstance(doc, dict) or "rosbag2_bagfile_information" not in doc:
                raise BagError(f"{meta}: not rosbag2 bag metadata (no "
                               "'rosbag2_bagfile_information'; delete it to read the .mcap "
                               "files alone)")
            info = doc["rosbag2_bagfile_information"]
            storage = str(info.get("storage_identifier", ""))
            rel = [str(x) for x in info.get("relative_file_paths", [])]
            mode = str(info.get("compression_mode", "") or "").lower()
            fmt = str(info.get("compression_format", "") or "").lower()
            topics = info.get("topics_with_message_count", []) or []
        except BagError:
            raise
        except ConfigError as err:  # not YAML, or beyond the bounds of any YAML read
            raise BagError(str(err)) from None
        except Exception as err:  # any layout problem
            raise BagError(f"{meta}: unreadable bag metadata ({one_line(err)})") from None
        if storage != "mcap":
            raise BagError(
                f"{path}: storage '{storage}' is not supported; only MCAP bags are read "
                "(convert with ros2 bag convert)"
            )
        if mode not in ("", "none") and fmt != "zstd":
            raise BagError(f"{path}: compression format '{fmt}' is not supported")
        escaping = [x for x in rel if Path(x).is_absolute() or ".." in Path(x).parts]
        if escaping:
            raise BagError(f"{meta}: names file(s) outside the bag: {brief(', '.join(escaping))}; "
                           "refused")
        files = [path / Path(x).name for x in rel]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise BagError(f"{path}: bag file(s) listed in metadata.yaml missing: {missing}")
        if mode == "file":
            self._tmpdir = tempfile.TemporaryDirectory(prefix="lidarcal-bag-")
            unpacked = []
            for f in files:
                out = Path(self._tmpdir.name) / f.name.removesuffix(".zstd")
                try:
                    decompress_file(f, out)
                except BeyondLimitError as err:
                    raise BagError(f"{err}; refused") from None
                except ReaderError as err:
                    raise BagError(str(err)) from None
                unpacked.append(out)
            files = unpacked
        self._message_compressed = mode == "message"
        from rosbags.rosbag2.metadata import parse_qos

        qos: dict[str, list[Qos]] = {}
        for entry in topics:
            try:
                tm = entry["topic_metadata"]
                qos[str(tm["name"])] = parse_qos(tm.get("offered_qos_profiles", []))
            except Exception:  # QoS is informative only
                continue
        return files, qos

    def _open_file(self, path: Path) -> None:
        try:
            with path.open("rb") as stream:
                head = stream.read(16)
        except OSError as err:
            raise BagError(f"{path}: cannot read ({err.strerror})") from None
        if head.startswith(_SQLITE_MAGIC):
            raise BagError(
                f"{path}: sqlite3 storage is not supported; convert the bag to MCAP "
                "(ros2 bag convert)"
            )
        if not head:
            raise BagError(f"{path}: empty file, not an MCAP bag")
        if not head.startswith(_MCAP_MAGIC):
            raise BagError(f"{path}: not an MCAP file (bad magic bytes)")
        reader = BoundedMcapReader(path)
        try:
            reader.open()
        except Exception as err:  # a foreign encoding, else damage
            text = one_line(err)
            foreign = _foreign_encodings(path)
            if foreign:
                raise BagError(f"{path}: not a ROS 2 bag: messages on {foreign} are not "
                               "CDR-encoded ROS 2 messages (lidarcal reads the bags of ros2 "
                               "bag record -s mcap)") from None
            if isinstance(err, BeyondLimitError):
                raise BagError(f"{path}: {text}; refused") from None
            if isinstance(err, ReaderError) and "Profile is not ros2" in text:
                raise BagError(f"{path}: MCAP profile is not 'ros2'; not a ROS 2 bag") from None
            raise BagError(_damage_message(path, text)) from None
        self._files.append(_File(path, reader, list(reader.connections)))

    def _collect_topics(self, meta_qos: dict[str, list[Qos]]) -> None:
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        qos: dict[str, list[Qos]] = {}
        defs: dict[str, str] = {}
        starts, ends = [], []
        for index, file in enumerate(self._files):
            md = file.reader.metadata
            if md.message_count:
                starts.append(md.start_time)
                ends.append(md.end_time - 1)
            for conn in file.connections:
                msgtype = normalize_msgtype(conn.msgtype)
                self._connection_types[(index, conn.id)] = msgtype
                if conn.topic in types and types[conn.topic] != msgtype:
                    logger.warning(
                        "%s: topic %s has types %s and %s",
                        self.path, conn.topic, types[conn.topic], msgtype,
                    )
                types.setdefault(conn.topic, msgtype)
                counts[conn.topic] = counts.get(conn.topic, 0) + conn.msgcount
                ext = conn.ext
                if isinstance(ext, ConnectionExtRosbag2) and ext.offered_qos_profiles:
                    qos.setdefault(conn.topic, []).extend(ext.offered_qos_profiles)
                if conn.msgdef.format != MessageDefinitionFormat.NONE and conn.msgdef.data:
                    defs.setdefault(conn.topic, conn.msgdef.data)
                    self._register(msgtype, conn.msgdef.data, conn.msgdef.format)
        if not all(self._resolves(t) for t in set(types.values())):
            add_standard_types(self._typestore)
        self.start_ns = min(starts) if starts else 0
        self.end_ns = max(ends) if ends else 0
        self.topics = {
            topic: TopicInfo(
                types[topic],
                counts[topic],
                tuple(qos.get(topic) or meta_qos.get(topic, [])),
                defs.get(topic, ""),
            )
            for topic in sorted(types)
        }

    def _resolves(self, msgtype: str) -> bool:
        """Whether the typestore defines ``msgtype`` and every type it uses (a bag may give
        a type's definition without those of the types it uses)."""
        try:
            self._typestore.get_msgdef(msgtype)
        except Exception:  # (rosbags raises KeyError, or its own errors for bad ones)
            return False
        return True

    def _register(self, msgtype: str, text: str, fmt: MessageDefinitionFormat) -> None:
        """Add the bag's definition of ``msgtype`` (and of the types it uses), unless an
        earlier connection gave one."""
        if msgtype in self._typestore.fielddefs:
            return
        try:
            if fmt == MessageDefinitionFormat.MSG:
                typs = get_types_from_msg(text, msgtype)
            else:
                sep = "=" * 80 + "\n"
                typs = {}
                if text.startswith(f"{sep}IDL: "):
                    for part in text.split(sep)[1:]:
                        typs.update(get_types_from_idl(part.split("\n", 1)[1]))
                else:
                    typs.update(get_types_from_idl(text))
            new = {k: v for k, v in typs.items() if k not in self._typestore.fielddefs}
            self._typestore.register(new)
        except Exception as err:  # an unparsable definition is not fatal yet
            logger.debug("%s: cannot register %s from the bag: %s", self.path, msgtype, err)

    # -- reading -----------------------------------------------------------------------

    def messages(
        self, topics: Iterable[str] | None = None
    ) -> Iterator[tuple[str, str, int, bytes]]:
        """Messages in log-time order, merged across the bag's files.

        Parameters
        ----------
        topics : iterable of str, optional
            Topics to read; all when None. Topics absent from the bag are ignored.

        Yields
        ------
        topic : str
        msgtype : str
            Normalised message type.
        log_time_ns : int
            Log (receive) time, nanoseconds.
        raw : bytes
            CDR-serialised message.

        Raises
        ------
        BagError
            A file turns out truncated or corrupt while reading.
        """
        wanted = None if topics is None else set(topics)
        sources = []
        for index, file in enumerate(self._files):
            conns = [c for c in file.connections if wanted is None or c.topic in wanted]
            if conns:
                sources.append(self._file_messages(index, file, conns))
        if len(sources) == 1:
            yield from sources[0]
        else:
            yield from heapq.merge(*sources, key=lambda m: m[2])

    def _file_messages(
        self, index: int, file: _File, conns: list[Connection]
    ) -> Iterator[tuple[str, str, int, bytes]]:
        by_id = {c.id: c for c in conns}
        fast = chunk_messages(file.reader, set(by_id))
        source: Iterator[tuple[Any, int, bytes]] = file.reader.messages(conns) \
            if fast is None else ((by_id[k], t, data) for k, t, data in fast)
        count = 0
        while True:
            try:
                conn, timestamp, data = next(source)
                if self._message_compressed:
                    data = bounded_decompress(data, "zstd", CHUNK_LIMIT, what="a message")
            except StopIteration:
                return
            except BeyondLimitError as err:
                raise BagError(f"{file.path}: {one_line(err)}; refused") from None
            except Exception as err:  # damage inside the file
                raise BagError(
                    f"{file.path}: truncated or corrupt MCAP ({one_line(err)}); "
                    f"{count} messages were read before the damage"
                ) from None
            count += 1
            yield conn.topic, self._connection_types[(index, conn.id)], timestamp, data

    def indexed_files(self) -> list[BoundedMcapReader] | None:
        """The open readers of the bag's MCAP files, whose chunks hold its messages as
        :meth:`messages` yields them; None when the messages are compressed one by one."""
        return None if self._message_compressed else [file.reader for file in self._files]

    @property
    def typestore(self) -> Any:
        """The rosbags typestore that decodes the bag: its own definitions, the standard
        ROS 2 ones only where those are missing or incomplete (a writer may share it:
        :class:`~lidarcal_ros.io.bag.writer.BagWriter`'s ``typestore``)."""
        return self._typestore

    def deserialize(self, raw: bytes | memoryview, msgtype: str, *, topic: str = "") -> Any:
        """Decode a CDR message.

        Parameters
        ----------
        raw : bytes
            CDR bytes as yielded by :meth:`messages`.
        msgtype : str
            Message type (``pkg/msg/Type`` or ``pkg/Type``).
        topic : str, keyword-only
            Named in error messages.

        Returns
        -------
        object
            A rosbags message object; arrays (e.g. ``PointCloud2.data``) are views on ``raw``.

        Raises
        ------
        BagError
            Unknown type or undecodable bytes.
        """
        msgtype = normalize_msgtype(msgtype)
        where = f" on {topic}" if topic else ""
        if msgtype not in self._typestore.fielddefs:
            raise BagError(f"{self.path}: no definition for message type {msgtype}{where}")
        try:
            return self._typestore.deserialize_cdr(raw, msgtype)
        except Exception as err:  # corrupt bytes
            raise BagError(
                f"{self.path}: cannot decode {msgtype} message{where} ({one_line(err)})"
            ) from None

    def close(self) -> None:
        """Close the bag's files."""
        for file in self._files:
            try:
                file.reader.close()
            except Exception:  # closing must not fail
                logger.debug("error closing %s", file.path, exc_info=True)
        self._files = []
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None

    def __enter__(self) -> BagReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> Literal[False]:
        self.close()
        return False


def open_bag(path: str | os.PathLike[str]) -> BagReader:
    """Open a rosbag2 directory (MCAP storage) or a bare ``.mcap`` file for reading.

    Raises
    ------
    BagError
        Missing path, not a bag, unsupported storage (sqlite3), truncated or corrupt file.
    """
    return BagReader(path)


__all__ = ["BagReader", "ReadableMcap", "TopicInfo", "open_bag"]
