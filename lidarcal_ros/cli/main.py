"""``lidarcal``: simulate, calibrate (and more) from the command line.

Exit statuses (:data:`EXIT_STATUSES`, also in ``lidarcal --help``):

- 0: success.
- 1: bad input, or an output that cannot be written: one line on stderr,
  ``lidarcal COMMAND: error: REASON``, naming the file, topic, field or parameter at fault
  (and, for a failed write, the operating system's reason). No output is left half-written.
- 2: usage error (argparse).
- 3: an unexpected exception (a bug), also in one line; ``-vv`` adds its traceback.
- 4: ``calibrate`` wrote a calibration whose adjustment did not converge
  (``converged: false`` in the file, a warning line on stderr).
- 5: ``calibrate --write-identity`` could estimate nothing and wrote a calibration that moves
  no point (a warning line on stderr says why).
- 130: interrupted (Ctrl-C).

Where a command goes on despite something wrong (points dropped, a control point unused, a
file without a CRS), it says so in a warning line, ``lidarcal COMMAND: warning: ...``, with
the count. Every command that writes refuses an existing output unless given
``--overwrite``, in the same words.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from lidarcal_ros import __version__
from lidarcal_ros.errors import ConfigError, LidarcalError

logger = logging.getLogger("lidarcal")

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2
EXIT_INTERNAL_ERROR = 3
EXIT_NOT_CONVERGED = 4
#: ``calibrate --write-identity`` estimated nothing and wrote a calibration moving no point.
EXIT_NOTHING_ESTIMATED = 5
EXIT_INTERRUPTED = 130

#: What each exit status means (``lidarcal --help`` prints this).
EXIT_STATUSES: dict[int, str] = {
    EXIT_OK: "success",
    EXIT_BAD_INPUT: "bad input or an output that cannot be written (one line on stderr)",
    EXIT_USAGE: "usage error",
    EXIT_INTERNAL_ERROR: "internal error (a bug; -vv for the traceback)",
    EXIT_NOT_CONVERGED: "calibrate: the adjustment did not converge (calibration written "
                        "with converged: false)",
    EXIT_NOTHING_ESTIMATED: "calibrate --write-identity: nothing could be estimated "
                            "(calibration written that moves no point)",
    EXIT_INTERRUPTED: "interrupted",
}


def _check_output(path: Path, overwrite: bool, *, directory: bool = False) -> None:
    """Refuse an output that cannot be written before any work (same words everywhere)."""
    from lidarcal_ros.io.output_files import check_output

    check_output(path, overwrite=overwrite, directory=directory)


def _add_quiet(p: Any) -> None:
    """``-q/--quiet`` of the commands that show progress."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (it shows only on a terminal anyway)")


def _progress_bar(enabled: bool) -> tuple[Any, Any]:
    """A tqdm-backed progress callback (stderr; silent when not a terminal)."""
    if not enabled:
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=100, unit="%", file=sys.stderr, leave=False,
               bar_format="{desc:<28} {bar} {elapsed}", disable=None)

    def update(stage: str, fraction: float) -> None:
        bar.set_description_str(stage)
        bar.n = int(round(100 * max(0.0, min(1.0, fraction))))
        bar.refresh()

    return update, bar.close


