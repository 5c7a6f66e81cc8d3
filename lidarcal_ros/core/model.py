"""The bias model of method.md sections 2-3: design matrix and point correction.

All functions are vectorised over points. ``x`` and ``z`` are the point's lateral and vertical
coordinates in the laser frame (metres; ``z`` negative), ``kappa`` the heading (radians, map
frame, ``kappa = atan2(-d_x, d_y)``), ``beta`` the mirror angle (radians). The parameter order is
:data:`lidarcal_ros.core.params.PARAMETER_NAMES`.
"""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core import kernels
from lidarcal_ros.core.params import N_PARAMETERS


def design_matrix(
    x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """Impact of the eight biases on each point, method.md eq. [8].

    Parameters
    ----------
    x, z, kappa, beta : (n,) float64
        Laser-frame lateral/vertical coordinate (m), heading (rad), mirror angle (rad).

    Returns
    -------
    (n, 3, 8) float64
        ``A`` such that ``X_biased = X_true + A @ delta`` (rows X, Y, Z of the map frame).
    """
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    c = np.cos(kappa)
    s = np.sin(kappa)
    sb = np.sin(beta)
    cb = np.cos(beta)
    a = np.zeros((*x.shape, 3, N_PARAMETERS))
    a[..., 0, 0] = c
    a[..., 0, 1] = -s
    a[..., 0, 3] = z * s
    a[..., 0, 4] = z * c
    a[..., 0, 5] = -x * s
    a[..., 0, 6] = -c * sb
    a[..., 0, 7] = z * beta * c
    a[..., 1, 0] = s
    a[..., 1, 1] = c
    a[..., 1, 3] = -z * c
    a[..., 1, 4] = z * s
    a[..., 1, 5] = x * c
    a[..., 1, 6] = -s * sb
    a[..., 1, 7] = z * beta * s
    a[..., 2, 2] = 1.0
    a[..., 2, 4] = -x
    a[..., 2, 6] = -cb
    a[..., 2, 7] = -x * beta
    return a


def normal_design_rows(
    normal: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """``n^T A`` for each point: the design row of a point-to-patch observation, without
    materialising the (n, 3, 8) matrix.

    Parameters
    ----------
    normal : (n, 3) float64
        Unit patch normals in the map frame.
    x, z, kappa, beta : (n,) float64
        As in :func:`design_matrix`.

    Returns
    -------
    (n, 8) float64
    """
    nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
    c = np.cos(kappa)
    s = np.sin(kappa)
    sb = np.sin(beta)
    cb = np.cos(beta)
    # Horizontal normal component along the body's right (c, s) and forward (-s, c) axes.
    n_right = nx * c + ny * s
    n_fwd = -nx * s + ny * c
    rows = np.empty((normal.shape[0], N_PARAMETERS))
    rows[:, 0] = n_right
    rows[:, 1] = n_fwd
    rows[:, 2] = nz
    rows[:, 3] = -z * n_fwd
    rows[:, 4] = z * n_right - x * nz
    rows[:, 5] = x * n_fwd
    rows[:, 6] = -sb * n_right - cb * nz
    rows[:, 7] = beta * (z * n_right - x * nz)
    return rows


Trig = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def point_offsets(
    delta: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray,
    *, trig: Trig | None = None,
) -> np.ndarray:
    """``A @ delta`` for each point: the displacement the biases cause, map frame, metres.

    Parameters
    ----------
    trig : (cos kappa, sin kappa, sin beta, cos beta), keyword-only, optional
        Known already (:meth:`~lidarcal_ros.core.local_trajectory.LaserGeometry.trig`);
        computed from ``kappa`` and ``beta`` otherwise.

    Returns
    -------
    (n, 3) float64
    """
    return _offsets(delta, x, z, kappa, beta, trig, np.empty((0, 3)))


def _offsets(delta: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray,
             beta: np.ndarray, trig: Trig | None, base: np.ndarray) -> np.ndarray:
    """:func:`point_offsets`, or ``base - `` them (one pass: :func:`kernels.bias_offsets`).

    Body frame: the displacement to the right is ``dX + z dphi - sin(beta) dr + z beta dS``,
    forward ``dY - z domega + x dkappa``, up ``dZ - x dphi - cos(beta) dr - x beta dS``; the
    horizontal part is rotated by kappa into the map frame.
    """
    if trig is None:
        trig = (np.cos(kappa), np.sin(kappa), np.sin(beta), np.cos(beta))
    c, s, sb, cb = (np.asarray(a, dtype=np.float64) for a in trig)
    return kernels.bias_offsets(np.asarray(delta, dtype=np.float64),
                                np.asarray(x, dtype=np.float64), np.asarray(z, dtype=np.float64),
                                np.asarray(beta, dtype=np.float64), c, s, sb, cb, base)


def correct_points(
    xyz: np.ndarray,
    delta: np.ndarray,
    x: np.ndarray,
    z: np.ndarray,
    kappa: np.ndarray,
    beta: np.ndarray,
    *,
    trig: Trig | None = None,
) -> np.ndarray:
    """Method.md eq. [13]: ``X_corrected = X_biased - A @ delta_hat``.

    Parameters
    ----------
    xyz : (n, 3) float64
        Biased points, map frame, metres.
    delta : (8,) float64
        Estimated biases, SI units.
    trig : keyword-only, optional
        As in :func:`point_offsets`.

    Returns
    -------
    (n, 3) float64
        New array of corrected points.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape != (np.shape(x)[0], 3):
        raise ValueError(f"xyz of shape {xyz.shape} for {np.shape(x)[0]} points")
    return _offsets(delta, x, z, kappa, beta, trig, xyz)


def boresight_matrix(domega: float, dphi: float, dkappa: float) -> np.ndarray:
    """Exact boresight rotation ``Rz(dkappa) Ry(dphi) Rx(domega)`` (body frame).

    Its small-angle form is method.md's ``R_B = I + skew(domega, dphi, dkappa)``; this order is
    the one that reproduces the ``exact_offset`` of the shared test vectors.
    """
    cw, sw = np.cos(domega), np.sin(domega)
    cp, sp = np.cos(dphi), np.sin(dphi)
    ck, sk = np.cos(dkappa), np.sin(dkappa)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cw, -sw], [0.0, sw, cw]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[ck, -sk, 0.0], [sk, ck, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def correct_points_exact(
    xyz: np.ndarray, origin: np.ndarray, kappa: np.ndarray, delta: np.ndarray
) -> np.ndarray:
    """Remove the biases exactly: invert the biased georeferencing of method.md eq. [1]-[2].

    The delivered point is ``X_b = X_o + R_kappa d + R_kappa R_B rho_b`` with the recorded range
    and mirror angle inside ``rho_b = -r [sin beta, 0, cos beta]``; the system used the biased
    (nominal) values ``d = (dX, dY, dZ)``, ``R_B(domega, dphi, dkappa)``, range offset ``dr`` and
    mirror scale ``1 + dS``. Undoing them: ``rho_b = R_B^T (R_kappa^T (X_b - X_o) - d)``,
    ``r_true = |rho_b| - dr``, ``theta = beta / (1 + dS)``, and the true point is
    ``X_o + R_kappa (-r_true) [sin theta, 0, cos theta]``, keeping the (small) along-track
    component of ``rho_b`` that the local trajectory leaves.

    Agrees with :func:`correct_points` (eq. [13]) to second order in the biases; used while
    iterating so that large biases (150 arcsec, 0.2 m) leave no linearisation error.

    Parameters
    ----------
    xyz : (n, 3) float64
        Delivered points, map frame, metres.
    origin : (n, 3) float64
        Firing positions ``X_o(t)`` from the local trajectory, map frame, metres.
    kappa : (n,) float64
        Headings, radians.
    delta : (8,) float64
        Biases, SI.
    """
    d = np.asarray(delta, dtype=np.float64)
    c = np.cos(kappa)
    s = np.sin(kappa)
    rel = xyz - origin
    # Body frame (right, forward, up) minus the lever arm.
    q = np.empty_like(rel)
    q[:, 0] = c * rel[:, 0] + s * rel[:, 1] - d[0]
    q[:, 1] = -s * rel[:, 0] + c * rel[:, 1] - d[1]
    q[:, 2] = rel[:, 2] - d[2]
    rho = q @ boresight_matrix(d[3], d[4], d[5])  # R_B^T q, row-wise
    r_rec = np.hypot(rho[:, 0], rho[:, 2])
    beta = np.arctan2(-rho[:, 0], -rho[:, 2])
    r_true = r_rec - d[6]
    theta = beta / (1.0 + d[7])
    bx = -r_true * np.sin(theta)
    by = rho[:, 1]
    bz = -r_true * np.cos(theta)
    out = np.empty_like(rel)
    out[:, 0] = origin[:, 0] + c * bx - s * by
    out[:, 1] = origin[:, 1] + s * bx + c * by
    out[:, 2] = origin[:, 2] + bz
    return out
