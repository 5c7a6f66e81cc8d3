"""The flight configuration: one schema for the parameters file, the CLI and the live nodes.

Each parameter has a dotted name (``calibration.solve_for``), a type, a default, a unit and a
range. The CLI validates a parameters file against it; the nodes declare ROS 2 parameters from
it (with descriptors) and validate run-time changes with the same code, so a value refused live
is refused offline with the same reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, TypeVar

from lidarcal_ros.core.adjustment.least_squares import DEFAULT_MAX_SIGMA, ObservabilityLimits
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.sensor_frame import TimeConvention
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryErrorSettings, TrajectoryModel
from lidarcal_ros.errors import ConfigError

if TYPE_CHECKING:  # (imported where used: the correction reads configurations too)
    from lidarcal_ros.core.calibration.calibrate import CalibrationSettings

OptionsT = TypeVar("OptionsT")


@dataclass(frozen=True)
class ParameterSpec:
    """One flight-configuration parameter.

    ``kind`` is one of ``float``, ``int``, ``str``, ``bool``, ``str_list``.
    """

    default: Any
    kind: str
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False


def float_parameter(default: float, description: str, minimum: float | None = None,
                    maximum: float | None = None, read_only: bool = False) -> ParameterSpec:
    """The spec of a real-valued parameter (``kind`` ``float``) in ``[minimum, maximum]``
    (no bound where None), in the unit its ``description`` names."""
    return ParameterSpec(float(default), "float", description, minimum, maximum,
                         read_only=read_only)


def int_parameter(default: int, description: str, minimum: int, maximum: int) -> ParameterSpec:
    """The spec of an integer parameter (``kind`` ``int``) in ``[minimum, maximum]``."""
    return ParameterSpec(int(default), "int", description, minimum, maximum)


_DEFAULT_SOLVE = ("dX", "dY", "domega", "dphi", "dkappa", "dr", "dS")

#: Every flight-configuration parameter, by dotted name.
SCHEMA: dict[str, ParameterSpec] = {
    "frame_id": ParameterSpec("map", "str", "Map frame of points and trajectory", read_only=True),
    "time_field": ParameterSpec("t", "str", "PointCloud2 field holding the firing time "
                                "(aliases: time, timestamp, gps_time)"),
    "topics.points": ParameterSpec("/lidar/points", "str", "Input strips (PointCloud2)",
                                   read_only=True),
    "topics.trajectory": ParameterSpec("/lidar/trajectory", "str",
                                       "Trajectory (PoseStamped or Odometry)", read_only=True),
    "topics.control_points": ParameterSpec("/lidar/control_points", "str",
                                           "Control points (PointCloud2, transient local)",
                                           read_only=True),
    "topics.corrected": ParameterSpec("/lidar/points_corrected", "str",
                                      "Corrected clouds (PointCloud2)", read_only=True),
    "topics.trajectory_corrected": ParameterSpec(
        "/lidar/trajectory_corrected", "str", "Corrected trajectory (the input trajectory's "
        "type, less each strip's trajectory error) in a corrected bag", read_only=True),
    "topics.tf_static": ParameterSpec(
        "/tf_static", "str", "Static transforms (tf2_msgs/TFMessage, transient local): the "
        "nominal mounting of clouds in the sensor's frame", read_only=True),
    "topics.extrinsic": ParameterSpec(
        "/lidar/calibration/extrinsic", "str", "The calibrated mounting of clouds in the "
        "sensor's frame (geometry_msgs/TransformStamped, transient local): base_link -> "
        "sensor_frame.calibrated_frame, as on /tf_static but needing no tf2_msgs",
        read_only=True),
    "sensor_frame.base_frame": ParameterSpec(
        "base_link", "str", "The frame whose poses the trajectory gives (REP-105 base_link) "
        "when the clouds are in the sensor's frame (docs/method.md section 12); an "
        "Odometry's child_frame_id takes its place where set"),
    "sensor_frame.mounting": ParameterSpec(
        "", "str", "Nominal mounting base_link -> sensor frame 'x,y,z,qx,qy,qz,qw' (m; "
        "quaternion as on /tf_static) for clouds in the sensor's frame; used instead of "
        "/tf_static where set; '' = from /tf_static"),
    "sensor_frame.calibrated_frame": ParameterSpec(
        "", "str", "Child frame of the calibrated mounting the calibrator offers on /tf_static "
        "and topics.extrinsic (base_link -> this frame) for clouds in the sensor's frame; "
        "'' = '<sensor frame>_calibrated', beside the nominal robot_state_publisher sends"),
    "sensor_frame.time_convention": ParameterSpec(
        "auto", "str", "Per-point time of clouds in the sensor's frame: 'relative' to "
        "header.stamp, 'absolute', or 'auto' (from the first cloud's values against its "
        "stamp; the assumption is printed)", choices=tuple(c.value for c in TimeConvention)),
    "sensor_frame.estimate_timing": ParameterSpec(
        False, "bool", "Estimate the timing bias dt of clouds in the sensor's frame (delivered "
        "- true per-point time, s; docs/method.md section 12) with their mounting: written as "
        "the extrinsic block's time_offset_s and taken off the points' times by the "
        "correction; held at 0, said so, where the flight cannot see it (straight lines at "
        "one speed and a steady attitude)"),
    "sensor_frame.timing_max_sigma_s": float_parameter(
        0.001, "With sensor_frame.estimate_timing: the largest sigma of a usable timing bias "
        "dt, s; a flight that determines it less well holds it at 0 and says so", 1e-6, 1.0),
    "sensor_frame.timing_max_correlation": float_parameter(
        0.95, "With sensor_frame.estimate_timing: the largest multiple correlation of a "
        "usable timing bias dt with the mounting's biases (0.99 with dY on straight lines at "
        "one speed, 0.6 with a multirotor's wobble); beyond it dt is held at 0, said so, and "
        "the mounting calibrated again without it", 0.5, 1.0),
    "sensor_frame.lever_arm_sigma_m": float_parameter(
        0.05, "How well the nominal mounting's lever arm is known, 1 sigma per axis, m: a "
        "lever-arm bias held at it (dZ without control points) moves the others through the "
        "attitude's changes, and their sigmas allow for that (0: taken as exact)", 0.0, 1.0),
    "ins.position_sigma_m": float_parameter(
        0.0, "The INS's horizontal position error, 1 sigma per axis (east, north), m: the "
        "biases' sigmas allow for what it moves them by (0 with the other ins.* sigmas: the "
        "INS taken as exact)", 0.0, 10.0),
    "ins.height_sigma_m": float_parameter(
        0.0, "The INS's height error, 1 sigma, m (as ins.position_sigma_m)", 0.0, 10.0),
    "ins.attitude_sigma_arcsec": float_parameter(
        0.0, "The INS's roll and pitch errors, 1 sigma each, arcsec (as "
        "ins.position_sigma_m)", 0.0, 36000.0),
    "ins.heading_sigma_arcsec": float_parameter(
        0.0, "The INS's heading error, 1 sigma, arcsec (as ins.position_sigma_m)", 0.0,
        36000.0),
    "ins.position_correlation_s": float_parameter(
        30.0, "How long the INS's position errors stay alike (first-order Gauss-Markov), s; "
        "0: white noise, each sample its own", 0.0, 86400.0),
    "ins.attitude_correlation_s": float_parameter(
        20.0, "How long the INS's attitude errors stay alike (first-order Gauss-Markov), s; "
        "0: white noise, each sample its own", 0.0, 86400.0),
    "sensor.wavelength_nm": float_parameter(1064.0, "Laser wavelength, nm", 300.0, 2000.0),
    "sensor.beam_divergence_mrad": float_parameter(0.33, "Beam divergence, mrad", 0.01, 10.0),
    "sensor.fov_deg": float_parameter(
        50.0, "Full field of view of the scanner, degrees", 1.0, 180.0),
    "sensor.pulse_rate_hz": float_parameter(70000.0, "Pulse repetition frequency, Hz", 1.0, 1e7),
    "sensor.range_noise_m": float_parameter(0.03, "Range noise (1 sigma), metres", 1e-4, 1.0),
    "atmosphere.visibility_km": float_parameter(48.3, "Visibility of the day, km", 0.1, 500.0),
    "atmosphere.temperature_c": float_parameter(29.8, "Air temperature, deg C", -60.0, 60.0),
    "atmosphere.pressure_kpa": float_parameter(101.81, "Air pressure, kPa", 50.0, 110.0),
    "radiometry.reference_range_m": float_parameter(
        1000.0, "Range reflectance is normalised to, metres", 1.0, 1e5),
    "radiometry.calibration_constant": float_parameter(
        0.0, "Intensity of a Lambertian target of reflectance 1 at the reference range, normal "
        "incidence, clear air and reference power: with it reflectance is the Lambertian "
        "reflectance (0-1); 0 = not known (reflectance relative, in intensity units)", 0.0, 1e12),
    "radiometry.reference_target": ParameterSpec(
        "", "str", "Box 'xmin,ymin,xmax,ymax' (map frame, m) over a surface of known "
        "reflectance: lidarcal report and correct derive the calibration constant from it "
        "when none is given; '' = none"),
    "radiometry.reference_target_reflectance": float_parameter(
        0.0, "Lambertian reflectance of the reference target (0 = no target)", 0.0, 1.5),
    "radiometry.reference_pulse_rate_hz": float_parameter(
        70000.0, "Pulse rate of the reference power, Hz", 1.0, 1e7),
    "radiometry.power_model": ParameterSpec(
        "constant", "str", "Transmitted power: constant, or inversely proportional to pulse "
        "rate (pulse_rate)", choices=("constant", "pulse_rate")),
    "radiometry.min_cos_incidence": float_parameter(
        0.1, "Clamp of cos(incidence); below it points are flagged grazing", 0.01, 1.0),
    "radiometry.uncertain_incidence_max_deg": float_parameter(
        60.0, "Where the normal is uncertain (rough neighbourhood, or an estimate beyond the "
        "grazing clamp) the incidence term is bounded at this angle, deg", 0.0, 89.0),
    "calibration.solve_for": ParameterSpec(list(_DEFAULT_SOLVE), "str_list",
                                           "Parameters to estimate (others held fixed)"),
    "calibration.control_points_file": ParameterSpec("", "str",
                                                     "CSV id,x,y,z of vertical control points"),
    "calibration.max_iterations": int_parameter(10, "Most match-solve iterations", 1, 100),
    "calibration.convergence_fraction": float_parameter(
        0.01, "Converged when every correction is below this fraction of its sigma", 1e-6, 1.0),
    "calibration.robust_k": float_parameter(
        3.0, "Outlier rejection at this many robust sigmas", 1.5, 20.0),
    "calibration.control_weight": float_parameter(
        1.0, "Weight of a control observation relative to a strip-pair one", 0.0, 1e6),
    "calibration.control_plane_points": int_parameter(
        24, "Points of the least-squares plane a control point is compared with (its nearest "
        "in the strip); 0 compares it with the TIN facet under it", 0, 1000),
    "calibration.max_correlation": float_parameter(
        0.999, "Above this |correlation| two parameters are reported as not separable", 0.5, 1.0),
    "calibration.thinning_cell_m": float_parameter(
        0.0, "Keep one point per square cell of this size (m) of the map per strip and cloud "
        "before calibrating (bounds memory and work for dense sensors; about 0.5 for tens of "
        "points per square metre); 0 keeps every point", 0.0, 100.0),
    "calibration.memory": ParameterSpec(
        "whole", "str", "How lidarcal calibrate holds the mission: 'whole' (every point in "
        "memory, read once) or 'bounded' (the bag read four times; each strip pair's sample "
        "points chosen as whole chooses them, then only they, the surface strip's points "
        "within 3 point spacings + 1 m of them and those near a control point are held: "
        "memory set by the samples (matching.per_class_cap), not by the mission's size; "
        "the estimate within 0.05 sigma of whole's)", choices=("whole", "bounded")),
    "calibration.calibration_file": ParameterSpec("lidarcal_calibration.yaml", "str",
                                                  "Where ~/save writes the calibration"),
    "calibration.trajectory.model": ParameterSpec(
        "auto", "str", "Per-strip trajectory errors estimated with the biases (docs/method.md "
        "section 11): 'none' (the trajectory as exact), 'offset' (3 per strip), 'drift' "
        "(offset and linear drift, 6 per strip), 'spline' (a cubic B-spline in time per axis, "
        "knots calibration.trajectory.knot_interval_s apart), 'auto' (spline where it fits the "
        "data clearly better than none; both are calibrated and compared, live as in batch)",
        choices=tuple(m.value for m in TrajectoryModel)),
    "calibration.trajectory.offset_sigma_horizontal_m": float_parameter(
        0.05, "A-priori sigma of a strip's horizontal trajectory offset (the navigation "
        "solution's accuracy), m; where the trajectory carries per-epoch sigmas (an SBET's "
        "smrmsg) a strip's own come from them instead", 1e-4, 10.0),
    "calibration.trajectory.offset_sigma_vertical_m": float_parameter(
        0.05, "A-priori sigma of a strip's vertical trajectory offset, m (per-epoch sigmas "
        "of the trajectory take its place, as the horizontal's)", 1e-4, 10.0),
    "calibration.trajectory.drift_sigma_m_per_s": float_parameter(
        0.002, "A-priori sigma of a strip's trajectory drift rate, per axis, m/s (spline: of "
        "the change between knots, per second)", 1e-6, 1.0),
    "calibration.trajectory.knot_interval_s": float_parameter(
        20.0, "Time between the knots of the spline model, s", 1.0, 3600.0),
    "calibration.trajectory.correlation_s": float_parameter(
        0.0, "How long the navigation solution's position error stays alike, s: the strips' "
        "errors tied across the flight as a first-order Gauss-Markov process (strips flown "
        "close in time alike; the offset sigmas its sigmas); 0: each strip's independent",
        0.0, 36000.0),
    "matching.trajectory_window_s": float_parameter(
        0.5, "Half-width of the local-trajectory window, s", 0.01, 60.0),
    "matching.heading_source": ParameterSpec(
        "auto", "str", "Heading of the local trajectory: 'track' (docs/method.md: the direction of "
        "the fitted line), 'attitude' (the trajectory's orientation: a crabbing aircraft), "
        "'auto' (the orientation where the trajectory has one that agrees with the track "
        "within 20 degrees, else the track)", choices=tuple(m.value for m in HeadingSource)),
    "matching.model": ParameterSpec(
        "auto", "str", "Point-positioning model: 'level' (docs/method.md sections 2-4: a level "
        "platform), 'rigorous' (section 10: the poses' full INS attitude, roll, pitch and "
        "heading, interpolated to each firing time), 'auto' (rigorous where the poses carry "
        "a usable attitude at 10 Hz or more, else level)",
        choices=tuple(m.value for m in PositioningModel)),
    "matching.max_normal_distance_m": float_parameter(
        2.0, "Largest point-to-patch distance accepted at the first iteration, metres", 0.01, 50.0),
    "matching.min_normal_distance_m": float_parameter(0.15, "Smallest matching threshold later "
                                                      "iterations shrink to, metres", 0.001, 50.0),
    "matching.max_edge_factor": float_parameter(
        4.0, "Longest patch edge, in point spacings", 1.0, 100.0),
    "matching.max_slope_deg": float_parameter(70.0, "Steepest usable patch, degrees", 1.0, 89.9),
    "matching.max_bend_deg": float_parameter(
        10.0, "Largest angle between a patch and its neighbours, degrees", 0.1, 90.0),
    "matching.flat_slope_deg": float_parameter(
        5.0, "Patches (and all their neighbours) flatter than this "
        "observe vertical effects only, degrees", 0.0, 45.0),
    "matching.overlap_cell_m": float_parameter(
        10.0, "Cell of the overlap raster, metres", 0.5, 1000.0),
    "matching.max_candidates_per_pair": int_parameter(
        100_000, "Candidate points matched per pair at the first iteration", 100, 100_000_000),
    "matching.per_class_cap": int_parameter(
        3000, "Correspondences kept per slope/aspect class and pair", 10, 10_000_000),
    "qa.rmsdz_warn_m": float_parameter(
        0.08, "Swath-to-swath RMS discrepancy above which QA warns, metres "
        "(USGS LBS QL2: 8 cm)", 0.0, 10.0),
    "qa.max_difference_m": float_parameter(0.16, "Discrepancy no point pair may exceed, metres "
                                           "(USGS LBS QL2: 16 cm)", 0.0, 10.0),
}
for _parameter in PARAMETER_NAMES:
    SCHEMA[f"calibration.fixed.{_parameter}"] = float_parameter(
        0.0, f"Value of {_parameter} when not estimated (surveyed), SI units")


#: The names of lidarcal's nodes: the sections of a parameters file that reach them.
FLIGHT_CONFIG_NODE = "lidarcal_flight_config"
CALIBRATOR_NODE = "lidarcal_calibrator"
CORRECTOR_NODE = "lidarcal_corrector"


def _node_parameter(default: Any, description: str, minimum: float | None = None,
                    maximum: float | None = None, *, read_only: bool = False) -> ParameterSpec:
    """A node's own parameter, of the kind of its ``default``."""
    kind = {bool: "bool", int: "int", float: "float", str: "str"}[type(default)]
    return ParameterSpec(default, kind, description, minimum, maximum, read_only=read_only)


