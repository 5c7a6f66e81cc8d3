"""Reading and writing rosbag2 bags with MCAP storage, without ROS.

Reading accepts a rosbag2 directory (``metadata.yaml`` plus ``*.mcap``) or a bare ``.mcap``
file, also when schema names lack ``/msg/`` (``sensor_msgs/PointCloud2``). Writing produces a
rosbag2 directory (metadata version 8, MCAP storage, zstd-compressed chunks) that
``ros2 bag play`` and Foxglove open, or a bare MCAP file when the path ends in ``.mcap``.

Times: bag log times and header stamps are integer nanoseconds; mission times are float
seconds on the same clock. Coordinates are metres in the map frame (``header.frame_id``).
"""

from __future__ import annotations

import functools
import heapq
import itertools
import logging
import math
import os
import struct
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinitionFormat,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2.errors import ReaderError, WriterError
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from lidarcal_ros.core.attitude import IDENTITY_XYZW
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.thinning import first_per_cell
from lidarcal_ros.errors import BagError, CloudFormatError, ConfigError, InputError, OutputError
from lidarcal_ros.io.mcap_chunks import chunk_messages
from lidarcal_ros.io.mcap_storage import BagWriterBackend
from lidarcal_ros.io.output_files import EXISTS, os_reason, remove_quietly, temporary_beside
from lidarcal_ros.io.pointcloud import (
    DEFAULT_COORDINATE_TOLERANCE_M,
    CloudColumns,
    array_to_cloud_parts,
    cloud_to_array,
    extract_columns,
    extract_xyz,
    float32_warning,
    make_point_dtype,
)

logger = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

#: Trajectory message types read_mission accepts, with how to get the position and the
#: orientation (None: the type has none).
TRAJECTORY_TYPES: dict[str, Callable[[Any], tuple[Any, Any]]] = {
    POSE_STAMPED: lambda m: (m.pose.position, m.pose.orientation),
    ODOMETRY: lambda m: (m.pose.pose.position, m.pose.pose.orientation),
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        lambda m: (m.pose.pose.position, m.pose.pose.orientation),
    "geometry_msgs/msg/PointStamped": lambda m: (m.point, None),
}


def trajectory_sample(msgtype: str, msg: Any
                      ) -> tuple[float, tuple[float, float, float], tuple[float, ...]]:
    """A trajectory message of one of :data:`TRAJECTORY_TYPES` as ``(t, (x, y, z), q)``:
    header stamp (s), position (m) and its orientation quaternion ``(x, y, z, w)`` (NaN
    where the type has none; the identity is kept, and read as none by
    :class:`~lidarcal_ros.core.mission.Trajectory`)."""
    pos, q = TRAJECTORY_TYPES[msgtype](msg)
    quat = _NO_ORIENTATION if q is None else (float(q.x), float(q.y), float(q.z), float(q.w))
    return (stamp_seconds(msg.header.stamp), (float(pos.x), float(pos.y), float(pos.z)),
            quat)


_NO_ORIENTATION = (math.nan, math.nan, math.nan, math.nan)
#: A PoseStamped in CDR after its encapsulation: stamp (sec, nanosec), the frame id's length;
#: then, 8-byte aligned, position and orientation.
_POSE_HEADER = struct.Struct("<iII")
_POSE_BODY = struct.Struct("<7d")


class TrajectorySamples:
    """Trajectory messages gathered into a :class:`~lidarcal_ros.core.mission.Trajectory`
    (in any order), with the frames they are in."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.xyz: list[tuple[float, float, float]] = []
        self.orientation: list[tuple[float, ...]] = []
        self.frames: set[str] = set()

    def add(self, msgtype: str, msg: Any) -> None:
        t, xyz, q = trajectory_sample(msgtype, msg)
        self.t.append(t)
        self.xyz.append(xyz)
        self.orientation.append(q)
        self.frames.add(str(msg.header.frame_id))

    def add_raw(self, msgtype: str, raw: bytes | memoryview,
                decode: Callable[[memoryview, str], Any]) -> None:
        """Add a message from its CDR bytes: a little-endian ``PoseStamped`` read straight
        from them (the same numbers as its decoded message gives, a tenth of the time: the
        poses of a long mission number tens of thousands), any other through
        ``decode(bytes, msgtype)``."""
        if msgtype == POSE_STAMPED and len(raw) >= 16 and raw[1] == 1:  # CDR, little-endian
            sec, nanosec, size = _POSE_HEADER.unpack_from(raw, 4)
            end = 16 + size  # of the frame id, its NUL included
            body = 4 + (end - 4 + 7) // 8 * 8
            if size and body + _POSE_BODY.size == len(raw) and raw[end - 1] == 0:
                x, y, z, qx, qy, qz, qw = _POSE_BODY.unpack_from(raw, body)
                self.t.append(float(sec) + int(nanosec) * 1e-9)  # (stamp_seconds)
                self.xyz.append((x, y, z))
                self.orientation.append((qx, qy, qz, qw))
                self.frames.add(bytes(raw[16:end - 1]).decode())
                return
        self.add(msgtype, decode(memoryview(raw), msgtype))

    def __len__(self) -> int:
        return len(self.t)

    def trajectory(self, source: str) -> Trajectory:
        """The samples as a trajectory, in time order, screened as a whole
        (:func:`~lidarcal_ros.core.mission.screen_samples`: poses with a non-finite stamp or
        position, and stamps repeated at conflicting positions, left out with a warning line
        counting them).

        Raises
        ------
        TrajectoryError
            Every pose at one stamp (the header stamps were not set), or fewer than two usable
            poses: one line naming ``source`` (file and topic).
        """
        return Trajectory.from_samples(np.asarray(self.t, dtype=np.float64),
                                       np.asarray(self.xyz, dtype=np.float64),
                                       np.asarray(self.orientation).reshape(-1, 4),
                                       source=source)


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_NS = 1_000_000_000
_WRITTEN_CORE = frozenset({"x", "y", "z", "t", "intensity", "strip_id"})
_INFINITE = QosTime(9223372036, 854775807)


def _store() -> Typestore:
    """A fresh typestore with the standard ROS 2 message definitions."""
    store = getattr(Stores, "ROS2_JAZZY", Stores.ROS2_HUMBLE)
    return get_typestore(store)


def normalize_msgtype(name: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``; names that already have a namespace are kept."""
    parts = name.split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


