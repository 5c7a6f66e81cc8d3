"""The I/O floor of ``lidarcal correct``: read a mission bag and write the same output with
no correction at all.

    .venv/bin/python bench/io_floor.py BAG OUT.mcap [ZSTD_LEVEL]    # or OUT.laz

What a converter written with the same libraries does, in one thread: every message of the
bag read in order (rosbags' reader: MCAP chunks decompressed, records parsed); each cloud
decoded into a numpy view of its points; for an MCAP output, every message passed through and
beside each cloud a cloud of the corrected layout (the input's fields, then the five fields
``lidarcal correct`` adds) serialised and written (rosbags' writer: zstd chunks at the level
``lidarcal correct`` uses, which the benchmark passes); for a LAZ output, every point written
as LAS 1.4 point format 6 with the same fields and extra bytes (x, y, z scaled to millimetres,
GPS time, intensity, strip as point source, return numbers, scan angle, reflectance, range,
incidence, flags) by laspy with lazrs, in runs of at least 100k points. The coordinates are
moved and the added fields hold varied floats, so that the output compresses as lidarcal's
does. Process start and imports included (the benchmark times the process). Imports nothing
of lidarcal.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

POINTS = "/lidar/points"
CORRECTED = "/lidar/points_corrected"
#: The fields lidarcal correct adds, as it lays them out (4-byte aligned after the input's).
ADDED = (("reflectance", "<f4"), ("range", "<f4"), ("incidence", "<f4"),
         ("scan_angle", "<f4"), ("correction_flags", "u1"))
DATATYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
CODES = {np.dtype(v).str.lstrip("<|"): k for k, v in DATATYPES.items()}


def cloud_array(msg) -> np.ndarray:
    """The points of a (little-endian, one-row-per-point) PointCloud2 as a structured view."""
    dtype = np.dtype({"names": [f.name for f in msg.fields],
                      "formats": [DATATYPES[f.datatype] for f in msg.fields],
                      "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    return np.frombuffer(msg.data, dtype=dtype, count=msg.width * msg.height)


def output_dtype(dtype: np.dtype) -> np.dtype:
    """The corrected layout of a cloud of ``dtype``: its fields, then the fields of
    :data:`ADDED`, each aligned to its size from the next 4 bytes on, rows padded to 8 bytes."""
    names, formats, offsets = list(dtype.names), [dtype.fields[n][0] for n in dtype.names], \
        [dtype.fields[n][1] for n in dtype.names]
    pos = (dtype.itemsize + 3) // 4 * 4
    for name, kind in ADDED:
        k = np.dtype(kind)
        pos = (pos + k.itemsize - 1) // k.itemsize * k.itemsize
        names.append(name)
        formats.append(k)
        offsets.append(pos)
        pos += k.itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": (pos + 7) // 8 * 8})


def fill_added(rows: np.ndarray, arr: np.ndarray) -> None:
    """New coordinates (moved by a centimetre) and values in the added fields as varied as
    the correction's (floats of the points' own coordinates): zeros, or coordinates the same
    as the input's in the same chunk, would compress to nothing, and the floor's output must
    cost what lidarcal's does to compress."""
    for c in "xyz":
        rows[c] = arr[c] + 0.01
    x, y, z = arr["x"] - arr["x"][0], arr["y"] - arr["y"][0], arr["z"] - arr["z"][0]
    rows["reflectance"] = arr["intensity"] * (1.0 + 1e-3 * np.sin(x))
    rows["range"] = 1000.0 + x + 0.5 * y + 0.25 * z
    rows["incidence"] = 1e-3 * y + 1e-4 * x
    rows["scan_angle"] = 1e-3 * x + 1e-5 * z