_QUEUE_DEPTH = _node_parameter(1000, "Depth of the point-cloud subscription queue", 1, 100000,
                               read_only=True)
_TRAJECTORY_TYPE = _node_parameter(
    "auto", "Trajectory message type, or 'auto': PoseStamped until a publisher of another "
    "accepted type (Odometry, PoseWithCovarianceStamped, PointStamped) is seen, then that one. "
    "Give the type when a node of the same process publishes another type on the topic (one "
    "DDS participant holds a topic with one type only)", read_only=True)

#: The parameters each node declares beside :data:`SCHEMA` (its own), by node name: the nodes
#: declare them from here, and the CLI tells a node's own key in a parameters file from a
#: misspelt one by them.
NODE_PARAMETERS: dict[str, dict[str, ParameterSpec]] = {
    FLIGHT_CONFIG_NODE: {},
    CALIBRATOR_NODE: {
        "memory_budget_points": _node_parameter(
            0, "Points held for the calibration; past it the oldest complete strip is "
            "released first (0: about half of this machine's memory, at some 700 bytes a "
            "point)", 0, 2**40),
        "strip_gap_s": _node_parameter(
            2.0, "Seconds of point time without a point of a strip after which the strip is "
            "complete", 0.0, 3600.0),
        "idle_close_s": _node_parameter(
            2.0, "Wall seconds without any input after which every open strip is complete "
            "(0: never)", 0.0, 3600.0),
        "checkpoint_file": _node_parameter(
            "", "Checkpoint written after each solve and read at start ('' = none)"),
        "queue_depth": _QUEUE_DEPTH,
        "trajectory_type": _TRAJECTORY_TYPE,
    },
    CORRECTOR_NODE: {
        "calibration": _node_parameter(
            "", "Calibration YAML used until the calibrator publishes an estimate ('' = the "
            "configuration's calibration.fixed values)"),
        "queue_depth": _QUEUE_DEPTH,
        "best_effort": _node_parameter(False, "Subscribe to points with best-effort "
                                       "reliability", read_only=True),
        "trajectory_type": _TRAJECTORY_TYPE,
        "trajectory_buffer_s": _node_parameter(600.0, "Seconds of trajectory kept", 1.0, 1e6),
        "max_trajectory_wait_s": _node_parameter(
            5.0, "Longest wall time a chunk waits for the trajectory to cover it, s", 0.0,
            600.0),
        "flush_timeout_s": _node_parameter(
            0.05, "Wall time without a new chunk after which held chunks are corrected "
            "without look-ahead, s", 0.0, 60.0),
        "lookahead": _node_parameter(
            False, "Wait for the next chunks of a strip so that points at a chunk's leading "
            "edge have neighbours on both sides for the normal: the normals of `lidarcal "
            "correct`, a few chunks later (false: correct each chunk at once with the earlier "
            "ones as neighbours; least latency)"),
        "workers": _node_parameter(
            1, "Threads correcting chunks in parallel (the compiled loops run without the "
            "interpreter lock; one corrects 4M points/s with room to spare, and each further "
            "thread costs some 8% more CPU per point: the points of a chunk move between the "
            "cores' caches)", 1, 64, read_only=True),
        "batch_points": _node_parameter(
            0, "Chunks of one strip corrected together up to this many points (0: one chunk "
            "at a time, least latency)", 0, 100_000_000, read_only=True),
        "separate_process": _node_parameter(
            True, "Correct in a child process with its own interpreter lock, so that the "
            "node's callbacks never wait for the numerics (false: in a thread of the node)",
            read_only=True),
        "max_backlog_mib": _node_parameter(
            512, "Most received clouds (MiB) waiting for the correction; beyond it the oldest "
            "waiting ones are dropped and counted, so that an overload (or a trajectory that "
            "stopped) cannot exhaust memory (0: no limit)", 0, 1 << 20),
        "shared_memory_mib": _node_parameter(
            96, "Shared memory (MiB) of each of the two rings that carry clouds to the child "
            "process and back; a cloud that does not fit goes through a pipe (0: pipes only)",
            0, 65536, read_only=True),
    },
}
#: Parameters every ROS 2 node declares. A parameters file may hold them; the CLI passes
#: them over.
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")


