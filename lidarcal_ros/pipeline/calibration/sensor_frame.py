"""Clouds in the sensor's frame through the calibration (docs/method.md section 12).

A bag's driver clouds, the INS's poses of ``base_link`` and the nominal mounting read with the
configuration's topics and ``sensor_frame.*`` parameters; the mounting calibrated
(:func:`~lidarcal_ros.core.calibration.extrinsic.calibrate_mounting`), written as the
calibration file's biases and ``extrinsic`` block with a URDF joint beside it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Progress
from lidarcal_ros.core.calibration.extrinsic import (
    MOUNTING_SOLVE_FOR,
    TIMING_SLOT,
    MountingCalibration,
    calibrate_mounting,
    mounting_settings,
)
from lidarcal_ros.core.config import SCHEMA, FlightConfig
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel, ScannerKind
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.simulation.uav_payload import UavPayloadMission
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryModel
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.bag.sensor_bag import (
    SensorBag,
    SensorTimeFormat,
    read_sensor_bag,
    sensor_frame_of,
    write_sensor_bag,
)
from lidarcal_ros.io.calibration_file import Extrinsic, read_extrinsic, write_calibration
from lidarcal_ros.io.yaml_file import read_yaml
from lidarcal_ros.pipeline.calibration.procedure import (
    truth_document,
    write_simulation_files,
)

logger = logging.getLogger(__name__)


def parse_mounting(text: str) -> Mounting | None:
    """``sensor_frame.mounting``: ``'x,y,z,qx,qy,qz,qw'`` (m; a TF quaternion) as a Mounting,
    None for ``''``.

    Raises
    ------
    ConfigError
        Not seven numbers, or a zero quaternion; one line naming the parameter.
    """
    if not text.strip():
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 7:
        raise ConfigError(f"sensor_frame.mounting: expected 'x,y,z,qx,qy,qz,qw' (m, quaternion), "
                          f"got '{text}'")
    try:
        return Mounting.from_quaternion(values[:3], values[3:])
    except ConfigError as exc:
        raise ConfigError(f"sensor_frame.mounting: {exc}") from None


def _time_field(config: FlightConfig, given: str | None) -> str | None:
    """The driver's time field: as given, or the configuration's where it is not the map-frame
    default (``t``, which an Ouster has but a Velodyne has not): else found by name."""
    if given:
        return given
    field = config["time_field"]
    return None if field == SCHEMA["time_field"].default else field


def load_sensor_bag(bag: str | Path, config: FlightConfig, *,
                    time_field: str | None = None) -> SensorBag | None:
    """The bag's clouds in the sensor's frame with the configuration's topics and
    ``sensor_frame.*`` parameters; None where the clouds are in the trajectory's frame or
    the map frame (``frame_id``): a mission bag of map-frame clouds, read as before."""
    points, trajectory = config["topics.points"], config["topics.trajectory"]
    if sensor_frame_of(bag, points_topic=points, trajectory_topic=trajectory,
                       map_frame=config["frame_id"]) is None:
        return None
    return read_sensor_bag(
        bag, points_topic=points, trajectory_topic=trajectory,
        tf_topic=config["topics.tf_static"], base_frame=config["sensor_frame.base_frame"],
        time_field=_time_field(config, time_field),
        time_convention=config["sensor_frame.time_convention"],
        mounting=parse_mounting(config["sensor_frame.mounting"]))


def mounting_solve_for(requested: Iterable[str], *,
                       has_control: bool) -> tuple[tuple[str, ...], str]:
    """The biases a mounting's calibration estimates of those asked for (``lidarcal
    calibrate --solve-for``, else ``calibration.solve_for``; the calibrator's
    ``calibration.solve_for``), in docs/method.md's order, and one line saying what was left
    out ('': nothing). ``dS`` (a linear scanner's scale) is no parameter of a general
    scanner's clouds: left out; ``dZ`` (the vertical lever arm, which moves every strip alike)
    only with control points (``has_control``), else held at the nominal. The default
    ``calibration.solve_for`` thus gives :data:`~lidarcal_ros.core.calibration.extrinsic.
    MOUNTING_SOLVE_FOR`, and ``dZ`` too with control points."""
    wanted = set(requested)
    if has_control and wanted == set(SCHEMA["calibration.solve_for"].default):
        wanted.add("dZ")  # the default: what the data can see, the vertical lever arm too
    names = tuple(n for n in PARAMETER_NAMES if n in wanted)
    why = {"dS": "dS is no parameter of clouds in the sensor's frame (a linear scanner's "
                 "scale)"}
    if not has_control:
        why["dZ"] = "dZ needs control points (held at the nominal)"
    left = [n for n in names if n in why]
    kept = tuple(n for n in names if n not in why)
    return kept, ("calibration.solve_for: " + "; ".join(why[n] for n in left) if left else "")


def log_solve_for_note(note: str, requested: Iterable[str]) -> None:
    """Say :func:`mounting_solve_for`'s note in one line: a warning where ``requested`` is
    not the default ``calibration.solve_for`` (someone asked for it), else for the record."""
    if note:
        default = set(SCHEMA["calibration.solve_for"].default)
        logger.log(logging.INFO if set(requested) == default else logging.WARNING, "%s", note)


def sensor_calibration_settings(solve_for: tuple[str, ...] | None = None, *,
                                config: FlightConfig | None = None) -> CalibrationSettings:
    """The settings of a mounting's calibration, ``lidarcal calibrate``'s and the
    calibrator node's: ``config``'s matching, adjustment and trajectory options (default:
    the defaults), on the biases of ``solve_for`` (default
    :data:`~lidarcal_ros.core.calibration.extrinsic.MOUNTING_SOLVE_FOR`; ``dS`` is no
    parameter of such clouds), a general scanner, the rigorous model and no largest sigma of
    a usable bias (:func:`~lidarcal_ros.core.calibration.extrinsic.mounting_settings`), the
    timing bias with ``sensor_frame.estimate_timing`` (its limits
    ``sensor_frame.timing_max_sigma_s`` and ``timing_max_correlation``);
    ``calibration.trajectory.model: auto`` is ``none`` here (no strip trajectory errors)."""
    names = MOUNTING_SOLVE_FOR if solve_for is None else \
        tuple(n for n in PARAMETER_NAMES if n in solve_for and n != TIMING_SLOT)
    if config is None:
        base = mounting_settings(solve_for=names)
    else:
        configured = config.calibration_settings()
        base = mounting_settings(**{
            f.name: getattr(configured, f.name) for f in dataclasses.fields(configured)
            if f.name not in ("solve_for", "limits", "timing", "timing_max_correlation",
                              "held_sigma")},
            solve_for=names, timing=bool(config["sensor_frame.estimate_timing"]),
            timing_max_sigma_s=float(config["sensor_frame.timing_max_sigma_s"]),
            timing_max_correlation=float(config["sensor_frame.timing_max_correlation"]),
            lever_arm_sigma_m=float(config["sensor_frame.lever_arm_sigma_m"]))
        base = replace(base, limits=replace(base.limits,
                                            max_correlation=configured.limits.max_correlation))
        if base.trajectory.model is TrajectoryModel.AUTO:
            # Strip trajectory errors take up what the lever arm moves (a shift of each
            # strip): a mounting's calibration estimates them only where asked to.
            base = replace(base, trajectory=replace(base.trajectory,
                                                    model=TrajectoryModel.NONE))
    return replace(base, scanner=ScannerKind.GENERAL, model=PositioningModel.RIGOROUS)


def calibrate_sensor_bag(data: SensorBag, *, solve_for: tuple[str, ...] | None = None,
                         config: FlightConfig | None = None,
                         control: ControlPoints | None = None,
                         progress: Progress | None = None) -> MountingCalibration:
    """Calibrate the mounting of a bag's sensor-frame clouds
    (:func:`sensor_calibration_settings` of ``config``; ``solve_for`` as
    :func:`mounting_solve_for` gives it), with vertical ``control`` points (map frame) where
    given."""
    logger.info("%s: %d points in %s, mounting %s -> %s from %s", data.path, data.n_points,
                data.frame_id, data.base_frame, data.frame_id, data.mounting_source)
    return calibrate_mounting(data.xyz, data.t, data.trajectory, data.mounting,
                              settings=sensor_calibration_settings(solve_for, config=config),
                              control=control, progress=progress)


def extrinsic_of(data: SensorBag, cal: MountingCalibration) -> Extrinsic:
    """The calibration file's ``extrinsic`` block of a calibrated bag."""
    return with_timing(Extrinsic(data.base_frame, data.frame_id, cal.mounting, cal.nominal),
                       cal)


def with_timing(extrinsic: Extrinsic, cal: MountingCalibration) -> Extrinsic:
    """``extrinsic`` with the timing bias of ``cal`` (0 and no sigma where not estimated)."""
    sigma = cal.time_offset_sigma_s
    return replace(extrinsic, time_offset_s=cal.time_offset_s,
                   time_offset_sigma_s=float(sigma) if np.isfinite(sigma) else None,
                   time_offset_correlation=dict(cal.time_offset_correlation),
                   time_offset_note=cal.time_offset_note)


def write_mounting_calibration(path: str | Path, data: SensorBag | Extrinsic,
                               cal: MountingCalibration, *, overwrite: bool = True) -> Path:
    """Write the calibration file of a mounting (the biases as any calibration's, the
    ``extrinsic`` block: of a bag's frames, or as given) and the URDF joint beside it; the
    file's path. ``lidarcal calibrate`` and the calibrator's ``~/save`` alike."""
    extrinsic = with_timing(data, cal) if isinstance(data, Extrinsic) else extrinsic_of(data, cal)
    return write_calibration(path, cal.result, overwrite=overwrite, extrinsic=extrinsic)


def format_mounting(data: SensorBag, cal: MountingCalibration,
                    truth: Mounting | None = None) -> list[str]:
    """Lines saying the calibrated mounting against the nominal (and the truth where known):
    translation mm, rotation arcsec about ``base_link``'s axes, with sigmas."""
    arcsec = np.degrees(1.0) * 3600.0

    def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1, 1)))
                     * 3600.0)

    t, s_t = cal.mounting.translation, cal.translation_sigma_m
    moved = rotation_angle(cal.nominal.rotation, cal.mounting.rotation)
    shift_mm = float(np.linalg.norm(t - cal.nominal.translation)) * 1e3
    lines = [f"mounting {data.base_frame} -> {data.frame_id} (nominal from "
             f"{data.mounting_source}):",
             "  translation " + ", ".join(f"{v:+.4f}" for v in t) + " m  (sigma "
             + ", ".join("held" if not np.isfinite(v) else f"{v * 1e3:.1f}" for v in s_t)
             + " mm)",
             "  rotation [qx, qy, qz, qw] " + ", ".join(f"{v:+.6f}" for v in
                                                         cal.mounting.quaternion)
             + "  (sigma " + ", ".join("held" if not np.isfinite(v) else f"{v * arcsec:.1f}"
                                       for v in cal.rotation_sigma_rad) + " arcsec)",
             f"  moved from the nominal by {moved:.0f} arcsec and {shift_mm:.1f} mm; "
             f"range offset dr {cal.range_offset_m * 1e3:+.1f} mm"]
    if np.isfinite(cal.time_offset_sigma_s):
        lines.append(f"  timing bias dt {cal.time_offset_s * 1e3:+.3f} ms (sigma "
                     f"{cal.time_offset_sigma_s * 1e3:.3f} ms): taken off the points' times "
                     "by lidarcal correct")
    elif cal.time_offset_note:
        lines.append("  timing bias dt not estimated: held at 0 (the flight cannot see it)")
    if truth is not None:
        d = (t - truth.translation) * 1e3
        lines.append(f"  against the truth: rotation "
                     f"{rotation_angle(truth.rotation, cal.mounting.rotation):.1f} arcsec, "
                     f"translation {d[0]:+.1f}, {d[1]:+.1f}, {d[2]:+.1f} mm")
    return lines




