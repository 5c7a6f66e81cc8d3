"""``lidarcal simulate`` (a mission with known biases), ``lidarcal plan`` (what a plan can see)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from lidarcal_ros.cli.common import finite_float, other_paths
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.output_files import check_output

__all__ = ["add_plan_command", "add_simulate_command", "cmd_plan", "cmd_simulate"]


def add_simulate_command(sub: Any) -> None:
    """The ``lidarcal simulate`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("simulate", help="synthetic mission with known biases",
                       description="Ray-cast a linear scanner over built-up terrain with known "
                       "biases; write a mission bag, control points (CSV) and the truth (YAML).")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output rosbag2 directory; OUT_control.csv and OUT_truth.yaml beside it")
    p.add_argument("--scenario", default="paper", choices=("paper", "flat", "one_track"),
                   help="flight configuration and terrain (default: paper)")
    p.add_argument("--seed", type=int, default=0, help="random seed (terrain, noise)")
    p.add_argument("--density", type=finite_float, default=1.0,
                   help="points per m^2 at the 1150 m lines (default 1.0)")
    p.add_argument("--line-length", type=finite_float, default=1000.0, help="metres (default 1000)")
    p.add_argument("--biases", default=None,
                   help="e.g. 'dX=0.05,domega=-29arcsec,dr=11.8cm' (default: paper-like)")
    p.add_argument("--range-noise", type=finite_float, default=0.02, help="metres (default 0.02)")
    p.add_argument("--control", type=int, default=None,
                   help="number of vertical control points (default 1; with --uav 0), written "
                   "to OUT_control.csv")
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
    p.add_argument("--trajectory-errors", default=None, metavar="SPEC",
                   help="deliver the trajectory with per-strip errors, as a GNSS/INS solution "
                   "errs (docs/method.md section 11): each strip's points and trajectory carry "
                   "e_s(t) = offset + drift (t - t_mid) + a slow oscillation, drawn per strip "
                   "and axis and recorded in the truth. 'typical': offsets 4 cm horizontal / "
                   "5 cm vertical sigma, drift 1 cm per 10 s sigma, a 1 cm oscillation of "
                   "period 60 s; or KEY=VALUE settings (those not given 0, or as typical "
                   "after 'typical,'), e.g. 'offset_h=4cm,offset_v=5cm,drift=1cm/10s,"
                   "oscillation=1cm,period=60s,seed=3' (default: no error)")
    uav = p.add_argument_group(
        "UAV payload", "--uav flies a spinning multi-beam lidar on a multirotor instead "
        "(docs/method.md section 12) and writes its recording as ros2 bag record does: the "
        "driver's clouds in the sensor's frame on /velodyne_points, nav_msgs/Odometry of "
        "base_link on /ins/odometry at 100 Hz, the nominal mounting on /tf_static; OUT_truth.yaml "
        "holds the biases and the true mounting. --seed and --control apply; the linear "
        "scanner's other options do not")
    uav.add_argument("--uav", action="store_true", help="simulate a UAV payload")
    uav.add_argument("--layout", default="vlp16", choices=("vlp16", "os1-32"),
                     help="the scanner: Velodyne VLP-16 (frame velodyne, time FLOAT32 s) or "
                     "Ouster OS1-32 (frame os_sensor, t UINT32 ns) (default vlp16)")
    uav.add_argument("--uav-lines", type=int, default=4, help="lines flown (default 4)")
    uav.add_argument("--uav-line-length", type=float, default=200.0,
                     help="metres (default 200)")
    uav.add_argument("--columns", type=int, default=None,
                     help="firings of each beam per revolution (default: the layout's; fewer "
                     "make a lighter bag)")
    uav.add_argument("--exact-ins", action="store_true",
                     help="an INS without error (default: a tactical-grade one's)")
    uav.add_argument("--time-format", default="driver",
                     choices=("driver", "timestamp-absolute", "timestamp-relative"),
                     help="per-point time: the layout's driver field, or Hesai's/Livox's "
                     "timestamp FLOAT64 s, absolute or after the stamp (default driver)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_simulate)


def _parse_two_numbers(text: str, option: str, what: str) -> tuple[float, float]:
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


def _parse_rough_air(text: str) -> Any:
    """The RoughAir of ``--rough-air [SPEC]``: the reported one with SPEC's changes."""
    from lidarcal_ros.core.simulation.flight_path import REPORTED_ROUGH_AIR

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
    return _changed(REPORTED_ROUGH_AIR, changes, option="--rough-air", prefix="rough air: ",
                    keys=_ROUGH_AIR_KEYS)


def _changed(base: Any, changes: dict[str, Any], *, option: str, prefix: str,
             keys: dict[str, tuple[str, Any]]) -> Any:
    """The dataclass ``base`` with ``changes`` (field: value); the ConfigError its checks raise
    said as ``option``'s (its ``prefix`` dropped, each field named by its key in ``keys``)."""
    from dataclasses import replace

    try:
        return replace(base, **changes)
    except ConfigError as exc:
        reason = str(exc).removeprefix(prefix)
        for key, (name, _) in keys.items():  # in the option's own words
            reason = reason.replace(name, key)
        raise ConfigError(f"{option}: {reason}") from None


#: ``--trajectory-errors`` keys: the TrajectoryErrorSpec field each sets and its unit ("length",
#: "time", "speed": a length per time, or "count": an integer).
_TRAJECTORY_ERROR_KEYS: dict[str, tuple[str, str]] = {
    "offset_h": ("offset_horizontal_m", "length"), "offset_v": ("offset_vertical_m", "length"),
    "drift": ("drift_m_per_s", "speed"), "oscillation": ("oscillation_m", "length"),
    "period": ("oscillation_period_s", "time"), "seed": ("trajectory_error_seed", "count"),
}


def _trajectory_error_value(key: str, text: str) -> float | int:
    """A ``--trajectory-errors`` value in SI (ValueError if it is not one)."""
    from lidarcal_ros.core.units import LENGTH_UNITS, TIME_UNITS, parse_quantity

    unit = _TRAJECTORY_ERROR_KEYS[key][1]
    if unit == "count":
        return int(text)
    if unit == "speed" and "/" in text:
        length, _, per = text.partition("/")
        return parse_quantity(length, LENGTH_UNITS) / parse_quantity(per, TIME_UNITS,
                                                                     bare_one=True)
    return parse_quantity(text, TIME_UNITS if unit == "time" else LENGTH_UNITS)


def _parse_trajectory_errors(text: str) -> Any:
    """The TrajectoryErrorSpec of ``--trajectory-errors SPEC``: ``typical``, and/or KEY=VALUE
    changes (to no error, or to the typical given first)."""
    from lidarcal_ros.core.simulation.spec import TYPICAL_TRAJECTORY_ERRORS, TrajectoryErrorSpec

    parts = [p.strip() for p in text.split(",") if p.strip()]
    base = TrajectoryErrorSpec()
    if parts and parts[0] == "typical":
        base, parts = TYPICAL_TRAJECTORY_ERRORS, parts[1:]
    if not parts and base is not TYPICAL_TRAJECTORY_ERRORS:
        raise ConfigError(f"--trajectory-errors: expected 'typical' or KEY=VALUE, got '{text}'")
    changes: dict[str, Any] = {}
    for part in parts:
        key, eq, value = (v.strip() for v in part.partition("="))
        if not eq or key not in _TRAJECTORY_ERROR_KEYS:
            raise ConfigError(f"--trajectory-errors: expected 'typical' first, then KEY=VALUE "
                              f"with KEY one of {', '.join(_TRAJECTORY_ERROR_KEYS)}, got "
                              f"'{part}'")
        try:
            changes[_TRAJECTORY_ERROR_KEYS[key][0]] = _trajectory_error_value(key, value)
        except (ValueError, ZeroDivisionError):
            raise ConfigError(f"--trajectory-errors: {key} '{value}' is not "
                              f"{_TRAJECTORY_ERROR_HINTS[_TRAJECTORY_ERROR_KEYS[key][1]]}"
                              ) from None
    return _changed(base, changes, option="--trajectory-errors", prefix="trajectory errors: ",
                    keys=_TRAJECTORY_ERROR_KEYS)


#: What a ``--trajectory-errors`` value of each unit looks like.
_TRAJECTORY_ERROR_HINTS = {"length": "a length (e.g. 4cm, 0.04)",
                           "time": "a time (e.g. 60s, 1min)",
                           "speed": "a drift rate (e.g. 1cm/10s, 1mm/s, 0.001)",
                           "count": "an integer"}


def _read_flight_lines(path: Path) -> list[dict[str, Any]]:
    """The validated lines of ``--lines YAML`` (a list, or a mapping with ``lines``)."""
    from lidarcal_ros.core.simulation.spec import normalise_lines
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


def _simulate_uav(args: argparse.Namespace) -> int:
    """``lidarcal simulate --uav``: a UAV payload's recording and its truth."""
    from lidarcal_ros.core.params import PARAMETER_NAMES
    from lidarcal_ros.core.simulation.uav_payload import UavPayloadSpec, simulate_uav_payload
    from lidarcal_ros.io.bag.sensor_bag import SensorTimeFormat
    from lidarcal_ros.pipeline.calibration.procedure import parse_biases
    from lidarcal_ros.pipeline.calibration.sensor_frame import write_uav_simulation

    biases = None
    if args.biases is not None:
        values = parse_biases(args.biases)
        biases = tuple(values.get(n, 0.0) for n in PARAMETER_NAMES)
    exact = {"ins_position_sigma_m": (0.0, 0.0, 0.0),
             "ins_attitude_sigma_deg": (0.0, 0.0, 0.0)} if args.exact_ins else {}
    spec = UavPayloadSpec(layout=args.layout, seed=args.seed, n_lines=args.uav_lines,
                          line_length_m=args.uav_line_length, columns=args.columns,
                          biases=biases, n_control=args.control or 0,
                          **exact)  # type: ignore[arg-type]
    started = time.perf_counter()
    mission = simulate_uav_payload(spec)
    paths = write_uav_simulation(args.output, mission,
                                 time_format=SensorTimeFormat(args.time_format),
                                 overwrite=args.overwrite)
    print(f"simulated {mission.clouds.xyz.shape[0]} points in {len(mission.clouds)} clouds of "
          f"a {mission.scanner.name} in frame {mission.clouds.frame_id}, {spec.n_lines} lines "
          f"({time.perf_counter() - started:.1f} s)")
    for label, path in paths.items():
        print(f"  {label}: {path}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run ``lidarcal simulate`` with the parsed ``args``; its exit status."""
    if args.uav:
        return _simulate_uav(args)
    from lidarcal_ros.core.simulation.flight_path import REPORTED_CRAB_DEG
    from lidarcal_ros.core.simulation.simulate import stream_mission
    from lidarcal_ros.core.simulation.spec import (
        DEFAULT_BIASES,
        FOV_DEG,
        FlightSpec,
        NoiseSpec,
        SensorSpec,
        SimulationSpec,
        SiteSpec,
        TrajectoryErrorSpec,
        crab_wind,
        scenario_lines,
    )
    from lidarcal_ros.pipeline.calibration.procedure import (
        parse_biases,
        simulation_paths,
        write_simulation_stream,
    )

    for key, path in simulation_paths(args.output).items():
        check_output(path, overwrite=args.overwrite, directory=key == "bag",
                     inputs=other_paths(args, "output"))  # (--lines named as the truth)
    origin = _parse_two_numbers(args.origin, "--origin", "X,Y")
    if not args.density > 0:
        raise ConfigError(f"--density must be positive, got {args.density}")
    rough_air = None if args.rough_air is None else _parse_rough_air(args.rough_air)
    trajectory_errors = (TrajectoryErrorSpec() if args.trajectory_errors is None
                         else _parse_trajectory_errors(args.trajectory_errors))
    lines = None if args.lines is None else _read_flight_lines(args.lines)
    if args.wind is not None:
        wind = _parse_two_numbers(args.wind, "--wind", "E,N in m/s")
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
        site=SiteSpec(n_control=1 if args.control is None else args.control, origin=origin),
        trajectory_errors=trajectory_errors)
    started = time.perf_counter()
    # a line at a time, a block of points at a time: a mission of any size in bounded memory
    stream = stream_mission(spec)
    paths, n_points = write_simulation_stream(args.output, stream, overwrite=args.overwrite)
    print(f"simulated {n_points} points in {len(spec.line_specs())} strips "
          f"({time.perf_counter() - started:.1f} s)")
    for label, path in paths.items():
        print(f"  {label}: {path}")
    return 0


def add_plan_command(sub: Any) -> None:
    """The ``lidarcal plan`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("plan", help="which parameters a flight plan can recover",
                       description="Simulate a flight plan's lines over the chosen terrain, form "
                       "the normal matrix the calibration would see and report, per parameter, "
                       "whether it can be estimated, its predicted sigma and its largest "
                       "correlation, with advice in words.")
    p.add_argument("plan", type=Path, help="flight plan YAML (docs/interface.md)")
    p.add_argument("--json", action="store_true", help="print JSON (docs/interface.md format)")
    p.add_argument("--seed", type=int, default=0, help="terrain seed (default 0)")
    p.set_defaults(func=cmd_plan)


