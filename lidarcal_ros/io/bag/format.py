"""What the bag reader and writer share: message types, typestore, QoS records, time conversions.

Bag log times and header stamps are integer nanoseconds; mission times float seconds.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

#: Nanoseconds in a second (bag log times and stamps are integer nanoseconds).
NS_PER_SECOND = 1_000_000_000
_INFINITE = QosTime(9223372036, 854775807)


def standard_typestore() -> Typestore:
    """A fresh typestore with the standard ROS 2 message definitions."""
    store = getattr(Stores, "ROS2_JAZZY", Stores.ROS2_HUMBLE)
    return get_typestore(store)


def empty_typestore() -> Typestore:
    """A typestore without a type, for the definitions a bag carries (building the standard
    one imports every ROS 2 release's definitions: some 0.07 s)."""
    return get_typestore(Stores.EMPTY)


def add_standard_types(store: Typestore) -> None:
    """Add to ``store`` the standard ROS 2 types it lacks (those it has are kept)."""
    standard = standard_typestore()
    missing = {k: v for k, v in standard.fielddefs.items() if k not in store.fielddefs}
    if missing:
        store.register(missing)


def normalize_msgtype(name: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``; names that already have a namespace are kept."""
    parts = name.split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    return name


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
    return int(sec) * NS_PER_SECOND + round(float(t - sec) * 1e9)


def ns_to_seconds(ns: int) -> float:
    """Integer nanoseconds to float seconds."""
    sec, nsec = divmod(int(ns), NS_PER_SECOND)
    return float(sec) + nsec * 1e-9


def stamp_seconds(stamp: Any) -> float:
    """A builtin_interfaces/Time as float seconds (the trajectory's times)."""
    return float(stamp.sec) + int(stamp.nanosec) * 1e-9


__all__ = ["NS_PER_SECOND", "ODOMETRY", "POINTCLOUD2", "POSE_STAMPED",
           "POSE_WITH_COVARIANCE_STAMPED", "add_standard_types",
           "empty_typestore", "make_qos", "normalize_msgtype", "ns_to_seconds", "seconds_to_ns",
           "stamp_seconds", "standard_typestore"]
