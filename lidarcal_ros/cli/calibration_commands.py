"""``lidarcal calibrate``, ``lidarcal evaluate`` and ``lidarcal report``."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

from lidarcal_ros.cli.common import (
    add_bag_and_calibration_arguments,
    add_bag_argument,
    add_dask_option,
    add_quiet_option,
    other_paths,
    progress_bar,
)
from lidarcal_ros.cli.exit_status import EXIT_NOT_CONVERGED, EXIT_NOTHING_ESTIMATED, EXIT_OK
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.output_files import check_output

__all__ = [
    "add_calibrate_command", "add_evaluate_command", "add_report_command", "cmd_calibrate",
    "cmd_evaluate", "cmd_report",
]

logger = logging.getLogger("lidarcal")


def add_calibrate_command(sub: Any) -> None:
    """The ``lidarcal calibrate`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("calibrate", help="estimate the system biases from a mission bag",
                       description="Quasi-rigorous calibration (Habib et al. 2011) of a "
                       "mission bag; writes the calibration file and prints a report.")
    add_bag_argument(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="calibration YAML")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--control", type=Path, help="control points CSV id,x,y,z")
    p.add_argument("--solve-for", default=None,
                   help="comma-separated parameters to estimate, e.g. dX,dY,domega,dphi")
    p.add_argument("--points", help="points topic (default from config)")
    p.add_argument("--trajectory", help="trajectory topic (default from config)")
    p.add_argument("--time-field", help="time field of the clouds (t, time, gps_time...; "
                   "clouds in the sensor's frame: time, t, timestamp, offset_time, found by "
                   "name when not given)")
    p.add_argument("--truth", type=Path, help="truth YAML of a simulation, shown beside")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--write-identity", action="store_true",
                   help="when nothing can be estimated (one strip, no overlap, no usable "
                   "patches, nothing observable), still write -o: a calibration that moves "
                   "no point (every bias at its fixed value, 0 unless configured; none "
                   "estimated; converged false) with the strips' agreement as delivered, "
                   "which lidarcal correct accepts; exit status 5 instead of 1")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_dask_option(p)
    add_quiet_option(p)
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Run ``lidarcal calibrate`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.core.calibration.result import NothingEstimated
    from lidarcal_ros.core.params import parse_parameter_list
    from lidarcal_ros.io.bag.sensor_bag import sensor_frame_of
    from lidarcal_ros.io.calibration_file import calibration_document, write_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration.procedure import (
        Truth,
        calibrate_mission,
        convergence_warning,
        format_agreement,
        format_report,
        load_for_calibration,
    )
    from lidarcal_ros.pipeline.calibration.sensor_frame import load_sensor_bag
    from lidarcal_ros.pipeline.executor import open_executor, parse_dask_option

    if args.dask is not None:
        parse_dask_option(args.dask)  # (a malformed value refused before any work)
    check_output(args.output, overwrite=args.overwrite, inputs=other_paths(args, "output"))
    config = load_flight_config(args.config)
    overrides = {}
    if args.points:
        overrides["topics__points"] = args.points
    if args.trajectory:
        overrides["topics__trajectory"] = args.trajectory
    if args.time_field:
        overrides["time_field"] = args.time_field
    config = config.with_values(**overrides)
    solve_for = None
    if args.solve_for is not None:
        try:
            solve_for = parse_parameter_list(args.solve_for)
        except ValueError as exc:
            raise ConfigError(f"--solve-for: {exc}") from None
    truth = Truth.read(args.truth) if args.truth else None
    started = time.perf_counter()
    if args.dask is not None and sensor_frame_of(
            args.bag, points_topic=config["topics.points"],
            trajectory_topic=config["topics.trajectory"], map_frame=config["frame_id"]):
        raise ConfigError(f"--dask: {args.bag} holds clouds in the sensor's frame, whose "
                          "mounting is calibrated in this process only; leave --dask out")
    sensor = load_sensor_bag(args.bag, config)
    if sensor is not None:
        return _calibrate_mounting(args, config, sensor, solve_for, truth, started)
    progress, close = progress_bar(not args.quiet)
    unestimated: NothingEstimated | None = None
    try:
        # (the cluster, if any, is shut down on every way out: errors, Ctrl-C, SIGTERM)
        with open_executor(args.dask) as executor:
            parts = None if args.dask is None else executor
            mission = load_for_calibration(args.bag, config, control_csv=args.control,
                                           progress=progress, executor=parts)
            result = calibrate_mission(mission, config, solve_for=solve_for,
                                       progress=progress, executor=parts)
    except NothingEstimated as exc:
        unestimated, result = exc, exc.result
    finally:
        close()
    path = write_calibration(args.output, result, overwrite=args.overwrite) \
        if unestimated is None or args.write_identity else None
    elapsed = time.perf_counter() - started
    n_ctrl = len(mission.control) if mission.control is not None else 0
    title = (f"{args.bag}: {len(mission.strips)} strips, {mission.n_points} points, "
             f"{len(result.pairs)} overlapping pairs, "
             f"{n_ctrl} control point{'' if n_ctrl == 1 else 's'} ({elapsed:.1f} s)")
    if args.json:
        import json

        print(json.dumps(calibration_document(result), indent=1))
    elif unestimated is not None:
        print(format_agreement(result, config, title=title, identity_written=path))
    else:
        print(format_report(result, config, title=title, truth=truth))
        print(f"calibration written to {path}")
    if unestimated is not None:
        if path is None:
            raise unestimated
        logger.warning("nothing could be estimated (%s); %s moves no point", unestimated.reason,
                       path)
        return EXIT_NOTHING_ESTIMATED
    warning = convergence_warning(result, config)
    if warning:
        logger.warning("%s: %s", path, warning)
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def _calibrate_mounting(args: argparse.Namespace, config: Any, sensor: Any,
                        solve_for: tuple[str, ...] | None, truth: Any, started: float) -> int:
    """``lidarcal calibrate`` of clouds in the sensor's frame (docs/method.md section 12): the
    mounting calibrated, the file with its ``extrinsic`` block and the URDF joint beside it."""
    from lidarcal_ros.io.calibration_file import calibration_document, urdf_path
    from lidarcal_ros.io.survey.control import read_control_csv
    from lidarcal_ros.pipeline.calibration.procedure import convergence_warning, format_report
    from lidarcal_ros.pipeline.calibration.sensor_frame import (
        calibrate_sensor_bag,
        extrinsic_of,
        format_mounting,
        log_solve_for_note,
        mounting_solve_for,
        truth_mounting,
        write_mounting_calibration,
    )

    check_output(urdf_path(args.output), overwrite=args.overwrite,
                 inputs=other_paths(args, "output"))
    csv = args.control or config["calibration.control_points_file"] or None
    control = read_control_csv(csv) if csv else None
    # --solve-for, else calibration.solve_for, as the calibrator node takes it
    requested = solve_for if solve_for is not None else config["calibration.solve_for"]
    names, note = mounting_solve_for(requested, has_control=control is not None)
    log_solve_for_note(note, requested)
    progress, close = progress_bar(not args.quiet)
    try:
        cal = calibrate_sensor_bag(sensor, solve_for=names, config=config, control=control,
                                   progress=progress)
    finally:
        close()
    path = write_mounting_calibration(args.output, sensor, cal, overwrite=args.overwrite)
    result = cal.result
    title = (f"{args.bag}: {len(cal.lines)} lines, {sensor.n_points} points in "
             f"{sensor.frame_id}, {len(result.pairs)} overlapping pairs "
             f"({time.perf_counter() - started:.1f} s)")
    if args.json:
        import json

        print(json.dumps(calibration_document(result, extrinsic=extrinsic_of(sensor, cal)),
                         indent=1))
    else:
        print(format_report(result, config, title=title, truth=truth))
        true = truth_mounting(args.truth) if args.truth else None
        print("\n".join(format_mounting(sensor, cal, true)))
        print(f"calibration written to {path}, URDF joint to {urdf_path(path)}")
    warning = convergence_warning(result, config)
    if warning:
        logger.warning("%s: %s", path, warning)
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def add_evaluate_command(sub: Any) -> None:
    """The ``lidarcal evaluate`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("evaluate", help="relative and absolute accuracy before and after a "
                       "calibration",
                       description="The paper's accuracy measures: per overlapping strip pair "
                       "the rigid transformation (3 shifts, 3 rotations) that co-aligns the "
                       "pair, by point-to-patch ICP, with the strips as delivered and as "
                       "corrected (Table 3); residuals and RMSE at check points not used in "
                       "the adjustment (Table 4).")
    add_bag_and_calibration_arguments(p)
    p.add_argument("--check-points", type=Path,
                   help="CSV id,x,y,z of surveyed check points (not the control used)")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--max-points", type=int, default=100_000,
                   help="points per pair used by the ICP (default 100000)")
    p.add_argument("--json", action="store_true", help="print JSON (SI units)")
    add_dask_option(p)
    p.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Run ``lidarcal evaluate`` with the parsed ``args``; its exit status."""
    import json

    from lidarcal_ros.io.calibration_file import read_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.survey.control import read_control_csv
    from lidarcal_ros.pipeline.calibration.procedure import load_mission
    from lidarcal_ros.pipeline.evaluation import evaluate_mission, format_evaluation
    from lidarcal_ros.pipeline.executor import open_executor, parse_dask_option

    if args.dask is not None:
        parse_dask_option(args.dask)  # (a malformed value refused before any work)
    if args.max_points < 100:
        raise ConfigError(f"--max-points must be at least 100, got {args.max_points}")
    config = load_flight_config(args.config)
    calibration = read_calibration(args.calibration)
    check = read_control_csv(args.check_points) if args.check_points else None
    mission = load_mission(args.bag, config)
    # (the cluster, if any, is shut down on every way out: errors, Ctrl-C, SIGTERM)
    with open_executor(args.dask) as executor:
        ev = evaluate_mission(mission, calibration.delta, config.calibration_settings(),
                              check_points=check, max_points_per_pair=args.max_points,
                              executor=executor)
    print(json.dumps(ev.as_dict(), indent=1) if args.json else format_evaluation(ev))
    return 0