# ---------------------------------------------------------------------------- simulate
def _add_simulate(sub: Any) -> None:
    p = sub.add_parser("simulate", help="synthetic mission with known biases",
                       description="Ray-cast a linear scanner over built-up terrain with known "
                       "biases; write a mission bag, control points (CSV) and the truth (YAML).")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output rosbag2 directory; OUT_control.csv and OUT_truth.yaml beside it")
    p.add_argument("--scenario", default="paper", choices=("paper", "flat", "one_track"),
                   help="flight configuration and terrain (default: paper)")
    p.add_argument("--seed", type=int, default=0, help="random seed (terrain, noise)")
    p.add_argument("--density", type=float, default=1.0,
                   help="points per m^2 at the 1150 m lines (default 1.0)")
    p.add_argument("--line-length", type=float, default=1000.0, help="metres (default 1000)")
    p.add_argument("--biases", default=None,
                   help="e.g. 'dX=0.05,domega=-29arcsec,dr=11.8cm' (default: paper-like)")
    p.add_argument("--range-noise", type=float, default=0.02, help="metres (default 0.02)")
    p.add_argument("--control", type=int, default=1, help="number of control points")
    p.add_argument("--origin", default="0,0",
                   help="map X,Y added to everything, e.g. 500000,5000000 (default 0,0)")
    p.add_argument("--wind", default=None,
                   help="E,N m/s where the air moves: the sensor flies crabbed into the "
                   "crosswind, a heading the trajectory's positions do not show "
                   "(default 0,0; with --rough-air, 5 deg of crab across the first line)")
    p.add_argument("--rough-air", nargs="?", const="", default=None, metavar="SPEC",
                   help="fly in turbulence, as an INS records it: alone, the reported "
                   "roll +-4 deg, pitch +-2.5 deg, 1 deg heading wobble, heave and sway "
                   "+-0.5 m, periods 2-30 s, the orientation at 50 Hz, 5 deg of crab; or "
                   "changes to it, e.g. 'roll=6,pitch=3,yaw=0.5,heave=1,sway=0,"
                   "min-period=3,max-period=20,components=5,rate=100,seed=4'")
    p.add_argument("--lines", type=Path, default=None, metavar="YAML",
                   help="explicit flight lines instead of the scenario's: a YAML list of "
                   "{id, start: [x, y], end: [x, y], height} in metres about the area's "
                   "centre, each optionally turning (turn_deg_s: heading rate, positive "
                   "left; or bank_deg: a coordinated turn's bank, right wing down positive) "
                   "or banked straight (roll_deg)")
    p.add_argument("--attitude", action=argparse.BooleanOptionalAction, default=None,
                   help="write the sensor's orientation (roll, pitch, heading) as the "
                   "trajectory's, as an INS would (default: with --rough-air or banked or "
                   "turning lines; otherwise identity orientation, positions only)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_simulate)


def _two_numbers(text: str, option: str, what: str) -> tuple[float, float]:
    """``A,B`` of an option as two floats (ConfigError naming the option otherwise)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"{option}: expected {what}, got '{text}'") from None
    if len(values) != 2:
        raise ConfigError(f"{option}: expected {what}, got '{text}'")
    return values[0], values[1]


#: ``--rough-air`` keys: the RoughAir field each sets, and its type.
_ROUGH_AIR_KEYS: dict[str, tuple[str, type]] = {
    "roll": ("roll_deg", float), "pitch": ("pitch_deg", float), "yaw": ("yaw_deg", float),
    "heave": ("heave_m", float), "sway": ("sway_m", float),
    "min-period": ("min_period_s", float), "max-period": ("max_period_s", float),
    "components": ("components", int), "rate": ("ins_rate_hz", float), "seed": ("seed", int),
}


def _rough_air(text: str) -> Any:
    """The RoughAir of ``--rough-air [SPEC]``: the reported one with SPEC's changes."""
    from dataclasses import replace

    from lidarcal_ros.core.flight_path import REPORTED_ROUGH_AIR

    changes: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = part.partition("=")
        key = key.strip()
        if not eq or key not in _ROUGH_AIR_KEYS:
            raise ConfigError(f"--rough-air: expected KEY=VALUE with KEY one of "
                              f"{', '.join(_ROUGH_AIR_KEYS)}, got '{part}'")
        name, kind = _ROUGH_AIR_KEYS[key]
        try:
            changes[name] = kind(value.strip())
        except ValueError:
            raise ConfigError(f"--rough-air: {key} '{value.strip()}' is not "
                              f"{'an integer' if kind is int else 'a number'}") from None
    try:
        return replace(REPORTED_ROUGH_AIR, **changes)
    except ConfigError as exc:
        reason = str(exc).removeprefix("rough air: ")
        for key, (name, _) in _ROUGH_AIR_KEYS.items():  # in the option's own words
            reason = reason.replace(name, key)
        raise ConfigError(f"--rough-air: {reason}") from None


def _flight_lines(path: Path) -> list[dict[str, Any]]:
    """The validated lines of ``--lines YAML`` (a list, or a mapping with ``lines``)."""
    from lidarcal_ros.core.simulation_spec import normalise_lines
    from lidarcal_ros.io.yaml_file import read_yaml

    doc = read_yaml(path, what="flight lines")
    if isinstance(doc, dict):
        doc = doc.get("lines")
    if not isinstance(doc, list):
        raise ConfigError(f"{path}: expected a list of lines (or a mapping with 'lines')")
    try:
        return normalise_lines(doc)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _cmd_simulate(args: argparse.Namespace) -> int:
    from lidarcal_ros.core.flight_path import REPORTED_CRAB_DEG
    from lidarcal_ros.core.simulate import simulate_mission
    from lidarcal_ros.core.simulation_spec import (
        DEFAULT_BIASES,
        FOV_DEG,
        FlightSpec,
        NoiseSpec,
        SensorSpec,
        SimulationSpec,
        SiteSpec,
        crab_wind,
        scenario_lines,
    )
    from lidarcal_ros.pipeline.calibration import (
        parse_biases,
        simulation_paths,
        write_simulation,
    )

    for key, path in simulation_paths(args.output).items():
        _check_output(path, args.overwrite, directory=key == "bag")
    origin = _two_numbers(args.origin, "--origin", "X,Y")
    if not args.density > 0:
        raise ConfigError(f"--density must be positive, got {args.density}")
    rough_air = None if args.rough_air is None else _rough_air(args.rough_air)
    lines = None if args.lines is None else _flight_lines(args.lines)
    if args.wind is not None:
        wind = _two_numbers(args.wind, "--wind", "E,N in m/s")
    elif rough_air is not None:
        wind = crab_wind(REPORTED_CRAB_DEG,
                         lines or scenario_lines(args.scenario, args.line_length, FOV_DEG))
    else:
        wind = (0.0, 0.0)
    spec = SimulationSpec(
        seed=args.seed,
        biases=dict(DEFAULT_BIASES) if args.biases is None else parse_biases(args.biases),
        flight=FlightSpec(scenario=args.scenario, lines=lines, line_length_m=args.line_length,
                          wind_mps=wind, rough_air=rough_air),
        sensor=SensorSpec(density=args.density, attitude=args.attitude),
        noise=NoiseSpec(range_noise_m=args.range_noise),
        site=SiteSpec(n_control=args.control, origin=origin))
    started = time.perf_counter()
    sim = simulate_mission(spec)
    paths = write_simulation(args.output, sim, overwrite=args.overwrite)
    print(f"simulated {sim.mission.n_points} points in {len(sim.mission.strips)} strips "
          f"({time.perf_counter() - started:.1f} s)")
    for label, path in paths.items():
        print(f"  {label}: {path}")
    return 0


# ---------------------------------------------------------------------------- calibrate
def _add_calibrate(sub: Any) -> None:
    p = sub.add_parser("calibrate", help="estimate the system biases from a mission bag",
                       description="Quasi-rigorous calibration (Habib et al. 2011) of a "
                       "mission bag; writes the calibration file and prints a report.")
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    p.add_argument("-o", "--output", required=True, type=Path, help="calibration YAML")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--control", type=Path, help="control points CSV id,x,y,z")
    p.add_argument("--solve-for", default=None,
                   help="comma-separated parameters to estimate, e.g. dX,dY,domega,dphi")
    p.add_argument("--points", help="points topic (default from config)")
    p.add_argument("--trajectory", help="trajectory topic (default from config)")
    p.add_argument("--time-field", help="time field of the clouds (t, time, gps_time...)")
    p.add_argument("--truth", type=Path, help="truth YAML of a simulation, shown beside")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--write-identity", action="store_true",
                   help="when nothing can be estimated (one strip, no overlap, no usable "
                   "patches, nothing observable), still write -o: a calibration that moves "
                   "no point (every bias at its fixed value, 0 unless configured; none "
                   "estimated; converged false) with the strips' agreement as delivered, "
                   "which lidarcal correct accepts; exit status 5 instead of 1")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    _add_quiet(p)
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from lidarcal_ros.core.calibration_result import NothingEstimated
    from lidarcal_ros.core.params import parse_parameter_list
    from lidarcal_ros.io.calibration_file import calibration_document, write_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration import (
        Truth,
        calibrate_mission,
        convergence_warning,
        format_agreement,
        format_report,
        load_mission,
    )

    _check_output(args.output, args.overwrite)
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
    progress, close = _progress_bar(not args.quiet)
    unestimated: NothingEstimated | None = None
    try:
        mission = load_mission(args.bag, config, control_csv=args.control)
        result = calibrate_mission(mission, config, solve_for=solve_for, progress=progress)
    except NothingEstimated as exc:
        unestimated, result = exc, exc.result
    finally:
        close()
    path = write_calibration(args.output, result) \
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


