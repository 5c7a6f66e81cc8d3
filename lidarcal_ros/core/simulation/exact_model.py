"""The exact bias model of the simulated system: what a biased system reports for a pulse.

Exact geometry, not docs/method.md section 3's linearisation; the bias convention
(``nominal - true``): docs/internals.md, "The simulator".
"""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import body_rotations_from_attitude
from lidarcal_ros.core.georeferencing.bias_model import boresight_matrix
from lidarcal_ros.core.params import as_vector


def georeference(
    trajectory_position: np.ndarray,
    rotation: np.ndarray,
    range_true: np.ndarray | float,
    theta: np.ndarray | float,
    biases: dict[str, float],
    range_noise: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Point reported by the biased system for a pulse of known true geometry (docs/method.md
    section 10: ``X_b = X_o + R_ins [dX, dY, dZ] + R_ins R_B rho``,
    ``rho = -(r_true + dr + noise) [sin((1 + dS) theta), 0, cos((1 + dS) theta)]``).

    Parameters
    ----------
    trajectory_position : (n, 3) or (3,)
        IMU origin at the firing time, map frame.
    rotation : (n, 3, 3), (1, 3, 3) or (3, 3)
        ``R_ins``, body (right, forward, up) to map, at the firing time
        (:func:`~lidarcal_ros.core.georeferencing.attitude.body_rotations_from_attitude`).
    range_true, theta : true range (m) and physical mirror angle (rad).
    biases : dict
        Bias values (nominal - true), SI; missing keys are 0.
    range_noise : additive range noise, metres.

    Returns
    -------
    (n, 3) or (3,) float64
    """
    xo = np.asarray(trajectory_position, dtype=np.float64)
    single = xo.ndim == 1
    xo = xo.reshape(-1, 3)
    r_ins = np.asarray(rotation, dtype=np.float64).reshape(-1, 3, 3)
    delta = as_vector(biases)
    rb = boresight_matrix(delta[3], delta[4], delta[5])
    r = np.asarray(range_true, dtype=np.float64) + delta[6] + np.asarray(range_noise)
    beta = (1.0 + delta[7]) * np.asarray(theta, dtype=np.float64)
    sb, cb = np.sin(beta), np.cos(beta)
    # v = dL + R_B rho, rho = -r [sin beta, 0, cos beta]
    vx = delta[0] - r * (rb[0, 0] * sb + rb[0, 2] * cb)
    vy = delta[1] - r * (rb[1, 0] * sb + rb[1, 2] * cb)
    vz = delta[2] - r * (rb[2, 0] * sb + rb[2, 2] * cb)
    n = int(np.broadcast(xo[:, 0], vx, r_ins[:, 0, 0]).size)
    out = np.empty((n, 3))
    for i in range(3):
        # X_o first, then term by term: a level R_ins (zeros and ones off the heading's
        # cosines and sines) gives the same bits as R_kappa written out.
        out[:, i] = xo[:, i] + r_ins[:, i, 0] * vx + r_ins[:, i, 1] * vy + r_ins[:, i, 2] * vz
    return out[0] if single and n == 1 else out


def biased_from_pulse(
    trajectory_position: np.ndarray,
    kappa: np.ndarray | float,
    range_true: np.ndarray | float,
    theta: np.ndarray | float,
    biases: dict[str, float],
    range_noise: np.ndarray | float = 0.0,
) -> np.ndarray:
    """:func:`georeference` from a level platform of heading(s) ``kappa`` (rad):
    ``R_ins = R_kappa``."""
    return georeference(trajectory_position, body_rotations_from_attitude(0.0, 0.0, kappa),
                        range_true, theta, biases, range_noise)


def true_pulse(
    trajectory_position: np.ndarray, kappa: np.ndarray | float, true_point: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Range and physical mirror angle of the pulse of the (ideal) true system that hit a point.

    The true point must lie in the true scan plane through ``trajectory_position`` (its
    along-track laser coordinate, ignored here, is then zero).
    """
    xo = np.asarray(trajectory_position, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(true_point, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(kappa), np.sin(kappa)
    dx, dy, dz = (p - xo).T
    rx = c * dx + s * dy  # R_kappa^T (P - X_o)
    rz = dz
    theta = np.arctan2(-rx, -rz)
    return np.hypot(rx, rz), theta


def biased_point_exact(
    trajectory_position: np.ndarray,
    kappa: np.ndarray | float,
    true_point: np.ndarray,
    biases: dict[str, float],
) -> np.ndarray:
    """Exact biased point for a true point observed from ``trajectory_position`` at ``kappa``.

    Inverts the true pulse (``rho = R_kappa^T (P - X_o)``, ``theta = atan2(-rho_x, -rho_z)``,
    ``r = |rho|``) and re-georeferences it with the biased system (docs/internals.md).
    Vectorised: ``(3,)`` or ``(n, 3)`` points, scalar or ``(n,)`` kappa.
    """
    single = np.asarray(true_point).ndim == 1
    r, theta = true_pulse(trajectory_position, kappa, true_point)
    out = biased_from_pulse(
        np.asarray(trajectory_position, dtype=np.float64).reshape(-1, 3), kappa, r, theta,
        biases,
    )
    return out.reshape(3) if single else out


__all__ = ["biased_from_pulse", "biased_point_exact", "georeference", "true_pulse"]