def add_report_command(sub: Any) -> None:
    """The ``lidarcal report`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("report", help="self-contained HTML QA report of a calibration",
                       description="One HTML file, figures embedded, readable offline: the "
                       "USGS LBS quality level met; the flight lines, trajectory, control and "
                       "check points on a map and a table per strip; the biases with sigmas "
                       "and correlations; the strip-to-strip height differences over the "
                       "block before and after (one colour scale); per strip pair the normal "
                       "discrepancies; the co-alignment of each pair and the check-point "
                       "residuals of lidarcal evaluate; control residuals; the reflectance, "
                       "its variance-to-mean ratio against slope and maps; the inputs with "
                       "sizes and SHA-256, the configuration and the date.",
                       epilog="The evaluation (point-to-patch ICP per pair) costs about as "
                       "much as the rest of the report; --evaluation reuses a saved "
                       "'lidarcal evaluate --json' output of the same calibration instead.")
    add_bag_and_calibration_arguments(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="output HTML file")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file; "
                   "the calibration's, for the same sample points)")
    p.add_argument("--control", type=Path, help="control points CSV id,x,y,z")
    p.add_argument("--check-points", type=Path,
                   help="CSV id,x,y,z of surveyed check points (not the control used)")
    p.add_argument("--evaluation", type=Path,
                   help="JSON of 'lidarcal evaluate --json' for the same bag and calibration "
                   "(default: evaluate here)")
    p.add_argument("--crs", help="CRS of the map frame, named on the maps, e.g. EPSG:32633")
    add_dask_option(p)
    add_quiet_option(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_report)


def cmd_report(args: argparse.Namespace) -> int:
    """Run ``lidarcal report`` with the parsed ``args``; its exit status."""
    import shlex

    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.report.page import write_html_report
    from lidarcal_ros.io.survey.las_writer import parse_crs
    from lidarcal_ros.pipeline.executor import open_executor, parse_dask_option
    from lidarcal_ros.pipeline.report.build import build_report

    if args.dask is not None:
        parse_dask_option(args.dask)  # (a malformed value refused before any work)
    check_output(args.output, overwrite=args.overwrite, inputs=other_paths(args, "output"))
    config = load_flight_config(args.config)
    crs = parse_crs(args.crs) if args.crs else None
    started = time.perf_counter()
    progress, close = progress_bar(not args.quiet)
    try:
        # (the cluster, if any, is shut down on every way out: errors, Ctrl-C, SIGTERM)
        with open_executor(args.dask) as executor:
            content = build_report(args.bag, args.calibration, config,
                                   control_csv=args.control, config_source=args.config,
                                   check_points_csv=args.check_points,
                                   evaluation_json=args.evaluation, crs=crs,
                                   command=shlex.join(["lidarcal", *args.argv]),
                                   progress=progress, executor=executor)
        path = write_html_report(args.output, content, overwrite=args.overwrite,
                                 progress=progress)
    finally:
        close()
    quality = content.quality.best.name if content.quality and content.quality.best else "none"
    print(f"report written to {path}: {len(content.pairs)} strip pairs, "
          f"{len(content.control)} control residuals, USGS LBS {quality} "
          f"({time.perf_counter() - started:.1f} s)")
    return 0