# ---------------------------------------------------------------------------- correct
def _add_bag_and_calibration(p: Any) -> None:
    """The arguments of the commands that read a mission bag with a calibration."""
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    p.add_argument("--calibration", required=True, type=Path,
                   help="calibration YAML (lidarcal calibrate)")


def _add_correct(sub: Any) -> None:
    p = sub.add_parser("correct", help="apply a calibration and correct intensity to reflectance",
                       description="Move every point by the estimated biases (method.md eq. "
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
                       "incidence uncertain). LAS: extra bytes reflectance, range, incidence, "
                       "correction_flags; flag 1 also sets 'withheld'.")
    _add_bag_and_calibration(p)
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output: .mcap or a directory (rosbag2), or .las/.laz")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--crs", help="CRS of the map frame for LAS/LAZ output, e.g. EPSG:32633")
    p.add_argument("--points", help="points topic (default from config)")
    p.add_argument("--trajectory", help="trajectory topic (default from config)")
    p.add_argument("--corrected", help="output topic of the corrected clouds (default from "
                   "config)")
    p.add_argument("--time-field", help="time field of the clouds (t, time, gps_time...)")
    p.add_argument("--workers", type=int, default=2,
                   help="threads correcting batches in parallel (default 2; 1: all in one "
                   "thread)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    _add_quiet(p)
    p.set_defaults(func=_cmd_correct)


def _cmd_correct(args: argparse.Namespace) -> int:
    from lidarcal_ros.core.allocator import tune_allocator
    from lidarcal_ros.io.calibration_file import read_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.las import parse_crs
    from lidarcal_ros.pipeline.bag_correction import CorrectOptions, correct_bag, output_kind

    tune_allocator()
    config = load_flight_config(args.config)
    overrides = {}
    for opt, name in (("points", "topics__points"), ("trajectory", "topics__trajectory"),
                      ("corrected", "topics__corrected"), ("time_field", "time_field")):
        if getattr(args, opt):
            overrides[name] = getattr(args, opt)
    config = config.with_values(**overrides)
    calibration = read_calibration(args.calibration)
    crs = parse_crs(args.crs) if args.crs else None
    if args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    out = args.output
    _check_output(out, args.overwrite,
                  directory=output_kind(out) == "bag" and out.suffix != ".mcap")
    progress, close = _progress_bar(not args.quiet)
    try:
        report = correct_bag(args.bag, calibration, args.output, config,
                             CorrectOptions(crs=crs, overwrite=args.overwrite,
                                            workers=args.workers), progress=progress)
    finally:
        close()
    for line in report.lines():
        print(line)
    return 0


# ---------------------------------------------------------------------------- report
def _add_report(sub: Any) -> None:
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
    _add_bag_and_calibration(p)
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
    _add_quiet(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    import shlex

    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.html_report import write_html_report
    from lidarcal_ros.io.las import parse_crs
    from lidarcal_ros.pipeline.report import build_report

    _check_output(args.output, args.overwrite)
    config = load_flight_config(args.config)
    crs = parse_crs(args.crs) if args.crs else None
    started = time.perf_counter()
    progress, close = _progress_bar(not args.quiet)
    try:
        content = build_report(args.bag, args.calibration, config, control_csv=args.control,
                               config_source=args.config, check_points_csv=args.check_points,
                               evaluation_json=args.evaluation, crs=crs,
                               command=shlex.join(["lidarcal", *args.argv]),
                               progress=progress)
        path = write_html_report(args.output, content, overwrite=args.overwrite,
                                 progress=progress)
    finally:
        close()
    quality = content.quality.best.name if content.quality and content.quality.best else "none"
    print(f"report written to {path}: {len(content.pairs)} strip pairs, "
          f"{len(content.control)} control residuals, USGS LBS {quality} "
          f"({time.perf_counter() - started:.1f} s)")
    return 0


# ---------------------------------------------------------------------------- replay / run / record
def _add_replay(sub: Any) -> None:
    from lidarcal_ros.cli.ros_commands import add_replay_arguments

    p = sub.add_parser("replay", help="publish a bag to live topics with its original timing",
                       description="Publish a bag's messages (raw CDR) on their topics with "
                       "the original timing scaled by --rate; --clock publishes /clock for "
                       "nodes with use_sim_time.")
    add_replay_arguments(p)
    p.set_defaults(func=_cmd_replay)


def _cmd_replay(args: argparse.Namespace) -> int:
    from lidarcal_ros.cli.ros_commands import cmd_replay

    return cmd_replay(args)


def _add_run(sub: Any) -> None:
    from lidarcal_ros.cli.ros_commands import add_run_arguments

    p = sub.add_parser("run", help="start the node suite (calibrator, corrector, flight config)",
                       description="Start lidarcal_flight_config, lidarcal_calibrator and "
                       "lidarcal_corrector in this process; Ctrl-C or SIGTERM stops them "
                       "cleanly.")
    add_run_arguments(p)
    p.set_defaults(func=_cmd_run)


def _cmd_run(args: argparse.Namespace) -> int:
    from lidarcal_ros.cli.ros_commands import cmd_run

    return cmd_run(args)


def _add_record(sub: Any) -> None:
    from lidarcal_ros.cli.ros_commands import add_record_arguments

    p = sub.add_parser("record", help="record live topics (default: the outputs) to MCAP",
                       description="Record topics (raw CDR, with their types and durability) "
                       "into a rosbag2 MCAP bag; Ctrl-C or SIGTERM finishes the bag.")
    add_record_arguments(p)
    p.set_defaults(func=_cmd_record)


def _cmd_record(args: argparse.Namespace) -> int:
    from lidarcal_ros.cli.ros_commands import cmd_record

    return cmd_record(args)


# ---------------------------------------------------------------------------- plan
def _add_plan(sub: Any) -> None:
    p = sub.add_parser("plan", help="which parameters a flight plan can recover",
                       description="Simulate a flight plan's lines over the chosen terrain, form "
                       "the normal matrix the calibration would see and report, per parameter, "
                       "whether it can be estimated, its predicted sigma and its largest "
                       "correlation, with advice in words.")
    p.add_argument("plan", type=Path, help="flight plan YAML (interface.md)")
    p.add_argument("--json", action="store_true", help="print JSON (interface.md format)")
    p.add_argument("--seed", type=int, default=0, help="terrain seed (default 0)")
    p.set_defaults(func=_cmd_plan)


def _cmd_plan(args: argparse.Namespace) -> int:
    import json

    from lidarcal_ros.core.params import display_value
    from lidarcal_ros.core.planning import predict
    from lidarcal_ros.io.plan_file import read_flight_plan

    report = predict(read_flight_plan(args.plan), seed=args.seed)
    if args.json:
        print(json.dumps(report.to_json_dict(), indent=1))
        return 0
    print(f"{args.plan}: {report.strip_pairs} overlapping strip pairs, "
          f"{report.correspondences} correspondences; model: {report.model}")
    for name, pred in report.parameters.items():
        if pred.estimable and pred.sigma is not None:
            value, unit = display_value(name, pred.sigma)
            print(f"  {name:<7} estimable   sigma {value:9.3g} {unit:<6} largest correlation "
                  f"{pred.max_correlation:.2f} with {pred.correlated_with}")
        else:
            print(f"  {name:<7} NOT estimable: {pred.reason}")
    for line in report.advice:
        print(f"advice: {line}")
    return 0


# ---------------------------------------------------------------------------- evaluate
def _add_evaluate(sub: Any) -> None:
    p = sub.add_parser("evaluate", help="relative and absolute accuracy before and after a "
                       "calibration",
                       description="The paper's accuracy measures: per overlapping strip pair "
                       "the rigid transformation (3 shifts, 3 rotations) that co-aligns the "
                       "pair, by point-to-patch ICP, with the strips as delivered and as "
                       "corrected (Table 3); residuals and RMSE at check points not used in "
                       "the adjustment (Table 4).")
    _add_bag_and_calibration(p)
    p.add_argument("--check-points", type=Path,
                   help="CSV id,x,y,z of surveyed check points (not the control used)")
    p.add_argument("--config", type=Path, help="flight configuration (ROS 2 parameters file)")
    p.add_argument("--max-points", type=int, default=100_000,
                   help="points per pair used by the ICP (default 100000)")
    p.add_argument("--json", action="store_true", help="print JSON (SI units)")
    p.set_defaults(func=_cmd_evaluate)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from lidarcal_ros.io.calibration_file import read_calibration
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.io.control import read_control_csv
    from lidarcal_ros.pipeline.calibration import load_mission
    from lidarcal_ros.pipeline.evaluation import evaluate_mission, format_evaluation

    if args.max_points < 100:
        raise ConfigError(f"--max-points must be at least 100, got {args.max_points}")
    config = load_flight_config(args.config)
    calibration = read_calibration(args.calibration)
    check = read_control_csv(args.check_points) if args.check_points else None
    mission = load_mission(args.bag, config)
    ev = evaluate_mission(mission, calibration.delta, config.calibration_settings(),
                          check_points=check, max_points_per_pair=args.max_points)
    print(json.dumps(ev.as_dict(), indent=1) if args.json else format_evaluation(ev))
    return 0


# ---------------------------------------------------------------------------- import
def _add_import(sub: Any) -> None:
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
    p.add_argument("inputs", nargs="+", type=Path, metavar="STRIP",
                   help="LAS or LAZ files")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output rosbag2 directory (or .mcap file)")
    p.add_argument("--trajectory", dest="trajectory_source", default="estimate",
                   metavar="SBET|CSV|estimate",
                   help="SBET (.out), ASCII trajectory, or 'estimate' to rebuild it from "
                   "multiple returns (default)")
    p.add_argument("--crs", help="CRS of the points, e.g. EPSG:32633 (default: LAS header)")
    p.add_argument("--trajectory-crs",
                   help="CRS of the trajectory positions (default EPSG:4979 for SBET and "
                   "lat/lon columns, the points' CRS for ASCII x,y,z)")
    p.add_argument("--trajectory-time", default="auto",
                   choices=("auto", "week", "adjusted", "gps", "unix"),
                   help="time base of the trajectory file (default: SBET week seconds, ASCII "
                   "by magnitude and overlap with the points)")
    p.add_argument("--gps-week", type=int, help="GPS week of week-second times")
    p.add_argument("--strip-gap", type=float, default=10.0,
                   help="GPS-time gap separating strips without point source ids, s "
                   "(default 10)")
    p.add_argument("--returns", default="all", choices=("all", "first", "last"),
                   help="returns written to the bag (default all; every return feeds "
                   "--trajectory estimate)")
    p.add_argument("--frame", default="map", help="map frame id (default map)")
    p.add_argument("--points", default="/lidar/points", help="points topic")
    p.add_argument("--trajectory-topic", default="/lidar/trajectory", help="trajectory topic")
    p.add_argument("--trajectory-rate", type=float, default=50.0,
                   help="trajectory samples kept per second, 0 for all (default 50)")
    p.add_argument("--memory-points", type=int, default=2_000_000,
                   help="points held in memory before spilling sorted runs to disk")
    p.add_argument("--qa-cell", type=float, default=2.0,
                   help="cell of the swath-to-swath overlap QA grid, m (default 2; 0: none)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    _add_quiet(p)
    p.set_defaults(func=_cmd_import)


def _cmd_import(args: argparse.Namespace) -> int:
    from lidarcal_ros.pipeline.importer import ImportOptions, import_mission

    _check_output(args.output, args.overwrite, directory=args.output.suffix != ".mcap")
    options = ImportOptions(
        trajectory=args.trajectory_source, crs=args.crs, trajectory_crs=args.trajectory_crs,
        trajectory_time=args.trajectory_time, gps_week=args.gps_week,
        strip_gap_s=args.strip_gap, returns=args.returns, frame_id=args.frame,
        points_topic=args.points, trajectory_topic=args.trajectory_topic,
        trajectory_rate_hz=args.trajectory_rate, memory_points=args.memory_points,
        qa_cell_m=args.qa_cell, overwrite=args.overwrite)
    progress, close = _progress_bar(not args.quiet)
    try:
        report = import_mission(args.inputs, args.output, options, progress)
    finally:
        close()
    for line in report.lines():
        print(line)
    return 0


# ---------------------------------------------------------------------------- recover
def _add_recover(sub: Any) -> None:
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
    p.set_defaults(func=_cmd_recover)


def _cmd_recover(args: argparse.Namespace) -> int:
    from lidarcal_ros.io.bag_recovery import recover_bag

    if args.output.resolve() != args.bag.resolve():  # (recover_bag names that mistake)
        _check_output(args.output, args.overwrite, directory=args.output.suffix != ".mcap")
    recovered = recover_bag(args.bag, args.output, overwrite=args.overwrite,
                            points_topic=args.points, trajectory_topic=args.trajectory,
                            time_field=args.time_field)
    for line in recovered.lines():
        print(line)
    return 0


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lidarcal",
        description="Airborne LiDAR calibration (quasi-rigorous, Habib et al. 2011) and "
                    "radiometric correction for ROS 2.",
        epilog="exit status: " + "; ".join(f"{code} {meaning}"
                                           for code, meaning in EXIT_STATUSES.items()),
    )
    parser.add_argument("--version", action="version", version=f"lidarcal {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_simulate(sub)
    _add_calibrate(sub)
    _add_correct(sub)
    _add_report(sub)
    _add_replay(sub)
    _add_run(sub)
    _add_record(sub)
    _add_plan(sub)
    _add_evaluate(sub)
    _add_import(sub)
    _add_recover(sub)
    return parser


class _CommandFormatter(logging.Formatter):
    """Log records as ``lidarcal COMMAND: warning: MESSAGE`` lines, like the error line
    (with the logger's name too when verbose)."""

    def __init__(self, command: str, *, names: bool) -> None:
        super().__init__()
        self.prefix = f"lidarcal {command}: "
        self.names = names

    def formatMessage(self, record: logging.LogRecord) -> str:
        name = f"{record.name}: " if self.names else ""
        return f"{self.prefix}{record.levelname.lower()}: {name}{record.getMessage()}"


@contextlib.contextmanager
def _log_lines(command: str, verbose: int) -> Iterator[None]:
    """Log records of the command to stderr as :class:`_CommandFormatter` lines, for the
    command's duration (``main`` may be called more than once in a process)."""
    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_CommandFormatter(command, names=verbose > 0))
    level = root.level
    root.addHandler(handler)
    root.setLevel(logging.WARNING - 10 * min(verbose, 2))
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lidarcal`` console script (exit statuses: module docstring)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # (a report records it)
    with _log_lines(args.command, args.verbose):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args))
    except LidarcalError as exc:
        print(f"lidarcal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"lidarcal {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # a file the command reads or writes
        from lidarcal_ros.io.output_files import os_reason

        where = f"{exc.filename}: " if exc.filename else ""
        print(f"lidarcal {args.command}: error: {where}{os_reason(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug: still one line, traceback with -vv
        logger.debug("traceback", exc_info=True)
        text = " ".join(str(exc).split())
        print(f"lidarcal {args.command}: internal error: {type(exc).__name__}: {text} "
              "(rerun with -vv for the traceback)", file=sys.stderr)
        return EXIT_INTERNAL_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