def make_qos(*, transient_local: bool = False) -> Qos:
    """The offered QoS profile lidarcal records: reliable, volatile or transient-local."""
    return Qos(
        QosHistory.UNKNOWN,
        0,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        _INFINITE,
        _INFINITE,
        QosLiveliness.AUTOMATIC,
        _INFINITE,
        False,
    )


def seconds_to_ns(t: float) -> int:
    """Float seconds to integer nanoseconds, rounded to the nearest nanosecond."""
    sec = np.floor(t)
    return int(sec) * _NS + round(float(t - sec) * 1e9)


def ns_to_seconds(ns: int) -> float:
    """Integer nanoseconds to float seconds."""
    sec, nsec = divmod(int(ns), _NS)
    return float(sec) + nsec * 1e-9


def stamp_seconds(stamp: Any) -> float:
    """A builtin_interfaces/Time as float seconds (the trajectory's times)."""
    return float(stamp.sec) + int(stamp.nanosec) * 1e-9


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


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
    reader: McapReader
    connections: list[Connection] = field(default_factory=list)


def _zstd_decompress(data: bytes) -> bytes:
    if sys.version_info >= (3, 14):  # pragma: no cover
        from compression import zstd
    else:
        from backports import zstd
    return bytes(zstd.decompress(data))


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
        from mcap.stream_reader import StreamReader

        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        with self.path.open("rb") as stream:
            records = iter(StreamReader(stream, record_size_limit=self.RECORD_LIMIT).records)
            while True:
                # Only the reader's own failures are damage, not those of the consumer.
                try:
                    record = next(records)
                except StopIteration:
                    return
                except Exception as exc:
                    self.damage = _one_line(exc)
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
    from mcap.stream_reader import StreamReader

    schemas: dict[int, str] = {}
    foreign: dict[str, str] = {}
    try:
        with path.open("rb") as stream:
            for record in StreamReader(stream, record_size_limit=ReadableMcap.RECORD_LIMIT
                                       ).records:
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
        self.path = Path(path)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns = 0
        self.end_ns = 0
        self._files: list[_File] = []
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        self._message_compressed = False
        self._typestore = _store()
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
        from ruamel.yaml import YAML

        try:
            doc = YAML(typ="safe").load(meta.read_text())
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
        except Exception as err:  # any YAML or layout problem
            raise BagError(f"{meta}: unreadable bag metadata ({_one_line(err)})") from None
        if storage != "mcap":
            raise BagError(
                f"{path}: storage '{storage}' is not supported; only MCAP bags are read "
                "(convert with ros2 bag convert)"
            )
        if mode not in ("", "none") and fmt != "zstd":
            raise BagError(f"{path}: compression format '{fmt}' is not supported")
        files = [path / Path(x).name for x in rel]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise BagError(f"{path}: bag file(s) listed in metadata.yaml missing: {missing}")
        if mode == "file":
            self._tmpdir = tempfile.TemporaryDirectory(prefix="lidarcal-bag-")
            unpacked = []
            for f in files:
                out = Path(self._tmpdir.name) / f.name.removesuffix(".zstd")
                out.write_bytes(_zstd_decompress(f.read_bytes()))
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
        reader = McapReader(path)
        try:
            reader.open()
        except Exception as err:  # a foreign encoding, else damage
            text = _one_line(err)
            foreign = _foreign_encodings(path)
            if foreign:
                raise BagError(f"{path}: not a ROS 2 bag: messages on {foreign} are not "
                               "CDR-encoded ROS 2 messages (lidarcal reads the bags of ros2 "
                               "bag record -s mcap)") from None
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

    def _register(self, msgtype: str, text: str, fmt: MessageDefinitionFormat) -> None:
        """Add a bag's definition of a type the standard typestore lacks."""
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
                    data = _zstd_decompress(data)
            except StopIteration:
                return
            except Exception as err:  # damage inside the file
                raise BagError(
                    f"{file.path}: truncated or corrupt MCAP ({_one_line(err)}); "
                    f"{count} messages were read before the damage"
                ) from None
            count += 1
            yield conn.topic, self._connection_types[(index, conn.id)], timestamp, data

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
                f"{self.path}: cannot decode {msgtype} message{where} ({_one_line(err)})"
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


def _present(bag: BagReader) -> str:
    return ", ".join(bag.topics) or "none"


