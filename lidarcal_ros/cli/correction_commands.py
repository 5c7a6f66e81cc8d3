"""``lidarcal correct``: a calibration and the radiometric model applied to a mission bag."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lidarcal_ros.cli.common import (
    add_bag_and_calibration_arguments,
    add_dask_option,
    add_quiet_option,
    other_paths,
    progress_bar,
)
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.output_files import check_output

__all__ = ["add_correct_command", "cmd_correct"]


def add_correct_command(sub: Any) -> None:
    """The ``lidarcal correct`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("correct", help="apply a calibration and correct intensity to reflectance",
                       description="Move every point by the estimated biases (docs/method.md eq. "
                       "[13]) and turn its intensity into reflectance (radar equation); write "
                       "a bag (corrected clouds beside the input topics) or LAS/LAZ 1.4.",
                       epilog="Corrected clouds carry every input field, x, y, z corrected, "
                       "and FLOAT32 reflectance (intensity normalised to the reference range, "
                       "normal incidence, clear air, over radiometry.calibration_constant: the "
                       "Lambertian reflectance 0-1 with that constant or a reference target, "
                       "else relative in intensity units), range (m), incidence (rad), "
                       "scan_angle "
                       "(rad), plus UINT8 correction_flags: 1 not corrected (trajectory gap; "
                       "x, y, z as delivered, the rest NaN), 2 grazing incidence (cosine "
                       "clamped), 4 no surface normal (incidence, reflectance NaN), 8 no "
                       "intensity (reflectance NaN), 16 rough surface (edge, vegetation: "
                       "incidence uncertain), 32 volume return (not the last of its pulse: "
                       "canopy; no incidence correction, incidence NaN). LAS: extra bytes "
                       "reflectance, range, incidence, "
                       "correction_flags; flag 1 also sets 'withheld'.")
    add_bag_and_calibration_arguments(p)
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output: .mcap or a directory (rosbag2), or .las/.laz")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--crs", help="CRS of the map frame, e.g. EPSG:32633: written into LAS/LAZ "
                   "output; an SBET --trajectory-out needs it")
    p.add_argument("--points", help="points topic (default from config)")
    p.add_argument("--trajectory", help="trajectory topic (default from config)")
    p.add_argument("--corrected", help="output topic of the corrected clouds (default from "
                   "config)")
    p.add_argument("--trajectory-corrected", help="output topic of the corrected trajectory "
                   "(default from config; written where the calibration holds trajectory "
                   "errors)")
    p.add_argument("--trajectory-out", type=Path, metavar="FILE",
                   help="also write the corrected trajectory (delivered less each strip's "
                   "estimated trajectory error; interpolated between strips) as lidarcal "
                   "import reads it: FILE.out or FILE.sbet an Applanix SBET (WGS 84 latitude, "
                   "longitude, ellipsoidal height from --crs; GPS week seconds), else ASCII "
                   "time,x,y,z[,roll,pitch,heading]")
    p.add_argument("--time-field", help="time field of the clouds (t, time, gps_time...)")
    p.add_argument("--workers", type=int, default=2,
                   help="threads correcting batches in parallel (default 2; 1: all in one "
                   "thread)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_dask_option(p)
    add_quiet_option(p)
    p.set_defaults(func=cmd_correct)


def cmd_correct(args: argparse.Namespace) -> int:
    """Run ``lidarcal correct`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.core.allocator import tune_allocator
    from lidarcal_ros.io.calibration_file import read_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.survey.las_writer import parse_crs
    from lidarcal_ros.pipeline.correction.bag import CorrectOptions, correct_bag, output_kind
    from lidarcal_ros.pipeline.executor import open_executor, parse_dask_option

    if args.dask is not None:
        parse_dask_option(args.dask)  # (a malformed value refused before any work)
    tune_allocator()
    config = load_flight_config(args.config)
    overrides = {}
    for opt, name in (("points", "topics__points"), ("trajectory", "topics__trajectory"),
                      ("corrected", "topics__corrected"),
                      ("trajectory_corrected", "topics__trajectory_corrected"),
                      ("time_field", "time_field")):
        if getattr(args, opt):
            overrides[name] = getattr(args, opt)
    config = config.with_values(**overrides)
    calibration = read_calibration(args.calibration)
    crs = parse_crs(args.crs) if args.crs else None
    if args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    out = args.output
    check_output(out, overwrite=args.overwrite, inputs=other_paths(args, "output"),
                 directory=output_kind(out) == "bag" and out.suffix != ".mcap")
    if args.trajectory_out is not None:
        check_output(args.trajectory_out, overwrite=args.overwrite,
                     inputs=other_paths(args, "trajectory_out"))
    progress, close = progress_bar(not args.quiet)
    try:
        # (the cluster, if any, is shut down on every way out: errors, Ctrl-C, SIGTERM)
        with open_executor(args.dask) as executor:
            report = correct_bag(args.bag, calibration, args.output, config,
                                 CorrectOptions(crs=crs, overwrite=args.overwrite,
                                                workers=args.workers,
                                                trajectory_out=args.trajectory_out),
                                 progress=progress,
                                 executor=None if args.dask is None else executor)
    finally:
        close()
    for line in report.lines():
        print(line)
    return 0


