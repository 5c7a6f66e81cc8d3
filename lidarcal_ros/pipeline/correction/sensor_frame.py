"""Clouds in the sensor's frame georeferenced with a calibration's mounting, then corrected.

docs/method.md section 12: each point ``X = X_mb(t) + R_mb(t) (t_bs + R_bs p)`` with the
calibrated mounting of the calibration file's ``extrinsic`` block, the range less ``dr`` and
the time less the block's timing bias ``time_offset_s``.
The points then go through the map-frame correction (reflectance, flags) with no biases left
to remove, on the trajectory of the sensor's origin and the rigorous model, whose laser vector
``R_ins^T (X - X_o)`` is then the sensor's ``P R_bs p`` exactly (the same interpolation both
ways: :mod:`lidarcal_ros.core.calibration.extrinsic`). ``lidarcal correct`` and the corrector
node alike.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lidarcal_ros.core.calibration.extrinsic import sensor_trajectory
from lidarcal_ros.core.config import SCHEMA, FlightConfig
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting, georeference
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.calibration_file import CalibrationRecord, Extrinsic
from lidarcal_ros.io.cloud.sensor_time import SensorCloudDecoder
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings

__all__ = ["SensorFrameGeoreference", "map_layout", "sensor_extrinsic"]

#: The time field of the map-frame clouds made here (lidarcal's layout).
TIME_FIELD = "t"


def sensor_extrinsic(record: CalibrationRecord, frame_id: str, *, where: str) -> Extrinsic:
    """The calibrated mounting of clouds in the sensor's frame ``frame_id``: the calibration's
    ``extrinsic`` block.

    Raises
    ------
    InputError
        The calibration holds none (one of map-frame clouds), or one of another sensor.
    """
    extrinsic = record.extrinsic
    if extrinsic is None:
        raise InputError(
            f"{where}: clouds in the sensor's frame '{frame_id}' need the calibrated mounting, "
            "and the calibration has no extrinsic block (lidarcal calibrate of such a bag "
            "writes one)")
    if extrinsic.child != frame_id:
        raise InputError(f"{where}: clouds in frame '{frame_id}' but the calibration's "
                         f"extrinsic block is the mounting of '{extrinsic.child}'")
    return extrinsic


def map_layout(intensity: bool) -> np.dtype[Any]:
    """The map-frame cloud made of a driver's: ``x, y, z, t`` float64 (m, absolute s),
    ``intensity`` float32 where the driver's cloud has one."""
    spec = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), (TIME_FIELD, "<f8")]
    if intensity:
        spec.append(("intensity", "<f4"))
    return np.dtype(spec)


@dataclasses.dataclass
class SensorFrameGeoreference:
    """Driver clouds into the map frame with a calibrated mounting (module docstring).

    Attributes
    ----------
    extrinsic : Extrinsic
        The calibration's ``base_link -> sensor``.
    range_offset_m : float
        ``dr``, subtracted from every range, m.
    map_frame : str
        The trajectory's frame, the clouds' made here.
    decoder : SensorCloudDecoder
        Reads the driver's per-point time (its field and convention decided on the first
        cloud).
    base : Trajectory
        Poses of ``base_link`` so far (orientation required).
    origin : Trajectory
        Those of the sensor's origin with the calibrated lever arm
        (:func:`~lidarcal_ros.core.calibration.extrinsic.sensor_trajectory`): the corrector's
        trajectory.
    """

    extrinsic: Extrinsic
    range_offset_m: float
    map_frame: str
    decoder: SensorCloudDecoder
    base: Trajectory = dataclasses.field(
        default_factory=lambda: Trajectory(np.zeros(0), np.zeros((0, 3))))
    origin: Trajectory = dataclasses.field(
        default_factory=lambda: Trajectory(np.zeros(0), np.zeros((0, 3))))

    @classmethod
    def from_config(cls, record: CalibrationRecord, config: FlightConfig, frame_id: str,
                    map_frame: str, *, where: str) -> SensorFrameGeoreference:
        """With ``config``'s ``time_field`` (where not the map-frame default ``t``: else
        found by name, as ``lidarcal calibrate`` reads it) and
        ``sensor_frame.time_convention``."""
        field = str(config["time_field"])
        return cls(sensor_extrinsic(record, frame_id, where=where),
                   float(record.values["dr"]), map_frame,
                   SensorCloudDecoder(
                       field=None if field == SCHEMA["time_field"].default else field,
                       convention=config["sensor_frame.time_convention"]))

    @property
    def mounting(self) -> Mounting:
        """The calibrated mounting."""
        return self.extrinsic.mounting

    def settings(self, settings: CorrectionSettings) -> CorrectionSettings:
        """``settings`` for the georeferenced clouds: no biases (the mounting and ``dr`` hold
        them), the rigorous model on the sensor's origin, lidarcal's time field, no
        trajectory errors (a mounting's calibration estimates none)."""
        return dataclasses.replace(settings, delta=np.zeros_like(settings.delta),
                                   model=PositioningModel.RIGOROUS, time_field=TIME_FIELD,
                                   trajectory_errors=None)

    def set_trajectory(self, base: Trajectory) -> Trajectory:
        """Take the poses of ``base_link`` (all so far); the sensor origin's trajectory.

        Raises
        ------
        TrajectoryError
            Poses without orientation.
        """
        self.base = base
        self.origin = sensor_trajectory(base, self.mounting)
        return self.origin

    def cloud(self, points: np.ndarray, stamp_s: float, *, source: str) -> np.ndarray:
        """A driver's cloud (structured, stamped ``stamp_s`` s) in the map frame
        (:func:`map_layout`, the points' order kept), each point's time less the
        calibration's timing bias (``extrinsic.time_offset_s``: the true time, at which its
        pose is looked up and which its ``t`` holds): points without a return (at the
        sensor's origin or not finite), or outside the trajectory's span, NaN (the
        correction flags them not corrected).

        Raises
        ------
        CloudFormatError
            No usable time field or coordinates.
        """
        xyz, t, intensity = self.decoder.decode(points, stamp_s, source=source)
        if self.extrinsic.time_offset_s:  # the true times: the poses are looked up there
            t = t - self.extrinsic.time_offset_s
        out = np.empty(len(t), dtype=map_layout(intensity is not None))
        out[TIME_FIELD] = t
        if intensity is not None:
            out["intensity"] = intensity
        span = self.origin.t
        ok = (np.isfinite(xyz).all(axis=1) & (np.einsum("ij,ij->i", xyz, xyz) > 0.0)
              & (t >= span[0]) & (t <= span[-1])) if len(span) >= 2 else \
            np.zeros(len(t), dtype=bool)
        where = np.full((len(t), 3), np.nan)
        if ok.any():
            # the rotation alone: the sensor's origin is the trajectory's (module docstring)
            geo = georeference(xyz[ok], t[ok], self.origin,
                               Mounting(self.mounting.rotation, np.zeros(3)),
                               range_offset=self.range_offset_m, source=source)
            where[ok] = geo.xyz
        out["x"], out["y"], out["z"] = where[:, 0], where[:, 1], where[:, 2]
        return out

