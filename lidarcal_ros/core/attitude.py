"""The INS attitude of the trajectory: quaternions, rotations and their interpolation.

Conventions (method.md section 10)
----------------------------------
A trajectory pose's orientation is REP-103's: the unit quaternion ``q = (x, y, z, w)`` rotates
the body frame (x forward, y left, z up) into the map frame (x east, y north, z up). Method.md's
body frame is right-forward-up, so the rotation from it to the map is

``R_ins = R(q) P^T`` with ``P = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]``

and, for a heading ``kappa`` (method.md's: the forward axis points along ``(-sin kappa,
cos kappa)``), a pitch (nose up positive, about the body's right axis) and a roll (right wing
down positive, about the forward axis), ``R_ins = Rz(kappa) Rx(pitch) Ry(roll)``. A level pose
gives ``R_ins = R_kappa``, the rotation of sections 2-4.

An orientation is *absent* where the pose's quaternion is the identity (the contract allows
it: "orientation may be identity"), zero or not finite: such a sample is a row of NaN.
"""

from __future__ import annotations

import math

import numpy as np

#: Method.md's body axes (right, forward, up) in REP-103's (forward, left, up):
#: ``v_rep = P v_method``.
P_BODY = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

#: The identity quaternion, ``(x, y, z, w)``.
IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)