def node_options(cls: Callable[..., OptionsT], node: str, values: Mapping[str, Any]
                 ) -> OptionsT:
    """A node's options object ``cls`` (a dataclass whose fields are parameters of ``node``,
    :data:`NODE_PARAMETERS`) from the node's parameter values, each one missing at its
    parameter's default."""
    own = NODE_PARAMETERS[node]
    return cls(**{f.name: values.get(f.name, own[f.name].default)
                  for f in fields(cls)})  # type: ignore[arg-type]  # (a dataclass)


def undeclared(names: Iterable[str], node: str | None = None) -> list[str]:
    """Of ``names``, those that ``node`` (default: any lidarcal node) does not declare: in
    a parameters file, misspelt or misplaced keys, which a node would ignore."""
    known = set(SCHEMA) | set(ROS_PARAMETERS)
    for name, own in NODE_PARAMETERS.items():
        if node is None or name == node:
            known.update(own)
    return [n for n in names if n not in known]


def coerce(name: str, value: Any) -> Any:
    """Check one value against the schema and return it in its canonical type.

    Raises
    ------
    ConfigError
        One line naming the parameter and what is wrong.
    """
    spec = SCHEMA.get(name)
    if spec is None:
        raise ConfigError(f"unknown parameter '{name}'")
    return check_value(name, spec, value)