def read_mission(
    path: str | os.PathLike[str],
    *,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    control_topic: str | None = "/lidar/control_points",
    time_field: str = "t",
    thinning_cell_m: float = 0.0,
    box: tuple[float, float, float, float] | None = None,
    coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M,
) -> Mission:
    """Read a mission bag into memory.

    Parameters
    ----------
    path : path-like
        rosbag2 directory or bare ``.mcap`` file.
    points_topic : str, keyword-only
        ``sensor_msgs/PointCloud2`` chunks with ``x, y, z`` (map frame, m), a FLOAT64 time
        field (absolute s) and ``strip_id``/``point_source_id``.
    trajectory_topic : str, keyword-only
        ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry`` (also
        ``PoseWithCovarianceStamped``, ``PointStamped``): IMU origin in the map frame.
    control_topic : str or None, keyword-only
        ``PointCloud2`` with ``x, y, z`` control points; the last message is used. Ignored
        when absent from the bag or None.
    time_field : str, keyword-only
        Time field of the clouds (see :func:`~lidarcal_ros.io.pointcloud.extract_columns`).
    thinning_cell_m : float, keyword-only
        Keep only the first point of each square cell of this size (m) per strip in each
        cloud (:mod:`lidarcal_ros.core.thinning`; counted in ``thinned_points``); 0 keeps
        every point.
    box : (xmin, ymin, xmax, ymax), keyword-only, optional
        Keep only the points inside this box of the map frame (m): a part of a mission
        read without holding the rest.
    coordinate_tolerance_m : float, keyword-only
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (m; the range noise):
        coarser is refused, a step above a tenth of it is warned about
        (:func:`~lidarcal_ros.io.pointcloud.extract_columns`).

    Returns
    -------
    Mission
        Strips sorted by ``strip_id``, points within a strip sorted by time; fields other
        than x, y, z, time, intensity and strip id go to ``Strip.extra`` in their own dtype
        (a strip keeps a field only if all its points have it). Points with a non-finite
        x, y, z or t are dropped and counted in ``dropped_non_finite``.

    Raises
    ------
    BagError
        Bag unreadable, a required topic missing or of the wrong type.
    CloudFormatError
        A cloud lacks a required field.
    InputError
        Clouds and trajectory are in different frames.
    """
    with open_bag(path) as bag:
        for topic in (points_topic, trajectory_topic):
            if topic not in bag.topics:
                raise BagError(
                    f"{bag.path}: topic {topic} not found; topics present: {_present(bag)}"
                )
        _expect_type(bag, points_topic, (POINTCLOUD2,))
        _expect_type(bag, trajectory_topic, tuple(TRAJECTORY_TYPES))
        use_control = control_topic is not None and control_topic in bag.topics
        if use_control:
            assert control_topic is not None
            _expect_type(bag, control_topic, (POINTCLOUD2,))
        wanted = [points_topic, trajectory_topic] + ([control_topic] if use_control else [])

        acc = _CloudAccumulator(points_topic, time_field, thinning_cell_m, box,
                                coordinate_tolerance_m)
        samples = TrajectorySamples()
        decode_pose = functools.partial(bag.deserialize, topic=trajectory_topic)
        control_msg: Any = None
        for topic, msgtype, _log_ns, raw in bag.messages([t for t in wanted if t]):
            is_pose = topic == trajectory_topic
            ok_type = msgtype in TRAJECTORY_TYPES if is_pose else msgtype == POINTCLOUD2
            if not ok_type:
                raise BagError(f"{bag.path}: topic {topic} carries a {msgtype} message")
            if is_pose:
                samples.add_raw(msgtype, raw, decode_pose)
                continue
            msg = bag.deserialize(memoryview(raw), msgtype, topic=topic)
            if topic == points_topic:
                acc.add(msg)
            else:
                control_msg = msg
        if not acc.n_messages:
            raise BagError(f"{bag.path}: topic {points_topic} has no messages")
        if not samples:
            raise BagError(f"{bag.path}: topic {trajectory_topic} has no messages")
        frame = _check_frames(bag.path, points_topic, acc.frames, trajectory_topic,
                              samples.frames)
        control = None
        if control_msg is not None:
            assert control_topic is not None
            control = _control_from_cloud(bag.path, control_topic, control_msg, frame,
                                          coordinate_tolerance_m)
        strips, dropped = acc.strips()
        if not strips and not acc.outside_box:  # (a box may hold nothing: its reader says)
            raise InputError(
                f"{bag.path}: all {dropped} points on {points_topic} have a non-finite x, y, z "
                "or t" if dropped else
                f"{bag.path}: all {acc.n_messages} clouds on {points_topic} are empty")
        trajectory = samples.trajectory(f"{bag.path}: trajectory {trajectory_topic}")
    note = float32_warning(acc.coordinate_step_m, coordinate_tolerance_m)
    if note:
        logger.warning("%s: %s: %s", path, points_topic, note)
    if dropped:
        logger.warning("%s: dropped %d points with non-finite x, y, z or t", path, dropped)
    return Mission(trajectory, strips, control, frame, dropped, acc.thinned)


def _expect_type(bag: BagReader, topic: str, types: Sequence[str]) -> None:
    got = bag.topics[topic].msgtype
    if got not in types:
        raise BagError(
            f"{bag.path}: topic {topic} has type {got}; expected {' or '.join(types)}"
        )


