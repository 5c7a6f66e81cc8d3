"""``lidarcal import`` (survey deliveries into a mission bag) and ``lidarcal recover``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lidarcal_ros.cli.common import (
    add_dask_option,
    add_quiet_option,
    finite_float,
    other_paths,
    progress_bar,
)
from lidarcal_ros.io.output_files import check_output
from lidarcal_ros.io.url_cache import source_of

__all__ = ["add_import_command", "add_recover_command", "cmd_import", "cmd_recover"]


def add_import_command(sub: Any) -> None:
    """The ``lidarcal import`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("import", help="LAS/LAZ strips and a trajectory into a mission bag",
                       description="Bring LAS/LAZ flight lines (LAS 1.0-1.4, any number of "
                       "files) and an Applanix SBET, an ASCII trajectory time,x,y,z[,...], or "
                       "a trajectory rebuilt from multiple returns into a mission bag that "
                       "calibrate, correct and replay read.",
                       epilog="Strips come from point_source_id, or from GPS-time gaps where "
                       "it is 0 or the same everywhere. LAS GPS time is adjusted standard "
                       "time (global encoding bit 0) or week seconds, SBET time week seconds: "
                       "the GPS week comes from the absolute side, the bag's clock is UNIX "
                       "time whenever an absolute time is known, else week seconds. SBET "
                       "positions (EPSG:4979) are projected to the points' CRS, heights kept "
                       "ellipsoidal unless the CRS is compound; coordinates in feet are "
                       "converted to metres.")
    p.add_argument("inputs", nargs="+", type=source_of, metavar="STRIP",
                   help="LAS or LAZ files (paths or URLs: s3://, https://...)")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output rosbag2 directory (or .mcap file)")
    p.add_argument("--trajectory", dest="trajectory_source", default="estimate",
                   metavar="SBET|CSV|estimate",
                   help="SBET (.out), ASCII trajectory, or 'estimate' to rebuild it from "
                   "multiple returns (default)")
    p.add_argument("--trajectory-accuracy", metavar="SMRMSG|none",
                   help="the SBET's accuracy file (Applanix smrmsg): per-epoch position "
                   "sigmas carried in the bag (PoseWithCovarianceStamped) and used as the "
                   "strips' trajectory-error priors (default: smrmsg_NAME.out beside "
                   "sbet_NAME.out where there is one; none: not)")
    p.add_argument("--crs", help="CRS of the points, e.g. EPSG:32633 (default: LAS header)")
    p.add_argument("--trajectory-crs",
                   help="CRS of the trajectory positions (default EPSG:4979 for SBET and "
                   "lat/lon columns, the points' CRS for ASCII x,y,z)")
    # (the choices of --trajectory-time and --returns are the values of TimeBase and
    # Returns, spelled out: their modules are too heavy to import for the parser)
    p.add_argument("--trajectory-time", default="auto",
                   choices=("auto", "week", "adjusted", "gps", "unix"),
                   help="time base of the trajectory file (default: SBET week seconds, ASCII "
                   "by magnitude and overlap with the points)")
    p.add_argument("--gps-week", type=int, help="GPS week of week-second times")
    p.add_argument("--strip-gap", type=finite_float, default=10.0,
                   help="GPS-time gap separating strips without point source ids, s "
                   "(default 10)")
    p.add_argument("--returns", default="all", choices=("all", "first", "last"),
                   help="returns written to the bag (default all; every return feeds "
                   "--trajectory estimate)")
    p.add_argument("--frame", default="map", help="map frame id (default map)")
    p.add_argument("--points", default="/lidar/points", help="points topic")
    p.add_argument("--trajectory-topic", default="/lidar/trajectory", help="trajectory topic")
    p.add_argument("--trajectory-rate", type=finite_float, default=50.0,
                   help="trajectory samples kept per second, 0 for all (default 50)")
    p.add_argument("--memory-points", type=int, default=2_000_000,
                   help="points held in memory before spilling sorted runs to disk")
    p.add_argument("--qa-cell", type=finite_float, default=2.0,
                   help="cell of the swath-to-swath overlap QA grid, m (default 2; 0: none)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_dask_option(p)
    add_quiet_option(p)
    p.set_defaults(func=cmd_import)


def cmd_import(args: argparse.Namespace) -> int:
    """Run ``lidarcal import`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.pipeline.executor import open_executor, parse_dask_option
    from lidarcal_ros.pipeline.importing.importer import import_mission
    from lidarcal_ros.pipeline.importing.options import ImportOptions

    if args.dask is not None:
        parse_dask_option(args.dask)  # (a malformed value refused before any work)
    # The trajectory and its accuracy file are named by strings (or 'estimate', 'none').
    named = [Path(v) for v in (args.trajectory_source, args.trajectory_accuracy)
             if v not in (None, "estimate", "none")]
    check_output(args.output, overwrite=args.overwrite, directory=args.output.suffix != ".mcap",
                 inputs=[*other_paths(args, "output"), *named])
    options = ImportOptions(
        trajectory=args.trajectory_source, crs=args.crs, trajectory_crs=args.trajectory_crs,
        trajectory_accuracy=args.trajectory_accuracy,
        # (the flags' words: ImportOptions makes them TimeBase, None for auto, and Returns)
        trajectory_time=args.trajectory_time, gps_week=args.gps_week,
        strip_gap_s=args.strip_gap, returns=args.returns, frame_id=args.frame,
        points_topic=args.points, trajectory_topic=args.trajectory_topic,
        trajectory_rate_hz=args.trajectory_rate, memory_points=args.memory_points,
        qa_cell_m=args.qa_cell, overwrite=args.overwrite)
    progress, close = progress_bar(not args.quiet)
    try:
        # (the cluster, if any, is shut down on every way out: errors, Ctrl-C, SIGTERM)
        with open_executor(args.dask) as executor:
            report = import_mission(args.inputs, args.output, options, progress,
                                    executor=None if args.dask is None else executor)
    finally:
        close()
    for line in report.lines():
        print(line)
    return 0


def add_recover_command(sub: Any) -> None:
    """The ``lidarcal recover`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("recover", help="a damaged bag's readable messages into a new bag",
                       description="Read a bag whose recording was cut (no MCAP summary or "
                       "footer, no metadata.yaml) from the start, and write every message "
                       "readable before the damage to a new, complete bag.")
    p.add_argument("bag", type=Path, help="damaged rosbag2 directory or .mcap file")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="new rosbag2 directory (or a bare .mcap file)")
    p.add_argument("--points", default="/lidar/points",
                   help="points topic: clouds past the last readable trajectory sample are "
                   "left out (default /lidar/points)")
    p.add_argument("--trajectory", default="/lidar/trajectory",
                   help="trajectory topic (default /lidar/trajectory)")
    p.add_argument("--time-field", default="t",
                   help="time field of the clouds (default t, or its alias time, timestamp, "
                   "gps_time)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_recover)


def cmd_recover(args: argparse.Namespace) -> int:
    """Run ``lidarcal recover`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.io.bag.recovery import recover_bag

    if args.output.resolve() != args.bag.resolve():  # (recover_bag names that mistake)
        check_output(args.output, overwrite=args.overwrite, directory=args.output.suffix != ".mcap",
                 inputs=other_paths(args, "output"))
    recovered = recover_bag(args.bag, args.output, overwrite=args.overwrite,
                            points_topic=args.points, trajectory_topic=args.trajectory,
                            time_field=args.time_field)
    for line in recovered.lines():
        print(line)
    return 0