def check_value(name: str, spec: ParameterSpec, value: Any) -> Any:
    """Check one value of parameter ``name`` against its ``spec`` (of :data:`SCHEMA` or
    :data:`NODE_PARAMETERS`) and return it in its canonical type.

    Raises
    ------
    ConfigError
        One line naming the parameter and what is wrong.
    """
    kind = spec.kind
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        out: Any = float(value)
        if not math.isfinite(out):
            raise ConfigError(f"{name}: must be finite, got {value!r}")
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        out = int(value)
    elif kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        out = value
    elif kind == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        out = value
        if spec.choices and value not in spec.choices:
            raise ConfigError(f"{name}: '{value}' is not one of {', '.join(spec.choices)}")
    elif kind == "str_list":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{name}: expected a list of names, got {value!r}")
        out = list(value)
        if name == "calibration.solve_for":
            unknown = [v for v in out if v not in PARAMETER_NAMES]
            if unknown:
                raise ConfigError(f"{name}: unknown parameter(s) {', '.join(unknown)}; "
                                  f"known: {', '.join(PARAMETER_NAMES)}")
    else:  # pragma: no cover - schema error
        raise ConfigError(f"{name}: unsupported kind {kind}")
    if spec.minimum is not None and out < spec.minimum:
        raise ConfigError(f"{name}: {out} is below the minimum {spec.minimum}")
    if spec.maximum is not None and out > spec.maximum:
        raise ConfigError(f"{name}: {out} is above the maximum {spec.maximum}")
    return out


