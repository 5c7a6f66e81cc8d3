"""A trajectory file's positions and attitude in the map's CRS.

:func:`project` takes a :class:`~lidarcal_ros.io.survey.trajectory_files.TrajectoryFile`'s positions
(geographic, or in another projected CRS) to the map's with PROJ, refusing in one line a
transformation PROJ cannot do well (a geoid model it lacks); :func:`map_orientation` turns its
roll, pitch and heading into REP-103 quaternions in the map frame, the heading turned from
true (or the file's grid) north to the map's grid north by the meridian convergence;
:func:`write_sbet_trajectory` is the inverse: a map-frame trajectory as an SBET.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import (
    attitude_from_quaternions,
    quaternions_from_attitude,
    quaternions_from_headings,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import InputError, OutputError, TrajectoryError
from lidarcal_ros.io.survey.trajectory_files import (
    SBET_DTYPE,
    WEEK_S,
    TimeBase,
    TrajectoryFile,
    to_gps_seconds,
)

logger = logging.getLogger(__name__)

#: The geographic CRS of an SBET written (WGS 84, ellipsoidal heights): the import's default.
SBET_CRS = "EPSG:4979"


def make_transformer(source_crs: Any, target_crs: Any, *, where: str) -> Any:
    """A pyproj transformer (x/y in the CRSs' easting/northing or lon/lat order).

    Raises
    ------
    TrajectoryError
        The best transformation needs a grid PROJ does not have (a geoid model for a
        compound target CRS, a datum grid), or none exists.
    """
    import pyproj

    try:
        transformer = pyproj.Transformer.from_crs(source_crs, target_crs, always_xy=True,
                                                  only_best=True)
    except pyproj.exceptions.ProjError as exc:
        raise TrajectoryError(
            f"{where}: cannot transform from {source_crs.name} to {target_crs.name} "
            f"({' '.join(str(exc).split())})"
        ) from None
    desc = transformer.description or ""
    if "ballpark vertical" in desc.lower():
        raise TrajectoryError(
            f"{where}: heights of {target_crs.name} need a geoid model PROJ does not have "
            "(install the PROJ grid, enable PROJ_NETWORK, or give --crs with a 2-D CRS to "
            "keep ellipsoidal heights)"
        )
    return transformer


def project(
    traj: TrajectoryFile, source_crs: Any, target_crs: Any, *, block: int = 1_000_000
) -> np.ndarray:
    """Positions of ``traj`` in ``target_crs`` (units of that CRS), ``(n, 3)`` float64.

    Geographic input: longitude, latitude (deg) and ellipsoidal height (m) of
    ``source_crs`` (a 3-D geographic CRS). A 2-D projected target keeps the ellipsoidal
    height (in metres); a compound target converts it to its vertical datum (geoid model
    needed, see :func:`make_transformer`).
    """
    transformer = make_transformer(source_crs, target_crs, where=str(traj.path))
    out = np.empty((len(traj), 3))
    for i0 in range(0, len(traj), block):
        sl = slice(i0, min(i0 + block, len(traj)))
        x, y, z = transformer.transform(traj.a[sl], traj.b[sl], traj.c[sl])
        out[sl, 0], out[sl, 1], out[sl, 2] = x, y, z
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryError(
            f"{traj.path}: sample {k} ({traj.a[k]:.6f}, {traj.b[k]:.6f}) cannot be projected "
            f"to {target_crs.name}; wrong CRS?"
        )
    return out


def map_heading(traj: TrajectoryFile, source_crs: Any, target_crs: Any) -> np.ndarray | None:
    """docs/method.md's ``kappa`` (rad) of each sample in the map (``target_crs``; None: the
    file's own), from the file's heading; None when it has none.

    A heading clockwise from north is ``-kappa`` (the body's forward axis points along
    ``(-sin kappa, cos kappa)``). Samples in another CRS than the map's are turned from its
    north (true north for geographic ones) to the map's grid north by the convergence at each
    sample, found by transforming a point a little north of it (11 m): up to a few degrees
    in a UTM zone, as much as the crab the heading is there to see.
    """
    if traj.heading_deg is None:
        return None
    heading = np.radians(traj.heading_deg)
    if target_crs is not None and source_crs is not None:
        transformer = make_transformer(source_crs, target_crs, where=str(traj.path))
        heading = heading + grid_convergence(transformer, traj.a, traj.b, traj.c,
                                             geographic=traj.geographic)
    return np.mod(-heading + math.pi, 2.0 * math.pi) - math.pi


def grid_convergence(transformer: Any, a: np.ndarray, b: np.ndarray, c: np.ndarray, *,
                     geographic: bool) -> np.ndarray:
    """The angle (rad, clockwise) from the target's grid north to the source's north at
    each point ``(a, b, c)`` of the source CRS (longitude and latitude in degrees where
    ``geographic``): the direction of a point a little north of it (1e-4 degree of latitude,
    or 10 units) in the target, as :func:`map_heading` turns a heading by it."""
    step = 1e-4 if geographic else 10.0
    x0, y0, _ = transformer.transform(a, b, c)
    x1, y1, _ = transformer.transform(a, np.asarray(b) + step, c)
    return np.arctan2(np.asarray(x1) - x0, np.asarray(y1) - y0)


def map_orientation(traj: TrajectoryFile, source_crs: Any, target_crs: Any
                    ) -> tuple[np.ndarray | None, bool]:
    """The INS orientation of each sample in the map (``target_crs``; None: the file's own).

    Returns
    -------
    orientation : (n, 4) float64 or None
        REP-103 quaternions xyzw (:mod:`lidarcal_ros.core.georeferencing.attitude`): the file's
        roll, pitch and heading (``kappa`` from :func:`map_heading`, in grid north), NaN rows where
        a sample's heading is not finite; level poses where the file has a heading only; None
        without a heading.
    full_attitude : bool
        The orientation carries the file's roll and pitch.

    Notes
    -----
    An SBET's ``C_b^n = Rz(heading) Ry(pitch) Rx(roll)`` (NED: north, east, down; body
    forward, right, down) is ``R(q) = T_n C_b^n T_b`` in ENU and REP-103's FLU, with
    ``T_b = diag(1, -1, -1)`` and ``T_n`` swapping north and east and flipping down. As
    ``T_b`` is a half turn about the forward axis, ``T_b Rz(h) Ry(p) Rx(r) T_b =
    Rz(-h) Ry(-p) Rx(r)`` and ``T_n T_b = Rz(pi/2)``: ``R(q) = Rz(pi/2 - heading) Ry(-pitch)
    Rx(roll)``, which is
    :func:`~lidarcal_ros.core.georeferencing.attitude.quaternions_from_attitude` of ``(roll, pitch,
    kappa = -heading)``. The map's grid north is true north turned about the vertical by the
    meridian convergence: a rotation about the map's up axis, the outermost factor, so it adds to
    ``kappa`` exactly and leaves roll and pitch as they are (a conformal projection turns the local
    level frame without tilting it).
    """
    kappa = map_heading(traj, source_crs, target_crs)
    if kappa is None:
        return None, False
    if traj.roll_deg is None or traj.pitch_deg is None:
        return quaternions_from_headings(kappa), False
    q = quaternions_from_attitude(np.radians(traj.roll_deg), np.radians(traj.pitch_deg), kappa)
    q[~np.isfinite(kappa)] = np.nan
    return q, True


def write_sbet_trajectory(path: str | os.PathLike[str], trajectory: Trajectory, map_crs: Any,
                          *, overwrite: bool = False) -> tuple[Path, int | None]:
    """Write a map-frame ``trajectory`` as an Applanix SBET that ``lidarcal import`` reads
    back to the same poses (docs/interface.md, "Outputs"): the inverse of :func:`project`
    and :func:`map_orientation`.

    Records (17 little-endian float64, docs/import.md): the time in GPS seconds of the week
    of the first sample (UNIX times; later weeks run on past 604800 s; times before 1980,
    not UNIX, written as they are with a warning); latitude and longitude (rad) and height
    above the WGS 84 ellipsoid (m) from the map's ``map_crs`` (a 2-D projected CRS's heights
    are taken as ellipsoidal, as the import takes them); velocities north, east and down
    (m/s, from the positions by central differences: a trajectory carries none); roll,
    pitch and the true heading (rad, the map's grid heading turned by the meridian
    convergence), zero where the trajectory has none (a heading without roll and pitch:
    zero roll and pitch; a sample without an orientation: NaN heading); wander angle,
    accelerations and angular rates zero. Atomic
    (:func:`~lidarcal_ros.io.output_files.write_bytes`).

    Returns
    -------
    (Path, int or None)
        The file and the GPS week of its times (None where they are not UNIX times).

    Raises
    ------
    InputError
        ``map_crs`` is not a projected CRS.
    TrajectoryError
        PROJ cannot transform from ``map_crs`` to WGS 84 (:func:`make_transformer`).
    OutputError
        ``path`` exists and ``overwrite`` is False, or it cannot be written (one line).
    """
    import pyproj

    from lidarcal_ros.io.output_files import EXISTS, write_bytes
    from lidarcal_ros.io.survey.las_reader import crs_units
    from lidarcal_ros.io.survey.las_writer import GPS_EPOCH_UNIX

    p = Path(path)
    check_map_crs(map_crs, where=str(p))
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise OutputError(f"{p}: {EXISTS}")
    geographic = pyproj.CRS(SBET_CRS)
    to_geographic = make_transformer(map_crs, geographic, where=str(p))
    hfac, vfac = crs_units(map_crs)
    three_d = map_crs.is_compound or len(map_crs.axis_info) >= 3
    native = trajectory.xyz / np.array([hfac, hfac, vfac if three_d else 1.0])
    lon, lat, height = (np.asarray(v, dtype=np.float64) for v in to_geographic.transform(
        native[:, 0], native[:, 1], native[:, 2]))
    convergence = grid_convergence(make_transformer(geographic, map_crs, where=str(p)),
                                   lon, lat, height, geographic=True)
    rec = np.zeros(len(trajectory), dtype=SBET_DTYPE)
    rec["time"], week = _week_seconds(trajectory.t, p, GPS_EPOCH_UNIX)
    rec["latitude"], rec["longitude"], rec["altitude"] = np.radians(lat), np.radians(lon), height
    if len(trajectory) > 1:
        east, north, up = np.gradient(trajectory.xyz, trajectory.t, axis=0).T
        cos_c, sin_c = np.cos(convergence), np.sin(convergence)
        rec["x_velocity"] = north * cos_c + east * sin_c  # (true north, east, down)
        rec["y_velocity"] = east * cos_c - north * sin_c
        rec["z_velocity"] = -up
    if trajectory.orientation is not None:
        roll, pitch, kappa = attitude_from_quaternions(trajectory.orientation)
        heading = -kappa - convergence  # (clockwise from true north)
        rec["heading"] = np.mod(heading + math.pi, 2.0 * math.pi) - math.pi
        if trajectory.full_attitude:
            rec["roll"] = np.where(np.isfinite(roll), roll, 0.0)
            rec["pitch"] = np.where(np.isfinite(pitch), pitch, 0.0)
    write_bytes(p, rec.tobytes(), what="SBET", overwrite=overwrite)
    return p, week


def _week_seconds(t: np.ndarray, p: Path, gps_epoch_unix: float) -> tuple[np.ndarray, int | None]:
    """GPS seconds of the week of the first of the UNIX times ``t`` (s), and that week;
    times before the GPS epoch (not UNIX: a simulation's own clock) as they are."""
    if not len(t) or float(t[0]) < gps_epoch_unix:
        if len(t):
            logger.warning("%s: the trajectory's times are before 1980 (not UNIX/ROS times?): "
                           "written unchanged as week seconds", p)
        return np.asarray(t, dtype=np.float64), None
    gps = to_gps_seconds(t, TimeBase.UNIX)
    week = int(math.floor(float(gps[0]) / WEEK_S))
    return gps - week * WEEK_S, week


def check_map_crs(crs: Any, *, where: str) -> None:
    """Refuse a map CRS that is not projected (or compound on a projected one): the map
    frame is projected, in metres or another linear unit.

    Raises
    ------
    InputError
        One line naming ``where`` and the CRS.
    """
    if not (crs.is_projected or (crs.is_compound and crs.sub_crs_list[0].is_projected)):
        raise InputError(f"{where}: CRS '{crs.name}' is not projected; the map frame is a "
                         "projected CRS (give --crs EPSG:N of the map)")


__all__ = ["SBET_CRS", "check_map_crs", "grid_convergence", "make_transformer", "map_heading",
           "map_orientation", "project", "write_sbet_trajectory"]