def normalise_quaternions(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(n, 4)`` xyzw, NaN rows where absent (identity, zero or non-finite).

    The sign is chosen so that consecutive rows lie in the same hemisphere (``q`` and ``-q``
    are the same rotation; interpolation needs the shorter arc).
    """
    q = np.array(q, dtype=np.float64, copy=True).reshape(-1, 4)
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))
    with np.errstate(invalid="ignore", divide="ignore"):
        q /= norm[:, None]
    absent = ~np.isfinite(q).all(axis=1) | ~(norm > 0.0) | (
        (q[:, 0] == 0.0) & (q[:, 1] == 0.0) & (q[:, 2] == 0.0))
    q[absent] = np.nan
    if q.shape[0] > 1:
        flip = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0.0
        # Cumulative parity: a row is flipped when an odd number of sign changes precede it.
        parity = np.concatenate(([False], np.logical_xor.accumulate(flip)))
        q[parity] = -q[parity]
    return q


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """``R(q)`` (n, 3, 3) of unit quaternions ``(n, 4)`` xyzw (REP-103 body -> map)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    r[:, 0, 1] = 2.0 * (x * y - z * w)
    r[:, 0, 2] = 2.0 * (x * z + y * w)
    r[:, 1, 0] = 2.0 * (x * y + z * w)
    r[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    r[:, 1, 2] = 2.0 * (y * z - x * w)
    r[:, 2, 0] = 2.0 * (x * z - y * w)
    r[:, 2, 1] = 2.0 * (y * z + x * w)
    r[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return r


def body_rotations(q: np.ndarray) -> np.ndarray:
    """``R_ins = R(q) P^T`` (n, 3, 3): method.md's body frame (right, forward, up) -> map.

    Its columns are the body's right, forward and up axes in the map frame: ``R(q)``'s
    columns are REP-103's forward, left and up, and right = -left.
    """
    r = rotation_matrices(q)
    out = np.empty_like(r)
    out[:, :, 0] = -r[:, :, 1]
    out[:, :, 1] = r[:, :, 0]
    out[:, :, 2] = r[:, :, 2]
    return out


def quaternions_from_attitude(roll: np.ndarray, pitch: np.ndarray, kappa: np.ndarray
                              ) -> np.ndarray:
    """Quaternions ``(n, 4)`` xyzw of poses with ``R_ins = Rz(kappa) Rx(pitch) Ry(roll)``
    (radians; module docstring).

    ``R(q) = R_ins P = Rz(kappa + pi/2) Ry'(...)``: in REP-103's axes the roll is about x
    (forward) and the pitch about -y (the left axis: nose up is a negative rotation about it),
    so ``R(q) = Rz(kappa + pi/2) Ry(-pitch) Rx(roll)``.
    """
    roll = np.asarray(roll, dtype=np.float64).reshape(-1)
    pitch = np.broadcast_to(np.asarray(pitch, dtype=np.float64), roll.shape)
    kappa = np.broadcast_to(np.asarray(kappa, dtype=np.float64), roll.shape)
    yaw = kappa + 0.5 * math.pi
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(-0.5 * pitch), np.sin(-0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    # q = qz(yaw) * qy(-pitch) * qx(roll)
    q = np.empty((roll.shape[0], 4))
    q[:, 0] = cy * cp * sr - sy * sp * cr
    q[:, 1] = cy * sp * cr + sy * cp * sr
    q[:, 2] = sy * cp * cr - cy * sp * sr
    q[:, 3] = cy * cp * cr + sy * sp * sr
    return q


def quaternions_from_headings(kappa: np.ndarray) -> np.ndarray:
    """Level quaternions ``(n, 4)`` xyzw of headings ``kappa`` (rad); NaN rows for NaN."""
    kappa = np.asarray(kappa, dtype=np.float64).reshape(-1)
    q = quaternions_from_attitude(np.zeros_like(kappa), np.zeros_like(kappa), kappa)
    q[~np.isfinite(kappa)] = np.nan
    return q


def attitude_from_quaternions(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``roll, pitch, kappa`` (rad, each (n,)) of quaternions (n, 4) xyzw, inverse of
    :func:`quaternions_from_attitude` (pitch within +-90 deg). NaN rows give NaN."""
    r = body_rotations(np.asarray(q, dtype=np.float64).reshape(-1, 4))
    # R_ins = Rz(k) Rx(p) Ry(r): third row (-cp sr, sp, cp cr), first column's ... see below.
    # Rx(p) Ry(r) = [[cr, 0, sr], [sp sr, cp, -sp cr], [-cp sr, sp, cp cr]].
    pitch = np.arcsin(np.clip(r[:, 2, 1], -1.0, 1.0))
    roll = np.arctan2(-r[:, 2, 0], r[:, 2, 2])
    # The forward column is Rz(k) (0, cp, sp): its horizontal part points along the heading.
    kappa = np.arctan2(-r[:, 0, 1], r[:, 1, 1])
    return roll, pitch, kappa


def headings_from_quaternions(q: np.ndarray) -> np.ndarray:
    """``kappa`` (rad, in ``(-pi, pi]``) of quaternions (n, 4) xyzw: the yaw of the body's
    forward axis projected on the horizontal, whatever the roll and pitch; NaN for NaN rows
    or a forward axis straight up or down."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    fx = w * w + x * x - y * y - z * z  # R(q) (1, 0, 0), horizontal part, times |q|^2
    fy = 2.0 * (x * y + w * z)
    with np.errstate(invalid="ignore"):
        kappa = np.arctan2(fy, fx) - 0.5 * math.pi
    kappa = np.where(kappa <= -math.pi, kappa + 2.0 * math.pi, kappa)
    return np.where((fx == 0.0) & (fy == 0.0), np.nan, kappa)


def slerp(t_samples: np.ndarray, q_samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Quaternions ``(n, 4)`` at times ``t`` by spherical linear interpolation between the
    samples bracketing each time (clamped to the first and last sample outside them).

    Parameters
    ----------
    t_samples : (m,) float64
        Sample times, s, strictly increasing.
    q_samples : (m, 4) float64
        Unit quaternions xyzw in one hemisphere from sample to sample
        (:func:`normalise_quaternions`); NaN rows give NaN.
    t : (n,) float64
        Times, s.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    m = t_samples.shape[0]
    if m == 0:
        return np.full((t.shape[0], 4), np.nan)
    if m == 1:
        return np.repeat(q_samples[:1], t.shape[0], axis=0)
    i = np.clip(np.searchsorted(t_samples, t, side="right") - 1, 0, m - 2)
    t0, t1 = t_samples[i], t_samples[i + 1]
    f = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    q0, q1 = q_samples[i], q_samples[i + 1]
    cos_theta = np.clip(np.einsum("ij,ij->i", q0, q1), -1.0, 1.0)
    theta = np.arccos(cos_theta)
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        w0 = np.where(small, 1.0 - f, np.sin((1.0 - f) * theta) / sin_theta)
        w1 = np.where(small, f, np.sin(f * theta) / sin_theta)
    out = w0[:, None] * q0 + w1[:, None] * q1
    out /= np.sqrt(np.einsum("ij,ij->i", out, out))[:, None]
    return out


__all__ = [
    "IDENTITY_XYZW", "P_BODY", "attitude_from_quaternions", "body_rotations",
    "headings_from_quaternions", "normalise_quaternions", "quaternions_from_attitude",
    "quaternions_from_headings", "rotation_matrices", "slerp",
]