def parse_target_box(text: str) -> tuple[float, float, float, float]:
    """``radiometry.reference_target``: ``'xmin,ymin,xmax,ymax'`` (map frame, m) as floats.

    Raises
    ------
    ConfigError
        Not four finite numbers with ``xmin < xmax`` and ``ymin < ymax``.
    """
    name = "radiometry.reference_target"
    try:
        values = tuple(float(v) for v in str(text).split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{name}: expected 'xmin,ymin,xmax,ymax' in metres, got {text!r}")
    x0, y0, x1, y1 = values
    if not (x0 < x1 and y0 < y1):
        raise ConfigError(f"{name}: an empty box {text!r} (need xmin < xmax and ymin < ymax)")
    return x0, y0, x1, y1


def cross_check(values: Mapping[str, Any], *, has_control: bool | None = None) -> str | None:
    """Checks across parameters; returns the reason a configuration is refused, or None.

    ``has_control``: whether control points are available; None = judge from
    ``calibration.control_points_file``.
    """
    solve_for = set(values.get("calibration.solve_for", _DEFAULT_SOLVE))
    if has_control is None:
        has_control = bool(values.get("calibration.control_points_file", ""))
    if not has_control and "dZ" in solve_for:
        return ("calibration.solve_for: dZ cannot be estimated without vertical control "
                "(strips alone cannot see it); give control points or fix dZ")
    if not has_control and {"dZ", "dr"} <= solve_for:
        return "calibration.solve_for: dZ and dr both solved without control"
    lo = values.get("matching.min_normal_distance_m", 0.15)
    hi = values.get("matching.max_normal_distance_m", 2.0)
    if lo > hi:
        return (f"matching.min_normal_distance_m ({lo}) exceeds "
                f"matching.max_normal_distance_m ({hi})")
    box = values.get("radiometry.reference_target", "")
    known = values.get("radiometry.reference_target_reflectance", 0.0)
    if bool(box) != bool(known):
        return ("radiometry.reference_target and radiometry.reference_target_reflectance go "
                "together: give both (the box and the reflectance of its surface) or neither")
    if box:
        try:
            parse_target_box(box)
        except ConfigError as exc:
            return str(exc)
    plane_points = values.get("calibration.control_plane_points", 24)
    if 0 < plane_points < 3:
        return (f"calibration.control_plane_points: {plane_points} points make no plane; "
                "give 3 or more, or 0 for the TIN facet")
    warn = values.get("qa.rmsdz_warn_m", 0.08)
    err = values.get("qa.max_difference_m", 0.16)
    if warn > err:
        return f"qa.rmsdz_warn_m ({warn}) exceeds qa.max_difference_m ({err})"
    return None


@dataclass
class FlightConfig:
    """Validated flight configuration (dotted names -> values)."""

    values: dict[str, Any] = field(default_factory=lambda: {k: s.default
                                                            for k, s in SCHEMA.items()})

    @classmethod
    def from_mapping(cls, flat: Mapping[str, Any], *, source: str = "configuration",
                     check: bool = True) -> FlightConfig:
        """Validate dotted-name values over the defaults.

        Raises
        ------
        ConfigError
            Naming ``source`` and the parameter at fault.
        """
        cfg = cls()
        for name, value in flat.items():
            try:
                cfg.values[name] = coerce(name, value)
            except ConfigError as exc:
                raise ConfigError(f"{source}: {exc}") from None
        if check:
            reason = cross_check(cfg.values, has_control=True)
            if reason:
                raise ConfigError(f"{source}: {reason}")
        return cfg

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    def with_values(self, **updates: Any) -> FlightConfig:
        """A copy with dotted names (``__`` for ``.``) replaced, validated."""
        out = FlightConfig(dict(self.values))
        for key, value in updates.items():
            name = key.replace("__", ".")
            out.values[name] = coerce(name, value)
        return out

    def calibration_settings(self) -> CalibrationSettings:
        """The adjustment options this configuration sets."""
        from lidarcal_ros.core.adjustment.ins_noise import InsNoise
        from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
        from lidarcal_ros.core.georeferencing.local_trajectory import TrajectoryWindow

        values = self.values
        fixed = {n: float(values[f"calibration.fixed.{n}"]) for n in PARAMETER_NAMES}
        return CalibrationSettings(
            solve_for=tuple(values["calibration.solve_for"]),
            fixed=fixed,
            window=TrajectoryWindow(values["matching.trajectory_window_s"]),
            heading_source=HeadingSource(values["matching.heading_source"]),
            model=PositioningModel(values["matching.model"]),
            fov_deg=values["sensor.fov_deg"],
            max_normal_distance_m=values["matching.max_normal_distance_m"],
            min_normal_distance_m=values["matching.min_normal_distance_m"],
            max_edge_factor=values["matching.max_edge_factor"],
            max_slope_deg=values["matching.max_slope_deg"],
            max_bend_deg=values["matching.max_bend_deg"],
            flat_slope_deg=values["matching.flat_slope_deg"],
            overlap_cell_m=values["matching.overlap_cell_m"],
            max_candidates_per_pair=values["matching.max_candidates_per_pair"],
            per_class_cap=values["matching.per_class_cap"],
            max_iterations=values["calibration.max_iterations"],
            convergence_fraction=values["calibration.convergence_fraction"],
            robust_k=values["calibration.robust_k"],
            control_weight=values["calibration.control_weight"],
            control_plane_points=values["calibration.control_plane_points"],
            limits=ObservabilityLimits(max_correlation=values["calibration.max_correlation"],
                                       max_sigma=dict(DEFAULT_MAX_SIGMA)),
            trajectory=TrajectoryErrorSettings(
                TrajectoryModel(values["calibration.trajectory.model"]),
                offset_sigma_horizontal_m=values[
                    "calibration.trajectory.offset_sigma_horizontal_m"],
                offset_sigma_vertical_m=values["calibration.trajectory.offset_sigma_vertical_m"],
                drift_sigma_m_per_s=values["calibration.trajectory.drift_sigma_m_per_s"],
                knot_interval_s=values["calibration.trajectory.knot_interval_s"],
                correlation_s=values["calibration.trajectory.correlation_s"]),
            ins_noise=InsNoise(
                (values["ins.position_sigma_m"],) * 2 + (values["ins.height_sigma_m"],),
                (math.radians(values["ins.attitude_sigma_arcsec"] / 3600.0),) * 2
                + (math.radians(values["ins.heading_sigma_arcsec"] / 3600.0),),
                (values["ins.position_correlation_s"], values["ins.attitude_correlation_s"])),
        )


__all__ = [
    "CALIBRATOR_NODE", "CORRECTOR_NODE", "FLIGHT_CONFIG_NODE", "NODE_PARAMETERS",
    "ROS_PARAMETERS", "SCHEMA", "FlightConfig", "ParameterSpec", "check_value", "coerce",
    "cross_check", "float_parameter", "int_parameter", "node_options", "parse_target_box",
    "undeclared",
]
