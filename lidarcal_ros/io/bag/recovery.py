"""Recovery of a damaged mission bag: every message readable before the damage, in a new bag.

docs/internals.md, "Bags".
"""

from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lidarcal_ros.errors import BagError
from lidarcal_ros.io.bag.format import normalize_msgtype, stamp_seconds
from lidarcal_ros.io.bag.reader import ReadableMcap
from lidarcal_ros.io.bag.writer import BagWriter

logger = logging.getLogger(__name__)


@dataclass
class RecoveredBag:
    """What :func:`recover_bag` kept.

    Attributes
    ----------
    output : Path
        The bag written.
    messages : dict of str to int
        Messages kept, per topic.
    start_ns, end_ns : int
        Log times of the first and last message kept, nanoseconds (0 if none).
    damage : dict of str to str
        Per damaged file, what ended its reading; intact files are absent.
    skipped : dict of str to str
        Topics left out, and why (not CDR, no schema).
    clouds_after_trajectory : int
        Clouds of a cut recording left out because they reach past its last readable
        trajectory sample.
    """

    output: Path
    messages: dict[str, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    damage: dict[str, str] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    clouds_after_trajectory: int = 0

    def lines(self) -> list[str]:
        """A summary for people."""
        total = sum(self.messages.values())
        span = (self.end_ns - self.start_ns) / 1e9 if total else 0.0
        out = [f"{self.output}: {total} messages kept, {span:.1f} s of log time"]
        out += [f"  {topic}: {n}" for topic, n in sorted(self.messages.items())]
        if not self.damage:
            out.append("no damage found: every message of the source was kept")
        for name, what in self.damage.items():
            out.append(f"{name}: read up to the damage ({what})")
        if self.clouds_after_trajectory:
            out.append(f"{self.clouds_after_trajectory} clouds left out: they reach past the "
                       "last readable trajectory sample")
        out += [f"{topic}: left out ({why})" for topic, why in self.skipped.items()]
        return out


def bag_files(source: Path) -> list[Path]:
    """The MCAP files of a bag, in recording order: a bare file, or a rosbag2 directory's
    ``*.mcap`` by their split index (``name_0.mcap``, ``name_1.mcap``, ...), whether or not
    ``metadata.yaml`` was written."""
    if not source.exists():
        raise BagError(f"{source}: no such bag (file or directory not found)")
    if source.is_file():
        return [source]

    def split_index(path: Path) -> tuple[int, str]:
        found = re.search(r"_(\d+)$", path.stem)
        return (int(found.group(1)) if found else 0, path.name)

    files = sorted(source.glob("*.mcap"), key=split_index)
    if not files:
        zstd = sorted(source.glob("*.mcap.zstd"))
        if zstd:
            raise BagError(f"{source}: file-compressed bag ({zstd[0].name}): decompress it "
                           "first (zstd -d); a cut zstd file cannot be recovered here")
        raise BagError(f"{source}: no .mcap file to recover")
    return files


def recover_bag(source: str | os.PathLike[str], output: str | os.PathLike[str], *,
                overwrite: bool = False, points_topic: str = "/lidar/points",
                trajectory_topic: str = "/lidar/trajectory",
                time_field: str = "t") -> RecoveredBag:
    """Write every message of ``source`` readable before its damage to a new bag ``output``.

    Where the recording was cut, the clouds that reach past the last readable trajectory
    sample are left out too (counted in the summary): the trajectory usually stops a little
    before the points do, and points it does not cover cannot be georeferenced (``lidarcal
    calibrate`` refuses a mission with such points).

    Parameters
    ----------
    source : path-like
        A rosbag2 directory (``metadata.yaml`` may be missing) or a bare ``.mcap`` file.
    output : path-like
        The new bag: a directory, or a bare file if it ends in ``.mcap``.
    overwrite : bool, keyword-only
        Replace an existing output.
    points_topic, trajectory_topic, time_field : str, keyword-only
        Where the strips and the trajectory are (docs/interface.md), and the points' time field
        (``t`` also finds the aliases ``time``, ``timestamp``, ``gps_time``).

    Returns
    -------
    RecoveredBag

    Raises
    ------
    BagError
        No MCAP file in ``source``, ``output`` is ``source``, or nothing was readable.
    """
    source, output = Path(source), Path(output)
    if output.resolve() == source.resolve():
        raise BagError(f"{output}: the output must not be the damaged bag itself")
    files = [ReadableMcap(path) for path in bag_files(source)]
    # First pass: where the readable trajectory ends (and which files are damaged).
    trajectory_end = -math.inf
    for file in files:
        for channel, schema, message in file.messages():
            if channel.topic == trajectory_topic and schema is not None:
                trajectory_end = max(trajectory_end, _header_seconds(message.data, schema))
    cut = any(file.damage for file in files)
    result = RecoveredBag(output, damage={str(f.path): f.damage for f in files if f.damage})
    keep_until = trajectory_end if cut and math.isfinite(trajectory_end) else math.inf
    with BagWriter(output, overwrite=overwrite) as writer:
        for file in files:
            declared: dict[int, tuple[str, str] | None] = {}
            for channel, schema, message in file.messages():
                if channel.id not in declared:
                    declared[channel.id] = _declare(channel, schema, writer, result)
                kept = declared[channel.id]
                if kept is None:
                    continue
                topic, msgtype = kept
                if topic == points_topic and _latest_point_s(message.data, time_field) > \
                        keep_until:
                    result.clouds_after_trajectory += 1
                    continue
                stamp = int(message.log_time)
                writer.write_raw(topic, msgtype, stamp, message.data)
                first = not result.messages
                result.messages[topic] = result.messages.get(topic, 0) + 1
                result.start_ns = stamp if first else min(result.start_ns, stamp)
                result.end_ns = stamp if first else max(result.end_ns, stamp)
        if not result.messages:
            raise BagError(f"{source}: no message is readable"
                           + "".join(f"; {name}: {what}" for name, what in
                                     result.damage.items())
                           + "".join(f"; {topic} left out: {why}" for topic, why in
                                     result.skipped.items()))
    for name, what in result.damage.items():
        logger.info("%s: read up to the damage (%s)", name, what)
    return result


def _header_seconds(data: bytes, schema: Any) -> float:
    """``header.stamp`` of a trajectory message, s (-inf if it cannot be read)."""
    from lidarcal_ros.io.cloud.messages import deserialize

    try:
        return stamp_seconds(deserialize(data, normalize_msgtype(schema.name)).header.stamp)
    except Exception:  # not a stamped message: it does not bound the points
        return -math.inf


def _latest_point_s(data: bytes, time_field: str) -> float:
    """The latest firing time of a cloud, s (-inf if it has none or cannot be read: such a
    cloud is kept as it is, for the commands that read it to judge)."""
    from lidarcal_ros.io.cloud.columns import resolve_time_field, time_span
    from lidarcal_ros.io.cloud.messages import parse_cloud

    try:
        points = parse_cloud(data).points
        latest = time_span(points[resolve_time_field(points, time_field)])[1]
    except Exception:  # a malformed cloud is not this tool's to refuse
        return -math.inf
    return latest if math.isfinite(latest) else -math.inf


def _declare(channel: Any, schema: Any, writer: BagWriter,
             result: RecoveredBag) -> tuple[str, str] | None:
    """Declare a channel's topic in the output; None for one that cannot be kept."""
    if schema is None or channel.message_encoding != "cdr":
        why = "no schema" if schema is None else f"encoding {channel.message_encoding!r}"
        result.skipped[channel.topic] = f"{why}, not a ROS 2 CDR message"
        return None
    msgtype = normalize_msgtype(schema.name)
    definition = schema.data.decode("utf-8", "replace") if schema.encoding == "ros2msg" else None
    writer.add_topic(channel.topic, msgtype, latched=_latched(channel.metadata),
                     msgdef=definition)
    return channel.topic, msgtype


def _latched(metadata: dict[str, str]) -> bool:
    """Whether rosbag2 recorded the topic as offered with transient-local durability (as
    the control points are), from the channel's ``offered_qos_profiles`` (parsed by rosbags,
    as :class:`~lidarcal_ros.io.bag.reader.BagReader` parses them)."""
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2.metadata import parse_qos

    try:
        profiles = parse_qos(metadata.get("offered_qos_profiles", ""))
    except Exception:  # unreadable QoS: informative only, as for BagReader
        return False
    return any(q.durability == QosDurability.TRANSIENT_LOCAL for q in profiles)


__all__ = ["RecoveredBag", "bag_files", "recover_bag"]