# ------------------------------------------------------------------ the simulated payload

def write_uav_simulation(output: str | Path, mission: UavPayloadMission, *,
                         time_format: SensorTimeFormat = SensorTimeFormat.DRIVER,
                         overwrite: bool = False) -> dict[str, Path]:
    """Write a simulated UAV payload (:func:`~lidarcal_ros.core.simulation.uav_payload.
    simulate_uav_payload`) as ``ros2 bag record`` records it (the clouds on
    ``/velodyne_points``, ``/ins/odometry``, ``/tf_static`` with the nominal mounting), its
    control points (``OUT_control.csv``, where it has some) and the truth beside it
    (``OUT_truth.yaml``: the biases, the true and nominal mountings, the spec); all or, where
    one fails, none of them."""
    spec = {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(mission.spec).items()}
    doc = truth_document(dict(zip(PARAMETER_NAMES, mission.biases.tolist(), strict=True)),
                         {"uav_payload": spec})
    doc["mounting"] = Extrinsic("base_link", mission.clouds.frame_id, mission.truth_mounting,
                                mission.nominal).document()

    def bag(path: Path) -> dict[str, Any]:
        write_sensor_bag(path, mission.clouds, mission.trajectory, mission.nominal,
                         time_format=time_format, overwrite=overwrite)
        return doc

    return write_simulation_files(output, mission.control, bag, overwrite=overwrite)


def truth_mounting(path: str | Path) -> Mounting | None:
    """The true mounting of a simulated payload's truth file (``mounting``:
    :func:`write_uav_simulation`); None where the file has none."""
    doc = read_yaml(Path(path), what="truth file")
    block = doc.get("mounting") if isinstance(doc, dict) else None
    return None if block is None else read_extrinsic(Path(path), block).mounting


__all__ = ["calibrate_sensor_bag", "extrinsic_of", "format_mounting", "load_sensor_bag",
           "log_solve_for_note", "mounting_solve_for", "parse_mounting",
           "sensor_calibration_settings", "truth_mounting", "with_timing",
           "write_mounting_calibration", "write_uav_simulation"]