def cmd_plan(args: argparse.Namespace) -> int:
    """Run ``lidarcal plan`` with the parsed ``args``; its exit status."""
    import json

    from lidarcal_ros.core.params import display_value
    from lidarcal_ros.core.planning import predict
    from lidarcal_ros.io.survey.plan_file import read_flight_plan

    report = predict(read_flight_plan(args.plan), seed=args.seed)
    if args.json:
        print(json.dumps(report.to_json_dict(), indent=1))
        return 0
    print(f"{args.plan}: {report.strip_pairs} overlapping strip pairs, "
          f"{report.correspondences} correspondences; model: {report.model}")
    for title, predictions in (("", report.parameters),
                               ("with each strip's trajectory drift estimated too (priors 5 cm, "
                                "2 mm/s):", report.with_trajectory_errors)):
        if title and predictions:
            print(title)
        for name, pred in predictions.items():
            if pred.estimable and pred.sigma is not None:
                value, unit = display_value(name, pred.sigma)
                print(f"  {name:<7} estimable   sigma {value:9.3g} {unit:<6} largest "
                      f"correlation {pred.max_correlation:.2f} with {pred.correlated_with}")
            else:
                print(f"  {name:<7} NOT estimable: {pred.reason}")
    for line in report.advice:
        print(f"advice: {line}")
    return 0


