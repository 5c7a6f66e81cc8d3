"""The bias model of method.md sections 2-3: design matrix and point correction.

All functions are vectorised over points. ``x`` and ``z`` are the point's lateral and vertical
coordinates in the laser frame (metres; ``z`` negative), ``kappa`` the heading (radians, map
frame, ``kappa = atan2(-d_x, d_y)``), ``beta`` the mirror angle (radians). The parameter order is
:data:`lidarcal_ros.core.params.PARAMETER_NAMES`.
"""

from __future__ import annotations

import numpy as np

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


def point_offsets(
    delta: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """``A @ delta`` for each point: the displacement the biases cause, map frame, metres.

    Returns
    -------
    (n, 3) float64
    """
    d = np.asarray(delta, dtype=np.float64)
    c = np.cos(kappa)
    s = np.sin(kappa)
    sb = np.sin(beta)
    cb = np.cos(beta)
    # Body-frame (right, forward) displacement, then rotate by kappa.
    right = d[0] + z * d[4] - sb * d[6] + z * beta * d[7]
    fwd = d[1] - z * d[3] + x * d[5]
    out = np.empty((np.shape(x)[0], 3))
    out[:, 0] = c * right - s * fwd
    out[:, 1] = s * right + c * fwd
    out[:, 2] = d[2] - x * d[4] - cb * d[6] - x * beta * d[7]
    return out


def correct_points(
    xyz: np.ndarray,
    delta: np.ndarray,
    x: np.ndarray,
    z: np.ndarray,
    kappa: np.ndarray,
    beta: np.ndarray,
) -> np.ndarray:
    """Method.md eq. [13]: ``X_corrected = X_biased - A @ delta_hat``.

    Parameters
    ----------
    xyz : (n, 3) float64
        Biased points, map frame, metres.
    delta : (8,) float64
        Estimated biases, SI units.

    Returns
    -------
    (n, 3) float64
        New array of corrected points.
    """
    return xyz - point_offsets(delta, x, z, kappa, beta)
