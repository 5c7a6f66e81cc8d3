"""A trajectory file's positions and attitude in the map's CRS.

:func:`project` takes a :class:`~lidarcal_ros.io.survey.trajectory_files.TrajectoryFile`'s positions
(geographic, or in another projected CRS) to the map's with PROJ, refusing in one line a
transformation PROJ cannot do well (a geoid model it lacks); :func:`map_orientation` turns its
roll, pitch and heading into REP-103 quaternions in the map frame, the heading turned from
true (or the file's grid) north to the map's grid north by the meridian convergence.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import (
    quaternions_from_attitude,
    quaternions_from_headings,
)
from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.survey.trajectory_files import TrajectoryFile


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
        step = 1e-4 if traj.geographic else 10.0  # degrees of latitude, or units north
        x0, y0, _ = transformer.transform(traj.a, traj.b, traj.c)
        x1, y1, _ = transformer.transform(traj.a, traj.b + step, traj.c)
        heading = heading + np.arctan2(np.asarray(x1) - x0, np.asarray(y1) - y0)
    return np.mod(-heading + math.pi, 2.0 * math.pi) - math.pi


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


__all__ = ["make_transformer", "map_heading", "map_orientation", "project"]
