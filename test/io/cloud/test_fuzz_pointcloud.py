"""Property-based fuzzing of the PointCloud2 decoder: any fields, sizes and bytes give points
or a one-line CloudFormatError, never another exception or an allocation beyond the data."""

from __future__ import annotations

import numpy as np
from helpers_fuzz import BUDGET, mutated_bytes
from hypothesis import example, given
from hypothesis import strategies as st

from lidarcal_ros.errors import CloudFormatError
from lidarcal_ros.io.bag.format import POINTCLOUD2
from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud, serialize, typestore

U32 = 2**32 - 1
_sizes = st.one_of(st.integers(0, 64), st.sampled_from([U32, 2**31, 2**31 - 1, 2**16 + 1]))


@st.composite
def clouds(draw: st.DrawFn) -> bytes:
    """CDR of a PointCloud2 whose every size may lie or overflow."""
    ts = typestore()
    PointField = ts.types["sensor_msgs/msg/PointField"]
    PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    fields = [PointField(name=draw(st.sampled_from(["x", "y", "z", "t", "intensity", "", "x"])),
                         offset=draw(_sizes), datatype=draw(st.integers(0, 12)),
                         count=draw(_sizes))
              for _ in range(draw(st.integers(0, 5)))]
    data = np.frombuffer(draw(st.binary(max_size=512)), dtype=np.uint8)
    msg = PointCloud2(header=Header(stamp=Time(sec=1, nanosec=2), frame_id="map"),
                      height=draw(_sizes), width=draw(_sizes), fields=fields,
                      is_bigendian=draw(st.booleans()), point_step=draw(_sizes),
                      row_step=draw(_sizes), data=data, is_dense=True)
    return serialize(msg, POINTCLOUD2)


def _check(raw: bytes) -> None:
    try:
        cloud = parse_cloud(raw, source="/fuzz")
    except CloudFormatError as err:
        assert "\n" not in str(err) and str(err).startswith("/fuzz: ")
        return
    # Points are what the data holds: a view, or (padded rows) a copy no larger than it.
    assert cloud.points.nbytes <= len(raw)
    assert len(cloud) == cloud.msg.width * cloud.msg.height


@BUDGET
@given(clouds())
@example(b"")
def test_any_cloud_layout_gives_points_or_one_line(raw: bytes) -> None:
    _check(raw)


_VALID = cloud_cdr(0, "map", np.zeros(20, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                 ("t", "<f8")]))


@BUDGET
@given(mutated_bytes(bytes(_VALID)))
def test_damaged_cloud_bytes_give_points_or_one_line(raw: bytes) -> None:
    _check(raw)


def test_the_fuzzed_decoder_reads_an_honest_cloud() -> None:
    """The seed of the mutations is read whole (a fuzzer of a decoder that refuses
    everything would pass)."""
    cloud = parse_cloud(bytes(_VALID), source="/fuzz")
    assert len(cloud) == 20 and cloud.points.dtype.names == ("x", "y", "z", "t")