def _check_frames(
    path: Path, points_topic: str, cloud_frames: set[str], traj_topic: str, traj_frames: set[str]
) -> str:
    if len(cloud_frames) > 1:
        raise InputError(
            f"{path}: clouds on {points_topic} are in several frames: {sorted(cloud_frames)}"
        )
    if len(traj_frames) > 1:
        raise InputError(
            f"{path}: poses on {traj_topic} are in several frames: {sorted(traj_frames)}"
        )
    cloud_frame = next(iter(cloud_frames))
    traj_frame = next(iter(traj_frames))
    if cloud_frame != traj_frame:
        raise InputError(
            f"{path}: clouds on {points_topic} are in frame '{cloud_frame}' but the "
            f"trajectory on {traj_topic} is in frame '{traj_frame}'"
        )
    return cloud_frame


def _control_from_cloud(path: Path, topic: str, msg: Any, frame: str,
                        coordinate_tolerance_m: float) -> ControlPoints | None:
    if msg.header.frame_id != frame:
        raise InputError(
            f"{path}: control points on {topic} are in frame '{msg.header.frame_id}' but "
            f"the clouds are in '{frame}'"
        )
    xyz = extract_xyz(cloud_to_array(msg, source=topic), source=topic,
                      coordinate_tolerance_m=coordinate_tolerance_m)
    ok = np.isfinite(xyz).all(axis=1)
    if not ok.all():
        logger.warning("%s: dropped %d non-finite control points", topic, int((~ok).sum()))
        xyz = xyz[ok]
    if not len(xyz):
        logger.warning("%s: control point cloud is empty", topic)
        return None
    return ControlPoints([f"C{i + 1}" for i in range(len(xyz))], xyz)


