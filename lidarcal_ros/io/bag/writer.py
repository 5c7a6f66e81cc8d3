"""Writing rosbag2 bags with MCAP storage, without ROS.

A rosbag2 directory or a bare ``.mcap``, complete or absent (docs/internals.md, "Bags"). Times
integer nanoseconds; coordinates metres in ``header.frame_id``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import Connection
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2.errors import WriterError
from rosbags.typesys import get_types_from_msg

from lidarcal_ros.core.georeferencing.attitude import IDENTITY_XYZW
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import BagError, OutputError, one_line
from lidarcal_ros.io.bag.chunk_copy import ChunkCopy, adopt_and_copy, plan_chunk_copy
from lidarcal_ros.io.bag.chunk_writer import BagWriterBackend
from lidarcal_ros.io.bag.format import (
    NS_PER_SECOND,
    POINTCLOUD2,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    add_standard_types,
    make_qos,
    normalize_msgtype,
    standard_typestore,
)
from lidarcal_ros.io.cloud.pointcloud import array_to_cloud_parts, without_padding_garbage
from lidarcal_ros.io.output_files import (
    APPEARED,
    EXISTS,
    install,
    os_reason,
    remove_quietly,
    temporary_beside,
)

logger = logging.getLogger(__name__)


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


def _storage_name(name: str) -> str:
    """``name`` cut (at a character) so that its storage file ``NAME.mcap`` fits in the 255
    bytes of a file name."""
    while len(f"{name}.mcap".encode()) > 255:
        name = name[:-1]
    return name


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
    typestore : rosbags Typestore, keyword-only
        The type definitions to write with, e.g. an input bag's
        (:attr:`~lidarcal_ros.io.bag.reader.BagReader.typestore`: its messages passed
        through keep their definitions); the standard ROS 2 ones are added where a type is
        missing. Default: the standard ones.

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
        typestore: Any = None,
    ) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.latched_topics = set(latched_topics)
        self.compress = compress
        self._bare = self.path.suffix == ".mcap"
        inner = self.path.stem if self._bare else self.path.name
        # A legal directory name of up to 255 bytes: the storage file in it, NAME.mcap, would
        # pass the limit; such a bag is staged under a shorter name and renamed whole.
        short = _storage_name(inner)
        self._staged = staged or self._bare or short != inner
        self._staging = temporary_beside(self.path)
        # The bag inside the staging directory keeps its final name where it can (the names
        # of its files in metadata.yaml come from it).
        self._target = self._staging / short if self._staged else self.path
        self._writer: BagWriterBackend | None = None
        self._connections: dict[str, Connection] = {}
        self._typestore = standard_typestore() if typestore is None else typestore
        self._standard_added = typestore is None

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
        except BaseException:  # Ctrl-C, SIGTERM: the staging directory goes too
            self._discard()
            raise
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
            ``.msg`` definition text (ROS 2 concatenated form) for types the writer's
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
        self._register_type(topic, msgtype, msgdef)
        if latched is None:
            latched = topic in self.latched_topics
        self._connections[topic] = self._writer.add_connection(
            topic,
            msgtype,
            typestore=self._typestore,
            offered_qos_profiles=[make_qos(transient_local=latched)],
        )

    def _register_type(self, topic: str, msgtype: str, msgdef: str | None) -> None:
        """Make ``msgtype`` known to the typestore (from ``msgdef`` where the typestore
        lacks it, else from the standard definitions); BagError if it cannot be."""
        if msgtype in self._typestore.fielddefs:
            return
        if not msgdef:
            self._add_standard_types()
            if msgtype in self._typestore.fielddefs:
                return
            raise BagError(f"{self.path}: unknown message type {msgtype} for {topic}")
        try:
            typs = get_types_from_msg(msgdef, msgtype)
            self._typestore.register(
                {k: v for k, v in typs.items() if k not in self._typestore.fielddefs}
            )
        except Exception as err:  # bad definition text
            raise BagError(
                f"{self.path}: cannot parse definition of {msgtype} ({one_line(err)})"
            ) from None

    def _add_standard_types(self) -> None:
        """The standard ROS 2 types, where the typestore given lacks them (once)."""
        if not self._standard_added:
            add_standard_types(self._typestore)
            self._standard_added = True

    @property
    def _types(self) -> dict[str, Any]:
        """The typestore's message classes, the standard ones among them (typed writes)."""
        self._add_standard_types()
        return self._typestore.types

    @property
    def message_classes(self) -> dict[str, Any]:
        """The message classes by type name (``pkg/msg/Type``) to build what
        :meth:`write_message` writes; the standard ROS 2 ones among them."""
        return self._types

    def copy_chunks_of(self, bag: Any, new_topics: dict[str, str]) -> ChunkCopy | None:
        """Pass every message of an open input bag through by copying its compressed
        chunks (:mod:`lidarcal_ros.io.bag.chunk_copy`), where it allows that.

        Call before writing anything. The input's topics then have the input's channel and
        schema records (QoS as recorded), and their messages are in the output: write
        only messages on ``new_topics`` (topic -> type) afterwards.

        Parameters
        ----------
        bag : BagReader
        new_topics : dict of str to str
            Topics the output adds, and their types.

        Returns
        -------
        ChunkCopy or None
            What was copied; None when nothing was (the input does not allow it, or a
            topic of it has a type this writer cannot record): write every message.
        """
        if self._writer is None or self._connections:
            raise BagError(f"{self.path}: chunks are copied only into a new, empty bag")
        plan = plan_chunk_copy(bag, new_topics, new_topics.values())
        if plan is None:
            return None
        try:
            for copied in plan.channels.values():
                topic = copied.channel.topic
                self._register_type(topic, copied.msgtype, bag.topics[topic].msgdef or None)
        except BagError as err:
            logger.info("%s: chunks not copied (%s); messages written one by one",
                        bag.path, err)
            return None
        digests = {c.msgtype: self._typestore.hash_rihs01(c.msgtype)
                   for c in plan.channels.values()}
        try:
            adopt_and_copy(self._writer, plan, digests)
        except (WriterError, OSError) as err:
            raise OutputError(f"{self.path}: cannot write bag ({os_reason(err)})") from None
        for connection in self._writer.connections:
            self._connections[connection.topic] = connection
        return plan

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
            Definition text for a type the writer's typestore lacks.
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
        types = self._types
        sec, nsec = divmod(int(stamp_ns), NS_PER_SECOND)
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
            Structured array (e.g. of :func:`~lidarcal_ros.io.cloud.pointcloud.make_point_dtype`),
            written as one row of ``len(points)`` points.
        is_dense : bool or None, keyword-only
            Default: whether ``x, y, z`` (if present) are all finite.
        """
        fields, point_step, data = array_to_cloud_parts(without_padding_garbage(points))
        n = data.size // point_step if point_step else 0
        if is_dense is None:
            names = points.dtype.names or ()
            is_dense = all(bool(np.isfinite(points[c]).all()) for c in "xyz" if c in names)
        types = self._types
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
        types = self._types
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
        orientation where it has one, else the identity. A trajectory with position sigmas
        is written as PoseWithCovarianceStamped instead (every sample: one type a topic),
        the covariance diagonal in x, y, z (map E, N, U; m^2), zero where a sample has no
        sigma and for the orientation (unknown)."""
        q = None if trajectory.orientation is None else trajectory.orientation[index]
        quaternion = (IDENTITY_XYZW if q is None or np.isnan(q).any()
                      else tuple(float(v) for v in q))
        if trajectory.position_sigma is None:
            self.write_pose(topic, stamp_ns, frame_id, trajectory.xyz[index],
                            quaternion_xyzw=quaternion)
            return
        sigma = trajectory.position_sigma[index]
        covariance = np.zeros(36)
        covariance[[0, 7, 14]] = np.where(np.isfinite(sigma), sigma, 0.0) ** 2
        types = self._types
        x, y, z = (float(v) for v in trajectory.xyz[index])
        qx, qy, qz, qw = quaternion
        msg = types[POSE_WITH_COVARIANCE_STAMPED](
            header=self._header(stamp_ns, frame_id),
            pose=types["geometry_msgs/msg/PoseWithCovariance"](
                pose=types["geometry_msgs/msg/Pose"](
                    position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                    orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
                covariance=covariance))
        self.write_message(topic, POSE_WITH_COVARIANCE_STAMPED, stamp_ns, msg)

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
                install(self._target / f"{self._target.name}.mcap" if self._bare
                        else self._target, self.path, overwrite=self.overwrite)
        except FileExistsError:
            self._discard()
            raise OutputError(f"{self.path}: {APPEARED}") from None
        except Exception as err:  # surface as one line, leaving nothing partial
            self._discard()
            raise OutputError(f"{self.path}: cannot finish bag ({os_reason(err)})") from None
        except BaseException:  # Ctrl-C, SIGTERM
            self._discard()
            raise
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


__all__ = ["BagWriter"]