def to_mcap(bag: Path, out: Path, zstd_level: int) -> int:
    """Copy the bag to an MCAP bag at ``out`` with, beside each cloud, one of the corrected
    layout (zstd at ``zstd_level``); the number of points."""
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    tmp = Path(tempfile.mkdtemp(prefix=".floor-", dir=out.parent)) / "bag"
    points = 0
    with Reader(bag) as reader:
        writer = Writer(tmp, version=8, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            zstd = sys.modules["rosbags.rosbag2.storage_mcap"].zstd
            options = {zstd.CompressionParameter.compression_level: zstd_level,
                       zstd.CompressionParameter.checksum_flag: 1}  # (as lidarcal's chunks)
            writer.storage.compressor = lambda data: zstd.compress(data, options=options)
            conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
                     for c in reader.connections}
            corrected = writer.add_connection(CORRECTED, "sensor_msgs/msg/PointCloud2",
                                              typestore=store)
            field_cls = store.types["sensor_msgs/msg/PointField"]
            for conn, stamp, raw in reader.messages():
                writer.write(conns[conn.id], stamp, raw)
                if conn.topic != POINTS:
                    continue
                msg = store.deserialize_cdr(memoryview(raw), conn.msgtype)
                arr = cloud_array(msg)
                dtype = output_dtype(arr.dtype)
                rows = np.zeros(len(arr), dtype=dtype)
                rows.view(np.uint8).reshape(len(arr), dtype.itemsize)[:, :arr.dtype.itemsize] = \
                    arr.view(np.uint8).reshape(len(arr), arr.dtype.itemsize)
                fill_added(rows, arr)
                fields = [field_cls(name=n, offset=dtype.fields[n][1],
                                    datatype=CODES[dtype.fields[n][0].str.lstrip("<|")], count=1)
                          for n in dtype.names]
                new = dataclasses.replace(msg, height=1, width=len(arr), fields=fields,
                                          point_step=dtype.itemsize,
                                          row_step=len(arr) * dtype.itemsize,
                                          data=rows.view(np.uint8))
                writer.write(corrected, stamp, store.serialize_cdr(new, conn.msgtype))
                points += len(arr)
    (tmp / "bag.mcap").replace(out)
    shutil.rmtree(tmp.parent)
    return points


def to_laz(bag: Path, out: Path, zstd_level: int) -> int:
    """Write the bag's points to a LAZ 1.4 file (point format 6 with the corrected fields as
    extra bytes) at ``out``; the number of points (``zstd_level`` unused)."""
    import laspy
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.dtype(k)) for n, k in (
        ("reflectance", "f4"), ("range", "f4"), ("incidence", "f4"),
        ("correction_flags", "u1"))])
    header.scales = np.array([0.001, 0.001, 0.001])
    points = 0
    run: list[np.ndarray] = []
    writer = None

    def write(parts: list[np.ndarray]) -> None:
        nonlocal writer
        arr = np.concatenate(parts)
        if writer is None:
            header.offsets = np.array([np.floor(arr["x"].min() / 1e3) * 1e3,
                                       np.floor(arr["y"].min() / 1e3) * 1e3, 0.0])
            writer = laspy.open(str(out), mode="w", header=header, do_compress=True)
        rec = laspy.ScaleAwarePointRecord.zeros(len(arr), header=header)
        rec.x, rec.y, rec.z = arr["x"] + 0.01, arr["y"] + 0.01, arr["z"] + 0.01
        rec.gps_time = arr["t"] - 1e9
        rec.intensity = np.clip(np.rint(arr["intensity"]), 0, 65535).astype(np.uint16)
        rec.point_source_id = arr["strip_id"].astype(np.uint16)
        rec.return_number = np.ones(len(arr), np.uint8)
        rec.number_of_returns = np.ones(len(arr), np.uint8)
        rec.scan_angle = np.rint((arr["x"] - arr["x"].mean()) / 1000.0 / 0.006).astype(
            np.int16)
        x, y, z = arr["x"] - arr["x"][0], arr["y"] - arr["y"][0], arr["z"] - arr["z"][0]
        rec["reflectance"] = arr["intensity"] * (1.0 + 1e-3 * np.sin(x))
        rec["range"] = 1000.0 + x + 0.5 * y + 0.25 * z
        rec["incidence"] = 1e-3 * y + 1e-4 * x
        rec["correction_flags"] = np.zeros(len(arr), np.uint8)
        writer.write_points(rec)

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == POINTS]
        run_points = 0
        for conn, _stamp, raw in reader.messages(connections=conns):
            arr = cloud_array(store.deserialize_cdr(memoryview(raw), conn.msgtype))
            run.append(arr)
            run_points += len(arr)
            points += len(arr)
            if run_points >= 100_000:
                write(run)
                run, run_points = [], 0
        if run:
            write(run)
    assert writer is not None
    writer.close()
    return points


def main(argv: list[str]) -> int:
    """Write the I/O floor output of the command line's bag; exit status 0, or 2 for a usage
    error."""
    if len(argv) not in (2, 3) or argv[0] in ("-h", "--help"):
        print("usage: io_floor.py BAG OUT.mcap|OUT.laz [ZSTD_LEVEL]", file=sys.stderr)
        return 2
    bag, out = Path(argv[0]), Path(argv[1])
    level = int(argv[2]) if len(argv) > 2 else 3
    n = (to_laz if out.suffix == ".laz" else to_mcap)(bag, out, level)
    print(f"io_floor: {n} points -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
