"""Compiled per-point loops of the calibration's model: bias removal and point-to-patch rows.

Both positioning models run through them: a ``rotation`` with a row per point is ``R_ins``
(docs/method.md section 10), an empty one means ``R_kappa`` (sections 2-4). The rules of
compiled loops: docs/internals.md, "Compiled loops".
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


@inlined
def _to_body(rigorous: bool, rotation: np.ndarray, c: np.ndarray, s: np.ndarray, i: int,
             vx: float, vy: float, vz: float) -> tuple[float, float, float]:
    """``R^T v`` of point ``i`` (as ``LaserGeometry.to_body`` of :mod:`.laser_geometry`)."""
    if rigorous:
        r = rotation[i]
        return (r[0, 0] * vx + r[1, 0] * vy + r[2, 0] * vz,
                r[0, 1] * vx + r[1, 1] * vy + r[2, 1] * vz,
                r[0, 2] * vx + r[1, 2] * vy + r[2, 2] * vz)
    return c[i] * vx + s[i] * vy, -s[i] * vx + c[i] * vy, vz


@inlined
def _to_map(rigorous: bool, rotation: np.ndarray, c: np.ndarray, s: np.ndarray, i: int,
            bx: float, by: float, bz: float) -> tuple[float, float, float]:
    """``R b`` of point ``i`` (as ``LaserGeometry.to_map`` of :mod:`.laser_geometry`)."""
    if rigorous:
        r = rotation[i]
        return (r[0, 0] * bx + r[0, 1] * by + r[0, 2] * bz,
                r[1, 0] * bx + r[1, 1] * by + r[1, 2] * bz,
                r[2, 0] * bx + r[2, 1] * by + r[2, 2] * bz)
    return c[i] * bx - s[i] * by, s[i] * bx + c[i] * by, bz


@compiled
def exact_correction_and_geometry(xyz: np.ndarray, origin: np.ndarray, cos_kappa: np.ndarray,
                                  sin_kappa: np.ndarray, rotation: np.ndarray,
                                  delta: np.ndarray, boresight: np.ndarray,
                                  corrected: np.ndarray, shift: np.ndarray, x: np.ndarray,
                                  y: np.ndarray, z: np.ndarray, beta: np.ndarray,
                                  sin_beta: np.ndarray, cos_beta: np.ndarray,
                                  general: bool, with_geometry: bool) -> None:
    """The biases removed exactly and the laser geometry of the corrected points, in one
    pass: :func:`lidarcal_ros.core.georeferencing.bias_model.correct_points_exact` followed by
    :func:`lidarcal_ros.core.georeferencing.laser_geometry.geometry_at` and its :meth:`trig`.

    Per point: ``q = R^T (X_b - X_o) - d``, ``rho = q @ boresight`` (``R_B^T q``),
    ``r = hypot(rho_x, rho_z) - dr``, ``theta = atan2(-rho_x, -rho_z) / (1 + dS)``, the
    corrected point ``X_o + R (-r sin theta, rho_y, -r cos theta)``; then, seen from the same
    firing position and frame, ``(x, y, z) = R^T (X_c - X_o)`` (the level model: ``x``
    across the heading, ``z`` the height difference, ``y`` not kept), ``beta = atan(x / z)``
    and ``sin beta = -x / r``, ``cos beta = -z / r`` with ``r`` the range (``hypot(x, z)``
    level, ``|(x, y, z)|`` rigorous).

    A ``general`` scanner (rigorous; docs/method.md section 12) has no mirror angle: the
    recorded laser vector is ``rho = R_B^T R^T (X_b - X_o)``, the range is shortened along
    it, ``rho (1 - dr / |rho|)``, and the lever-arm bias moves the origin:
    the corrected point is ``X_o + R (rho (1 - dr / |rho|) - d)``, exactly the georeferencing
    with the mounting of ``mounting_from_biases``; ``dS`` does not enter.

    Parameters
    ----------
    xyz, origin : (n, 3) float64
        Delivered points and their firing positions, map frame, m.
    cos_kappa, sin_kappa : (n,) float64
        The level model's heading per point (unused when ``rotation`` has a row per point).
    rotation : (n, 3, 3) or (0, 3, 3) float64
        ``R_ins`` per point (rigorous), or empty (level).
    delta : (8,) float64
        Biases, SI.
    boresight : (3, 3) float64
        :func:`~lidarcal_ros.core.georeferencing.bias_model.boresight_matrix` of ``delta``.
    corrected, shift : (n, 3) float64
        Receive the corrected points and ``xyz - corrected``, m.
    x, y, z, beta, sin_beta, cos_beta : (n,) float64
        Receive the geometry of the corrected points (``y`` only for the rigorous model:
        pass an empty array for the level one).
    general : bool
        A general scanner's correction (above) instead of a linear one's.
    with_geometry : bool
        False: neither the shift nor the geometry is computed (their arrays may be empty;
        where wanted, the geometry of some points comes from :func:`corrected_geometry`).
    """
    n = xyz.shape[0]
    rigorous = rotation.shape[0] == n and n > 0
    d0, d1, d2, d6, d7 = delta[0], delta[1], delta[2], delta[6], delta[7]
    b = boresight
    for i in range(n):
        ox, oy, oz = origin[i, 0], origin[i, 1], origin[i, 2]
        qx, qy, qz = _to_body(rigorous, rotation, cos_kappa, sin_kappa, i,
                              xyz[i, 0] - ox, xyz[i, 1] - oy, xyz[i, 2] - oz)
        if general:
            rx = qx * b[0, 0] + qy * b[1, 0] + qz * b[2, 0]
            ry = qx * b[0, 1] + qy * b[1, 1] + qz * b[2, 1]
            rz = qx * b[0, 2] + qy * b[1, 2] + qz * b[2, 2]
            f = 1.0 - d6 / math.sqrt(rx * rx + ry * ry + rz * rz)
            mx, my, mz = _to_map(True, rotation, cos_kappa, sin_kappa, i,
                                 rx * f - d0, ry * f - d1, rz * f - d2)
        else:
            qx -= d0
            qy -= d1
            qz -= d2
            rx = qx * b[0, 0] + qy * b[1, 0] + qz * b[2, 0]
            ry = qx * b[0, 1] + qy * b[1, 1] + qz * b[2, 1]
            rz = qx * b[0, 2] + qy * b[1, 2] + qz * b[2, 2]
            r_true = math.hypot(rx, rz) - d6
            theta = math.atan2(-rx, -rz) / (1.0 + d7)
            mx, my, mz = _to_map(rigorous, rotation, cos_kappa, sin_kappa, i,
                                 -r_true * math.sin(theta), ry, -r_true * math.cos(theta))
        cx, cy, cz = ox + mx, oy + my, oz + mz
        corrected[i, 0], corrected[i, 1], corrected[i, 2] = cx, cy, cz
        if with_geometry:
            shift[i, 0] = xyz[i, 0] - cx
            shift[i, 1] = xyz[i, 1] - cy
            shift[i, 2] = xyz[i, 2] - cz
            _geometry_at(rigorous, rotation, cos_kappa, sin_kappa, i, i, cx - ox, cy - oy,
                         cz - oz, x, y, z, beta, sin_beta, cos_beta)


@inlined
def _geometry_at(rigorous: bool, rotation: np.ndarray, cos_kappa: np.ndarray,
                 sin_kappa: np.ndarray, i: int, j: int, ex: float, ey: float, ez: float,
                 x: np.ndarray, y: np.ndarray, z: np.ndarray, beta: np.ndarray,
                 sin_beta: np.ndarray, cos_beta: np.ndarray) -> None:
    """The geometry of point ``i`` seen at ``e = X_c - X_o`` (map frame, m) from its firing
    position, written at ``j``: ``(x, y, z) = R^T e`` (level: ``y`` not kept), ``beta``,
    ``sin beta``, ``cos beta`` (:func:`exact_correction_and_geometry`)."""
    if rigorous:
        gx, gy, gz = _to_body(True, rotation, cos_kappa, sin_kappa, i, ex, ey, ez)
        y[j] = gy
        r = math.sqrt(gx * gx + gy * gy + gz * gz)
    else:
        gx, gz = ex * cos_kappa[i] + ey * sin_kappa[i], ez
        r = math.hypot(gx, gz)
    x[j] = gx
    z[j] = gz
    beta[j] = math.atan(gx / gz)
    inv_r = 1.0 / r
    sin_beta[j] = -gx * inv_r
    cos_beta[j] = -gz * inv_r


@compiled
def corrected_geometry(corrected: np.ndarray, origin: np.ndarray, cos_kappa: np.ndarray,
                       sin_kappa: np.ndarray, rotation: np.ndarray, index: np.ndarray,
                       x: np.ndarray, y: np.ndarray, z: np.ndarray, beta: np.ndarray,
                       sin_beta: np.ndarray, cos_beta: np.ndarray) -> None:
    """The geometry :func:`exact_correction_and_geometry` gives the corrected points, of the
    points ``index`` of ``corrected`` (n, 3) only, written at ``0 .. len(index)`` (the same
    arithmetic: the same bits)."""
    rigorous = rotation.shape[0] == corrected.shape[0] and corrected.shape[0] > 0
    for j in range(index.shape[0]):
        i = index[j]
        _geometry_at(rigorous, rotation, cos_kappa, sin_kappa, i, j,
                     corrected[i, 0] - origin[i, 0], corrected[i, 1] - origin[i, 1],
                     corrected[i, 2] - origin[i, 2], x, y, z, beta, sin_beta, cos_beta)


@compiled
def add_normal_rows(normal: np.ndarray, index: np.ndarray, weight: np.ndarray,
                    x: np.ndarray, y: np.ndarray, z: np.ndarray, beta: np.ndarray,
                    sin_beta: np.ndarray, cos_beta: np.ndarray, cos_kappa: np.ndarray,
                    sin_kappa: np.ndarray, rotation: np.ndarray, out: np.ndarray) -> None:
    """``out += weight * n^T A`` of point ``index[i]`` of a strip for each observation ``i``
    (:func:`lidarcal_ros.core.georeferencing.bias_model.geometry_normal_rows` of
    ``geometry.take(index)``, times the weights): the normal turned into the body frame, ``n_b = R^T
    n``, and the row ``n_b^T C`` of
    :func:`~lidarcal_ros.core.georeferencing.bias_model.body_normal_rows`.

    Parameters
    ----------
    normal : (k, 3) float64
        Unit normals, map frame.
    index : (k,) int64
        The strip's point of each observation.
    weight : (k,) float64
        Factor of each row (empty: 1).
    x, z, beta, sin_beta, cos_beta, cos_kappa, sin_kappa : (n,) float64; rotation : (n, 3, 3)
        The strip's geometry (rotation empty for the level model).
    y : (n,) float64, or empty
        The forward coordinate of a general scanner's laser vector, m (docs/method.md section
        12: ``domega [0, -z, y]``, ``dkappa [-y, x, 0]``, ``dr rho / |rho|``, ``dS`` 0);
        empty: a linear scanner's (section 10's columns, ``y`` taken as 0).
    out : (k, 8) float64
        Rows to add to.
    """
    k = normal.shape[0]
    rigorous = rotation.shape[0] == x.shape[0] and x.shape[0] > 0
    general = y.shape[0] == x.shape[0] and x.shape[0] > 0
    weighted = weight.shape[0] == k
    for i in range(k):
        p = index[i]
        nr, nf, nu = _to_body(rigorous, rotation, cos_kappa, sin_kappa, p,
                              normal[i, 0], normal[i, 1], normal[i, 2])
        xp, zp = x[p], z[p]
        lean = zp * nr - xp * nu
        # section 12's y terms added last, so that y = 0 leaves section 10's row to the bit
        yp = y[p] if general else 0.0
        along = yp / math.sqrt(xp * xp + yp * yp + zp * zp) if general else 0.0
        row = (nr, nf, nu, -zp * nf + yp * nu, lean, xp * nf - yp * nr,
               -sin_beta[p] * nr - cos_beta[p] * nu + along * nf,
               0.0 if general else beta[p] * lean)
        if weighted:
            w = weight[i]
            for j in range(8):
                out[i, j] += w * row[j]
        else:
            for j in range(8):
                out[i, j] += row[j]


__all__ = ["add_normal_rows", "corrected_geometry", "exact_correction_and_geometry"]