class _CloudAccumulator:
    """Collects columns of cloud chunks; groups them into strips once at the end.

    Optional columns (``intensity`` and extra fields) may be missing from some chunks; a
    strip keeps such a column only if every one of its points had it.
    """

    def __init__(self, topic: str, time_field: str, thinning_cell_m: float = 0.0,
                 box: tuple[float, float, float, float] | None = None,
                 coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M) -> None:
        self.topic = topic
        self.box = box
        self.time_field = time_field
        self.thinning_cell_m = float(thinning_cell_m)
        self.coordinate_tolerance_m = coordinate_tolerance_m
        self.coordinate_step_m = 0.0  # the coarsest FLOAT32 step met
        self.outside_box = 0  # points left out by the box
        self.thinned = 0
        self.frames: set[str] = set()
        self.xyz: list[np.ndarray] = []
        self.t: list[np.ndarray] = []
        self.sid: list[np.ndarray] = []
        self.optional: dict[str, dict[int, np.ndarray]] = {}  # name -> message index -> col
        self.n_messages = 0

    def add(self, msg: Any) -> None:
        index = self.n_messages
        self.n_messages += 1
        self.frames.add(msg.header.frame_id)
        arr = cloud_to_array(msg, source=self.topic)
        cols = extract_columns(arr, time_field=self.time_field, source=self.topic,
                               coordinate_tolerance_m=self.coordinate_tolerance_m)
        self.coordinate_step_m = max(self.coordinate_step_m, cols.coordinate_step_m)
        if cols.strip_id is None:
            raise CloudFormatError(
                f"{self.topic}: cloud lacks field 'strip_id' (or 'point_source_id'); "
                f"fields present: {', '.join(arr.dtype.names or ())}"
            )
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            x, y = cols.xyz[:, 0], cols.xyz[:, 1]
            inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            self.outside_box += int(inside.size - np.count_nonzero(inside))
            cols, arr = cols.take(inside), arr[inside]
        if self.thinning_cell_m > 0:
            cols, arr = self._thinned(cols, arr)
        strip_id = cols.strip_id
        assert strip_id is not None  # (checked above; thinning keeps it)
        self.xyz.append(cols.xyz)
        self.t.append(cols.t)
        self.sid.append(strip_id)
        if cols.intensity is not None:
            self.optional.setdefault("intensity", {})[index] = cols.intensity
        names = arr.dtype.names or ()
        sid_name = "strip_id" if "strip_id" in names else "point_source_id"
        core = {"x", "y", "z", "intensity", cols.time_field, sid_name}
        for name in names:
            if name in core:
                continue
            col = arr[name]
            self.optional.setdefault("extra:" + name, {})[index] = col.astype(
                col.dtype.newbyteorder("=")
            )

    def _thinned(self, cols: CloudColumns, arr: np.ndarray
                 ) -> tuple[CloudColumns, np.ndarray]:
        """The cloud's points thinned (:func:`~lidarcal_ros.core.thinning.first_per_cell`
        among the finite ones, as the calibrator node does); the non-finite ones stay, to be
        dropped and counted with the others."""
        assert cols.strip_id is not None
        finite = cols.finite()
        keep = first_per_cell(cols.xyz, cols.strip_id, self.thinning_cell_m, valid=finite)
        keep |= ~finite
        left_out = int(keep.size - np.count_nonzero(keep))
        if not left_out:
            return cols, arr
        self.thinned += left_out
        return cols.take(keep), arr[keep]

    def _optional_column(
        self, name: str, parts: dict[int, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray | None] | None:
        """Concatenated column and per-point presence mask (None: present everywhere)."""
        first = next(iter(parts.values()))
        if any(p.shape[1:] != first.shape[1:] for p in parts.values()):
            logger.warning("%s: field '%s' changes shape between clouds; ignored",
                           self.topic, name.removeprefix("extra:"))
            return None
        dtype = np.result_type(*{p.dtype for p in parts.values()})
        if len(parts) == self.n_messages:
            return np.concatenate([parts[i] for i in range(self.n_messages)]), None
        chunks, mask = [], []
        for i, t in enumerate(self.t):
            got = parts.get(i)
            chunks.append(got if got is not None else np.zeros((t.size, *first.shape[1:]), dtype))
            mask.append(np.full(t.size, got is not None))
        return np.concatenate(chunks).astype(dtype, copy=False), np.concatenate(mask)

    def strips(self) -> tuple[list[Strip], int]:
        xyz = np.concatenate(self.xyz) if len(self.xyz) > 1 else self.xyz[0]
        t = np.concatenate(self.t) if len(self.t) > 1 else self.t[0]
        sid = np.concatenate(self.sid) if len(self.sid) > 1 else self.sid[0]
        columns: dict[str, np.ndarray] = {}
        masks: dict[str, np.ndarray] = {}
        for name, parts in self.optional.items():
            got = self._optional_column(name, parts)
            if got is not None:
                columns[name] = got[0]
                if got[1] is not None:
                    masks[name] = got[1]
        self.xyz, self.t, self.sid, self.optional = [], [], [], {}

        ok = np.isfinite(xyz).all(axis=1) & np.isfinite(t)
        dropped = int(ok.size - np.count_nonzero(ok))
        if dropped:
            xyz, t, sid = xyz[ok], t[ok], sid[ok]
            columns = {k: v[ok] for k, v in columns.items()}
            masks = {k: v[ok] for k, v in masks.items()}

        perm, bounds = _strip_order(sid, t)
        if perm is not None:
            xyz, t, sid = xyz[perm], t[perm], sid[perm]
            columns = {k: v[perm] for k, v in columns.items()}
            masks = {k: v[perm] for k, v in masks.items()}
        strips = []
        for a, b in _pairs(bounds):
            sid_a = int(sid[a])
            keep: dict[str, np.ndarray] = {}
            for name, col in columns.items():
                mask = masks.get(name)
                if mask is not None and not mask[a:b].all():
                    if mask[a:b].any():
                        logger.warning("%s: field '%s' missing from some clouds of strip %d; "
                                       "ignored for that strip", self.topic,
                                       name.removeprefix("extra:"), sid_a)
                    continue
                keep[name] = col[a:b]
            intensity = keep.pop("intensity", None)
            extra = {k.removeprefix("extra:"): v for k, v in keep.items()}
            strips.append(Strip(sid_a, xyz[a:b], t[a:b], intensity, extra))
        return strips, dropped


def _pairs(bounds: Sequence[int]) -> Iterator[tuple[int, int]]:
    """Consecutive ``(start, stop)`` pairs of a boundary list."""
    return itertools.pairwise(bounds)


def _nondecreasing(a: np.ndarray) -> bool:
    return bool(a.size < 2 or np.all(a[1:] >= a[:-1]))


def _strip_order(sid: np.ndarray, t: np.ndarray) -> tuple[np.ndarray | None, list[int]]:
    """Permutation sorting by (strip id, time), or None if already sorted; strip bounds."""
    perm: np.ndarray | None = None
    if not _nondecreasing(sid):
        perm = np.argsort(sid, kind="stable")
        sid = sid[perm]
    bounds = [0, *(np.flatnonzero(sid[1:] != sid[:-1]) + 1).tolist(), int(sid.size)]
    if sid.size == 0:
        return None, [0]
    for a, b in _pairs(bounds):
        seg = t[a:b] if perm is None else t[perm[a:b]]
        if not _nondecreasing(seg):
            if perm is None:
                perm = np.arange(sid.size)
            sub = np.argsort(seg, kind="stable")
            perm[a:b] = perm[a:b][sub]
    return perm, bounds


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _check_replaceable(path: Path) -> None:
    """Refuse to replace an existing output that does not look like a bag lidarcal could
    have written (a project directory given as ``-o`` by mistake)."""
    if path.is_symlink():
        return
    if path.is_dir():
        allowed = {".mcap", ".yaml", ".zstd", ".db3"}
        odd = [p.name for p in path.iterdir() if p.is_dir() or p.suffix not in allowed]
        if odd:
            raise OutputError(
                f"{path}: refusing to overwrite a directory that is not a bag "
                f"(contains {', '.join(sorted(odd)[:3])})"
            )
    elif path.suffix != ".mcap":
        raise OutputError(f"{path}: refusing to overwrite a file that is not an .mcap")


def _install(new: Path, path: Path) -> None:
    """Move a complete output ``new`` to ``path``, replacing what was there only now."""
    old = None
    if path.exists() or path.is_symlink():
        old = path.with_name(f".{path.name}.lidarcal-old-{os.getpid()}")
        path.rename(old)
    try:
        new.rename(path)
    except OSError:
        if old is not None:
            old.rename(path)
        raise
    if old is not None:
        remove_quietly(old)


class BagWriter:
    """Write a rosbag2 bag with MCAP storage; use as a context manager.

    Parameters
    ----------
    path : path-like
        Output rosbag2 directory; a path ending in ``.mcap`` gives a bare MCAP file.
    overwrite : bool, keyword-only
        Replace an existing output (which must look like a bag). Otherwise an existing
        output is refused with :class:`~lidarcal_ros.errors.OutputError`.
    latched_topics : iterable of str, keyword-only
        Topics recorded as offered with transient-local durability.
    compress : bool, keyword-only
        zstd chunk compression inside the MCAP file.
    staged : bool, keyword-only
        Write under a hidden name beside ``path`` and move the bag into place (an existing
        output replaced) only when it is complete: if the ``with`` block or the writing fails
        (disk full), nothing partial is left and a previous output is untouched. False (a
        live recording, which a power loss may cut: ``lidarcal recover`` reads what it
        holds) writes a rosbag2 directory in place, an existing one removed first.

    Notes
    -----
    Metadata version 8 is written (QoS as a YAML string), which rosbag2 from Humble on
    reads. A bare ``.mcap`` is always staged (rosbags writes a directory around it).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        latched_topics: Iterable[str] = (),
        compress: bool = True,
        staged: bool = True,
    ) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.latched_topics = set(latched_topics)
        self.compress = compress
        self._bare = self.path.suffix == ".mcap"
        self._staged = staged or self._bare
        self._staging = temporary_beside(self.path)
        # The bag inside the staging directory keeps its final name (the names of its files
        # in metadata.yaml come from it).
        self._target = (self._staging / (self.path.stem if self._bare else self.path.name)
                        if self._staged else self.path)
        self._writer: BagWriterBackend | None = None
        self._connections: dict[str, Connection] = {}
        self._typestore = _store()

    def open(self) -> BagWriter:
        """Create the output; called on entering the ``with`` block.

        Raises
        ------
        OutputError
            The output exists and ``overwrite`` is False (or it does not look like a bag),
            its directory is missing, or the bag cannot be created.
        """
        if self.path.exists() or self.path.is_symlink():
            if not self.overwrite:
                raise OutputError(f"{self.path}: {EXISTS}")
            _check_replaceable(self.path)
            if not self._staged:
                remove_quietly(self.path)
        if not self.path.parent.is_dir():
            raise OutputError(f"{self.path}: directory {self.path.parent} does not exist")
        remove_quietly(self._staging)
        try:
            writer = BagWriterBackend(self._target, version=8,
                                      storage_plugin=StoragePlugin.MCAP)
            if self.compress:
                writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            writer.open()
        except (WriterError, OSError) as err:
            self._discard()
            raise OutputError(f"{self.path}: cannot create bag ({os_reason(err)})") from None
        self._writer = writer
        return self

    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        latched: bool | None = None,
        msgdef: str | None = None,
    ) -> None:
        """Declare a topic (done implicitly by the ``write_*`` methods).

        Parameters
        ----------
        topic, msgtype : str
        latched : bool or None, keyword-only
            Offer transient-local durability; None: whether ``topic`` is in
            ``latched_topics``.
        msgdef : str or None, keyword-only
            ``.msg`` definition text (ROS 2 concatenated form) for types the standard
            typestore lacks.
        """
        if self._writer is None:
            raise BagError(f"{self.path}: bag is not open for writing")
        msgtype = normalize_msgtype(msgtype)
        if topic in self._connections:
            have = self._connections[topic].msgtype
            if have != msgtype:
                raise BagError(f"{self.path}: topic {topic} already has type {have}, not {msgtype}")
            return
        if msgtype not in self._typestore.fielddefs:
            if not msgdef:
                raise BagError(f"{self.path}: unknown message type {msgtype} for {topic}")
            try:
                typs = get_types_from_msg(msgdef, msgtype)
                self._typestore.register(
                    {k: v for k, v in typs.items() if k not in self._typestore.fielddefs}
                )
            except Exception as err:  # bad definition text
                raise BagError(
                    f"{self.path}: cannot parse definition of {msgtype} ({_one_line(err)})"
                ) from None
        if latched is None:
            latched = topic in self.latched_topics
        self._connections[topic] = self._writer.add_connection(
            topic,
            msgtype,
            typestore=self._typestore,
            offered_qos_profiles=[make_qos(transient_local=latched)],
        )

    def write_raw(
        self,
        topic: str,
        msgtype: str,
        stamp_ns: int,
        raw: bytes | memoryview,
        *,
        msgdef: str | None = None,
    ) -> None:
        """Write an already CDR-serialised message (e.g. read from another bag).

        Parameters
        ----------
        topic, msgtype : str
        stamp_ns : int
            Log time, nanoseconds.
        raw : bytes
            CDR bytes.
        msgdef : str or None, keyword-only
            Definition text for a type the standard typestore lacks.
        """
        self.add_topic(topic, msgtype, msgdef=msgdef)
        if stamp_ns < 0:
            raise BagError(f"{self.path}: negative log time {stamp_ns} on {topic}")
        assert self._writer is not None
        try:
            self._writer.write(self._connections[topic], int(stamp_ns), raw)
        except (WriterError, OSError) as err:
            raise OutputError(f"{self.path}: cannot write bag ({os_reason(err)})") from None

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        types = self._typestore.types
        sec, nsec = divmod(int(stamp_ns), _NS)
        if not 0 <= sec < 2**31:
            raise BagError(f"{self.path}: stamp {stamp_ns} ns out of range for a ROS 2 Time")
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
            frame_id=frame_id,
        )

    def write_message(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialise and write a rosbags message object of ``msgtype``."""
        msgtype = normalize_msgtype(msgtype)
        self.add_topic(topic, msgtype)
        raw = self._typestore.serialize_cdr(msg, msgtype)
        self.write_raw(topic, msgtype, stamp_ns, raw)

    def write_cloud(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        points: np.ndarray,
        *,
        is_dense: bool | None = None,
    ) -> None:
        """Write a structured point array as a ``sensor_msgs/msg/PointCloud2``.

        Parameters
        ----------
        topic : str
        stamp_ns : int
            Header stamp and log time, nanoseconds.
        frame_id : str
            Frame of the points.
        points : numpy.ndarray
            Structured array (e.g. of :func:`~lidarcal_ros.io.pointcloud.make_point_dtype`),
            written as one row of ``len(points)`` points.
        is_dense : bool or None, keyword-only
            Default: whether ``x, y, z`` (if present) are all finite.
        """
        fields, point_step, data = array_to_cloud_parts(points)
        n = data.size // point_step if point_step else 0
        if is_dense is None:
            names = points.dtype.names or ()
            is_dense = all(bool(np.isfinite(points[c]).all()) for c in "xyz" if c in names)
        types = self._typestore.types
        point_field = types["sensor_msgs/msg/PointField"]
        msg = types[POINTCLOUD2](
            header=self._header(stamp_ns, frame_id),
            height=1,
            width=n,
            fields=[
                point_field(name=name, offset=off, datatype=dt, count=cnt)
                for name, off, dt, cnt in fields
            ],
            is_bigendian=False,
            point_step=point_step,
            row_step=n * point_step,
            data=data,
            is_dense=is_dense,
        )
        self.write_message(topic, POINTCLOUD2, stamp_ns, msg)

    def write_pose(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        xyz: Sequence[float] | np.ndarray,
        *,
        quaternion_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> None:
        """Write a ``geometry_msgs/msg/PoseStamped``.

        Parameters
        ----------
        topic : str
        stamp_ns : int
            Header stamp and log time, nanoseconds.
        frame_id : str
        xyz : (3,) float
            Position in ``frame_id``, metres.
        quaternion_xyzw : (4,) float, keyword-only
            Orientation; identity by default.
        """
        types = self._typestore.types
        x, y, z = (float(v) for v in xyz)
        qx, qy, qz, qw = (float(v) for v in quaternion_xyzw)
        msg = types[POSE_STAMPED](
            header=self._header(stamp_ns, frame_id),
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            ),
        )
        self.write_message(topic, POSE_STAMPED, stamp_ns, msg)

    def write_trajectory_pose(self, topic: str, stamp_ns: int, frame_id: str,
                              trajectory: Trajectory, index: int) -> None:
        """Write sample ``index`` of ``trajectory`` as a PoseStamped: its position, and its
        orientation where it has one, else the identity."""
        q = None if trajectory.orientation is None else trajectory.orientation[index]
        self.write_pose(topic, stamp_ns, frame_id, trajectory.xyz[index],
                        quaternion_xyzw=IDENTITY_XYZW if q is None or np.isnan(q).any()
                        else tuple(float(v) for v in q))

    def close(self) -> None:
        """Finish the bag (index, metadata.yaml) and move it into place.

        Raises
        ------
        OutputError
            The bag cannot be finished (disk full); nothing is left of it.
        """
        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
            if self._staged:
                _install(self._target / f"{self._target.name}.mcap" if self._bare
                         else self._target, self.path)
        except Exception as err:  # surface as one line, leaving nothing partial
            self._discard()
            raise OutputError(f"{self.path}: cannot finish bag ({os_reason(err)})") from None
        remove_quietly(self._staging)

    def abort(self) -> None:
        """Stop writing and remove the partial output (a previous output stays)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.abort()
            except Exception:  # best effort
                logger.debug("error aborting %s", self.path, exc_info=True)
        self._discard()

    def _discard(self) -> None:
        remove_quietly(self._staging if self._staged else self.path)

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> Literal[False]:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def _strip_points(
    strip: Strip, floats: dict[str, np.ndarray], where: str
) -> np.ndarray:
    """The strip as one structured array of the lidarcal output layout."""
    n = len(strip)
    if strip.xyz.shape != (n, 3):
        raise InputError(f"{where}: xyz has shape {strip.xyz.shape}, expected ({n}, 3)")
    if not 0 <= strip.strip_id <= np.iinfo(np.uint16).max:
        raise InputError(f"{where}: strip_id {strip.strip_id} does not fit UINT16")
    base = make_point_dtype(tuple(floats), intensity=strip.intensity is not None)
    spec: list[tuple[Any, ...]] = [(name, base.fields[name][0]) for name in base.names or ()]  # type: ignore[index]
    natives: dict[str, np.ndarray] = {}
    for name, values in strip.extra.items():
        if name in _WRITTEN_CORE or name in floats:
            raise InputError(f"{where}: extra field '{name}' clashes with another field")
        arr = np.asarray(values)
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        if arr.shape[:1] != (n,) or arr.ndim > 2 or arr.dtype.kind not in "iuf":
            raise InputError(
                f"{where}: extra field '{name}' has shape {arr.shape} and dtype {arr.dtype}; "
                f"expected ({n},) or ({n}, k) numbers"
            )
        natives[name] = arr
        spec.append((name, arr.dtype.newbyteorder("<"), arr.shape[1:]))
    dtype = np.dtype(spec, align=True) if natives else base
    out = np.empty(n, dtype=dtype)
    out["x"], out["y"], out["z"] = strip.xyz[:, 0], strip.xyz[:, 1], strip.xyz[:, 2]
    out["t"] = strip.t
    if strip.intensity is not None:
        out["intensity"] = strip.intensity
    out["strip_id"] = strip.strip_id
    for name, values in {**floats, **natives}.items():
        if np.shape(values)[:1] != (n,):
            raise InputError(f"{where}: extra field '{name}' has {len(values)} values, not {n}")
        out[name] = values
    return out


def _chunk_bounds(t: np.ndarray, chunk_seconds: float) -> list[int]:
    """Boundaries of consecutive ``chunk_seconds`` windows over sorted times (NaN last)."""
    n_finite = int(np.count_nonzero(np.isfinite(t)))
    if n_finite == 0:
        return [0, int(t.size)]
    tf = t[:n_finite]
    edges = tf[0] + chunk_seconds * np.arange(1, np.floor((tf[-1] - tf[0]) / chunk_seconds) + 1)
    cuts = np.unique(np.searchsorted(tf, edges, side="left"))
    cuts = cuts[(cuts > 0) & (cuts < n_finite)]
    return [0, *cuts.tolist(), int(t.size)]


def write_mission_bag(
    path: str | os.PathLike[str],
    mission: Mission,
    *,
    chunk_seconds: float = 0.1,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    control_topic: str = "/lidar/control_points",
    overwrite: bool = False,
    extra_point_fields: dict[str, list[np.ndarray]] | None = None,
) -> Path:
    """Write a mission as a bag of the lidarcal contract.

    Parameters
    ----------
    path : path-like
        Output rosbag2 directory (or bare ``.mcap`` file).
    mission : Mission
    chunk_seconds : float, keyword-only
        Duration of scanning per PointCloud2 chunk, seconds.
    points_topic, trajectory_topic, control_topic : str, keyword-only
    overwrite : bool, keyword-only
        Replace an existing output.
    extra_point_fields : dict of str to list of arrays, keyword-only
        Further FLOAT32 point fields, one array per strip (in ``mission.strips`` order).
        ``Strip.extra`` arrays are written too, in their own dtype.

    Returns
    -------
    pathlib.Path
        The written bag.

    Notes
    -----
    Each strip becomes time-ordered chunks with fields ``x, y, z, t`` FLOAT64,
    ``intensity`` FLOAT32 (if present), ``strip_id`` UINT16 and the extras, stamped with the
    chunk's first point time, in ``mission.frame_id``. The trajectory is written as
    PoseStamped, with its orientation where it has one, else the identity; the
    control points as one transient-local
    PointCloud2 (x, y, z) at the start. All messages are in log-time order.
    """
    if not chunk_seconds > 0:
        raise ConfigError(f"chunk_seconds must be positive, got {chunk_seconds}")
    extras = extra_point_fields or {}
    for name, per_strip in extras.items():
        if len(per_strip) != len(mission.strips):
            raise InputError(
                f"{path}: extra field '{name}' has {len(per_strip)} arrays for "
                f"{len(mission.strips)} strips"
            )
    frame = mission.frame_id
    # (stamp_ns, kind: 0 pose / 1 cloud, index) events, sorted once.
    events: list[tuple[int, int, int]] = []
    clouds: list[np.ndarray] = []
    for k, strip in enumerate(mission.strips):
        where = f"{path}: strip {strip.strip_id}"
        t = np.asarray(strip.t, dtype=np.float64)
        sorted_ = bool(np.isfinite(t).all()) and _nondecreasing(t)
        order = None if sorted_ else np.argsort(t, kind="stable")  # NaN times go last
        floats = {name: np.asarray(v[k], dtype=np.float32) for name, v in extras.items()}
        points = _strip_points(strip, floats, where)
        if order is not None:
            points = points[order]
        if len(points) and not np.isfinite(points["t"][0]):
            raise InputError(f"{where}: no finite point time")
        if len(points) and points["t"][0] < 0:
            raise InputError(f"{where}: negative point time {points['t'][0]}")
        bounds = _chunk_bounds(points["t"], chunk_seconds)
        for a, b in _pairs(bounds):
            if b > a:
                clouds.append(points[a:b])
                events.append((seconds_to_ns(points["t"][a]), 1, len(clouds) - 1))
    traj = mission.trajectory
    for i in range(len(traj)):
        if not traj.t[i] >= 0:
            raise InputError(f"{path}: trajectory time {traj.t[i]} is negative or not finite")
        events.append((seconds_to_ns(traj.t[i]), 0, i))
    events.sort()
    start_ns = events[0][0] if events else 0

    latched = [control_topic] if mission.control is not None else []
    with BagWriter(path, overwrite=overwrite, latched_topics=latched) as writer:
        if mission.control is not None and len(mission.control):
            xyz = np.asarray(mission.control.xyz, dtype=np.float64).reshape(-1, 3)
            cp = np.empty(len(xyz), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
            cp["x"], cp["y"], cp["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            writer.write_cloud(control_topic, start_ns, frame, cp)
        for stamp, kind, key in events:
            if kind == 1:
                writer.write_cloud(points_topic, stamp, frame, clouds[key])
            else:
                writer.write_trajectory_pose(trajectory_topic, stamp, frame, traj, key)
    logger.info(
        "%s: wrote %d strips (%d chunks), %d poses", path, len(mission.strips),
        len(clouds), len(traj),
    )
    return Path(path)
